"""``labctl report RUN``: (re)draw a run's report from its record."""

from __future__ import annotations

import click

from ._common import emit, json_option


def match_gates(ctx, run_dir) -> dict[int, dict[str, str]]:
    """For each recorded standard view k, the gate that dropped each library object whose score is null:
    ``{k: {object: "height" | "shape"}}``. The recorded standard image is scored again against the
    library (``view_scores``: the eccentricity/size gates only); an object with a view that passes them
    but none that also lets its marker rest at the measured height (``height_gate``) fell to the
    marker-height gate. A view whose scores do not come out as recorded (the library changed since) is
    left out, so the report never names a gate it cannot show."""
    import math

    import cv2
    import numpy as np

    from ..library.matching import height_gate, view_scores
    from ..library.views import mm_per_px
    from ..records import load_run
    from ..records.events import spec
    from ..vision.shape import features_from_image

    match = spec("match")
    run = load_run(run_dir)
    scale = mm_per_px(ctx.mobile_camera, ctx.lab.config.viewing.standoff_mm)
    _, ids = ctx.index.name_ids()
    names = np.asarray(ctx.index.names)
    out: dict[int, dict[str, str]] = {}
    for e in run.of(match.name):
        k, scores = match.valid(e, "view"), match.valid(e, "scores")
        img = cv2.imread(str(run.path / f"standard_{k}.png"), cv2.IMREAD_UNCHANGED) if k is not None else None
        if img is None or scores is None:
            continue
        try:
            s = view_scores(features_from_image(img, scale), ctx.index)
        except Exception:  # noqa: BLE001 — a view that cannot be scored again names no gate
            continue
        h, tol = match.valid(e, "marker_height_mm"), match.valid(e, "height_tol_mm")
        g = height_gate(ctx.index, h, tol) if h is not None and tol is not None else np.ones(len(s), bool)
        gates, same = {}, True
        for name, rec in scores.items():
            rows = names == name
            if not rows.any():
                same = False
                break
            shape_ok = np.isfinite(s[rows])
            if rec is not None:  # the recorded score must come out again (the height gate only drops)
                both = shape_ok & g[rows]
                got = [float(np.min(s[rows][m])) for m in (shape_ok, both) if m.any()]  # gate ignored, or applied
                same = same and any(math.isclose(x, float(rec), rel_tol=1e-6, abs_tol=1e-9) for x in got)
                continue
            gates[name] = "height" if shape_ok.any() and not (shape_ok & g[rows]).any() else "shape"
        if same:
            out[int(k)] = gates
    return out


def report_gates(ctx, run_dir) -> dict[int, dict[str, str]] | None:
    """:func:`match_gates`, or None when the record cannot be scored again (the report then says
    "gated out" without naming which gate)."""
    try:
        return match_gates(ctx, run_dir)
    except Exception:  # noqa: BLE001 — the report is drawn all the same
        return None


@click.command("report")
@click.argument("run_ref", metavar="RUN")
@json_option
def report_cmd(run_ref: str) -> None:
    """Write RUN's report.html and report.png from its record (RUN: an id from ``labctl runs list``,
    ``last`` or a path); a failed run's report leads with why."""
    from ..errors import UserInputError
    from ..records import load_run, write_report
    from ..records.report import failure_reason
    from ._common import get_ctx
    from .runs import resolve_run

    run = resolve_run(run_ref)
    if not (run / "meta.json").is_file():
        raise UserInputError(f"{run} is not a run record (no meta.json)")
    try:
        from ..decisions.context import RunContext

        ctx = RunContext.load(get_ctx().lab())
    except Exception:  # noqa: BLE001 — a record read away from its lab still gets its report
        ctx = None
    out = write_report(run, gates=report_gates(ctx, run) if ctx is not None else None)
    reason = failure_reason(load_run(run))
    data = {"report": str(out), "failed": reason is not None, "failure": reason}

    def human(console):
        if reason is not None:
            console.print(f"[bold red]run failed:[/] {reason}", highlight=False)
        console.print(f"report: {out}")

    emit(data, human)
