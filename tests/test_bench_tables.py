"""``labctl bench`` tables at 100 columns: no line wider, no table cropped, no dict fragments or cut-off
cells — on a real ``bench vision --quick`` result (trimmed: 5 of its degradation cases) and on a
synthetic record list that is wider still."""

from __future__ import annotations

import io
import json
from pathlib import Path

from rich.console import Console

from labctl.cli.bench import print_bench

DATA = Path(__file__).parent / "data" / "bench_vision_sample.json"


def _render(monkeypatch, results: dict) -> list[str]:
    monkeypatch.setenv("COLUMNS", "100")
    out = io.StringIO()
    print_bench(Console(file=out, color_system=None), results)  # the width from COLUMNS, as in a terminal
    return out.getvalue().splitlines()


def _check(lines: list[str]) -> None:
    assert lines and max(len(x) for x in lines) <= 100
    text = "\n".join(lines)
    cells = text.replace("the baseline's", "").replace("this case's", "")
    assert "{" not in cells and "':" not in cells  # no dict's repr in a cell
    assert "…" not in text  # no cell or table cut short
    for line in lines:  # every table row closes with its right border: nothing cropped at the edge
        if line[:1] in "┏┃┡│└":
            assert line.rstrip()[-1] in "┓┃┩│┘", line


def test_bench_vision_fits_100_columns(monkeypatch):
    results = json.loads(DATA.read_text())
    lines = _render(monkeypatch, results)
    _check(lines)
    text = "\n".join(lines)
    # every number of every record is shown, once flattened: e.g. the paired difference of the first case
    first = results["vision"]["suite"][0]
    assert f"{first['paired']['normal_deg_p95']['diff']:.4g}" in text
    assert "condition / strength" in text and "clean / -" in text


def test_a_wide_record_list_is_split_into_tables_that_fit(monkeypatch):
    records = [{"case": f"case number {i}", "nested": {f"metric_{k}": {"mean": 1.0 / (k + 1), "p95": 100.25 + k}
                                                          for k in range(12)}} for i in range(3)]
    lines = _render(monkeypatch, {"area": {"records": records}})
    _check(lines)
    titles = [x for x in lines if x.startswith("bench area: records")]
    assert len(titles) > 1 and titles[0].rstrip().endswith(f"(1/{len(titles)})")
    assert sum(x.count("100.2") for x in lines) == 3  # metric_0's p95 of each record, shown once each
