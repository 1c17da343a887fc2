"""Settings of the minutiae matcher: the dissertation's Table 4.1, extended (chapter 4).

:class:`MatchParams` holds every setting of :class:`~.matcher.Matcher`; ``_length_tol`` is the
edge-length tolerance they imply (wider when the scale is estimated).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np


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
    crease_search_candidates : int
        Peaks a search at the coarse level takes; each is searched again near its place at
        the fine level (:func:`~.crease_search.local_peaks`), and the proposals are those
        with the most hits there. The view search does so only when the coarse-to-fine ICP
        of its proposals leaves the best below ``rescue_below``.
    crease_search_fine_work : int
        A search whose work at the fine level (:data:`~.crease_search.FINE`: half the pixel
        resolution, rotations 3 px apart at the query's reach) exceeds this runs at the
        coarse level (:data:`~.crease_search.COARSE`: a quarter, 6 px; an eighth of the
        work) and its peaks are ranked again at the fine level (``crease_search_candidates``).
        The
        default keeps block-vs-block searches of blocks up to ~130 px fine; a block of more
        than ~80 px in its 3x localisation region is searched coarse, 4-6x faster.
    view_search : bool
        With crease images, a localised set too large for the crease search above (a camera
        footprint in its landmark region) is searched first, at the finest level
        (:data:`~.crease_search.LEVELS`) whose work fits ``crease_search_max_work``, over
        scales as well (``search_scale``); the minutiae's votes are tried only when that
        stays below ``rescue_below``, and their sweep never (it would only add chances; a
        set no level fits gets votes and sweep). On real images the minutiae of albedo
        edges (snow, forest, fields) rarely repeat those of a render, so the votes may
        propose nothing right; the crease skeleton largely repeats.
    search_scale : float
        Relative scale error the crease searches of a localisation cover (the prior's height
        above ground: 10 % moves the edge of a 256 px view by 13 px, more than a hit's
        tolerance), and their ICP then fits; block comparisons search no scale.
    view_search_background : float
        That search counts hits above the reference's local crease density within this
        sigma (search px, :class:`~.crease_search.CreaseSearchReference`).
    ridge_check : bool
        When both sets also come with ridge skeletons (the lines between the valleys, see
        :class:`~.features.minutiae.FeatureExtractor`), add their agreement at each registration to
        its score, like the valleys' (:func:`~.crease_check.crease_evidence`), and let the
        crease ICP pull on them too: a second, largely independent check of a small block's
        registration, at no extra search.
    ridge_check_below : int
        ... at every registration scored only when the smaller set has fewer minutiae than
        this (it costs ~0.2 ms per scored registration, and pulls on the ICP); a larger set's
        chosen registration still gets its ridge agreement added
        (:func:`~.scoring.with_ridge_evidence`): on real images minutiae counts overstate
        the evidence, albedo edges add minutiae that pair with nothing in a render.
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
        chances to unrelated pairs of such small sets; a localised set the view search
        fits (``view_search``) has had it first. The ridges' evidence does not count
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

    Raises
    ------
    ValueError
        On construction, naming the setting: a number outside its ``RANGES`` entry (NaN
        and infinities included), a string not among its ``CHOICES``, ``edge_min`` not below
        ``edge_max``, or a ``crease_rescue_radii`` that is not positive.
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
    crease_search_candidates: int = 48
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

    # (min, max) of every numeric setting, None = open: checked on construction, and the
    # matcher node's parameter ranges (issue 22). ``threshold`` is open here: a study sets
    # -1e9 to collect every score; FIX_RANGES is what a matcher publishing fixes accepts.
    POSITIVE = 1e-9  # the least "> 0" value: rclpy's ranges are closed
    RANGES = {
        **dict.fromkeys(("pos_tol", "angle_tol", "edge_length_tol", "edge_angle_tol",
                         "edge_max", "rot_bin", "trans_bin", "crease_radius",
                         "crease_angle_tol", "crease_spacing"), (POSITIVE, None)),
        **dict.fromkeys(("k_query", "k_ref", "n_hypotheses", "n_rotation_peaks",
                         "ransac_iterations", "k_roots", "crease_search_max_side",
                         "crease_search_max_work", "crease_search_proposals",
                         "crease_search_candidates"), (1, None)),
        **dict.fromkeys(("edge_min", "roots_above", "min_minutiae", "min_minutiae_creases",
                         "pos_floor", "angle_floor", "crease_exclude_radius",
                         "crease_search_below", "crease_search_fine_work",
                         "view_search_background", "ridge_check_below", "min_crease_pixels",
                         "seed"), (0, None)),
        "max_rotation": (0.0, math.pi), "min_support_ratio": (0.0, 1.0),
        "max_scale_change": (0.0, 0.9), "search_scale": (0.0, 0.5),
        "threshold": (None, None), "rescue_below": (None, None),
    }
    # a negative threshold would accept matches likelier to be chance than not
    FIX_RANGES = {**RANGES, "threshold": (0.0, None)}
    CHOICES = {"candidates": ("auto", "hash", "roots"),
               "descriptor": ("shape_context", "mcc", "both")}

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in self.CHOICES:
                self._require(value in self.CHOICES[f.name], f.name,
                              f"one of {self.CHOICES[f.name]}", value)
            elif f.name in self.RANGES:
                self._check_number(f.name, value, isinstance(f.default, int))
        self._require(self.edge_min < self.edge_max, "edge_min", "below edge_max",
                      self.edge_min)
        radii = self.crease_rescue_radii
        self._require(all(math.isfinite(r) and r > 0 for r in radii), "crease_rescue_radii",
                      "positive radii (px)", radii)

    def _check_number(self, name: str, value, integral: bool):
        """ValueError unless ``value`` is a number (an int for int settings) in its range,
        finite (``rescue_below`` may be -inf: no wider try, or inf: always one)."""
        lo, hi = self.RANGES[name]
        kinds = (int, np.integer) if integral else (int, float, np.integer, np.floating)
        self._require(isinstance(value, kinds) and not isinstance(value, bool), name,
                      "an int" if integral else "a number", value)
        finite = math.isfinite(value) or (name == "rescue_below" and not math.isnan(value))
        if finite and (lo is None or value >= lo) and (hi is None or value <= hi):
            return
        what = ("finite" if lo is None and hi is None else f"<= {hi:g}" if lo is None
                else f"in [{lo:g}, {hi:g}]" if hi is not None
                else "> 0" if lo == self.POSITIVE else f">= {lo:g}")
        self._require(False, name, what, value)

    @staticmethod
    def _require(ok: bool, name: str, what: str, value):
        if not ok:
            raise ValueError(f"MatchParams.{name} must be {what}, got {value!r}")

    @property
    def crease_tolerances(self) -> dict:
        """The crease evidence's and covariance's tolerances, as their keyword arguments
        (:func:`~.crease_check.crease_evidence`)."""
        return dict(radius=self.crease_radius, angle_tol=self.crease_angle_tol,
                    spacing=self.crease_spacing)


def _length_tol(p: MatchParams, length):
    if p.estimate_scale:
        return p.edge_length_tol + p.max_scale_change * length
    return np.full(np.shape(length), p.edge_length_tol)
