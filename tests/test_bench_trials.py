"""``labctl bench trials``'s per-trial breakdown: its parts add up to the trials' wall time, it leaves the
runtime as it found it, and the timed trials give the same results as untimed ones."""

from __future__ import annotations

import shutil
from collections import defaultdict

import pytest

from labctl.bench import trials as bench
from labctl.experiments.trials import _context, plan_specs, run_one
from labctl.sim.lab import SimLab
from labctl.workspace import sample_lab_path


@pytest.mark.timeout(300)
def test_the_breakdown_adds_up_and_unwraps(tmp_path):
    root = tmp_path / "lab"
    shutil.copytree(sample_lab_path(), root, ignore=shutil.ignore_patterns("runs"))
    build = SimLab.__dict__["build"]
    out = bench.breakdown(str(root), 1)
    assert SimLab.__dict__["build"] is build  # every wrapped entry point restored as stored
    assert out["trials"] == 3 and out["sim_s_per_trial"] > 1.0
    parts = out["parts"]
    assert set(parts) <= set(bench._TIMED)
    assert {"render (both cameras)", "tracking (Kalman/IMM update, predict)", "the loop itself"} <= set(parts)
    total = sum(p["ms_per_trial"] for p in parts.values())
    # exclusive times: they sum to the whole trial (run_one's own few statements aside), never to more
    assert 0.9 * out["ms_per_trial"] <= total <= 1.001 * out["ms_per_trial"] + 0.5
    # timing does not change a trial
    ctx = _context(str(root))[1]
    spec = plan_specs(1, "line", bench.SPEEDS, ctx.names, 200)[0]
    plain = run_one(str(root), 0, spec, None)
    acc: dict[str, float] = defaultdict(float)
    with bench._timed(acc):
        timed = run_one(str(root), 0, spec, None)
    assert timed == plain and acc["render (both cameras)"] > 0
