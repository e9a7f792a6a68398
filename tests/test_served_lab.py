"""``labctl sim serve``'s pieces: the served world is consistent (the fixed camera's stream shows the table
where the served GRBL put it, moved through the real driver over the ser2net-style TCP bridge), the
``--lab-out`` lab, and the conveyor."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from labctl.config import load_lab
from labctl.errors import UserInputError
from labctl.workspace import sample_lab_path


def _red_centroid(image: np.ndarray) -> np.ndarray:
    """Centroid (u, v) of the strongly red pixels, by a plain BGR rule (independent of labctl.vision)."""
    b, g, r = (image[:, :, i].astype(int) for i in range(3))
    mask = (r > 120) & (r > g + 60) & (r > b + 60)
    assert mask.sum() > 20, "no marker visible"
    v, u = np.nonzero(mask)
    return np.array([u.mean(), v.mean()])


def test_served_fixed_stream_shows_the_table_where_the_served_grbl_put_it():
    from labctl.drivers.cameras import StreamCamera
    from labctl.drivers.grbl import GrblTable
    from labctl.geometry import invert, make_T
    from labctl.runtime.simlab import ServedLab
    from labctl.sim import truth

    lab = load_lab(sample_lab_path())
    spec = {"seed": 1, "object_name": "block", "trajectory": "line", "speed_mm_s": 8.0, "tcp": True,
            "baud": 115200}
    with ServedLab(lab, spec) as served:
        ep = served.endpoints()
        assert ep["table"].startswith("socket://")
        cam = StreamCamera(ep["fixed_camera"], timestamps="header", timeout_s=10.0)
        table = GrblTable(ep["table"], 115200, reset_on_open=False, timeout_s=10.0)
        seen = []
        with table, cam:
            table.ensure_ready(unlock=True)  # the served board powers up homing-locked; the test vouches
            for xy in ((200.0, 150.0), (300.0, 250.0)):
                st = table.move_to(*xy)
                assert st.position[:2] == pytest.approx(xy, abs=0.01)
                cam.grab()  # one whole frame after the motion ended, then the one to measure
                seen.append(_red_centroid(cam.grab().image))
    # the same displacement projected with the true fixed camera (an overhead camera: ~0.93 mm/px)
    model, T_w_c = truth.camera_model(lab.fixed_camera), truth.fixed_camera_pose(lab.fixed_camera)
    T_t_o = served.placement.T_t_o(served.obj)
    centre_o = np.mean([m.center for m in served.obj.markers], axis=0)
    expected = [model.project_world(invert(T_w_c), (make_T(None, [x, y, 0.0]) @ T_t_o @ [*centre_o, 1.0])[:3][None])[0]
                for x, y in ((200.0, 150.0), (300.0, 250.0))]
    shift_seen, shift_expected = seen[1] - seen[0], expected[1] - expected[0]
    assert np.linalg.norm(shift_expected) > 100  # the object crossed a good part of the image
    assert np.linalg.norm(shift_seen - shift_expected) < 2.0, (shift_seen, shift_expected)


class _FakeServed:
    spec: dict = {}

    def __init__(self, conveyor=None):
        self.conveyor = conveyor

    def endpoints(self):
        return {"table": "/dev/pts/98", "robot": "socket://127.0.0.1:4001",
                "fixed_camera": "http://127.0.0.1:8080/fixed.mjpg", "mobile_camera": "http://127.0.0.1:8080/mobile.mjpg"}

    def truth(self):
        return {"true_identity": "tee", "endpoints": self.endpoints()}


def test_lab_out_is_all_real_kinds_without_the_simulators_truth(tmp_path):
    from labctl.runtime.simlab import write_served_lab

    lab = load_lab(sample_lab_path())
    out = write_served_lab(lab, tmp_path / "served", _FakeServed())
    written = load_lab(out)
    assert written.kinds == {"table": "grbl", "robot": "serial", "fixed_camera": "stream", "mobile_camera": "stream"}
    assert written.table.port == "/dev/pts/98" and written.robot.port == "socket://127.0.0.1:4001"
    assert written.fixed_camera.url.endswith("/fixed.mjpg") and written.fixed_camera.timestamps == "header"
    assert written.host_link.transport == "tcp"
    text = (out / "drivers" / "mobile_camera.yaml").read_text() + (out / "drivers" / "fixed_camera.yaml").read_text()
    assert "hand_eye" not in text and "noise_sigma" not in text
    assert yaml.safe_load((out / "drivers" / "fixed_camera.yaml").read_text())["eye_w_mm"] is None
    assert json.loads((out / "served_truth.json").read_text())["true_identity"] == "tee"
    assert (out / "calibration" / "fixed_camera.yaml").is_file() and (out / "object_library").is_dir()
    with pytest.raises(UserInputError, match="not empty"):
        write_served_lab(lab, out, _FakeServed())
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    with pytest.raises(UserInputError, match="not empty"):  # --force replaces only an earlier served lab
        write_served_lab(lab, tmp_path / "mine", _FakeServed(), force=True)
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"
    conveyor_lab = load_lab(write_served_lab(lab, out, _FakeServed(conveyor=object()), force=True))
    assert conveyor_lab.table is None and conveyor_lab.config.run.trajectory == "external"
    assert not any(p.name.startswith(".served.tmp") for p in tmp_path.iterdir())


def test_conveyor_starts_only_when_the_fixed_camera_is_watched_without_a_pause():
    import threading

    from labctl.drivers.interfaces import Frame
    from labctl.runtime.simlab import Conveyor
    from labctl.sim.clock import VirtualClock
    from labctl.sim.emulators.grbl import GrblEmulator

    clock = VirtualClock(0.0)
    grbl = GrblEmulator(clock.now, start_mm=(150.0, 200.0, 0.0))
    conveyor = Conveyor(grbl, threading.RLock(), ["$X", "G90", "G1 X250 Y200 F600"], delay_s=1.0)

    class Cam:
        t = 0.0

        def grab(self):
            return Frame(image=np.zeros((2, 2, 3), np.uint8), t=self.t, seq=0)

    cam = conveyor.watch(Cam())
    cam.grab()  # one look (labctl devices): nothing
    for t in np.arange(2.0, 2.9, 0.1):  # watched again after a pause, but not for a whole second yet
        Cam.t = float(t)
        cam.grab()
    assert conveyor.started_at is None
    Cam.t = 3.05
    cam.grab()
    assert conveyor.started_at == pytest.approx(3.05)
    clock.advance(20.0 - clock.now())  # 100 mm at 10 mm/s from t = 3.05
    grbl.advance(clock.now())
    assert grbl.machine_position()[0] == pytest.approx(250.0, abs=0.01)  # it really moved the part


def test_stream_timestamps_align_with_the_served_motion():
    """While the served GRBL moves the table at 50 mm/s, each frame's object position (from the image)
    against the emulator's position at the frame's time gives the timestamp error: about zero with the
    X-Timestamp header, the pipeline's latency when frames are stamped on arrival."""
    import threading

    from labctl.drivers.cameras import StreamCamera
    from labctl.drivers.grbl import GrblTable
    from labctl.runtime.simlab import ServedLab

    lab = load_lab(sample_lab_path())
    spec = {"seed": 1, "object_name": "block", "trajectory": "line", "speed_mm_s": 8.0, "baud": 115200}
    with ServedLab(lab, spec) as served:
        ep = served.endpoints()
        clock = served.clock.now  # the served world's clock: frames and emulator on one time axis
        header = StreamCamera(ep["fixed_camera"], timestamps="header", clock=clock, timeout_s=10.0)
        arrival = StreamCamera(ep["fixed_camera"], timestamps="arrival", clock=clock, timeout_s=10.0)
        table = GrblTable(ep["table"], 115200, reset_on_open=False, timeout_s=10.0)
        with table, header, arrival:
            table.ensure_ready(unlock=True)  # the served board powers up homing-locked; the test vouches
            table.move_to(150.0, 200.0)
            header.grab()
            c0 = _red_centroid(header.grab().image)
            table.move_to(250.0, 200.0)
            header.grab()
            c1 = _red_centroid(header.grab().image)
            px_per_mm = (c1 - c0) / 100.0  # straight down on a plane parallel to the image: linear
            mover = threading.Thread(target=table.move_to, args=(150.0, 200.0, 3000.0))
            mover.start()
            errors = {"header": [], "arrival": []}
            for _ in range(12):
                for name, cam in (("header", header), ("arrival", arrival)):
                    f = cam.grab()
                    x_img = 250.0 + float((_red_centroid(f.image) - c1) @ px_per_mm / (px_per_mm @ px_per_mm))
                    x_emu = float(served.grbl.position_at(f.t)[0])
                    v = -50.0 if 152.0 < x_emu < 248.0 else None  # cruising back at F3000 (not accelerating)
                    if v is not None:
                        errors[name].append((x_emu - x_img) / v)  # > 0: the stamp is late
            mover.join()
    dt_header, dt_arrival = np.median(errors["header"]), np.median(errors["arrival"])
    assert len(errors["header"]) >= 3 and len(errors["arrival"]) >= 3
    assert abs(dt_header) < 0.012, errors  # within a third of a frame at 30 frames/s
    assert dt_arrival > dt_header + 0.005, errors  # arrival stamps carry the render/encode/transfer delay
    print(f"timestamp error: header {1e3 * dt_header:.1f} ms, arrival {1e3 * dt_arrival:.1f} ms (medians)")


def _plate_centroid(image: np.ndarray) -> np.ndarray:
    """Centroid (u, v) of the bright calibration plate's silhouette: a plain grey-level rule and the filled
    outer contour (OpenCV moments), independent of labctl's dot detection."""
    import cv2

    mask = (image.min(axis=2) > 150).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    assert contours, "no plate visible"
    m = cv2.moments(max(contours, key=cv2.contourArea))
    return np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])


def _polygon_centroid(p: np.ndarray) -> np.ndarray:
    x, y = p[:, 0], p[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    a = cross.sum() / 2
    return np.array([((x + np.roll(x, -1)) * cross).sum(), ((y + np.roll(y, -1)) * cross).sum()]) / (6 * a)


def _fresh_frame(cam, distinct: int = 4):
    """A frame exposed after a scene change: frames already on their way (encoded, in the socket,
    in the grabber) show the old scene, so wait for several new ones and keep the last."""
    seqs, frame = set(), None
    while len(seqs) < distinct:
        frame = cam.grab()
        seqs.add(frame.seq)
    return frame


def test_served_scene_control_puts_the_calibration_target_on_a_spacer_and_back():
    """``/control/scene`` (what ``labctl sim place-target`` posts): the fixed camera's stream shows the plate
    where the true camera projects it on a 0 and a 60 mm spacer, then the run's object again; bad values are 400."""
    import urllib.error
    import urllib.request

    from labctl.calibration.run import lab_target
    from labctl.drivers.cameras import StreamCamera
    from labctl.geometry import invert, make_T
    from labctl.runtime.simlab import ServedLab
    from labctl.sim import truth

    lab = load_lab(sample_lab_path())
    target = lab_target(lab.calibration_dir)
    model, T_w_c = truth.camera_model(lab.fixed_camera), truth.fixed_camera_pose(lab.fixed_camera)
    spec = {"seed": 1, "object_name": "block", "trajectory": "line", "speed_mm_s": 8.0, "scene": "calibration",
            "fps": 15}
    start = (150.0, 200.0)  # the line trajectory's start: where the served table is
    seen, expected = {}, {}
    with ServedLab(lab, spec) as served:
        url = served.endpoints()["scene_control"]

        def post(query):
            with urllib.request.urlopen(urllib.request.Request(f"{url}?{query}", method="POST"), timeout=10) as r:
                return json.loads(r.read())

        cam = StreamCamera(served.endpoints()["fixed_camera"], timestamps="header", timeout_s=10.0)
        with cam:
            for h in (0.0, 60.0):
                info = post(f"scene=calibration&spacer_mm={h:g}")
                assert info["scene"] == "calibration" and info["spacer_mm"] == h
                seen[h] = _plate_centroid(_fresh_frame(cam).image)
                solid = target.solid().transformed(make_T(None, served.world.table_origin_w) @
                                                   target.T_table_t(start, h))
                top = solid.vertices[solid.vertices[:, 2] > solid.vertices[:, 2].max() - 1e-6]
                px = model.project_world(invert(T_w_c), top)
                order = np.argsort(np.arctan2(*(px - px.mean(axis=0)).T[::-1]))
                expected[h] = _polygon_centroid(px[order])
            assert post("scene=object")["scene"] == "object"
            image = _fresh_frame(cam).image
            with pytest.raises(urllib.error.HTTPError) as bad:
                post("spacer_mm=-5")
            assert bad.value.code == 400 and "spacer_mm" in json.loads(bad.value.read())["error"]
    _red_centroid(image)  # the object's red markers are back (the target has none: dark dots, blue fiducials)
    for h in seen:
        assert np.linalg.norm(seen[h] - expected[h]) < 1.5, (h, seen[h], expected[h])
    shift_seen, shift_expected = seen[60.0] - seen[0.0], expected[60.0] - expected[0.0]
    assert np.linalg.norm(shift_expected) > 3  # the spacer visibly moves the plate in the image
    assert np.linalg.norm(shift_seen - shift_expected) < 0.5, (shift_seen, shift_expected)


def test_place_target_without_a_served_lab_is_one_line_and_exit_3_or_2(tmp_path):
    import subprocess
    import sys

    def run(*args):
        return subprocess.run([sys.executable, "-m", "labctl", "--lab", str(sample_lab_path()), "sim", *args],
                              capture_output=True, text=True, timeout=60)

    r = run("place-target", "60", "2", "2", "--url", "http://127.0.0.1:9/control/scene")
    assert r.returncode == 3 and len(r.stderr.strip().splitlines()) == 1 and "127.0.0.1:9" in r.stderr, r.stderr
    r = run("place-target", "60")  # the sample lab is not a served lab: no served_truth.json
    assert r.returncode == 2 and "served_truth.json" in r.stderr and "Traceback" not in r.stderr, r.stderr
