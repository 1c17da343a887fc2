"""Parameters of the terrain-navigation EKF, with units and defaults.

The names are the ROS parameter names the ``ekf`` node declares (``config/ekf.yaml``), so the
node can map them one to one with ``EkfParams(**{name: node.get_parameter(name).value ...})``.

IMU defaults: ScanEagle-class tactical/industrial MEMS IMU
----------------------------------------------------------
The numbers are representative of the MEMS units flown in ScanEagle-class small UAS
autopilots (e.g. Analog Devices ADIS1646x/1648x, VectorNav VN-100/VN-300 class), rounded
up rather than down so a real unit of that class is not over-trusted:

=============================  =====================  ============================================
gyro_noise_density             1.7e-4 rad/s/sqrt(Hz)  0.01 deg/s/sqrt(Hz) = 0.6 deg/sqrt(h) ARW
accel_noise_density            1.0e-3 m/s^2/sqrt(Hz)  ~100 micro-g/sqrt(Hz) = 0.06 m/s/sqrt(h) VRW
gyro_bias_random_walk          5.0e-6 rad/s^2/sqrt(Hz)  bias wanders ~ 25 deg/h (1 sigma) per hour
accel_bias_random_walk         1.0e-4 m/s^3/sqrt(Hz)  bias wanders ~ 0.6 mg (1 sigma) per hour
init_gyro_bias_sigma           2.5e-4 rad/s           ~50 deg/h residual turn-on bias after the
                                                      usual pre-launch gyro zeroing on the ground
init_accel_bias_sigma          2.0e-2 m/s^2           ~2 mg turn-on bias
=============================  =====================  ============================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

#: The radius holding 90 % of a circular normal error, in its per-axis sigmas:
#: sqrt(-2 ln 0.1). Data sheets state a DEM's horizontal accuracy as that radius (CE90).
CE90_PER_SIGMA = math.sqrt(-2.0 * math.log(0.1))


def map_bias_sigma(dem_ce90: float) -> float:
    """``init_map_bias_sigma`` (m per axis) of a DEM whose stated absolute horizontal
    accuracy is ``dem_ce90`` m, the circular error at 90 % (SRTM: 20 m, so 9.3 m).

    Raises ValueError for a CE90 that is not a positive finite number.
    """
    value = float(dem_ce90)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"a DEM's horizontal CE90 must be a positive number of metres, got "
                         f"{dem_ce90!r}")
    return value / CE90_PER_SIGMA


@dataclass
class EkfParams:
    """Settings of :class:`terrain_nav_ros.core.estimation.ekf.TerrainEkf` (SI units throughout).

    Attributes
    ----------
    gravity : float
        Magnitude of gravity (m/s^2); acts along -z of the ENU map frame. Default 9.80665.
    gyro_noise_density : float
        Gyro white noise (angle random walk), rad/s/sqrt(Hz). Default 1.7e-4.
    accel_noise_density : float
        Accelerometer white noise (velocity random walk), m/s^2/sqrt(Hz). Default 1.0e-3.
    gyro_bias_random_walk : float
        Gyro bias random walk, rad/s^2/sqrt(Hz). Default 5.0e-6.
    accel_bias_random_walk : float
        Accelerometer bias random walk, m/s^3/sqrt(Hz). Default 1.0e-4.
    init_position_sigma : float
        1-sigma position uncertainty when initialising from a pose without covariance (m).
        Default 10.0.
    init_velocity_sigma : float
        1-sigma velocity uncertainty at initialisation (m/s). Default 2.0.
    init_roll_pitch_sigma : float
        1-sigma roll/pitch uncertainty at initialisation (rad). Default 0.0087 (0.5 deg),
        what accelerometer levelling or a hand-over from the autopilot's AHRS gives.
    init_yaw_sigma : float
        1-sigma yaw uncertainty at initialisation (rad). Default 0.035 (2 deg), a hand-over
        from GNSS-aided heading. Larger initial attitude errors make any EKF of this kind
        overconfident in yaw (it linearises at a tilted/rotated estimate, which invents yaw
        information in straight flight): with 2 / 5 deg the Monte Carlo NEES grew to ~18 for
        15 states; with 0.5 / 2 deg it stays at 15. Use larger values when that is the truth
        (the filter still converges in turns), but expect an optimistic yaw sigma.
    init_gyro_bias_sigma : float
        1-sigma gyro turn-on bias left after pre-launch zeroing (rad/s). Default 2.5e-4.
    init_accel_bias_sigma : float
        1-sigma accelerometer turn-on bias (m/s^2). Default 2.0e-2.
    init_mode : str
        How the filter starts: ``"pose"`` (a pose given with ``set_initial_pose``, re-used
        after a time-jump reset), ``"gnss"`` (first GNSS fixes), ``"fix"`` (first terrain
        fixes). Default ``"fix"``.
    init_min_fix_interval : float
        When initialising from fixes that carry no velocity, the second fix used to derive
        velocity and course must be at least this much later than the first (s). Default 10.0.
    init_max_speed : float
        A pair of such fixes whose difference means a faster speed (m/s) starts nothing: one
        of them is wrong (a receiver's first output, a false match). The older is dropped and
        the newer waits for a partner. Default 150.0 (a small fixed-wing with wind to spare).
    fix_gate_probability : float
        Chi-square gate probability for terrain fixes (dof = measurement dimension); >= 1
        disables gating. Default 0.999.
    baro_gate_probability : float
        Same for barometric altitude. Default 0.999.
    gnss_gate_probability : float
        Same for GNSS position. Default 0.999.
    fuse_gnss : bool
        If False, GNSS is used to initialise and is compared with the estimate (NIS
        recorded) but never updates it. Default True.
    reset_after_rejections : int
        After this many consecutive gated-out fixes (or GNSS measurements), the position is
        reset to the next one of that source (recovers from divergence), unless the other
        source was accepted since the first of them (then that source is the one off, e.g.
        spoofed GNSS); 0 disables. The reset also widens the velocity, attitude and bias
        variances to at least their initial ones: the dead reckoning that diverged is
        suspect too. A baro streak resets the height unless an accepted fix or GNSS (during
        it, or the last before it) measured the height well enough to vouch for the
        filter's. Default 10.
    history_length : float
        Length of the state / IMU history used for delayed measurements (s). Measurements
        older than the history are rejected as stale. Default 3.0.
    max_future : float
        A measurement stamped up to this far ahead of the newest IMU sample is queued and
        applied when the IMU reaches its stamp; further ahead it is rejected (s). Default 0.5.
    time_jump_reset : float
        An IMU stamp this far from the previous one, back or ahead, is refused as a glitch
        unless ``time_jump_confirm`` samples continue from it (bag loop, simulator restart),
        which resets the filter; smaller backward steps are rejected as out of order (s).
        Default 1.0.
    time_jump_confirm : int
        Consecutive samples, each within ``max_imu_dt`` of the previous, that confirm a time
        jump. Default 5 (50 ms at 100 Hz): one or a few bad stamps never reset the filter.
    max_imu_outage : float
        A confirmed jump ahead of up to this long is an IMU outage, not a new timeline: the
        filter integrates across it as a gap (as it does for any gap shorter than
        ``time_jump_reset``) instead of resetting (s). Default 10.0.
    reinit_timeout : float
        After a reset with ``init_mode`` gnss or fix, when no measurement of that source came
        within this time of the new timeline, the filter restarts from its last good state
        with the initial covariance added, instead of waiting for a source that may be gone
        (GNSS denied) (s). Default 2.0.
    max_imu_dt : float
        IMU intervals longer than this are integrated but flagged as a gap (s). Default 0.1.
    nis_history_length : int
        Number of per-update NIS records kept in the diagnostics. Default 200.
    relocalisation_agreement_probability : float
        A relocalisation the gate rejects is held as a candidate; the filter resets (or, with
        ``init_mode="fix"``, starts) onto it only when another one agrees: their displacement
        minus the dead-reckoned one is inside this chi-square probability (3 dof) of the sum
        of their covariances and the dead reckoning's growth over the interval. In (0, 1):
        there is no "off", an unverified relocalisation never moves the filter. Default 0.999.
    relocalisation_timeout : float
        A held relocalisation expires this long after its stamp (s, filter time). Must exceed
        ``init_min_fix_interval`` with ``init_mode="fix"`` (a cold start needs two that far
        apart). Default 30.0.
    relocalisation_min_interval : float
        Two relocalisations agree only when their stamps are at least this far apart (s):
        different frames, overlapping less (a wrong place found in overlapping frames moves
        with them). Default 1.0.
    relocalisation_fuse_max_sigma : float
        A relocalisation inside the gate is fused on its own only while the estimate's
        horizontal sigma is at most this (m); beyond it the gate, about four sigma wide, is no
        check on a search of the whole mission area, and the relocalisation is held like one
        outside the gate. Default 500.0 (a gate of ~1.5 km radius: a wrong place anywhere in
        a 100 x 100 km area falls into it less than once in 1000).
    relocalisation_speed_sigma : float
        Before the filter runs there is no dead reckoning: the displacement between two
        relocalisations is tested against a zero-mean speed prior of this sigma per axis
        (m/s). Default 50.0 (faster than a ScanEagle-class aircraft cruises).
    level_sigma : float
        Accelerometer levelling (:meth:`TerrainEkf.process_imu`): 1-sigma of the roll and
        pitch measured by the direction of the specific force less the turn's centripetal
        acceleration, summed over ``level_period`` (rad). It stands for the accelerations
        the model leaves out (speed changes, gusts, sideslip); the samples' own noise is
        measured from their scatter and added to it. Default 0.008727 (0.5 deg, 0.086
        m/s^2 sustained over the period); 0 turns the levelling off.
    level_period : float
        Time the levelling sums the specific force over (s). Default 1.0.
    level_gate_probability : float
        Chi-square gate probability for the levelling. Default 0.999.
    init_wind_sigma : float
        1-sigma of each horizontal wind component at initialisation (m/s); the wind starts
        at zero. The levelling needs it, since a turn's centripetal acceleration is the air
        velocity's (in a turn at rate r an unknown wind w leans it by r w / g: 6 deg in a
        6 deg/s turn at 10 m/s), and the sideslip measures it. Default 10.0.
    wind_random_walk : float
        How fast the wind may change, per horizontal component (m/s/sqrt(s)). Default 0.1
        (1 m/s in 100 s).
    init_baro_bias_sigma : float
        1-sigma of the baro bias at initialisation (m): the error of the offset that puts the
        pressure altitude into ENU up (the ekf node learns it from the filter's height once
        its sigma is below ``baro_offset_max_sigma``, 10 m, or it is set). Default 10.0.
    baro_bias_random_walk : float
        How fast the baro bias may change (m/sqrt(s)): the weather's pressure changes, ~8 m
        per hPa. Default 0.1 (6 m in an hour).
    init_camera_mount_sigma : float
        1-sigma of the camera mount's error about body x and y at initialisation (rad): how
        well the declared mount (``camera_mount_rpy``) points the camera. Default 1 degree
        (a mount set from drawings); a boresight calibration gets it to ~0.1 degree.
    camera_mount_random_walk : float
        How fast the mount's error may change (rad/sqrt(s)): a rigid mount flexing with
        temperature and load. Default 1e-5 (0.03 degree in an hour).
    init_camera_scale_sigma : float
        1-sigma of the camera's scale error at initialisation: how far a ground match's
        height above its plane, measured by the registration's scale, may be off in
        proportion (the CameraInfo's focal length against the lens's). Default 0.02 (a
        calibrated lens is within a few tenths of a percent; 2 % leaves room for one
        focused elsewhere). A height beyond what it allows is left out of the fix.
    camera_scale_random_walk : float
        How fast the camera's scale error may change (1/sqrt(s)): the focal length with
        temperature. Default 1e-5 (0.06 % in an hour).
    init_map_bias_sigma : float
        1-sigma of the map bias, per horizontal axis, at initialisation (m): how far the
        DEM (and so every terrain fix) may be off its true place. Default 10.0 (SRTM's
        stated absolute horizontal accuracy is 20 m at 90 %, about 9 m per axis); a DEM
        surveyed onto the mission's datum is within a few metres. :func:`map_bias_sigma`
        gives it from a data sheet's CE90 (a mission.yaml's ``dem_horizontal_ce90``).
    map_bias_random_walk : float
        How fast the map bias may change (m/sqrt(s)): a DEM's error varies slowly over the
        area flown. Default 0.1 (6 m in an hour).
    sideslip_sigma : float
        1-sigma of the sideslip, measured as zero every ``level_period`` (m/s of lateral air
        velocity): a fixed wing in coordinated flight, with the IMU's x axis along its
        fuselage; it holds the sideslip of turns and gusts and a mount misalignment of a
        degree or two. Default 1.0; 0 turns it off (an aircraft that flies sideways: a
        multicopter), when only the turns' levellings see the wind.
    sideslip_gate_probability : float
        Chi-square gate probability for the sideslip. Default 0.999.
    """

    gravity: float = 9.80665
    gyro_noise_density: float = 1.7e-4
    accel_noise_density: float = 1.0e-3
    gyro_bias_random_walk: float = 5.0e-6
    accel_bias_random_walk: float = 1.0e-4
    init_position_sigma: float = 10.0
    init_velocity_sigma: float = 2.0
    init_roll_pitch_sigma: float = float(np.deg2rad(0.5))
    init_yaw_sigma: float = float(np.deg2rad(2.0))
    init_gyro_bias_sigma: float = 2.5e-4
    init_accel_bias_sigma: float = 2.0e-2
    init_mode: str = "fix"
    init_min_fix_interval: float = 10.0
    init_max_speed: float = 150.0
    fix_gate_probability: float = 0.999
    baro_gate_probability: float = 0.999
    gnss_gate_probability: float = 0.999
    fuse_gnss: bool = True
    reset_after_rejections: int = 10
    history_length: float = 3.0
    max_future: float = 0.5
    time_jump_reset: float = 1.0
    time_jump_confirm: int = 5
    max_imu_outage: float = 10.0
    reinit_timeout: float = 2.0
    max_imu_dt: float = 0.1
    nis_history_length: int = 200
    relocalisation_agreement_probability: float = 0.999
    relocalisation_timeout: float = 30.0
    relocalisation_min_interval: float = 1.0
    relocalisation_fuse_max_sigma: float = 500.0
    relocalisation_speed_sigma: float = 50.0
    level_sigma: float = float(np.deg2rad(0.5))
    level_period: float = 1.0
    level_gate_probability: float = 0.999
    init_wind_sigma: float = 10.0
    wind_random_walk: float = 0.1
    init_baro_bias_sigma: float = 10.0
    baro_bias_random_walk: float = 0.1
    init_camera_mount_sigma: float = float(np.deg2rad(1.0))
    camera_mount_random_walk: float = 1e-5
    init_camera_scale_sigma: float = 0.02
    camera_scale_random_walk: float = 1e-5
    init_map_bias_sigma: float = 10.0
    map_bias_random_walk: float = 0.1
    sideslip_sigma: float = 1.0
    sideslip_gate_probability: float = 0.999

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, (int, float)) and not np.isfinite(value):
                raise ValueError(f"EkfParams.{f.name} must be finite, got {value}")
        positive = ("gravity", "gyro_noise_density", "accel_noise_density",
                    "init_position_sigma", "init_velocity_sigma", "init_roll_pitch_sigma",
                    "init_yaw_sigma", "history_length", "time_jump_reset", "max_imu_dt")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"EkfParams.{name} must be > 0, got {getattr(self, name)}")
        for name in ("fix_gate_probability", "baro_gate_probability", "gnss_gate_probability",
                     "level_gate_probability", "sideslip_gate_probability"):
            if not 0.0 < getattr(self, name):
                raise ValueError(f"EkfParams.{name} must be in (0, 1], got {getattr(self, name)}")
        if self.level_sigma < 0 or self.level_period <= 0 or self.sideslip_sigma < 0:
            raise ValueError("EkfParams.level_sigma and sideslip_sigma must be >= 0 and "
                             f"level_period > 0, got {self.level_sigma}, "
                             f"{self.sideslip_sigma}, {self.level_period}")
        if self.init_camera_mount_sigma <= 0 or self.camera_mount_random_walk < 0:
            raise ValueError("EkfParams.init_camera_mount_sigma must be > 0 and "
                             "camera_mount_random_walk >= 0, got "
                             f"{self.init_camera_mount_sigma}, {self.camera_mount_random_walk}")
        if self.init_camera_scale_sigma <= 0 or self.camera_scale_random_walk < 0:
            raise ValueError("EkfParams.init_camera_scale_sigma must be > 0 and "
                             "camera_scale_random_walk >= 0, got "
                             f"{self.init_camera_scale_sigma}, {self.camera_scale_random_walk}")
        if self.init_map_bias_sigma <= 0 or self.map_bias_random_walk < 0:
            raise ValueError("EkfParams.init_map_bias_sigma must be > 0 and "
                             f"map_bias_random_walk >= 0, got {self.init_map_bias_sigma}, "
                             f"{self.map_bias_random_walk}")
        if self.init_baro_bias_sigma <= 0 or self.baro_bias_random_walk < 0:
            raise ValueError("EkfParams.init_baro_bias_sigma must be > 0 and "
                             f"baro_bias_random_walk >= 0, got {self.init_baro_bias_sigma}, "
                             f"{self.baro_bias_random_walk}")
        if self.init_wind_sigma <= 0 or self.wind_random_walk < 0:
            raise ValueError("EkfParams.init_wind_sigma must be > 0 and wind_random_walk >= 0, "
                             f"got {self.init_wind_sigma}, {self.wind_random_walk}")
        if self.time_jump_confirm < 1 or self.reinit_timeout < 0 or self.max_imu_outage < 0:
            raise ValueError("EkfParams.time_jump_confirm must be >= 1, reinit_timeout and "
                             f"max_imu_outage >= 0, got {self.time_jump_confirm}, "
                             f"{self.reinit_timeout}, {self.max_imu_outage}")
        self._check_relocalisation()
        if self.init_mode not in ("pose", "gnss", "fix"):
            raise ValueError("EkfParams.init_mode must be pose, gnss or fix, "
                             f"not {self.init_mode!r}")

    def _check_relocalisation(self):
        if not 0.0 < self.relocalisation_agreement_probability < 1.0:
            raise ValueError("EkfParams.relocalisation_agreement_probability must be in (0, 1), "
                             f"got {self.relocalisation_agreement_probability}")
        if not (self.relocalisation_speed_sigma > 0 and self.relocalisation_fuse_max_sigma > 0
                and 0 <= self.relocalisation_min_interval < self.relocalisation_timeout):
            raise ValueError("EkfParams.relocalisation_speed_sigma and "
                             "relocalisation_fuse_max_sigma must be > 0 and "
                             "0 <= relocalisation_min_interval < relocalisation_timeout, got "
                             f"{self.relocalisation_speed_sigma}, "
                             f"{self.relocalisation_fuse_max_sigma}, "
                             f"{self.relocalisation_min_interval}, {self.relocalisation_timeout}")
        if self.init_mode == "fix" and self.relocalisation_timeout <= self.init_min_fix_interval:
            raise ValueError("EkfParams.relocalisation_timeout must exceed init_min_fix_interval "
                             "with init_mode fix (a cold start needs two relocalisations that far "
                             f"apart), got {self.relocalisation_timeout} <= "
                             f"{self.init_min_fix_interval}")

    def gate_probability(self, source: str) -> float:
        """Gate probability configured for a measurement source (fix, baro, gnss)."""
        return getattr(self, f"{source}_gate_probability", self.fix_gate_probability)
