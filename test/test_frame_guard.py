"""FrameGuard: a frozen camera (the same image under new stamps) and stamps that do not move
forward are refused with their reason; new frames pass, and a frozen source is caught for as
long as it repeats."""

import numpy as np

from terrain_nav_ros.core.camera.frame_guard import FrameGuard


def _frames(n, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (48, 64), dtype=np.uint8) for _ in range(n)]


def test_new_frames_pass_and_a_frozen_camera_is_caught_until_it_moves_again():
    guard, (a, b, c) = FrameGuard(), _frames(3)
    assert guard.check(1.0, a) == "" and guard.check(1.1, b) == ""
    for k, t in enumerate((1.2, 1.3, 1.4), start=1):
        why = guard.check(t, b.copy())
        assert why.startswith("camera frozen") and f"{k} frame(s) in a row" in why
    assert guard.check(1.5, c) == "" and guard.frozen_run == 0
    b_noisy = b.copy()
    b_noisy[0, 0] ^= 1                  # one count of noise: a new frame
    assert guard.check(1.6, b_noisy) == ""


def test_repeated_and_out_of_order_stamps_are_refused_and_do_not_move_the_reference():
    guard, (a, b, c) = FrameGuard(), _frames(3)
    assert guard.check(2.0, a) == ""
    for t in (2.0, 1.9):
        assert guard.check(t, b).startswith("frame repeated or out of order")
    assert guard.check(2.1, b) == ""          # b was never accepted: it is new
    assert guard.check(2.2, c) == ""


def test_other_shapes_or_encodings_are_new_frames():
    guard, (a,) = FrameGuard(), _frames(1)
    assert guard.check(1.0, a) == ""
    assert guard.check(1.1, a.astype(np.uint16)) == ""
    assert guard.check(1.2, a[:10, :10].copy()) == ""
    assert guard.check(1.3, a[:10, :10].copy()).startswith("camera frozen")


def test_repeats_of_a_constant_image_are_not_taken_for_a_frozen_camera():
    # a covered lens or a saturated frame has no noise left: its repeats are bit-identical
    # and must reach the extractor, which says what they are (constant, no drainage)
    guard, (a,) = FrameGuard(), _frames(1)
    assert guard.check(1.0, a) == ""
    for t, value in ((1.1, 0), (1.2, 0), (1.3, 255), (1.4, 255)):
        assert guard.check(t, np.full((48, 64), value, np.uint8)) == ""
    assert guard.check(1.5, a) == "" and guard.check(1.6, a.copy()).startswith("camera frozen")


def test_a_stamp_far_ahead_or_a_clock_that_jumps_back_costs_a_few_frames_not_the_flight():
    """One frame stamped an hour ahead, or a clock restarted (bag --loop): the frames after
    it go forward among themselves, and the third in a row restarts the guard; repeated
    stamps never do."""
    frames = _frames(12)
    guard = FrameGuard()
    assert guard.check(100.0, frames[0]) == "" and guard.check(3700.0, frames[1]) == ""
    answers = [guard.check(101.0 + k, frames[2 + k]) for k in range(5)]
    assert [a == "" for a in answers] == [False, False, True, True, True]
    assert guard.restarts == 1
    # a clock that jumps back by a minute
    assert [guard.check(50.0 + k, frames[7 + k]) == "" for k in range(4)] == \
        [False, False, True, True]
    # the same stamp over and over is a repeat, however long it goes on
    guard = FrameGuard()
    assert guard.check(10.0, frames[0]) == ""
    assert all(guard.check(9.0, f) for f in frames[1:])
    assert guard.restarts == 0
