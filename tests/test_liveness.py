"""Liveness bookkeeping: a worker's watch on its peer and on its supervisor (issue 13)."""

from __future__ import annotations

import multiprocessing as mp

from labctl.decisions import messages as m
from labctl.runtime.live import PeerWatch, _Control, plausible


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_peer_watch_grace_only_until_the_first_message():
    c = Clock()
    w = PeerWatch("recognizer", dead_after_s=3.0, start_timeout_s=60.0, clock=c)
    c.t = 59.0
    assert w.lost() is None  # still starting: imports, device opening
    c.t = 61.0
    assert "never answered within 60 s" in w.lost()
    w = PeerWatch("recognizer", dead_after_s=3.0, start_timeout_s=60.0, clock=c)
    c.t += 10.0
    w.heard()  # first beat: from now on the short bound holds
    c.t += 2.9
    assert w.lost() is None
    c.t += 0.2
    why = w.lost()
    assert why and "went silent" in why and "dead_after_s 3" in why
    w.heard()
    assert w.lost() is None and w.max_gap_s >= 3.0


def test_control_notices_a_silent_or_vanished_supervisor():
    worker_end, sup_end = mp.Pipe()
    ctl = _Control(worker_end, "predictor", dead_after_s=0.2)
    assert ctl.supervisor_lost() is None  # no beat yet: no verdict
    sup_end.send(("beat", 0.0))
    assert ctl.supervisor_lost() is None
    ctl.t_supervisor -= 1.0  # a second without a beat (SIGSTOP)
    assert "went silent" in ctl.supervisor_lost()
    sup_end.close()  # SIGKILL: the pipe closes
    assert "control pipe closed" in ctl.supervisor_lost()


def test_implausible_recognizer_messages_are_dropped():
    class Ctx:
        names = ["a", "b", "c"]

    assert plausible(m.Identity(2, 0.5, 1, (2,)), Ctx)
    assert not plausible(m.Identity(7, 0.5, 1, (7,)), Ctx)
    assert not plausible(m.Ambiguous((0, 9)), Ctx)
    assert plausible(m.FrameTaken(1, 0.0), Ctx)
