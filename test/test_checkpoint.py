"""The filter's state on disk, for a restarted ekf (core.estimation.checkpoint)."""

import numpy as np
import pytest

from terrain_nav_ros.core.estimation.checkpoint import (
    GAP_ACCEL_SIGMA,
    Checkpoint,
    CheckpointError,
    load_checkpoint,
    resume_from,
    save_checkpoint,
)
from terrain_nav_ros.core.estimation.ekf import TerrainEkf
from terrain_nav_ros.core.estimation.ekf_params import EkfParams
from terrain_nav_ros.core.terrain.geodesy import EnuOrigin


def _running_filter():
    ekf = TerrainEkf(EkfParams())
    ekf.initialize(100.0, [10.0, 20.0, 3000.0], [30.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0],
                   baro_bias=2.0, camera_mount=[0.001, -0.002], camera_scale=0.003,
                   map_bias=[4.0, -3.0])
    for k in range(1, 101):   # 1 s of level flight
        ekf.process_imu(100.0 + 0.01 * k, (0.0, 0.0, 0.0), (0.0, 0.0, 9.80665))
    return ekf


def test_a_checkpoint_reads_back_as_written(tmp_path):
    state = _running_filter().state
    path = tmp_path / "ekf.npz"
    origin = EnuOrigin(36.5, -84.3, 300.0)
    save_checkpoint(path, Checkpoint(state, origin, -12.5))
    save_checkpoint(path, Checkpoint(state, origin, -12.5))   # replaced
    back = load_checkpoint(path)
    for name in ("position", "velocity", "quaternion", "gyro_bias", "accel_bias",
                 "covariance", "wind", "baro_bias", "camera_mount", "camera_scale",
                 "map_bias"):
        np.testing.assert_array_equal(getattr(back.state, name), getattr(state, name))
    assert back.state.stamp == state.stamp == pytest.approx(101.0)
    assert back.origin == origin and back.baro_offset == -12.5
    assert [p.name for p in tmp_path.iterdir()] == ["ekf.npz"]   # no temporary left
    save_checkpoint(path, Checkpoint(state))
    assert load_checkpoint(path).origin is None and load_checkpoint(path).baro_offset is None


def test_a_state_is_carried_across_the_gap_with_its_uncertainty_grown():
    state = _running_filter().state
    resumed = resume_from(Checkpoint(state), state.stamp + 3.0, max_age=10.0)
    np.testing.assert_allclose(resumed.position, state.position + 3.0 * state.velocity)
    assert resumed.stamp == state.stamp + 3.0
    grown = np.diag(resumed.covariance) - np.diag(state.covariance)
    # at least a held acceleration's spread over the gap, in position and velocity
    assert np.all(grown[:3] >= (GAP_ACCEL_SIGMA * 0.5 * 9.0) ** 2 * 0.999)
    assert np.all(grown[3:6] >= (GAP_ACCEL_SIGMA * 3.0) ** 2 * 0.999)
    assert np.all(grown[6:9] > 0) and np.all(grown[9:] == 0)   # biases and wind kept
    np.testing.assert_array_equal(resumed.quaternion, state.quaternion)
    np.testing.assert_array_equal(resumed.map_bias, [4.0, -3.0])   # the map did not move
    ekf = TerrainEkf(EkfParams())   # and a filter takes it
    assert ekf.initialize(resumed.stamp, resumed.position, resumed.velocity,
                          resumed.quaternion, resumed.covariance, resumed.gyro_bias,
                          resumed.accel_bias, resumed.wind).accepted


@pytest.mark.parametrize("gap, words", [(30.0, "stale"), (-5.0, "from a later time")])
def test_a_stale_or_later_checkpoint_is_not_resumed(gap, words):
    state = _running_filter().state
    with pytest.raises(CheckpointError, match=words):
        resume_from(Checkpoint(state), state.stamp + gap, max_age=10.0)


def test_a_damaged_checkpoint_is_a_clear_error(tmp_path):
    path = tmp_path / "ekf.npz"
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_checkpoint(path)
    save_checkpoint(path, Checkpoint(_running_filter().state))
    save_checkpoint(tmp_path / "good.npz", Checkpoint(_running_filter().state))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_checkpoint(path)
    np.savez(path, **{**dict(np.load(tmp_path / "good.npz")),
                      "position": np.array([np.nan, 0.0, 0.0])})
    with pytest.raises(CheckpointError, match="'position' is not finite"):
        load_checkpoint(path)
    np.savez(path, **{**dict(np.load(tmp_path / "good.npz")),
                      "origin": np.array([123.0, 0.0, 0.0])})   # no such latitude
    with pytest.raises(CheckpointError, match="latitude 123"):
        load_checkpoint(path)
