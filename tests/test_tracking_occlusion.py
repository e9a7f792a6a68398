"""The tracker bridges a short occlusion of the marker on its prediction and says so; a long one loses the track.

A scripted occluder blanks the fixed camera's frames over a time span of a virtual run (as a link of the arm
crossing the camera's view of the object would); the record must show the gap — a ``track_bridged`` event
with the frames the occluder actually blanked, or a ``marker_lost`` event beyond ``tracking.max_bridge_s``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from labctl.config import load_lab
from labctl.decisions.context import RunContext
from labctl.records.events import validate
from labctl.runtime.virtual import TrialSpec, simulate_run
from labctl.sim.arm import ARM_COLOUR_BGR
from labctl.sim.world import SimWorld
from labctl.tracking.bridge import OcclusionBridge
from labctl.workspace import sample_lab_path

FPS = 30.0


@pytest.fixture(scope="module")
def lab():
    return load_lab(sample_lab_path())


@pytest.fixture(scope="module")
def ctx(lab):
    return RunContext.load(lab)


class Log:
    """A record that keeps the events (each checked against the declared schema) and drops images."""

    def __init__(self):
        self.events: list[tuple[str, dict]] = []

    def event(self, name, **fields):
        import json

        from labctl.records.record import to_jsonable  # the record's own conversion of numpy values

        line = json.loads(json.dumps(to_jsonable(fields)))
        validate({"event": name, "wall": 0.0, **line})
        self.events.append((name, line))

    def save_image(self, *a, **k):
        return None

    def named(self, name):
        return [f for n, f in self.events if n == name]


def occluded_run(monkeypatch, lab, ctx, start_s: float, n_frames: int, seed: int = 3):
    """A virtual run whose fixed-camera frames are blanked (the arm's grey) for ``n_frames`` frame times from
    ``start_s`` after the first frame; returns the result, the log and the times of the frames blanked."""
    orig = SimWorld.render
    first: list[float] = []
    blanked: list[float] = []

    def render(self, role, t, *a, **k):
        res = orig(self, role, t, *a, **k)
        if role == "fixed":
            if not first:
                first.append(t)
            if first[0] + start_s <= t < first[0] + start_s + n_frames / FPS - 1e-9:
                res.image[...] = ARM_COLOUR_BGR
                blanked.append(t)
        return res

    monkeypatch.setattr(SimWorld, "render", render)
    log = Log()
    res = simulate_run(lab, ctx, TrialSpec("line", 8.0, None, seed), log)
    return res, log, blanked


def test_bridge_bookkeeping():
    b = OcclusionBridge(1.0)
    assert b.seen(0.0) is None and not b.open
    for k in range(1, 6):
        b.missed(k / FPS)
    assert b.open and b.frames == 5 and b.bridging(5 / FPS) and not b.expired(0.9)
    closed = b.seen(6 / FPS)
    assert closed is not None and closed.frames == 5 and closed.duration_s == pytest.approx(6 / FPS)
    for k in range(7, 7 + 40):
        b.missed(k / FPS)
    assert b.expired(46 / FPS) and not b.bridging(46 / FPS)
    assert b.seen(47 / FPS) is None  # too long: not a bridge
    assert len(b.bridged) == 1
    with pytest.raises(ValueError):
        OcclusionBridge(0.0)


def test_short_occlusion_is_bridged_and_recorded(monkeypatch, lab, ctx):
    n = 9  # 0.3 s, while the robot flies to the first view
    res, log, blanked = occluded_run(monkeypatch, lab, ctx, 0.6, n)
    assert len(blanked) == n
    bridges = log.named("track_bridged")
    assert len(bridges) == 1, bridges
    b = bridges[0]
    assert b["frames"] == n
    assert b["t_start"] < blanked[0] and b["t_end"] > blanked[-1]
    assert b["duration_s"] == pytest.approx((n + 1) / FPS, abs=1e-6)
    assert b["duration_s"] <= lab.config.tracking.max_bridge_s
    assert not log.named("marker_lost")
    # the track went on: sightings after the gap, and the run found the object
    assert any(f["t"] > blanked[-1] for f in log.named("track"))
    assert res["failure"] is None and res["correct"], res


def test_long_occlusion_loses_the_track_with_a_record(monkeypatch, lab, ctx):
    limit = lab.config.tracking.max_bridge_s
    n = int(np.ceil(1.5 * limit * FPS))
    res, log, blanked = occluded_run(monkeypatch, lab, ctx, 0.6, n)
    assert len(blanked) == n
    lost = log.named("marker_lost")
    assert len(lost) == 1, lost
    assert lost[0]["gap_s"] > limit and lost[0]["frames"] >= int(limit * FPS)
    assert blanked[0] < lost[0]["t"] <= blanked[-1]
    # a later stage goes on coasting on the prediction; that gap is not called a bridge
    stage_at = [f["stage"] for f in log.named("stage") if f["t"] <= lost[0]["t"]][-1]
    assert lost[0].get("coasting") is (stage_at != "track")
    assert not [b for b in log.named("track_bridged") if b["t_start"] < blanked[-1] < b["t_end"]]


def test_the_bound_is_the_setting(monkeypatch, lab, ctx):
    """The same 1.5-s occlusion is a bridge when tracking.max_bridge_s allows 2 s."""
    cfg = lab.config
    lab2 = dataclasses.replace(lab, config=dataclasses.replace(
        cfg, tracking=dataclasses.replace(cfg.tracking, max_bridge_s=2.0)))
    ctx2 = dataclasses.replace(ctx, lab=lab2)
    n = int(np.ceil(1.5 * cfg.tracking.max_bridge_s * FPS))
    _, log, blanked = occluded_run(monkeypatch, lab2, ctx2, 0.6, n)
    bridges = [b for b in log.named("track_bridged") if b["t_start"] < blanked[0]]
    assert not log.named("marker_lost")
    assert bridges and bridges[0]["frames"] == n and bridges[0]["duration_s"] > cfg.tracking.max_bridge_s
