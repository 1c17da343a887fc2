"""What the ``matcher`` node decides between camera sets and fixes, without ROS.

The node (:mod:`terrain_nav_ros.nodes.matcher_node`) localises each camera minutia set in a
landmark set (:mod:`.matcher`, dissertation chapter 4) and turns the match into a fix
(:mod:`.pva_fix`); around that it decides:

* which landmark set a camera set is matched in: the newest whose region holds its centre
  (:class:`LandmarkSets`);
* what a ground-match fix adds for the prior's tilt (:func:`add_prior_tilt`) and, with the
  heading measured, its body attitude and attitude covariance (:func:`fix_attitude`);
* the velocity of two fixes close enough in time (:class:`FixVelocity`);
* the tallies and timings its diagnostics report (:class:`AnswerTally`);
* when a run of no-fixes is worth asking whether the camera image is flipped, and how
  such a frame's ground set is mirrored back (:class:`FlipCheck`).
"""

from __future__ import annotations

import math
from collections import Counter, deque

import numpy as np
from scipy.spatial.transform import Rotation

from .pva_fix import (
    STATUS_POSITION,
    STATUS_POSITION_ATTITUDE,
    PvaFixEstimate,
    reason_kind,
    velocity_from_fixes,
)

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR = 0, 1, 2
# Variance (rad^2) given to roll and pitch when only the heading is measured: 10 deg.
UNOBSERVED_TILT_VAR = math.radians(10.0) ** 2


class LandmarkSets:
    """The latest landmark sets, each ``(minutiae, index, origin)``, newest last.

    Parameters
    ----------
    max_sets : int
        Sets kept; the oldest is dropped for a new one.
    """

    def __init__(self, max_sets: int):
        self.sets: deque = deque(maxlen=max_sets)

    def add(self, minutiae, index, origin) -> None:
        """Keep a set: its :class:`~terrain_nav_ros.core.features.minutia_set.MinutiaSet`,
        its :class:`~.index.MinutiaIndex` (None without minutiae) and its ENU origin."""
        self.sets.append((minutiae, index, origin))

    def holding(self, east: float, north: float):
        """The newest set whose region holds the point, or None."""
        for minutiae, index, origin in reversed(self.sets):
            if minutiae.georef.contains(east, north):
                return minutiae, index, origin
        return None

    @property
    def any_with_minutiae(self) -> bool:
        """Whether some set has minutiae to match in."""
        return any(index is not None for _, index, _ in self.sets)

    def __len__(self) -> int:
        return len(self.sets)


def add_prior_tilt(fix: PvaFixEstimate, height_above_ground: float,
                   tilt_sigma: float) -> None:
    """Add, in place, the horizontal error a prior tilt error of ``tilt_sigma`` (rad) makes
    in a ground-projected frame ``height_above_ground`` (m) up: a valid fix's horizontal
    variances grow by ``(height * tilt_sigma)**2``, and its ``projection_height`` becomes 0
    (the error is in the covariance now, for a fix whose projection attitude is not the
    filter's, or that the filter compares by its covariance alone)."""
    if fix.valid:
        fix.covariance[:2, :2] += np.eye(2) * (height_above_ground * tilt_sigma) ** 2
        fix.projection_height = 0.0


def fix_attitude(fix: PvaFixEstimate, r_body_optical: np.ndarray, use_heading: bool,
                 heading_floor: float, tilt_variance: float = UNOBSERVED_TILT_VAR) -> np.ndarray:
    """The body attitude ``R_enu_body`` a fix reports, with its status and attitude
    covariance set in place.

    The fix's rotation is the camera optical frame's; the mount turns it into the body's. A
    ground match (status position) with a heading measurement and ``use_heading`` becomes
    position-attitude: the ground image was rotated by the prior's heading error, so the
    prior attitude is turned about Up by the registration's rotation; roll and pitch are not
    seen by a nadir ground match and get a variance that leaves the filter's alone
    (:data:`UNOBSERVED_TILT_VAR`), the yaw variance at least ``heading_floor`` (rad) squared.
    A projection whose roll and pitch were measured apart from the filter (a pose-free
    frame's, levelled from the accelerometers) gives their variance as ``tilt_variance``.

    A track mosaic's fix (``mosaic_lag`` > 0) keeps the prior attitude: its frames were
    projected with the estimate's headings over its span and laid out by the estimate's
    velocity, so its rotation measures the estimate's own past, not the heading now. Taken
    for the heading (sigma 0.6 deg), it closed a loop: in a replay of a low flight jammed
    from take-off the mosaics' headings led the estimate's 30 deg off, and the estimate
    410 m off the truth with a 40 m sigma.
    """
    r_enu_body = fix.rotation @ r_body_optical.T
    if fix.status == STATUS_POSITION and use_heading and fix.yaw_variance >= 0 \
            and not fix.mosaic_lag > 0.0:
        r_enu_body = Rotation.from_rotvec([0.0, 0.0, fix.yaw_correction]).as_matrix() \
            @ r_enu_body
        fix.covariance[3:, 3:] = np.diag([tilt_variance, tilt_variance,
                                          fix.yaw_variance + heading_floor ** 2])
        fix.covariance[:3, 3:] = fix.covariance[3:, :3] = 0.0
        fix.status = STATUS_POSITION_ATTITUDE
    return r_enu_body


class FixVelocity:
    """Velocity from consecutive fixes at most ``max_gap`` s apart.

    Parameters
    ----------
    max_gap : float
        Largest time between two fixes that give a velocity (s).
    """

    def __init__(self, max_gap: float):
        self.max_gap = max_gap
        self.last: tuple[float, np.ndarray, np.ndarray] | None = None

    def update(self, stamp: float, position, covariance, mosaic: bool = False,
               relocalisation: bool = False):
        """Take the fix at ``stamp``; return ``(velocity, covariance)`` from the previous
        one (:func:`~.pva_fix.velocity_from_fixes`), or None when there is none close
        enough before it.

        A track mosaic's fix (``mosaic``) gives none and is not kept as the previous: its
        position measures the estimate's velocity error times its frames' age (the ekf
        models that lag), and consecutive mosaics share most of their frames, so their
        difference is neither independent fixes' nor the aircraft's velocity. A
        relocalisation gives none but is kept: the fix before it was searched around the
        estimate it contradicts."""
        if mosaic:
            self.last = None
            return None
        out = None
        if (self.last is not None and not relocalisation
                and 0 < stamp - self.last[0] <= self.max_gap):
            out = velocity_from_fixes(self.last[1], self.last[2], self.last[0], position,
                                      covariance, stamp)
        self.last = (stamp, np.array(position, copy=True), np.array(covariance, copy=True))
        return out


class FlipCheck:
    """Whether the camera image may be flipped (a driver's flip option, a mirror in the
    optics): a flipped frame projects to its ground mirrored, which no turn lies on the
    terrain, so every frame scores below the threshold and nothing else says why.

    Every ``every`` frames of a run scoring below the threshold in the tile, the node tries
    the frame's ground set mirrored back (:meth:`mirrors`); a match names the flip
    (:attr:`found`) until a frame is fixed as it is.

    Parameters
    ----------
    every : int
        Frames below the threshold in a row between two tries; 0 never tries.
    """

    def __init__(self, every: int):
        self.every = int(every)
        self.run = 0
        self.found = ""

    def note(self, fixed: bool, below_threshold: bool, mosaic: bool = False) -> bool:
        """Count a frame answered in the tile; whether to try its mirrors now.

        A track mosaic (``mosaic``) below the threshold is not counted and never tried: its
        frames, each flipped, lie side by side along the track, so no line mirrors it back
        onto the terrain. Its fix still ends a run (the camera is not flipped)."""
        if fixed:
            self.run, self.found = 0, ""
            return False
        if mosaic:
            return False
        self.run = self.run + 1 if below_threshold else 0
        return self.every > 0 and self.run > 0 and self.run % self.every == 0

    @staticmethod
    def mirrors(position, r_enu_optical, plane: float,
                centre_ray=(0.0, 0.0, 1.0)) -> dict[str, tuple[np.ndarray, float]]:
        """The ground line across which each flip mirrors a frame's ground image, as (its
        point under the image's centre, ENU east and north; its angle, rad from East,
        counter-clockwise): a flip left to right across the image's middle column, top to
        bottom across its middle row. ``centre_ray`` is the image centre's ray in the
        optical frame (the principal point's by default); the frame's ground lies on the
        projection ``plane`` (m)."""
        r = np.asarray(r_enu_optical, float)
        p = np.asarray(position, float)
        ray = r @ np.asarray(centre_ray, float)
        # a frame that can be projected looks down: its centre's ray meets the plane
        t = (plane - p[2]) / ray[2] if ray[2] < 0 else 0.0
        centre = p[:2] + t * ray[:2]
        cols, rows = r @ (0.0, 1.0, 0.0), r @ (1.0, 0.0, 0.0)
        return {"left to right": (centre, math.atan2(cols[1], cols[0])),
                "top to bottom": (centre, math.atan2(rows[1], rows[0]))}


class AnswerTally:
    """Fixes, no-fixes by kind and answer times, for the node's diagnostics."""

    def __init__(self):
        self.fixes = 0
        self.no_fixes = 0
        self.no_fix_kinds: Counter = Counter()
        self.answer_ms: list[float] = []    # time per camera set since the last report
        self.last_fix_at: float | None = None
        self.last_match = (math.nan, 0)     # score and pairings of the last fix

    def no_fix(self, reason: str) -> None:
        """Count a no-fix under its reason's kind (:func:`~.pva_fix.reason_kind`)."""
        self.no_fixes += 1
        self.no_fix_kinds[reason_kind(reason)] += 1

    def fix(self, similarity: float, pairings: int, now: float) -> None:
        """Count a fix (``now``: wall clock, s)."""
        self.fixes += 1
        self.last_fix_at = now
        self.last_match = (float(similarity), pairings)

    def answered(self, milliseconds: float) -> None:
        """Note the time one camera set took."""
        self.answer_ms.append(milliseconds)

    def report(self, now: float, since_camera: float, camera_timeout: float,
               have_landmark: bool, failures: int, new_failures: int,
               landmark_sets: int) -> tuple[int, str, dict]:
        """The level, message and key-value pairs of one diagnostics report; the answer
        times restart.

        Parameters
        ----------
        now : float
            Wall clock (s).
        since_camera : float
            Wall time since the last camera set, or since start-up (s).
        camera_timeout : float
            Longer than this without camera minutiae is a warning (s).
        have_landmark : bool
            Whether a landmark set with minutiae is held (else a warning).
        failures, new_failures : int
            Callback failures in all and since the previous report (any new one is an
            error).
        landmark_sets : int
            Landmark sets held.
        """
        level, problems = OK, []
        if new_failures:
            level = ERROR
            problems.append(f"{new_failures} message(s) failed in a callback: see the log")
        if since_camera > camera_timeout:
            level = max(level, WARN)
            problems.append(f"no camera minutiae for {since_camera:.0f} s")
        if not have_landmark:
            level = max(level, WARN)
            problems.append("no landmark set with minutiae")
        times, self.answer_ms = self.answer_ms, []
        values = {
            "fixes": self.fixes, "no_fixes": self.no_fixes,
            "camera_sets_since_last_report": len(times),
            "answer_ms_median": float(np.median(times)) if times else math.nan,
            "answer_ms_max": max(times, default=math.nan),
            "time_since_last_fix": (math.nan if self.last_fix_at is None
                                    else now - self.last_fix_at),
            "last_fix_similarity": self.last_match[0],
            "last_fix_pairings": self.last_match[1],
            "landmark_sets": landmark_sets,
            "failures": failures,
        }
        values.update({f"no_fix: {kind}": n for kind, n in self.no_fix_kinds.most_common()})
        message = "; ".join(problems) or (f"{len(times)} camera set(s) answered since the "
                                          "last report")
        return level, message, values
