"""Stamps that must go forward, and a clock that restarts.

A stream's stamp that does not move forward is a late, repeated or out-of-order message:
used, it would date data wrongly (a camera frame matched where the aircraft was, an
estimate that sends an autopilot back in time). But a clock that jumps back for real (a bag
played with ``--loop``, a driver or simulator restarted at zero), or one message stamped
far ahead (a glitch, a PTP step), would leave every later message "behind" until the new
clock passed the old one: an hour of them for a stamp an hour ahead. Messages behind the
last one that go forward among themselves, :attr:`StampOrder.confirm` of them in a row, are
a new clock: the order starts again from them, as the ekf does from IMU samples that go on
from a jump (``time_jump_confirm``). Repeated stamps never go forward, so they never
restart it.
"""

from __future__ import annotations

from enum import StrEnum


class Order(StrEnum):
    """Where a stamp stands against the stream's last one."""

    NEXT = "next"            # after the last: take it
    BEHIND = "behind"        # not after the last: a late, repeated or out-of-order message
    NEW_CLOCK = "new clock"  # the stream's clock restarted: take it, and go on from it


class StampOrder:
    """Checks each stamp of a stream against the last one taken.

    Parameters
    ----------
    confirm : int
        Stamps in a row, behind the last one and going forward among themselves, that are
        a new clock.
    """

    def __init__(self, confirm: int = 3):
        self.confirm = confirm
        self.last: float | None = None
        self.restarts = 0
        self._behind: list[float] = []   # the latest stamps behind the last one taken

    def check(self, stamp: float) -> Order:
        """Where ``stamp`` [s] stands; a NEXT or NEW_CLOCK one becomes the last."""
        if self.last is not None and not stamp > self.last:
            if self._behind and not stamp > self._behind[-1]:
                self._behind.clear()
            self._behind.append(stamp)
            if len(self._behind) < self.confirm:
                return Order.BEHIND
            self.restarts += 1
            self._behind.clear()
            self.last = stamp
            return Order.NEW_CLOCK
        self._behind.clear()
        self.last = stamp
        return Order.NEXT
