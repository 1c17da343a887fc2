"""The filter accepts relocalisations safely (issue 24): fused when they agree with the
estimate, held when they do not, a reset (or a cold start) only on two that agree with the IMU's
motion between them, and the navigation state that says so (core, no ROS)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_ekf import flight

from terrain_nav_ros.core.estimation.ekf import EkfParams, Reason, TerrainEkf
from terrain_nav_ros.core.estimation.ekf_health import (
    FOUND,
    LOST,
    SEARCHING,
    TRACKING,
    NavigationLog,
    navigation_state,
)
from terrain_nav_ros.core.estimation.relocalisation import dead_reckoning_covariance
from terrain_nav_ros.core.sim.trajectory_sim import straight_flight

KIDNAP = np.array([5000.0, 0.0, 0.0])   # the estimate is this far off the truth
SIGMA = 20.0                            # relocalisation position sigma (m)
COV = np.eye(3) * SIGMA**2
LOST_SIGMA = 1000.0


@pytest.fixture(scope="module")
def straight():
    """60 s straight and level at 30 m/s (100 Hz IMU with the default MEMS errors)."""
    params = EkfParams(init_mode="pose")
    rng, truth, imu = flight(straight_flight(60.0), 24, params)
    return rng, truth, imu


class Flight:
    """A filter flown along the truth; ``fly_to(t)`` integrates the IMU up to ``t``."""

    def __init__(self, straight, params: EkfParams, offset=KIDNAP, start: bool = True):
        self.rng, self.truth, self.imu = straight
        self.ekf = TerrainEkf(params)
        self.k = 0
        if start:
            t = self.truth
            self.ekf.initialize(t.t[0], t.position[0] + offset, t.velocity[0],
                                t.quaternion[0])

    def fly_to(self, seconds: float):
        t, imu = self.truth, self.imu
        while self.k + 1 < len(t) and t.t[self.k + 1] <= seconds + 1e-9:
            self.k += 1
            self.ekf.process_imu(t.t[self.k], imu.gyro[self.k], imu.accel[self.k])

    def truth_at(self, seconds: float) -> np.ndarray:
        return self.truth.position[int(self.truth.at(seconds))]

    def fix(self, seconds: float, shift=(0.0, 0.0, 0.0), relocalisation: bool = True,
            noise: bool = True):
        """A fix at the truth (+ ``shift``) at ``seconds``, after flying there."""
        self.fly_to(seconds)
        position = self.truth_at(seconds) + shift
        if noise:
            position = position + self.rng.normal(0.0, SIGMA / 2, 3)
        return self.ekf.process_fix(self.truth.t[int(self.truth.at(seconds))], position, COV,
                                    relocalisation=relocalisation)

    @property
    def error(self) -> float:
        return float(np.linalg.norm(self.ekf.state.position - self.truth.position[self.k]))

    @property
    def state(self) -> str:
        return navigation_state(self.ekf.diagnostics, LOST_SIGMA)[0]


def test_a_consistent_relocalisation_is_fused_like_any_fix(straight):
    f = Flight(straight, EkfParams(init_mode="pose"), offset=np.zeros(3))
    f.fly_to(5.0)
    sigma_before = f.ekf.diagnostics.position_sigma
    out = f.fix(5.0)
    assert (out.accepted, out.reason) == (True, Reason.OK)
    assert f.ekf.diagnostics.position_sigma < sigma_before
    assert f.ekf.diagnostics.relocalisation_candidates == 0 and f.state == TRACKING


def test_one_far_relocalisation_does_not_move_the_estimate(straight):
    f = Flight(straight, EkfParams(init_mode="pose"))
    f.fly_to(5.0)
    before = f.ekf.state
    out = f.fix(5.0)
    assert (out.accepted, out.reason) == (False, Reason.RELOCALISATION_HELD)
    after = f.ekf.state
    np.testing.assert_array_equal(after.position, before.position)
    np.testing.assert_array_equal(after.covariance, before.covariance)
    assert f.ekf.diagnostics.relocalisation_candidates == 1 and f.state == SEARCHING
    f.fly_to(20.0)
    assert f.error > 4900.0 and f.ekf.diagnostics.relocalisation_resets == 0


def test_two_agreeing_far_relocalisations_reset_the_position(straight):
    f = Flight(straight, EkfParams(init_mode="pose"))
    assert f.fix(5.0).reason == Reason.RELOCALISATION_HELD
    f.fly_to(10.0)
    velocity, quaternion = f.ekf.state.velocity.copy(), f.ekf.state.quaternion.copy()
    out = f.fix(10.0)
    assert (out.accepted, out.reason) == (True, Reason.RELOCALISATION_RESET)
    assert f.error < 3 * SIGMA
    # velocity and attitude stay the filter's: only the position is reset
    np.testing.assert_allclose(f.ekf.state.velocity, velocity, atol=1e-9)
    np.testing.assert_allclose(f.ekf.state.quaternion, quaternion, atol=1e-9)
    d = f.ekf.diagnostics
    assert d.relocalisation_resets == 1 and d.relocalisation_candidates == 0
    assert d.found.stamp == pytest.approx(10.0)
    assert np.linalg.norm(d.found.jump + KIDNAP) < 3 * SIGMA    # jumped back ~5 km west
    detail = navigation_state(d, LOST_SIGMA)[1]
    assert f.state == FOUND and detail.startswith("position reset onto agreeing")
    assert "at 10.000 s: jumped 50" in detail or "at 10.000 s: jumped 49" in detail
    # the filter tracks the ordinary fixes that follow
    assert f.fix(12.0, relocalisation=False).reason == Reason.OK
    assert f.state == TRACKING and f.error < 3 * SIGMA


@pytest.mark.parametrize("second_shift", [(600.0, 0.0, 0.0), (0.0, 3000.0, 0.0)],
                         ids=["600m_off_the_imu_motion", "another_place"])
def test_relocalisations_inconsistent_with_the_imu_motion_do_not_reset(straight,
                                                                       second_shift):
    f = Flight(straight, EkfParams(init_mode="pose"))
    assert f.fix(5.0).reason == Reason.RELOCALISATION_HELD
    assert f.fix(10.0, second_shift).reason == Reason.RELOCALISATION_HELD
    assert f.ekf.diagnostics.relocalisation_candidates == 2 and f.error > 4900.0


def test_the_same_wrong_place_found_twice_does_not_agree(straight):
    """Two frames 5 s apart matched to one fixed spot: the aircraft flew 150 m meanwhile."""
    f = Flight(straight, EkfParams(init_mode="pose"))
    spot = f.truth_at(5.0) + [0.0, 8000.0, 0.0]
    for t in (5.0, 10.0):
        f.fly_to(t)
        assert f.ekf.process_fix(t, spot, COV, relocalisation=True).reason == \
            Reason.RELOCALISATION_HELD
    assert f.ekf.diagnostics.relocalisation_resets == 0


def test_relocalisations_of_one_frame_or_too_close_in_time_do_not_agree(straight):
    f = Flight(straight, EkfParams(init_mode="pose", relocalisation_min_interval=2.0))
    assert f.fix(5.0).reason == Reason.RELOCALISATION_HELD
    assert f.fix(6.0).reason == Reason.RELOCALISATION_HELD       # 1 s < 2 s apart
    assert f.fix(8.0).reason == Reason.RELOCALISATION_RESET      # agrees with the first


def test_held_relocalisations_expire(straight):
    f = Flight(straight, EkfParams(init_mode="pose", relocalisation_timeout=10.0))
    assert f.fix(5.0).reason == Reason.RELOCALISATION_HELD
    f.fly_to(14.0)
    assert f.ekf.diagnostics.relocalisation_candidates == 1
    f.fly_to(16.0)
    assert f.ekf.diagnostics.relocalisation_candidates == 0 and f.state == TRACKING
    # a relocalisation that would have agreed with the expired one is held in its turn
    assert f.fix(17.0).reason == Reason.RELOCALISATION_HELD
    assert f.fix(22.0).reason == Reason.RELOCALISATION_RESET


def test_ordinary_far_fixes_stay_gated_and_relocalisations_never_arm_a_reset(straight):
    f = Flight(straight, EkfParams(init_mode="pose", reset_after_rejections=2))
    for t, shift in ((3.0, (0, 0, 0)), (6.0, (0, 4000, 0)), (9.0, (0, -4000, 0))):
        assert f.fix(t, shift).reason == Reason.RELOCALISATION_HELD
    # three rejected relocalisations armed nothing: an ordinary far fix is gated
    out = f.fix(12.0, relocalisation=False)
    assert (out.accepted, out.reason) == (False, Reason.GATED)
    assert f.error > 4900.0 and f.ekf.diagnostics.position_resets == 0


def test_a_late_relocalisation_agreeing_with_a_held_one_resets_at_its_stamp(straight):
    f = Flight(straight, EkfParams(init_mode="pose"))
    assert f.fix(5.0).reason == Reason.RELOCALISATION_HELD
    f.fly_to(11.0)
    t = f.truth.t[int(f.truth.at(10.0))]
    out = f.ekf.process_fix(t, f.truth_at(10.0), COV, relocalisation=True)   # 1 s late
    assert out.reason == Reason.RELOCALISATION_RESET and f.error < 3 * SIGMA


# ----------------------------------------------------------------------------- cold start
def test_cold_start_from_two_agreeing_relocalisations_and_not_from_one(straight):
    params = EkfParams(init_mode="fix")    # init_min_fix_interval 10 s
    f = Flight(straight, params, start=False)
    assert f.state == LOST
    out = f.fix(2.0)
    assert (out.accepted, out.reason) == (False, Reason.RELOCALISATION_HELD)
    assert not f.ekf.initialized and f.state == SEARCHING
    assert "relocalisation that agrees" in f.ekf.waiting_for()
    # 5 s later: agrees, but too close for a velocity by difference
    assert f.fix(7.0).reason == Reason.RELOCALISATION_HELD and not f.ekf.initialized
    out = f.fix(14.0)
    assert out.reason == Reason.INITIALIZED and f.ekf.initialized
    f.fly_to(15.0)
    assert f.error < 3 * SIGMA
    assert np.linalg.norm(f.ekf.state.velocity - f.truth.velocity[f.k]) < 5.0
    d = f.ekf.diagnostics
    assert d.found is not None and d.found.jump is None and f.state == FOUND
    assert f.fix(17.0, relocalisation=False).reason == Reason.OK and f.state == TRACKING


def test_cold_start_refuses_relocalisations_no_aircraft_could_fly_between(straight):
    f = Flight(straight, EkfParams(init_mode="fix"), start=False)
    assert f.fix(2.0).reason == Reason.RELOCALISATION_HELD
    # 4 km in 12 s: 330 m/s against a 50 m/s speed prior
    assert f.fix(14.0, (0.0, 4000.0, 0.0)).reason == Reason.RELOCALISATION_HELD
    assert not f.ekf.initialized and f.ekf.diagnostics.relocalisation_candidates == 2


def test_gnss_init_mode_does_not_start_from_relocalisations(straight):
    f = Flight(straight, EkfParams(init_mode="gnss"), start=False)
    assert f.fix(2.0).reason == Reason.NOT_INITIALIZED
    assert f.fix(14.0).reason == Reason.NOT_INITIALIZED and not f.ekf.initialized


# ----------------------------------------------------------------------------- the model
def test_dead_reckoning_covariance_matches_the_filters_own_propagation(straight):
    """Without updates, position covariance grows by exactly the displacement's covariance
    (the initial position error is independent of the rest): the closed form must agree with
    the filter's step-by-step propagation over 10 s of level flight (without levelling and
    sideslip, which are updates too)."""
    params = EkfParams(init_mode="pose", level_sigma=0.0, sideslip_sigma=0.0)
    f = Flight(straight, params, offset=np.zeros(3))
    P0, q0 = f.ekf.state.covariance, f.ekf.state.quaternion
    f.fly_to(10.0)
    grown = f.ekf.state.covariance[:3, :3] - P0[:3, :3]
    model = dead_reckoning_covariance(P0, q0, f.ekf.t - f.truth.t[0], params.gravity,
                                      params.accel_noise_density, params.gyro_noise_density)
    np.testing.assert_allclose(np.sqrt(np.diag(model)), np.sqrt(np.diag(grown)), rtol=0.02)


def test_relocalisation_parameters_are_validated():
    for bad in (dict(relocalisation_agreement_probability=1.0),
                dict(relocalisation_agreement_probability=0.0),
                dict(relocalisation_timeout=0.5, relocalisation_min_interval=1.0),
                dict(relocalisation_speed_sigma=0.0),
                dict(relocalisation_fuse_max_sigma=0.0),
                dict(init_mode="fix", relocalisation_timeout=5.0)):
        with pytest.raises(ValueError, match="relocalisation"):
            EkfParams(**bad)
    EkfParams(init_mode="pose", relocalisation_timeout=5.0)


# ----------------------------------------------------------------------------- the state
def test_navigation_state_goes_lost_searching_found_tracking_and_logs_each_change(straight):
    f = Flight(straight, EkfParams(init_mode="fix"), start=False)
    log = NavigationLog()
    lines = []

    def observe():
        line = log.change(*navigation_state(f.ekf.diagnostics, LOST_SIGMA))
        if line:
            lines.append(line)

    f.fly_to(1.0)
    observe()
    for t in (2.0, 8.0, 14.0, 20.0):
        f.fix(t, relocalisation=t < 20.0)
        observe()
        observe()   # no change, no line
    assert [line.split(":")[0].split(" (")[0] for line in lines] == [
        f"navigation {s}" for s in (LOST, SEARCHING, FOUND, TRACKING)]
    assert lines[2].startswith("navigation found (was searching): started from agreeing")


def test_navigation_state_is_lost_beyond_the_sigma_bound(straight):
    f = Flight(straight, EkfParams(init_mode="pose", init_position_sigma=800.0),
               offset=np.zeros(3))
    assert f.state == LOST      # horizontal sigma sqrt(2) * 800 m
    assert navigation_state(f.ekf.diagnostics, 2000.0)[0] == TRACKING
    assert math.isinf(TerrainEkf(EkfParams()).diagnostics.horizontal_sigma)


def test_a_lost_estimates_gate_is_no_check_on_a_relocalisation(straight):
    """Horizontal sigma ~2.8 km: a relocalisation 1.5 km off the estimate is inside the gate
    but is held all the same, until a second one agrees."""
    params = EkfParams(init_mode="pose", init_position_sigma=2000.0)
    f = Flight(straight, params, offset=np.array([1500.0, 0.0, 0.0]))
    out = f.fix(5.0)
    assert out.nis < out.gate and out.reason == Reason.RELOCALISATION_HELD
    assert f.error > 1400.0
    assert f.fix(10.0).reason == Reason.RELOCALISATION_RESET and f.error < 3 * SIGMA
    trusting = Flight(straight, EkfParams(init_mode="pose", init_position_sigma=2000.0,
                                          relocalisation_fuse_max_sigma=1e5),
                      offset=np.array([1500.0, 0.0, 0.0]))
    assert trusting.fix(5.0).reason == Reason.OK


def test_a_rewind_across_the_reset_applies_it_again_and_counts_it_once(straight):
    f = Flight(straight, EkfParams(init_mode="pose"))
    f.fix(5.0)
    assert f.fix(10.0).reason == Reason.RELOCALISATION_RESET
    f.fly_to(11.0)
    late = f.ekf.process_fix(9.5, f.truth_at(9.5), COV)    # stamped before the reset
    assert late.reason == Reason.GATED                     # against the estimate at 9.5
    f.fly_to(12.0)
    assert f.error < 3 * SIGMA
    d = f.ekf.diagnostics
    assert d.relocalisation_resets == 1 and d.found.stamp == pytest.approx(10.0)
