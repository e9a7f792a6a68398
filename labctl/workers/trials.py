"""Many simulated runs in virtual time (``labctl trials``): success rates and timing tables."""

from __future__ import annotations

import statistics
from collections.abc import Sequence

from ..config import Lab
from .context import RunContext
from .virtual import TrialSpec, simulate_run


def _median(values):
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def run_trials(lab: Lab, *, n: int, trajectory: str, speeds: Sequence[float], objects: Sequence[str] | None,
               seed: int = 0, record: bool = True, console=None) -> dict:
    """Run ``n`` trials per speed with seeds ``seed, seed+1, …``; objects cycle through ``objects``
    (all of the library if None). Each trial keeps a run record (unless ``record`` is False)."""
    from ..errors import UserInputError
    from ..records import RunRecord

    ctx = RunContext.load(lab)
    names = list(objects) if objects else list(ctx.names)
    missing = [o for o in names if o not in ctx.library]
    if missing:
        raise UserInputError(f"no object {missing[0]!r} in the library (have: {', '.join(ctx.names)})")
    specs = [TrialSpec(trajectory, float(v), names[i % len(names)], seed + i) for v in speeds for i in range(n)]
    results = []
    progress = None
    if console is not None:
        from rich.progress import Progress

        progress = Progress(console=console, transient=True)
        progress.start()
        task = progress.add_task("trials", total=len(specs))
    try:
        for spec in specs:
            rec = None
            if record:
                rec = RunRecord.create(lab.runs_dir, {"command": "trials", **spec.__dict__}, durable=False)
            res = simulate_run(lab, ctx, spec, rec)
            if rec is not None:
                res["record"] = str(rec.path)
                rec.finish(res)
                rec.close()
            results.append(res)
            if progress is not None:
                progress.advance(task)
    finally:
        if progress is not None:
            progress.stop()
    return summarize(results)


def summarize(results: list[dict]) -> dict:
    by_speed = []
    for v in sorted({r["speed_mm_s"] for r in results}):
        rs = [r for r in results if r["speed_mm_s"] == v]
        ok = [r for r in rs if r["correct"]]
        ratios = [r["time_to_identity_s"] / r["lower_bound_s"] for r in ok if r.get("lower_bound_s")]
        ratios_q = [r["time_to_identity_s"] / r["lower_bound_quintic_s"] for r in ok if r.get("lower_bound_quintic_s")]
        by_speed.append({
            "speed_mm_s": v, "n": len(rs), "success_rate": len(ok) / len(rs),
            "time_to_identity_s_median": _median([r["time_to_identity_s"] for r in ok]),
            "lower_bound_s_median": _median([r.get("lower_bound_s") for r in ok]),
            "ratio_to_lower_bound_median": _median(ratios),
            "ratio_to_quintic_bound_median": _median(ratios_q),
            "views_mean": statistics.fmean([r["views"] for r in rs]) if rs else 0.0,
        })
    stages = sorted({k for r in results for k in r.get("stages", {})})
    stage_medians = {k: _median([r["stages"].get(k) for r in results if r["correct"]]) for k in stages}
    link_util = [r["link"]["utilisation"] for r in results if "link" in r]
    return {
        "n": len(results),
        "success_rate": sum(r["correct"] for r in results) / len(results) if results else 0.0,
        "by_speed": by_speed,
        "stage_medians_s": {k: v for k, v in stage_medians.items() if v is not None},
        "link_utilisation_median": _median(link_util),
        "failed": [{k: r.get(k) for k in ("seed", "true_identity", "identity", "speed_mm_s", "failure", "record")}
                   for r in results if not r["correct"]],
        "trials": results,
    }
