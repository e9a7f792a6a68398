"""Streaming never blocks the run (issue 13, Build 1): the predictor pumps the table's program from
its loop, so a long G2/G3 — acknowledged by GRBL only when it leaves the planner — no longer holds
up tracking. Virtual time, GRBL emulator behind the real driver; ground truth from the simulator."""

from __future__ import annotations

import pytest

from labctl.config import load_lab
from labctl.decisions.context import RunContext
from labctl.drivers.programs import program
from labctl.records import RunRecord, load_run
from labctl.runtime.virtual import TrialSpec, simulate_run
from labctl.sim.clock import VirtualClock
from labctl.sim.lab import SimLab
from labctl.workspace import sample_lab_path


@pytest.fixture(scope="module")
def lab():
    return load_lab(sample_lab_path())


def test_pump_returns_at_once_while_an_arc_executes(lab):
    clock = VirtualClock()
    bench = SimLab.build(lab, clock, devices=("table", "robot"), table_start_mm=(200.0, 200.0))
    bench.open()
    prog = bench.table.start_program(program("circle", 8.0, start=(200.0, 200.0)))
    t0 = clock.now()
    for _ in range(300):  # 10 virtual s of a 63 s circle
        t = clock.advance(1 / 30)
        bench.advance(t)
        before = clock.now()
        prog.pump(0.0)
        assert clock.now() == before  # no waiting inside pump
    assert clock.now() - t0 == pytest.approx(10.0, abs=0.05)
    assert prog.acked == prog.total - 1 and prog.active  # the circle itself is still in GRBL's planner
    assert bench.grbl.moving
    assert bench.table.stop().state == "Idle"


def test_an_arc_run_waits_under_a_second_and_logs_progress(tmp_path, lab):
    rec = RunRecord.create(tmp_path / "runs", {"command": "test"})
    res = simulate_run(lab, RunContext.load(lab), TrialSpec("arc", 8.0, None, 1), rec)
    rec.finish(res)
    assert res["correct"] is True
    assert res["stages"]["wait"] < 1.0  # was 29.6 s with the blocking stream
    progress = load_run(rec.path).of("table_progress")
    assert progress and progress[0]["total"] == 5 and progress[-1]["acked"] >= 4
