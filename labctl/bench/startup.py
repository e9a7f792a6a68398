"""``labctl bench startup``: live start-up, command to the first tracked frame of the fixed camera.

Runs ``labctl run --trajectory line --seed k`` as a fresh process ``n`` times on a fresh ``labctl init``
lab (the sample simulated lab, live: forkserver, simulated lab, both workers, the 9600-bps table) and
reads each run's ``result.json``: ``startup_s`` holds every start-up phase in s after the command's own
process started (its start time from /proc, not the bench's clock), the last one
``first_tracked_frame`` (the first ``track`` event's wall stamp). Medians per phase.

*Warm*: the page cache holds the interpreter, the packages and the lab (every run after the first).
*Cold*: the first run after ``sync; echo 3 > /proc/sys/vm/drop_caches`` — only as root; elsewhere it is
reported as not measurable rather than guessed. Byte-code caches (``__pycache__``) stay as they are in
both: a user's installed labctl has them. The runs do not inherit ``PYTHONDONTWRITEBYTECODE`` (a development
environment may set it): without it every process of every run compiled labctl's sources again, which no
installed labctl does; the first (unmeasured or cold) run writes them, as Python does for any user.

*Against a base tree*: with ``$LABCTL_BENCH_BASE`` set to another checkout (the commit before a change),
both trees are timed in the same bench, run by run alternating (the order swapped every round, one lab
each), cold and warm, and the report gives each median with the ratio new/base: on a shared machine only a
ratio timed side by side says what the code changed.

*Cold, empty cache*: the simulated lab reads its table texture, pixel rays and meshes from the disk cache
(``labctl.fsutil.cached_arrays``); one more cold run with ``$LABCTL_CACHE_DIR`` pointing at an empty folder
is a machine's very first run.

Also the command's own import cost (``python -X importtime``, the modules ``labctl run`` imports before
the simulated lab can start), largest cumulative first. The load average is reported beside every
number: on a shared machine it, not the code, sets most of the spread.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ._timing import row

DROP_CACHES = Path("/proc/sys/vm/drop_caches")
RUN_TIMEOUT_S = 180.0  # one live run on a loaded 2-core machine (≈10 s when quiet)
# what ``labctl run`` imports before its simulated lab can start (labctl/cli/run.py, in its order)
COMMAND_IMPORTS = ("import labctl.cli; import labctl.runtime.live; import labctl.decisions.context; "
                   "import labctl.records; import labctl.cli.report")


BASE_ENV = "LABCTL_BENCH_BASE"  # another checkout to time beside this one, run by run


def _env(tree: Path | None, cache_dir: Path | None = None) -> dict:
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)  # byte-code as an installed labctl has it (module docstring)
    if tree is not None:  # time another checkout (e.g. the commit before a change) with the same bench
        env["PYTHONPATH"] = str(tree)
    if cache_dir is not None:  # the simulated lab's disk cache (labctl.fsutil.cache_root)
        env["LABCTL_CACHE_DIR"] = str(cache_dir)
    return env


def can_drop_caches() -> bool:
    """True when this process may drop the page cache (root, and /proc/sys/vm writable)."""
    return os.geteuid() == 0 and os.access(DROP_CACHES, os.W_OK)


def drop_caches() -> None:
    """Write back dirty pages and drop the page cache, dentries and inodes (root only)."""
    os.sync()
    DROP_CACHES.write_text("3\n")


def one_run(lab: Path, seed: int, tree: Path | None = None, cache_dir: Path | None = None) -> dict:
    """One ``labctl run --trajectory line`` in a fresh process; its ``startup_s`` phases, the wall time of
    the whole command, its exit code and the load average when it started."""
    load = os.getloadavg()[0]
    t0 = time.time()
    proc = subprocess.run([sys.executable, "-m", "labctl", "--lab", str(lab), "--json", "run", "--trajectory",
                           "line", "--seed", str(seed)], capture_output=True, text=True, timeout=RUN_TIMEOUT_S,
                          env=_env(tree, cache_dir), cwd=lab)
    out: dict = {"seed": seed, "exit_code": proc.returncode, "command_s": round(time.time() - t0, 3),
                 "load_avg": round(load, 2)}
    try:
        result = json.loads(proc.stdout)
    except json.JSONDecodeError:
        out["error"] = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return out
    out["startup_s"] = result.get("startup_s") or {}
    out["first_tracked_frame_s"] = out["startup_s"].get("first_tracked_frame")
    out["identity"] = result.get("identity")
    return out


def import_breakdown(tree: Path | None = None, top: int = 8) -> dict:
    """The command's imports (``-X importtime``): total s and the ``top`` largest cumulative top-level-ish
    packages (s), in a fresh interpreter."""
    proc = subprocess.run([sys.executable, "-X", "importtime", "-c", COMMAND_IMPORTS], capture_output=True,
                          text=True, env=_env(tree), timeout=RUN_TIMEOUT_S)
    rows = []
    for line in proc.stderr.splitlines():
        if not line.startswith("import time:") or "|" not in line or "cumulative" in line:
            continue
        _, cum, name = line.split("|")
        depth = (len(name) - len(name.lstrip())) // 2
        rows.append((name.strip(), int(cum) / 1e6, depth))
    roots = {n: s for n, s, d in rows if d == 0 and n.startswith("labctl")}
    third = {n: s for n, s, d in rows if "." not in n and d > 0}
    biggest = sorted(third.items(), key=lambda kv: -kv[1])[:top]
    total = sum(s for _, s, d in rows if d == 0)
    return {"total_s": round(total, 3), "labctl_roots_s": {k: round(v, 3) for k, v in roots.items()},
            "largest_packages_s": {k: round(v, 3) for k, v in biggest}}


def _summary(res: dict, warm: list[dict]) -> dict:
    ok = [w for w in warm if w.get("first_tracked_frame_s") is not None]
    phases: dict[str, list[float]] = {}
    for w in ok:
        for k, v in w["startup_s"].items():
            phases.setdefault(k, []).append(v)
    res["warm"] = warm
    res["warm_median_phases_s"] = {k: round(statistics.median(v), 3)
                                   for k, v in sorted(phases.items(), key=lambda kv: statistics.median(kv[1]))}
    res["warm_first_tracked_frame_s"] = sorted(w["first_tracked_frame_s"] for w in ok)
    res["warm_failed"] = len(warm) - len(ok)
    return res


def measure(n: int, *, cold: bool = True, tree: Path | None = None, base: Path | None = None) -> dict:
    """``n`` warm runs (after one unmeasured warm-up when ``cold`` is not measured) and, as root, one
    cold run first (and one cold with an empty disk cache); medians of each phase. With ``base`` (another
    checkout) the same for it, alternating run by run, under ``"base"``."""
    trees: dict[str, Path | None] = {"new": tree} if base is None else {"new": tree, "base": base}
    with tempfile.TemporaryDirectory(prefix="labctl-bench-startup-") as tmp:
        labs = {}
        for name, t in trees.items():
            labs[name] = Path(tmp) / f"lab-{name}"
            subprocess.run([sys.executable, "-m", "labctl", "init", str(labs[name])], check=True,
                           capture_output=True, env=_env(t), timeout=RUN_TIMEOUT_S)
        out: dict[str, dict] = {name: {"runs": n} for name in trees}
        measurable = cold and can_drop_caches()
        for name, t in trees.items():
            if measurable:
                drop_caches()
                out[name]["cold"] = one_run(labs[name], 1, t)
            else:
                out[name]["cold"] = {"error": "not measurable here: dropping the page cache needs root" if cold
                                     else "not asked for"}
                one_run(labs[name], 1, t)  # the warm runs then all find the cache filled
        if measurable:  # a machine's first run: nothing in the simulated lab's disk cache either
            empty = Path(tmp) / "empty-cache"
            drop_caches()
            out["new"]["cold_empty_cache"] = one_run(labs["new"], 1, tree, cache_dir=empty)
        warm: dict[str, list[dict]] = {name: [] for name in trees}
        for i in range(n):
            for name in (list(trees) if i % 2 == 0 else list(trees)[::-1]):
                warm[name].append(one_run(labs[name], 2 + i, trees[name]))
    res = _summary(out["new"], warm["new"])
    if base is not None:
        b = _summary(out["base"], warm["base"])
        res["base"] = b
        res["base_tree"] = str(base)
    return res


def _ratio(new: float | None, base: float | None) -> float | None:
    return round(new / base, 3) if new is not None and base else None


def run(quick: bool = False) -> dict:
    """Time live start-up warm (median of 2 or 5 runs) and cold (root only), plus the command's imports; beside
    the checkout ``$LABCTL_BENCH_BASE`` names, if set, with the ratios."""
    base = os.environ.get(BASE_ENV)
    res = measure(2 if quick else 5, base=Path(base) if base else None)
    res["imports"] = import_breakdown()
    rows = []

    def rows_for(r: dict, label: str, versus: dict | None) -> None:
        firsts = r["warm_first_tracked_frame_s"]
        if firsts:
            med = statistics.median(firsts)
            extra = {} if versus is None or not versus["warm_first_tracked_frame_s"] else {
                "ratio_to_base": _ratio(med, statistics.median(versus["warm_first_tracked_frame_s"]))}
            rows.append(row(f"command → first tracked frame, warm{label}", med, baseline="goal 1.5 s",
                            baseline_s=1.5, load_avg=statistics.median(w["load_avg"] for w in r["warm"]), **extra))
        for key, what in (("cold", "cold"), ("cold_empty_cache", "cold, empty disk cache")):
            c = r.get(key, {}).get("first_tracked_frame_s")
            if c is not None:
                extra = {} if versus is None else {
                    "ratio_to_base": _ratio(c, versus.get("cold", {}).get("first_tracked_frame_s"))}
                rows.append(row(f"command → first tracked frame, {what}{label}", c, baseline="goal 4 s",
                                baseline_s=4.0, load_avg=r[key]["load_avg"], **extra))

    rows_for(res, "", res.get("base"))
    if "base" in res:
        rows_for(res["base"], " (base tree)", None)
    rows.append(row("command's imports (-X importtime)", res["imports"]["total_s"]))
    res["rows"] = rows
    return res
