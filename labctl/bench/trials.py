"""Trials benchmark: how fast virtual trials run, on one core and on all of them.

* ``real-time factor per core``: each trial's simulated seconds over its wall seconds on a 1-job sweep
  (records off), median over the trials after the first (the first pays the process's imports and caches,
  a fixed cost, reported apart); also per CPU second. The goal is ≥ 25× per core.
* ``sweep N trials, 1 job`` against ``sweep N trials, J jobs``: the process pool (``labctl trials
  --jobs J``), pool start included (the whole :func:`~labctl.experiments.trials.run_sweep` call); the goal
  on two cores is ≥ 1.8× at 48 trials. ``identical`` says whether the per-trial results are the serial
  sweep's (they must be).
* ``J jobs, forkserver``: the same jobs on a pool whose workers start from a fork server (the executor
  before the workers were forked from the warm parent), timed in the same run: the old path.
* ``breakdown``: where a trial's wall time goes (exclusive times of the runtime's entry points: setup,
  simulation, rendering, vision, tracking, planning, the recognizer), per trial.
"""

from __future__ import annotations

import contextlib
import functools
import os
import shutil
import statistics
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from ._timing import row

SPEEDS = (4.0, 8.0, 12.0)


def _sweep(lab, n: int, jobs: int) -> tuple[float, dict, list[tuple[float, float]]]:
    """Wall time of one sweep, its summary, and each trial's (wall, CPU) seconds (serial sweeps only)."""
    from ..experiments.trials import run_sweep

    marks = [(time.perf_counter(), time.process_time())]
    per_trial: list[tuple[float, float]] = []

    def mark(res, done, total):
        now = (time.perf_counter(), time.process_time())
        per_trial.append((now[0] - marks[-1][0], now[1] - marks[-1][1]))
        marks.append(now)

    t0 = time.perf_counter()
    s = run_sweep(lab, n=n, trajectory="line", speeds=list(SPEEDS), objects=None, seed=100, record=False,
                  n_jobs=jobs, on_result=mark if jobs == 1 else None)
    return time.perf_counter() - t0, s, per_trial


def _forkserver(lab, spec_trials: list[dict], jobs: int) -> tuple[float, list[dict]]:
    """The same trials on a pool started from a fork server, pool start included."""
    from ..experiments.trials import execute

    t0 = time.perf_counter()
    out = list(execute(str(lab.root), list(enumerate(spec_trials)), None, n_jobs=jobs, pool_start="forkserver"))
    return time.perf_counter() - t0, out


# the entry points timed (exclusive of the ones they call), by what they are
_TIMED: dict[str, list[tuple[str, str | None, str]]] = {
    "setup (lab, devices, workers)": [("labctl.sim.lab", "SimLab", "build"), ("labctl.sim.lab", "SimLab", "open"),
                                      ("labctl.drivers.robot", "SerialRobot", "ensure_ready"),
                                      ("labctl.decisions.predictor", "PredictorPlanner", "__init__")],
    "simulate (world, emulators, link)": [("labctl.sim.lab", "SimLab", "advance"),
                                          ("labctl.decisions.predictor", "ProgramProgress", "pump"),
                                          ("labctl.runtime.virtual", "LinkMeter", "carry"),
                                          ("labctl.drivers.robot", "SerialRobot", "heartbeat"),
                                          ("labctl.drivers.robot", "SerialRobot", "poll")],
    "render (both cameras)": [("labctl.sim.world", "SimWorld", "render")],
    "vision (fixed camera's markers)": [("labctl.decisions.predictor", None, "detect_markers"),
                                        ("labctl.decisions.predictor", None, "detect_markers_windowed"),
                                        ("labctl.decisions.predictor", None, "red_blob_centroid")],
    "tracking (Kalman/IMM update, predict)": [("labctl.tracking.tracker", "MarkerTracker", "update"),
                                              ("labctl.tracking.tracker", "MarkerTracker", "predict"),
                                              ("labctl.tracking.tracker", "MarkerTracker", "predict_path")],
    "planning (predictor: state machine, plans)": [("labctl.decisions.predictor", "PredictorPlanner", "tick"),
                                                   ("labctl.decisions.predictor", "PredictorPlanner", "on_frames"),
                                                   ("labctl.decisions.predictor", "PredictorPlanner",
                                                    "on_message")],
    "recognizer (mobile images: markers, pose, match)": [("labctl.decisions.recognizer", "Recognizer", "handle")],
    "the loop itself": [("labctl.runtime.virtual", None, "simulate_run")],
}


@contextlib.contextmanager
def _timed(acc: dict[str, float]):
    """Wrap each of :data:`_TIMED`'s entry points to add its exclusive wall time to ``acc`` (restored on exit)."""
    import importlib

    stack: list[float] = []
    undo: list[tuple[object, str, object]] = []

    def wrap(f, cat):
        @functools.wraps(f)
        def g(*a, **k):
            t0 = time.perf_counter()
            stack.append(0.0)
            try:
                return f(*a, **k)
            finally:
                dt = time.perf_counter() - t0
                acc[cat] += dt - stack.pop()
                if stack:
                    stack[-1] += dt
        return g

    try:
        for cat, points in _TIMED.items():
            for mod, cls, name in points:
                module = importlib.import_module(mod)
                owner = getattr(module, cls) if cls else module
                undo.append((owner, name, owner.__dict__[name]))  # as stored (a classmethod stays one)
                setattr(owner, name, wrap(getattr(owner, name), cat))
        yield
    finally:
        for owner, name, f in reversed(undo):
            setattr(owner, name, f)


def breakdown(lab_root: str, n: int) -> dict:
    """Per-trial wall time (ms) by part, over ``n`` trials per speed in this process (after one warm-up trial)."""
    from ..experiments.trials import _context, plan_specs, run_one

    ctx = _context(lab_root)[1]
    specs = plan_specs(n, "line", SPEEDS, ctx.names, 200)
    run_one(lab_root, 0, specs[0], None)
    acc: dict[str, float] = defaultdict(float)
    sim = 0.0
    with _timed(acc):
        t0 = time.perf_counter()
        for i, s in enumerate(specs):
            sim += run_one(lab_root, i, s, None)["sim_time_s"]
        wall = time.perf_counter() - t0
    k = len(specs)
    parts = {cat: {"ms_per_trial": round(1000 * v / k, 1), "share": round(v / wall, 3)}
             for cat, v in sorted(acc.items(), key=lambda kv: -kv[1])}
    return {"trials": k, "ms_per_trial": round(1000 * wall / k, 1), "sim_s_per_trial": round(sim / k, 3),
            "parts": parts, "note": "timing wrappers add a few % to the whole"}


def run(quick: bool = False) -> dict:
    """Real-time factor per core, the J-job sweep against 1 job (and against the fork-server pool), a breakdown."""
    from ..config import load_lab
    from ..workspace import sample_lab_path

    jobs = max(2, os.cpu_count() or 1)
    n = 1 if quick else 16  # per speed, 3 speeds: 48 trials, the sweep size
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "lab"
        shutil.copytree(sample_lab_path(), root, ignore=shutil.ignore_patterns("runs"))
        lab = load_lab(root)
        t1, serial, per_trial = _sweep(lab, n, 1)
        tj, pool, _ = _sweep(lab, n, jobs)
        import threading

        pool_start = "fork" if threading.active_count() == 1 else "forkserver"  # what the J-job sweep used
        t_fs, fs = _forkserver(lab, _specs(lab, n), jobs)
        parts = breakdown(str(root), 1)

    def comparable(trials):
        return sorted(({k: v for k, v in t.items() if k != "record"} for t in trials), key=lambda t: t["index"])

    identical = comparable(pool["trials"]) == comparable(serial["trials"])
    identical_fs = comparable(fs) == comparable(serial["trials"])
    trials = serial["trials"]  # in index order, the order the serial sweep ran them
    rt = [t["sim_time_s"] / w for t, (w, _) in zip(trials, per_trial)][1:] or [trials[0]["sim_time_s"]
                                                                              / per_trial[0][0]]
    rt_cpu = [t["sim_time_s"] / c for t, (_, c) in zip(trials, per_trial)][1:] or [trials[0]["sim_time_s"]
                                                                                  / per_trial[0][1]]
    sim_s = statistics.median(t["sim_time_s"] for t in trials)
    wall_trial = statistics.median(w for w, _ in per_trial[1:] or per_trial)
    return {
        "rows": [row(f"sweep {len(trials)} trials, 1 job", t1),
                 row(f"sweep {len(trials)} trials, {jobs} jobs (pool start included)", tj, baseline="1 job",
                     baseline_s=t1, identical=identical),
                 row(f"sweep {len(trials)} trials, {jobs} jobs, fork-server pool (the old path)", t_fs,
                     baseline="1 job", baseline_s=t1, identical=identical_fs),
                 row(f"{jobs} jobs: warm-parent fork against the fork server", tj, baseline="fork server",
                     baseline_s=t_fs),
                 row("virtual trial (1-job sweep, median after the first)", wall_trial, baseline="simulated time",
                     baseline_s=sim_s),
                 row("first trial of the sweep (imports, caches)", per_trial[0][0])],
        "real_time_factor_per_core": round(statistics.median(rt), 2),
        "real_time_factor_per_cpu_s": round(statistics.median(rt_cpu), 2),
        "speedup": round(t1 / tj, 2),
        "speedup_forkserver": round(t1 / t_fs, 2),
        "jobs": jobs,
        "pool_start": pool_start,
        "identical_to_serial": identical and identical_fs,
        "breakdown": parts,
        "load_average": os.getloadavg()[0],
        "targets": {"speedup_2_jobs": 1.8, "real_time_factor_per_core": 25},
        "ratio_means": "baseline time / this time (> 1: faster than the baseline)",
    }


def _specs(lab, n: int) -> list[dict]:
    from ..experiments.trials import _context, plan_specs

    return plan_specs(n, "line", SPEEDS, _context(str(lab.root))[1].names, 100)
