"""The trials report: Wilson intervals, the per-object breakdown and confusion matrix, every trial as a
point, the bounds explained, failures grouped by cause, and the sweep's date, lab, library and seeds."""

from __future__ import annotations

import hashlib
import json
import re

import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import binomtest

from labctl.experiments.trials import summarize
from labctl.records.sweep_report import (
    QUINTIC_TEXT,
    failure_cause,
    render_sweep_figure,
    sweep_figure,
    wilson_interval,
    write_sweep_report,
)


@given(st.integers(1, 400).flatmap(lambda n: st.tuples(st.integers(0, n), st.just(n))))
def test_wilson_interval_is_scipys(kn):
    k, n = kn
    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    assert wilson_interval(k, n) == pytest.approx((ci.low, ci.high), abs=1e-9)


def _trial(i, true, ident, speed, traj="line", failure=None):
    ok = ident == true
    return {"index": i, "seed": 100 + i, "true_identity": true, "identity": ident, "correct": ok,
            "speed_mm_s": speed, "trajectory": traj, "failure": failure, "views": 1,
            "time_to_identity_s": 3.0 + 0.1 * i if ident else None, "lower_bound_s": 2.5 if ident else None,
            "lower_bound_quintic_s": 3.1 if ident else None, "stages": {"wait": 0.3, "track": 0.1},
            "record": None}


def _sweep(tmp_path):
    trials = [_trial(0, "tee", "tee", 8.0), _trial(1, "wedge", "wedge", 8.0), _trial(2, "tee", "wedge", 8.0),
              _trial(3, "tee", None, 40.0, failure="no identity within the run's 90 s"),
              _trial(4, "wedge", None, 40.0, "zigzag", failure="no identity within the run's 12.5 s"),
              _trial(5, "wedge", "wedge", 40.0, "zigzag")]
    folder = tmp_path / "trials-20261202T010203Z"
    folder.mkdir()
    (folder / "spec.json").write_text(json.dumps({"lab": "/labs/bench", "seed": 100, "library": "/labs/lib",
                                                  "library_sha256": "ab" * 32, "objects": ["tee", "wedge"]}))
    summary = summarize(trials)
    summary.update({"planned": 6, "interrupted": False})
    return folder, summary, trials


def test_report_has_every_part(tmp_path):
    folder, summary, trials = _sweep(tmp_path)
    text = write_sweep_report(folder, summary).read_text()
    facts = re.search(r'<table id="facts">(.*?)</table>', text, re.S).group(1)
    assert "2026-12-02 01:02:03 UTC" in facts and "/labs/bench" in facts and "abababababababab" in facts
    assert "100–105 (6 seeds)" in facts and "line, zigzag" in facts and "8, 40" in facts
    lo, hi = wilson_interval(3, 6)
    assert f"50.0 % (3/6; 95 % CI {100 * lo:.1f}–{100 * hi:.1f} %)" in text
    obj = re.search(r'<table id="by-object">(.*?)</table>', text, re.S).group(1)
    tee = re.search(r"<tr><td>tee</td><td>3</td><td>([^<]*)</td><td>([^<]*)</td><td>([^<]*)</td>", obj)
    assert tee and tee.group(1).startswith("33.3 % (1/3") and tee.group(3) == "wedge ×1"
    # the confusion matrix: tee row has tee 1, wedge 1, none 1
    conf = re.search(r'<table class="conf">(.*?)</table>', text, re.S).group(1)
    head = re.findall(r"<th>([^<]*)</th>", conf.split("</tr>")[0])
    assert head[1:] == ["tee", "wedge", "none"]
    tee_row = next(r for r in conf.split("</tr>") if r.startswith("<tr><th>tee"))
    assert re.findall(r">(\d*)</td>", tee_row) == ["1", "1", "1"]
    # the bounds in words, the quintic's ratio below 1 explained
    assert "at least 1" in text and "below 1" in QUINTIC_TEXT and "below 1" in text
    # the two timeouts are one cause; the wrong answer another
    causes = dict(re.findall(r"<h3>([^<]*) \((\d+)\)</h3>", text))
    assert causes == {"no identity within the run&#x27;s # s": "2", "identified the wrong object": "1"}
    trajs = re.search(r'<table id="by-trajectory">(.*?)</table>', text, re.S).group(1)
    assert trajs.count("<tr><td>") == 3  # line@8, line@40, zigzag@40


def test_figure_draws_every_trial(tmp_path):
    import io

    import matplotlib.image as mpimg

    _, summary, trials = _sweep(tmp_path)
    assert mpimg.imread(io.BytesIO(render_sweep_figure(summary))).shape[1] >= 1000
    ax1, ax2, ax3, ax4 = sweep_figure(summary).axes[:4]
    dots = [ln for ln in ax1.get_lines() if ln.get_marker() == "."]
    assert len(dots) == len(trials)  # every trial a point, at 100 (correct) or 0
    assert sorted(float(ln.get_ydata()[0]) for ln in dots) == [0.0] * 3 + [100.0] * 3
    # the Wilson bars: line at 8 mm/s is 2 of 3
    lo, hi = wilson_interval(2, 3)
    caps = [ln for ln in ax1.get_lines() if ln.get_marker() == "_"]
    ys = sorted(float(y) for ln in caps for y in ln.get_ydata())
    assert any(y == pytest.approx(100 * lo) for y in ys) and any(y == pytest.approx(100 * hi) for y in ys)
    assert sum(len(ln.get_xdata()) for ln in ax2.get_lines()) == 3  # the correct trials' times
    assert failure_cause(trials[3]) == failure_cause(trials[4])


def test_sweep_spec_names_its_library_by_hash(tmp_path):
    import shutil

    from labctl.config import load_lab
    from labctl.experiments.trials import run_sweep
    from labctl.workspace import sample_lab_path

    root = tmp_path / "lab"
    shutil.copytree(sample_lab_path(), root, ignore=shutil.ignore_patterns("runs"))
    lab = load_lab(root)
    s = run_sweep(lab, n=1, trajectory="line", speeds=[8.0], objects=["tee"], seed=3, n_jobs=1, record=False)
    spec = json.loads((lab.runs_dir / s["sweep"].split("/")[-1] / "spec.json").read_text())
    h = hashlib.sha256()
    lib = root / "object_library"
    for p in sorted(q for q in lib.rglob("*") if q.is_file() and not q.name.startswith(".")):
        h.update(str(p.relative_to(lib)).encode() + b"\0" + p.read_bytes())
    assert spec["library_sha256"] == h.hexdigest() and spec["created_utc"].startswith("20")
    text = (lab.runs_dir / s["sweep"].split("/")[-1] / "report.html").read_text()
    assert spec["library_sha256"][:16] in text and str(root) in text


@pytest.mark.parametrize("n", [1, 3, 10, 49, 120])
def test_all_correct_or_all_failed_groups_draw(tmp_path, n):
    """k = n and k = 0: the interval ends exactly at 1 and 0 (rounding once made matplotlib refuse a bar)."""
    assert wilson_interval(n, n)[1] == 1.0 and wilson_interval(0, n)[0] == 0.0
    trials = [_trial(i, "tee", "tee", 8.0) for i in range(n)] + [_trial(n + i, "tee", None, 40.0, failure="x")
                                                                 for i in range(n)]
    folder = tmp_path / "trials-x"
    folder.mkdir()
    s = summarize(trials)
    s.update({"planned": 2 * n, "interrupted": False})
    assert write_sweep_report(folder, s).is_file() and (folder / "report.png").stat().st_size > 1000


def test_the_summary_gives_the_bound_ratio_per_trajectory_and_speed():
    """Each trajectory × speed cell's median ``ratio_to_bound`` over its correct trials only, by hand."""
    def trial(traj, speed, tti, bound, correct=True):
        return {"trajectory": traj, "speed_mm_s": speed, "time_to_identity_s": tti, "lower_bound_s": bound,
                "correct": correct, "views": 1, "stages": {"wait": 0.3}, "seed": 0}

    trials = [trial("line", 4.0, 3.0, 2.5), trial("line", 4.0, 2.6, 2.0), trial("line", 4.0, 9.0, 2.0, False),
              trial("line", 8.0, 2.4, 2.0), trial("arc", 4.0, 2.2, 2.0)]
    by = summarize(trials)["by_trajectory"]
    assert by["line"]["by_speed"]["4"]["ratio_to_bound_median"] == pytest.approx((1.2 + 1.3) / 2)
    assert by["line"]["by_speed"]["4"]["success_rate"] == pytest.approx(2 / 3)
    assert by["line"]["by_speed"]["8"]["ratio_to_bound_median"] == pytest.approx(1.2)
    assert by["line"]["ratio_to_bound_median"] == pytest.approx(1.2)  # of 1.2, 1.3, 1.2
    assert by["arc"]["ratio_to_bound_median"] == pytest.approx(1.1) and by["arc"]["n"] == 1
