"""Trials benchmark: a sweep on one worker process against the same sweep on all cores.

* ``sweep N trials, 1 job``: the baseline, timed in the same run.
* ``sweep N trials, J jobs``: the process pool (``labctl trials --jobs J``). ``ratio`` is the
  speed-up (1-job wall time / J-job wall time); the target on two cores is ≥ 1.8. ``identical``
  says whether the per-trial results are the same as the serial sweep's (they must be).
* ``virtual trial`` rows: simulated seconds per wall second and per CPU second of one trial.

Each sweep is repeated (medians); records are off so that disk writes do not dominate.
"""

from __future__ import annotations

import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from ._timing import row


def _sweep(lab, n: int, jobs: int) -> tuple[float, dict]:
    from ..experiments.trials import run_sweep

    t0 = time.perf_counter()
    s = run_sweep(lab, n=n, trajectory="line", speeds=[4.0, 12.0], objects=None, seed=100, record=False, n_jobs=jobs)
    return time.perf_counter() - t0, s


def run(quick: bool = False) -> dict:
    """Time a trial sweep on one process and on a pool of all cores; speed-up, identity of results, sim-time rate."""
    from ..config import load_lab
    from ..workspace import sample_lab_path

    jobs = max(2, os.cpu_count() or 1)
    # per speed: 4 or 96 trials a sweep. A pool pays a fixed start (its processes, each loading the
    # lab and library once, ~2 s here), so the speed-up of a short sweep understates a long one's.
    n = 2 if quick else 48  # (96: trials got shorter, 0.5 s each, and 48 no longer amortised the start)
    repeat = 1
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "lab"
        shutil.copytree(sample_lab_path(), root, ignore=shutil.ignore_patterns("runs"))
        lab = load_lab(root)
        serial = [_sweep(lab, n, 1) for _ in range(repeat)]
        pool = [_sweep(lab, n, jobs) for _ in range(repeat)]
    t1 = statistics.median(w for w, _ in serial)
    tj = statistics.median(w for w, _ in pool)

    def comparable(s):
        return [{k: v for k, v in t.items() if k != "record"} for t in s["trials"]]

    identical = all(comparable(s) == comparable(serial[0][1]) for _, s in serial + pool)
    trials = serial[0][1]["trials"]
    sim_s = statistics.median(t["sim_time_s"] for t in trials)
    per_trial = t1 / len(trials)
    return {
        "rows": [row(f"sweep {len(trials)} trials, 1 job", t1),
                 row(f"sweep {len(trials)} trials, {jobs} jobs", tj, baseline="1 job", baseline_s=t1,
                     identical=identical),
                 row("virtual trial (serial sweep, per trial)", per_trial, baseline="simulated time",
                     baseline_s=sim_s)],
        "speedup": round(t1 / tj, 2),
        "jobs": jobs,
        "identical_to_serial": identical,
        "virtual_time_factor": round(sim_s / per_trial, 2),
        "targets": {"speedup_2_jobs": 1.8, "virtual_time_factor": 15},
        "ratio_means": "baseline time / this time (> 1: faster than the baseline)",
    }
