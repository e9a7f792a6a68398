"""``labctl trials``: many simulated runs in virtual time, on this machine's cores or a Dask cluster."""

from __future__ import annotations

import os
from pathlib import Path

import click

from ..errors import UserInputError
from ._common import emit, get_ctx, json_option, live_console
from .run import TRAJECTORIES, _speed


@click.command("trials")
@click.option("--n", "n", type=int, default=20, show_default=True, help="Number of simulated runs per speed.")
@click.option("--trajectory", default=None,
              help="line, arc, circle or zigzag, or a comma-separated list to sweep (default: lab.yaml).")
@click.option("--profile", "profile", default=None,
              help="Robot segment profile quintic or ruckig, or a comma-separated list to compare on the same seeds "
                   "(default: lab.yaml's run.profile).")
@click.option("--speed", default=None, help="Table speed mm/s, or a comma-separated list to sweep.")
@click.option("--objects", default=None, help="Comma-separated objects to cycle through (default: all).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the first trial.")
@click.option("--record/--no-record", default=True, show_default=True, help="Keep a run record per trial.")
@click.option("--keep", type=click.Choice(["all", "failures"]), default="all", show_default=True,
              help="Which trials' records to keep: all, or only those that failed (their images and events; the "
                   "others' results stay in results.jsonl).")
@click.option("--view", is_flag=True, help="Serve a live view of the trial being run on a local web page (its URL "
              "goes to stderr), with a Stop button (Ctrl-C's path: the partial summary is kept).")
@click.option("--view-port", type=click.IntRange(0, 65535), default=None,
              help="The live view's port (default: lab.yaml view.port; 0: any free port).")
@click.option("--jobs", "-j", type=int, default=None, help="Worker processes (default: all cores).")
@click.option("--scheduler", default=None, metavar="local|ADDRESS",
              help="Run on Dask instead of a local process pool: 'local' starts a LocalCluster of --jobs workers, "
                   "ADDRESS (tcp://host:8786) uses a running cluster's scheduler (pip install 'labctl[cluster]').")
@click.option("--resume", type=click.Path(path_type=Path), default=None,
              help="Continue an interrupted sweep folder (runs/trials-…); other options are ignored.")
@json_option
def trials_cmd(n, trajectory, profile, speed, objects, seed, record, keep, view, view_port, jobs, scheduler,
               resume) -> None:
    """Many simulated runs in virtual time with deterministic seeds, in parallel.

    Writes one folder, runs/trials-<time>/: spec, per-trial results and records, summary.json and
    report.html. Results do not depend on --jobs or --scheduler. Ctrl-C keeps and prints the partial summary."""
    from ..experiments.trials import run_sweep

    c = get_ctx()
    lab = c.lab()
    if n < 1:
        raise UserInputError(f"--n must be at least 1, got {n}")
    n_jobs = (os.cpu_count() or 1) if jobs is None else jobs
    if n_jobs < 1:
        raise UserInputError(f"--jobs must be at least 1, got {jobs}")
    try:
        speeds = [float(s) for s in speed.split(",")] if speed else [lab.config.run.speed_mm_s]
    except ValueError:
        raise UserInputError(f"--speed must be numbers separated by commas, got {speed!r}") from None
    for s in speeds:
        _speed(s, lab)
    names = [o.strip() for o in objects.split(",") if o.strip()] if objects else None
    trajs = [t.strip() for t in (trajectory or lab.config.run.trajectory).split(",") if t.strip()]
    for traj in trajs or [""]:
        if traj not in TRAJECTORIES:
            raise UserInputError(f"--trajectory must be one of {', '.join(TRAJECTORIES)} (or a comma-separated "
                                  f"list), got {traj!r}")
    profiles = [p.strip().lower() for p in profile.split(",") if p.strip()] if profile else [None]
    for prof in profiles or [""]:
        if prof not in (None, "quintic", "ruckig"):
            raise UserInputError(f"--profile must be quintic or ruckig (or both, comma-separated), got {prof!r}")
    if resume is not None and not resume.is_dir():
        raise UserInputError(f"--resume: no sweep folder at {resume}")

    if view and not record:
        raise UserInputError("--view shows the trials' records: it cannot go with --no-record")
    page = None
    if view:
        from .run import _bind_view

        page = _bind_view(lab, view_port)  # a taken port: refused before the sweep starts
        click.get_current_context().call_on_close(page.close)

    def follow(folder: Path) -> None:
        if page is not None:
            page.follow_newest(folder / "trials").start()
            click.echo(f"live view: {page.url}", err=True)

    con = live_console()  # never into a piped result
    progress = _Progress(con) if con is not None else None
    try:
        with progress or _nothing():
            summary = run_sweep(lab, n=n, trajectory=trajs[0] if len(trajs) == 1 else trajs, speeds=speeds,
                                objects=names, seed=seed, record=record, keep=keep, n_jobs=n_jobs,
                                scheduler=scheduler,
                                resume=resume, profiles=profiles, on_sweep=follow,
                                on_result=progress.update if progress else None)
    except KeyboardInterrupt as exc:
        partial = getattr(exc, "summary", None)
        if partial is not None:
            emit(partial, lambda con: _print_trials(con, partial))
        raise
    emit(summary, lambda con: _print_trials(con, summary))


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


class _Progress:
    """Completed trials, the success rate so far and the time left (rich)."""

    def __init__(self, console):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        # redrawn on each finished trial, without rich's refresh thread: with no other thread running, the
        # process pool forks its workers from this process (experiments.trials._pool)
        self.bar = Progress(TextColumn("trials"), BarColumn(), MofNCompleteColumn(),
                            TextColumn("{task.fields[ok]}"), TimeRemainingColumn(), console=console, transient=True,
                            auto_refresh=False)
        self.task = None
        self.correct = 0
        self.seen = 0

    def __enter__(self):
        self.bar.start()
        return self

    def __exit__(self, *exc):
        self.bar.stop()
        return False

    def update(self, result: dict, done: int, total: int) -> None:
        self.seen += 1
        self.correct += bool(result.get("correct"))
        ok = f"success {100 * self.correct / self.seen:.1f} %"
        if self.task is None:
            self.task = self.bar.add_task("trials", total=total, completed=done, ok=ok)
        else:
            self.bar.update(self.task, completed=done, ok=ok)
        self.bar.refresh()


def _num(value, unit: str = "") -> str:
    return "-" if value is None else f"{value:.2f}{unit}"


def _ratio(value) -> str:
    return "-" if value is None else f"{value:.3f}"


def _print_trials(console, s: dict) -> None:
    from rich.table import Table

    t = Table("speed mm/s", "n", "success", "time to identity (median)", "× honest bound", "×quintic bound",
              "views (mean)", title="trials")
    for row in s["by_speed"]:
        t.add_row(f"{row['speed_mm_s']:g}", str(row["n"]), f"{100 * row['success_rate']:.1f} %",
                  _num(row["time_to_identity_s_median"], " s"), _num(row["ratio_to_lower_bound_median"]),
                  _num(row["ratio_to_quintic_bound_median"]), f"{row['views_mean']:.2f}")
    console.print(t)
    by_traj = s.get("by_trajectory") or {}
    if by_traj:  # the honest-bound ratio per trajectory and speed (median of the correct trials)
        speeds = sorted({v for row in by_traj.values() for v in row.get("by_speed", {})}, key=float)
        tt = Table("trajectory", "n", "success", *[f"× bound at {v} mm/s" for v in speeds], "× bound (all)",
                   title="× honest bound per trajectory and speed (median)")
        for name, row in by_traj.items():
            tt.add_row(name, str(row["n"]), f"{100 * row['success_rate']:.1f} %",
                       *[_ratio(row.get("by_speed", {}).get(v, {}).get("ratio_to_bound_median")) for v in speeds],
                       _ratio(row.get("ratio_to_bound_median")))
        console.print(tt)
    st = Table("stage", "median s", title="stage timings (pipeline order)")
    for k, v in s["stage_medians_s"].items():
        st.add_row(k, f"{v:.2f}")
    console.print(st)
    if len(s.get("by_profile", [])) > 1:  # robot segment profiles compared on the same seeds
        stages = list(s["stage_medians_s"])
        pt = Table("profile", "n", "success", "time to identity (median)", *stages, title="robot segment profiles")
        for row in s["by_profile"]:
            pt.add_row(str(row["profile"]), str(row["n"]), f"{100 * row['success_rate']:.1f} %",
                       _num(row["time_to_identity_s_median"], " s"),
                       *[_num(row["stage_medians_s"].get(k), "") for k in stages])
        console.print(pt)
    o = s.get("overall") or {}
    if o.get("time_to_identity_s_median") is not None:
        console.print(f"all speeds: time to identity median {_num(o['time_to_identity_s_median'], ' s')} "
                      f"({_num(o.get('time_from_first_sight_s_median'), ' s')} from first sight), "
                      f"{_num(o.get('ratio_to_lower_bound_median'))}× the honest bound")
    from ..records.sweep_report import wilson_interval

    k = sum(bool(t.get("correct")) for t in s.get("trials", []))
    lo, hi = wilson_interval(k, s["n"])
    console.print("× honest bound: time to identity over first sight + the legs' minimum time + frame times "
                  "(≥ 1); × quintic bound: over the paper's quintic legs, which a jerk-limited run can beat "
                  "(< 1 possible)", highlight=False)
    head = f"success rate {100 * s['success_rate']:.1f} % of {s['n']} trials (95 % CI {100 * lo:.1f}–{100 * hi:.1f} %)"
    if s.get("interrupted"):
        head += f" (interrupted: {s['n']} of {s.get('planned')} done; --resume {s['sweep']} continues)"
    console.print(head)
    for f in s["failed"]:
        console.print(f"[red]failed[/] seed {f['seed']} {f['true_identity']} @ {f['speed_mm_s']} mm/s: "
                      f"{f.get('failure') or 'identified as ' + str(f.get('identity'))}  {f.get('record') or ''}")
    if s.get("sweep"):
        console.print(f"sweep: {s['sweep']}  (report.html, summary.json)")
