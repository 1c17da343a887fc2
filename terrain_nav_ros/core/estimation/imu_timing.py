"""IMU stamp screening: a single badly stamped sample is refused, a real time jump resets.

A flight system must not let one sample decide that time has jumped: a sample stamped 5 s
in the past or 1 h in the future is far more often a driver or clock glitch than a new
timeline, and integrating it (or resetting on it) loses navigation. So a stamp further than
``max_step`` from the last accepted one, in either direction, is held as *suspect* and
refused. Only when ``confirm`` consecutive samples continue consistently from the suspect
stamp (each one later than the previous by at most ``max_period``: a bag loop, a simulator
restart) is the jump real; the caller then resets and is handed those samples to start the
new timeline with. A sample that continues the old timeline drops the suspects.

ROS-free; used by :class:`terrain_nav_ros.core.estimation.ekf.TerrainEkf`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

__all__ = ["ImuTiming", "ImuTimingGuard"]


class ImuTiming(StrEnum):
    """Verdict on one IMU stamp."""

    PASS = "pass"          # near the last accepted stamp: hand it to the filter
    SUSPECT = "suspect"    # far from it: refuse (held as a possible new timeline)
    JUMP = "jump"          # confirmed new timeline: reset, then take ``pending``


@dataclass
class ImuTimingGuard:
    """Decides, sample by sample, whether an IMU stamp is usable, suspect or a time jump.

    Parameters
    ----------
    max_step : float
        A stamp further than this from the last accepted one, either way, is suspect (s).
    max_period : float
        Samples of a new timeline must follow each other by (0, max_period] s.
    confirm : int
        Consecutive consistent samples (the first suspect one included) that make a jump.

    Attributes
    ----------
    last : float or None
        Last accepted stamp (s).
    pending : list
        Payloads of the suspect run; after a ``JUMP``, the samples of the new timeline in
        order (the caller takes them with :meth:`take_pending`).
    refused, jumps : int
        Suspect stamps refused, and jumps confirmed, so far.

    Examples
    --------
    >>> g = ImuTimingGuard(max_step=1.0, max_period=0.1, confirm=3)
    >>> [g.check(t).value for t in (0.0, 0.01, 3600.0, 0.02)]
    ['pass', 'pass', 'suspect', 'pass']
    >>> [g.check(t).value for t in (-5.0, -4.99, -4.98)]
    ['suspect', 'suspect', 'jump']
    >>> g.take_pending(), g.refused, g.jumps
    ([-5.0, -4.99, -4.98], 3, 1)
    """

    max_step: float
    max_period: float
    confirm: int
    last: float | None = None
    pending: list = field(default_factory=list)
    refused: int = 0
    jumps: int = 0
    _suspect_last: float | None = None

    def __post_init__(self):
        if not (self.max_step > 0 and self.max_period > 0 and self.confirm >= 1):
            raise ValueError("ImuTimingGuard needs max_step > 0, max_period > 0, confirm >= 1")

    def check(self, stamp: float, payload=None) -> ImuTiming:
        """Classify ``stamp`` (finite, s); ``payload`` (default the stamp) is kept while
        suspect so the caller can replay the new timeline after a jump."""
        payload = stamp if payload is None else payload
        if self.last is None or abs(stamp - self.last) <= self.max_step:
            self.last = stamp
            self.pending.clear()
            self._suspect_last = None
            return ImuTiming.PASS
        prev = self._suspect_last
        if prev is None or not 0.0 < stamp - prev <= self.max_period:
            self.pending.clear()   # not a continuation: this one starts a new suspect run
        self.pending.append(payload)
        self._suspect_last = stamp
        if len(self.pending) < self.confirm:
            self.refused += 1
            return ImuTiming.SUSPECT
        self.last = stamp
        self._suspect_last = None
        self.jumps += 1
        return ImuTiming.JUMP

    def take_pending(self) -> list:
        """The suspect run's payloads (the new timeline after a ``JUMP``), emptied."""
        out, self.pending = self.pending, []
        return out
