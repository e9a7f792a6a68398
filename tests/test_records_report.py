"""Run reports from synthetic records: every section present, early ends shown as "not reached"."""

from __future__ import annotations

import base64
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from labctl.records import RunRecord, load_run, write_report
from labctl.records.report import SECTIONS, render_figure


def _marker_image(cx, cy, a, b, theta_deg):
    img = np.full((240, 320, 3), 40, np.uint8)
    cv2.ellipse(img, (int(cx), int(cy)), (int(a), int(b)), theta_deg, 0, 360, (0, 0, 255), -1)
    return img


def _full_run(tmp_path):
    rec = RunRecord.create(tmp_path, {"trajectory": "line", "speed_mm_s": 8.0, "object": "wedge"})
    rec.event("worker_started", role="predictor", pid=11)
    rec.event("worker_started", role="recognizer", pid=12)
    rec.event("tracking_prior", t=0.0, family="line", curve_prior=0.001)
    for t, st in ((0.0, "track"), (1.0, "intercept"), (2.0, "initial"), (2.5, "standard"), (3.0, "match"),
                  (3.1, "done")):
        rec.event("stage", t=t, stage=st)
    for i in range(20):
        t = 0.1 * i
        rec.event("track", t=t, x=100 + 8 * t, y=50.0, px=[160.0 + i, 120.0])
        if i % 5 == 4:
            rec.event("predict", t=t, path=[[100 + 8 * (t + s), 50.0] for s in np.linspace(0, 5, 11)])
        rec.event("robot", t=t, p=np.array([300 - 10 * t, 20 + 2 * t, 400.0]))
    rec.save_image("initial1", _marker_image(160, 120, 30, 18, 20))
    rec.save_image("initial2", _marker_image(150, 125, 28, 20, 35))
    rec.event("marker_pose", t=2.0, view_id=2, marker=0,
              ellipses={"initial1": [160, 120, 30, 18, np.deg2rad(20)], "initial2": [150, 125, 28, 20, np.deg2rad(35)]},
              center_w=[120.0, 50.0, 35.0], normal_w=[0.0, 0.0, 1.0], resolved=True, index=0, margin_deg=3.1,
              threshold_deg=0.1, suspect=False, scores_deg=[0.2, 3.3], pose=None, consistency=None)
    std = np.full((240, 320), 90, np.uint8)
    sil = np.zeros((240, 320), bool)
    sil[60:180, 100:220] = True
    std[sil] = 200
    rec.save_image("standard_0", std)
    rec.save_image("silhouette_0", sil)
    rec.event("match", t=3.0, view_id=3, view=0, scores={"wedge": 0.04, "cube": 0.61, "prism": np.float32(0.97)},
              candidates=["wedge"], best="wedge", planned_marker_height_mm=35.0)  # lower is better
    rec.finish({"identity": "wedge", "true_identity": "wedge", "correct": True, "time_to_identity_s": 9.2,
                "views": 1, "stages": {"track": 3.0, "intercept": 4.0, "standard": 2.2}})
    return rec


def _section(html_text, sid):
    m = re.search(rf'<section id="{sid}">(.*?)</section>', html_text, re.S)
    assert m, f"section {sid} missing"
    return m.group(1)


def test_full_report_has_every_section_and_a_figure(tmp_path):
    rec = _full_run(tmp_path)
    out = write_report(rec.path)
    assert out == rec.path / "report.html"
    text = out.read_text()
    for sid in SECTIONS:
        assert "not reached" not in _section(text, sid), sid
    assert "20 tracked points, 4 predictions, 20 robot samples" in _section(text, "paths")
    assert 'href="initial1.png"' in _section(text, "markers") and "3.1" in _section(text, "markers")
    assert 'href="silhouette_0.png"' in _section(text, "standard")
    scores = _section(text, "scores")
    assert scores.index("wedge") < scores.index("cube") < scores.index("prism")  # best (lowest) first
    assert "lower is better" in scores
    assert 'id="failure"' not in text
    assert "time_to_identity_s" in _section(text, "summary")  # every field, folded under the summary
    assert "identified wedge: correct (sim truth: wedge)" in _section(text, "summary")
    # the embedded figure is the same PNG as report.png and decodes to an image
    b64 = re.search(r'src="data:image/png;base64,([^"]+)"', text).group(1)
    png = base64.b64decode(b64)
    assert png == (rec.path / "report.png").read_bytes()
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[0] > 300 and img.shape[1] > 600


def test_figure_draws_the_recorded_data(tmp_path):
    rec = _full_run(tmp_path)
    fig = render_figure(load_run(rec.path))
    axes = fig.axes
    titles = [ax.get_title() for ax in axes]
    assert any("paths" in t for t in titles)
    paths_ax = next(ax for ax in axes if "paths" in ax.get_title())
    labels = {line.get_label() for line in paths_ax.get_lines()}
    assert {"tracked (KF)", "predicted", "robot (x-y)"} <= labels
    # axes fit the data: every drawn point inside, and no more than a margin beyond it
    xs = np.concatenate([ln.get_xdata() for ln in paths_ax.get_lines()])
    ys = np.concatenate([ln.get_ydata() for ln in paths_ax.get_lines()])
    fig.canvas.draw()
    (x0, x1), (y0, y1) = paths_ax.get_xlim(), paths_ax.get_ylim()
    assert x0 <= xs.min() and xs.max() <= x1 and y0 <= ys.min() and ys.max() <= y1
    span = max(np.ptp(xs), np.ptp(ys))
    assert max(x1 - x0, y1 - y0) < 1.5 * span
    # the object's own path, up close: its panel spans the tracked and predicted path, not the robot's travel
    close = next(ax for ax in axes if "up close" in ax.get_title())
    (cx0, cx1) = close.get_xlim()
    assert cx0 <= 100 and cx1 >= 100 + 8 * 1.9 + 8 * 5 and cx1 - cx0 < 1.5 * (8 * 1.9 + 8 * 5 + 0.8 * 3)
    pred = next(ln for ln in close.get_lines() if ln.get_label() == "predicted")
    track = next(ln for ln in close.get_lines() if ln.get_label() == "tracked (KF)")
    assert pred.get_zorder() > track.get_zorder()  # drawn over the track it continues
    tracked = next(line for line in paths_ax.get_lines() if line.get_label() == "tracked (KF)")
    assert np.allclose(tracked.get_xdata(), [100 + 0.8 * i for i in range(20)])
    # ellipses drawn where recorded, in pixel coordinates
    m1 = next(ax for ax in axes if ax.get_title() == "Marker image initial1")
    ell = m1.patches[0]
    assert ell.center == (160, 120) and ell.width == pytest.approx(60) and ell.angle == pytest.approx(20)
    std_ax = next(ax for ax in axes if ax.get_title().startswith("Standard view 0"))
    assert "silhouette" in std_ax.get_title() and std_ax.collections  # the silhouette contour
    score_ax = next(ax for ax in axes if ax.get_title().startswith("Match scores"))
    widths = sorted(p.get_width() for p in score_ax.patches)
    assert widths == pytest.approx([0.04, 0.61, 0.97])
    assert "lower is better" in score_ax.get_xlabel()
    bars = sorted(score_ax.patches, key=lambda b: -b.get_y())  # top bar first
    assert [round(b.get_width(), 2) for b in bars] == [0.04, 0.61, 0.97]  # best at the top


def test_early_ended_run_reports_not_reached(tmp_path):
    rec = RunRecord.create(tmp_path, {"trajectory": "arc"})
    rec.event("worker_started", role="predictor", pid=11)
    for i in range(5):
        rec.event("track", t=0.1 * i, x=10.0 * i, y=0.0, px=[10.0 * i, 0.0])
    rec.event("failure", t=0.5, stage="intercept", reason="recognizer worker died")
    text = write_report(rec.path).read_text()
    assert "5 tracked points" in _section(text, "paths")
    for sid in ("standard", "scores"):
        assert "not reached" in _section(text, sid)
    assert "initial1: not reached" in _section(text, "markers")
    assert "did not finish" in _section(text, "summary")
    assert "failure" in _section(text, "events")
    assert (rec.path / "report.png").stat().st_size > 1000
    # the figure leads with the cause and the fixed camera, not with a panel per step never reached
    fig = render_figure(load_run(rec.path))
    titles = [ax.get_title() for ax in fig.axes]
    assert "Standard view" not in titles and "Match scores" not in titles
    assert "Fixed camera, last frame" in titles and "Stage timeline" in titles
    assert "recognizer worker died" in " ".join(fig._suptitle.get_text().split())


def test_report_of_an_empty_record_and_of_bad_event_fields(tmp_path):
    rec = RunRecord.create(tmp_path, checked=False)  # as a broken or older writer left it
    rec.event("track", t="soon", x=None, y=1)  # malformed: ignored, not a crash
    rec.event("predict", t=0.0, path="nowhere")
    rec.event("robot", t=0.0, p=[1, 2])
    rec.event("match", scores={"a": float("nan")})
    rec.event("marker_pose", ellipses={"initial1": [1, 2, 3]})
    text = write_report(rec.path).read_text()
    for sid in ("paths", "standard", "scores"):
        assert "not reached" in _section(text, sid)


def test_several_standard_views_are_all_shown(tmp_path):
    rec = _full_run(tmp_path)
    std = np.full((240, 320), 90, np.uint8)
    rec.save_image("standard_1", std)  # second view, silhouette never saved
    text = write_report(rec.path).read_text()
    sec = _section(text, "standard")
    assert "standard_0.png" in sec and "standard_1.png" in sec and "silhouette not recorded" in sec
    titles = [ax.get_title() for ax in render_figure(load_run(rec.path)).axes]
    assert "Standard view 1 (silhouette not recorded)" in titles


def test_failed_run_report_leads_with_the_reason(tmp_path):
    rec = RunRecord.create(tmp_path, {"trajectory": "line"})
    for i in range(5):
        rec.event("track", t=0.1 * i, x=10.0 * i, y=0.0, px=[10.0 * i, 0.0])
    why = "no marker gave a usable pose (radius 8 mm does not fit the detected ellipse)"
    rec.finish({"identity": None, "failure": why})
    text = write_report(rec.path).read_text()
    lead = text.index('id="failure"')
    assert why in text[lead:lead + 400]
    # before the figure and before every panel or section that says "not reached"
    assert lead < text.index("<figure") and lead < text.index("not reached")
    assert all(lead < text.index(f'<section id="{sid}">') for sid in SECTIONS)
    fig = render_figure(load_run(rec.path))
    assert why in fig._suptitle.get_text() and "FAILED" in fig._suptitle.get_text()


def test_unfinished_run_report_leads_with_the_last_event(tmp_path):
    rec = RunRecord.create(tmp_path, {"trajectory": "arc"})
    rec.event("failure", t=0.0, stage="intercept", reason="recognizer worker died")
    text = write_report(rec.path).read_text()
    lead = text.index('id="failure"')
    assert "did not finish" in text[lead:lead + 300] and "last event: failure" in text[lead:lead + 300]
    assert lead < text.index("<figure")


def test_report_command_redraws_a_failed_run_and_names_the_reason(tmp_path, capsys):
    import json

    from fakes import run_cli

    rec = RunRecord.create(tmp_path, {"trajectory": "line"})
    rec.finish({"identity": None, "failure": "the object left the fixed camera's field of view"})
    code, out, err = run_cli(capsys, "--json", "report", str(rec.path))
    data = json.loads(out)
    assert code == 0 and data["failed"] and "left the fixed camera" in data["failure"], err
    assert (rec.path / "report.html").is_file() and (rec.path / "report.png").is_file()
    code, out, err = run_cli(capsys, "report", str(tmp_path))  # a folder that is no record: bad input
    assert code == 2 and len(err.strip().splitlines()) == 1 and "not a run record" in err


def test_title_says_what_was_identified_and_whether_it_was_right(tmp_path):
    rec = _full_run(tmp_path)
    assert "identified wedge: correct (sim truth: wedge)" in render_figure(load_run(rec.path))._suptitle.get_text()
    rec.finish({"identity": "wedge", "true_identity": "cube", "correct": False})
    fig = render_figure(load_run(rec.path))
    assert "identified wedge: WRONG (sim truth: cube)" in fig._suptitle.get_text()
    text = write_report(rec.path).read_text()
    assert "<title>labctl run" in text and "WRONG (sim truth: cube)" in text[: text.index("</title>")]
    rec.finish({"identity": "wedge"})  # a real lab: no truth, nothing claimed
    assert "no ground truth" in render_figure(load_run(rec.path))._suptitle.get_text()


def test_timeline_has_no_negative_duration_and_says_why_it_clamped(tmp_path):
    """A live record whose first frame was exposed 12.4 ms before the predictor's start (as records
    written before the predictor's fix carry: ``wait: -0.0124``)."""
    rec = RunRecord.create(tmp_path, {"trajectory": "line"})
    rec.event("tracking_prior", t=5.0, family="line", curve_prior=0.001)
    for t, st in ((4.9876, "track"), (5.2, "intercept"), (6.0, "initial"), (6.5, "initial"), (7.0, "standard"),
                  (8.0, "match"), (8.1, "done")):
        rec.event("stage", t=t, stage=st)
    rec.finish({"identity": "wedge", "stages": {"wait": -0.0124, "track": 0.2124}})
    from labctl.records.report import timeline

    stages = timeline(load_run(rec.path))
    assert [s.stage for s in stages] == ["wait", "track", "intercept", "initial", "standard", "match"]
    assert all(s.duration_s >= 0 for s in stages)
    assert stages[0].duration_s == 0 and stages[0].clamped_s == pytest.approx(0.0124)
    assert stages[1].duration_s == pytest.approx(0.2) and stages[3].duration_s == pytest.approx(1.0)
    sec = _section(write_report(rec.path).read_text(), "timeline")
    assert "12.4 ms before it began" in sec and "-0.0" not in sec


def test_stage_times_never_count_a_stage_backwards():
    """The source of the negative wait: a stage entered on a frame exposed before the previous stage began."""
    from labctl.decisions.predictor import StageTimes

    st = StageTimes()
    st.enter("wait", 5.0)
    st.enter("track", 4.9876)  # the live camera's latest frame at the start
    st.enter("intercept", 5.2)
    assert st.durations == {"wait": 0.0, "track": pytest.approx(0.2)}


def _lab(tmp_path, capsys, **run_settings):
    from fakes import run_cli

    lab = tmp_path / "lab"
    code, _, err = run_cli(capsys, "init", str(lab))
    assert code == 0, err
    if run_settings:
        text = (lab / "lab.yaml").read_text()
        for k, v in run_settings.items():
            text = re.sub(rf"(?m)^(  {k}:).*$", rf"\g<1> {v}", text)
        (lab / "lab.yaml").write_text(text)
    return lab


def test_report_names_the_gate_that_dropped_each_object(tmp_path, capsys):
    """Seed 8 on the sample lab: the standard view measures its marker 75 mm up, and three objects whose
    silhouette would pass fall to the marker-height gate. The oracle: the library's own ``view_scores``
    with and without the measured height (the gate inside the scoring), on the recorded image."""
    from fakes import run_cli

    from labctl.config import load_lab
    from labctl.decisions.context import RunContext
    from labctl.library.matching import view_scores
    from labctl.library.views import mm_per_px
    from labctl.vision.shape import features_from_image

    lab = _lab(tmp_path, capsys)
    code, out, err = run_cli(capsys, "--lab", str(lab), "--json", "run", "--virtual", "--seed", "8")
    import json

    res = json.loads(out)
    assert code == 0 and res["correct"], err
    run = load_run(res["record"])
    ev = run.of("match")[-1]
    ctx = RunContext.load(load_lab(lab))
    img = cv2.imread(str(run.path / f"standard_{ev['view']}.png"), cv2.IMREAD_UNCHANGED)
    f = features_from_image(img, mm_per_px(ctx.mobile_camera, ctx.lab.config.viewing.standoff_mm))
    names = np.asarray(ctx.index.names)
    free = view_scores(f, ctx.index)
    held = view_scores(f, ctx.index, height_mm=ev["marker_height_mm"], height_tol_mm=ev["height_tol_mm"])
    by_height = {n for n, s in ev["scores"].items() if s is None
                 and np.isfinite(free[names == n]).any() and not np.isfinite(held[names == n]).any()}
    by_shape = {n for n, s in ev["scores"].items() if s is None and not np.isfinite(free[names == n]).any()}
    assert by_height and by_shape  # the seed shows both gates
    sec = _section(Path(res["report"]).read_text(), "scores")
    rows = dict(re.findall(r"<tr><th>([a-z_]+)</th><td>[^<]*</td><td>([^<]*)</td></tr>", sec))
    assert {n for n, why in rows.items() if why.startswith("marker-height gate")} == by_height
    assert {n for n, why in rows.items() if why.startswith("shape gate")} == by_shape
    assert rows[res["identity"]] == "the answer"
    # every object of the library has its row: none silently missing
    assert set(rows) == set(ctx.names)
    ax = next(a for a in render_figure(run).axes if a.get_title().startswith("Match scores"))
    assert {t.get_text() for t in ax.get_yticklabels()} == set(ctx.names)


def test_failed_virtual_run_report_shows_the_fixed_camera_and_the_cause(tmp_path, capsys):
    from fakes import run_cli

    lab = _lab(tmp_path, capsys, timeout_s="0.8")
    code, out, err = run_cli(capsys, "--lab", str(lab), "run", "--virtual", "--seed", "3")
    assert code == 1 and "no identity within the run's 0.8 s" in err
    rec = sorted((lab / "runs").iterdir())[-1]
    frame = cv2.imread(str(rec / "fixed_last.png"))
    assert frame is not None and frame.shape[:2] == (480, 640)  # the whole fixed image, not the object's window
    fig = render_figure(load_run(rec))
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[0] == "Fixed camera, last frame" and fig.axes[0].images
    assert "not reached" not in " ".join(t.get_text() for ax in fig.axes for t in ax.texts)
    title = " ".join(fig._suptitle.get_text().split())
    assert "FAILED in stage intercept" in title and "within the run's 0.8 s" in title
