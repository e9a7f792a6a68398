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

    emit(results, lambda console: print_bench(console, results))


def print_bench(console, results: dict) -> None:
    """Every area's rows and other results as tables that fit the console's width."""
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
    console.print(f"ratio: {RATIO_MEANS}. Medians; --json gives every number.", highlight=False)


RATIO_MEANS = "the baseline's median time ÷ this case's median time, both timed in this run (> 1: faster)"


def _print_extra(console, area: str, extra: dict) -> None:
    """An area's other results as tables: scalars (nested keys dotted) in one, each list of records in its own
    (:func:`_record_tables`)."""
    from rich.table import Table

    scalars = Table(title=f"bench {area}: results", title_justify="left")
    scalars.add_column("result", overflow="fold")
    scalars.add_column("value", overflow="fold")
    for key, value in extra.items():
        if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            for t in _record_tables(f"bench {area}: {key}", value, console.width):
                console.print(t)
            continue
        for k, v in _leaves(value, key):
            scalars.add_row(k, _cell(v))
    if scalars.row_count:
        console.print(scalars)


def _record_tables(title: str, records: list[dict], width: int) -> list:
    """A list of records as tables no wider than ``width`` columns: nested values flattened to one cell each
    (``a.b`` keys, never a dict in a cell); the records' text columns (their names) repeated in every table
    and the numbers split over as many tables as it takes to fit."""
    from rich.table import Table

    flat = [{k[1:]: v for k, v in _leaves(r, "")} for r in records]
    cols = list(dict.fromkeys(k for r in flat for k in r))
    ids = [c for c in cols if all(isinstance(r.get(c), str | type(None)) for r in flat)]
    nums = [c for c in cols if c not in ids]
    cells = [{c: _cell(r.get(c)) for c in cols} for r in flat]

    name = " / ".join(ids) or "#"
    for i, x in enumerate(cells):  # the text columns as one name column, wrapped at ID_WIDTH
        x[name] = " / ".join(x[c] for c in ids) if ids else str(i + 1)

    def need(c: str) -> int:  # a column's width: its widest cell or its header's longest word
        head = max((len(w) for w in c.replace(".", " ").replace("_", " ").split()), default=1)
        return max(head, max(len(x[c]) for x in cells))

    def table(chunk: list[str], part: str = ""):
        t = Table(title=title + part, title_justify="left")
        w = min(need(name), ID_WIDTH)
        t.add_column(name, min_width=w, max_width=w, overflow="fold")
        for c in chunk:
            t.add_column(c.replace(".", " ").replace("_", " "), justify="right", overflow="fold",
                         min_width=need(c), max_width=need(c))
        for x in cells:
            t.add_row(*(x[c] for c in [name, *chunk]))
        return t

    def fits(chunk: list[str]) -> bool:  # each column at its minimum, 1 padding each side, 1 rule between
        cols = [min(need(name), ID_WIDTH), *(need(c) for c in chunk)]
        return sum(cols) + 3 * len(cols) + 1 <= width

    chunks: list[list[str]] = [[]]
    for c in nums:
        if chunks[-1] and not fits([*chunks[-1], c]):
            chunks.append([])
        chunks[-1].append(c)
    n = len(chunks)
    return [table(chunk, f" ({i + 1}/{n})" if n > 1 else "") for i, chunk in enumerate(chunks)]


ID_WIDTH = 20  # the name column of a record table: wide enough for "background texture", wraps beyond


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
