"""The filter's state kept on disk, so that a restarted ekf resumes where it left off.

A navigation process can die in flight (a crash, the out-of-memory killer) and be started
again by its supervisor. Started afresh, the filter would begin again from its
``init_mode`` source: with GNSS denied, none, or for ``init_mode: pose`` the take-off pose,
a wrong estimate. The ekf node therefore writes its state a few times a second
(:func:`save_checkpoint`: atomically, so a reader never sees half a file), and a restarted
node that finds a recent one resumes from it (:func:`resume_from`).

Nothing is measured while the process is down, so the state is carried across the gap at
constant velocity, and the covariance grows by what a manoeuvre in the gap could have
changed: an acceleration of :data:`GAP_ACCEL_SIGMA` and a body rate of
:data:`GAP_RATE_SIGMA`, each held for the whole gap (a fixed wing entering a turn). The
biases and the wind are kept. The first fixes and levellings then correct the guess.
"""

from __future__ import annotations

import math
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..terrain.geodesy import EnuOrigin
from .ekf import DIM_STATE, NavState
from .strapdown import IDX_P, IDX_V

__all__ = ["Checkpoint", "CheckpointError", "save_checkpoint", "load_checkpoint",
           "resume_from", "checkpoint_path", "GAP_ACCEL_SIGMA", "GAP_RATE_SIGMA",
           "RUN_DIR_VARIABLE"]

# The folder a graph's nodes share for one run (the graph runner's log folder, or a fresh
# one the runner or the launch file makes): the default home of the ekf's checkpoint, so
# that a node resumes only from its own run's.
RUN_DIR_VARIABLE = "TERRAIN_NAV_RUN_DIR"
CHECKPOINT_NAME = "ekf_checkpoint.npz"

# What the aircraft may do while the filter is down: a 17 deg bank's acceleration, and a
# roll into it or the turn it makes (m/s^2, rad/s).
GAP_ACCEL_SIGMA = 3.0
GAP_RATE_SIGMA = 0.1

_VECTORS = {"position": 3, "velocity": 3, "quaternion": 4, "gyro_bias": 3, "accel_bias": 3,
            "wind": 2, "baro_bias": 1, "camera_mount": 2, "camera_scale": 1, "map_bias": 2}


class CheckpointError(ValueError):
    """A checkpoint that cannot be read or used, with the reason."""


@dataclass(frozen=True)
class Checkpoint:
    """A saved estimate and what the node needs with it.

    Attributes
    ----------
    state : NavState
        The estimate at ``state.stamp``.
    origin : EnuOrigin or None
        The ENU origin it is expressed in (its latitude, longitude and height are kept).
    baro_offset : float or None
        ENU up minus pressure altitude (m), once learnt.
    """

    state: NavState
    origin: EnuOrigin | None = None
    baro_offset: float | None = None


def save_checkpoint(path, checkpoint: Checkpoint) -> None:
    """Write ``checkpoint`` to ``path`` (``.npz``), replacing the previous one atomically."""
    path = Path(path)
    s, o = checkpoint.state, checkpoint.origin
    arrays = {name: np.asarray(getattr(s, name), float) for name in _VECTORS}
    arrays.update(stamp=np.float64(s.stamp), covariance=np.asarray(s.covariance, float),
                  origin=np.asarray([o.lat, o.lon, o.alt] if o else [], float),
                  baro_offset=np.asarray([] if checkpoint.baro_offset is None
                                         else [checkpoint.baro_offset], float))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)


def load_checkpoint(path) -> Checkpoint:
    """Read a checkpoint; raises :class:`CheckpointError` naming what is wrong with it."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: np.array(data[key], float) for key in data.files}
    except FileNotFoundError:
        raise CheckpointError(f"no checkpoint at {path}") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise CheckpointError(f"{path.name} is not a readable checkpoint: {err}") from None
    expected = {**_VECTORS, "stamp": 1, "covariance": DIM_STATE * DIM_STATE}
    for name, size in expected.items():
        if name not in arrays or arrays[name].size != size:
            raise CheckpointError(f"{path.name}: '{name}' missing or of the wrong size")
        if not np.isfinite(arrays[name]).all():
            raise CheckpointError(f"{path.name}: '{name}' is not finite")
    origin, offset = arrays.get("origin", np.empty(0)), arrays.get("baro_offset", np.empty(0))
    try:
        origin = EnuOrigin(*origin) if origin.size == 3 else None
    except ValueError as err:
        raise CheckpointError(f"{path.name}: {err}") from None
    state = NavState(float(arrays["stamp"]), *(arrays[name] for name in
                                               ("position", "velocity", "quaternion",
                                                "gyro_bias", "accel_bias")),
                     arrays["covariance"].reshape(DIM_STATE, DIM_STATE), arrays["wind"],
                     float(arrays["baro_bias"].ravel()[0]), arrays["camera_mount"],
                     float(arrays["camera_scale"].ravel()[0]), arrays["map_bias"])
    return Checkpoint(state, origin, float(offset[0]) if offset.size == 1 else None)


def resume_from(checkpoint: Checkpoint, stamp: float, max_age: float) -> NavState:
    """The checkpoint's state carried to ``stamp`` across the gap (module docstring).

    Raises :class:`CheckpointError` when the checkpoint is more than ``max_age`` s old at
    ``stamp``, or newer than it (another run's, or a clock that went back).
    """
    s = checkpoint.state
    gap = stamp - s.stamp
    if not 0.0 <= gap <= max_age:
        raise CheckpointError(
            f"the checkpoint is {gap:.1f} s old at the first IMU sample (resumed only within "
            f"0-{max_age:g} s): " + ("stale" if gap > 0 else "from a later time"))
    transition = np.eye(DIM_STATE)
    transition[IDX_P, IDX_V] = gap * np.eye(3)
    grown = transition @ s.covariance @ transition.T
    accel_spread = GAP_ACCEL_SIGMA * np.r_[[0.5 * gap * gap] * 3, [gap] * 3]
    grown[:6, :6] += np.diag(accel_spread ** 2)
    grown[6:9, 6:9] += np.eye(3) * (GAP_RATE_SIGMA * gap) ** 2
    grown[8, 8] = min(grown[8, 8], math.pi ** 2)
    return NavState(stamp, s.position + gap * s.velocity, s.velocity.copy(),
                    s.quaternion.copy(), s.gyro_bias.copy(), s.accel_bias.copy(),
                    0.5 * (grown + grown.T), s.wind.copy(), s.baro_bias,
                    s.camera_mount.copy(), s.camera_scale, s.map_bias.copy())


def checkpoint_path(setting: str, environ=None) -> Path | None:
    """Where the ekf keeps its checkpoint: ``setting`` if given, "none" for nowhere, else
    :data:`CHECKPOINT_NAME` in the run folder named by :data:`RUN_DIR_VARIABLE` (None
    outside a graph run)."""
    if setting == "none":
        return None
    if setting:
        return Path(setting)
    run_dir = (os.environ if environ is None else environ).get(RUN_DIR_VARIABLE)
    return Path(run_dir) / CHECKPOINT_NAME if run_dir else None
