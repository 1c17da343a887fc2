"""Benchmark of the EKF core: cost per IMU prediction and per measurement update.

Runs a simulated 200 Hz IMU (survey flight, ScanEagle-class MEMS defaults) through
:class:`terrain_nav_ros.core.estimation.ekf.TerrainEkf` and reports wall time per call and the
share of one core a 200 Hz IMU plus 0.5 Hz fixes and 10 Hz baro would use (target <= 10 %).

Usage::

    .venv/bin/python benchmarks/bench_ekf.py [--seconds 60] [--rate 200] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from terrain_nav_ros.core.estimation.ekf import EkfParams, TerrainEkf
from terrain_nav_ros.core.sim.imu_sim import ImuErrorModel, simulate_fixes, simulate_imu
from terrain_nav_ros.core.sim.trajectory_sim import simulate_trajectory, survey_flight


def _timed(fn, args_list):
    """Per-call wall times (s) of ``fn(*args)`` over ``args_list``."""
    out = np.empty(len(args_list))
    clock = time.perf_counter
    for i, args in enumerate(args_list):
        t0 = clock()
        fn(*args)
        out[i] = clock() - t0
    return out


def _summary(times):
    us = np.asarray(times) * 1e6
    return {"n": int(us.size), "mean_us": float(us.mean()), "median_us": float(np.median(us)),
            "p99_us": float(np.percentile(us, 99))}


def run(seconds: float, rate: float, seed: int = 0) -> dict:
    """Simulate and time; returns the figures as a dict."""
    params = EkfParams(init_mode="pose")
    rng = np.random.default_rng(seed)
    truth = simulate_trajectory(survey_flight(seconds, leg_s=min(60.0, seconds / 3)),
                                rate_hz=rate)
    imu = simulate_imu(truth, ImuErrorModel.from_params(params), rng)
    fixes = simulate_fixes(truth, rng, period=2.0, sigma=20.0,
                           attitude_sigma=np.deg2rad(1.0))
    ekf = TerrainEkf(params)
    ekf.initialize(0.0, truth.position[0], truth.velocity[0], truth.quaternion[0])

    # 1) IMU prediction alone (no measurement pending).
    n = len(truth)
    predict = _timed(ekf.process_imu,
                     [(truth.t[k], imu.gyro[k], imu.accel[k]) for k in range(1, n)])

    # 2) Updates at the current filter time, on a fresh filter fed the same IMU.
    ekf = TerrainEkf(params)
    ekf.initialize(0.0, truth.position[0], truth.velocity[0], truth.quaternion[0])
    fix_k = set(fixes.index.tolist())
    upd3, upd6, upd_baro, late = [], [], [], []
    pending_late = []
    lag = int(round(0.5 * rate))
    for k in range(1, n):
        ekf.process_imu(truth.t[k], imu.gyro[k], imu.accel[k])
        if k in fix_k:
            j = int(np.searchsorted(fixes.index, k))
            if j % 3 == 0:      # 3-D position fix on time
                upd3 += list(_timed(ekf.process_fix, [(fixes.t[j], fixes.position[j],
                                                       fixes.covariance[j][:3, :3])]))
            elif j % 3 == 1:    # position + attitude (PvaFix with attitude) on time
                upd6 += list(_timed(lambda *a: ekf.process_fix(*a[:3], quaternion=a[3]),
                                    [(fixes.t[j], fixes.position[j], fixes.covariance[j],
                                      fixes.attitude[j])]))
            else:               # 3-D fix arriving 0.5 s late: rewind and replay
                pending_late.append((k + lag, j))
        if pending_late and pending_late[0][0] == k:
            _, j = pending_late.pop(0)
            late += list(_timed(ekf.process_fix, [(fixes.t[j], fixes.position[j],
                                                   fixes.covariance[j][:3, :3])]))
        if k % int(rate / 10) == 0:
            upd_baro += list(_timed(ekf.process_baro,
                                    [(truth.t[k], truth.position[k, 2], 2.25)]))

    res = {
        "python": platform.python_version(), "machine": platform.processor() or
        platform.machine(), "imu_rate_hz": rate, "seconds": seconds,
        "predict": _summary(predict), "fix3": _summary(upd3), "fix6": _summary(upd6),
        "fix3_late_0p5s": _summary(late), "baro": _summary(upd_baro),
    }
    share = (res["predict"]["mean_us"] * 200.0 + res["fix6"]["mean_us"] * 0.5
             + res["baro"]["mean_us"] * 10.0) * 1e-6
    res["core_share_200hz"] = share
    share_late = (res["predict"]["mean_us"] * 200.0 + res["fix3_late_0p5s"]["mean_us"] * 0.5
                  + res["baro"]["mean_us"] * 10.0) * 1e-6
    res["core_share_200hz_late_fixes"] = share_late
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="simulated flight length (s)")
    ap.add_argument("--rate", type=float, default=200.0, help="IMU rate (Hz)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", help="also write the figures to this file")
    args = ap.parse_args(argv)
    res = run(args.seconds, args.rate, args.seed)
    print(f"EKF core benchmark: {args.seconds:.0f} s survey flight, IMU {args.rate:.0f} Hz, "
          f"Python {res['python']}")
    print(f"{'call':<34}{'n':>7}{'mean us':>10}{'median us':>11}{'p99 us':>10}")
    labels = {"predict": "IMU prediction (process_imu)",
              "fix3": "3-D position fix, on time",
              "fix6": "position + attitude fix, on time",
              "fix3_late_0p5s": "3-D fix 0.5 s late (rewind+replay)",
              "baro": "baro altitude"}
    for key, label in labels.items():
        s = res[key]
        print(f"{label:<34}{s['n']:>7}{s['mean_us']:>10.1f}{s['median_us']:>11.1f}"
              f"{s['p99_us']:>10.1f}")
    print(f"CPU share of one core, 200 Hz IMU + 0.5 Hz PvaFix + 10 Hz baro: "
          f"{100 * res['core_share_200hz']:.2f} % (target <= 10 %)")
    print(f"  same with every fix 0.5 s late: {100 * res['core_share_200hz_late_fixes']:.2f} %")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=2)


if __name__ == "__main__":
    main()
