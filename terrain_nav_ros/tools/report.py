"""What a replay achieved: fix and fused errors against the truth, dead reckoning, latency, load.

:func:`analyse` reads the bag that was played (sensors and, for simulated flights,
``/ground_truth/odometry`` plus ``mission.yaml``) and the bag recorded from the graph
(``/nav/odometry``, ``/nav/pva_fix`` and the intermediate topics), and returns plain numbers;
:func:`format_report` prints them and :func:`plot` draws the trajectory over the hillshaded DEM
and the error against time with the filter's 3-sigma bound.

IMU-only dead reckoning is the same filter core (:class:`~.core.estimation.ekf.TerrainEkf`) fed the
same IMU, barometer and pre-denial GNSS, but no terrain fixes: the drift the terrain fixes remove.
"""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

import numpy as np
import yaml

from ..core.estimation.baro import pressure_to_altitude
from ..core.estimation.ekf import TerrainEkf
from ..core.estimation.ekf_params import EkfParams
from ..core.matching.pva_fix import reason_kind
from ..core.terrain.geodesy import EnuOrigin
from . import bags

STAGE_TOPICS = ("/camera/image_ground", "/camera/minutiae", "/nav/pva_fix")
CAMERA_TOPICS = ("/camera/image_raw", "/camera/image_raw/compressed")   # in the input bag


def _stamp(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def read_mission(bag: Path) -> dict:
    """The simulator's mission.yaml beside the bag, or {} for bags recorded elsewhere."""
    path = Path(bag) / "mission.yaml"
    return yaml.safe_load(path.read_text()) if path.is_file() else {}


def plain(value):
    """Nested dicts/lists/tuples of numpy or Python scalars -> what yaml.safe_dump takes
    (NaN becomes null)."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and math.isnan(value):
        return None
    return value


def _series(bag, topic):
    """(stamps, positions, (horizontal covariance trace, height variance)) of an Odometry
    topic."""
    t, p, var = [], [], []
    for m in bags.read(bag, [topic]):
        msg = bags.decode(m)
        pos = msg.pose.pose.position
        t.append(_stamp(msg))
        p.append((pos.x, pos.y, pos.z))
        cov = np.asarray(msg.pose.covariance).reshape(6, 6)
        var.append((max(cov[0, 0], 0.0) + max(cov[1, 1], 0.0), max(cov[2, 2], 0.0)))
    return np.array(t), np.array(p).reshape(-1, 3), np.array(var).reshape(-1, 2)


def _fixes(bag):
    out = []
    for m in bags.read(bag, ["/nav/pva_fix"]):
        msg = bags.decode(m)
        p = msg.pose.pose.position
        cov = np.asarray(msg.pose.covariance).reshape(6, 6)
        out.append({"stamp": _stamp(msg), "received": m.timestamp_ns * 1e-9,
                    "status": int(msg.status), "reason": msg.reason,
                    "relocalisation": bool(msg.relocalisation),
                    "position": np.array([p.x, p.y, p.z]), "cov_xy": cov[:2, :2],
                    "pairings": int(msg.num_pairings), "similarity": float(msg.similarity)})
    return out


def _ekf_health(bag) -> str:
    """The EKF's last word on its health (its /nav/ekf/diagnostics filter status)."""
    last = ""
    for m in bags.read(bag, ["/nav/ekf/diagnostics"]):
        for status in bags.decode(m).status:
            if status.name == "ekf: filter":
                last = status.message
    return last or "it published no diagnostics either"


def ekf_fix_use(bag) -> dict | None:
    """What the EKF did with the matcher's fixes, from its last diagnostics: fused, rejected
    by its gate, refused before it (by reason), its last health (level, message) and its
    map bias (east, north, horizontal sigma m). None without diagnostics."""
    last = None
    for m in bags.read(bag, ["/nav/ekf/diagnostics"]):
        last = bags.decode(m)
    if last is None:
        return None
    use = {"fused": 0, "gated": 0, "refused": {}, "level": 0, "health": "",
           "without_height": 0}
    for status in last.status:
        values = {kv.key: kv.value for kv in status.values}
        if status.name == "ekf: filter":
            # (the replay's end stops the IMU: not a health problem of the flight)
            use["level"] = int(status.level)
            use["health"] = "; ".join(part for part in status.message.split("; ")
                                      if not part.startswith("no IMU for "))
            use["refused"] = {k.split(":", 1)[1]: int(v) for k, v in values.items()
                              if k.startswith("rejected_input/fix:")
                              and not k.endswith(":not_initialized")}
            use["without_height"] = int(values.get("fix_heights_left_out", 0))
            if "map_bias_east_m" in values:
                use["map_bias"] = [float(values[f"map_bias_{k}_m"])
                                   for k in ("east", "north", "sigma")]
        elif status.name == "ekf: fix":
            use["fused"] = int(values.get("accepted", 0))
            use["gated"] = int(values.get("rejected", 0))
    return use


def _odometry_stopped(input_bag, odometry_end: float, grace: float = 5.0) -> dict | None:
    """Where the fused odometry ended more than ``grace`` s before the bag's IMU did (an
    IMU refused mid-flight): that stamp and the IMU's last, in s from the IMU's first."""
    first = last = None
    for m in bags.read(input_bag, ["/imu/data"]):
        first = m.timestamp_ns if first is None else first
        last = m.timestamp_ns
    if last is None or last * 1e-9 - odometry_end <= grace:
        return None
    return {"at": odometry_end - first * 1e-9, "imu_end": (last - first) * 1e-9}


def navigation_events(bag) -> list[str]:
    """What the EKF's diagnostics said it found, in order: each reset onto (or start from)
    agreeing relocalisations, once (the ``found`` value of its ``ekf: filter`` status)."""
    events = []
    for m in bags.read(bag, ["/nav/ekf/diagnostics"]):
        for status in bags.decode(m).status:
            if status.name != "ekf: filter":
                continue
            found = {kv.key: kv.value for kv in status.values}.get("found", "never")
            if found != "never" and (not events or events[-1] != found):
                events.append(found)
    return events


def frames_received(bag) -> int | None:
    """Camera frames that reached camera_ingest, from its diagnostics' ``frames_received``
    (summed over its lives when it restarted); None without those diagnostics."""
    total = last = None
    for m in bags.read(bag, ["/camera_ingest/diagnostics"]):
        for status in bags.decode(m).status:
            value = {kv.key: kv.value for kv in status.values}.get("frames_received")
            if value is None or not value.isdigit():
                continue
            n = int(value)
            if total is None:
                total = 0
            elif n < last:   # a new life of the node: its count started again
                total += last
            last = n
    return None if total is None else total + last


def _latencies(bag) -> dict:
    """Receive time minus the camera frame's stamp for each pipeline stage (s)."""
    out = {}
    for topic in STAGE_TOPICS:
        lat = [m.timestamp_ns * 1e-9 - _stamp(bags.decode(m)) for m in bags.read(bag, [topic])]
        if lat:
            out[topic] = np.array(lat)
    return out


def dead_reckoning(bag, origin: EnuOrigin, denied_after: float, t0: float):
    """IMU(+baro, +GNSS before denial) navigation with the filter core; (t, positions)."""
    ekf = TerrainEkf(EkfParams(init_mode="gnss"))
    gnss_up = baro_offset = None
    t_out, p_out = [], []
    for m in bags.read(bag, ["/imu/data", "/gnss/fix", "/baro/pressure"]):
        msg = bags.decode(m)
        stamp = _stamp(msg)
        if m.topic == "/imu/data":
            w, a = msg.angular_velocity, msg.linear_acceleration
            ekf.process_imu(stamp, (w.x, w.y, w.z), (a.x, a.y, a.z))
            if ekf.initialized and (not t_out or stamp - t_out[-1] >= 0.1):
                t_out.append(stamp)
                p_out.append(ekf.state.position.copy())
        elif m.topic == "/gnss/fix":
            if stamp - t0 >= denied_after or msg.status.status < 0 or \
                    not math.isfinite(msg.latitude):
                continue
            e, n, u = origin.geodetic_to_enu(msg.latitude, msg.longitude, msg.altitude)
            cov = np.asarray(msg.position_covariance, float).reshape(3, 3)
            ekf.process_gnss(stamp, [float(e), float(n), float(u)], cov)
            gnss_up = float(u)
        else:
            altitude = float(pressure_to_altitude(msg.fluid_pressure))
            if baro_offset is None and gnss_up is not None and ekf.initialized:
                baro_offset = gnss_up - altitude  # align the baro to the GNSS height once
            if baro_offset is not None:
                ekf.process_baro(stamp, altitude + baro_offset, 4.0)
    return np.array(t_out), np.array(p_out).reshape(-1, 3)


def _position_errors(t_est, p_est, t_truth, p_truth):
    """Horizontal and height errors of an estimate at the truth stamps it covers, with
    those stamps."""
    inside = (t_truth >= t_est[0]) & (t_truth <= t_est[-1]) if len(t_est) else \
        np.zeros(len(t_truth), bool)
    e, n, u = (np.interp(t_truth[inside], t_est, p_est[:, k]) - p_truth[inside, k]
               for k in range(3))
    return t_truth[inside], np.hypot(e, n), np.abs(u)


def settled_after(t: np.ndarray, err: np.ndarray, bound: float) -> float:
    """The time from which ``err`` stays at or below ``bound`` to the end (the first
    sample's time if it always does; NaN if the last sample is above)."""
    above = np.flatnonzero(np.asarray(err) > bound)
    if not len(above):
        return float(t[0]) if len(t) else math.nan
    return float(t[above[-1] + 1]) if above[-1] + 1 < len(t) else math.nan


def analyse(input_bag, output_bag, usage: dict | None = None,
            denied_after: float | None = None) -> dict:
    """Metrics of one replay (plain numbers and arrays for the plots). ``denied_after``
    (s from the start) overrides the bag's GNSS denial, e.g. 0 when the replay left the
    GNSS out."""
    mission = read_mission(input_bag)
    info = {t.topic: t for t in bags.topics(input_bag)}
    result: dict = {"input_bag": str(input_bag), "output_bag": str(output_bag),
                    "usage": usage or {}}
    fixes = _fixes(output_bag)
    good = [f for f in fixes if f["status"] > 0]
    result["fixes"] = {"frames": len(fixes), "fixes": len(good),
                       "no_fix": len(fixes) - len(good),
                       "relocalisations": sum(f["relocalisation"] for f in good),
                       "in_bag": sum(info[t].count for t in CAMERA_TOPICS if t in info),
                       "received": frames_received(output_bag),
                       "lost_on_the_way": None,
                       "reasons": Counter(reason_kind(f["reason"]) for f in fixes
                                          if f["status"] == 0).most_common(6)}
    received = result["fixes"]["received"]
    if received is not None:   # frames of the bag that never reached camera_ingest
        result["fixes"]["lost_on_the_way"] = max(result["fixes"]["in_bag"] - received, 0)
    if len(fixes) < result["fixes"]["in_bag"]:   # where, to tell a start from a stall
        result["fixes"]["unanswered_at"] = unanswered_at(input_bag, [f["stamp"] for f in fixes])
    result["navigation_events"] = navigation_events(output_bag)
    result["ekf_fix_use"] = ekf_fix_use(output_bag)
    result["latency"] = {k: v for k, v in _latencies(output_bag).items()}
    t_fused, p_fused, var_fused = _series(output_bag, "/nav/odometry")
    result["series"] = {"fused": (t_fused, p_fused, var_fused), "fixes": good}
    if not len(t_fused):   # say why, or the report only shows empty sections
        result["no_odometry"] = _ekf_health(output_bag)
    elif (stopped := _odometry_stopped(input_bag, t_fused[-1])) is not None:
        result["odometry_stopped"] = {**stopped, "why": _ekf_health(output_bag)}
    if "/ground_truth/odometry" not in info:
        result["truth"] = None
        return result
    t_truth, p_truth, _ = _series(input_bag, "/ground_truth/odometry")
    t0 = t_truth[0]
    denied = float(mission.get("gnss_denied_after_s", 0.0) if denied_after is None
                   else denied_after)
    result["truth"] = (t_truth, p_truth)
    result["t0"], result["denied_after"] = t0, denied
    if good:
        t_fix = np.array([f["stamp"] for f in good])
        p_fix = np.array([f["position"] for f in good])
        idx = np.clip(np.searchsorted(t_truth, t_fix), 0, len(t_truth) - 1)
        offset = p_fix[:, :2] - p_truth[idx, :2]
        err = np.hypot(*offset.T)
        sigma = np.sqrt([max(np.trace(f["cov_xy"]), 0.0) for f in good])
        nees = normalised_errors(offset, np.array([f["cov_xy"] for f in good]))
        result["fixes"]["first_after"] = float(t_fix.min() - t0)
        result["fix_error"] = {"median": float(np.median(err)),
                               "p95": float(np.percentile(err, 95)),
                               "max": float(err.max()),
                               "within_3_sigma": float(np.mean(err <= 3 * sigma)),
                               "nees_mean": _mean_or_nan(nees),
                               "nees_median": float(np.median(nees)) if len(nees) else math.nan}
    window = t_truth - t0 >= denied
    if len(t_fused):
        te, err, up = _position_errors(t_fused, p_fused, t_truth[window], p_truth[window])
        # consistency: the share of the errors within 3 of the covariance's sigmas
        sigma = np.sqrt([np.interp(te, t_fused, v) for v in var_fused.T]).reshape(2, -1)
        result["fused_error"] = {**_stats(err), "within_3_sigma": _within(err, sigma[0])}
        result["fused_height_error"] = {**_stats(up), "within_3_sigma": _within(up, sigma[1])}
        if len(te):
            result["fused_error"]["first_after"] = float(te[0] - t0)
        if mission.get("landmark_gsd") and len(te):
            bound = 2.0 * float(mission["landmark_gsd"])
            result["fused_error"]["below_2_gsd_after"] = settled_after(te - t0, err, bound)
            reached = np.flatnonzero(err <= bound)
            result["fused_error"]["first_below_2_gsd_after"] = \
                float(te[reached[0]] - t0) if len(reached) else math.nan
        result["series"]["fused_error"] = (te - t0, err, 3 * sigma[0])
    origin = mission.get("origin")
    if origin:
        t_dr, p_dr = dead_reckoning(input_bag, EnuOrigin(*origin), denied, t0)
        if len(t_dr):
            te, err, _ = _position_errors(t_dr, p_dr, t_truth[window], p_truth[window])
            result["dr_error"] = _stats(err)
            result["series"]["dr"] = (t_dr, p_dr)
            result["series"]["dr_error"] = (te - t0, err)
    return result


def unanswered_at(input_bag, answered_stamps, limit: int = 10) -> list[float]:
    """Seconds after the bag's first camera frame of its frames (the first ``limit``) that
    no /nav/pva_fix answered: the first frames (a recorder or a graph not yet listening),
    a stretch (a stall) or the last (a graph stopped before it caught up)."""
    answered = {round(t, 3) for t in answered_stamps}
    stamps = [_stamp(bags.decode(m)) for m in bags.read(input_bag, list(CAMERA_TOPICS))]
    if not stamps:
        return []
    t0 = min(stamps)
    return [round(t - t0, 2) for t in sorted(stamps) if round(t, 3) not in answered][:limit]


def normalised_errors(offset: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """NEES ``e^T P^-1 e`` of 2-D errors ``offset`` (n, 2) under their covariances (n, 2, 2),
    for those whose covariance is finite and positive definite. Consistent covariances give
    a chi-square with 2 degrees of freedom: mean 2, median 1.39; far below, the covariances
    are too wide (the filter under-weighs the fixes), far above, too narrow."""
    offset, covariance = np.asarray(offset, float), np.asarray(covariance, float)
    if not len(offset):
        return np.empty(0)
    usable = np.isfinite(covariance).all(axis=(1, 2)) & (covariance[:, 0, 0] > 0) & \
        (np.linalg.det(np.nan_to_num(covariance)) > 0)
    e, p = offset[usable], covariance[usable]
    return np.einsum("ni,ni->n", e, np.linalg.solve(p, e[..., None])[..., 0])


def _mean_or_nan(values: np.ndarray) -> float:
    return float(np.mean(values)) if len(values) else math.nan


def _within(err: np.ndarray, sigma: np.ndarray) -> float:
    return float(np.mean(err <= 3.0 * sigma)) if len(err) else math.nan


def _stats(err: np.ndarray) -> dict:
    if not len(err):
        return {"rms": math.nan, "max": math.nan, "final": math.nan, "samples": 0}
    return {"rms": float(np.sqrt(np.mean(err ** 2))), "max": float(err.max()),
            "final": float(err[-1]), "samples": int(len(err))}


def _consistency(stats: dict) -> str:
    within = stats.get("within_3_sigma", math.nan)
    return "" if math.isnan(within) else f"; within 3 sigma {100 * within:.0f}%"


def format_report(r: dict, gsd: float | None = None) -> str:
    """Human-readable summary of :func:`analyse`'s result."""
    lines = ["", "terrain_nav replay report", "=" * 25,
             f"input bag:  {r['input_bag']}", f"output bag: {r['output_bag']}"]
    if r.get("no_odometry"):
        lines.append(f"NO ODOMETRY: the EKF published none; its last diagnostics: "
                     f"{r['no_odometry']}")
    if r.get("odometry_stopped"):
        s = r["odometry_stopped"]
        lines.append(f"ODOMETRY STOPPED at {s['at']:.1f} s of the IMU's {s['imu_end']:.1f} s; "
                     f"the EKF's last diagnostics: {s['why']}")
    f = r["fixes"]
    lines.append(f"camera frames answered: {f['frames']} of {f['in_bag']}  fixes: "
                 f"{f['fixes']}  no fix: {f['no_fix']}")
    if f.get("relocalisations"):
        lines.append(f"  of the fixes, {f['relocalisations']} relocalisation(s) (searched over "
                     "the whole mission area)")
    if f["in_bag"] and f["frames"] < f["in_bag"]:
        respawned = sorted(n for n, u in (r.get("usage") or {}).items() if u.get("respawns"))
        lost = f.get("lost_on_the_way")
        if respawned:
            why = f"died with {', '.join(respawned)} or came while it restarted"
        elif lost is None:
            why = "lost on the way to camera_ingest, or the graph fell behind"
        else:
            why = (f"{lost} never reached camera_ingest (lost on the way), "
                   f"{max(f['received'] - f['frames'], 0)} reached it and fell behind")
        at = f.get("unanswered_at")
        where = f"; at {', '.join(f'{t:g}' for t in at)} s after the first" if at else ""
        lines.append(f"WARNING: {f['in_bag'] - f['frames']} camera frames of the bag got no "
                     f"answer ({why}{where})")
    for reason, count in f["reasons"]:
        lines.append(f"  no fix x{count}: {reason}")
    if "first_after" in f:
        lines.append(f"  first fix {f['first_after']:.0f} s after the start")
    use = r.get("ekf_fix_use")
    if use is not None and f["fixes"]:
        refused = sum(use["refused"].values())
        without = use.get("without_height", 0)
        lines.append(f"  the ekf fused {use['fused']} of them"
                     + (f" ({without} without their height)" if without else "")
                     + f", its gate rejected {use['gated']}, it refused {refused}"
                     + "".join(f"; {n} {why}" for why, n in sorted(use["refused"].items())))
        if use.get("map_bias"):
            east, north, sigma = use["map_bias"]
            lines.append(f"  the map's offset as the ekf ended (where the fixes put the "
                         f"aircraft less where it is): {east:+.1f} m east, {north:+.1f} m "
                         f"north, sigma {sigma:.1f} m (horizontal)")
        if use["fused"] < f["fixes"] // 2:
            lines.append(f"WARNING: the ekf fused under half the fixes; its last health: "
                         f"{use['health'] or 'OK'}")
    for event in r.get("navigation_events", []):
        lines.append(f"ekf found: {event}")
    if "fix_error" in r:
        e = r["fix_error"]
        lines.append(f"fix error vs truth (horizontal): median {e['median']:.1f} m, p95 "
                     f"{e['p95']:.1f} m, max {e['max']:.1f} m; within 3 sigma "
                     f"{100 * e['within_3_sigma']:.0f}%")
        if math.isfinite(e.get("nees_mean", math.nan)):
            lines.append(f"  fix NEES mean {e['nees_mean']:.2f}, median {e['nees_median']:.2f} "
                         "(covariances true to the errors: 2 and 1.39; below, too wide)")
    if r.get("truth") is not None:
        lines.append(f"GPS denied after {r['denied_after']:.0f} s; over the denied part:")
        for key, label in (("fused_error", "fused (terrain + IMU)"),
                           ("dr_error", "IMU-only dead reckoning")):
            if key in r:
                e = r[key]
                extra = f" = {e['rms'] / gsd:.1f} GSD" if gsd and key == "fused_error" else ""
                lines.append(f"  {label:26s} RMS {e['rms']:8.1f} m{extra}, max {e['max']:8.1f} m,"
                             f" final {e['final']:8.1f} m" + _consistency(e))
                if key == "fused_error" and "fused_height_error" in r:
                    h = r["fused_height_error"]
                    lines.append(f"  {'fused height':26s} RMS {h['rms']:8.1f} m, max "
                                 f"{h['max']:8.1f} m, final {h['final']:8.1f} m"
                                 + _consistency(h))
                if key == "fused_error" and e.get("first_after", 0.0) > 1.0:
                    lines.append(f"  first estimate {e['first_after']:.0f} s after the start")
                if key == "fused_error" and "below_2_gsd_after" in e:
                    settled = e["below_2_gsd_after"]
                    lines.append(f"  fused error at or below 2 GSD from {settled:.0f} s "
                                 f"after the start on (first {e['first_below_2_gsd_after']:.0f}"
                                 " s after it)")
    else:
        lines.append("no /ground_truth/odometry in the input bag: errors not computed")
    if r["latency"]:
        lines.append("latency from camera frame stamp (p50 / p95):")
        for topic, lat in r["latency"].items():
            lines.append(f"  {topic:24s} {1e3 * np.median(lat):7.0f} ms / "
                         f"{1e3 * np.percentile(lat, 95):7.0f} ms")
    if r["usage"]:
        lines.append("per node: CPU (share of one core) / peak RSS:")
        for name, u in sorted(r["usage"].items()):
            wall = u.get("last", 0) - u.get("started", 0)
            share = f"{100 * u['cpu_s'] / wall:5.1f}%" if wall >= 1.0 else "  n/a"
            respawned = f" (died and respawned {u['respawns']}x)" if u.get("respawns") else ""
            lines.append(f"  {name:18s} {u['cpu_s']:7.1f} s CPU ({share})"
                         f" / {u['peak_rss_mb']:6.0f} MB{respawned}")
    return "\n".join(lines)


def plot(r: dict, out_dir: Path, background=None) -> list[Path]:
    """Trajectory and error plots as PNG files; ``background`` = (hillshade, extent)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    written = []
    s = r["series"]
    fig, ax = plt.subplots(figsize=(8, 8))
    if background is not None:
        ax.imshow(background[0], extent=background[1], cmap="gray", origin="upper", alpha=0.8)
    if r.get("truth") is not None:
        ax.plot(*r["truth"][1][:, :2].T, "k-", lw=1.5, label="truth")
    if "dr" in s:
        ax.plot(*s["dr"][1][:, :2].T, "r--", lw=1, label="IMU-only dead reckoning")
    t_f, p_f, _ = s["fused"]
    if len(t_f):
        ax.plot(*p_f[:, :2].T, "b-", lw=1, label="fused (EKF)")
    if s["fixes"]:
        p = np.array([f["position"] for f in s["fixes"]])
        ax.plot(p[:, 0], p[:, 1], "g+", ms=8, label="terrain fixes")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal")
    ax.legend(loc="best")
    ax.set_title("trajectory over the DEM (hillshade)")
    if r.get("truth") is not None:
        p = r["truth"][1]
        pad = 0.15 * max(np.ptp(p[:, 0]), np.ptp(p[:, 1]), 500.0)
        ax.set_xlim(p[:, 0].min() - pad, p[:, 0].max() + pad)
        ax.set_ylim(p[:, 1].min() - pad, p[:, 1].max() + pad)
    path = out_dir / "trajectory.png"
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    written.append(path)
    if "fused_error" in s:
        fig, ax = plt.subplots(figsize=(9, 4))
        te, err, bound = s["fused_error"]
        ax.plot(te, err, "b-", label="fused horizontal error")
        ax.plot(te, bound, "b:", label="fused 3-sigma bound")
        if "dr_error" in s:
            ax.plot(*s["dr_error"], "r--", label="IMU-only error")
        ax.set_yscale("log")
        ax.set_xlabel("time since start [s]")
        ax.set_ylabel("horizontal error [m]")
        ax.legend(loc="best")
        ax.set_title("error over the GPS-denied part")
        path = out_dir / "error.png"
        fig.savefig(path, dpi=110, bbox_inches="tight")
        plt.close(fig)
        written.append(path)
    return written
