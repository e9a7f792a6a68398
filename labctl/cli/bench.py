"""``labctl bench NAME``: time the hot paths against baselines measured in the same run.

Each area lives in ``labctl/bench/<name>.py`` and provides ``run(quick: bool) -> dict`` whose
``rows`` are ``{"case", "median_s", "baseline", "ratio", ...}`` and whose other keys are
free-form results (accuracies, rates). Medians only; ratios are against the baseline timed in
the same process, so a busy machine shifts both.
"""

from __future__ import annotations

import importlib
import pkgutil

import click

from ._common import emit, json_option


def _areas() -> list[str]:
    from .. import bench

    return sorted(m.name for m in pkgutil.iter_modules(bench.__path__) if not m.name.startswith("_"))


@click.command("bench")
@click.argument("names", nargs=-1)
@click.option("--quick", is_flag=True, help="Fewer repetitions (a smoke run).")
@json_option
def bench_group(names: tuple[str, ...], quick: bool) -> None:
    """Time the hot paths (areas: vision, planning, recognition, sim, devices, …; default all)."""
    from ..errors import UserInputError

    areas = _areas()
    unknown = [n for n in names if n not in areas]
    if unknown:
        raise UserInputError(f"unknown bench area {unknown[0]!r} (have: {', '.join(areas)})")
    results = {}
    for name in names or areas:
        results[name] = importlib.import_module(f"labctl.bench.{name}").run(quick=quick)

    def human(console):
        from rich.table import Table

        for name, res in results.items():
            t = Table("case", "median", "baseline", "ratio", title=f"bench {name}")
            for r in res.get("rows", []):
                ratio = r.get("ratio")
                t.add_row(str(r.get("case")), _fmt_s(r.get("median_s")), str(r.get("baseline") or "-"),
                          f"{ratio:.2f}×" if isinstance(ratio, int | float) else "-")
            console.print(t)
            extra = {k: v for k, v in res.items() if k != "rows"}
            if extra:
                console.print(extra)

    emit(results, human)


def _fmt_s(s) -> str:
    if not isinstance(s, int | float):
        return "-"
    return f"{s * 1e6:.1f} µs" if s < 1e-3 else f"{s * 1e3:.2f} ms" if s < 1 else f"{s:.2f} s"
