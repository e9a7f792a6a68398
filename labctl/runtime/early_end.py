"""When a live run that drives the table can no longer succeed: the cause, before ``run.timeout_s``.

Two causes, each a setting of ``lab.yaml`` ``run:`` (paper §5.2: the fixed camera tracks the object
the table moves; without a marker in its images, or once the table stands still, the stages that
follow have nothing new to work with):

* no marker seen by the fixed camera for ``no_marker_s`` while the run waits for one;
* the table program has ended (every line acknowledged and GRBL reports ``Idle``) and no identity
  came within ``after_program_s`` of that.

Pure logic on the run clock (s): the live predictor's loop feeds it and fails the run with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..drivers.grbl import GrblTable, ProgramStream


@dataclass
class EarlyEnd:
    """Decides from what the run loop saw whether the run can still succeed.

    ``no_marker_s`` / ``after_program_s``: the two bounds (s; None: that cause is not checked).
    ``t0``: the run clock when the loop started (s)."""

    no_marker_s: float | None
    after_program_s: float | None
    t0: float
    t_unseen_since: float | None = None  # the wait for a marker began (loop start or the last loss)
    t_program_end: float | None = None  # the table program ended (run clock, s)

    def __post_init__(self) -> None:
        self.t_unseen_since = self.t0

    def program_ended(self, t: float) -> None:
        """The table program ended at ``t`` (s): kept once, the first time."""
        if self.t_program_end is None:
            self.t_program_end = t

    def check(self, now: float, *, waiting: bool) -> str | None:
        """The reason the run cannot succeed at ``now`` (s), or None. ``waiting``: the run has no marker in
        track (the predictor's ``wait`` stage)."""
        if not waiting:
            self.t_unseen_since = None
        elif self.t_unseen_since is None:
            self.t_unseen_since = now
        if (self.no_marker_s is not None and self.t_unseen_since is not None
                and now - self.t_unseen_since > self.no_marker_s):
            return f"no marker seen by the fixed camera in {self.no_marker_s:g} s"
        if (self.after_program_s is not None and self.t_program_end is not None
                and now - self.t_program_end > self.after_program_s):
            return (f"the table program ended at t={self.t_program_end:.1f} s and no identity "
                    f"in the {self.after_program_s:g} s since")
        return None


def program_ended(program: ProgramStream, table: GrblTable) -> bool:
    """The table's program has ended: every line acknowledged, and a status report after the last
    acknowledgement says ``Idle`` (the table stands still from then on)."""
    st = table.last_status
    if not program.done or st is None or table.last_status_t < program.last_progress:
        return False
    return st.state == "Idle"


__all__ = ["EarlyEnd", "program_ended"]
