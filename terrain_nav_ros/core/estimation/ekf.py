"""Error-state EKF fusing IMU dead reckoning with intermittent terrain fixes (ROS-free).

Built on :class:`filterpy.kalman.ExtendedKalmanFilter`: its ``x``, ``P`` and ``update`` are
used as they are; prediction is this module's strapdown (filterpy's linear predict does not
apply to an INS).

State
-----
``kf.x`` (23 x 1) and ``kf.P`` (23 x 23) follow this order:

======  ==============  ===================================================================
index   symbol          meaning
======  ==============  ===================================================================
0:3     p               position, ENU map frame (m)
3:6     v               velocity, ENU (m/s)
6:9     dtheta          attitude error, small rotation about the ENU axes (rad); always 0
                        between updates: it is folded into the nominal quaternion
9:12    b_g             gyro bias, body FLU (rad/s)
12:15   b_a             accelerometer bias, body FLU (m/s^2)
15:17   w               wind, east and north (m/s): the ground velocity less the air's
17      b_baro          baro bias (m): the barometer's height less the true height
18:20   mu              camera mount error, a small rotation about body x and y (rad): the
                        camera's true mount is ``Exp(mu)`` times the declared one
20      k               camera scale error: a ground match's height above the projection
                        plane, measured by its scale, is ``(1 + k)`` times the true one
21:23   b_map           map bias, east and north (m): where a terrain fix puts the aircraft
                        less where it is; the DEM's (and its renders') georeferencing error
======  ==============  ===================================================================

The wind is no IMU state: the accelerometer levelling needs it (a turn's centripetal
acceleration is the air velocity's) and the sideslip of a fixed wing in coordinated flight,
which is about zero, measures it (the crab between the heading and the track), as autopilot
EKFs without an airspeed sensor do.

The baro bias is what the weather and the offset that put the pressure altitude into ENU up
add to the barometer: it starts at ``init_baro_bias_sigma`` (the offset is learnt from the
filter's own height), wanders at ``baro_bias_random_walk`` (a pressure change of 1 hPa is
~8 m) and is observed wherever another reference measures the height (GNSS, and the
fixes whose scale measured their height: below). Without it a baro of 10 Hz, taken as white noise,
made the height sigma a few decimetres around a bias of metres.

The camera mount error is how far the camera's boresight is off the mount the graph declares
(``camera_mount_rpy``): a frame projected onto the ground with the filter's attitude and the
declared mount lands ``height x mu`` from where it should, so a mount off by 2 degrees put every
ground fix 60 m off at 1700 m above ground, and the filter, taking the fixes for truth, followed
them. It turns the ray as the attitude error does (:func:`tilt_lever`), but about body axes: it
rotates with the heading, while the attitude's tilt is levelled by the accelerometers. GNSS
beside the fixes observes it at once; without GNSS, turns do (the fixes' offset swings with the
heading, the IMU's dead reckoning does not). It starts at ``init_camera_mount_sigma`` and
wanders at ``camera_mount_random_walk``. A turn of the mount about the boresight does not move
a nadir fix and is not estimated.

The camera scale error is what a focal length off the CameraInfo's (or a lens focused
elsewhere) does to a ground match's height: the registration's scale measures the height
above the projection plane, ``projection_height``, to about 0.1 %, but times ``(1 + k)``. So
the fix's height measures ``p_z + k x projection_height``: GNSS or the baro's calibrated bias
beside the fixes observe ``k``; without them the height above ground's changes over the
terrain part ``k`` from the baro bias. It starts at ``init_camera_scale_sigma`` and wanders at
``camera_scale_random_walk``. A fix's height that its gate alone would reject (a focal length
off by more than the prior allows) is left out and the rest of the fix fused
(``FUSED_WITHOUT_HEIGHT``): the horizontal position does not depend on the scale.

The map bias is the DEM's horizontal georeferencing error: every terrain fix is a
registration onto the DEM's renders, so it measures ``p + b_map``, and a DEM (or, in a
simulation, an image draped on it) 30 m off its true place puts every fix 30 m off. Taken
as independent noise, as it was, fix after fix averaged it into the estimate. It starts at
``init_map_bias_sigma`` (a DEM's stated horizontal accuracy), is learnt wherever GNSS and
terrain fixes meet (the start of a flight before the jamming) and then taken out of every
later fix; without GNSS it is not observed and its sigma stays in the position's, as a doubt
no number of fixes averages away. It wanders at ``map_bias_random_walk`` (a DEM's error
changes slowly over the area flown). GNSS and the operator's ``set_position`` are in the
true frame and do not measure it.

A fix from a track mosaic (a low camera's frames composed along its track, each moved into the
newest frame's estimate by the filter's own dead reckoning) carries the velocity's error over
the frames' ages: its horizontal position measures ``p - lag x (v - v_hat)``, ``lag`` the
mosaic's mean age (``mosaic_lag``). The update models it, so such a fix also corrects the
velocity, and weighs less while the velocity is in doubt.

The nominal attitude is the unit quaternion ``q`` (``[x, y, z, w]``, body -> ENU) kept beside
``kf.x``; the true attitude is ``Exp(dtheta) * q``. Position, velocity and biases are additive,
so for them ``kf.x`` is the estimate itself; only the attitude needs the error-state
treatment (inject after each update, then reset ``dtheta`` and rotate ``P`` accordingly).

Timing
------
Every IMU sample is integrated over ``(t_prev, t]`` (zero-order hold of the sample stamped
``t``). Each measurement is applied at its own stamp by splitting the IMU interval that
contains it, whether it arrives before the IMU reaches that stamp (it is queued), on time, or
late (the filter rewinds to the history entry before the stamp and re-propagates the stored
IMU samples, re-applying the later measurements). All three orders therefore give the same
estimate. Measurements older than the history are stale.

IMU stamps are screened first (:class:`~terrain_nav_ros.core.estimation.imu_timing.ImuTimingGuard`):
a sample stamped more than ``time_jump_reset`` from the previous one, in either direction, is
refused (``STAMP_OFF_PERIOD``) unless ``time_jump_confirm`` consecutive samples continue from it,
which is a real time jump. A jump ahead of at most ``max_imu_outage`` is an IMU outage: integrated
across as a gap (``IMU_GAP``). Any other (bag loop, simulator restart) resets the filter
(``TIME_JUMP_RESET``), which starts the new timeline with those samples and re-initialises per
``init_mode``; with ``gnss``/``fix``, when no measurement of that source
has come ``reinit_timeout`` s into the new timeline, it starts again from the last good state
with the initial covariance added (``REINITIALIZED``) rather than wait for a source that may
be gone.

Relocalisations
---------------
A fix marked ``relocalisation`` (found by a search of the whole mission area, independent of
the estimate) is fused when the gate accepts it. One it rejects is held
(``RELOCALISATION_HELD``) with the estimate at its stamp; when another relocalisation, at least
``relocalisation_min_interval`` s apart, agrees with a held one (their displacement matches the
dead-reckoned one within a chi-square test: :mod:`.relocalisation`), the position is reset onto
the newer evaluation (``RELOCALISATION_RESET``; velocity, attitude and biases kept), or before
initialisation with ``init_mode="fix"`` the filter starts from the pair. Held ones expire
after ``relocalisation_timeout``. One unverified relocalisation never moves the filter, and
relocalisations never count towards ``reset_after_rejections``.

Every public ``process_*`` method returns an :class:`Outcome` with a :class:`Reason`; bad input
never raises and never stops the filter.

Mapping for the ROS node (kept out of this module)
--------------------------------------------------
* ``sensor_msgs/Imu`` in ``base_link`` (FLU) -> ``process_imu(stamp, angular_velocity,
  linear_acceleration)``; rotate first if the IMU frame differs.
* ``PvaFix`` -> ``process_fix(stamp, position, covariance, velocity=..., quaternion=...,
  relocalisation=...)`` with the covariance ordered ``[position, velocity?, attitude?]``.
* ``NavSatFix`` -> ENU through the mission's pyproj transformer -> ``process_gnss``.
* Barometric altitude minus the map origin height -> ``process_baro``.
* Output: :attr:`TerrainEkf.state` (``NavState``; ``pose_covariance()`` gives the 6x6 ROS
  Pose layout) and :attr:`TerrainEkf.diagnostics` (``EkfDiagnostics``).
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections import Counter, deque
from dataclasses import dataclass, field
from enum import StrEnum
from functools import lru_cache

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from scipy.stats import chi2

from .ekf_params import EkfParams
from .imu_timing import ImuTiming, ImuTimingGuard
from .relocalisation import Candidate, Found, RelocalisationCandidates
from .strapdown import (
    DIM_ERR,
    GRAVITY,
    IDX_BA,
    IDX_BG,
    IDX_P,
    IDX_TH,
    IDX_V,
    StrapdownStep,
    attitude_error,
    quat_exp,
    quat_from_euler,
    quat_multiply,
    quat_normalize,
    quat_to_matrix,
    skew,
)

# The filter's states: the mechanisation's error states, the wind (east, north), the baro
# bias, the camera mount's error (about body x and y), the camera's scale error, the map
# bias (east, north).
IDX_W = slice(DIM_ERR, DIM_ERR + 2)
IDX_BARO = DIM_ERR + 2
IDX_MOUNT = slice(DIM_ERR + 3, DIM_ERR + 5)
IDX_SCALE = DIM_ERR + 5
IDX_MAP = slice(DIM_ERR + 6, DIM_ERR + 8)
DIM_STATE = DIM_ERR + 8
# The baro measures the height and its own bias.
_BARO_LEVER = np.zeros((1, DIM_STATE))
_BARO_LEVER[0, IDX_BARO] = 1.0

__all__ = ["DIM_STATE", "IDX_BARO", "IDX_MAP", "IDX_MOUNT", "IDX_SCALE", "IDX_W",
           "EkfDiagnostics", "EkfParams", "NavState", "Outcome", "Reason", "TerrainEkf",
           "UpdateRecord", "tilt_lever"]


class Reason(StrEnum):
    """Why an input was accepted, deferred or rejected."""

    OK = "ok"
    INITIALIZED = "initialized"
    QUEUED = "queued_until_imu_reaches_stamp"
    WAITING_FOR_INIT = "stored_for_initialisation"
    INIT_TOO_FAST = "initialisation_pair_implies_an_impossible_speed"
    IMU_GAP = "imu_gap_integrated"
    POSITION_RESET = "position_reset_after_consecutive_rejections"
    NOT_INITIALIZED = "not_initialized"
    NON_FINITE = "non_finite_value"
    BAD_SHAPE = "bad_shape"
    BAD_COVARIANCE = "covariance_not_positive_definite"
    BAD_QUATERNION = "quaternion_not_unit"
    BAD_PROJECTION_HEIGHT = "projection_height_negative_or_not_finite"
    BAD_MOSAIC_LAG = "mosaic_lag_negative_or_not_finite"
    DUPLICATE = "duplicate_stamp"
    OUT_OF_ORDER = "out_of_order"
    STALE = "older_than_history"
    TOO_FAR_AHEAD = "too_far_in_future"
    GATED = "chi_square_gate"
    COMPARED_ONLY = "compared_not_fused"
    STUCK = "repeated_bit_for_bit"
    PROBATION = "compared_after_a_jump"
    TIME_JUMP_RESET = "time_jump_reset"
    STAMP_OFF_PERIOD = "stamp_far_from_expected_period"
    REINITIALIZED = "reinitialised_from_last_good_state"
    RELOCALISATION_HELD = "relocalisation_held_until_another_agrees"
    RELOCALISATION_RESET = "position_reset_on_agreeing_relocalisations"
    FUSED_WITHOUT_HEIGHT = "fused_without_its_height"


@dataclass(frozen=True)
class Outcome:
    """Result of feeding one input to the filter.

    Attributes
    ----------
    accepted : bool
        True if the input changed the estimate. For ``QUEUED`` it means "taken": the gate
        decision is made when the IMU reaches the stamp and shows up in the diagnostics.
    reason : Reason
    nis : float or None
        Normalised innovation squared of a measurement update.
    gate : float or None
        Chi-square threshold the NIS was compared with.
    """

    accepted: bool
    reason: Reason
    nis: float | None = None
    gate: float | None = None


@dataclass(frozen=True)
class UpdateRecord:
    """One measurement evaluation, for the NIS diagnostic."""

    stamp: float
    source: str
    dim: int
    nis: float
    gate: float
    accepted: bool


@dataclass(frozen=True)
class NavState:
    """Snapshot of the estimate at ``stamp``.

    Attributes
    ----------
    stamp : float
        Time (s) of the newest IMU sample integrated.
    position, velocity : ndarray, (3,)
        ENU (m, m/s).
    quaternion : ndarray, (4,)
        Body -> ENU ``[x, y, z, w]``.
    gyro_bias, accel_bias : ndarray, (3,)
        Body frame (rad/s, m/s^2).
    covariance : ndarray, (23, 23)
        Error-state covariance in the documented state order.
    wind : ndarray, (2,)
        East and north (m/s): where the air moves to.
    baro_bias : float
        The barometer's height less the true height (m).
    camera_mount : ndarray, (2,)
        The camera mount's error about body x and y (rad).
    camera_scale : float
        The camera's scale error ``k`` (a ground match's height above its plane is
        ``1 + k`` times the true one).
    map_bias : ndarray, (2,)
        The map's bias, east and north (m): where a terrain fix puts the aircraft less
        where it is.
    """

    stamp: float
    position: np.ndarray
    velocity: np.ndarray
    quaternion: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    covariance: np.ndarray
    wind: np.ndarray
    baro_bias: float = 0.0
    camera_mount: np.ndarray = field(default_factory=lambda: np.zeros(2))
    camera_scale: float = 0.0
    map_bias: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def pose_covariance(self) -> np.ndarray:
        """6x6 covariance of (position, attitude about ENU axes), the ROS Pose layout."""
        idx = np.r_[0:3, 6:9]
        return self.covariance[np.ix_(idx, idx)]


@dataclass
class EkfDiagnostics:
    """Filter health, for the node's diagnostic topic.

    Attributes
    ----------
    initialized : bool
    stamp : float or None
        Filter time (s).
    records : deque of UpdateRecord
        Most recent measurement evaluations (NIS, gate, decision).
    accepted, rejected : Counter
        Measurements accepted / rejected by the chi-square gate, per source.
    input_rejections : Counter
        Inputs refused before any update, per ``"<source>:<reason>"``.
    resets : int
        Time-jump resets (confirmed jumps, either direction).
    reinitialisations : int
        Restarts from the last good state after a reset (no init source came).
    imu_stamps_refused : int
        IMU samples refused when they came because their stamp was far from the expected
        period (those that a confirmed jump then proves right are integrated after all).
    position_resets : int
        Position resets after consecutive rejections.
    relocalisation_resets : int
        Position resets onto agreeing relocalisations.
    baro_steps : int
        Jumps of the barometer detected (:meth:`TerrainEkf.process_baro`).
    baro_step : float
        What is taken off every baro height now (m): the sum of the jumps since the filter
        last (re)started (a reset forgets it, as the node then learns its offset again).
    tilt_drifts : int
        Drifts of the tilt the accelerometer levelling found (a gyro bias that stepped).
    heading_drifts : int
        Drifts of the heading the fixes that measure one found (a yaw gyro bias that
        stepped).
    heading_disputes : int
        Such drifts not followed because no fix's heading had agreed with the filter's yet
        since it started: a heading off from the first fix on is the camera's (its mount's
        yaw, an image turned), not a gyro's drift.
    relocalisation_candidates : int
        Relocalisations held, waiting for another to agree (expired ones dropped).
    found : Found or None
        The last reset onto (or start from) agreeing relocalisations since the filter last
        (re)started.
    imu_gaps : int
        IMU intervals longer than ``max_imu_dt``.
    last_accepted : dict
        Stamp of the last accepted measurement per source.
    covariance_trace : float
        Trace of the full error covariance (mixed units, for trend only).
    position_sigma : float
        sqrt of the trace of the position covariance (m).
    horizontal_sigma : float
        sqrt of the east + north position variances (m).
    wind : tuple of float
        Wind estimate, east and north (m/s).
    wind_sigma : float
        sqrt of the sum of its two variances (m/s).
    baro_bias, baro_bias_sigma : float
        The barometer's bias estimate and its sigma (m).
    height_sigma : float
        1-sigma of the height (m).
    camera_mount : tuple
        The camera mount's error about body x and y (rad).
    camera_mount_sigma : float
        sqrt of the sum of its two variances (rad).
    camera_scale, camera_scale_sigma : float
        The camera's scale error and its sigma.
    map_bias : tuple
        The map's bias, east and north (m).
    map_bias_sigma : float
        sqrt of the sum of its two variances (m).
    heights_left_out, heights_left_out_in_a_row : int
        Fixes fused without their height (``FUSED_WITHOUT_HEIGHT``): in all, and since the
        last fix fused with it.
    """

    initialized: bool = False
    stamp: float | None = None
    records: deque = field(default_factory=deque)
    accepted: Counter = field(default_factory=Counter)
    rejected: Counter = field(default_factory=Counter)
    input_rejections: Counter = field(default_factory=Counter)
    resets: int = 0
    reinitialisations: int = 0
    imu_stamps_refused: int = 0
    position_resets: int = 0
    relocalisation_resets: int = 0
    baro_steps: int = 0
    baro_step: float = 0.0
    tilt_drifts: int = 0
    heading_drifts: int = 0
    heading_disputes: int = 0
    relocalisation_candidates: int = 0
    found: Found | None = None
    imu_gaps: int = 0
    last_accepted: dict = field(default_factory=dict)
    covariance_trace: float = float("nan")
    position_sigma: float = float("nan")
    horizontal_sigma: float = float("nan")
    wind: tuple = (float("nan"), float("nan"))
    wind_sigma: float = float("nan")
    baro_bias: float = float("nan")
    baro_bias_sigma: float = float("nan")
    height_sigma: float = float("nan")
    camera_mount: tuple = (float("nan"), float("nan"))
    camera_mount_sigma: float = float("nan")
    camera_scale: float = float("nan")
    camera_scale_sigma: float = float("nan")
    map_bias: tuple = (float("nan"), float("nan"))
    map_bias_sigma: float = float("nan")
    heights_left_out: int = 0
    heights_left_out_in_a_row: int = 0

    def time_since(self, source: str = "fix") -> float | None:
        """Seconds since the last accepted measurement of ``source`` (None if never)."""
        if self.stamp is None or source not in self.last_accepted:
            return None
        return self.stamp - self.last_accepted[source]

    @property
    def time_since_last_fix(self) -> float | None:
        """Seconds since the last accepted terrain fix (None if never)."""
        return self.time_since("fix")

    def last_nis(self, source: str) -> float | None:
        """NIS of the most recent evaluation of ``source``."""
        for rec in reversed(self.records):
            if rec.source == source:
                return rec.nis
        return None


def _lagged_rows(meas: _Measurement) -> tuple[np.ndarray, np.ndarray]:
    """The horizontal position rows of a mosaic's fix and the velocity state each moves
    with (the mosaic's frames were moved horizontally)."""
    k = np.flatnonzero(meas.rows < 2)
    return k, meas.rows[k] + 3


@lru_cache(maxsize=64)
def _gate(probability: float, dof: int) -> float:
    """Chi-square threshold (inf when gating is disabled)."""
    return float("inf") if probability >= 1.0 else float(chi2.ppf(probability, dof))


@dataclass(eq=False)
class _Measurement:
    """A validated measurement in the log (kept for re-application while in the history)."""

    stamp: float
    seq: int
    source: str
    z: np.ndarray            # (m,) measured values; attitude rows hold the quaternion's log later
    R: np.ndarray            # (m, m)
    rows: np.ndarray         # state index measured by each row
    attitude: np.ndarray | None = None   # measured quaternion, attitude rows are rows[-3:]
    outcome: Outcome | None = None
    reset: bool = False      # apply as a position reset instead of a gated update
    relocalisation: bool = False   # found by a mission-wide search, independent of the prior
    probation: bool = False  # compared, never fused (a baro height just after a jump)
    attitude_lever: np.ndarray | None = None   # (m, 3): how dtheta moves the measured rows
    body_up: np.ndarray | None = None   # a levelling's measured up direction, body frame
    state_lever: np.ndarray | None = None   # (m, DIM_STATE): how the state moves them too
    velocity_lag: float = 0.0   # s: horizontal rows measure p - lag (v - v_hat) (a mosaic's)
    reopen: list | None = None   # found a drift (_test_drift): (states, variance floor)

    @property
    def key(self):
        return (self.stamp, self.seq)


@dataclass(frozen=True)
class _Entry:
    """History entry: state at ``t`` after the IMU sample stamped ``t`` and all measurements
    stamped <= t that were known."""

    t: float
    gyro: np.ndarray
    accel: np.ndarray
    x: np.ndarray
    q: np.ndarray
    P: np.ndarray


class TerrainEkf:
    """Error-state strapdown EKF with gated, delay-tolerant measurement updates.

    Parameters
    ----------
    params : EkfParams, optional
        Settings; defaults to ``EkfParams()``.

    Examples
    --------
    >>> ekf = TerrainEkf(EkfParams(init_mode="pose"))
    >>> ekf.set_initial_pose([0, 0, 500], [30, 0, 0], [0, 0, 0, 1])
    >>> ekf.process_imu(0.0, [0, 0, 0], [0, 0, 9.80665]).reason
    <Reason.INITIALIZED: 'initialized'>
    """

    def __init__(self, params: EkfParams | None = None):
        self.params = params or EkfParams()
        p = self.params
        self.kf = ExtendedKalmanFilter(dim_x=DIM_STATE, dim_z=3)
        self._step = StrapdownStep(p.gravity, DIM_STATE)
        self._tmp = np.empty((DIM_STATE, DIM_STATE))
        self._Q = np.zeros((DIM_STATE, DIM_STATE))
        self._q_dt = None
        # Q = dt * Q1 + dt^2 * Q2 + dt^3 * Q3, so a jittering IMU period costs three axpys.
        i3 = np.arange(3)
        self._Q1, self._Q2, self._Q3 = (np.zeros((DIM_STATE, DIM_STATE)) for _ in range(3))
        qa = p.accel_noise_density**2
        self._Q1[i3 + 3, i3 + 3] = qa
        self._Q1[i3 + 6, i3 + 6] = p.gyro_noise_density**2
        self._Q1[i3 + 9, i3 + 9] = p.gyro_bias_random_walk**2
        self._Q1[i3 + 12, i3 + 12] = p.accel_bias_random_walk**2
        wind = np.arange(IDX_W.start, IDX_W.stop)
        self._Q1[wind, wind] = p.wind_random_walk**2
        self._Q1[IDX_BARO, IDX_BARO] = p.baro_bias_random_walk**2
        mount = np.arange(IDX_MOUNT.start, IDX_MOUNT.stop)
        self._Q1[mount, mount] = p.camera_mount_random_walk**2
        self._Q1[IDX_SCALE, IDX_SCALE] = p.camera_scale_random_walk**2
        map_bias = np.arange(IDX_MAP.start, IDX_MAP.stop)
        self._Q1[map_bias, map_bias] = p.map_bias_random_walk**2
        self._Q2[i3, i3 + 3] = self._Q2[i3 + 3, i3] = qa / 2.0
        self._Q3[i3, i3] = qa / 3.0
        self._seq = itertools.count()
        self._initial_pose = None
        self._baro_repeats = (b"", 0)   # last baro height (bytes) and how often in a row
        # Outlives resets: it decides what a reset is.
        self._timing = ImuTimingGuard(p.time_jump_reset, p.max_imu_dt, p.time_jump_confirm)
        self._diag = EkfDiagnostics(records=deque(maxlen=p.nis_history_length))
        self._candidates = RelocalisationCandidates(
            _gate(p.relocalisation_agreement_probability, 3), p.relocalisation_timeout,
            gravity=p.gravity, accel_noise_density=p.accel_noise_density,
            gyro_noise_density=p.gyro_noise_density, speed_sigma=p.relocalisation_speed_sigma)
        self._clear()

    # ------------------------------------------------------------------ state access
    def _clear(self):
        """Forget the estimate, history and logs (not the diagnostics counters)."""
        self.initialized = False
        self.t = None
        self.q = np.array([0.0, 0.0, 0.0, 1.0])
        self.kf.x = np.zeros((DIM_STATE, 1))
        self.kf.P = np.eye(DIM_STATE)
        self._x = self.kf.x[:, 0]
        self._history: deque[_Entry] = deque()
        self._log: list[_Measurement] = []
        self._pre_init_imu: deque = deque()
        self._init_candidates: deque[_Measurement] = deque(maxlen=_INIT_CANDIDATES)
        self._consecutive = Counter()
        self._streak_start: dict[str, float] = {}   # stamp of each source's first rejection
        # (stamp, smallest height error it would have caught) of accepted fixes and GNSS
        self._height_checks: deque = deque(maxlen=64)
        self._last_baro_gap: tuple[float, float] | None = None   # last accepted: stamp, z - h
        self._baro_jumped = False   # the current baro streak began with a jump
        self._baro_probation = 0    # baro heights still to compare only, after a jump
        self._diag.baro_step = 0.0
        self._level_sum = [0.0, 0.0, 0.0]   # since _level_start: of C (f - b_a) - turn
        self._level_rates = [0.0, 0.0, 0.0]   # ... of the ENU body rate
        self._level_squares = [0.0, 0.0]      # ... of the east and north force squared
        self._level_count = 0
        self._level_start = None
        # per source of _DRIFT_TESTS: (stamp, innovation, S) of its latest measurements
        self._drift_windows = {source: deque(maxlen=max(test.windows))
                               for source, test in _DRIFT_TESTS.items()}
        # the sources of _DRIFT_TESTS whose reference has agreed with the filter (accepted)
        # since it started: only their drifts are followed
        self._drift_confirmed: set[str] = set()
        self._reset_armed: set[str] = set()
        self._last_good: NavState | None = None   # set after a time jump, for re-init
        self._init_source_seen = False
        self._reinit_after = math.inf
        self._candidates.clear()
        self._diag.initialized = False
        self._diag.stamp = None
        self._diag.found = None

    @property
    def state(self) -> NavState:
        """Current estimate (copies)."""
        x = self._x
        return NavState(self.t, x[IDX_P].copy(), x[IDX_V].copy(), self.q.copy(),
                        x[IDX_BG].copy(), x[IDX_BA].copy(), self.kf.P.copy(),
                        x[IDX_W].copy(), float(x[IDX_BARO]), x[IDX_MOUNT].copy(),
                        float(x[IDX_SCALE]), x[IDX_MAP].copy())

    @property
    def diagnostics(self) -> EkfDiagnostics:
        """Filter health (the live object, refreshed on access)."""
        self._refresh_diagnostics()
        return self._diag

    def _refresh_diagnostics(self):
        d = self._diag
        d.initialized, d.stamp = self.initialized, self.t
        d.imu_stamps_refused = self._timing.refused
        now = self._now()
        if now is not None:
            self._candidates.expire(now)
        d.relocalisation_candidates = len(self._candidates)
        P = self.kf.P
        d.covariance_trace = float(np.trace(P))
        d.position_sigma = float(np.sqrt(np.trace(P[IDX_P, IDX_P])))
        d.horizontal_sigma = float(np.sqrt(P[0, 0] + P[1, 1])) if self.initialized else math.inf
        d.wind = tuple(float(w) for w in self._x[IDX_W]) if self.initialized else \
            (math.nan, math.nan)
        d.wind_sigma = float(np.sqrt(np.trace(P[IDX_W, IDX_W]))) if self.initialized else \
            math.nan
        known = self.initialized
        d.baro_bias = float(self._x[IDX_BARO]) if known else math.nan
        d.baro_bias_sigma = float(np.sqrt(P[IDX_BARO, IDX_BARO])) if known else math.nan
        d.height_sigma = float(np.sqrt(P[2, 2])) if known else math.nan
        d.camera_mount = tuple(float(m) for m in self._x[IDX_MOUNT]) if known else \
            (math.nan, math.nan)
        d.camera_mount_sigma = float(np.sqrt(np.trace(P[IDX_MOUNT, IDX_MOUNT]))) if known \
            else math.nan
        d.camera_scale = float(self._x[IDX_SCALE]) if known else math.nan
        d.camera_scale_sigma = float(np.sqrt(P[IDX_SCALE, IDX_SCALE])) if known else math.nan
        d.map_bias = tuple(float(b) for b in self._x[IDX_MAP]) if known else \
            (math.nan, math.nan)
        d.map_bias_sigma = float(np.sqrt(np.trace(P[IDX_MAP, IDX_MAP]))) if known \
            else math.nan

    def _now(self) -> float | None:
        """Filter time, or before initialisation the newest IMU stamp buffered (None if none)."""
        if self.t is not None:
            return self.t
        return self._pre_init_imu[-1][0] if self._pre_init_imu else None

    # ------------------------------------------------------------------ initialisation
    def default_covariance(self) -> np.ndarray:
        """Initial 23x23 covariance from the ``init_*_sigma`` parameters."""
        p = self.params
        sig = np.r_[[p.init_position_sigma] * 3, [p.init_velocity_sigma] * 3,
                    [p.init_roll_pitch_sigma] * 2, p.init_yaw_sigma,
                    [p.init_gyro_bias_sigma] * 3, [p.init_accel_bias_sigma] * 3,
                    [p.init_wind_sigma] * 2, p.init_baro_bias_sigma,
                    [p.init_camera_mount_sigma] * 2, p.init_camera_scale_sigma,
                    [p.init_map_bias_sigma] * 2]
        return np.diag(sig**2)

    def initialize(self, stamp: float, position, velocity, quaternion, covariance=None,
                   gyro_bias=None, accel_bias=None, wind=None,
                   baro_bias: float = 0.0, camera_mount=None,
                   camera_scale: float = 0.0, map_bias=None) -> Outcome:
        """Start (or restart) the filter from a full state at ``stamp``.

        Parameters
        ----------
        stamp : float
            Time (s) the state refers to.
        position, velocity : array_like, (3,)
            ENU (m, m/s).
        quaternion : array_like, (4,)
            Body -> ENU ``[x, y, z, w]``.
        covariance : array_like, optional
            Error covariance in the state order, (23, 23), (21, 21), (20, 20), (18, 18),
            (17, 17) or (15, 15); default :meth:`default_covariance`. The states it leaves
            out (the map bias; the camera scale too, at 20 x 20; the camera mount too, at
            18 x 18; the baro bias too, at 17 x 17; the wind too, at 15 x 15) start
            uncorrelated at their ``init_*_sigma``.
        gyro_bias, accel_bias : array_like, (3,), optional
            Initial bias estimates (default zero).
        wind : array_like, (2,), optional
            Initial wind, east and north (m/s; default zero).
        baro_bias : float, optional
            Initial baro bias (m).
        camera_mount : array_like, (2,), optional
            Initial camera mount error about body x and y (rad; default zero).
        camera_scale : float, optional
            Initial camera scale error (default zero).
        map_bias : array_like, (2,), optional
            Initial map bias, east and north (m; default zero).

        Returns
        -------
        Outcome
        """
        vals = [np.asarray(v, dtype=float) for v in (position, velocity, quaternion)]
        if [v.shape for v in vals] != [(3,), (3,), (4,)]:
            return self._refuse("init", Reason.BAD_SHAPE)
        if not all(np.all(np.isfinite(v)) for v in vals) or not np.isfinite(stamp):
            return self._refuse("init", Reason.NON_FINITE)
        q = _unit_quaternion(vals[2])
        if q is None:
            return self._refuse("init", Reason.BAD_QUATERNION)
        P = self.default_covariance()
        if covariance is not None:
            given = np.array(covariance, float)
            n = given.shape[0] if given.ndim == 2 else 0
            leading = (DIM_ERR, IDX_BARO, IDX_MOUNT.start, IDX_SCALE, IDX_MAP.start)
            if given.shape == (n, n) and n in leading:   # the leading states
                P[:n, :n] = given
            else:
                P = given
        if P.shape != (DIM_STATE, DIM_STATE) or not is_positive_definite(P):
            return self._refuse("init", Reason.BAD_COVARIANCE)
        pre_init = [s for s in self._pre_init_imu if s[0] > stamp]
        self._clear()
        x = np.zeros(DIM_STATE)
        x[IDX_P], x[IDX_V] = vals[0], vals[1]
        if gyro_bias is not None:
            x[IDX_BG] = gyro_bias
        if accel_bias is not None:
            x[IDX_BA] = accel_bias
        if wind is not None:
            x[IDX_W] = wind
        x[IDX_BARO] = baro_bias
        if camera_mount is not None:
            x[IDX_MOUNT] = camera_mount
        x[IDX_SCALE] = camera_scale
        if map_bias is not None:
            x[IDX_MAP] = map_bias
        self.kf.x = x.reshape(-1, 1).copy()
        self._x = self.kf.x[:, 0]
        self.kf.P = 0.5 * (P + P.T)
        self.q = q
        self.t = float(stamp)
        self.initialized = True
        self._store(None, None)
        for t, gyro, accel in pre_init:   # IMU that arrived while waiting for a fix
            self._integrate(t, gyro, accel)   # screened by the timing guard already
        return Outcome(True, Reason.INITIALIZED)

    def set_initial_pose(self, position, velocity, quaternion, stamp: float | None = None,
                         covariance=None) -> Outcome:
        """Initial state for ``init_mode="pose"``, applied now or at the first IMU sample.

        The pose is remembered and re-applied after a time-jump reset (bag loop).
        """
        self._initial_pose = (position, velocity, quaternion, covariance)
        if stamp is None:
            return Outcome(True, Reason.WAITING_FOR_INIT)
        return self.initialize(stamp, position, velocity, quaternion, covariance)

    def _init_from_measurement(self, meas: _Measurement) -> Outcome:
        """Initialise from GNSS or fixes: at once when they carry velocity and attitude,
        otherwise from two fixes ``init_min_fix_interval`` apart (velocity by difference,
        yaw from course, level roll/pitch) that imply a possible speed. The fixes of the
        last :data:`_INIT_CANDIDATE_SPAN` s are held as partners, so one wrong fix (a
        receiver's 2-D fix at altitude 0) costs only itself, first or second."""
        self._init_source_seen = True
        if 3 in meas.rows:
            return self._init_from(meas)
        p = self.params
        candidates = self._init_candidates
        while candidates and meas.stamp - candidates[0].stamp > \
                p.init_min_fix_interval + _INIT_CANDIDATE_SPAN:
            candidates.popleft()
        older = [c for c in candidates if meas.stamp - c.stamp >= p.init_min_fix_interval]
        candidates.append(meas)
        if not older:
            return Outcome(True, Reason.WAITING_FOR_INIT)
        for first in sorted(older, key=lambda c: -c.stamp):   # the shortest span first
            speed = np.linalg.norm(meas.z[:3] - first.z[:3]) / (meas.stamp - first.stamp)
            if speed <= p.init_max_speed:
                return self._init_from(meas, first)
        return Outcome(False, Reason.INIT_TOO_FAST)

    def _init_from_relocalisation(self, meas: _Measurement) -> Outcome:
        """Cold start from relocalisations: hold each one until another, far enough apart
        for a velocity by difference (``init_min_fix_interval``), agrees with it; then start
        from the pair as from two fixes. One relocalisation alone never starts the filter."""
        p = self.params
        self._init_source_seen = True
        candidate = Candidate(meas.stamp, meas.z[:3].copy(), meas.R[:3, :3].copy(),
                              measurement=meas)
        now = self._now()
        self._candidates.expire(meas.stamp if now is None else max(now, meas.stamp))
        partner = self._candidates.agreeing(
            candidate, max(p.init_min_fix_interval, p.relocalisation_min_interval))
        if partner is None:
            self._candidates.hold(meas.seq, candidate)
            return Outcome(False, Reason.RELOCALISATION_HELD)
        first, second = sorted((partner.measurement, meas), key=lambda m: m.stamp)
        out = self._init_from(second, first)
        if out.accepted:
            self._diag.found = Found(second.stamp)
        return out

    def _init_from(self, meas: _Measurement, first: _Measurement | None = None) -> Outcome:
        """Initialise at ``meas``: its velocity, or the difference from ``first``'s
        position; its attitude, or level with the nose along the course."""
        p = self.params
        pos, pcov = meas.z[:3], meas.R[:3, :3]
        if first is None:
            v, vcov = meas.z[3:6], meas.R[3:6, 3:6]
        else:
            dt = meas.stamp - first.stamp
            v = (pos - first.z[:3]) / dt
            vcov = (pcov + first.R[:3, :3]) / dt**2
        P = self.default_covariance()
        P[IDX_P, IDX_P] = pcov
        P[IDX_V, IDX_V] = vcov
        if meas.source == "fix":
            _position_from_the_map(P)
        q = meas.attitude
        if q is not None:
            P[IDX_TH, IDX_TH] = meas.R[-3:, -3:]
        else:
            # Level, nose along the course. Course is not heading (wind, sideslip), so the
            # yaw sigma is at least init_yaw_sigma.
            speed_h = max(float(np.hypot(v[0], v[1])), 1e-3)
            q = quat_from_euler(0.0, -np.arctan2(v[2], speed_h), np.arctan2(v[1], v[0]))
            sig_course = np.sqrt(np.trace(vcov[:2, :2]) / 2.0) / speed_h
            P[8, 8] = max(p.init_yaw_sigma, min(sig_course, np.pi)) ** 2
        out = self.initialize(meas.stamp, pos, v, q, P)
        if out.accepted:
            self._diag.last_accepted[meas.source] = meas.stamp
            self._diag.accepted[meas.source] += 1
        return out

    def waiting_for(self) -> str:
        """What the filter waits for to initialise ("" once initialised), for diagnostics:
        a bag whose GNSS ends before the second fix otherwise left only "not initialised"."""
        if self.initialized:
            return ""
        p = self.params
        if p.init_mode == "pose":
            return "an initial pose and an IMU sample"
        if self._candidates.held:
            stamps = ", ".join(f"{c.stamp:.3f}" for c in self._candidates.held)
            return (f"a relocalisation that agrees with the one(s) held at {stamps} s, "
                    f"{max(p.init_min_fix_interval, p.relocalisation_min_interval):g} s or "
                    "more apart")
        if not self._init_candidates:
            off_clock = sum(self._diag.input_rejections[f"{p.init_mode}:{r.value}"]
                            for r in (Reason.TOO_FAR_AHEAD, Reason.STALE))
            if off_clock:
                return (f"a {p.init_mode} measurement on the IMU's clock ({off_clock} "
                        "refused, stamped far from the IMU's: another clock, GPS time "
                        "against UTC?)")
            return f"a first {p.init_mode} measurement"
        first = min(c.stamp for c in self._init_candidates)
        if len(self._init_candidates) == 1:
            return (f"a second {p.init_mode} measurement {p.init_min_fix_interval:g} s or more "
                    f"after the one at {first:.3f} s (or one with velocity)")
        return (f"a {p.init_mode} measurement {p.init_min_fix_interval:g} s or more after one "
                f"of those held since {first:.3f} s, at {p.init_max_speed:g} m/s or less from "
                "it (or one with velocity)")

    def reset(self):
        """Forget the estimate (keeps counters); re-initialises per ``init_mode``."""
        self._clear()
        self._diag.resets += 1

    def _time_jump(self) -> Outcome:
        """Bridge an IMU outage, or reset on any other confirmed jump and start the new
        timeline with its samples."""
        pending = self._timing.take_pending()
        if self.initialized and 0 < pending[0][0] - self.t <= self.params.max_imu_outage:
            for sample in pending:   # the first one integrates across the outage
                self._integrate(*sample)
            return Outcome(True, Reason.IMU_GAP)
        last = self.state if self.initialized else None
        self.reset()
        self._last_good = last
        self._reinit_after = pending[0][0] + self.params.reinit_timeout
        for sample in pending:
            self._integrate(*sample)
        return Outcome(False, Reason.TIME_JUMP_RESET)

    def _reinitialize(self, stamp: float) -> Outcome:
        """Start again from the last good state with the initial covariance added: the
        time across the jump is unknown, so the state is a guess that fixes must correct."""
        s = self._last_good
        P = s.covariance + self.default_covariance()
        out = self.initialize(stamp, s.position, s.velocity, s.quaternion, 0.5 * (P + P.T),
                              s.gyro_bias, s.accel_bias)
        if not out.accepted:
            return out
        self._diag.reinitialisations += 1
        return Outcome(True, Reason.REINITIALIZED)

    # ------------------------------------------------------------------ IMU
    def process_imu(self, stamp: float, gyro, accel) -> Outcome:
        """Integrate one IMU sample.

        Parameters
        ----------
        stamp : float
            Sample time (s).
        gyro : array_like, (3,)
            Angular rate, body FLU (rad/s), bias not removed.
        accel : array_like, (3,)
            Specific force, body FLU (m/s^2), gravity not removed (level at rest reads
            ``+g`` on z).

        Every ``level_period`` the samples also level the filter: the direction of their
        specific force, less the turn's centripetal acceleration, is fused as a measurement
        of roll and pitch (source ``"level"``, ``level_sigma``), the one tilt reference the
        ground matches do not take from the filter; a drift of its innovations reopens the
        tilt, the roll and pitch gyro biases and the horizontal velocity
        (``diagnostics.tilt_drifts``). With it the sideslip is measured as zero (source
        ``"sideslip"``, ``sideslip_sigma``), which with the turns estimates the wind.

        Returns
        -------
        Outcome
            ``OK``/``IMU_GAP`` when integrated; ``INITIALIZED`` when a stored initial pose
            started the filter; rejections: ``NON_FINITE``, ``BAD_SHAPE``, ``DUPLICATE``,
            ``OUT_OF_ORDER``, ``NOT_INITIALIZED``, ``STAMP_OFF_PERIOD``;
            ``TIME_JUMP_RESET`` after a reset, ``REINITIALIZED`` when it restarted from the
            last good state.
        """
        # Plain floats: cheaper than numpy for 3-vectors at IMU rate.
        try:
            gyro = tuple(float(v) for v in np.ravel(gyro))
            accel = tuple(float(v) for v in np.ravel(accel))
            stamp = float(stamp)
        except (TypeError, ValueError):
            return self._refuse("imu", Reason.BAD_SHAPE)
        if len(gyro) != 3 or len(accel) != 3:
            return self._refuse("imu", Reason.BAD_SHAPE)
        if not math.isfinite(stamp + sum(gyro) + sum(accel)):
            return self._refuse("imu", Reason.NON_FINITE)
        timing = self._timing.check(stamp, (stamp, gyro, accel))
        if timing == ImuTiming.SUSPECT:
            return self._refuse("imu", Reason.STAMP_OFF_PERIOD)
        if timing == ImuTiming.JUMP:
            return self._time_jump()
        return self._integrate(stamp, gyro, accel)

    def _integrate(self, stamp: float, gyro, accel) -> Outcome:
        """A sample whose stamp passed the timing screen: integrate, buffer or refuse."""
        if not self.initialized:
            return self._imu_before_init(stamp, gyro, accel)
        if stamp == self.t:
            return self._refuse("imu", Reason.DUPLICATE)
        if stamp < self.t:
            return self._refuse("imu", Reason.OUT_OF_ORDER)
        gap = stamp - self.t > self.params.max_imu_dt
        self._advance(stamp, gyro, accel)
        if self.params.level_sigma > 0.0 or self.params.sideslip_sigma > 0.0:
            self._accumulate_level()
        if gap:
            self._diag.imu_gaps += 1
            return Outcome(True, Reason.IMU_GAP)
        return Outcome(True, Reason.OK)

    def _imu_before_init(self, stamp, gyro, accel) -> Outcome:
        if self.params.init_mode == "pose" and self._initial_pose is not None:
            return self.initialize(stamp, *self._initial_pose)
        if (self._last_good is not None and not self._init_source_seen
                and stamp >= self._reinit_after):
            return self._reinitialize(stamp)
        buf = self._pre_init_imu
        if buf and stamp <= buf[-1][0]:
            return self._refuse("imu", Reason.OUT_OF_ORDER)
        buf.append((stamp, gyro, accel))
        while buf and buf[0][0] < stamp - self.params.history_length:
            buf.popleft()
        return self._refuse("imu", Reason.NOT_INITIALIZED)

    def _predict(self, t_new: float, gyro, accel):
        """Strapdown mean plus covariance ``P = F P F^T + Q`` over ``(self.t, t_new]``."""
        dt = t_new - self.t
        F = self._step.step(self._x, self.q, gyro, accel, dt)
        P = self.kf.P
        np.dot(F, P, out=self._tmp)
        np.dot(self._tmp, F.T, out=P)
        P += self._process_noise(dt)
        self.t = t_new

    def _process_noise(self, dt: float) -> np.ndarray:
        if dt != self._q_dt:
            Q = self._Q
            np.multiply(self._Q1, dt, out=Q)
            Q += self._Q2 * dt**2
            Q += self._Q3 * dt**3
            self._q_dt = dt
        return self._Q

    def _advance(self, t_new: float, gyro, accel):
        """Integrate one IMU sample, applying logged measurements stamped in (t, t_new]."""
        log = self._log
        if log and log[-1].stamp > self.t:
            i = bisect.bisect_right(log, self.t, key=lambda m: m.stamp)
            for meas in log[i:]:
                if meas.stamp > t_new:
                    break
                if meas.stamp > self.t:
                    self._predict(meas.stamp, gyro, accel)
                self._evaluate(meas)
        if t_new > self.t:   # not already there because a measurement sat at t_new
            self._predict(t_new, gyro, accel)
        self._store(gyro, accel)

    def _accumulate_level(self):
        """Accelerometer levelling, a tilt reference independent of the gyros and of the
        fixes (which carry the filter's own tilt): sum the specific force less the turn's
        centripetal acceleration (body rate x air velocity), in ENU, and every
        ``level_period`` submit its direction as a measurement of the tilt (source
        ``"level"``), with the sideslip (:meth:`_submit_sideslip`)."""
        fx, fy, fz = self._step.force_less_turn
        rx, ry, rz = self._step.rate_enu
        total, rates, squares = self._level_sum, self._level_rates, self._level_squares
        total[0] += fx
        total[1] += fy
        total[2] += fz
        squares[0] += fx * fx
        squares[1] += fy * fy
        rates[0] += rx
        rates[1] += ry
        rates[2] += rz
        self._level_count += 1
        if self._level_start is None:
            self._level_start = self.t
        if self.t - self._level_start < self.params.level_period:
            return
        x = self._x
        # The step took the turn off with the ground velocity; the wind's part is the air's.
        up = np.array(total) + np.cross(rates, np.r_[x[IDX_W], 0.0])
        rate = np.array(rates) / self._level_count
        noise = self._level_noise(total, squares)
        total[:] = rates[:] = (0.0, 0.0, 0.0)
        squares[:] = (0.0, 0.0)
        self._level_count = 0
        self._level_start = self.t
        self._submit_sideslip()
        # Rolling into or out of a turn (or pulling up), the body rate is not the
        # velocity's and the turn model multiplies every velocity error by it: skipped.
        if self.params.level_sigma <= 0.0 or math.hypot(rate[0], rate[1]) > _LEVEL_MAX_TILT_RATE:
            return
        up /= np.linalg.norm(up)
        C = quat_to_matrix(self.q)
        # The estimates taken off lean the measured up by their errors, through the turn a
        # velocity error e_v by (rate x e_v) / g, a wind one e_w by -(rate x e_w) / g, a
        # gyro bias one e_g by (C e_g) x (v - w) / g and an attitude one dtheta, which turns
        # the body rate, by rate x ((v - w) x dtheta) / g (a heading error leans a turn's
        # levelling along the track); an accelerometer bias one e_a by C e_a / g: the update
        # takes the levelling as a measurement of them too.
        air = self._air_velocity()
        lean = np.zeros((3, DIM_STATE))
        lean[:, IDX_V] = skew(rate)
        lean[:, IDX_W] = -skew(rate)[:, :2]
        lean[:, IDX_TH] = skew(rate) @ skew(air)
        lean[:, IDX_BG] = skew(air) @ C
        lean[:, IDX_BA] = C
        lean = _LEAN_ROWS @ lean / self.params.gravity
        R = np.eye(2) * (self.params.level_sigma**2 + noise)
        self._submit(self.t, "level", lean @ x, R, np.array([6, 7]), None,
                     body_up=C.T @ up, state_lever=lean)

    def _level_noise(self, total, squares) -> float:
        """Variance (rad^2) the samples' own scatter puts on a levelling's tilt: that of
        the mean horizontal specific force over the period (the samples' variance over
        their count, taken as independent), over g^2. Nil for a clean IMU, it is the
        levelling's whole error under vibration, which level_sigma (the model's) does not
        hold."""
        n = self._level_count
        if n < 2:
            return 0.0
        spread = sum(max(sq / n - (t / n) ** 2, 0.0)
                     for sq, t in zip(squares, total[:2], strict=True))
        return 0.5 * spread / (n - 1) / self.params.gravity**2

    def _submit_sideslip(self):
        """The sideslip, zero in coordinated flight of a fixed wing: the air velocity's
        component along the body's lateral axis, measured as 0 with ``sideslip_sigma``
        (source ``"sideslip"``). With the ground velocity the fixes pin, it is the crab
        between heading and track, which measures the crosswind in straight flight and
        the whole wind over a turn. Not below :data:`_SIDESLIP_MIN_AIRSPEED`, where the
        aircraft is not flying (a launch, a bench test)."""
        if self.params.sideslip_sigma <= 0.0:
            return
        if math.hypot(*self._air_velocity()[:2]) < _SIDESLIP_MIN_AIRSPEED:
            return
        self._submit(self.t, "sideslip", np.zeros(1),
                     np.array([[self.params.sideslip_sigma**2]]), _NO_ROWS, None)

    def _sideslip_row(self) -> np.ndarray:
        """Jacobian (DIM_STATE,) of the sideslip ``b . (v - w)`` at the estimate, ``b`` the
        body's lateral axis in ENU: a small rotation dtheta turns it into ``b +
        dtheta x b``, which adds ``b . ((v - w) x dtheta)``."""
        lateral = quat_to_matrix(self.q)[:, 1]
        air = self._air_velocity()
        row = np.zeros(DIM_STATE)
        row[IDX_V] = lateral
        row[IDX_W] = -lateral[:2]
        row[IDX_TH] = lateral @ skew(air)
        return row

    def _air_velocity(self) -> np.ndarray:
        """The estimate's velocity through the air, ENU (m/s): the ground velocity less the
        (horizontal) wind."""
        air = self._x[IDX_V].copy()
        air[:2] -= self._x[IDX_W]
        return air

    def _store(self, gyro, accel):
        """Append the current state to the history and drop what fell out of it."""
        hist = self._history
        hist.append(_Entry(self.t, gyro, accel, self._x.copy(), self.q.copy(),
                           self.kf.P.copy()))
        horizon = self.t - self.params.history_length
        while len(hist) > 1 and hist[1].t <= horizon:
            hist.popleft()
        while self._log and self._log[0].stamp < hist[0].t:
            self._log.pop(0)

    # ------------------------------------------------------------------ measurements
    def process_fix(self, stamp: float, position, covariance, velocity=None, quaternion=None,
                    source: str = "fix", relocalisation: bool = False,
                    projection_height: float = 0.0, mosaic_lag: float = 0.0) -> Outcome:
        """Position fix (optionally with velocity and/or attitude), e.g. a terrain PvaFix.

        Parameters
        ----------
        stamp : float
            Time the fix refers to (s); may be older than the newest IMU sample.
        position : array_like, (3,)
            ENU position (m).
        covariance : array_like, (m, m)
            Covariance of ``[position, velocity?, attitude?]`` in that order: 3x3, 6x6
            (position + velocity or position + attitude) or 9x9. Attitude covariance is of
            the small rotation about the ENU axes (rad^2), as in ROS PoseWithCovariance.
        velocity : array_like, (3,), optional
            ENU velocity (m/s).
        quaternion : array_like, (4,), optional
            Body -> ENU attitude ``[x, y, z, w]``.
        source : str
            Counter / gate key: ``"fix"`` (terrain) or ``"gnss"``.
        relocalisation : bool
            The fix was found by a search of the whole mission area, independent of the
            estimate. Fused when the gate accepts it; otherwise held
            (``RELOCALISATION_HELD``) until another relocalisation agrees with it, when the
            position is reset onto it (``RELOCALISATION_RESET``) or, before initialisation
            with ``init_mode="fix"``, the filter starts from the pair
            (:mod:`~.relocalisation`). Its velocity, if any, is ignored: a difference from a
            fix searched around the estimate it contradicts. It never counts towards
            ``reset_after_rejections`` nor becomes an armed reset.
        projection_height : float
            For a fix from a frame projected onto the ground with the filter's own attitude
            (a ground match): the camera's height (m) above the projection plane. Such a fix
            registers the ground point the prior attitude put straight below the camera, so
            its horizontal position carries that attitude's tilt error times this height
            (:func:`tilt_lever`); the update models it instead of treating it as noise, which
            a stream of fixes with one tilt error would average into a position bias. Its
            height, measured by the registration's scale, carries the camera's scale error
            times this height. 0: the fix does not depend on the filter's attitude (PnP, GNSS,
            pose-free frames).
        mosaic_lag : float
            For a fix from a track mosaic: the mean age (s) of its pixels. Its frames were
            moved into the newest one's estimate by the filter's dead reckoning, so its
            horizontal position measures ``p - mosaic_lag x (v - v_hat)``; the update models
            that. 0: a single frame (or any other fix).

        Returns
        -------
        Outcome
        """
        if not (math.isfinite(projection_height) and projection_height >= 0.0):
            return self._refuse(source, Reason.BAD_PROJECTION_HEIGHT)
        if not (math.isfinite(mosaic_lag) and mosaic_lag >= 0.0):
            return self._refuse(source, Reason.BAD_MOSAIC_LAG)
        parts = [np.asarray(position, dtype=float)]
        rows = [np.arange(0, 3)]
        if velocity is not None and not relocalisation:
            parts.append(np.asarray(velocity, dtype=float))
            rows.append(np.arange(3, 6))
        att = None
        if quaternion is not None:
            att = np.asarray(quaternion, dtype=float)
            if att.shape != (4,):
                return self._refuse(source, Reason.BAD_SHAPE)
            if not np.isfinite(att).all():
                return self._refuse(source, Reason.NON_FINITE)
            att = _unit_quaternion(att)
            if att is None:
                return self._refuse(source, Reason.BAD_QUATERNION)
            parts.append(np.zeros(3))
            rows.append(np.arange(6, 9))
        if any(p.shape != (3,) for p in parts):
            return self._refuse(source, Reason.BAD_SHAPE)
        lever = None
        state_lever = np.zeros((3 * len(parts), DIM_STATE))
        if source == "fix":   # a terrain fix is in the map's frame: it measures p + b_map
            state_lever[:2, IDX_MAP] = np.eye(2)
        if projection_height > 0.0:
            lever = np.zeros((3 * len(parts), 3))
            lever[:3] = tilt_lever(projection_height)
            state_lever[2, IDX_SCALE] = projection_height
        if not state_lever.any():
            state_lever = None
        return self._submit(stamp, source, np.concatenate(parts), covariance,
                            np.concatenate(rows), att, relocalisation, lever=lever,
                            state_lever=state_lever, velocity_lag=mosaic_lag)

    def set_position(self, stamp: float, position, covariance) -> Outcome:
        """Put the position at ``position`` (ENU, m; 3x3 covariance) at ``stamp``, whatever
        the estimate: an operator's re-seed (robot_localization's ``set_pose``, position
        only). Not gated; velocity, attitude and biases stay the filter's, and the position
        is decorrelated from them (``POSITION_RESET`` under the source ``"set_pose"``)."""
        position = np.asarray(position, dtype=float)
        if position.shape != (3,):
            return self._refuse("set_pose", Reason.BAD_SHAPE)
        return self._submit(stamp, "set_pose", position, covariance, np.arange(0, 3), None,
                            reset=True)

    def process_gnss(self, stamp: float, position, covariance) -> Outcome:
        """GNSS position already converted to the ENU map frame (m), with its 3x3 covariance
        (NavSatFix's ``position_covariance`` is ENU).

        With ``fuse_gnss=False`` GNSS only initialises the filter (``init_mode="gnss"``) and
        is otherwise compared with the estimate: its NIS is recorded (reason
        ``COMPARED_ONLY``) but the state is not updated, so a GPS-denied run can be scored
        against GNSS while it is still available.
        """
        return self.process_fix(stamp, position, covariance, source="gnss")

    def process_baro(self, stamp: float, altitude: float, variance: float) -> Outcome:
        """Barometric altitude as ENU up (m, already referred to the map origin height),
        with its variance (m^2).

        A baro that jumps (its height differs from the filter's by far more than the last
        accepted one did, within a second: a static port that ices or clears, a driver
        fault) has stepped: the jump is taken off this and every later height
        (``diagnostics.baro_step``), as a new offset learnt at once, and the streak it
        begins never resets the height. The next ``_BARO_STUCK - 1`` heights are only
        compared (``PROBATION``): a sensor that jumped and froze (a baro stuck at 90 kPa)
        would otherwise hold the height still while the aircraft climbs, until refused.
        A height repeated bit for bit ``_BARO_STUCK`` times in a row is refused
        (``STUCK``): sensor noise no longer moves it, however plausible the value."""
        altitude = np.asarray(altitude, dtype=float)
        value, repeats = self._baro_repeats
        key = altitude.tobytes()
        self._baro_repeats = (key, repeats + 1 if key == value else 1)
        if self._baro_repeats[1] >= _BARO_STUCK:
            return self._refuse("baro", Reason.STUCK)
        return self._submit(stamp, "baro", np.atleast_1d(altitude - self._diag.baro_step),
                            np.atleast_2d(np.asarray(variance, dtype=float)), np.array([2]),
                            None, state_lever=_BARO_LEVER)

    def _submit(self, stamp, source, z, covariance, rows, attitude,
                relocalisation: bool = False, reset: bool = False, lever=None,
                body_up=None, state_lever=None, velocity_lag: float = 0.0) -> Outcome:
        """Validate, log and apply (now, queued or in the past) one measurement; with
        ``reset``, as a position reset (not gated)."""
        m = len(z)
        R = np.asarray(covariance, dtype=float)
        if R.shape != (m, m):
            return self._refuse(source, Reason.BAD_SHAPE)
        if not (np.isfinite(z).all() and np.isfinite(R).all() and np.isfinite(stamp)):
            return self._refuse(source, Reason.NON_FINITE)
        if not is_positive_definite(R):
            return self._refuse(source, Reason.BAD_COVARIANCE)
        meas = _Measurement(float(stamp), next(self._seq), source, z.copy(), 0.5 * (R + R.T),
                            rows, attitude, relocalisation=relocalisation, reset=reset,
                            attitude_lever=lever, body_up=body_up,
                            state_lever=state_lever, velocity_lag=float(velocity_lag))
        if not self.initialized:
            if source != self.params.init_mode:
                return self._refuse(source, Reason.NOT_INITIALIZED)
            off_clock = self._off_the_imu_clock(meas.stamp, relocalisation)
            if off_clock is not None:   # GNSS in GPS time with the IMU in UTC (18 s)
                # and those held before the IMU came, on the same clock, go too
                kept = [c for c in self._init_candidates
                        if self._off_the_imu_clock(c.stamp, False) is None]
                self._init_candidates = deque(kept, maxlen=_INIT_CANDIDATES)
                return self._refuse(source, off_clock)
            if relocalisation:
                return self._init_from_relocalisation(meas)
            return self._init_from_measurement(meas)
        if any(o.stamp == meas.stamp and o.source == source for o in self._log):
            return self._refuse(source, Reason.DUPLICATE)
        if meas.stamp - self.t > self.params.max_future:
            return self._refuse(source, Reason.TOO_FAR_AHEAD)
        if meas.stamp < self._history[0].t:
            return self._refuse(source, Reason.STALE)
        if source in self._reset_armed and not relocalisation:   # armed by _record
            meas.reset = True
            self._reset_armed.discard(source)
        bisect.insort(self._log, meas, key=lambda o: o.key)
        if meas.stamp > self.t:
            return Outcome(True, Reason.QUEUED)
        self._apply_in_past(meas)
        return meas.outcome

    def _off_the_imu_clock(self, stamp: float, relocalisation: bool) -> Reason | None:
        """Before the start, the screen an initialised filter applies to a measurement's
        stamp, against the IMU buffered meanwhile: a start at a stamp far from the IMU's
        would integrate its samples across the gap, or refuse them all as out of order. A
        relocalisation may be late (a search of the whole area takes seconds): only one
        ahead of the IMU is refused."""
        if not self._pre_init_imu:
            return None
        newest = self._pre_init_imu[-1][0]
        if stamp - newest > self.params.max_future:
            return Reason.TOO_FAR_AHEAD
        if not relocalisation and stamp < newest - self.params.history_length:
            return Reason.STALE
        return None

    def _apply_in_past(self, meas: _Measurement):
        """Rewind to the last history entry at or before the stamp, apply, re-propagate."""
        hist = self._history
        replay = []
        while hist[-1].t > meas.stamp:
            replay.append(hist.pop())
        e = hist[-1]
        self._x[:] = e.x
        self.q[:] = e.q
        self.kf.P = e.P.copy()
        self.t = e.t
        if meas.stamp == e.t:
            # Entry already holds the measurements stamped at e.t: apply this one and
            # overwrite the entry so a later rewind to e.t includes it.
            self._evaluate(meas)
            hist.pop()
            self._history.append(_Entry(e.t, e.gyro, e.accel, self._x.copy(), self.q.copy(),
                                        self.kf.P.copy()))
        for entry in reversed(replay):
            self._advance(entry.t, entry.gyro, entry.accel)

    def _evaluate(self, meas: _Measurement):
        """Gate and apply a measurement at the current filter time; record the outcome."""
        if meas.reset:
            outcome = self._position_reset(meas)
        elif meas.relocalisation:
            outcome = self._relocalise(meas)
        else:
            gap = self._baro_gap(meas) if meas.source == "baro" else None
            if gap is not None and meas.outcome is None and self._baro_probation:
                meas.probation = True
                self._baro_probation -= 1
            self._test_drift(meas)
            outcome = self._update(meas)
            if gap is not None and meas.outcome is None:
                self._note_baro_gap(meas, outcome, gap)
        self._record(meas, outcome)

    def _test_drift(self, meas: _Measurement):
        """Whether the last innovations of one attitude reference lean one way, by the gate
        on their mean over a few window lengths: a gyro bias that stepped beyond its random
        walk turns the attitude steadily, which each measurement alone would not reject for
        several times the window (its gate is ~4 sigma wide) and a gyro bias the filter is
        sure of would not follow. When they do, the angle's variance is reopened to the
        mean's square and the gyro bias's about the same axes to the innovations' slope:
        this and later updates then move them (on a re-application after a rewind, again).

        Two references are tested apart (:data:`_DRIFT_TESTS`): the levellings' tilt
        (``diagnostics.tilt_drifts``; not the yaw bias: a roll-axis drift would be taken as
        the lean its turn compensation gives) and the heading of fixes that measure one
        (``diagnostics.heading_drifts``)."""
        test = _DRIFT_TESTS.get(meas.source)
        if test is None or meas.relocalisation:
            return
        if meas.outcome is None:
            rows = np.flatnonzero(np.isin(meas.rows, test.rows))
            if len(rows) != len(test.rows):
                return
            z, H = self._innovation(meas)
            z, H = z[rows], H[rows]
            S = H @ self.kf.P @ H.T + meas.R[np.ix_(rows, rows)]
            window = self._drift_windows[meas.source]
            window.append((meas.stamp, z - H @ self._x, S))
            gate = _gate(self.params.gate_probability(meas.source), len(rows))
            for n in test.windows:   # short ones see a fast drift first, long ones a slow one
                if len(window) < n:
                    continue
                recent = list(window)[-n:]
                if self._drifted(recent, gate, meas, test, self._position_aided_since(
                        recent[0][0])):
                    window.clear()
                    if self._disputed(meas, recent):
                        meas.reopen = None
                        self._diag.heading_disputes += 1
                    else:
                        setattr(self._diag, test.counter,
                                getattr(self._diag, test.counter) + 1)
                    break
        for states, variance in meas.reopen or ():
            self._widen(states, variance)

    def _disputed(self, meas: _Measurement, window: list) -> bool:
        """Whether a heading drift :meth:`_drifted` found in ``window`` is the fixes' own:
        their innovations are over :data:`_HEADING_DISPUTE` (RMS) and none of their headings
        has agreed with the filter since it started (a camera mount yawed 90 deg, an image
        turned 180, whose innovations wrap around +-180 and average to anything). A crab in
        the wind, the widest honest gap between a first heading and the fixes', stays
        below; a gyro's drift is caught while a few degrees."""
        if meas.source != "fix" or meas.source in self._drift_confirmed:
            return False
        innovations = np.array([w[1] for w in window])
        return math.sqrt(float(np.mean(innovations ** 2))) > _HEADING_DISPUTE

    def _position_aided_since(self, stamp: float) -> bool:
        """Whether a position (fix or GNSS) was accepted at or after ``stamp``."""
        last = self._diag.last_accepted
        return any(last.get(source, -math.inf) >= stamp for source in _POSITION_SOURCES)

    @staticmethod
    def _drifted(window: list, gate: float, meas: _Measurement, test: _DriftTest,
                 position_aided: bool) -> bool:
        """Whether the mean of a window of ``(stamp, innovation, S)`` is outside the gate;
        if so, set ``meas.reopen`` to the angle's floor (the mean's square), the rate
        biases' (the innovations' slope squared) and, for a tilt, the horizontal velocity's
        (g times the mean times the window's span) and, while positions were fused over
        the window, the horizontal accelerometer biases' (g times the mean, squared)."""
        t = np.array([w[0] for w in window])
        innovations = np.array([w[1] for w in window])
        mean = innovations.mean(axis=0)
        mean_cov = sum(w[2] for w in window) / len(window)**2
        if not mean @ np.linalg.solve(mean_cov, mean) > gate:
            return False
        span = t[-1] - t[0]
        t -= t.mean()
        slope = float(np.linalg.norm(t @ innovations / max(t @ t, 1e-9)))
        meas.reopen = [(test.angle, float(mean @ mean)), (test.rate_biases, slope**2)]
        if test.acceleration_per_angle:
            # The drift the filter missed over the window had the dead reckoning integrate
            # the specific force with it: the horizontal velocity is off by about as much.
            lean = test.acceleration_per_angle * float(np.linalg.norm(mean))
            meas.reopen.append((_HORIZONTAL_VELOCITY, (lean * span)**2))
            if position_aided:
                # Or the lean is no tilt but an accelerometer bias that stepped (it leans
                # the measured up by bias / g), which the positions' dynamics tell apart;
                # without them the prior, a stable accelerometer, stands.
                meas.reopen.append((_HORIZONTAL_ACCEL_BIASES, lean**2))
        return True

    def _widen(self, states: np.ndarray, variance):
        """Raise the variances of ``states`` to at least ``variance`` (one, or one each),
        decorrelated from the rest."""
        P = self.kf.P
        floor = np.maximum(np.diag(P)[states], variance)
        P[states, :] = 0.0
        P[:, states] = 0.0
        P[states, states] = floor

    def _relocalise(self, meas: _Measurement) -> Outcome:
        """Fuse a relocalisation the gate accepts while the estimate is good enough for the
        gate to be a check; hold any other, and reset the position onto it when a held one
        agrees with it (:mod:`~.relocalisation`)."""
        tested = self._gate_test(meas)
        if tested is None:
            return Outcome(False, Reason.BAD_COVARIANCE)
        nis, gate = tested[2:4]
        # A gate ~4 sigma wide around a lost estimate is no check on a mission-wide search.
        trusted = math.sqrt(self.kf.P[0, 0] + self.kf.P[1, 1]) <= \
            self.params.relocalisation_fuse_max_sigma
        if nis <= gate and trusted:
            self._candidates.discard(meas.seq)   # held before a rewind changed the estimate
            return self._update(meas)
        candidate = Candidate(meas.stamp, meas.z[:3].copy(), meas.R[:3, :3].copy(),
                              self._x[IDX_P].copy(), self.kf.P.copy(), self.q.copy(), meas)
        self._candidates.expire(self.t)
        if self._candidates.agreeing(candidate, self.params.relocalisation_min_interval) is None:
            self._candidates.hold(meas.seq, candidate)
            return Outcome(False, Reason.RELOCALISATION_HELD, nis, gate)
        self._reset_onto(meas)
        return Outcome(True, Reason.RELOCALISATION_RESET, nis, gate)

    def _reset_onto(self, meas: _Measurement):
        """Reset the position onto an agreed relocalisation and say so (``found``)."""
        before = self._x[IDX_P].copy()
        meas.reset = True   # a re-application after a rewind resets again
        self._position_reset(meas)
        self._candidates.clear()
        self._diag.found = Found(meas.stamp, self._x[IDX_P] - before)
        self._diag.relocalisation_resets += 1

    def _innovation(self, meas: _Measurement):
        z = meas.z.copy()
        if meas.attitude is not None:
            # Attitude rows measure dtheta: the rotation from the nominal to the measured
            # attitude, about the ENU axes.
            z[-3:] = attitude_error(meas.attitude, self.q)
        if meas.body_up is not None:
            # The measured up, rotated to ENU by the estimate, leans by dtheta x e_z.
            up = quat_to_matrix(self.q) @ meas.body_up
            z += (up[1], -up[0])
        H = np.zeros((len(z), DIM_STATE))
        if meas.source == "sideslip":
            H[0] = self._sideslip_row()
        else:
            H[np.arange(len(z)), meas.rows] = 1.0
        if meas.attitude_lever is not None:
            H[:, IDX_TH] += meas.attitude_lever
            # the camera mount's error turns the ray as the attitude's does, about body axes
            H[:, IDX_MOUNT] += meas.attitude_lever @ quat_to_matrix(self.q)[:, :2]
        if meas.state_lever is not None:
            H += meas.state_lever
        if meas.velocity_lag:
            # h = p - lag (v - v_hat): the innovation stays z - p_hat, the gain learns v too
            k, velocity = _lagged_rows(meas)
            H[k, velocity] -= meas.velocity_lag
            z[k] -= meas.velocity_lag * self._x[velocity]
        return z, H

    def _gate_test(self, meas: _Measurement, keep: np.ndarray | None = None):
        """``(z, H, nis, gate, R)`` of a measurement (of its rows ``keep``, by default all)
        at the current filter time, or None when its innovation covariance is not positive
        definite."""
        z, H = self._innovation(meas)
        R = meas.R
        if keep is not None:
            z, H, R = z[keep], H[keep], R[np.ix_(keep, keep)]
        y = z - H @ self._x
        S = H @ self.kf.P @ H.T + R
        try:
            L = np.linalg.cholesky(S)
        except np.linalg.LinAlgError:
            return None
        w = np.linalg.solve(L, y)
        return z, H, float(w @ w), _gate(self.params.gate_probability(meas.source), len(z)), R

    def _update(self, meas: _Measurement) -> Outcome:
        tested = self._gate_test(meas)
        if tested is None:
            return Outcome(False, Reason.BAD_COVARIANCE)
        z, H, nis, gate, R = tested
        if meas.source == "gnss" and not self.params.fuse_gnss:
            return Outcome(False, Reason.COMPARED_ONLY, nis, gate)
        if meas.probation:
            return Outcome(False, Reason.PROBATION, nis, gate)
        reason = Reason.OK
        if nis > gate:
            tested = self._gate_test_without_height(meas)
            if tested is None:
                return Outcome(False, Reason.GATED, nis, gate)
            (z, H, nis, gate, R), reason = tested, Reason.FUSED_WITHOUT_HEIGHT
        self.kf.update(z.reshape(-1, 1), HJacobian=lambda _x: H, Hx=lambda x: H @ x, R=R)
        self._x = self.kf.x[:, 0]
        self._inject_attitude()
        return Outcome(True, reason, nis, gate)

    def _gate_test_without_height(self, meas: _Measurement):
        """``(z, H, nis, gate, R)`` of a terrain fix with its height row left out, when the
        rest passes its gate (None otherwise): a ground match's height comes from its scale,
        its horizontal position from its translation, and a camera whose focal length is off
        by more than the scale error's prior gets the first wrong, not the second. Only
        while the baro or GNSS holds the filter's height (accepted within
        ``_HEIGHT_HELD_FOR`` s): else the height in dispute may be the filter's own, run
        away with its accelerometers, and the whole fix is gated (a streak resets)."""
        if meas.source != "fix" or meas.relocalisation or 2 not in meas.rows:
            return None
        if all(self._diag.last_accepted.get(source, -math.inf) < meas.stamp - _HEIGHT_HELD_FOR
               for source in ("baro", "gnss")):
            return None
        tested = self._gate_test(meas, keep=meas.rows != 2)
        return tested if tested is not None and tested[2] <= tested[3] else None

    def _inject_attitude(self):
        """Fold dtheta into the quaternion, zero it and rotate P with the reset Jacobian."""
        dth = self._x[IDX_TH].copy()
        if not dth.any():
            return
        self.q = quat_normalize(quat_multiply(quat_exp(dth), self.q))
        self._x[IDX_TH] = 0.0
        G = np.eye(DIM_STATE)
        G[IDX_TH, IDX_TH] -= 0.5 * skew(dth)
        P = G @ self.kf.P @ G.T
        self.kf.P = 0.5 * (P + P.T)

    def _position_reset(self, meas: _Measurement) -> Outcome:
        """Replace the position by the measurement's, decorrelated from the rest: recovery
        when the filter has diverged. Velocity and attitude stay with the IMU: a terrain
        fix's velocity is a difference of two fixes (tens of m/s of noise at 1 s) and its
        tilt is unobserved, so adopting them outright can throw the filter further off. A
        levelling's reset is of the tilt: onto the levelling, with the velocity and gyro
        biases reopened and the roll and pitch biases to the drift rate of the streak."""
        z, H = self._innovation(meas)
        if meas.state_lever is not None:   # what the rows measure besides the state's lever
            z = z - meas.state_lever @ self._x
        if meas.attitude_lever is not None:   # (the attitude's error is 0 between updates)
            z = z - H[:, IDX_MOUNT] @ self._x[IDX_MOUNT]
        if meas.velocity_lag:   # onto the position measured, as the innovation takes it
            k, velocity = _lagged_rows(meas)
            z[k] += meas.velocity_lag * self._x[velocity]
        keep = meas.rows < 3 if meas.source != "level" else np.ones(len(meas.rows), bool)
        r = meas.rows[keep]
        P = self.kf.P
        P[r, :] = 0.0
        P[:, r] = 0.0
        P[np.ix_(r, r)] = meas.R[np.ix_(keep, keep)]
        if meas.source == "fix" and 0 in r:
            _position_from_the_map(P)
        self._x[r] = z[keep]
        if 2 in r and meas.source != "baro":
            # the height moved: the baro's last gap to it says nothing of a jump any more,
            # nor what fixes caught before of a height the baro now disputes
            self._last_baro_gap = None
            self._height_checks.clear()
        if meas.relocalisation:
            return Outcome(True, Reason.RELOCALISATION_RESET)
        if meas.source in _POSITION_SOURCES:
            self._reopen_dead_reckoning(_DEAD_RECKONING)
        elif meas.source == "baro":
            self._reopen_dead_reckoning(_VERTICAL_CHANNEL)
        elif meas.source == "level":
            self._inject_attitude()
            self._reopen_dead_reckoning(_LEVELLED)
            # The streak says how fast the tilt drifted since the last accepted levelling.
            last = self._diag.last_accepted.get("level", -math.inf)
            rate = float(np.linalg.norm(z)) / max(meas.stamp - last, self.params.level_period)
            self._widen(_TILT_RATE_BIASES, rate**2)
        return Outcome(True, Reason.POSITION_RESET)

    def _reopen_dead_reckoning(self, states: np.ndarray):
        """After a divergence, widen the uncertainties of ``states`` to at least their
        initial ones (``init_*_sigma``), decorrelated: the streak of rejections says the
        dead reckoning that carried the filter away is off too (a gyro or accelerometer
        bias that stepped beyond its random walk), and a filter still sure of it would
        diverge again from the new position. The values stay the IMU's. After fixes: the
        velocity, attitude and biases; after baro heights, which see the vertical channel
        alone: the vertical velocity and the accelerometer biases (reopening the tilt, which
        ground matches observe poorly, cost 16 m of horizontal error in a replay)."""
        self._widen(states, np.diag(self.default_covariance())[states])

    def _record(self, meas: _Measurement, outcome: Outcome):
        """Count an evaluation once; on re-application only fix up a changed decision."""
        d = self._diag
        first = meas.outcome is None
        if outcome.reason in (Reason.COMPARED_ONLY, Reason.PROBATION):
            if first:
                d.records.append(UpdateRecord(meas.stamp, meas.source, len(meas.z),
                                              outcome.nis, outcome.gate, False))
            meas.outcome = outcome
            return
        if first or meas.outcome.accepted != outcome.accepted:
            if not first:
                (d.accepted if meas.outcome.accepted else d.rejected)[meas.source] -= 1
            (d.accepted if outcome.accepted else d.rejected)[meas.source] += 1
        if first and outcome.nis is not None:
            d.records.append(UpdateRecord(meas.stamp, meas.source, len(meas.z), outcome.nis,
                                          outcome.gate, outcome.accepted))
        if outcome.accepted:
            d.last_accepted[meas.source] = max(meas.stamp,
                                               d.last_accepted.get(meas.source, -np.inf))
            if outcome.reason != Reason.FUSED_WITHOUT_HEIGHT:
                self._note_height_check(meas)
            if first and meas.source == "fix":
                left_out = outcome.reason == Reason.FUSED_WITHOUT_HEIGHT
                d.heights_left_out += left_out
                d.heights_left_out_in_a_row = (d.heights_left_out_in_a_row + 1) * left_out
            test = _DRIFT_TESTS.get(meas.source)
            if test is not None and np.isin(test.rows, meas.rows).all():
                self._drift_confirmed.add(meas.source)
        if first and not meas.relocalisation:   # relocalisations never arm a reset
            if outcome.reason == Reason.POSITION_RESET:
                d.position_resets += 1
            if outcome.accepted:
                self._consecutive[meas.source] = 0
            else:
                if not self._consecutive[meas.source]:
                    self._streak_start[meas.source] = meas.stamp
                self._consecutive[meas.source] += 1
                n = self.params.reset_after_rejections
                if n and self._consecutive[meas.source] >= n and self._diverged_for(meas):
                    self._arm_reset(meas.source)
        meas.outcome = outcome

    def _baro_gap(self, meas: _Measurement) -> float:
        """How far a baro height is from the filter's height with its bias (m)."""
        return float(meas.z[0]) - self._x[2] - self._x[IDX_BARO]

    def _note_baro_gap(self, meas: _Measurement, outcome: Outcome, gap: float):
        """Whether a baro streak begins with a jump: its first rejected height differs from
        the filter by far more than the last accepted one did, within a second (the 1-dof
        gate on the difference of two samples' noise). A filter integrating even a gross
        accelerometer fault moves a few metres per second; a baro that steps jumps: the
        step is taken off later heights and the streak never resets."""
        if outcome.accepted:
            self._last_baro_gap = (meas.stamp, gap)
            self._baro_jumped = False
            return
        if self._consecutive["baro"] or self._last_baro_gap is None:
            return
        stamp, last = self._last_baro_gap
        limit = math.sqrt(_gate(self.params.gate_probability("baro"), 1) * 2.0 * meas.R[0, 0])
        self._baro_jumped = meas.stamp - stamp <= _BARO_JUMP_WINDOW and abs(gap - last) > limit
        if self._baro_jumped:
            self._diag.baro_steps += 1
            self._diag.baro_step += gap - last
            self._baro_probation = _BARO_STUCK - 1

    def _note_height_check(self, meas: _Measurement):
        """Remember how well an accepted fix or GNSS measured the height: the smallest
        error of the filter's height its gate would have caught."""
        if meas.source not in _POSITION_SOURCES or 2 not in meas.rows:
            return
        k = int(np.flatnonzero(meas.rows == 2)[0])
        variance = meas.R[k, k]
        if meas.state_lever is not None:   # a ground match's height: the camera scale's doubt
            variance += float(meas.state_lever[k] @ self.kf.P @ meas.state_lever[k])
        gate = _gate(self.params.gate_probability(meas.source), 1)
        self._height_checks.append((meas.stamp, math.sqrt(variance * gate)))

    def _diverged_for(self, meas: _Measurement) -> bool:
        """Whether the streak of rejections ``meas`` ends may mean a diverged filter rather
        than a faulty source: no other reference of what it measures agreed with the filter
        since the streak began.

        For a fix or GNSS, the other one was not accepted meanwhile: when it agrees with
        the filter all along, the source is the one that is off (GNSS spoofed 200 m for 4 s
        was reset onto, and the fused error stayed ~200 m until ten fixes had been rejected
        in turn). For the barometer, no fix or GNSS accepted meanwhile, nor the last one
        before the streak, measured the height well enough to have caught the filter as far
        off as the baro says: with 3-D fixes a baro stuck 2 km off is rejected for good, but
        a ground match without a measured scale echoes the filter's height (sigma 10 % of
        the height above ground), a measured one is as good as the camera scale error's
        sigma allows, and a filter whose height an accelerometer bias carries away must come
        back onto the baro (an inertial vertical channel alone diverges); unless the streak
        began with a jump of the baro (:meth:`_note_baro_gap`). The levelling is the one
        tilt reference: its streaks always reset."""
        start = self._streak_start.get(meas.source, -math.inf)
        if meas.source == "baro":
            if self._baro_jumped:
                return False
            gap = abs(self._baro_gap(meas))
            checks = [c for c in self._height_checks if c[0] < start][-1:] + \
                [c for c in self._height_checks if c[0] >= start]
            return not any(caught <= gap for _, caught in checks)
        if meas.source == "level":
            return True
        if meas.source not in _POSITION_SOURCES:
            return False
        if meas.source == "fix" and self._diag.heading_disputes and \
                "fix" not in self._drift_confirmed:
            return False   # the fixes' heading is off: their positions are suspect too
        return all(self._diag.last_accepted.get(other, -math.inf) < start
                   for other in _POSITION_SOURCES - {meas.source})

    def _arm_reset(self, source: str):
        """Turn the next measurement of ``source`` to arrive into a position reset."""
        self._consecutive[source] = 0
        self._reset_armed.add(source)

    def _refuse(self, source: str, reason: Reason) -> Outcome:
        self._diag.input_rejections[f"{source}:{reason.value}"] += 1
        return Outcome(False, reason)


# The sideslip measures no state alone (its Jacobian is TerrainEkf._sideslip_row).
_NO_ROWS = np.zeros(0, dtype=int)
# Below this airspeed (m/s) the aircraft is not flying and its sideslip means nothing.
_SIDESLIP_MIN_AIRSPEED = 10.0
# Levellings are skipped over periods whose mean ENU body rate about a horizontal axis
# exceeds this (rad/s, 3 deg/s): a vertical velocity error of 1 m/s leans one by 0.3 deg.
_LEVEL_MAX_TILT_RATE = math.radians(3.0)
# The levelling's rows (dtheta_x, dtheta_y) from an ENU up leaning by u: (u_y, -u_x).
_LEAN_ROWS = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
# The absolute position references: a streak of gate rejections of one resets the position
# onto it unless the other agreed with the filter meanwhile (:meth:`TerrainEkf._diverged_for`;
# the barometer's streaks reset the height unless one of them measured it).
_POSITION_SOURCES = frozenset({"fix", "gnss"})
# A fix's height gated alone is left out of it only while the baro or GNSS held the height
# this recently (s): :meth:`TerrainEkf._gate_test_without_height`.
_HEIGHT_HELD_FOR = 2.0
# States a divergence reset reopens (:meth:`TerrainEkf._reopen_dead_reckoning`): after fixes,
# velocity, attitude, biases and the camera's mount and scale (a fix's own biases; not the
# map bias: the map did not move when the dead reckoning went off); after baro heights,
# the vertical velocity and the accelerometer biases.
_DEAD_RECKONING = np.arange(IDX_V.start, IDX_MAP.start)
_VERTICAL_CHANNEL = np.r_[IDX_V.stop - 1, np.arange(IDX_BA.start, IDX_BA.stop)]
# ... after levellings: the velocity (integrated with the drifted tilt), the gyro biases, the
# wind (through which the turns lean the levelling) and the horizontal accelerometer biases
# (which lean it as a tilt does).
_LEVELLED = np.r_[IDX_V.start:IDX_V.stop, IDX_BG.start:IDX_BG.stop, IDX_W.start:IDX_W.stop,
                  IDX_BA.start:IDX_BA.start + 2]
_TILT = np.arange(IDX_TH.start, IDX_TH.start + 2)
_HORIZONTAL_VELOCITY = np.arange(IDX_V.start, IDX_V.start + 2)
_TILT_RATE_BIASES = np.arange(IDX_BG.start, IDX_BG.start + 2)   # roll and pitch axes
_HORIZONTAL_ACCEL_BIASES = np.arange(IDX_BA.start, IDX_BA.start + 2)   # body x and y


def _position_from_the_map(P: np.ndarray) -> None:
    """``P`` (in place) for a horizontal position just set from a terrain fix (its
    covariance in ``P[:2, :2]``, uncorrelated): the fix is where the map puts the aircraft,
    ``p = z - b_map``, so the position's doubt holds the map bias's, anti-correlated with it."""
    bias = P[IDX_MAP, IDX_MAP].copy()
    P[:2, :2] += bias
    P[:2, IDX_MAP] = -bias
    P[IDX_MAP, :2] = -bias.T


@dataclass(frozen=True)
class _DriftTest:
    """An attitude reference whose innovations :meth:`TerrainEkf._test_drift` tests."""

    rows: np.ndarray          # the attitude error states its measurements' rows must hold
    angle: np.ndarray         # states reopened to the mean innovation's square
    rate_biases: np.ndarray   # states reopened to the innovations' slope squared
    windows: tuple            # the numbers of latest measurements whose means are tested
    counter: str              # the EkfDiagnostics field counting the drifts found
    acceleration_per_angle: float = 0.0   # m/s^2 of horizontal acceleration error per rad


_DRIFT_TESTS = {
    # The levellings' tilt, over the last 10 and 20 (s at level_period): in simulated
    # surveys a 20 s window cut the worst error of a pitch gyro bias step of 0.1 deg/s from
    # 93 to 53 m; a 5 s one, taking the drift rate from fewer levellings, lost more at
    # 0.2 deg/s than it won at 0.5.
    "level": _DriftTest(_TILT, _TILT, _TILT_RATE_BIASES, (10, 20), "tilt_drifts",
                        acceleration_per_angle=GRAVITY),
    # The heading of fixes that measure one, over the last 5, 10 and 20: a yaw bias of
    # 0.5 deg/s has them gated after ~5 s at the matcher's 0.5 deg heading sigma floor.
    "fix": _DriftTest(np.array([IDX_TH.start + 2]), np.array([IDX_TH.start + 2]),
                      np.array([IDX_BG.start + 2]), (5, 10, 20), "heading_drifts"),
}
# A baro height differing from the previous accepted one by more than noise allows is a jump
# only this soon after it (s): across a longer silence the filter may have drifted that far.
_BARO_JUMP_WINDOW = 1.0
# rad: a lean of the fixes' heading innovations beyond this, before any agreed, is the
# camera's, not a gyro's drift (:meth:`TerrainEkf._disputed`)
_HEADING_DISPUTE = math.radians(45.0)
# Initialising fixes held as partners for a later one: those of the last init_min_fix_interval
# plus this many seconds (a GNSS outage at start-up of up to that long costs no partner),
# and at most this many in all (5 Hz GNSS over the span).
_INIT_CANDIDATE_SPAN = 30.0
_INIT_CANDIDATES = 512
# Baro heights repeated bit for bit this many times in a row are a stuck sensor: its noise
# (a few Pa, over a resolution of about 1 Pa) no longer moves it.
_BARO_STUCK = 10


def tilt_lever(height: float) -> np.ndarray:
    """How a ground-projected fix's position moves with the projection attitude's error.

    The fix is the ground point the attitude used put straight below the camera, at
    ``height`` (m) above the projection plane. With the true attitude ``Exp(dtheta)`` times
    the one used (``dtheta`` about the ENU axes), the ray believed vertical really points
    along ``dtheta x (0, 0, -height)``, so the fix lands ``(-height * dtheta_n, height *
    dtheta_e)`` from the camera, and heading errors do not move it. Returns the (3, 3)
    Jacobian of the fixed position with respect to ``dtheta``.
    """
    return float(height) * np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


def is_positive_definite(R: np.ndarray) -> bool:
    """True for a finite, symmetric (to rounding), positive-definite matrix."""
    if not np.isfinite(R).all():
        return False
    scale = max(float(np.abs(R).max()), 1e-300)
    if np.abs(R - R.T).max() > 1e-9 * scale:
        return False
    try:
        np.linalg.cholesky(R)
    except np.linalg.LinAlgError:
        return False
    return True


def _unit_quaternion(q: np.ndarray) -> np.ndarray | None:
    """Normalised copy of a quaternion whose norm is within 1 % of one, else None."""
    n = float(np.linalg.norm(q))
    if not abs(n - 1.0) < 0.01:
        return None
    return quat_normalize(q)
