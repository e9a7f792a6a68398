"""A live run against the virtual run of the same seed: time to identity and where the difference goes.

Runs ``labctl run --trajectory line --seed k`` live (two worker processes, the simulated lab on ptys, real
time) and ``--virtual`` (one process, virtual time) for each seed on one lab, alternating, and prints per seed
the time to identity of each, their ratio, and the time each spent in every stage of the run (the result's
``stages``: wait = first sight, track, intercept, initial, standard, match), live minus virtual, with the load
average beside. A virtual run's computing takes no virtual time, so a stage's excess in the live run is the
computing, scheduling and frame delivery of that stage on this machine (the 9600-bps lines are paced in both).

    PYTHONPATH=. python tools/live_vs_virtual.py LAB --seeds 1 2 3 [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

STAGES = ("wait", "track", "intercept", "initial", "standard", "match")


def one(lab: Path, seed: int, virtual: bool) -> dict:
    """One run's result (``--json``), with the load average when it started."""
    load = os.getloadavg()[0]
    cmd = [sys.executable, "-m", "labctl", "--lab", str(lab), "--json", "run", "--trajectory", "line",
           "--seed", str(seed)] + (["--virtual"] if virtual else [])
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=lab)
    try:
        res = json.loads(proc.stdout)
    except json.JSONDecodeError:
        res = {"error": (proc.stderr.strip().splitlines() or ["no output"])[-1]}
    res["load_avg"] = round(load, 2)
    return res


def main(argv: list[str] | None = None) -> int:
    """Run the seeds, print one table (or ``--json``); exit 1 if a run gave no time to identity."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("lab", type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    rows = []
    for seed in a.seeds:
        v = one(a.lab, seed, virtual=True)
        live = one(a.lab, seed, virtual=False)
        tv, tl = v.get("time_to_identity_s"), live.get("time_to_identity_s")
        row = {"seed": seed, "virtual_s": tv, "live_s": tl, "ratio": None if not (tv and tl) else tl / tv,
               "load_avg": live["load_avg"], "same_identity": v.get("identity") == live.get("identity"),
               "virtual_ratio_to_bound": v.get("ratio_to_bound"), "live_ratio_to_bound": live.get("ratio_to_bound"),
               "excess_s": {s: round((live.get("stages") or {}).get(s, 0.0) - (v.get("stages") or {}).get(s, 0.0), 3)
                            for s in STAGES},
               "startup_s": (live.get("startup_s") or {}).get("first_tracked_frame"),
               "errors": [r["error"] for r in (v, live) if "error" in r]}
        rows.append(row)
    if a.json:
        print(json.dumps(rows, indent=1))
    else:
        print("seed  virtual  live   ratio  load | excess of the live run by stage (s): " + " ".join(STAGES))
        for r in rows:
            ex = " ".join(f"{r['excess_s'][s]:+.2f}" for s in STAGES)
            print(f"{r['seed']:>4}  {r['virtual_s'] or float('nan'):6.2f}  {r['live_s'] or float('nan'):5.2f}  "
                  f"{r['ratio'] or float('nan'):5.2f}  {r['load_avg']:4.1f} | {ex}  {' '.join(r['errors'])}")
        ratios = [r["ratio"] for r in rows if r["ratio"]]
        if ratios:
            print(f"median ratio live/virtual {statistics.median(ratios):.3f}")
    return 0 if all(r["ratio"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
