"""Many simulated runs in virtual time (``labctl trials``): a sweep, its executors and its summary.

A sweep is one folder, ``runs/trials-<UTC timestamp>/``:

* ``spec.json``: what was asked (trajectory, speeds, objects, seeds, lab) — enough to resume;
* ``results.jsonl``: one line per finished trial, appended as trials finish (any order);
* ``trials/<index>-seed<seed>/``: each trial's run record (unless records are off);
* ``summary.json`` and ``report.html`` (+ ``report.png``) once the sweep ends or is interrupted.

Each trial is a pure function of (lab, spec): the virtual runtime is deterministic per seed, so the
executors — in process, a local process pool (``--jobs``) or a Dask cluster (``--scheduler``) —
give identical results, and the summary is computed from results sorted by trial index.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path

from ..errors import UserInputError
from ..runtime.virtual import TrialSpec

SPEC = "spec.json"
RESULTS = "results.jsonl"
SUMMARY = "summary.json"

# Per-process cache of loaded labs and run contexts: a worker loads the lab, its calibration and its library
# once, for every trial it runs (a forked pool worker inherits the parent's).
_CONTEXTS: dict[str, tuple] = {}

# What a trial imports on its first run (``simulate_run`` imports the simulator lazily): imported once in the
# parent, or the fork server, before any worker starts, so no worker pays it on its first trial.
RUNTIME_MODULES = ("labctl.experiments.trials", "labctl.runtime.virtual", "labctl.decisions.context",
                   "labctl.decisions.predictor", "labctl.decisions.recognizer", "labctl.sim.clock", "labctl.sim.lab",
                   "labctl.sim.world", "labctl.sim.render", "labctl.runtime.simlab", "labctl.runtime.stopping",
                   "labctl.records", "labctl.records.record")


def _context(lab_root: str):
    if lab_root not in _CONTEXTS:
        from ..config import load_lab
        from ..decisions.context import RunContext

        lab = load_lab(Path(lab_root))
        _CONTEXTS[lab_root] = (lab, RunContext.load(lab))
    return _CONTEXTS[lab_root]


def warm(lab_root: str) -> None:
    """Import the runtime and load ``lab_root``'s context into this process (what every trial then reuses)."""
    import importlib

    for name in RUNTIME_MODULES:
        importlib.import_module(name)
    _context(lab_root)


def run_one(lab_root: str, index: int, spec: dict, records_dir: str | None) -> dict:
    """Run trial ``index`` (a :class:`TrialSpec` as a dict) and return its JSON-able result.

    Top-level and argument-only so that process pools and Dask workers can call it."""
    from ..records import RunRecord
    from ..records.record import to_jsonable
    from ..runtime.virtual import simulate_run

    lab, ctx = _context(lab_root)
    trial = TrialSpec(**spec)
    rec = None
    if records_dir is not None:
        rec = RunRecord.create(records_dir, {"command": "trials", "index": index, **spec}, durable=False)
        # Rename to a stable, sortable name: the record of trial k is trials/<k>-seed<seed>/.
        stable = Path(records_dir) / f"{index:05d}-seed{trial.seed}"
        if stable.exists():  # a trial cut off by an interrupted sweep: run it again from scratch
            shutil.rmtree(stable)
        rec.path.rename(stable)
        rec = RunRecord.open(stable, durable=False)
    res = simulate_run(lab, ctx, trial, rec)
    res["index"] = index
    if rec is not None:
        res["record"] = str(rec.path)
        rec.finish(res)
        rec.close()
    return to_jsonable(res)


def plan_specs(n: int, trajectory: str | Sequence[str], speeds: Sequence[float], objects: Sequence[str], seed: int,
               profiles: Sequence[str | None] = (None,)) -> list[dict]:
    """``n`` trials per speed (per trajectory, per robot profile) with seeds ``seed, seed+1, …``; objects
    cycle through ``objects``. Every profile runs the same seeds (paired comparison)."""
    trajectories = trajectory.split(",") if isinstance(trajectory, str) else list(trajectory)
    return [asdict(TrialSpec(traj, float(v), objects[i % len(objects)], seed + i, prof))
            for prof in profiles for traj in trajectories for v in speeds for i in range(n)]


# ---- executors: each yields results as they finish -------------------------------------------------

Job = tuple[int, dict]


def _serial(lab_root: str, jobs: list[Job], records_dir: str | None) -> Iterator[dict]:
    for index, spec in jobs:
        yield run_one(lab_root, index, spec, records_dir)


def _pool(lab_root: str, jobs: list[Job], records_dir: str | None, n_jobs: int,
          start: str | None = None) -> Iterator[dict]:
    import multiprocessing as mp
    import threading
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from multiprocessing.context import BaseContext

    if start is None:
        start = "fork" if threading.active_count() == 1 else "forkserver"
    if start == "fork":
        # fork from this process once it has imported the runtime and loaded the lab: a worker then starts with
        # nothing to import or load (the pool's start was ~2 s of a 16-s sweep on 2 cores). With no other thread
        # there is no lock a child could inherit held; the pool forks all its workers before its own thread starts.
        warm(lab_root)
        ctx: BaseContext = mp.get_context("fork")
    else:
        # another thread runs (an embedding program): forkserver, a clean interpreter per worker, whose server
        # imports the runtime once and every worker forks from it with everything imported
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload(list(RUNTIME_MODULES))
    with ProcessPoolExecutor(max_workers=n_jobs, mp_context=ctx, initializer=_ignore_sigint) as pool:
        pending = {pool.submit(run_one, lab_root, i, s, records_dir) for i, s in jobs}
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    yield f.result()
        finally:
            for f in pending:
                f.cancel()


def _ignore_sigint() -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and cancels the rest


LOCAL = "local"  # --scheduler local: a Dask LocalCluster on this machine's cores


def _dask(lab_root: str, jobs: list[Job], records_dir: str | None, address: str, n_workers: int) -> Iterator[dict]:
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise UserInputError("--scheduler needs Dask: pip install 'labctl[cluster]'") from None
    cluster = None
    if address == LOCAL:
        # one single-threaded worker process per core: a trial holds the GIL throughout
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None)
        address = cluster.scheduler_address
    try:
        with Client(address) as client:
            futures = [client.submit(run_one, lab_root, i, s, records_dir, pure=False, key=f"trial-{i}")
                       for i, s in jobs]
            try:
                for f in as_completed(futures):
                    yield f.result()
            finally:
                client.cancel(futures)
    finally:
        if cluster is not None:
            cluster.close()


def execute(lab_root: str, jobs: list[Job], records_dir: str | None, *, n_jobs: int = 1,
            scheduler: str | None = None, pool_start: str | None = None) -> Iterator[dict]:
    """Run ``jobs`` with the chosen executor, yielding each result when it finishes.

    ``scheduler``: a Dask scheduler's address (``tcp://host:8786``), or ``"local"`` for a LocalCluster of
    ``n_jobs`` worker processes on this machine. ``pool_start``: how the process pool starts its workers,
    ``"fork"`` (from this process, warmed first) or ``"forkserver"``; None: fork unless another thread runs
    (``labctl bench trials`` times both)."""
    if scheduler:
        return _dask(lab_root, jobs, records_dir, scheduler, max(1, min(n_jobs, len(jobs))))
    if n_jobs > 1 and len(jobs) > 1:
        return _pool(lab_root, jobs, records_dir, min(n_jobs, len(jobs)), pool_start)
    return _serial(lab_root, jobs, records_dir)


# ---- the sweep folder ---------------------------------------------------------------------------------

class Sweep:
    """One sweep's folder: its spec, the results so far (append-only) and the summary."""

    def __init__(self, path: Path):
        self.path = Path(path)

    @classmethod
    def create(cls, runs_dir: Path, spec: dict) -> Sweep:
        """A new sweep folder ``trials-<time>`` under ``runs_dir`` holding ``spec``."""
        from ..fsutil import atomic_write_text

        runs_dir.mkdir(parents=True, exist_ok=True)
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        for k in range(1000):
            path = runs_dir / (f"trials-{stamp}" if k == 0 else f"trials-{stamp}-{k:03d}")
            try:
                path.mkdir()
                break
            except FileExistsError:
                continue
        else:
            raise UserInputError(f"more than 1000 sweeps started at {stamp} in {runs_dir}")
        atomic_write_text(path / SPEC, json.dumps(spec, indent=2) + "\n")
        (path / RESULTS).touch()
        return cls(path)

    @classmethod
    def open(cls, path: Path) -> Sweep:
        """An existing sweep folder; raises UserInputError when it holds no sweep spec."""
        path = Path(path)
        if not (path / SPEC).is_file():
            raise UserInputError(f"{path} is not a trials sweep (no {SPEC})")
        return cls(path)

    @property
    def spec(self) -> dict:
        """The sweep's spec (trajectory, speeds, objects, seeds)."""
        try:
            return json.loads((self.path / SPEC).read_text())
        except (OSError, ValueError) as exc:
            raise UserInputError(f"{self.path / SPEC}: unreadable sweep spec ({exc})") from None

    def results(self) -> dict[int, dict]:
        """Finished results by trial index; a torn last line (a crash mid-write) is ignored."""
        out: dict[int, dict] = {}
        try:
            lines = (self.path / RESULTS).read_text().splitlines()
        except FileNotFoundError:
            return out
        for line in lines:
            try:
                r = json.loads(line)
            except ValueError:
                continue
            out[int(r["index"])] = r
        return out

    def append(self, result: dict) -> None:
        """Append one trial's result to the results file (one JSON line, appended in one write)."""
        line = (json.dumps(result, allow_nan=False) + "\n").encode()
        fd = os.open(self.path / RESULTS, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line)
        finally:
            os.close(fd)

    def finish(self, summary: dict) -> None:
        """Write the summary and the sweep's report."""
        from ..fsutil import atomic_write_text
        from ..records.sweep_report import write_sweep_report

        atomic_write_text(self.path / SUMMARY, json.dumps(summary, indent=2, allow_nan=False) + "\n")
        write_sweep_report(self.path, summary)


def library_digest(library_dir: Path) -> str:
    """SHA-256 over a library folder's files (relative path and bytes, in path order): which library a
    sweep ran against, for its report."""
    import hashlib

    h = hashlib.sha256()
    for p in sorted(q for q in library_dir.rglob("*") if q.is_file() and not q.name.startswith(".")):
        h.update(str(p.relative_to(library_dir)).encode() + b"\0")
        h.update(p.read_bytes())
    return h.hexdigest()


def run_sweep(lab, *, n: int, trajectory: str | Sequence[str], speeds: Sequence[float], objects: Sequence[str] | None,
              seed: int = 0, record: bool = True, keep: str = "all", n_jobs: int = 1, scheduler: str | None = None,
              profiles: Sequence[str | None] = (None,),
              resume: Path | None = None, on_result: Callable[[dict, int, int], None] | None = None,
              on_sweep: Callable[[Path], None] | None = None) -> dict:
    """Run (or resume) a sweep and return its summary; the summary is also written to the folder.

    ``keep``: "all" keeps every trial's record, "failures" deletes the record of each correct trial as it
    finishes (its result stays, with ``record`` null), so a long sweep keeps images only where something
    went wrong. ``on_sweep(folder)`` is called once the sweep's folder exists (a live view follows its
    trials). ``on_result(result, done, total)`` is called after each finished trial (progress). On
    KeyboardInterrupt the partial summary is written and attached to the exception as ``.summary``."""
    if resume is not None:
        sweep = Sweep.open(resume)
        spec = sweep.spec
    else:
        ctx = _context(str(lab.root))[1]  # fails early, in one line, without a calibration or a library
        names = list(objects) if objects else list(ctx.names)
        missing = [o for o in names if o not in ctx.library]
        if missing:
            raise UserInputError(f"no object {missing[0]!r} in the library (have: {', '.join(ctx.names)})")
        spec = {"lab": str(lab.root), "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "library": str(lab.library_dir), "library_sha256": library_digest(Path(lab.library_dir)),
                "trajectory": trajectory, "speeds": [float(v) for v in speeds],
                "objects": names, "n": n, "seed": seed, "record": record, "keep": keep,
                "profiles": list(profiles), "trials": plan_specs(n, trajectory, speeds, names, seed, profiles)}
        sweep = Sweep.create(Path(lab.runs_dir), spec)
    if on_sweep is not None:
        on_sweep(sweep.path)
    done = sweep.results()
    jobs = [(i, s) for i, s in enumerate(spec["trials"]) if i not in done]
    records_dir = str(sweep.path / "trials") if spec.get("record", True) else None
    total = len(spec["trials"])
    t0 = time.monotonic()
    try:
        for res in execute(spec["lab"], jobs, records_dir, n_jobs=n_jobs, scheduler=scheduler):
            if spec.get("keep") == "failures" and res.get("correct") and res.get("record"):
                shutil.rmtree(res["record"], ignore_errors=True)  # only where something went wrong
                res = {**res, "record": None}
            sweep.append(res)
            done[res["index"]] = res
            if on_result is not None:
                on_result(res, len(done), total)
    except KeyboardInterrupt as exc:
        summary = _finish(sweep, done, total, time.monotonic() - t0, interrupted=True)
        exc.summary = summary  # type: ignore[attr-defined]
        raise
    return _finish(sweep, done, total, time.monotonic() - t0, interrupted=False)


def _finish(sweep: Sweep, done: dict[int, dict], total: int, wall_s: float, *, interrupted: bool) -> dict:
    summary = summarize([done[i] for i in sorted(done)])
    summary.update({"sweep": str(sweep.path), "planned": total, "interrupted": interrupted, "wall_s": wall_s})
    sweep.finish(summary)
    return summary


# ---- the summary ----------------------------------------------------------------------------------------

STAGE_ORDER = ("wait", "track", "intercept", "initial", "standard", "match", "done", "failed")


def _median(values: Iterable) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def _cell(rs: list[dict]) -> dict:
    """One trajectory's (or trajectory × speed cell's) trials: n, success, median time to identity (s) and
    median ``ratio_to_bound`` (time to identity over the honest bound) of the correct ones."""
    ok = [r for r in rs if r["correct"]]
    return {"n": len(rs), "success_rate": len(ok) / len(rs) if rs else 0.0,
            "time_to_identity_s_median": _median([r["time_to_identity_s"] for r in ok]),
            "ratio_to_bound_median": _median([r["time_to_identity_s"] / r["lower_bound_s"] for r in ok
                                              if r.get("lower_bound_s")])}


def summarize(results: list[dict]) -> dict:
    """Success, time to identity and stage medians per speed; failures with their records."""
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
            "time_from_first_sight_s_median": _median([r.get("time_from_first_sight_s") for r in ok]),
            "views_mean": statistics.fmean([r["views"] for r in rs]) if rs else 0.0,
        })
    seen = {k for r in results for k in r.get("stages", {})}
    stages = [k for k in STAGE_ORDER if k in seen] + sorted(seen - set(STAGE_ORDER))
    stage_medians = {k: _median([r["stages"].get(k) for r in results if r["correct"]]) for k in stages}
    link_util = [r["link"]["utilisation"] for r in results if "link" in r]
    by_profile = []
    for prof in sorted({r.get("profile") or "" for r in results}):  # robot segment profiles
        rs = [r for r in results if (r.get("profile") or "") == prof]
        ok = [r for r in rs if r["correct"]]
        by_profile.append({"profile": prof or None, "n": len(rs), "success_rate": len(ok) / len(rs),
                           "time_to_identity_s_median": _median([r["time_to_identity_s"] for r in ok]),
                           "stage_medians_s": {k: v for k in stages
                                               if (v := _median([r["stages"].get(k) for r in ok])) is not None}})
    ok_all = [r for r in results if r["correct"]]
    overall = {
        "time_to_identity_s_median": _median([r["time_to_identity_s"] for r in ok_all]),
        "time_from_first_sight_s_median": _median([r.get("time_from_first_sight_s") for r in ok_all]),
        "lower_bound_s_median": _median([r.get("lower_bound_s") for r in ok_all]),
        "ratio_to_lower_bound_median": _median([r["time_to_identity_s"] / r["lower_bound_s"] for r in ok_all
                                                if r.get("lower_bound_s")]),
    }
    by_traj = {t: {**_cell(rs), "wait_s_median": _median([r["stages"].get("wait") for r in rs if r["correct"]]),
                   "by_speed": {f"{v:g}": _cell([r for r in rs if r["speed_mm_s"] == v])
                                for v in sorted({r["speed_mm_s"] for r in rs})}}
               for t in sorted({r["trajectory"] for r in results if r.get("trajectory") is not None})
               for rs in [[r for r in results if r.get("trajectory") == t]]}
    return {
        "n": len(results),
        "success_rate": sum(r["correct"] for r in results) / len(results) if results else 0.0,
        "by_speed": by_speed,
        "overall": overall,
        "by_trajectory": by_traj,
        "stage_medians_s": {k: v for k, v in stage_medians.items() if v is not None},
        "by_profile": by_profile,
        "link_utilisation_median": _median(link_util),
        "failed": [{k: r.get(k) for k in ("index", "seed", "true_identity", "identity", "speed_mm_s", "failure",
                                          "record")}
                   for r in results if not r["correct"]],
        "trials": results,
    }
