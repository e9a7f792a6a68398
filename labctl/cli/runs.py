"""``labctl runs list|show|prune`` and ``labctl export``: the lab's run records by id or path."""

from __future__ import annotations

import shutil
from pathlib import Path

import click

from ._common import emit, get_ctx, json_option


def _is_record(path: Path) -> bool:
    return path.is_dir() and ((path / "meta.json").is_file() or (path / "events.jsonl").is_file())


def _is_sweep(path: Path) -> bool:
    return path.is_dir() and (path / "spec.json").is_file()


def resolve_run(text: str, *, sweeps: bool = False) -> Path:
    """A run record (or, with ``sweeps``, a trials sweep) named by path or by its id under the lab's runs/.

    ``last`` names the newest record. Raises UserInputError (exit 2) in one line otherwise."""
    from ..errors import UserInputError

    ok = (lambda p: _is_record(p) or _is_sweep(p)) if sweeps else _is_record
    path = Path(text).expanduser()
    if ok(path):
        return path
    runs_dir = Path(get_ctx().lab().runs_dir)
    if text == "last":
        records = [p for p in _records(runs_dir) if _is_record(p)]
        if records:
            return records[-1]
        raise UserInputError(f"no run records in {runs_dir}")
    if "/" not in text and ok(runs_dir / text):
        return runs_dir / text
    what = "a run record or trials sweep" if sweeps else "a run record"
    if path.is_dir():
        raise UserInputError(f"{text} is not {what} (no meta.json or events.jsonl); list them with: labctl runs list")
    raise UserInputError(f"no run {text!r} (not a folder, nor an id in {runs_dir}); list them with: labctl runs list")


def _records(runs_dir: Path) -> list[Path]:
    if not runs_dir.is_dir():
        return []
    return sorted(p for p in runs_dir.iterdir() if _is_record(p) or _is_sweep(p))


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def _summary(path: Path) -> dict:
    from ..records.record import RecordError, load_run

    if _is_sweep(path):
        import json

        summary = path / "summary.json"
        data = json.loads(summary.read_text()) if summary.is_file() else {}
        n = sum(r.get("n", 0) for r in data.get("by_speed", []))
        return {"id": path.name, "kind": "trials", "finished": summary.is_file(), "trials": n,
                "identity": None, "correct": None, "failure": None, "bytes": _size(path)}
    try:
        run = load_run(path)
    except RecordError as exc:
        return {"id": path.name, "kind": "run", "finished": False, "failure": str(exc), "bytes": _size(path)}
    res = run.result or {}
    return {"id": path.name, "kind": "run", "finished": run.finished, "command": run.meta.get("command"),
            "identity": res.get("identity"), "correct": res.get("correct"), "failure": res.get("failure"),
            "time_to_identity_s": res.get("time_to_identity_s"), "bytes": _size(path)}


@click.group("runs")
def runs_group() -> None:
    """The lab's run records: list them, show one, prune old ones."""


@runs_group.command("list")
@json_option
def runs_list() -> None:
    """Every run record and trials sweep under the lab's runs/, oldest first, with its outcome and size."""
    runs_dir = Path(get_ctx().lab().runs_dir)
    rows = [_summary(p) for p in _records(runs_dir)]
    total = sum(r["bytes"] for r in rows)

    def human(con):
        from rich.table import Table

        t = Table("id", "kind", "identity", "correct", "failure", "MB", title=f"runs in {runs_dir}")
        for r in rows:
            t.add_row(r["id"], r["kind"], str(r.get("identity") or "-"), str(r.get("correct", "-")),
                      (r.get("failure") or "-")[:50], f"{r['bytes'] / 1e6:.1f}")
        con.print(t)
        con.print(f"{len(rows)} records, {total / 1e6:.1f} MB; next: labctl runs show ID, labctl report ID, "
                  f"or labctl runs prune --keep N")

    emit({"runs_dir": str(runs_dir), "runs": rows, "bytes": total}, human)


@runs_group.command("show")
@click.argument("run")
@json_option
def runs_show(run: str) -> None:
    """One record's outcome, by id (``labctl runs list``), ``last`` or path."""
    path = resolve_run(run, sweeps=True)
    data = {"path": str(path), **_summary(path)}

    def human(con):
        for k, v in data.items():
            con.print(f"{k}: {v}", highlight=False)
        con.print(f"next: labctl report {path.name}  (or labctl export {path.name} --mcap {path.name}.mcap)")

    emit(data, human)


@runs_group.command("prune")
@click.option("--keep", type=click.IntRange(min=0), required=True, help="Keep the newest KEEP records.")
@click.option("--sweeps/--no-sweeps", default=False, help="Also prune trials sweeps.  [default: no-sweeps]")
@click.option("--dry-run", is_flag=True, help="Say what would be removed; remove nothing.")
@json_option
def runs_prune(keep: int, sweeps: bool, dry_run: bool) -> None:
    """Remove all but the newest KEEP run records (sweeps only with --sweeps)."""
    runs_dir = Path(get_ctx().lab().runs_dir)
    candidates = [p for p in _records(runs_dir) if sweeps or not _is_sweep(p)]
    doomed = candidates[:max(0, len(candidates) - keep)]
    freed = 0
    for p in doomed:
        freed += _size(p)
        if not dry_run:
            shutil.rmtree(p)
    data = {"removed": [p.name for p in doomed], "kept": len(candidates) - len(doomed), "bytes_freed": freed,
            "dry_run": dry_run}

    def human(con):
        verb = "would remove" if dry_run else "removed"
        con.print(f"{verb} {len(doomed)} records ({freed / 1e6:.1f} MB), kept {data['kept']}")

    emit(data, human)


@click.command("export")
@click.argument("run")
@click.option("--mcap", "mcap_path", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Write the run as MCAP with Foxglove's schemas (opens in Foxglove or any MCAP reader).")
@click.option("--force", is_flag=True, help="Replace MCAP_PATH if it exists.")
@json_option
def export_cmd(run: str, mcap_path: Path, force: bool) -> None:
    """Export RUN (id, ``last`` or path) to a file other robotics tools open."""
    from ..errors import UserInputError
    from ..records import load_run
    from ..records.mcap_export import export_mcap

    path = resolve_run(run)
    if mcap_path.exists() and not force:
        raise UserInputError(f"{mcap_path} exists; pass --force to replace it")
    if not mcap_path.parent.is_dir():
        raise UserInputError(f"no folder {mcap_path.parent} for {mcap_path.name}")
    counts = export_mcap(load_run(path), mcap_path)
    size = mcap_path.stat().st_size
    data = {"run": str(path), "mcap": str(mcap_path), "messages": counts, "bytes": size}

    def human(con):
        con.print(f"wrote {mcap_path} ({sum(counts.values())} messages, {size / 1e6:.1f} MB): "
                  + ", ".join(f"{k} {v}" for k, v in counts.items()))
        con.print("next: open it in Foxglove (File > Open local file), or read it with the mcap package")

    emit(data, human)
