"""Bridging a gap in the fixed camera's sightings on the tracker's prediction (paper §5.2's one-step window).

On a real lab the arm reaching over the table crosses the fixed camera's view of it and can hide the
marker for a few frames. The track is not lost for that: the filter keeps predicting, the one-step
window follows the prediction, and the first sighting after the gap is gated against the prediction
like any other. A gap is a *bridge* while it lasts at most ``max_s`` (``tracking.max_bridge_s``); a
longer one means the prediction can no longer be trusted to place the window, and the track is lost.

:class:`OcclusionBridge` keeps the books (no clock: times arrive as arguments): :meth:`missed` for a
frame without a sighting, :meth:`seen` for one with, which returns the bridge it closes;
:meth:`expired` says when the gap has outlasted the bound. Seconds on the run's clock.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Bridge:
    """One gap in the sightings: from the last sighting ``t_start`` to the next ``t_end`` (s), ``frames``
    fixed-camera frames without a sighting in between."""

    t_start: float
    t_end: float
    frames: int

    @property
    def duration_s(self) -> float:
        """How long the track ran on its prediction alone (s)."""
        return self.t_end - self.t_start


class OcclusionBridge:
    """The current gap in a track's sightings, bridged up to ``max_s`` seconds (see the module doc)."""

    def __init__(self, max_s: float):
        if not max_s > 0:
            raise ValueError(f"max_s must be positive, got {max_s}")
        self.max_s = float(max_s)
        self.t_last: float | None = None  # the last sighting
        self.frames = 0  # frames missed since
        self.bridged: list[Bridge] = []

    @property
    def open(self) -> bool:
        """A gap is under way: frames have been missed since the last sighting."""
        return self.frames > 0

    def seen(self, t: float) -> Bridge | None:
        """A sighting at ``t`` (s): closes the gap under way, if any, and returns it as a :class:`Bridge`
        (kept in ``bridged``); None when no frame was missed or the gap had already expired."""
        closed = None
        if self.open and self.t_last is not None and not self.expired(t):
            closed = Bridge(self.t_last, float(t), self.frames)
            self.bridged.append(closed)
        self.t_last, self.frames = float(t), 0
        return closed

    def missed(self, t: float) -> None:
        """A frame at ``t`` (s) without a sighting (counted only once the track has a sighting)."""
        if self.t_last is not None and t > self.t_last:
            self.frames += 1

    def bridging(self, t: float) -> bool:
        """At ``t`` (s) the track is seen or bridged: the prediction may still place the search window."""
        return self.t_last is not None and t - self.t_last <= self.max_s

    def expired(self, t: float) -> bool:
        """The gap at ``t`` (s) has lasted longer than ``max_s``: the track is lost."""
        return self.t_last is not None and t - self.t_last > self.max_s

    def gap_s(self, t: float) -> float:
        """Seconds since the last sighting at ``t`` (s); 0 before any."""
        return 0.0 if self.t_last is None else float(t) - self.t_last

    def reset(self) -> None:
        """Forget the track (it was lost and starts again from nothing)."""
        self.t_last, self.frames = None, 0
