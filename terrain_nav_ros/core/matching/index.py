"""A minutia set prepared for matching (dissertation chapter 4).

:class:`MinutiaIndex` holds what matching a set needs, built once per set and reused (the
landmark region across camera frames, each block across a study's N x N comparisons): the
k-d tree, the neighbour edges and their hash, the point descriptors, and for the crease check
and the crease search the crease and ridge fields and rasters (built on first use).
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..features.minutia_set import MinutiaSet
from . import _matching_kernels as _kernels
from .crease_check import CreaseField, CreaseSamples
from .crease_search import (
    COARSE,
    FINE,
    LEVELS,
    CreaseSearchQuery,
    CreaseSearchReference,
    SearchLevel,
    search_rotations,
    search_scales,
)
from .descriptors import (
    EdgeHash,
    EdgeQuery,
    crease_descriptor,
    cylinder_code,
    neighbour_edges,
    shape_context,
    to_complex,
)
from .params import MatchParams, _length_tol

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
        crease descriptor and the crease check (see :class:`~.params.MatchParams`).
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
            self._crease_around = self.crease_samples.around_lists(
                self.z, self.params.crease_exclude_radius)
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
    def crease_centre(self) -> complex:
        """Mean of the crease pixels (math frame): the pivot of a rotation or scale step
        in the crease search."""
        z = self.crease_samples.z if self.crease_samples is not None else np.zeros(0)
        return complex(z.mean()) if len(z) else 0j

    @functools.cached_property
    def crease_reach(self) -> float:
        """90th percentile of the crease pixels' distance from their mean (px): the lever
        arm of a rotation or scale step in the crease search."""
        z = self.crease_samples.z if self.crease_samples is not None else np.zeros(0)
        return float(np.percentile(np.abs(z - self.crease_centre), 90)) if len(z) else 0.0

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
