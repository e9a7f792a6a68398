"""Output that reads well (issue 17, Build 5): defaults marked in ``lab show``, piped output one key per
line, ``--json`` unchanged."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from fakes import run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labctl.cli._common import key_lines
from labctl.config import load_lab
from labctl.config.lab import LabConfig
from labctl.config.schema import defaulted_keys
from labctl.workspace import init_workspace

KEY_LINE = re.compile(r"^[^\s:][^:]*: .*$")


def labctl(*args):
    return subprocess.run([sys.executable, "-m", "labctl", *args], capture_output=True, text=True, timeout=120)


@pytest.fixture
def lab(tmp_path) -> Path:
    root = init_workspace(tmp_path / "lab")
    text = (root / "lab.yaml").read_text()
    # leave out one key of run: and the whole tracking: section
    text = re.sub(r"^  fps: .*\n", "", text, flags=re.M)
    text = re.sub(r"^tracking:\n(  .*\n)+", "", text, flags=re.M)
    (root / "lab.yaml").write_text(text)
    return root


def test_defaulted_keys_follow_the_file_not_the_values():
    # a key set to its default value is set by the file; a missing section is all defaults
    keys = defaulted_keys(LabConfig, {"run": {"fps": 30.0}, "tracking": None, "marker": {}})
    assert "run.fps" not in keys and "run.speed_mm_s" in keys
    assert "tracking.gate_sigma" in keys and "marker.radius_mm" in keys and "name" in keys
    assert "run" not in keys and "tracking" not in keys  # sections expand to their keys
    assert "drivers.table" in defaulted_keys(LabConfig, {"drivers": {"robot": "r.yaml"}})
    assert "drivers.table" not in defaulted_keys(LabConfig, {"drivers": {"table": None}})


def test_lab_show_json_lists_the_defaults(lab):
    r = labctl("--lab", str(lab), "lab", "show", "--json")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    defaults = set(info["defaults"])
    assert {"config.run.fps", "config.tracking.gate_sigma", "config.tracking.model"} <= defaults
    assert "config.run.speed_mm_s" not in defaults and "config.marker.radius_mm" not in defaults
    # every listed key names a value of the same output
    for key in defaults:
        node = info
        for part in key.split("."):
            node = node[part]
    assert load_lab(lab).config.run.fps == 30.0  # the default the key came from


def test_lab_show_on_a_terminal_marks_defaults(lab, capsys, monkeypatch):
    monkeypatch.setattr("labctl.cli._common.stdout_is_terminal", lambda: True)
    code, out, err = run_cli(capsys, "--lab", str(lab), "lab", "show")
    assert code == 0, err
    rows = {ln.split()[0]: ln for ln in out.splitlines() if ln.strip()}
    assert rows["run.fps"].rstrip().endswith("(default)")
    assert rows["tracking.gate_sigma"].rstrip().endswith("(default)")
    assert "(default)" not in rows["run.speed_mm_s"] and "(default)" not in rows["marker.radius_mm"]


def test_piped_lab_show_is_one_key_per_line(lab):
    r = labctl("--lab", str(lab), "lab", "show")  # stdout is a pipe
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines and all(KEY_LINE.match(ln) for ln in lines), r.stdout
    keys = dict(ln.split(": ", 1) for ln in lines)
    assert keys["config.run.speed_mm_s"] == "8.0" and keys["drivers.table.kind"] == "sim"
    assert "config.run.fps" in keys["defaults"].split(", ")
    assert "┃" not in r.stdout and "\x1b" not in r.stdout  # no table, no colour


def test_piped_run_puts_identity_on_its_own_line_as_recorded(lab, capsys):
    code, out, err = run_cli(capsys, "--lab", str(lab), "run", "--virtual", "--seed", "1")  # capsys: not a TTY
    assert code in (0, 1), err
    lines = out.splitlines()
    assert all(KEY_LINE.match(ln) for ln in lines), out
    keys = dict(ln.split(": ", 1) for ln in lines)
    assert sum(ln.startswith("identity: ") for ln in lines) == 1
    assert "stages.track" in keys and "link.total_bytes" in keys
    # the same values as the record's result.json (the --json output is that dict)
    result = json.loads((Path(keys["record"]) / "result.json").read_text())
    assert keys["identity"] == (result["identity"] if result["identity"] is not None else "null")
    assert int(keys["link.total_bytes"]) == result["link"]["total_bytes"]
    assert float(keys["time_to_identity_s"]) == result["time_to_identity_s"]


_keys = st.text(alphabet="ab_xé7-", min_size=1, max_size=4)
_leaf = st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) \
    | st.text(alphabet="a: \n\\\r,", max_size=6)
_json = st.recursive(_leaf,
                     lambda inner: st.lists(inner, max_size=3) | st.dictionaries(_keys, inner, max_size=3),
                     max_leaves=12)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(_keys, _json, max_size=4))
def test_key_lines_are_single_lines_that_name_each_leaf(data):
    lines = key_lines(data)
    assert all("\n" not in ln and "\r" not in ln and ": " in ln for ln in lines)
    for ln in lines:  # every line's key leads to a value of the data
        key = ln.split(": ", 1)[0]
        node = data
        for part in re.findall(r"[^.\[\]]+|\[\d+\]", key):
            node = node[int(part[1:-1])] if part.startswith("[") else node[part]


def test_bench_prints_tables_and_what_a_ratio_means_not_a_raw_dict(capsys, monkeypatch):
    import types

    import labctl.cli.bench as bench_cli

    fake = types.ModuleType("labctl.bench.fake")
    fake.run = lambda quick: {"rows": [{"case": "fast path", "median_s": 0.002, "baseline": "slow path",
                                        "ratio": 4.0}],
                              "accuracy": [{"model": "cv", "rms_mm": 0.31}, {"model": "imm", "rms_mm": 0.27}],
                              "hit_rate": 0.975, "link": {"bytes": 654}}
    monkeypatch.setitem(sys.modules, "labctl.bench.fake", fake)
    monkeypatch.setattr(bench_cli, "_areas", lambda: ["fake"])
    monkeypatch.setattr("labctl.cli._common.stdout_is_terminal", lambda: True)
    code, out, err = run_cli(capsys, "bench", "fake")
    assert code == 0, err
    assert "{'" not in out and "{\"" not in out  # no raw dict
    tail = " ".join(out[out.index("ratio:"):].split())  # wrapped at the terminal's width, said once
    assert tail == f"ratio: {bench_cli.RATIO_MEANS}. Medians; --json gives every number."
    assert "4.00×" in out and "imm" in out and "0.27" in out and "link.bytes" in out and "0.975" in out
    code, out, err = run_cli(capsys, "--json", "bench", "fake")  # the raw data, whole, under --json
    assert json.loads(out) == {"fake": fake.run(True)}


def test_trials_summary_lists_stages_in_pipeline_order():
    from labctl.decisions.predictor import STAGES
    from labctl.experiments.trials import STAGE_ORDER, summarize

    stages = {"match": 0.1, "initial": 1.1, "intercept": 1.2, "standard": 2.0, "track": 0.4, "wait": 0.3}
    res = {"speed_mm_s": 8.0, "correct": True, "time_to_identity_s": 5.1, "lower_bound_s": 3.0, "views": 1}
    summary = summarize([{**res, "stages": dict(sorted(stages.items()))}])  # given alphabetically
    assert list(summary["stage_medians_s"]) == ["wait", "track", "intercept", "initial", "standard", "match"]
    assert STAGE_ORDER == STAGES  # the order the predictor runs its stages in


def test_live_view_shows_start_up_progress_then_the_recorded_byte_counts():
    import io

    from rich.console import Console

    from labctl.cli.run import _LiveView

    con = Console(file=io.StringIO(), width=100)
    view = _LiveView(con)

    def text():
        con.begin_capture()
        con.print(view._render())
        return con.end_capture()

    assert "starting" in text() and "s since the command started" in text()
    view.update({"role": "startup", "stage": "starting the simulated lab"})
    assert "starting: starting the simulated lab" in text()
    view.update({"role": "predictor", "t": 2.5, "stage": "track", "estimate": [10.0, 20.0],
                 "link": {"sent": 394, "received": 538}, "views": 0, "robot": None})
    assert "track" in text() and "sent 394 B, received 538 B" in text()
    # the last beat predates the last messages: the end shows result.json's counts
    view.finish({"identity": "tee", "link": {"bytes_sent": 408, "bytes_received": 538}})
    assert "sent 408 B, received 538 B" in text()
