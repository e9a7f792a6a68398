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
            if res.get("rows"):
                console.print(t)
            _print_extra(console, name, {k: v for k, v in res.items() if k not in ("rows", "ratio_means")})
        console.print(f"ratio: {RATIO_MEANS}. Medians; --json gives every number.", soft_wrap=True,
                      highlight=False)

    emit(results, human)


RATIO_MEANS = "the baseline's median time ÷ this case's median time, both timed in this run (> 1: faster)"


def _print_extra(console, area: str, extra: dict) -> None:
    """An area's other results as tables: scalars (nested keys dotted) in one, each list of records in its own."""
    from rich.table import Table

    scalars = Table("result", "value", title=f"bench {area}: results", title_justify="left")
    for key, value in extra.items():
        if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            cols = list(dict.fromkeys(k for v in value for k in v))
            t = Table(*cols, title=f"bench {area}: {key}", title_justify="left")
            for v in value:
                t.add_row(*(_cell(v.get(c)) for c in cols))
            console.print(t)
            continue
        for k, v in _leaves(value, key):
            scalars.add_row(k, _cell(v))
    if scalars.row_count:
        console.print(scalars)


def _leaves(value, key: str):
    """(dotted key, value) of each leaf of nested dicts; lists stay whole (one cell)."""
    if isinstance(value, dict) and value:
        for k, v in value.items():
            yield from _leaves(v, f"{key}.{k}")
    else:
        yield key, value


def _cell(v) -> str:
    from rich.markup import escape

    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return ", ".join(_cell(x) for x in v)
    return escape("-" if v is None else str(v))


def _fmt_s(s) -> str:
    if not isinstance(s, int | float):
        return "-"
    return f"{s * 1e6:.1f} µs" if s < 1e-3 else f"{s * 1e3:.2f} ms" if s < 1 else f"{s:.2f} s"
