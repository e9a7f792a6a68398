"""What checking each plan in the arm's joint space costs the planner: virtual trials on a lab whose robot is an
arm, with the planner's calls timed (this process's CPU time: on a shared machine wall time counts the others').

    python tools/arm_plan_cost.py [--lab DIR] [--n 2] [--speed 8]

Prints, per call, the median and 95th percentile of: the joint-space check of one path
(``ArmPlanner.check``), the whole fit of one plan (the check, and any stretched re-plans and their checks:
``PredictorPlanner._arm_fit``), the task-space plan it checks (``PredictorPlanner._plan_from``, the earliest
arrival), and the samples per checked path. A re-plan at 4 Hz must stay well inside a frame (33 ms at 30 fps).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np


def _timed(cls, name: str, store: list, extra=None):
    orig = getattr(cls, name)

    def wrapper(*args, **kw):
        t = time.process_time()  # this process's CPU: on a shared machine wall time counts the others' work
        out = orig(*args, **kw)
        store.append(time.process_time() - t)
        if extra is not None:
            extra(out)
        return out

    setattr(cls, name, wrapper)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lab", type=Path, default=Path(__file__).resolve().parents[1])
    ap.add_argument("--n", type=int, default=2, help="seeds per trajectory")
    ap.add_argument("--speed", type=float, default=8.0)
    args = ap.parse_args()

    from labctl.config import load_lab
    from labctl.decisions.context import RunContext
    from labctl.decisions.predictor import PredictorPlanner
    from labctl.planning.arm_plan import ArmPlanner
    from labctl.runtime.virtual import TrialSpec, simulate_run

    lab = load_lab(args.lab)
    if lab.arm is None:
        raise SystemExit(f"{args.lab}: the robot file names no arm")
    ctx = RunContext.load(lab)
    checks: list[float] = []
    fits: list[float] = []
    plans: list[float] = []
    samples: list[int] = []
    _timed(ArmPlanner, "check", checks, lambda path: samples.append(len(path.t)))
    _timed(PredictorPlanner, "_arm_fit", fits)
    _timed(PredictorPlanner, "_plan_from", plans)
    for traj in ("line", "arc", "circle", "zigzag"):
        for seed in range(args.n):
            res = simulate_run(lab, ctx, TrialSpec(traj, args.speed, None, seed))
            print(f"{traj} seed {seed}: {res['identity']} {res['time_to_identity_s']}")

    def stats(xs, scale=1e3):
        a = np.asarray(xs, float) * scale
        return f"median {statistics.median(a):.2f}, p95 {np.percentile(a, 95):.2f}, max {a.max():.2f} (n {len(a)})"

    print(f"joint-space check per path, ms: {stats(checks)}")
    print(f"arm fit per plan (checks + stretched re-plans), ms: {stats(fits)}")
    print(f"task-space plan (earliest or stretched), ms: {stats(plans)}")
    print(f"samples per checked path: {stats(samples, 1.0)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
