"""Pieces that moved into their layers (issue 17, Build 6): the fixed camera's red-blob fallback in
``vision``, the rest-to-rest lower bounds in ``planning``. Checked against independent computations."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.planning import rest_to_rest_times
from labctl.vision import red_blob_centroid


def _quintic_peaks(d: float, T: float) -> tuple[float, float]:
    """Peak speed and acceleration of the rest-to-rest quintic over distance d in time T, sampled."""
    t = np.linspace(0.0, T, 20001)
    u = t / T
    s = d * (10 * u**3 - 15 * u**4 + 6 * u**5)
    v = np.gradient(s, t)
    a = np.gradient(v, t)
    return float(np.abs(v).max()), float(np.abs(a[5:-5]).max())


def _bang_bang_distance(T: float, v_max: float, a_max: float) -> float:
    """Distance covered in T by the fastest rest-to-rest profile (simulated in small steps)."""
    dt = T / 200000
    t = np.arange(0, T, dt)
    vel = np.minimum.reduce([a_max * t, np.full_like(t, v_max), a_max * (T - t)])  # speed up, cruise, stop by T
    return float(np.sum(vel) * dt)


@settings(max_examples=30, deadline=None)
@given(st.floats(1.0, 2000.0), st.floats(50.0, 1500.0), st.floats(100.0, 5000.0))
def test_rest_to_rest_times_match_sampled_profiles(d, v_max, a_max):
    any_s, quintic_s = rest_to_rest_times([0.0, 0.0, 0.0], [d, 0.0, 0.0], v_max, a_max)
    v, a = _quintic_peaks(d, quintic_s)
    assert v <= v_max * 1.001 and a <= a_max * 1.01  # within the limits ...
    assert v >= v_max * 0.999 or a >= a_max * 0.99  # ... and one of them is reached: the shortest quintic
    assert _bang_bang_distance(any_s, v_max, a_max) == pytest.approx(d, rel=2e-3)
    assert any_s <= quintic_s


def test_rest_to_rest_is_symmetric_and_zero_for_no_move():
    assert rest_to_rest_times([1, 2, 3], [1, 2, 3], 100.0, 100.0) == (0.0, 0.0)
    a = rest_to_rest_times([0, 0, 0], [30, 40, 0], 100.0, 400.0)
    b = rest_to_rest_times([30, 40, 0], [0, 0, 0], 100.0, 400.0)
    assert a == b and a[0] == pytest.approx(50 / 100 + 100 / 400)  # cruises: 100²/400 = 25 mm < 50 mm
    assert rest_to_rest_times([0, 0], [10, 0], 100.0, 400.0)[0] == pytest.approx(2 * math.sqrt(10 / 400))


def test_red_blob_centroid_picks_the_nearest_blob_within_reach():
    img = np.full((240, 320, 3), 60, np.uint8)
    cv2.rectangle(img, (40, 100), (43, 130), (0, 0, 230), -1)  # a thin sliver: a marker seen edge-on
    cv2.circle(img, (250, 60), 12, (0, 0, 230), -1)  # a bigger blob elsewhere
    assert red_blob_centroid(img) == pytest.approx([250, 60], abs=0.5)  # no hint: the largest
    assert red_blob_centroid(img, (45, 110)) == pytest.approx([41.5, 115], abs=0.5)
    assert red_blob_centroid(img, (150, 200)) is None  # both further than max_jump_px
    assert red_blob_centroid(np.full((50, 50, 3), 60, np.uint8)) is None


def _lab_with(tmp_path, extra: str):
    from labctl.workspace import init_workspace

    root = init_workspace(tmp_path / "lab")
    text = (root / "lab.yaml").read_text().replace("\nrun:\n", f"\nrun:\n{extra}\n", 1)
    (root / "lab.yaml").write_text(text)
    return root


def test_predictor_policy_is_a_run_setting(tmp_path, capsys):
    """The predictor's interception horizon comes from lab.yaml run:, not a constant in the worker."""
    import json

    from fakes import run_cli

    root = _lab_with(tmp_path, "  plan_horizon_s: 0.05")
    code, out, err = run_cli(capsys, "--lab", str(root), "--json", "run", "--virtual", "--seed", "1")
    res = json.loads(out)
    assert code == 1 and res["identity"] is None and "unreachable" in res["failure"], (out, err)


@pytest.mark.parametrize("line", ["  max_viewpoints: 0", "  replan_every_s: -1", "  recognizer_timeout_s: .nan"])
def test_predictor_policy_settings_are_checked_at_load(tmp_path, capsys, line):
    from fakes import run_cli

    root = _lab_with(tmp_path, line)
    code, out, err = run_cli(capsys, "--lab", str(root), "lab", "show")
    key = line.split(":")[0].strip()
    assert code == 2 and len(err.strip().splitlines()) == 1 and f"run.{key}" in err, err
