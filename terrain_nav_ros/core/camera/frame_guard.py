"""Camera frames that must not become fixes: repeated stamps and frozen images.

A camera driver that hangs often keeps publishing its last image with new stamps, and a bag
spliced or replayed twice repeats stamps. Either way the matcher would localise the same
ground again and again and the filter would be pulled back to where the aircraft was, a
silently wrong answer. A real sensor's frames always differ (photon and read noise), so two
bit-identical consecutive frames mean a frozen source, and a stamp that does not move
forward means a repeated or out-of-order frame. :class:`FrameGuard` tells both apart from
good frames, for camera_ingest to answer them with a no-fix and its reason.

A clock that jumps back, or one frame stamped far ahead, is told apart from frames out of
order by :class:`~terrain_nav_ros.core.stamp_order.StampOrder`: :attr:`CONFIRM` frames in a
row behind the last one that go forward among themselves are a new clock, and the guard
starts again from them.

An image of one value (a covered lens, a black night frame, a frame saturated by glare) has
no noise left to differ by, so its repeats are not taken for a frozen source: they pass, and
the extractor answers them for what they are (a constant image, no drainage).
"""

from __future__ import annotations

import numpy as np

from ..stamp_order import Order, StampOrder


class FrameGuard:
    """Checks each camera frame against the previous one.

    Parameters
    ----------
    max_frozen_report : int
        Identical frames in a row after which the reason stops counting them (it still
        says frozen).
    """

    CONFIRM = 3   # frames in a row, going forward behind the last one, that restart it

    def __init__(self, max_frozen_report: int = 1000):
        self.max_frozen_report = max_frozen_report
        self._order = StampOrder(self.CONFIRM)
        self._image: np.ndarray | None = None
        self.frozen_run = 0

    @property
    def restarts(self) -> int:
        """New clocks taken so far."""
        return self._order.restarts

    def check(self, stamp: float, image: np.ndarray) -> str:
        """Why the frame at ``stamp`` [s] must not be used, or "" when it is a new frame.

        Only a frame that passes becomes the image the next ones are compared with, so a
        frozen source is caught for as long as it repeats it.
        """
        last = self._order.last
        order = self._order.check(stamp)
        if order == Order.BEHIND:
            return (f"frame repeated or out of order: stamp {stamp:.3f} s is not after the "
                    f"previous frame's {last:.3f} s")
        if order == Order.NEW_CLOCK:
            self._image = None
        if (self._image is not None and image.shape == self._image.shape
                and image.dtype == self._image.dtype and np.array_equal(image, self._image)
                and not _constant(image)):   # (the range only of a repeated frame)
            self.frozen_run = min(self.frozen_run + 1, self.max_frozen_report)
            return (f"camera frozen: the image of the last new frame again, {self.frozen_run} "
                    "frame(s) in a row (a real sensor's frames always differ)")
        self.frozen_run = 0
        self._image = image.copy()
        return ""


def _constant(image: np.ndarray) -> bool:
    """Whether every pixel holds the same value (nothing for sensor noise to change)."""
    return image.size == 0 or bool(image.min() == image.max())
