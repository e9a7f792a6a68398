"""The recogniser applies the two-view pose check (vision.pose_pair_consistency) to each marker it pairs
across the two initial images: a marker whose normals disagree between the views beyond their
covariances is treated as suspect, i.e. reported after every consistent marker (a last resort)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from labctl.decisions import messages as m
from labctl.decisions.recognizer import Recognizer, _Candidates
from labctl.drivers.interfaces import Frame
from labctl.vision import CirclePose, Ellipse, MarkerPoses


def _rot(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    t = math.radians(deg)
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _marker(cx, cy, trusted=True):
    ell = Ellipse.from_params((cx, cy), (20.0, 12.0), 0.3)
    return SimpleNamespace(ellipse=ell, centroid=(cx, cy), trusted=trusted)


def _poses(center, true_n, false_n, sigma_deg=0.2):
    """World = camera frame (identity camera pose): the recogniser's candidate pair with its covariances."""
    s = math.radians(sigma_deg)
    cands = (CirclePose(np.asarray(center, float), _unit(true_n)), CirclePose(np.asarray(center, float) + 1.0,
                                                                                _unit(false_n)))
    mp = MarkerPoses(cands, (s, s), np.stack([np.eye(3) * s * s / 2] * 2), np.stack([np.eye(3) * 0.04] * 2))
    out = _Candidates(cands)
    out.sigma_rad, out.camera_poses, out.R_w_c = s, mp, np.eye(3)
    return out


def _recognizer(found_per_image):
    lab = SimpleNamespace(config=SimpleNamespace(marker=SimpleNamespace(radius_mm=8.0),
                                                 run=SimpleNamespace(ambiguity_threshold=None)),
                          table=None, mobile_camera=SimpleNamespace(marker_hue_deg=(-15.0, 15.0),
                                                                    marker_min_saturation=0.45, response="linear"),
                          response_declared=lambda role: True)
    ctx = SimpleNamespace(lab=lab, mobile_camera=SimpleNamespace(width=640, height=480))
    rec = Recognizer(ctx, grab=lambda: None, log=lambda *a, **k: None)
    images = iter(found_per_image)
    rec._candidates = lambda frame, T: next(images)
    return rec


def _run(bend_deg):
    """Markers A and B, both resolved; B is the preferred one (the recogniser's order: it faces up the most,
    i.e. its normal has the least negative z in this identity world frame), and its normal turns by
    ``bend_deg`` between the views although the object only translated. Returns the reported normals in
    order and the true second-image normals of A and B."""
    a_true, a_false = _unit((0.1, 0.2, -1.0)), _unit((0.6, -0.3, -1.0))
    b_true, b_false = _unit((0.9, 0.1, -0.4)), _unit((0.2, 0.8, -0.6))
    shift = np.array([20.0, 0.0, 0.0])
    b2_true = _rot((1.0, 0.3, 0.0), bend_deg) @ b_true
    first = [(_marker(320, 240), _poses((0, 0, 500), a_true, a_false)),
             (_marker(420, 300), _poses((30, 20, 490), b_true, b_false))]
    second = [(_marker(340, 240), _poses(np.add((0, 0, 500), shift), a_true, _unit((-0.5, 0.4, -1.0)))),
              (_marker(440, 300), _poses(np.add((30, 20, 490), shift), b2_true, _unit((-0.3, -0.7, -0.6))))]
    rec = _recognizer([first, second])
    frame = Frame(np.zeros((480, 640, 3), np.uint8), 0.0, 1)
    msg1 = m.CaptureRequest(view_id=1, kind="initial1", t_capture=0.0, position=(0, 0, 0), rotvec=(0, 0, 0))
    msg2 = m.CaptureRequest(view_id=2, kind="initial2", t_capture=1.0, position=(0, 0, 0), rotvec=(0, 0, 0))
    rec._initial(msg1, frame, np.eye(4))
    replies = [r for r in rec._initial(msg2, frame, np.eye(4)) if isinstance(r, m.MarkerPose)]
    assert all(not r.ambiguous for r in replies)
    return [np.asarray(r.normal_w) for r in replies], a_true, b2_true


def test_consistent_markers_keep_the_preferred_order():
    normals, a, b2 = _run(0.0)
    assert len(normals) == 2 and np.allclose(normals[0], b2, atol=1e-4) and np.allclose(normals[1], a, atol=1e-4)


def test_a_marker_whose_views_disagree_is_reported_last():
    # 3° of bend against σ 0.2° per view: z ≈ 10, far past the check's 4 σ; the duality is still decided
    normals, a, b2 = _run(3.0)
    assert len(normals) == 2 and np.allclose(normals[0], a, atol=1e-4) and np.allclose(normals[1], b2, atol=1e-4)


def test_a_discarded_image_leaves_the_recognizer_as_before_it():
    """An image requested at the robot's promised arrival whose @DONE never came is discarded (m.Discard): the
    recognizer forgets the marker it took from it, so the retaken image is a first image again."""
    a_true, a_false = _unit((0.1, 0.2, -1.0)), _unit((0.6, -0.3, -1.0))
    found = [(_marker(320, 240), _poses((0, 0, 500), a_true, a_false))]
    moved = [(_marker(340, 240), _poses((20, 0, 500), a_true, _unit((-0.5, 0.4, -1.0))))]
    rec = _recognizer([found, found, moved])
    frames = iter(Frame(np.zeros((480, 640, 3), np.uint8), t, k) for k, t in enumerate((0.0, 1.0, 2.0, 3.0)))
    rec.grab = lambda: next(frames)
    req = lambda v, kind, t: m.CaptureRequest(view_id=v, kind=kind, t_capture=t, position=(0, 0, 0),  # noqa: E731
                                              rotvec=(0, 0, 0))
    assert [type(r) for r in rec.handle(req(1, "initial1", 0.0))] == [m.FrameTaken]
    assert rec.first is not None and rec.n_initial_seen == 1
    assert rec.handle(m.Discard(view_id=2)) == [] and rec.first is not None  # not the last image: nothing undone
    rec.handle(req(2, "initial1", 1.0))
    assert rec.handle(m.Discard(view_id=2)) == [] and rec.n_initial_seen == 1 and rec.first is not None
    rec.handle(req(3, "initial2", 2.0))  # paired with view 1's marker: one pose resolved
    assert rec.resolved_normals
    rec.handle(m.Discard(view_id=3))
    assert rec.resolved_normals == [] and rec.first is not None and rec.n_initial_seen == 1


def test_a_capture_skips_frames_exposed_before_its_request():
    """A free-running camera's latest frame may be older than the request (the robot still moving then): the
    recognizer takes the first frame stamped at or after ``t_capture``."""
    rec = _recognizer([[]])
    frames = iter(Frame(np.zeros((480, 640, 3), np.uint8), t, k) for k, t in enumerate((0.97, 0.999, 1.0, 1.03)))
    rec.grab = lambda: next(frames)
    assert rec._grab_after(1.0).t == 1.0
    rec.grab = lambda: Frame(np.zeros((480, 640, 3), np.uint8), 0.5, 1)  # a camera that never catches up
    assert rec._grab_after(1.0).t == 0.5  # at most MAX_STALE_GRABS skipped: no endless wait
