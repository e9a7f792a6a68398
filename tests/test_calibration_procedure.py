"""`labctl calibrate` as a procedure: the plan and --dry-run, the printable target, and stopping the
devices on every exit path (SIGINT, SIGTERM in a subprocess; a device fault in process)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from fakes import StillRobot
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.calibration.dots import detect_dots
from labctl.calibration.target import PlaneTarget, load_target, target_yaml
from labctl.cli import main
from labctl.workspace import init_workspace

REPO = Path(__file__).resolve().parents[1]


def _run(argv, capsys):
    code = 0
    try:
        main(argv)
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture
def lab(tmp_path):
    return init_workspace(tmp_path / "lab")


def test_dry_run_lists_the_plan_and_moves_nothing(lab, capsys):
    before = {p.name: p.stat().st_mtime_ns for p in (lab / "calibration").iterdir()}
    code, out, err = _run(["--lab", str(lab), "calibrate", "--dry-run", "--json"], capsys)
    assert code == 0, err
    plan = json.loads(out)
    assert plan["ok"] and plan["problems"] == []
    assert {f["spacer_mm"] for f in plan["fixed"]} == {0.0, 60.0} and len(plan["fixed"]) == 10
    assert len(plan["robot"]["stations"]) == 10 and len(plan["registration"]) == 5
    lo, hi = np.array([-800.0, -900.0, -150.0]), np.array([1400.0, 1300.0, 1300.0])  # drivers/robot.yaml
    for s in plan["robot"]["stations"] + [r["flange"] for r in plan["registration"]]:
        xyz = np.array(s["xyz_mm"] if "xyz_mm" in s else s)
        assert np.all(xyz >= lo) and np.all(xyz <= hi)
    assert max(s["tilt_deg"] for s in plan["robot"]["stations"]) > 20  # rotations about several axes
    assert {p.name: p.stat().st_mtime_ns for p in (lab / "calibration").iterdir()} == before


def test_dry_run_refuses_a_plan_outside_the_travel(lab, capsys):
    t = load_target(lab / "calibration" / "target.yaml")
    from dataclasses import replace

    bad = replace(t, fixed_positions_mm=((300.0, 200.0), (650.0, 100.0)))
    (lab / "calibration" / "target.yaml").write_text(target_yaml(bad))
    for argv in (["calibrate", "--dry-run"], ["calibrate"]):
        code, out, err = _run(["--lab", str(lab), *argv], capsys)
        assert code == 2
        assert err.count("\n") == 1 and "(650.0, 100.0) is outside the travel" in err
    assert not (lab / "calibration" / "captures").exists()  # the real run did not start


def test_bad_target_file_is_one_line_exit_2(lab, capsys):
    (lab / "calibration" / "target.yaml").write_text("kind: plane\npitch_mm: 3\n")
    code, out, err = _run(["--lab", str(lab), "calibrate"], capsys)
    assert code == 2 and err.count("\n") == 1 and "pitch too small" in err


def _svg_raster(svg: Path, px_per_mm: float) -> tuple[np.ndarray, float, float]:
    """Rasterise the SVG's rect and circles with OpenCV (sub-pixel, anti-aliased) from the parsed
    XML: an independent reading of the drawing. Returns (BGR image, page width, height in mm)."""
    root = ET.parse(svg).getroot()
    ns = {"s": "http://www.w3.org/2000/svg"}
    w_mm = float(root.get("width").removesuffix("mm"))
    h_mm = float(root.get("height").removesuffix("mm"))
    assert [float(v) for v in root.get("viewBox").split()] == pytest.approx([0, 0, w_mm, h_mm])
    shift = 4
    img = np.zeros((int(round(h_mm * px_per_mm)), int(round(w_mm * px_per_mm)), 3), np.uint8)

    def bgr(hexcol):
        r, g, b = (int(hexcol[i:i + 2], 16) for i in (1, 3, 5))
        return (b, g, r)

    img[:] = bgr(root.find("s:rect", ns).get("fill"))
    for c in root.findall("s:circle", ns):
        # pixel centres at integer coordinates: page point x mm lies at x·k − 0.5 px
        x, y, r = (float(c.get(k)) * px_per_mm for k in ("cx", "cy", "r"))
        cv2.circle(img, (int(round((x - 0.5) * 2**shift)), int(round((y - 0.5) * 2**shift))),
                   int(round(r * 2**shift)), bgr(c.get("fill")), -1, cv2.LINE_AA, shift)
    return img, w_mm, h_mm


def test_printable_target_is_true_scale_and_matches_its_geometry_file(tmp_path, capsys):
    out = tmp_path / "target.svg"
    code, _, err = _run(["--lab", str(REPO), "calibrate", "target", "--out", str(out)], capsys)
    assert code == 0, err
    geometry = load_target(tmp_path / "target.yaml")
    assert isinstance(geometry, PlaneTarget)
    assert yaml.safe_load((tmp_path / "target.yaml").read_text())["dots_mm"]  # dot centres listed
    k = 4.0  # px per mm
    img, w_mm, h_mm = _svg_raster(out, k)
    assert (w_mm, h_mm) == pytest.approx(geometry.footprint_mm)
    blobs = detect_dots(img)
    dots = geometry.solid().dots
    # the detected centres, read back to the target frame (x right, y up the page), are the file's
    page = (blobs.centers + 0.5) / k  # pixel centres at integers (as drawn)
    found = np.column_stack([page[:, 0] - w_mm / 2, h_mm / 2 - page[:, 1]])
    assert len(found) == len(dots)
    d = np.linalg.norm(found[:, None, :] - dots[None, :, :2], axis=2).min(axis=1)
    assert d.max() < 0.05
    assert int((blobs.chroma > 0.35).sum()) == len(geometry.fiducials)

    pdf = tmp_path / "t.pdf"
    code, _, err = _run(["--lab", str(REPO), "calibrate", "target", "--out", str(pdf), "--cols", "5", "--rows", "4",
                         "--pitch", "30"], capsys)
    assert code == 0, err
    box = re.search(rb"/MediaBox\s*\[\s*([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s*\]", pdf.read_bytes())
    small = load_target(tmp_path / "t.yaml")
    assert (small.cols, small.rows, small.pitch_mm) == (5, 4, 30.0)
    # PDF points are 1/72 in: the page is the plate, exactly
    assert float(box.group(3)) * 25.4 / 72 == pytest.approx(small.width_mm, abs=0.01)
    assert float(box.group(4)) * 25.4 / 72 == pytest.approx(small.length_mm, abs=0.01)
    code, _, err = _run(["calibrate", "target", "--out", str(tmp_path / "t.png")], capsys)
    assert code == 2 and "svg or .pdf" in err and err.count("\n") == 1


def test_device_fault_mid_run_stops_table_and_robot_and_writes_nothing(lab, monkeypatch, capsys):
    from labctl.errors import DeviceError
    from labctl.sim import camera as simcam
    from labctl.sim import rigs

    labs = []
    real_open = rigs.SimCalibrationLab.open

    def spy_open(self):
        labs.append(self)
        real_open(self)

    grabs = {"n": 0}
    real_grab = simcam.SimCamera.grab

    def failing_grab(self):
        grabs["n"] += 1
        if self.role == "mobile" and grabs["n"] > 3:
            # the robot is mid-way to its next station when the camera fails
            raise DeviceError("mobile camera: no frame within 2 s")
        return real_grab(self)

    monkeypatch.setattr(rigs.SimCalibrationLab, "open", spy_open)
    monkeypatch.setattr(simcam.SimCamera, "grab", failing_grab)
    before = {p.name: p.read_bytes() for p in (lab / "calibration").glob("*.yaml")}
    code, out, err = _run(["--lab", str(lab), "calibrate", "--camera", "mobile"], capsys)
    assert code == 3
    assert [ln for ln in err.splitlines() if ln.startswith("labctl")] == \
        ["labctl: error: mobile camera: no frame within 2 s"]
    sim = labs[0]
    now = sim.clock.now()
    sim.grbl.advance(now)
    assert not sim.grbl.moving and sim.grbl.state_word in ("Idle", "Hold:0")
    assert not sim.robot_emu.moving
    assert {p.name: p.read_bytes() for p in (lab / "calibration").glob("*.yaml")} == before


def _interrupt(lab: Path, sig: int, camera: str, after_images: int) -> tuple[int, str]:
    env = dict(os.environ, PYTHONPATH=str(REPO), COLUMNS="200")
    proc = subprocess.Popen([sys.executable, "-m", "labctl", "--lab", str(lab), "calibrate", "--camera", camera],
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            if len(list((lab / "calibration").glob("captures/*/*.png"))) >= after_images:
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()[1].decode()
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, err.decode()


@pytest.mark.parametrize("sig, camera, after", [(signal.SIGINT, "fixed", 2), (signal.SIGTERM, "mobile", 2)])
def test_signal_during_calibrate_stops_the_devices_one_line_exit_130(lab, sig, camera, after):
    before = {p.name: p.read_bytes() for p in (lab / "calibration").glob("*.yaml")}
    code, err = _interrupt(lab, sig, camera, after)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 130, err
    assert "Traceback" not in err
    assert len([ln for ln in lines if ln.startswith("labctl")]) == 1
    last = lines[-1]
    assert re.match(r"labctl: interrupted: table stopped \((Idle|Hold:0) at [\d.]+, [\d.]+\)", last), last
    if camera == "mobile":
        assert last.endswith("robot stopped")
    assert {p.name: p.read_bytes() for p in (lab / "calibration").glob("*.yaml")} == before
    assert len(list((lab / "calibration").glob("captures/*/*.png"))) >= after  # images taken so far are kept


def test_mixed_simulated_and_real_devices_are_refused(lab, capsys):
    f = lab / "drivers" / "fixed_camera.yaml"
    f.write_text(f.read_text().replace("kind: sim", "kind: v4l2").replace("device: null", "device: 0"))
    code, _, err = _run(["--lab", str(lab), "calibrate", "--camera", "fixed"], capsys)
    assert code == 2 and err.count("\n") == 1 and "all simulated or all real" in err
    assert not (lab / "calibration" / "captures").exists()


def test_prompt_command_places_the_target_or_refuses(tmp_path):
    from labctl.cli.calibrate import CommandPrompt, PromptRefused
    from labctl.errors import UserInputError

    log = tmp_path / "placed.txt"
    script = tmp_path / "place.py"
    script.write_text("import sys\nopen(sys.argv[1], 'a').write(' '.join(sys.argv[2:]) + '\\n')\n"
                      "sys.exit(3 if sys.argv[2] == '99' else 0)\n")
    p = CommandPrompt(f"{sys.executable} {script} {log}")
    p.place_target(0.0, 0, 2)
    p.place_target(60.0, 1, 2)
    assert log.read_text().splitlines() == ["0 1 2", "60 2 2"]
    with pytest.raises(PromptRefused, match="did not place the target on 99 mm") as refused:
        p.place_target(99.0, 0, 1)
    assert isinstance(refused.value.error, UserInputError)  # what the command exits with: 2


def test_served_truth_file_is_read_as_the_simulator_truth(tmp_path):
    """The served lab's truth file (labctl sim serve --lab-out) describes the same world."""
    from labctl.calibration.run import load_truth
    from labctl.config import load_lab
    from labctl.sim import truth
    from labctl.sim.rigs import SimCalibrationLab

    lab = load_lab(REPO)
    served = {"fixed_camera": {"T_w_c": truth.fixed_camera_pose(lab.fixed_camera).tolist(),
                               "model": truth.camera_model(lab.fixed_camera).to_dict()},
              "mobile_camera": {"T_f_c": truth.hand_eye(lab.mobile_camera).tolist(),
                                "model": truth.camera_model(lab.mobile_camera).to_dict()},
              "table_origin_w_mm": list(lab.table.origin_w_mm), "T_w_b": np.eye(4).tolist()}
    (tmp_path / "served_truth.json").write_text(json.dumps(served))
    got = load_truth(tmp_path / "served_truth.json")
    ref = SimCalibrationLab(lab, PlaneTarget()).truth()
    assert got.fixed_camera == ref["fixed_camera"] and got.mobile_camera == ref["mobile_camera"]
    for key in ("T_w_c1", "T_f_c2", "T_w_table"):
        assert np.allclose(getattr(got, key), ref[key])
    (tmp_path / "bad.json").write_text(json.dumps({"fixed_camera": {}}))
    from labctl.errors import UserInputError

    with pytest.raises(UserInputError, match="missing or malformed"):
        load_truth(tmp_path / "bad.json")


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-800.0, 800.0), min_size=3, max_size=3), st.lists(st.floats(-3.0, 3.0), min_size=3,
                                                                            max_size=3))
def test_segment_durations_keep_the_quintic_within_half_the_robot_limits(dp, rv):
    """The controller interpolates a quintic (docs/protocols/robot.md); sampled numerically, its
    peak speed, acceleration and angular speed stay within half the configured limits."""
    from labctl.calibration.procedure import Motion, segment_duration
    from labctl.geometry import make_T, rotvec_to_matrix

    m = Motion(v_max_mm_s=500.0, a_max_mm_s2=1500.0, w_max_deg_s=120.0)
    A = make_T(None, [100.0, -200.0, 900.0])
    B = make_T(rotvec_to_matrix(np.array(rv)), A[:3, 3] + np.array(dp))
    T = segment_duration(A, B, m)
    tau = np.linspace(0.0, 1.0, 2001)
    s = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
    v = np.gradient(s, tau) / T
    a = np.gradient(v, tau) / T
    d = float(np.linalg.norm(dp))
    ang = float(np.degrees(np.linalg.norm(rv))) if np.linalg.norm(rv) <= np.pi else None
    assert d * v.max() <= 0.5 * m.v_max_mm_s * 1.001
    assert d * np.abs(a).max() <= 0.5 * m.a_max_mm_s2 * 1.01
    if ang is not None:
        assert ang * v.max() <= 0.5 * m.w_max_deg_s * 1.001


def test_terminal_prompt_waits_for_enter_and_refuses_a_closed_stdin(monkeypatch, capsys):
    import io

    from labctl.cli.calibrate import PromptRefused, TerminalPrompt
    from labctl.errors import UserInputError

    monkeypatch.setattr(sys, "stdin", io.StringIO("\n"))
    TerminalPrompt().place_target(60.0, 1, 2)
    assert "[2/2] put the calibration target on its locating pins on the 60 mm spacer" in capsys.readouterr().err
    with pytest.raises(PromptRefused, match="stdin closed") as refused:
        TerminalPrompt().place_target(0.0, 0, 2)
    assert isinstance(refused.value.error, UserInputError)


def test_target_mounted_off_centre_and_turned_still_registers_the_table(tmp_path):
    """The mount (x, y, yaw) enters the fixed camera's points and the table registration; a
    turned, offset target must give the same table frame and camera poses as the truth.
    A smaller plan than the sample lab's keeps this quick."""
    from dataclasses import replace

    from labctl.calibration.procedure import Devices
    from labctl.calibration.run import Truth, nominal_for, run_lab_calibration
    from labctl.config import load_lab
    from labctl.sim.rigs import SimCalibrationLab

    root = init_workspace(tmp_path / "lab")
    for f in (root / "calibration").glob("*.yaml"):
        if f.name != "target.yaml":
            f.unlink()
    lab = load_lab(root)
    target = replace(PlaneTarget(), mount_on_table=(15.0, -10.0, 20.0), spacers_mm=(0.0, 45.0),
                     fixed_positions_mm=((285.0, 210.0), (150.0, 120.0), (420.0, 290.0)), robot_stations=6,
                     registration_positions_mm=((285.0, 210.0), (120.0, 90.0), (450.0, 120.0)))
    sim = SimCalibrationLab(lab, target, seed=3)
    sim.open()
    try:
        devs = Devices(sim.table, sim.robot, sim.cameras["fixed"], sim.cameras["mobile"], sim.clock)
        rep = run_lab_calibration(root / "calibration", devs, sim, target, nominal_for(lab), truth=Truth(**sim.truth()))
    finally:
        sim.close()
    assert sim.prompts == [0.0, 45.0]
    assert rep["table"]["error_vs_truth"]["origin_mm"] < 0.5 and rep["table"]["error_vs_truth"]["rotation_deg"] < 0.05
    assert rep["fixed_camera"]["error_vs_truth"]["table_plane"]["max_percent_of_fov"] < 0.1
    he = rep["mobile_camera"]["error_vs_truth"]["hand_eye"]
    assert he["rotation_deg"] < 0.2 and he["translation_mm"] < 1.0


class _StopsShortRobot(StillRobot):
    """A robot (the Robot interface plus the dialect's ``clear``) whose controller's watchdog cuts the
    first ``trips`` segments short halfway, latching E40 until CLEAR, as on an overloaded host."""

    def __init__(self, trips: int):
        from labctl.geometry import make_T

        self.T, self.trips, self.cleared, self.seg, self.fault = make_T(None, [0.0, 0.0, 1000.0]), trips, 0, 0, False

    def status(self):
        from labctl.drivers.interfaces import RobotStatus

        return RobotStatus(T_base_flange=self.T.copy(), moving=False, segment_id=self.seg, t=0.0)

    def segment(self, T, duration_s, segment_id):
        from labctl.drivers.robot import RobotError

        if self.fault:
            raise RobotError(40, "stopped by the watchdog: send CLEAR", "SEG")
        self.seg = segment_id
        if self.trips > 0:
            self.trips -= 1
            self.fault = True
            self.T[:3, 3] = (self.T[:3, 3] + np.asarray(T)[:3, 3]) / 2  # stopped halfway
        else:
            self.T = np.asarray(T, float).copy()

    def clear(self):
        self.fault, self.cleared = False, self.cleared + 1

    def heartbeat(self):
        pass


@pytest.mark.parametrize("trips, ok", [(0, True), (2, True), (6, False)])
def test_a_move_the_watchdog_cut_short_is_commanded_again_or_fails_never_grabs_off_pose(trips, ok):
    from labctl.calibration.procedure import Devices, Motion, _Robot
    from labctl.errors import DeviceError
    from labctl.geometry import make_T
    from labctl.sim.clock import VirtualClock

    robot = _StopsShortRobot(trips)
    devs = Devices(table=None, robot=robot, fixed=None, mobile=None, clock=VirtualClock())
    mover = _Robot(devs, Motion(robot_retries=5))
    goal = make_T(None, [300.0, -200.0, 900.0])
    if ok:
        assert np.allclose(mover.move(goal), goal)
        assert robot.cleared == trips and len(mover.recovered) == trips
    else:
        with pytest.raises(DeviceError, match="did not reach its pose"):
            mover.move(goal)
        assert not np.allclose(robot.T, goal)
