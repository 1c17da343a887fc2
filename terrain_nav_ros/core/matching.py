"""Minutiae-based terrain matching and localisation (dissertation chapter 4).

Pipeline (same for block-vs-block :func:`compare` and camera-in-region :func:`localise`):

1. **Candidates.** Edge correspondences (a pair of minutiae in A matched to a pair in B whose
   length and two relative angles agree; see :mod:`.descriptors`). Two generators:
   ``"hash"`` looks every edge of A up in a hash of B's edges (complete, best for blocks);
   ``"roots"`` first picks, for each minutia of A, the ``k_roots`` minutiae of B with the most
   similar shape context descriptor and compares only their local edges (the
   reference-pair selection of dissertation 4.2.2; bounded cost for a large landmark region).
   Every candidate is a minimal sample: two point correspondences fix a similarity transform.
   Its vote is weighted by the descriptor similarity of both correspondences.
2. **Consensus.** Hough voting of the candidate rotations, then of the translations at each
   rotation peak; the strongest (rotation, translation) cells give hypotheses with their
   supporting correspondences.
3. **Registration.** Vectorised 2-point RANSAC over each hypothesis' correspondences, least
   squares (complex Procrustes) on the inliers, then guided pairing over all minutiae and a
   final least-squares fit on the pairings, with a covariance from the residuals.
4. **Pairings** are one-to-one minutiae that agree within ``pos_tol`` px and ``angle_tol`` after
   the transform.
5. **Score** (see :func:`significance`): ``-log10`` of the chance of pairings this many and
   this close (position and direction residuals) between unrelated minutiae, given the
   densities in the overlap, the tolerances and the size of the searched transform space.
   One threshold then means one false-match rate at any minutia count and any search area,
   which ``pairings`` or ``pairings**2/(n1*n2)`` do not give (both are inflated for small
   sets). :func:`calibrate_threshold` sets the threshold from non-PVA scores.
6. **Crease check** (when both sets come with their crease skeletons,
   :mod:`.crease_check`): every registered hypothesis is refined and scored, the agreement of
   the crease pixels outside the paired minutiae's surroundings is added to its score (a
   binomial tail against the local chance of agreement), and the best total wins.
7. **Crease search** (:mod:`.crease_search`): when the smaller set has too few minutiae for
   their pair votes to propose the transform (a ~60 px block: 3-9 minutiae, 0-2 of them
   repeating), a brute-force FFT search over rotations and translations of the crease
   skeletons proposes more registrations, refined and scored by the crease check like the
   others. A search too large for the fine level (a block in its localisation region) runs
   at the coarse one, its proposals pulled onto the creases by the coarse-to-fine ICP.

All internal geometry is in the math frame ``z = col - 1j*row`` (see :mod:`.descriptors`);
results are reported in pixel coordinates.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, fields, replace
from enum import StrEnum

import cv2
import numpy as np
from scipy.spatial import cKDTree
from scipy.special import gammaln

from . import _matching_kernels as _kernels
from .crease_check import (
    CreaseEvidence,
    CreaseField,
    CreaseSamples,
    crease_covariance,
    crease_evidence,
    refine_on_creases,
)
from .crease_search import (
    COARSE,
    FINE,
    LEVELS,
    CreaseSearchQuery,
    CreaseSearchReference,
    SearchLevel,
    min_search_work,
    search_rotations,
    search_scales,
    search_transforms,
)
from .descriptors import (
    TWO_PI,
    EdgeHash,
    EdgeQuery,
    crease_descriptor,
    cylinder_code,
    from_complex,
    neighbour_edges,
    shape_context,
    to_complex,
    wrap_angle,
)
from .minutia_set import MinutiaSet


class Decision(StrEnum):
    """Outcome of a comparison."""

    MATCH = "match"
    NO_MATCH = "no_match"
    NO_DECISION = "no_decision"


@dataclass(frozen=True)
class MatchParams:
    """Settings of the matcher (the dissertation's Table 4.1, extended).

    Parameters
    ----------
    pos_tol : float
        Pairing radius (px) after the transform.
    angle_tol : float
        Pairing tolerance on minutia direction (rad).
    edge_length_tol : float
        Tolerance on edge length (px) for candidate edges.
    edge_angle_tol : float
        Tolerance on each edge's relative angle (rad) for candidate edges.
    k_query, k_ref : int
        Nearest-neighbour edges per minutia on the query (A) and reference (B) side; more on
        B so that spurious minutiae in B do not push true neighbours out of reach.
    edge_min, edge_max : float
        Edge length range (px).
    rot_bin, trans_bin : float
        Hough cell size for rotation (rad) and translation (px).
    n_hypotheses : int
        Hough cells verified by registration and pairing (the strongest of
        ``n_rotation_peaks`` rotations x 2 translations).
    n_rotation_peaks : int
        Rotation histogram peaks searched for translations: 3, because drainage patterns
        often hold a near-symmetric structure whose votes at the wrong rotation (~180 deg off)
        outnumber the true ones in a degraded view.
    min_support_ratio : float
        Cells with less than this fraction of the best cell's vote weight are not verified.
    ransac_iterations : int
        Random 2-point samples per hypothesis.
    estimate_scale : bool
        Fit a similarity with scale (else rotation + translation only).
    max_scale_change : float
        Relative scale difference allowed for candidates and fits when ``estimate_scale``.
    candidates : {"auto", "hash", "roots"}
        Candidate generator; ``"auto"`` uses roots when B has more than ``roots_above``
        minutiae.
    k_roots : int
        Descriptor-nearest minutiae of B per minutia of A for the roots generator.
    roots_above : int
    use_descriptors : bool
        Weight votes by descriptor similarity (hash generator).
    descriptor : {"shape_context", "mcc", "both"}
        Local descriptor of each minutia: the log-polar minutiae shape context, the
        cylinder code (:func:`~.descriptors.cylinder_code`), or both averaged.
    by_kind : bool
        Shape context split by minutia kind.
    max_rotation : float
        Largest rotation (rad) between the sets that is searched: pi = any; a small value
        uses a heading prior (ground-projected camera frames are already north-up within the
        estimate's yaw error) and shrinks both the work and the chance of a false match.
    min_minutiae : int
        Minimum minutiae in each set below which the answer is "no decision" (dissertation
        1.4); a set is also undecidable when even a perfect match could not reach
        ``threshold``.
    min_minutiae_creases : int
        The same minimum when the crease check applies: a few minutiae still give the
        candidate transforms, the creases carry the rest of the evidence.
    pos_floor, angle_floor : float
        Pairing residuals (px, rad) below which a pairing counts as exact in the score: finer
        agreement is below the extractor's resolution (and a least-squares fit pulls some
        residuals to zero), so it is no further evidence.
    crease_check : bool
        When both sets come with crease images, choose among the registered hypotheses, and
        score, with the agreement of the crease skeletons added to the minutiae evidence
        (:mod:`.crease_check`): a small block's few pairings are then not the only evidence.
    crease_radius, crease_angle_tol : float
        Position (px) and direction (rad) tolerance of a crease pixel hit.
    crease_spacing : float
        Crease pixels per effectively independent sample in the crease evidence.
    crease_exclude_radius : float
        Crease pixels this close (px) to a paired minutia of A are left out of the crease
        evidence: the transform aligns those stubs by construction, and the pairing already
        counts them.
    crease_descriptor : bool
        With crease images, also weight candidate votes by the crease shape descriptor (hash
        generator only).
    crease_search_below : int
        With crease images, when the smaller set has fewer minutiae than this, the crease
        skeletons are also searched by brute force (:mod:`.crease_search`) for transforms
        to register, in the wider try (``rescue_below``); 0 turns the search off.
    crease_search_max_side : int
        The search is skipped when the query's (A's) crease image is larger than this (px
        per side): the rotations searched grow with its size.
    crease_search_max_work : int
        ... or when the rotations times the padded FFT pixels of the search exceed this: its
        time and memory (~16 bytes each) grow with both; it bounds the level the search
        runs at (``crease_search_fine_work``). The default, ~0.5 s and 200 MB, lets any
        block of up to 160 px be searched, against a block or (at the coarse level) in its
        3x localisation region; a camera frame in a landmark region never is.
    crease_search_proposals : int
        Transforms the search proposes (twice as many at the coarse level).
    crease_search_fine_work : int
        A search whose work at the fine level (:data:`~.crease_search.FINE`: half the pixel
        resolution, rotations 3 px apart at the query's reach) exceeds this runs at the
        coarse level (:data:`~.crease_search.COARSE`: a quarter, 6 px; an eighth of the
        work) and its proposals get the coarse-to-fine ICP (``crease_rescue_radii``). The
        default keeps block-vs-block searches of blocks up to ~130 px fine; a block of more
        than ~80 px in its 3x localisation region is searched coarse, 4-6x faster.
    view_search : bool
        With crease images, a localised set too large for the crease search above (a camera
        footprint in its landmark region) whose first try stays below ``rescue_below`` is
        searched, at the finest level (:data:`~.crease_search.LEVELS`) whose work fits
        ``crease_search_max_work``, over scales as well (``search_scale``): the search is its
        wider try, instead of the sweep of the votes (which only a set no level fits gets).
        On real images the minutiae of albedo edges (snow, forest, fields) rarely repeat
        those of a render, so the minutiae's votes may propose nothing right; the crease
        skeleton largely repeats.
    search_scale : float
        Relative scale error the crease searches of a localisation cover (the prior's height
        above ground: 10 % moves the edge of a 256 px view by 13 px, more than a hit's
        tolerance), and their ICP then fits; block comparisons search no scale.
    view_search_background : float
        That search counts hits above the reference's local crease density within this
        sigma (search px, :class:`~.crease_search.CreaseSearchReference`).
    ridge_check : bool
        When both sets also come with ridge skeletons (the lines between the valleys, see
        :class:`~.minutiae.FeatureExtractor`), add their agreement at each registration to
        its score, like the valleys' (:func:`~.crease_check.crease_evidence`), and let the
        crease ICP pull on them too: a second, largely independent check of a small block's
        registration, at no extra search.
    ridge_check_below : int
        ... only when the smaller set has fewer minutiae than this: larger sets have
        evidence enough, and it costs ~0.2 ms per scored registration.
    min_crease_pixels : int
        Where the crease search runs, the minimum-minutiae rule becomes one on the drainage
        itself: fewer crease pixels than this in either set give "no decision" (a flat
        lake), however many minutiae.
    rescue_below : float
        A comparison whose best registration scores below this gets a second, wider try:
        hypotheses from every rotation cell, not only the rotation histogram's peaks (where
        the drainage runs one way, edges of unrelated minutiae pile up near one rotation and
        bury the true one in the marginal, not in the joint rotation-translation cells),
        and with creases the coarse-to-fine crease ICP below. For a set small enough for
        the crease search (``crease_search_*``) the search is the wider try instead: it
        covers every rotation and translation, and the sweep and the wide ICP would only add
        chances to unrelated pairs of such small sets; so is the view search for a localised
        set it fits (``view_search``). The ridges' evidence does not count
        towards this test (it was tuned without them, and they add to chance registrations
        too). A clear match never pays for it;
        ``-inf`` turns it off, the crease search with it. The score's count of transforms
        covers every rotation already, so the wider try adds no penalty beyond its extra
        hypotheses.
    crease_rescue_radii : tuple of float
        ICP pairing radii (px), coarse to fine, of the wider try: a transform that a few
        minutiae pairings put 5-10 px or a few degrees off is outside the 3 px ICP's reach,
        though its creases nearly overlap.
    threshold : float
        Score at and above which two sets match; calibrate it with
        :func:`calibrate_threshold`.
    seed : int
        RANSAC random seed (results are deterministic).
    """

    pos_tol: float = 5.0
    angle_tol: float = math.radians(30.0)
    edge_length_tol: float = 4.0
    edge_angle_tol: float = math.radians(25.0)
    k_query: int = 6
    k_ref: int = 10
    edge_min: float = 6.0
    edge_max: float = 160.0
    rot_bin: float = math.radians(5.0)
    trans_bin: float = 8.0
    n_hypotheses: int = 4
    n_rotation_peaks: int = 3
    min_support_ratio: float = 0.2
    ransac_iterations: int = 24
    estimate_scale: bool = False
    max_scale_change: float = 0.1
    candidates: str = "auto"
    k_roots: int = 6
    roots_above: int = 2000
    use_descriptors: bool = True
    descriptor: str = "shape_context"
    by_kind: bool = True
    min_minutiae: int = 10
    min_minutiae_creases: int = 4
    max_rotation: float = math.pi
    pos_floor: float = 0.75
    angle_floor: float = math.radians(1.5)
    crease_check: bool = True
    crease_radius: float = 1.5
    crease_angle_tol: float = math.radians(20.0)
    crease_spacing: float = 4.0
    crease_exclude_radius: float = 6.0
    crease_descriptor: bool = True
    crease_search_below: int = 64
    crease_search_max_side: int = 160
    crease_search_max_work: int = 12_000_000
    crease_search_proposals: int = 3
    crease_search_fine_work: int = 4_000_000
    view_search: bool = True
    search_scale: float = 0.1
    view_search_background: float = 3.0
    ridge_check: bool = True
    ridge_check_below: int = 64
    min_crease_pixels: int = 100
    rescue_below: float = 10.0
    crease_rescue_radii: tuple[float, ...] = (12.0, 8.0, 5.0, 3.0)
    threshold: float = 3.0
    seed: int = 0

    @property
    def crease_tolerances(self) -> dict:
        """The crease evidence's and covariance's tolerances, as their keyword arguments
        (:func:`~.crease_check.crease_evidence`)."""
        return dict(radius=self.crease_radius, angle_tol=self.crease_angle_tol,
                    spacing=self.crease_spacing)


# sets with at most this many edges get the finer edge hash (see EdgeHash subdivision)
_FINE_HASH_EDGES = 6000


class MinutiaIndex:
    """A minutia set prepared for matching: tree, edges, descriptors, footprint.

    Build it once per set and reuse it (e.g. the landmark region across camera frames, or
    each block across the N x N comparisons of a study).

    Parameters
    ----------
    ms : MinutiaSet
    params : MatchParams, optional
    crease : ndarray, optional
        Crease skeleton image in the pixel frame of ``ms`` (non-zero = crease); enables the
        crease descriptor and the crease check (see :class:`MatchParams`).
    ridges : ndarray, optional
        Ridge skeleton image in the same frame; enables the ridge check
        (``MatchParams.ridge_check``).
    """

    def __init__(self, ms: MinutiaSet, params: MatchParams | None = None,
                 crease: np.ndarray | None = None, ridges: np.ndarray | None = None):
        p = params or MatchParams()
        self.set = ms
        self.params = p
        self.z = to_complex(ms.col, ms.row)
        self.angle = ms.angle
        self.n = len(ms)
        self.xy = np.column_stack([self.z.real, self.z.imag])
        self.tree = cKDTree(self.xy) if self.n else None
        self.edges = neighbour_edges(ms, max(p.k_query, p.k_ref), p.edge_min, p.edge_max,
                                     tree=self.tree)
        self.descriptor = _descriptor(ms, p)
        self.crease_image = crease
        self.ridge_image = ridges
        self._ridge_samples = None
        self._ridge_field = None
        self._crease_descriptor = None
        self._crease_samples = None
        self._crease_field = None
        self._crease_search = {}   # by (search resolution, background)
        self._crease_query = {}    # by (max_rotation, search level, scale change)
        self._crease_around = None
        self._strided = None
        self.footprint = _footprint(ms)
        # the footprint as complex corners and as its box (x0, x1, y0, y1), for _overlap
        self.footprint_z = self.footprint[:, 0] + 1j * self.footprint[:, 1]
        self.footprint_box = (self.footprint[:, 0].min(), self.footprint[:, 0].max(),
                              self.footprint[:, 1].min(), self.footprint[:, 1].max())
        self.footprint32 = self.footprint.astype(np.float32)
        self.area = float(abs(cv2.contourArea(self.footprint32)))
        self.centroid = complex(self.z.mean()) if self.n else 0j
        # RMS radius of the minutiae about their centroid: the lever arm of a rotation
        self.radius = float(np.sqrt(np.mean(np.abs(self.z - self.centroid) ** 2))) if self.n \
            else 0.0
        self._hash = None
        self._query = None
        self._prepared = None

    def __len__(self) -> int:
        return self.n

    @property
    def crease(self) -> np.ndarray | None:
        """Crease shape descriptors (None without a crease image or with the descriptor off;
        built on first use: the region search never asks for them)."""
        if (self._crease_descriptor is None and self.crease_image is not None
                and self.params.crease_descriptor):
            self._crease_descriptor = crease_descriptor(self.set, self.crease_image)
        return self._crease_descriptor

    @property
    def crease_samples(self) -> CreaseSamples | None:
        """Crease pixels for the crease check as the query side (built on first use)."""
        if self._crease_samples is None and self.crease_image is not None:
            self._crease_samples = CreaseSamples.from_image(self.crease_image)
        return self._crease_samples

    def crease_samples_strided(self, stride: int) -> CreaseSamples:
        """Every ``stride``-th crease sample, in raster order (cached for one stride)."""
        if self._strided is None or self._strided[0] != stride:
            s = self.crease_samples
            self._strided = (stride, CreaseSamples(s.z[::stride], s.direction[::stride]))
        return self._strided[1]

    def crease_samples_around(self, minutiae: np.ndarray) -> np.ndarray:
        """Crease samples within ``crease_exclude_radius`` of the given minutiae (the
        per-minutia lists are built on first use, stored end to end)."""
        if self._crease_around is None:
            near = self.crease_samples.around(self.z, self.params.crease_exclude_radius)
            start = np.zeros(len(near) + 1, np.intp)
            np.cumsum([len(i) for i in near], out=start[1:])
            flat = np.concatenate(near) if near else np.zeros(0, np.intp)
            self._crease_around = (start, flat.astype(np.intp))
        start, flat = self._crease_around
        minutiae = np.asarray(minutiae, np.intp)
        if _kernels.HAVE_NUMBA:
            return _kernels.listed_segments(start, flat, minutiae)
        first, count = start[minutiae], start[minutiae + 1] - start[minutiae]
        # positions of the listed segments in ``flat``, without a Python loop
        ends = np.cumsum(count)
        return flat[np.arange(ends[-1] if len(ends) else 0)
                    + np.repeat(first - ends + count, count)]

    @property
    def crease_field(self) -> CreaseField | None:
        """Distance/direction field for the crease check as the reference (built on first
        use)."""
        if self._crease_field is None and self.crease_image is not None:
            self._crease_field = CreaseField(self.crease_image)
        return self._crease_field

    @property
    def ridge_samples(self) -> CreaseSamples | None:
        """Ridge pixels for the ridge check as the query side (built on first use)."""
        if self._ridge_samples is None and self.ridge_image is not None:
            self._ridge_samples = CreaseSamples.from_image(self.ridge_image)
        return self._ridge_samples

    @property
    def ridge_field(self) -> CreaseField | None:
        """Ridge distance/direction field as the reference (built on first use)."""
        if self._ridge_field is None and self.ridge_image is not None:
            self._ridge_field = CreaseField(self.ridge_image)
        return self._ridge_field

    def crease_search(self, level: SearchLevel = FINE,
                      background: float = 0.0) -> CreaseSearchReference | None:
        """Direction channels for the crease search as the reference (built on first use;
        ``background`` as :class:`~.crease_search.CreaseSearchReference`'s)."""
        key = (level.resolution, background)
        if key not in self._crease_search and self.crease_field is not None:
            self._crease_search[key] = CreaseSearchReference(
                self.crease_field, resolution=level.resolution, background=background)
        return self._crease_search.get(key)

    @functools.cached_property
    def crease_reach(self) -> float:
        """90th percentile of the crease pixels' distance from their mean (px): the lever
        arm of a rotation or scale step in the crease search."""
        z = self.crease_samples.z if self.crease_samples is not None else np.zeros(0)
        return float(np.percentile(np.abs(z - z.mean()), 90)) if len(z) else 0.0

    def crease_search_transforms(self, max_rotation: float, level: SearchLevel = FINE,
                                 max_scale_change: float = 0.0) -> tuple[np.ndarray,
                                                                         np.ndarray]:
        """Rotations and scales the crease search tries at ``level``."""
        reach, tol = self.crease_reach, level.rotation_tolerance
        return (search_rotations(max_rotation, reach, tol),
                search_scales(max_scale_change, reach, tol))

    def crease_search_query(self, max_rotation: float, level: SearchLevel = FINE,
                            max_scale_change: float = 0.0) -> CreaseSearchQuery | None:
        """This set's creases rasterised at the rotations (and scales within
        ``1 +- max_scale_change``) the crease search tries within ``max_rotation`` (built on
        first use: a camera block meets every landmark block)."""
        samples = self.crease_samples
        if samples is None:
            return None
        key = (max_rotation, level, max_scale_change)
        if key not in self._crease_query:
            rotations, scales = self.crease_search_transforms(max_rotation, level,
                                                              max_scale_change)
            self._crease_query[key] = CreaseSearchQuery(samples, rotations, level.resolution,
                                                        scales=scales)
        return self._crease_query[key]

    def prepare_as_reference(self, search: bool = False) -> MinutiaIndex:
        """Build now what matching against this set (as B, e.g. a landmark region) builds on
        first use: the edge hash for the hash candidate generator (and its crease
        descriptors), the crease and ridge fields and, with ``search``, the crease search's
        channels at both levels, squared and turned four ways (a small region that blocks are
        searched in). A region arrives before the frames it serves, so its first frame need
        not wait for them (~60 ms for a demo landmark region with creases). Returns self."""
        p = self.params
        hash_generator = _generator(self, p) == "hash"
        if hash_generator:
            self.edge_hash()
        if p.crease_check and self.crease_image is not None:
            _ = self.crease_field
            _ = self.ridge_field
            if hash_generator:
                _ = self.crease
            # the small sets' search (fine, coarse) and the view search (every level)
            wanted = [(level, 0.0) for level in (FINE, COARSE)]
            if p.view_search:
                wanted += [(level, p.view_search_background) for level in LEVELS]
            for level, background in wanted if search else ():
                reference = self.crease_search(level, background).squared()
                for turns in range(4):
                    reference.turned(turns)
        return self

    def edge_hash(self) -> EdgeHash:
        """Hash of this set's edges (built on first use)."""
        if self._hash is None:
            p = self.params
            reach = 1
            if p.estimate_scale:
                reach = int(np.ceil(_length_tol(p, p.edge_max) / p.edge_length_tol))
            # finer cells for a block-sized set (fewer candidates per look-up); a large
            # region keeps coarse ones (5x fewer table entries)
            sub = 2 if self.edges.valid.sum() <= _FINE_HASH_EDGES else 1
            self._hash = EdgeHash(self.edges, p.edge_length_tol, p.edge_angle_tol, p.edge_max,
                                  length_reach=reach, subdivision=sub)
        return self._hash

    def edge_query(self):
        """This set's first ``k_query`` edges as hash queries (cached): invariants, length
        tolerance, and per edge its two minutiae and direction."""
        if self._query is None:
            p, e = self.params, self.edges
            rows, cols = np.nonzero(e.valid[:, :min(p.k_query, e.k)])
            length = e.length[rows, cols]
            self._query = (length, e.beta_i[rows, cols], e.beta_j[rows, cols],
                           _length_tol(p, length), rows, e.j[rows, cols],
                           e.direction[rows, cols])
        return self._query

    def prepared_query(self, hb: EdgeHash) -> EdgeQuery:
        """This set's query edges in the cell layout of ``hb`` (cached per layout: one
        camera set is looked up in many landmark blocks' hashes)."""
        if self._prepared is None or self._prepared.geometry != hb.geometry:
            length, beta_i, beta_j, tol = self.edge_query()[:4]
            self._prepared = hb.prepare(length, beta_i, beta_j, tol)
        return self._prepared


def _generator(b: MinutiaIndex, p: MatchParams) -> str:
    """The candidate generator for reference set ``b``: ``p.candidates``, or with "auto"
    the root pairs for a large set and the edge hash otherwise."""
    if p.candidates != "auto":
        return p.candidates
    return "roots" if b.n > p.roots_above else "hash"


def _descriptor(ms: MinutiaSet, p: MatchParams) -> np.ndarray:
    if p.descriptor == "shape_context":
        return shape_context(ms, by_kind=p.by_kind)
    if p.descriptor == "mcc":
        return cylinder_code(ms)
    if p.descriptor == "both":
        # unit rows scaled by 1/sqrt(2): the dot product is the mean of both similarities
        both = np.hstack([shape_context(ms, by_kind=p.by_kind), cylinder_code(ms)])
        return (both / np.sqrt(2.0)).astype(np.float32)
    raise ValueError(f"MatchParams.descriptor: unknown {p.descriptor!r}")


def _footprint(ms: MinutiaSet) -> np.ndarray:
    """Outline (4, 2) of the raster in the math frame: georef extent, else point bbox."""
    if ms.georef is not None and ms.georef.width > 0 and ms.georef.height > 0:
        c0, c1, r0, r1 = -0.5, ms.georef.width - 0.5, -0.5, ms.georef.height - 0.5
    elif len(ms):
        c0, c1 = ms.col.min() - 0.5, ms.col.max() + 0.5
        r0, r1 = ms.row.min() - 0.5, ms.row.max() + 0.5
    else:
        c0 = c1 = r0 = r1 = 0.0
    return np.array([[c0, -r0], [c1, -r0], [c1, -r1], [c0, -r1]], float)


@dataclass
class MatchResult:
    """Outcome of :func:`compare` or :func:`localise`.

    Attributes
    ----------
    decision : Decision
    score : float
        Significance score (see :func:`significance`); -inf when nothing was registered.
    n_pairings : int
    pairings : ndarray, shape (m, 2)
        Index in A and index in B of each pairing.
    transform : ndarray, shape (2, 3)
        Pixel transform A -> B: ``[col', row'] = transform @ [col, row, 1]``; the form is
        ``[[a, b, tx], [-b, a, ty]]`` with ``a = s cos(theta)``, ``b = s sin(theta)``.
    rotation : float
        theta (rad), CCW in the north-up map (minutia angles grow by theta).
    scale : float
    scale_estimated : bool
        Whether the scale was fitted (else it is 1 by construction).
    covariance : ndarray, shape (4, 4)
        Covariance of (a, b, tx, ty) from the fit residuals.
    rms : float
        RMS pairing residual (px).
    n_a, n_b : int
        Minutiae in each set.
    n_overlap : tuple of int
        Minutiae of A inside B's footprint and of B inside A's, after the transform.
    expected_chance : float
        Pairings expected by chance at this transform (Poisson mean).
    pairing_ratio : float
        ``n_pairings**2 / (n_overlap_a * n_overlap_b)``, the classical normalised count.
    creases : CreaseEvidence or None
        Agreement of the crease skeletons at the transform (its ``score`` is included in
        ``score``), when both sets came with crease images and the crease check is on.
    ridges : CreaseEvidence or None
        The same for the ridge skeletons, when the ridge check applied.
    reason : str
        Why the decision is "no decision" or "no match", for logs and messages.
    """

    decision: Decision
    score: float = -np.inf
    n_pairings: int = 0
    pairings: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.intp))
    transform: np.ndarray = field(default_factory=lambda: np.full((2, 3), np.nan))
    rotation: float = np.nan
    scale: float = np.nan
    scale_estimated: bool = False
    covariance: np.ndarray = field(default_factory=lambda: np.full((4, 4), np.nan))
    rms: float = np.nan
    n_a: int = 0
    n_b: int = 0
    n_overlap: tuple[int, int] = (0, 0)
    expected_chance: float = np.nan
    pairing_ratio: float = 0.0
    creases: CreaseEvidence | None = None
    ridges: CreaseEvidence | None = None
    reason: str = ""

    @property
    def matched(self) -> bool:
        """True when the decision is a match."""
        return self.decision == Decision.MATCH

    def apply(self, col, row) -> tuple[np.ndarray, np.ndarray]:
        """Map pixel coordinates of A into B."""
        col = np.asarray(col, float)
        row = np.asarray(row, float)
        m = self.transform
        return m[0, 0] * col + m[0, 1] * row + m[0, 2], m[1, 0] * col + m[1, 1] * row + m[1, 2]

    def point_covariance(self, col: float, row: float) -> np.ndarray:
        """2x2 covariance (px^2) of the image in B of pixel (col, row) of A."""
        j = np.array([[col, row, 1.0, 0.0], [row, -col, 0.0, 1.0]])
        return j @ self.covariance @ j.T


# --------------------------------------------------------------------------- candidates


@dataclass
class _Votes:
    """Candidate edge correspondences: (ia -> ib) and (ja -> jb), rotation, weight."""

    ia: np.ndarray
    ja: np.ndarray
    ib: np.ndarray
    jb: np.ndarray
    theta: np.ndarray
    weight: np.ndarray


def _similarity_matrix(a: MinutiaIndex, b: MinutiaIndex, with_creases: bool = True):
    s = a.descriptor @ b.descriptor.T
    if with_creases and a.crease is not None and b.crease is not None:
        # 0.5 (s + max(crease products, 0)), in place (~18k entries a block pair)
        crease = a.crease @ b.crease.T
        s += np.maximum(crease, 0.0, out=crease)
        s *= 0.5
    return s


def _length_tol(p: MatchParams, length):
    if p.estimate_scale:
        return p.edge_length_tol + p.max_scale_change * length
    return np.full(np.shape(length), p.edge_length_tol)


def _hash_votes(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams) -> _Votes:
    hb = b.edge_hash()
    _, _, _, _, qi, qj, qdir = a.edge_query()
    q, e = hb.lookup_prepared(a.prepared_query(hb), p.edge_angle_tol)
    if _kernels.HAVE_NUMBA:
        ia, ja, ib, jb, theta = _kernels.hash_votes(q, e, qi, qj, qdir, hb.rows, hb.j,
                                                    hb.direction)
    else:
        ia, ja, ib, jb = qi[q], qj[q], hb.rows[e], hb.j[e]
        theta = wrap_angle(hb.direction[e] - qdir[q])
    if p.use_descriptors:
        s = _similarity_matrix(a, b)
        s = np.maximum(s, 0.0, out=s).ravel()
        if _kernels.HAVE_NUMBA and s.dtype == np.float32:
            w = _kernels.vote_weights(s, b.n, ia, ja, ib, jb)
        else:
            w = s[ia * b.n + ib] * s[ja * b.n + jb] + 0.05
    else:
        w = np.ones(len(ia))
    return _Votes(ia, ja, ib, jb, theta, w)


def _root_votes(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams) -> _Votes:
    # shape contexts only: the crease descriptor's product over a region's thousands of
    # minutiae would triple the localisation time (the hash generator for blocks keeps it)
    s = _similarity_matrix(a, b, with_creases=False)
    k = min(p.k_roots, b.n)
    top = np.argpartition(-s, k - 1, axis=1)[:, :k] if k < b.n else np.tile(
        np.arange(b.n), (a.n, 1))
    ra = np.repeat(np.arange(a.n), k)
    rb = top.ravel()
    ea, eb = a.edges, b.edges
    kq, kr = min(p.k_query, ea.k), min(p.k_ref, eb.k)
    la = ea.length[ra, :kq, None]
    lb = eb.length[rb, None, :kr]
    tol = _length_tol(p, la)
    ok = (ea.valid[ra, :kq, None] & eb.valid[rb, None, :kr] & (np.abs(la - lb) <= tol)
          & (np.abs(wrap_angle(ea.beta_i[ra, :kq, None] - eb.beta_i[rb, None, :kr]))
             <= p.edge_angle_tol)
          & (np.abs(wrap_angle(ea.beta_j[ra, :kq, None] - eb.beta_j[rb, None, :kr]))
             <= p.edge_angle_tol))
    r, qa, qb = np.nonzero(ok)
    ia, ib = ra[r], rb[r]
    ja, jb = ea.j[ia, qa], eb.j[ib, qb]
    theta = wrap_angle(eb.direction[ib, qb] - ea.direction[ia, qa])
    w = np.maximum(s[ia, ib], 0.0) * np.maximum(s[ja, jb], 0.0) + 0.05
    return _Votes(ia, ja, ib, jb, theta, w)


# --------------------------------------------------------------------------- consensus


@dataclass
class _Hypothesis:
    c: complex          # rotation (and scale) as a complex factor
    t: complex          # translation: z_b = c * z_a + t
    ia: np.ndarray      # supporting correspondences
    ib: np.ndarray
    support: float


def _rotation_peaks(theta, w, p: MatchParams, n_peaks: int) -> np.ndarray:
    """Centres of the strongest rotation cells (circular histogram, 3-cell smoothing)."""
    nb = max(4, int(round(TWO_PI / p.rot_bin)))
    if _kernels.HAVE_NUMBA:
        h = _kernels.rotation_histogram(theta, w, nb, nb / TWO_PI)
    else:
        k = (np.floor((theta + np.pi) * (nb / TWO_PI)).astype(np.intp)) % nb
        h = np.bincount(k, w, nb)
    h = np.concatenate([h[-1:], h, h[:1]])            # circular: pad one cell each side
    h = h[:-2] + h[1:-1] + h[2:]
    pad = np.concatenate([h[-1:], h, h[:1]])
    idx = np.flatnonzero((h >= pad[:-2]) & (h > pad[2:]) & (h > 0))
    idx = idx[np.argsort(-h[idx])][:n_peaks]
    # weak rotation peaks beside a dominant one are not worth a translation search
    idx = idx[h[idx] >= p.min_support_ratio * h[idx[0]]] if len(idx) else idx
    return (idx + 0.5) * (TWO_PI / nb) - np.pi


def _vote_midpoints(v: _Votes, a: MinutiaIndex, b: MinutiaIndex, sel=slice(None)):
    """The edge midpoints in A (from A's centroid) and in B of the votes ``sel``: the
    translation of A's centroid at rotation ``c`` is ``mid_b - c * mid_a``."""
    return (0.5 * (a.z[v.ia[sel]] + a.z[v.ja[sel]]) - a.centroid,
            0.5 * (b.z[v.ib[sel]] + b.z[v.jb[sel]]))


def _rotation_support(v: _Votes, a: MinutiaIndex, b: MinutiaIndex, p: MatchParams,
                      rotations: np.ndarray, midpoints=None) -> np.ndarray:
    """Weight of the strongest translation cell (3 x 3 cells centred on a voted one) at each
    rotation: the joint rotation-translation Hough, one rotation at a time, as
    :func:`_hypotheses` builds it at a rotation peak."""
    mid_a, mid_b = midpoints if midpoints is not None else _vote_midpoints(v, a, b)
    if _kernels.HAVE_NUMBA:
        return _kernels.rotation_support(v.theta, v.weight, mid_a, mid_b, rotations,
                                         2.0 * p.rot_bin, 1.0 / p.trans_bin)
    out = np.zeros(len(rotations))
    for k, th0 in enumerate(rotations):
        sel, d_sel = _near_rotation(v.theta, th0, p)
        w = v.weight[sel].astype(float)
        if len(sel) == 0 or w.sum() <= 0:
            continue
        c = np.exp(1j * (th0 + np.dot(w, d_sel) / w.sum()))
        gx, gy, nx, ny, h = _translation_grid(mid_b[sel] - c * mid_a[sel], w, p)
        h = np.pad(h, 1)
        box = sum(h[1 + dy:1 + dy + ny, 1 + dx:1 + dx + nx]
                  for dy in (-1, 0, 1) for dx in (-1, 0, 1))
        out[k] = box[gy, gx].max()
    return out


def _hypotheses(v: _Votes, a: MinutiaIndex, b: MinutiaIndex, p: MatchParams,
                sweep: bool = False):
    """Strongest (rotation, translation) Hough cells, best first: at the rotation
    histogram's peaks, or with ``sweep`` at the rotation cells whose strongest translation
    cell is heaviest, among those the peaks leave out."""
    if len(v.ia) == 0:
        return []
    hyps = []
    best = 0.0
    if p.max_rotation < math.pi:
        # a heading prior: only rotations within max_rotation of zero are searched
        keep = np.abs(wrap_angle(v.theta)) <= p.max_rotation + p.rot_bin
        v = _Votes(*(getattr(v, f.name)[keep] for f in fields(v)))
        if len(v.ia) == 0:
            return []
    peaks = _rotation_peaks(v.theta, v.weight, p, n_peaks=p.n_rotation_peaks)
    rotations = peaks
    midpoints = None   # of all votes, when the sweep needs them anyway
    if sweep:
        # the strongest joint cells among the rotations the peaks did not try (a peak is a
        # cell centre of the same grid: its hypotheses would come out the same)
        midpoints = _vote_midpoints(v, a, b)
        nb = max(4, int(round(TWO_PI / p.rot_bin)))
        cells = (np.arange(nb) + 0.5) * (TWO_PI / nb) - np.pi
        support = _rotation_support(v, a, b, p, cells, midpoints)
        support[np.rint((peaks + np.pi) * (nb / TWO_PI) - 0.5).astype(np.intp) % nb] = 0.0
        strongest = np.argsort(-support, kind="stable")[:p.n_rotation_peaks]
        rotations = cells[strongest[support[strongest] > 0]]
    for th0 in rotations:
        sel, d_sel = _near_rotation(v.theta, th0, p)
        w = v.weight[sel]
        if len(sel) == 0 or w.sum() < p.min_support_ratio * best:
            continue   # none of its cells could pass the verification cut in _match
        c = np.exp(1j * (th0 + np.dot(w, d_sel) / w.sum()))
        # translation of A's centroid at this rotation: a two-stage Hough keeps the
        # translation cells sharp (a per-vote rotation error would smear them)
        mid_a, mid_b = ((midpoints[0][sel], midpoints[1][sel]) if midpoints is not None
                        else _vote_midpoints(v, a, b, sel))
        t = mid_b - c * mid_a
        hyps.extend(_translation_peaks(t, sel, w, c, v, a, p, n_peaks=2,
                                       min_support=p.min_support_ratio * best))
        best = max(h.support for h in hyps) if hyps else 0.0
    hyps.sort(key=lambda h: -h.support)
    return hyps[:p.n_hypotheses]


def _near_rotation(theta, th0: float, p: MatchParams):
    """Votes within two rotation cells of ``th0``: their indices and angle differences."""
    if _kernels.HAVE_NUMBA:
        return _kernels.near_angles(theta, float(th0), 2.0 * p.rot_bin)
    d = wrap_angle(theta - th0)
    sel = np.flatnonzero(np.abs(d) <= 2.0 * p.rot_bin)
    return sel, d[sel]


def _translation_grid(t, w, p: MatchParams):
    """Translation Hough cells: each vote's cell ``(gx, gy)`` from the lowest translation,
    the grid size and the float64 weight per cell, shape ``(ny, nx)``."""
    if _kernels.HAVE_NUMBA:
        gx, gy, nx, ny, h = _kernels.translation_grid(t.real, t.imag, w, 1.0 / p.trans_bin)
        return gx, gy, nx, ny, h.reshape(ny, nx)
    x0, y0 = t.real.min(), t.imag.min()
    gx = ((t.real - x0) * (1.0 / p.trans_bin)).astype(np.intp)
    gy = ((t.imag - y0) * (1.0 / p.trans_bin)).astype(np.intp)
    nx, ny = int(gx.max()) + 1, int(gy.max()) + 1
    return gx, gy, nx, ny, np.bincount(gy * nx + gx, w, nx * ny).reshape(ny, nx)


def _translation_peaks(t, sel, w, c, v: _Votes, a: MinutiaIndex, p: MatchParams, n_peaks,
                       min_support: float = 0.0):
    """Strongest translation cells at rotation ``c``; cells weaker than ``min_support``
    (which :func:`_match` would not verify) are not built."""
    gx, gy, nx, ny, h = _translation_grid(t, w, p)
    h = h.astype(np.float32)
    # 3x3 box sum so that a cluster split over cell borders still counts as one
    box = cv2.boxFilter(h, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    out = []
    for _ in range(n_peaks):
        k = int(np.argmax(box))
        # (float32 box sums: a hair of slack so that no cell at the cut is lost)
        if box.flat[k] <= 0 or box.flat[k] < min_support * (1.0 - 1e-4):
            break
        py, px = divmod(k, nx)
        box[max(0, py - 2):py + 3, max(0, px - 2):px + 3] = 0
        if _kernels.HAVE_NUMBA:
            m = _kernels.cell_members(gx, gy, px, py)
        else:
            m = np.flatnonzero((np.abs(gx - px) <= 1) & (np.abs(gy - py) <= 1))
        wm = w[m]
        tc = complex(np.dot(wm, t[m]) / wm.sum())
        s = sel[m]
        ia = np.concatenate([v.ia[s], v.ja[s]])
        ib = np.concatenate([v.ib[s], v.jb[s]])
        out.append(_Hypothesis(c, tc - c * a.centroid, ia, ib, float(wm.sum())))
    return out


# --------------------------------------------------------------------------- registration


def fit_similarity(za, zb, w=None, scale: bool = False) -> tuple[complex, complex]:
    """Least-squares transform ``zb ~ c * za + t`` (complex Procrustes / Umeyama).

    Parameters
    ----------
    za, zb : ndarray of complex
        Corresponding points in the math frame.
    w : ndarray, optional
        Weights.
    scale : bool
        Estimate a scale (``|c|`` free) or a rigid motion (``|c| = 1``).

    Returns
    -------
    c, t : complex
        ``c`` is NaN when the points do not fix a rotation (e.g. all A or all B points
        coincide).
    """
    w = np.ones(len(za)) if w is None else np.asarray(w, float)
    ma = np.sum(w * za) / w.sum()
    mb = np.sum(w * zb) / w.sum()
    num = complex(np.sum(w * np.conj(za - ma) * (zb - mb)))
    if abs(num) < 1e-9:
        return complex(np.nan, np.nan), complex(np.nan, np.nan)
    if scale:
        c = num / float(np.sum(w * np.abs(za - ma) ** 2))
    else:
        c = num / abs(num)
    return complex(c), complex(mb - c * ma)


def _ransac(za, zb, dang, p: MatchParams, rng, c0: complex, t0: complex):
    """Best transform over 2-point samples (and the Hough guess); inlier mask."""
    m = len(za)
    n_it = min(p.ransac_iterations, m * (m - 1) // 2)
    i = j = np.zeros(0, np.int64)
    if n_it > 0:
        i = rng.integers(0, m, n_it)
        j = (i + rng.integers(1, m, n_it)) % m
    if _kernels.HAVE_NUMBA:
        return _kernels.ransac(za, zb, dang, i, j, complex(c0), complex(t0),
                               float(p.edge_min), bool(p.estimate_scale),
                               float(p.max_scale_change), float(p.pos_tol),
                               float(p.angle_tol))
    dz = za[j] - za[i]
    ok = (np.abs(dz) > p.edge_min) & (np.abs(zb[j] - zb[i]) > p.edge_min)
    c = (zb[j] - zb[i])[ok] / dz[ok]
    if not p.estimate_scale:
        c = c / np.abs(c)
    t = 0.5 * (zb[i] + zb[j])[ok] - c * 0.5 * (za[i] + za[j])[ok]
    cs, ts = np.concatenate([[c0], c]), np.concatenate([[t0], t])
    if p.estimate_scale:
        keep = np.abs(np.log(np.abs(cs))) <= p.max_scale_change
        keep[0] = True
        cs, ts = cs[keep], ts[keep]
    res = np.abs(cs[:, None] * za[None, :] + ts[:, None] - zb[None, :])
    ang = np.abs(wrap_angle(dang[None, :] - np.angle(cs)[:, None]))
    inl = (res <= p.pos_tol) & (ang <= p.angle_tol)
    best = int(np.argmax(inl.sum(axis=1)))
    return cs[best], ts[best], inl[best]


# reference sets up to this size are paired by brute force (numba) instead of the k-d tree
_BRUTE_PAIR_MAX = 400


def _pair(a: MinutiaIndex, b: MinutiaIndex, c: complex, t: complex, p: MatchParams,
          k: int = 3):
    """One-to-one pairings (ia, ib) within tolerance after ``z -> c z + t``."""
    zt = c * a.z + t
    k = min(k, b.n)
    if _kernels.HAVE_NUMBA and b.n <= _BRUTE_PAIR_MAX:
        # a block-sized B: brute force in one loop beats the tree query and the filtering
        i, j, cost = _kernels.pair_candidates(zt.real, zt.imag, b.z.real, b.z.imag, a.angle,
                                              b.angle, float(np.angle(c)), k,
                                              float(p.pos_tol), float(p.angle_tol))
        return _greedy_one_to_one(i, j, cost)
    # complex128 is (re, im) pairs in memory: the (n, 2) point array without a copy
    d, j = b.tree.query(zt.view(np.float64).reshape(-1, 2), k=k,
                        distance_upper_bound=p.pos_tol)
    d, j = d.reshape(a.n, k), j.reshape(a.n, k)
    i = np.repeat(np.arange(a.n), k)
    d, j = d.ravel(), j.ravel()
    ok = np.isfinite(d)
    i, j, d = i[ok], j[ok], d[ok]
    dang = np.abs(wrap_angle(b.angle[j] - a.angle[i] - np.angle(c)))
    ok = dang <= p.angle_tol
    i, j = i[ok], j[ok]
    cost = d[ok] / p.pos_tol + dang[ok] / p.angle_tol
    return _greedy_one_to_one(i, j, cost)


def _residuals(a: MinutiaIndex, b: MinutiaIndex, c: complex, t: complex, pairs):
    """Leave-one-out position (px) and direction (rad) residuals of the pairings.

    ``c, t`` are a least-squares fit to these pairings, which pulls each pairing towards
    itself: with few pairings a chance coincidence would look tighter than it is. The
    position residual is therefore divided by ``1 - h`` (``h`` the pairing's leverage in
    the linear fit ``zb = c za + t``), which is the residual under the fit without it.
    """
    ia, ib = pairs[:, 0], pairs[:, 1]
    za = a.z[ia]
    dist = np.abs(c * za + t - b.z[ib])
    dang = np.abs(wrap_angle(b.angle[ib] - a.angle[ia] - np.angle(c)))
    m = len(za)
    if m > 2:
        spread = np.abs(za - za.mean()) ** 2
        leverage = 1.0 / m + spread / max(float(spread.sum()), 1e-12)
        dist = dist / np.maximum(1.0 - leverage, 1e-3)
    return dist, dang


def _greedy_one_to_one(i, j, cost, rounds: int = 3):
    """Greedy one-to-one matching by increasing cost, vectorised as rounds of mutual bests.

    In each round a candidate is taken when it is the cheapest remaining one of both its
    ends; taken ends are then removed. On these sparse graphs three rounds are the greedy
    result in practice.
    """
    if _kernels.HAVE_NUMBA:
        return _kernels.greedy_one_to_one(i, j, cost, rounds)
    n_i = int(i.max(initial=-1)) + 1
    n_j = int(j.max(initial=-1)) + 1
    if len(i) == 0 or (np.bincount(i, minlength=n_i).max() == 1
                       and np.bincount(j, minlength=n_j).max() == 1):
        return np.column_stack([i, j])   # already one-to-one (common at these densities)
    order = np.argsort(cost, kind="stable")
    i, j = i[order], j[order]
    out_i, out_j = [], []
    for _ in range(rounds):
        if len(i) == 0:
            break
        k = np.arange(len(i))
        first_i = np.empty(n_i, np.intp)
        first_i[i[::-1]] = k[::-1]      # the last write wins: first occurrence of each i
        first_j = np.empty(n_j, np.intp)
        first_j[j[::-1]] = k[::-1]
        take = (first_i[i] == k) & (first_j[j] == k)
        out_i.append(i[take])
        out_j.append(j[take])
        used_i = np.zeros(n_i, bool)
        used_i[i[take]] = True
        used_j = np.zeros(n_j, bool)
        used_j[j[take]] = True
        keep = ~used_i[i] & ~used_j[j]
        i, j = i[keep], j[keep]
    if not out_i:
        return np.zeros((0, 2), np.intp)
    return np.column_stack([np.concatenate(out_i), np.concatenate(out_j)])


def _register(h: _Hypothesis, a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, rng):
    """RANSAC + least squares on a hypothesis' correspondences; pairings over all minutiae."""
    key = np.unique(h.ia * b.n + h.ib)
    ia, ib = key // b.n, key % b.n
    c, t = h.c, h.t
    if len(ia) >= 2:
        c, t, inl = _ransac(a.z[ia], b.z[ib], b.angle[ib] - a.angle[ia], p, rng, h.c, h.t)
        if inl.sum() >= 2:
            c1, t1 = fit_similarity(a.z[ia[inl]], b.z[ib[inl]], scale=p.estimate_scale)
            if np.isfinite(c1):   # degenerate inliers (one point each side): keep RANSAC's
                c, t = c1, t1
    return c, t, _pair(a, b, c, t, p)


def _refine(a: MinutiaIndex, b: MinutiaIndex, c, t, pairs, p: MatchParams, iterations=2):
    """Alternate least squares on the pairings and guided re-pairing."""
    for _ in range(iterations):
        if len(pairs) < 2:
            break
        c1, t1 = fit_similarity(a.z[pairs[:, 0]], b.z[pairs[:, 1]], scale=p.estimate_scale)
        if not np.isfinite(c1) or (p.estimate_scale
                                   and abs(math.log(abs(c1))) > p.max_scale_change):
            break
        new = _pair(a, b, c1, t1, p)
        if len(new) < len(pairs):
            break
        grown = len(new) > len(pairs)
        c, t, pairs = c1, t1, new
        if not grown:
            break   # same pairing count: the fit has settled
    return c, t, pairs


# --------------------------------------------------------------------------- score


def pairing_evidence(dist, dang, p: MatchParams) -> np.ndarray:
    """Evidence of each pairing: ``-ln`` of the chance of a pairing at least this close.

    A chance pairing lies uniformly in the pairing disc and angle window, so
    ``u = (dist / pos_tol)**2`` and ``v = dang / angle_tol`` are uniform on (0, 1) and
    ``-ln u - ln v`` is Gamma(2, 1)-distributed. Residuals below ``pos_floor`` /
    ``angle_floor`` count as those floors (finer agreement is not evidence).
    """
    u = np.maximum(np.asarray(dist, float), p.pos_floor) ** 2 / p.pos_tol ** 2
    v = np.maximum(np.asarray(dang, float), p.angle_floor) / p.angle_tol
    return -np.log(np.minimum(u, 1.0)) - np.log(np.minimum(v, 1.0))


_LOG_FACTORIAL = gammaln(np.arange(4096) + 1.0)   # ln j!, grown on demand


def _log_factorial(n: int) -> np.ndarray:
    global _LOG_FACTORIAL
    if n > len(_LOG_FACTORIAL):
        _LOG_FACTORIAL = gammaln(np.arange(2 * n) + 1.0)
    return _LOG_FACTORIAL[:n]


def compound_log10_sf(evidence: float, lam: float) -> float:
    """log10 P(S >= evidence) for S the summed evidence of chance pairings.

    The number of chance pairings is Poisson(lam) and each adds an independent Gamma(2, 1)
    (see :func:`pairing_evidence`), so ``P(S >= s) = sum_k Pois(k; lam) Q(2k, s)`` with Q the
    regularised upper incomplete gamma function. For integer ``2k``, ``Q(2k, s)`` is the
    Poisson(s) distribution function at ``2k - 1``, so all of them come from one cumulative
    sum of Poisson(s) probabilities: exact, and cheap.
    """
    if evidence <= 0:
        return 0.0
    if lam <= 0:
        return -np.inf
    # terms beyond both the Poisson bulk and k ~ evidence / 2 (where Q -> 1) are negligible
    k_max = int(max(2.0 * lam + 10.0 * math.sqrt(lam),
                    0.5 * evidence + 5.0 * math.sqrt(evidence))) + 20
    log_fact = _log_factorial(2 * k_max + 2)
    if _kernels.HAVE_NUMBA:
        return float(_kernels.compound_log10_sf(float(evidence), float(lam), k_max, log_fact))
    # ... and so are those whose Poisson(lam) weight alone is e^-40 below the k = 1 term
    k = np.arange(1.0, k_max + 1.0)
    log_pois = k * math.log(lam) - lam - log_fact[1:k_max + 1]
    first = log_pois[0] - evidence + math.log1p(evidence)          # ln of the k = 1 term
    beyond = np.flatnonzero((log_pois < first - 40.0) & (k > lam))
    if len(beyond):
        k_max = int(beyond[0]) + 1
        k, log_pois = k[:k_max], log_pois[:k_max]
    j = np.arange(2 * k_max, dtype=float)
    log_pmf = j * math.log(evidence) - evidence - log_fact[:2 * k_max]   # Poisson(s) at j
    top = float(log_pmf.max())
    with np.errstate(divide="ignore"):
        log_q = np.log(np.cumsum(np.exp(log_pmf - top))[1::2]) + top  # Q(2k, s), k = 1..
    log_terms = log_pois + log_q
    lost = ~np.isfinite(log_q)   # Q below exp(-745) of the largest Poisson(s) term
    if lost.any() and np.max(log_pois[lost]) + top - 745.0 > np.max(log_terms) - 40.0:
        # the underflowed terms might matter (huge evidence): the same sums in log space
        log_q = np.logaddexp.accumulate(log_pmf)[1::2]
        log_terms = log_pois + log_q
    peak = float(np.max(log_terms))
    return (peak + math.log(float(np.sum(np.exp(log_terms - peak))))) / math.log(10.0)


def significance(dist, dang, n_a: float, n_b: float, area: float, search_area: float,
                 radius_a: float, p: MatchParams) -> tuple[float, float]:
    """Score of a registration: how unlikely its pairings are between unrelated sets.

    Under the null hypothesis (different places) the ``n_b`` minutiae of B in the overlap of
    ``area`` px^2 are unrelated to A's ``n_a``; each of A's minutiae then finds a partner
    within ``pos_tol`` and ``angle_tol`` with probability ``n_b * pi pos_tol^2 / area *
    angle_tol / pi``, so the number of chance pairings is about Poisson with mean ``lam``,
    and each lands uniformly in the pairing disc and angle window. The test statistic is the
    summed :func:`pairing_evidence` of the pairings (a likelihood-ratio form: many pairings,
    and pairings much closer than the tolerances, both count; true pairings have residuals
    of ~1-2 px and a few degrees, chance ones fill the tolerances). The matcher tried many
    transforms, so the tail probability is multiplied by the number of distinguishable
    transforms in the search space (``search_area / (pi pos_tol^2)`` translations times
    ``2 pi / (pos_tol / radius_a)`` rotations, a Bonferroni bound).

    Parameters
    ----------
    dist, dang : array_like
        Position (px) and direction (rad) residual of each pairing.
    n_a, n_b : float
        Minutiae of A and of B in the overlap.
    area, search_area : float
        Overlap area and area of the searched translations (px^2).
    radius_a : float
        RMS radius of A's minutiae about their centroid (px): sets the rotation resolution.
    p : MatchParams

    Returns
    -------
    score : float
        ``-log10(P(S >= s) * n_transforms)``: about the base-10 logarithm of how many
        comparisons of unrelated terrain it takes to see one this good by chance.
    lam : float
        The expected number of chance pairings.
    """
    return _significance(float(np.sum(pairing_evidence(dist, dang, p))), n_a, n_b, area,
                         search_area, radius_a, p)


def _significance(evidence: float, n_a, n_b, area, search_area, radius_a, p: MatchParams):
    """:func:`significance` from the summed pairing evidence."""
    lam, log_trials = _chance_model(n_a, n_b, area, search_area, radius_a, p)
    return -compound_log10_sf(evidence, lam) - log_trials, lam


def _chance_model(n_a, n_b, area, search_area, radius_a, p: MatchParams):
    """Chance pairings expected at one transform, and log10 of the transforms searched."""
    cell = math.pi * p.pos_tol ** 2
    lam = n_a * n_b * cell / max(area, cell) * min(1.0, p.angle_tol / math.pi)
    lam = min(lam, float(min(n_a, n_b)))
    return lam, _log10_transforms(search_area, radius_a, p)


def _log10_transforms(search_area, radius_a, p: MatchParams) -> float:
    """log10 of the transforms distinguishable at the pairing tolerance in the search."""
    cell = math.pi * p.pos_tol ** 2
    # rotations searched: the whole circle, or the prior's window (max_rotation)
    n_rot = min(TWO_PI, 2.0 * p.max_rotation + p.rot_bin) / min(
        math.pi, p.pos_tol / max(radius_a, p.pos_tol))
    n_rot = max(n_rot, 1.0)
    return math.log10(max(search_area / cell, 1.0) * n_rot)


def _best_possible_score(m: int, n_a, n_b, area, search_area, radius_a, p: MatchParams,
                         enough: float) -> float:
    """Score of ``m`` exact pairings, or a lower bound of it when that is ``>= enough``.

    The Chernoff bound ``P(S >= s) <= exp(-s / 2 + 3 lam)`` (the compound Poisson-Gamma(2)
    tail at exponent 1/2) spares the exact tail when the answer is clearly yes.
    """
    lam, log_trials = _chance_model(n_a, n_b, area, search_area, radius_a, p)
    evidence = m * float(pairing_evidence(0.0, 0.0, p))
    bound = (0.5 * evidence - 3.0 * lam) / math.log(10.0) - log_trials
    if bound >= enough:
        return bound
    return -compound_log10_sf(evidence, lam) - log_trials


def calibrate_threshold(non_pva_scores, false_match_rate: float) -> float:
    """Score threshold giving at most ``false_match_rate`` accepted non-PVA comparisons.

    With enough samples (``n * rate >= 1``) this is the empirical upper quantile (the
    smallest threshold with at most ``rate * n`` scores at or above it). Rarer rates are
    extrapolated with an exponential tail fitted to the top 10% of scores (peaks over
    threshold, generalised Pareto with zero shape), which the significance score follows
    when its chance model is right (P(score > s) ~ 10**-s).

    Parameters
    ----------
    non_pva_scores : array_like
        Scores of comparisons between different places (non-finite ones are ignored as
        "no registration").
    false_match_rate : float
        Accepted fraction of non-PVA comparisons, in (0, 1).

    Returns
    -------
    float
        The threshold (a score must be >= it to match).
    """
    s = np.sort(np.asarray(non_pva_scores, float))
    s = s[np.isfinite(s)]
    if not 0 < false_match_rate < 1:
        raise ValueError("calibrate_threshold: false_match_rate must be in (0, 1)")
    if len(s) == 0:
        raise ValueError("calibrate_threshold: no finite non-PVA scores")
    n = len(s)
    allowed = int(math.floor(false_match_rate * n))
    if allowed >= 1:
        return float(np.nextafter(s[n - allowed - 1], np.inf))
    n_tail = max(5, n // 10)
    if n < n_tail + 1:
        return float(np.nextafter(s[-1], np.inf))
    u = s[n - n_tail - 1]
    beta = max(float(np.mean(s[n - n_tail:] - u)), 1e-6)
    thr = u + beta * math.log((n_tail / n) / false_match_rate)
    return float(max(thr, np.nextafter(s[-1], np.inf)))


# --------------------------------------------------------------------------- front ends


# settings baked into a MinutiaIndex (edges, hash, descriptors)
_INDEX_FIELDS = ("k_query", "k_ref", "edge_min", "edge_max", "edge_length_tol",
                 "edge_angle_tol", "by_kind", "descriptor", "estimate_scale",
                 "max_scale_change", "crease_descriptor", "crease_exclude_radius")


def _as_index(x, p: MatchParams, crease=None) -> MinutiaIndex:
    if isinstance(x, MinutiaIndex):
        bad = [f for f in _INDEX_FIELDS if getattr(x.params, f) != getattr(p, f)]
        if bad:
            raise ValueError(f"MinutiaIndex built with other settings ({', '.join(bad)}): "
                             "build it with this Matcher's index()")
        return x
    return MinutiaIndex(x, p, crease)


def _overlap(a: MinutiaIndex, b: MinutiaIndex, c: complex, t: complex):
    """Minutiae of A inside B's footprint, of B inside A's (mapped), and the overlap area."""
    in_b = _inside(c * a.z + t, b.footprint_box)
    in_a = _inside((b.z - t) / c, a.footprint_box)
    return int(in_b.sum()), int(in_a.sum()), _overlap_area(a, b, c, t)


def _overlap_area(a: MinutiaIndex, b: MinutiaIndex, c: complex, t: complex) -> float:
    """Area of A's footprint mapped into B, inside B's footprint."""
    fa_b = c * a.footprint_z + t
    # complex128 is (re, im) pairs in memory: the (n, 2) corner array without a stack
    area, _ = cv2.intersectConvexConvex(fa_b.view(np.float64).reshape(-1, 2)
                                        .astype(np.float32), b.footprint32)
    return float(area)


def _inside(z, box) -> np.ndarray:
    # footprints are axis-aligned rectangles in their own frame: box (x0, x1, y0, y1)
    x0, x1, y0, y1 = box
    return (z.real >= x0) & (z.real <= x1) & (z.imag >= y0) & (z.imag <= y1)


def truncated_sigma2(mean_r2: float, radius: float) -> float:
    """Per-axis variance of isotropic 2-D Gaussian errors seen only within ``radius``.

    Pairings exist only where the residual is below the pairing radius, so the mean squared
    residual underestimates the noise when the noise is not small against the radius. For a
    truncated Rayleigh radius ``E[r^2 | r < T] = 2 s - T^2 e^(-T^2/2s) / (1 - e^(-T^2/2s))``
    (``s`` the per-axis variance), increasing in ``s`` up to ``T^2 / 2``; solved by bisection.
    """
    t2 = radius * radius
    if mean_r2 <= 0:
        return 0.0
    if mean_r2 >= 0.5 * t2 * 0.999:
        return t2   # residuals uniform over the disc: the noise is at least the radius

    def mean_r2_of(s):
        q = math.exp(-t2 / (2 * s))
        return 2 * s - t2 * q / (1 - q)

    lo, hi = 0.5 * mean_r2, t2
    for _ in range(30):   # relative precision ~1e-9
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if mean_r2_of(mid) < mean_r2 else (lo, mid)
    return 0.5 * (lo + hi)


def _covariance(za, zb, c: complex, t: complex, scale: bool,
                radius: float) -> tuple[np.ndarray, float]:
    """Covariance of pixel-frame (a, b, tx, ty) from the residuals of the fit."""
    m = len(za)
    r = zb - (c * za + t)
    n_par = 4 if scale else 3
    sum_r2 = float(np.dot(r.real, r.real) + np.dot(r.imag, r.imag))
    rms = math.sqrt(sum_r2 / m) if m else np.nan
    if m * 2 <= n_par:
        return np.full((4, 4), np.nan), rms
    # unbiased for the fitted parameters, then corrected for the pairing-radius truncation
    sigma2 = truncated_sigma2(sum_r2 * 2.0 / (2 * m - n_par), radius)
    col, row = from_complex(za)
    # pixel model: col' = a col + b row + tx ; row' = -b col + a row + ty; the Jacobian rows
    # [col, row, 1, 0] and [row, -col, 0, 1] give the normal matrix [[s2 I, B], [B, m I]]
    # with B = [[sc, sr], [sr, -sc]], B @ B = q I: its inverse in closed form (Schur
    # complement (m - q / s2) I)
    sc, sr = float(col.sum()), float(row.sum())
    s2 = float(np.dot(col, col) + np.dot(row, row))
    q = sc * sc + sr * sr
    schur = m - q / s2 if s2 > 0 else 0.0
    if schur <= 1e-12 * m:
        return np.full((4, 4), np.nan), rms   # all points coincide: no rotation
    u = -1.0 / (s2 * schur)
    corner = 1.0 / s2 + q / (s2 * s2 * schur)
    inv = np.array([[corner, 0.0, u * sc, u * sr], [0.0, corner, u * sr, -u * sc],
                    [u * sc, u * sr, 1.0 / schur, 0.0], [u * sr, -u * sc, 0.0, 1.0 / schur]])
    return sigma2 * inv, rms


def _pixel_transform(c: complex, t: complex) -> np.ndarray:
    a, b = c.real, c.imag
    return np.array([[a, b, t.real], [-b, a, -t.imag]])


@dataclass(frozen=True)
class _Scored:
    """A refined registration and its score."""

    c: complex
    t: complex
    pairs: np.ndarray
    score: float
    lam: float
    n_overlap: tuple[int, int]
    creases: CreaseEvidence | None
    search_penalty: float = 0.0   # log10 of extra transforms searched, already in score
    ridges: CreaseEvidence | None = None


def _scored(a: MinutiaIndex, b: MinutiaIndex, c, t, pairs, search_area: float,
            radius_a: float, p: MatchParams, with_creases: bool) -> _Scored:
    """Minutiae significance of a registration, plus its crease evidence when asked."""
    if _kernels.HAVE_NUMBA:
        n_ao, n_bo, evidence = _kernels.registration_terms(
            a.z, b.z, a.angle, b.angle, pairs[:, 0], pairs[:, 1], complex(c), complex(t),
            float(np.angle(c)), a.footprint_box, b.footprint_box, float(p.pos_tol),
            float(p.angle_tol), float(p.pos_floor), float(p.angle_floor))
        area = _overlap_area(a, b, c, t)
    else:
        n_ao, n_bo, area = _overlap(a, b, c, t)
        evidence = float(np.sum(pairing_evidence(*_residuals(a, b, c, t, pairs), p)))
    n_ao, n_bo = max(n_ao, len(pairs)), max(n_bo, len(pairs))
    score, lam = _significance(evidence, n_ao, n_bo, area, search_area, radius_a, p)
    creases = ridges = None
    if with_creases:
        creases = crease_evidence(a.crease_samples, b.crease_field, c, t,
                                  skip=a.crease_samples_around(pairs[:, 0]),
                                  **p.crease_tolerances)
        score += creases.score
        ridge_channel = _ridge_channel(a, b, p)
        if ridge_channel is not None:
            ridges = crease_evidence(*ridge_channel, c, t, **p.crease_tolerances)
            score += ridges.score
    return _Scored(c, t, pairs, score, lam, (n_ao, n_bo), creases, ridges=ridges)


def _ridge_channel(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams):
    """A's ridge samples and B's ridge field when the ridge check applies (on, both sets
    with ridges, and a small set), else None."""
    if (p.ridge_check and a.ridge_image is not None and b.ridge_image is not None
            and min(a.n, b.n) < p.ridge_check_below):
        return a.ridge_samples, b.ridge_field
    return None


def _refined_on_creases(a: MinutiaIndex, b: MinutiaIndex, best: _Scored, search_area: float,
                        radius_a: float, p: MatchParams, radii=(3.0,)) -> _Scored:
    """The registration moved onto B's creases (point-to-line ICP at each pairing radius in
    turn), kept if it scores better: a transform fitted to a few minutiae pairings is off by
    a pixel or two, the creases have hundreds of pixels. With the ridge check, the ICP on
    the valleys alone and the one on valleys and ridges together both try (parallel ridges
    can pull a joint ICP a ridge spacing off where the valleys alone would not)."""
    ridges = _ridge_channel(a, b, p)
    moved = best
    for channel in (None, ridges) if ridges is not None else (None,):
        c, t = best.c, best.t
        for radius in radii:
            c, t = refine_on_creases(a.crease_samples, b.crease_field, c, t, radius=radius,
                                     angle_tol=p.crease_angle_tol, ridges=channel)
        if c == best.c and t == best.t:
            continue
        pairs = _pair(a, b, c, t, p)
        if len(pairs) < 2:
            continue
        tried = _scored(a, b, c, t, pairs, search_area, radius_a, p, True)
        tried = replace(tried, score=tried.score - best.search_penalty,
                        search_penalty=best.search_penalty)
        if tried.score > moved.score:
            moved = tried
    return moved


def _search_level(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams,
                  scale_change: float = 0.0) -> SearchLevel:
    """The crease search's level: fine unless its work there exceeds the fine budget."""
    fine = a.crease_search_query(p.max_rotation, FINE, scale_change).work(b.crease_image.shape)
    return FINE if fine <= p.crease_search_fine_work else COARSE


def _searches_creases(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams,
                      scale_change: float = 0.0) -> bool:
    """Whether the crease search runs: too few minutiae for the pair votes, a query small
    enough for its rotations, and a search within the work bound."""
    if min(a.n, b.n) >= p.crease_search_below or max(a.crease_image.shape) \
            > p.crease_search_max_side:
        return False
    level = _search_level(a, b, p, scale_change)
    return a.crease_search_query(p.max_rotation, level, scale_change).work(
        b.crease_image.shape) <= p.crease_search_max_work


# rotations x scales the view search rasterises at one level at most: a 256 px view's fine
# level (~300 rotations x 11 scales of ~5000 crease pixels) would take ~0.5 GB
_VIEW_SEARCH_MAX_TRANSFORMS = 4096


def _view_search_level(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams) -> SearchLevel | None:
    """The finest level at which the view search (``MatchParams.view_search``) of A in B
    fits the work bound, or None."""
    for level in LEVELS:
        rotations, scales = a.crease_search_transforms(p.max_rotation, level,
                                                       p.search_scale)
        n_transforms = len(rotations) * len(scales)
        if n_transforms > _VIEW_SEARCH_MAX_TRANSFORMS or min_search_work(
                n_transforms, b.crease_image.shape, level.resolution) \
                > p.crease_search_max_work:
            continue   # too many rasters or too much work for this level: try a coarser one
        query = a.crease_search_query(p.max_rotation, level, p.search_scale)
        if query.work(b.crease_image.shape) <= p.crease_search_max_work:
            return level
    return None


def _crease_search_registrations(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams,
                                 level: SearchLevel | None = None,
                                 scale_change: float = 0.0, background: float = 0.0):
    """Registrations (c, t, pairings) proposed by the crease search, each moved onto B's
    creases (they may have fewer than two minutiae pairings), and log10 of the transforms
    searched (at the fine level's rotations and scales: a coarse proposal is refined over
    them). ``level`` defaults to :func:`_search_level`'s; ``scale_change`` and
    ``background`` are the view search's (:class:`MatchParams`)."""
    level = level or _search_level(a, b, p, scale_change)
    coarse = level != FINE
    fine_rotations, fine_scales = a.crease_search_transforms(p.max_rotation, FINE,
                                                             scale_change)
    found = search_transforms(
        a.crease_search_query(p.max_rotation, level, scale_change),
        b.crease_search(level, background),
        n_best=p.crease_search_proposals * (2 if coarse else 1), hit_radius=p.crease_radius,
        distinct_rotations=len(fine_rotations) * len(fine_scales))
    out, reached = [], []
    ridges = _ridge_channel(a, b, p)
    scale = (1.0 - scale_change, 1.0 + scale_change) if scale_change > 0 else None
    radii = p.crease_rescue_radii if coarse else (3.0,)
    for c, t, _ in found.proposals:
        for k, radius in enumerate(radii):
            c, t = refine_on_creases(_icp_samples(a, radius), b.crease_field, c, t,
                                     radius=radius, angle_tol=p.crease_angle_tol,
                                     ridges=ridges, scale=scale)
            if k == 0 and len(radii) > 1:
                # proposals the first radius brings to the same place would go on alike:
                # one is refined and scored (and counted in the best-of-n), not each
                if any(_same_transform(a, c, t, c2, t2) for c2, t2 in reached):
                    break
                reached.append((c, t))
        else:
            out.append((c, t, _pair(a, b, c, t, p)))
    return out, found.log10_transforms


# The crease ICP at a pairing radius of at least _SPARSE_ICP_RADIUS px (the wide radii that
# only bring a coarse proposal within the fine radii's reach) uses every other crease pixel
# of a view with more than _SPARSE_ICP_ABOVE: neighbouring skeleton pixels put the same
# constraint on the transform, and a few thousand place it as well as twice as many.
_SPARSE_ICP_RADIUS = 8.0
_SPARSE_ICP_ABOVE = 2000


def _icp_samples(a: MinutiaIndex, radius: float) -> CreaseSamples:
    """A's crease samples for the crease ICP at ``radius`` (see _SPARSE_ICP_RADIUS)."""
    if radius >= _SPARSE_ICP_RADIUS and len(a.crease_samples) > _SPARSE_ICP_ABOVE:
        return a.crease_samples_strided(2)
    return a.crease_samples


def _same_transform(a: MinutiaIndex, c: complex, t: complex, c2: complex, t2: complex,
                    tolerance: float = 1.0) -> bool:
    """Whether two transforms of A map its crease pixels within ``tolerance`` px of each
    other (at the crease reach from their mean)."""
    centre = a.crease_samples.z.mean()
    return abs(c - c2) * a.crease_reach + abs((c - c2) * centre + t - t2) <= tolerance


def _low(best: _Scored | None, n_scored: int, p: MatchParams) -> bool:
    """Whether a try is not clear enough, on the evidence the wider tries were tuned for
    (the ridges add to chance registrations too)."""
    return best is None or (best.score - (best.ridges.score if best.ridges else 0.0)
                            - math.log10(max(n_scored, 1))) < p.rescue_below


def _registrations(hyps, a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, rng):
    """Registrations (c, t, pairings) of the hypotheses that come near the strongest, with
    at least two pairings."""
    registered = []
    for h in hyps:
        if h.support < p.min_support_ratio * hyps[0].support:
            break   # a clear winner: weak cells cannot beat it
        registered.append(_register(h, a, b, p, rng))
    return [r for r in registered if len(r[2]) >= 2]


def _best_registration(a: MinutiaIndex, b: MinutiaIndex, registered, search_area: float,
                       p: MatchParams, use_creases: bool, searched=(),
                       search_trials: float = 0.0, scored=()) -> tuple[_Scored | None, list]:
    """The best registration, refined, and the scored ones it was chosen from (``scored``,
    already scored, among them): (None, []) without any."""
    if not use_creases:
        if not registered:
            return None, []
        # the first registration with the most pairings (hypotheses come strongest first)
        r = max(registered, key=lambda r: len(r[2]))
        best = _scored(a, b, *_refine(a, b, *r, p), search_area, a.radius, p, False)
        return best, [best]
    # every registration refined and scored with its crease agreement (the searched ones
    # are already on B's creases: a refit to their few minutiae pairings would undo that);
    # the search over them is paid for like any other (Bonferroni)
    scored = list(scored) + [_scored(a, b, *_refine(a, b, *r, p), search_area, a.radius, p,
                                     True) for r in registered]
    # a searched registration was picked among the search's transforms at the crease
    # resolution, not the minutiae's: it pays for those instead
    trials = search_trials - _log10_transforms(search_area, a.radius, p)
    scored += [replace(s, score=s.score - trials, search_penalty=trials) for s in (
        _scored(a, b, *r, search_area, a.radius, p, True) for r in searched)]
    if not scored:
        return None, []
    best = max(scored, key=lambda s: s.score)
    return _refined_on_creases(a, b, best, search_area, a.radius, p), scored


def _sweep_try(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, votes: _Votes, rng,
               best: _Scored | None, n_scored: int, search_area: float,
               use_creases: bool) -> tuple[_Scored | None, int]:
    """The wider try of the minutiae's votes: hypotheses from every rotation cell, and the
    coarse-to-fine crease ICP of the best so far. Returns the best registration and the
    count scored, both updated."""
    wider = _registrations(_hypotheses(votes, a, b, p, sweep=True), a, b, p, rng)
    other, other_scored = _best_registration(a, b, wider, search_area, p, use_creases)
    n_scored += len(other_scored)
    if other is not None and (best is None or other.score > best.score):
        best = other
    if best is not None and use_creases:
        best = _refined_on_creases(a, b, best, search_area, a.radius, p,
                                   radii=p.crease_rescue_radii)
    return best, n_scored


def _view_try(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, level: SearchLevel,
              best: _Scored | None, n_scored: int,
              search_area: float) -> tuple[_Scored | None, int]:
    """The view search's try at ``level`` (:func:`_view_search_level`): its proposals, moved
    onto B's creases and scored. Returns the best registration and the count scored, both
    updated."""
    searched, trials = _crease_search_registrations(
        a, b, p, level, p.search_scale, p.view_search_background)
    view, view_scored = _best_registration(a, b, [], search_area, p, True, searched, trials)
    n_scored += len(view_scored)
    if view is not None and (best is None or view.score > best.score):
        best = view
    return best, n_scored


class Matcher:
    """Minutiae matcher (settings in the constructor, scikit-image style).

    Parameters
    ----------
    params : MatchParams, optional
    **overrides
        Fields of :class:`MatchParams` to change, e.g. ``Matcher(threshold=4.0)``.
    """

    def __init__(self, params: MatchParams | None = None, **overrides):
        self.params = replace(params or MatchParams(), **overrides)
        # every comparison draws the same RANSAC samples: one generator, rewound to its
        # seeded state (a new default_rng per comparison costs ~15 us)
        self._rng = np.random.default_rng(self.params.seed)
        self._rng_start = self._rng.bit_generator.state

    def index(self, ms: MinutiaSet, crease: np.ndarray | None = None,
              ridges: np.ndarray | None = None) -> MinutiaIndex:
        """Prepare a set (with its crease and ridge skeletons) for repeated matching."""
        return MinutiaIndex(ms, self.params, crease, ridges)

    def compare(self, a, b, crease_a=None, crease_b=None) -> MatchResult:
        """Block-vs-block similarity.

        Parameters
        ----------
        a, b : MinutiaSet or MinutiaIndex
        crease_a, crease_b : ndarray, optional
            Crease images (used only when building indexes here; ridge skeletons come
            with indexes, :meth:`index`).

        Returns
        -------
        MatchResult
            Transform maps A pixels to B pixels.
        """
        a = _as_index(a, self.params, crease_a)
        b = _as_index(b, self.params, crease_b)
        ra = float(np.sqrt(a.area / math.pi))
        rb = float(np.sqrt(b.area / math.pi))
        search = math.pi * (ra + rb) ** 2   # centre offsets with any overlap
        return self._match(a, b, search, localising=False)

    def localise(self, camera, landmark, crease_camera=None,
                 crease_landmark=None) -> MatchResult:
        """Find a camera minutia set inside a (much larger) landmark region.

        Parameters
        ----------
        camera : MinutiaSet or MinutiaIndex
        landmark : MinutiaSet or MinutiaIndex
            Build a :class:`MinutiaIndex` once when the same region serves several frames.

        Returns
        -------
        MatchResult
            Transform maps camera pixels to landmark pixels, with covariance; use
            :meth:`MatchResult.point_covariance` for e.g. the image centre.
        """
        a = _as_index(camera, self.params, crease_camera)
        b = _as_index(landmark, self.params, crease_landmark)
        return self._match(a, b, max(b.area, 1.0), localising=True)

    def _match(self, a: MinutiaIndex, b: MinutiaIndex, search_area: float,
               localising: bool) -> MatchResult:
        p = self.params
        base = MatchResult(Decision.NO_DECISION, n_a=a.n, n_b=b.n)
        use_creases = (p.crease_check and a.crease_image is not None
                       and b.crease_image is not None)
        # a view in its region: its scale is the prior's height above ground's, +-10 %
        scale_change = p.search_scale if localising else 0.0
        search = use_creases and _searches_creases(a, b, p, scale_change)
        if search:
            # the creases propose and carry the match: the rule is on their extent
            n_crease = (len(a.crease_samples), b.crease_field.n)
            if min(n_crease) < p.min_crease_pixels:
                base.reason = (f"too little drainage ({n_crease[0]}, {n_crease[1]} crease "
                               f"px); at least {p.min_crease_pixels} needed in each set")
                return base
        else:
            needed = max(p.min_minutiae_creases if use_creases else p.min_minutiae, 2)
            if min(a.n, b.n) < needed:
                base.reason = (f"too few minutiae ({a.n}, {b.n}); at least {needed} needed "
                               "in each set")
                return base
        radius_a = a.radius
        if not use_creases:   # with creases, the crease evidence can add what minutiae lack
            # B's minutiae that can fall under A (all of them for blocks of equal size)
            n_b_under_a = b.n * min(1.0, a.area / max(b.area, 1.0))
            best_possible = _best_possible_score(int(min(a.n, n_b_under_a)), a.n,
                                                 n_b_under_a, a.area, search_area, radius_a,
                                                 p, p.threshold)
            if best_possible < p.threshold:
                base.reason = ("too few minutiae: even a perfect match would score "
                               f"{best_possible:.2f} < threshold {p.threshold:.2f}")
                return base
        votes = _root_votes(a, b, p) if _generator(b, p) == "roots" else _hash_votes(a, b, p)
        rng = self._rng
        rng.bit_generator.state = self._rng_start
        registered = _registrations(_hypotheses(votes, a, b, p), a, b, p, rng)
        best, scored = _best_registration(a, b, registered, search_area, p, use_creases)
        n_scored = len(scored)
        low = _low(best, n_scored, p)
        if low and search:
            # the wider try of a set small enough for the crease search: it covers every
            # rotation and translation at the crease resolution (a sweep or a wide ICP would
            # only add chances to unrelated pairs); chosen together with the first try's
            searched, trials = _crease_search_registrations(a, b, p, None, scale_change)
            best, scored = _best_registration(a, b, [], search_area, p, use_creases,
                                              searched, trials, scored=scored)
            n_scored = len(scored)
        elif low:
            level = _view_search_level(a, b, p) if (
                localising and use_creases and p.view_search) else None
            if level is not None:
                # a view the view search fits: the search is its wider try (as the crease
                # search is a small set's): it covers every rotation, scale and translation
                # at the creases' resolution, where the sweep of the minutiae's votes
                # only adds chances (on real images the minutiae of albedo edges rarely
                # repeat those of a render, the crease skeleton largely does)
                best, n_scored = _view_try(a, b, p, level, best, n_scored, search_area)
            else:
                best, n_scored = _sweep_try(a, b, p, votes, rng, best, n_scored, search_area,
                                            use_creases)
        base.decision = Decision.NO_MATCH
        if best is None:
            base.reason = "no consistent transform"
            return base
        if use_creases:
            best = replace(best, score=best.score - math.log10(n_scored))   # best of n
        c, t, pairs, score = best.c, best.t, best.pairs, best.score
        n_ao, n_bo = best.n_overlap
        cov, rms = _covariance(a.z[pairs[:, 0]], b.z[pairs[:, 1]], c, t, p.estimate_scale,
                               p.pos_tol)
        if use_creases and (len(pairs) < 3 or not np.isfinite(cov).all()):
            # too few pairings for a covariance (a registration found by the crease search)
            cov = crease_covariance(a.crease_samples, b.crease_field, c, t,
                                    **p.crease_tolerances)
        ok = score >= p.threshold
        return MatchResult(
            decision=Decision.MATCH if ok else Decision.NO_MATCH, score=score,
            n_pairings=len(pairs), pairings=pairs, transform=_pixel_transform(c, t),
            rotation=float(np.angle(c)), scale=float(abs(c)),
            scale_estimated=p.estimate_scale, covariance=cov, rms=rms,
            n_a=a.n, n_b=b.n, n_overlap=(n_ao, n_bo), expected_chance=best.lam,
            pairing_ratio=len(pairs) ** 2 / max(n_ao * n_bo, 1), creases=best.creases,
            ridges=best.ridges,
            reason="" if ok else f"score {score:.2f} below threshold {p.threshold:.2f}")


def compare(a, b, params: MatchParams | None = None, **overrides) -> MatchResult:
    """Block-vs-block comparison with default or given settings (see :class:`Matcher`)."""
    return Matcher(params, **overrides).compare(a, b)


def localise(camera, landmark, params: MatchParams | None = None,
             **overrides) -> MatchResult:
    """Camera-in-landmark-region localisation (see :meth:`Matcher.localise`)."""
    return Matcher(params, **overrides).localise(camera, landmark)


def warm_up(params: MatchParams | None = None) -> None:
    """Run every matching path once on small synthetic sets.

    With numba installed the kernels load from numba's cache (or compile) on first use,
    ~0.4 s in all; a node calls this at start-up so that its first frame is not late.
    """
    rng = np.random.default_rng(0)

    def random_set():
        crease = np.zeros((96, 96), np.uint8)
        for x0, y0, x1, y1 in rng.integers(0, 96, (14, 4)):
            cv2.line(crease, (int(x0), int(y0)), (int(x1), int(y1)), 1, 1)
        rows, cols = np.nonzero(crease)
        pick = rng.choice(len(rows), 40, replace=False)
        ms = MinutiaSet(cols[pick].astype(float), rows[pick].astype(float),
                        rng.uniform(-np.pi, np.pi, 40), rng.choice([1, 3], 40).astype(np.uint8),
                        np.ones(40, np.float32))
        return ms, crease

    matcher = Matcher(params)
    (ms, crease), other = random_set(), random_set()
    full = matcher.index(ms, crease)
    matcher.compare(full, full)                               # the first try
    matcher.compare(full, matcher.index(*other))              # the wider try
    few = matcher.index(ms.subset(np.arange(2)), crease)
    matcher.compare(few, full)          # the crease search and the crease covariance
    matcher.localise(few, full)         # ... over scales, and the ICP with the scale
