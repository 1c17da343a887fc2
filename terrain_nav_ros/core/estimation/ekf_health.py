"""The ``ekf`` node's health report and refusal logs, without ROS.

What :mod:`terrain_nav_ros.nodes.ekf_node` publishes on ``/nav/ekf/diagnostics`` and logs,
computed from the filter's :class:`~.ekf.EkfDiagnostics`: the filter's level (OK, WARN,
ERROR) with the problems that set it (:func:`filter_health`), its key-value report
(:func:`filter_values`), one report per measurement source with the NIS of the updates since
the previous report (:func:`source_report`, :class:`NewRecords`), throttled refusal logs
(:class:`RefusalLog`), and the navigation state, lost / searching / found / tracking
(:func:`navigation_state`, logged once per change by :class:`NavigationLog`). The levels are
``diagnostic_msgs/DiagnosticStatus``'s.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from .ekf import EkfDiagnostics

OK, WARN, ERROR = 0, 1, 2
# Fixes in a row fused without their height before the health names the camera's scale.
HEIGHTS_LEFT_OUT_WARN = 5
SOURCES = ("fix", "baro", "gnss", "level", "sideslip")


@dataclass(frozen=True)
class HealthLimits:
    """When the filter's report turns WARN or ERROR.

    Attributes
    ----------
    fix_warn, fix_error : float
        Filter time without an accepted fix or GNSS (s).
    sigma_warn, sigma_error : float
        Position sigma (m).
    imu_timeout : float
        Wall time without an IMU sample before ERROR (s).
    lost_sigma : float
        Horizontal position sigma beyond which the navigation state is ``lost`` (m).
    """

    fix_warn: float = 30.0
    fix_error: float = 120.0
    sigma_warn: float = 50.0
    sigma_error: float = 200.0
    imu_timeout: float = 1.0
    lost_sigma: float = 1000.0


@dataclass
class Health:
    """A level and the problems that set it."""

    level: int = OK
    problems: list[str] = field(default_factory=list)

    def worse(self, level: int, text: str):
        """Raise the level to at least ``level`` and note why."""
        self.level = max(self.level, level)
        self.problems.append(text)

    @property
    def message(self) -> str:
        """The problems, or "ok"."""
        return "; ".join(self.problems) or "ok"


def time_since_fix(d: EkfDiagnostics) -> float | None:
    """Filter time since the last accepted fix or GNSS (None if never)."""
    ages = [a for a in (d.time_since("fix"), d.time_since("gnss")) if a is not None]
    return min(ages) if ages else None


LOST, SEARCHING, FOUND, TRACKING = "lost", "searching", "found", "tracking"


def navigation_state(d: EkfDiagnostics, lost_sigma: float) -> tuple[str, str]:
    """Where navigation stands, and why, as ``(state, detail)``.

    ``searching`` while relocalisations are held with none agreed yet (whatever the
    estimate: one that contradicts it is news); else ``lost`` with no estimate or a
    horizontal sigma beyond ``lost_sigma``; else ``found`` after a reset onto (or a start
    from) agreeing relocalisations, until a fix or GNSS stamped after it passes the gate;
    else ``tracking``.
    """
    if d.relocalisation_candidates:
        return SEARCHING, (f"{d.relocalisation_candidates} relocalisation(s) held, none "
                           "agreed yet")
    if not d.initialized:
        return LOST, "no estimate"
    if not d.horizontal_sigma <= lost_sigma:
        return LOST, f"horizontal sigma {d.horizontal_sigma:.0f} m > {lost_sigma:.0f} m"
    found = d.found
    confirmed = max(d.last_accepted.get("fix", -math.inf), d.last_accepted.get("gnss", -math.inf))
    if found is not None and confirmed <= found.stamp:
        return FOUND, found.describe()
    return TRACKING, ""


class NavigationLog:
    """The navigation state's changes, each once (not every frame it holds)."""

    def __init__(self):
        self.state: str | None = None

    def change(self, state: str, detail: str) -> str | None:
        """The line to log when ``state`` differs from the previous one, else None."""
        if state == self.state:
            return None
        before, self.state = self.state, state
        came = "" if before is None else f" (was {before})"
        return f"navigation {state}{came}" + (f": {detail}" if detail else "")


def filter_health(d: EkfDiagnostics, since_imu: float, waiting_for: str,
                  limits: HealthLimits, refused_stamps: int = 0,
                  gated: int = 0, imu_problem: str | None = None,
                  failed: int = 0, baro_unused: str = "") -> Health:
    """The filter's level and problems.

    Parameters
    ----------
    d : EkfDiagnostics
    since_imu : float
        Wall time since the last IMU sample (or since start-up) (s).
    waiting_for : str
        What an uninitialised filter waits for (:meth:`~.ekf.TerrainEkf.waiting_for`).
    limits : HealthLimits
    refused_stamps : int
        IMU stamps refused since the previous report.
    gated : int
        Measurements the chi-square gate rejected since the previous report.
    imu_problem : str, optional
        Why the IMU stream is refused for good (:class:`~.ekf_inputs.ImuConvention`,
        :class:`~.ekf_inputs.GyroScale`).
    failed : int
        Messages whose callback raised since the previous report (the node logged them and
        went on).
    baro_unused : str
        Why the baro heights that arrived since the previous report were none of them used
        (:meth:`SourceUse.report`), or "".
    """
    health = Health()
    if failed:
        health.worse(ERROR, f"{failed} message(s) failed in a callback: see the log")
    if baro_unused:
        # the height then drifts with the accelerometers, the fixes hardly hold it
        health.worse(WARN, f"baro unused: {baro_unused}")
    if imu_problem:
        health.worse(ERROR, f"IMU refused: {imu_problem}")
    if since_imu > limits.imu_timeout:
        health.worse(ERROR, f"no IMU for {since_imu:.1f} s")
    if not d.initialized:
        health.worse(WARN, f"not initialised: waiting for {waiting_for}")
    since_fix = time_since_fix(d)
    if d.initialized:
        if since_fix is None:
            health.worse(WARN, "no fix accepted yet")
        elif since_fix > limits.fix_error:
            health.worse(ERROR, f"no accepted fix for {since_fix:.0f} s")
        elif since_fix > limits.fix_warn:
            health.worse(WARN, f"no accepted fix for {since_fix:.0f} s")
        if d.position_sigma > limits.sigma_error:
            health.worse(ERROR, f"position sigma {d.position_sigma:.0f} m")
        elif d.position_sigma > limits.sigma_warn:
            health.worse(WARN, f"position sigma {d.position_sigma:.0f} m")
    if refused_stamps:
        health.worse(WARN, f"{refused_stamps} IMU stamp(s) far from the expected period refused")
    if gated:
        health.worse(WARN, f"{gated} measurement(s) rejected by the gate")
    if d.heading_disputes:
        health.worse(WARN, f"the fixes' heading never agreed with the filter's ("
                     f"{d.heading_disputes} drift(s) not followed): check the camera mount's "
                     "yaw (mount_rpy) and the image's orientation")
    if d.heights_left_out_in_a_row >= HEIGHTS_LEFT_OUT_WARN:
        health.worse(WARN, f"the fixes' heights disagree with the filter's beyond the camera "
                     f"scale error's prior ({d.heights_left_out_in_a_row} in a row fused "
                     "without them): check the CameraInfo's focal length")
    if d.relocalisation_candidates:
        health.worse(WARN, f"searching: {d.relocalisation_candidates} relocalisation(s) held, "
                     "none agreed yet")
    return health


class SourceUse:
    """Whether a sensor's messages are used: counted between reports, with the last reason
    one was not. A stream that arrives and is refused whole (a baro in kPa, on another
    clock, or never given its offset) must be said, not only counted."""

    def __init__(self):
        self._arrived = self._used = 0
        self._why = ""

    def arrived(self) -> None:
        self._arrived += 1

    def used(self) -> None:
        self._used += 1

    def refused(self, why: str) -> None:
        self._why = why

    def report(self) -> str:
        """Why none of the messages since the last report was used ("" if some were, or
        none arrived); starts the next period."""
        text = "" if not self._arrived or self._used else \
            f"none of {self._arrived} since the last report ({self._why})"
        self._arrived = self._used = 0
        return text


def gated_records(records, fuse_gnss: bool) -> list:
    """The records the chi-square gate rejected (GNSS only when it is fused)."""
    return [r for r in records if not r.accepted and r.nis > r.gate
            and (r.source != "gnss" or fuse_gnss)]


def filter_values(d: EkfDiagnostics, init_mode: str, imu_received: int, imu_dt: float,
                  no_fix_messages: int, baro_offset: float | None, origin,
                  node_rejections: Counter) -> dict:
    """The filter report's key-value pairs (``rejected_input/<source>:<reason>`` counts the
    core's and the node's refusals together)."""
    since_fix = time_since_fix(d)
    rejections = Counter(d.input_rejections)
    rejections.update(node_rejections)
    values = {
        "initialized": d.initialized, "init_mode": init_mode,
        "filter_time": "nan" if d.stamp is None else f"{d.stamp:.3f}",
        "time_since_last_fix": float("nan") if since_fix is None else since_fix,
        "position_sigma_m": d.position_sigma, "covariance_trace": d.covariance_trace,
        "wind_east_m_s": d.wind[0], "wind_north_m_s": d.wind[1],
        "wind_sigma_m_s": d.wind_sigma, "height_sigma_m": d.height_sigma,
        "baro_bias_m": d.baro_bias, "baro_bias_sigma_m": d.baro_bias_sigma,
        "camera_mount_roll_deg": math.degrees(d.camera_mount[0]),
        "camera_mount_pitch_deg": math.degrees(d.camera_mount[1]),
        "camera_mount_sigma_deg": math.degrees(d.camera_mount_sigma),
        "camera_scale_percent": 100.0 * d.camera_scale,
        "camera_scale_sigma_percent": 100.0 * d.camera_scale_sigma,
        "map_bias_east_m": d.map_bias[0], "map_bias_north_m": d.map_bias[1],
        "map_bias_sigma_m": d.map_bias_sigma,
        "fix_heights_left_out": d.heights_left_out,
        "resets": d.resets, "reinitialisations": d.reinitialisations,
        "imu_stamps_refused": d.imu_stamps_refused,
        "position_resets": d.position_resets, "imu_gaps": d.imu_gaps,
        "relocalisation_resets": d.relocalisation_resets,
        "baro_steps": d.baro_steps, "baro_step_m": d.baro_step, "tilt_drifts": d.tilt_drifts,
        "heading_drifts": d.heading_drifts,
        "heading_disputes": d.heading_disputes,
        "relocalisation_candidates": d.relocalisation_candidates,
        "found": "never" if d.found is None else d.found.describe(),
        "imu_received": imu_received, "imu_rate_hz": 1.0 / imu_dt,
        "no_fix_messages": no_fix_messages,
        "baro_offset_m": float("nan") if baro_offset is None else baro_offset,
        "enu_origin": "unknown" if origin is None else
        f"{origin.lat:.7f},{origin.lon:.7f},{origin.alt:.2f}",
    }
    values.update({f"rejected_input/{k}": v for k, v in sorted(rejections.items())})
    return values


def source_report(d: EkfDiagnostics, source: str, new) -> tuple[str, dict]:
    """One measurement source's message and key-value pairs: its counts, last and mean NIS
    over the records kept, and the NIS of the records ``new`` since the previous report
    (``!`` marks a rejected one)."""
    recs = [r for r in d.records if r.source == source]
    mine = [r for r in new if r.source == source]
    last = recs[-1] if recs else None
    return f"{len(mine)} update(s) since the last report", {
        "accepted": d.accepted[source], "rejected": d.rejected[source],
        "last_nis": last.nis if last else float("nan"),
        "gate": last.gate if last else float("nan"),
        "dof": last.dim if last else 0,
        "mean_nis": float(np.mean([r.nis for r in recs])) if recs else float("nan"),
        "nis": " ".join(f"{r.nis:.3g}{'' if r.accepted else '!'}" for r in mine),
        "last_accepted_stamp": f"{d.last_accepted.get(source, math.nan):.3f}",
    }


class NewRecords:
    """The filter's NIS records appended since the previous call (by identity: the record
    list is a bounded deque)."""

    def __init__(self):
        self._last = None

    def __call__(self, records) -> list:
        new = []
        for r in reversed(records):
            if r is self._last:
                break
            new.append(r)
        if records:
            self._last = records[-1]
        return new[::-1]


class RefusalLog:
    """Refusal logs at most once per ``period`` s per key, saying how many were skipped.

    Parameters
    ----------
    period : float
        Minimum time between two logs of one key (s).
    """

    def __init__(self, period: float):
        self.period = period
        self._last: dict[str, float] = {}
        self._suppressed: Counter = Counter()

    def text(self, key: str, text: str, now: float) -> str | None:
        """The line to log for ``key`` at ``now``, or None while it is throttled."""
        last = self._last.get(key)
        if last is not None and now - last < self.period:
            self._suppressed[key] += 1
            return None
        skipped = self._suppressed.pop(key, 0)
        self._last[key] = now
        return text + (f" ({skipped} more since the last report)" if skipped else "")
