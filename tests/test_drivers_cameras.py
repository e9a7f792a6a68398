"""Cameras: replay folders (stamped names and index.csv), the V4L2 driver's failure mode, the factory."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from labctl.drivers.cameras import CameraError, ReplayCamera, V4L2Camera, open_camera, save_stamped_frame
from labctl.drivers.interfaces import Camera, Frame
from labctl.sim.clock import VirtualClock
from labctl.workspace import sample_lab_path


def frames(n=5):
    rng = np.random.default_rng(0)
    return [Frame(image=rng.integers(0, 255, (24, 32, 3), dtype=np.uint8), t=0.1 * i + 0.0333, seq=i)
            for i in range(n)]


def test_replay_round_trip_in_order(tmp_path):
    src = frames()
    for f in reversed(src):
        save_stamped_frame(tmp_path, f)
    cam = ReplayCamera(tmp_path)
    assert isinstance(cam, Camera)
    with cam:
        got = [cam.grab() for _ in src]
        with pytest.raises(CameraError):
            cam.grab()  # end of the recording
    assert [g.t for g in got] == pytest.approx([f.t for f in src], abs=1e-6)
    assert all(np.array_equal(g.image, f.image) for g, f in zip(got, src))  # PNG is lossless


def test_replay_with_clock_gives_latest_frame(tmp_path):
    for f in frames():
        save_stamped_frame(tmp_path, f)
    clk = VirtualClock(0.01)
    with ReplayCamera(tmp_path, clock=clk) as cam:
        with pytest.raises(CameraError):
            cam.grab()  # before the first frame
        clk.sleep_until(0.25)
        assert cam.grab().t == pytest.approx(0.2333, abs=1e-6)


def test_replay_with_clock_catches_up_on_the_frames_stamped_since_the_last_delivered(tmp_path):
    src = frames(8)  # stamped 0.0333, 0.1333, ... 0.7333
    for f in src:
        save_stamped_frame(tmp_path, f)
    clk = VirtualClock(0.05)
    with ReplayCamera(tmp_path, clock=clk) as cam:
        assert [f.t for f in cam.grab_recent(4)] == pytest.approx([0.0333], abs=1e-6)
        clk.sleep_until(0.36)  # three more stamped meanwhile
        got = cam.grab_recent(4)
        assert [f.t for f in got] == pytest.approx([0.1333, 0.2333, 0.3333], abs=1e-6)
        assert all(np.array_equal(g.image, f.image) for g, f in zip(got, src[1:4]))
        clk.sleep_until(0.75)  # four more: the newest two
        assert [f.t for f in cam.grab_recent(2)] == pytest.approx([0.6333, 0.7333], abs=1e-6)


def test_replay_index_file(tmp_path):
    import cv2

    img = np.full((8, 8, 3), 200, np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), img)
    cv2.imwrite(str(tmp_path / "b.png"), img // 2)
    (tmp_path / "index.csv").write_text("t,file\n2.5,b.png\n1.0,a.png\n")
    with ReplayCamera(tmp_path) as cam:
        f1, f2 = cam.grab(), cam.grab()
    assert (f1.t, f2.t) == (1.0, 2.5) and f1.image[0, 0, 0] == 200


def test_replay_errors(tmp_path):
    with pytest.raises(CameraError):
        ReplayCamera(tmp_path / "nope").open()
    with pytest.raises(CameraError):
        ReplayCamera(tmp_path).open()  # empty folder


def test_v4l2_missing_device_is_a_camera_error():
    cam = V4L2Camera("/dev/video-does-not-exist", timeout_s=0.2)
    with pytest.raises(CameraError):
        cam.open()
    with pytest.raises(CameraError):
        cam.grab()


def test_factory_builds_replay_camera_from_lab(tmp_path):
    from labctl.config import load_lab

    lab = load_lab(sample_lab_path())
    for f in frames(2):
        save_stamped_frame(tmp_path, f)
    cfg = dataclasses.replace(lab.fixed_camera, kind="replay", folder=str(tmp_path))
    lab2 = dataclasses.replace(lab, fixed_camera=cfg)
    cam = open_camera("fixed", lab2)
    assert isinstance(cam, ReplayCamera)
    with cam:
        assert cam.grab().image.shape == (24, 32, 3)
