"""``labctl report RUN``: (re)draw a run's report from its record."""

from __future__ import annotations

import click

from ._common import emit, json_option


@click.command("report")
@click.argument("run_ref", metavar="RUN")
@json_option
def report_cmd(run_ref: str) -> None:
    """Write RUN's report.html and report.png from its record (RUN: an id from ``labctl runs list``,
    ``last`` or a path); a failed run's report leads with why."""
    from ..errors import UserInputError
    from ..records import load_run, write_report
    from ..records.report import failure_reason
    from .runs import resolve_run

    run = resolve_run(run_ref)
    if not (run / "meta.json").is_file():
        raise UserInputError(f"{run} is not a run record (no meta.json)")
    out = write_report(run)
    reason = failure_reason(load_run(run))
    data = {"report": str(out), "failed": reason is not None, "failure": reason}

    def human(console):
        if reason is not None:
            console.print(f"[bold red]run failed:[/] {reason}", highlight=False)
        console.print(f"report: {out}")

    emit(data, human)
