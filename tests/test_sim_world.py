"""The simulated lab: clocks, world geometry, simulated cameras, frame server, virtual lab, snapshot."""

from __future__ import annotations

import multiprocessing as mp
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.config import load_lab
from labctl.drivers.interfaces import Camera
from labctl.errors import DeviceError, UserInputError
from labctl.geometry import apply, invert, make_T, rot_x
from labctl.sim.camera import FrameClient, FrameServer, SimCamera
from labctl.sim.clock import ClockError, RealClock, VirtualClock
from labctl.sim.lab import Scene, SimLab
from labctl.sim.snapshot import snapshot
from labctl.sim.truth import fixed_camera_pose, hand_eye
from labctl.sim.world import (
    Placement,
    SimWorld,
    WorldError,
    builtin_test_object,
    home_flange_pose,
    random_placement,
    table_centre_w,
)
from labctl.workspace import sample_lab_path


@pytest.fixture(scope="module")
def lab():
    return load_lab(sample_lab_path())


@pytest.fixture(scope="module")
def block():
    return builtin_test_object(8.0)


# --- clocks ---------------------------------------------------------------------------------
def test_virtual_clock_moves_only_forward():
    c = VirtualClock(1.0)
    assert c() == 1.0
    c.sleep(0.25)
    c.advance(0.5)
    assert c.now() == pytest.approx(1.75)
    c.sleep_until(1.5)  # in the past: no-op
    assert c.now() == pytest.approx(1.75)
    c.sleep_until(3.0)
    assert c.now() == 3.0
    with pytest.raises(ClockError):
        c.advance(-1.0)
    with pytest.raises(ClockError):
        c.sleep_until(float("nan"))


def test_real_clock_sleeps():
    c = RealClock()
    t0 = c.now()
    c.sleep_until(t0 + 0.02)
    assert c.now() - t0 >= 0.02
    assert not c.is_virtual and VirtualClock().is_virtual


# --- world geometry -------------------------------------------------------------------------
@settings(max_examples=25, deadline=None, derandomize=True)
@given(seed=st.integers(0, 100_000))
def test_object_rests_on_the_table_in_every_placement(seed):
    obj = builtin_test_object(8.0)
    rng = np.random.default_rng(seed)
    p = random_placement(obj, rng)
    verts = apply(p.T_t_o(obj), obj.vertices)
    assert verts[:, 2].min() == pytest.approx(0.0, abs=1e-6)  # lowest point on z = 0, nothing below
    assert 0 <= p.yaw < 2 * np.pi and max(abs(v) for v in p.offset_xy) <= 30.0


def test_stable_poses_are_drawn_with_their_probabilities(block):
    rng = np.random.default_rng(5)
    counts = np.bincount([random_placement(block, rng).pose_index for _ in range(4000)],
                         minlength=len(block.stable_poses))
    expected = np.array([p for _, p in block.stable_poses])
    expected = expected / expected.sum()
    assert np.allclose(counts / counts.sum(), expected, atol=0.03)


def test_bad_pose_index_and_role_are_typed_errors(lab, block):
    with pytest.raises(WorldError):
        Placement(99, 0.0, (0.0, 0.0)).T_t_o(block)
    world = SimWorld.from_lab(lab, obj=block)
    with pytest.raises(WorldError):
        world.render("ceiling", 0.0)


def test_camera_poses_follow_the_driver_files_and_the_robot(lab):
    world = SimWorld.from_lab(lab)
    assert np.allclose(world.T_w_c("fixed", 3.0), fixed_camera_pose(lab.fixed_camera))
    T_b_f = make_T(rot_x(np.pi), (250.0, 10.0, 700.0))
    world.flange_pose_at = lambda t: T_b_f
    assert np.allclose(world.T_w_c("mobile", 0.0), T_b_f @ hand_eye(lab.mobile_camera))
    # default: the mobile camera at the robot's home, looking at the table's centre
    world = SimWorld.from_lab(lab)
    T = world.T_w_c("mobile", 0.0)
    assert np.allclose(T[:3, 3], lab.robot.home_mm)
    model = world.rigs["mobile"].model
    centre_px = model.project_world(invert(T), table_centre_w(lab)[None])[0]
    assert np.allclose(centre_px, [model.cx, model.cy], atol=1e-6)
    assert np.allclose(home_flange_pose(lab) @ hand_eye(lab.mobile_camera), T)


def test_fixed_camera_matches_the_papers_geometry(lab):
    world = SimWorld.from_lab(lab)
    model, T = world.rigs["fixed"].model, world.T_w_c1
    assert T[2, 3] == pytest.approx(1800.0)
    corners = np.array([[0, 0], [model.width - 1, model.height - 1.0]])
    # ground footprint of the image: about 600 mm across at about 0.93 mm per pixel
    n = model.normalized(corners)
    span_mm = (n[1] - n[0]) * 1800.0
    assert 590 < span_mm[0] < 610
    assert span_mm[0] / (model.width - 1) == pytest.approx(0.936, abs=0.01)


def test_rendered_marker_sits_where_the_truth_says(lab, block):
    world = SimWorld.from_lab(lab, obj=block, placement=Placement(0, 0.4, (10.0, -5.0)))
    res = world.render("fixed", 0.0, np.random.default_rng(0), truth=True)
    truth = world.truth(0.0)
    model = world.rigs["fixed"].model
    T_c_w = invert(world.T_w_c1)
    up = [i for i, (_, c, n) in enumerate(truth.markers_w) if n[2] > 0.99]
    assert len(up) == 1
    mid, c_w, n_w = truth.markers_w[up[0]]
    # ground truth in the camera frame agrees with the world truth
    c_c, n_c = res.markers_c[up[0]]
    assert np.allclose(c_c, apply(T_c_w, c_w)) and np.allclose(n_c, T_c_w[:3, :3] @ n_w)
    # the red blob's centroid is the projected marker centre
    img = res.image.astype(int)
    red = (img[..., 2] - img[..., 1]) > 60
    ys, xs = np.nonzero(red)
    assert res.marker_pixels[up[0]] == pytest.approx(len(xs), rel=0.1)
    expected = model.project(c_c[None])[0]
    assert np.hypot(xs.mean() - expected[0], ys.mean() - expected[1]) < 0.3
    # area: a circle of radius 8 mm at 0.936 mm/px·(1800-35)/1800
    r_px = 8.0 / (0.936 * (1800 - 35) / 1800)
    assert len(xs) == pytest.approx(np.pi * r_px**2, rel=0.08)


def test_object_rides_the_table(lab, block):
    world = SimWorld.from_lab(lab, obj=block, placement=Placement(0, 0.0, (0.0, 0.0)),
                              table_position=lambda t: (300.0 + 10.0 * t, 200.0, 0.0))
    a = world.render("fixed", 0.0, truth=True, rng=np.random.default_rng(1))
    b = world.render("fixed", 3.0, truth=True, rng=np.random.default_rng(1))
    assert np.allclose(world.T_w_o(3.0)[:3, 3] - world.T_w_o(0.0)[:3, 3], [30.0, 0.0, 0.0])
    ca = np.argwhere(a.mask).mean(axis=0)
    cb = np.argwhere(b.mask).mean(axis=0)
    # 30 mm along +x of W is about 30 / 0.936 · 1800 / (1800 − 17.5) px along the image columns
    assert cb[1] - ca[1] == pytest.approx(30.0 / 0.936 * 1800 / (1800 - 17.5), abs=0.3)
    assert abs(cb[0] - ca[0]) < 0.2


def test_motion_blur_from_the_world(lab, block):
    sharp = SimWorld.from_lab(lab, obj=block, table_position=lambda t: (300.0 + 100.0 * t, 200.0, 0.0))
    blurred = SimWorld.from_lab(lab, obj=block, table_position=lambda t: (300.0 + 100.0 * t, 200.0, 0.0),
                                exposure_s=0.05)
    a = sharp.render("fixed", 0.0, truth=True, rng=np.random.default_rng(1))
    b = blurred.render("fixed", 0.0, truth=True, rng=np.random.default_rng(1))
    row = int(np.argwhere(a.mask)[:, 0].mean())
    ga = a.image[row, :, 1].astype(float)
    gb = b.image[row, :, 1].astype(float)
    # the leading edge spreads over ~5 mm (5 px) instead of ~1 px
    assert np.count_nonzero(np.abs(np.diff(gb)) > 12) > np.count_nonzero(np.abs(np.diff(ga)) > 12)


# --- simulated cameras ----------------------------------------------------------------------
def test_sim_camera_paces_frames_on_the_clock(lab, block):
    clock = VirtualClock(0.0)
    world = SimWorld.from_lab(lab, obj=block)
    cam = SimCamera(world, "fixed", clock, fps=30.0, seed=3)
    assert isinstance(cam, Camera)
    with pytest.raises(DeviceError):
        cam.grab()
    cam.open()
    f0 = cam.grab()
    f1 = cam.grab()  # nothing new yet: waits one frame period on the virtual clock
    assert (f0.seq, f1.seq) == (0, 1)
    assert f1.t == pytest.approx(1 / 30) and clock.now() == pytest.approx(1 / 30)
    clock.advance(0.5)  # frames 2..15 are missed: grab returns the latest, never a stale one
    f2 = cam.grab()
    assert f2.seq == 16 and f2.t <= clock.now() < f2.t + 1 / 30
    assert f2.image.shape == (480, 640, 3) and f2.image.dtype == np.uint8
    assert cam.info()["fps"] == 30.0 and cam.info()["camera_model"]["f"] == 25.0


def _virtual_lab(lab, seed: int, truth: bool = False) -> SimLab:
    """The whole simulated lab on a virtual clock at t = 0: the test block placed by the seed."""
    return SimLab.build(lab, VirtualClock(0.0), scene=Scene.test_block(lab, seed), seed=seed, truth=truth)


def test_same_seed_same_frames_bit_for_bit(lab):
    a = _virtual_lab(lab, seed=11)
    b = _virtual_lab(lab, seed=11)
    c = _virtual_lab(lab, seed=12)
    for v in (a, b, c):
        v.cameras["fixed"].open()
        v.cameras["mobile"].open()
        v.clock.advance(0.2)
    fa, fb, fc = (v.cameras["fixed"].grab() for v in (a, b, c))
    assert fa.seq == fb.seq and np.array_equal(fa.image, fb.image)
    assert not np.array_equal(fa.image, fc.image)
    ma, mb = (v.cameras["mobile"].grab() for v in (a, b))
    assert np.array_equal(ma.image, mb.image)


def test_virtual_trial_moves_the_object_as_grbl_runs(lab):
    vl = _virtual_lab(lab, seed=2, truth=True)
    g = vl.grbl
    g.receive(b"$X\n")
    g.receive(b"G90 G1 X320 Y200 F480\n")  # 20 mm at 8 mm/s (with 200 mm/s² ramps)
    cam = vl.cameras["fixed"]
    cam.open()
    start = vl.world.T_w_o(0.0)[:3, 3]
    frames = [cam.grab() for _ in range(105)]  # 3.5 s
    end = vl.world.T_w_o(frames[-1].t)[:3, 3]
    assert np.allclose(end - start, [20.0, 0.0, 0.0], atol=1e-6)
    mid = frames[45]  # 1.5 s: cruising at 8 mm/s after a 0.04 s ramp
    moved = vl.world.T_w_o(mid.t)[0, 3] - start[0]
    assert moved == pytest.approx(8.0 * 1.5 - 8.0 * 8.0 / (2 * 200.0), abs=0.05)
    # the image follows: object mask centroid shifts by the moved distance in pixels
    c0 = np.argwhere(frames[0].meta["mask"]).mean(axis=0)
    c1 = np.argwhere(frames[-1].meta["mask"]).mean(axis=0)
    assert (c1[1] - c0[1]) * 0.936 == pytest.approx(20.0, rel=0.05)


# --- frame server -----------------------------------------------------------------------------
def test_frame_server_serves_frames_in_process(lab, block):
    clock = VirtualClock(0.0)
    cam = SimCamera(SimWorld.from_lab(lab, obj=block), "fixed", clock, fps=30.0, seed=1)
    cam.open()
    direct = SimCamera(SimWorld.from_lab(lab, obj=block), "fixed", VirtualClock(0.0), fps=30.0, seed=1)
    with FrameServer({"fixed": cam}) as server:
        with FrameClient(server.address, "fixed", server.authkey, timeout_s=10) as client:
            assert isinstance(client, Camera)
            f = client.grab()
            assert f.seq == 0 and np.array_equal(f.image, direct.render_frame(0).image)
            assert client.grab().seq == 1
            assert client.info()["role"] == "fixed"
        with FrameClient(server.address, "mobile", server.authkey) as bad:
            with pytest.raises(DeviceError, match="no camera"):
                bad.grab()
        with pytest.raises(DeviceError):
            FrameClient(server.address, "fixed", b"wrong key").open()
    with pytest.raises(DeviceError):
        FrameClient(server.address, "fixed", server.authkey).open()


def _grab_in_child(address, authkey, queue):
    with FrameClient(address, "fixed", authkey, timeout_s=20) as client:
        f = client.grab()
        queue.put((f.seq, f.t, f.image.shape, int(f.image.sum())))


def test_frame_server_serves_another_process(lab, block):
    cam = SimCamera(SimWorld.from_lab(lab, obj=block), "fixed", VirtualClock(0.0), fps=30.0, seed=1)
    cam.open()
    expected = int(SimCamera(SimWorld.from_lab(lab, obj=block), "fixed", VirtualClock(0.0), seed=1)
                   .render_frame(0).image.sum())
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    with FrameServer({"fixed": cam}) as server:
        child = ctx.Process(target=_grab_in_child, args=(server.address, server.authkey, queue))
        child.start()
        try:
            seq, t, shape, total = queue.get(timeout=60)
        finally:
            child.join(timeout=30)
            if child.is_alive():
                child.kill()
    assert (seq, t, shape, total) == (0, 0.0, (480, 640, 3), expected)


def _catch_up_in_child(address, authkey, go, queue):
    with FrameClient(address, "fixed", authkey, timeout_s=20) as client:
        queue.put(client.grab_recent(4)[-1].seq)
        go.wait(30)  # meanwhile the server's clock moves on 0.2 s: six frames
        queue.put([(f.seq, f.t, int(f.image.sum())) for f in client.grab_recent(4)])
        queue.put([f.seq for f in client.grab_recent(4)])  # none left: the next one, when its time comes


def test_frame_server_hands_a_busy_client_the_frames_it_missed(lab, block):
    """Another process asks for the frames exposed since its last one: the newest ``max_frames`` of them, in
    order, each exactly the frame the camera exposes at its own time (on the camera's fixed 30 Hz grid)."""
    clock = VirtualClock(0.0)
    cam = SimCamera(SimWorld.from_lab(lab, obj=block), "fixed", clock, fps=30.0, seed=1)
    cam.open()
    direct = SimCamera(SimWorld.from_lab(lab, obj=block), "fixed", VirtualClock(0.0), fps=30.0, seed=1)
    ctx = mp.get_context("spawn")
    go, queue = ctx.Event(), ctx.Queue()
    with FrameServer({"fixed": cam}) as server:
        child = ctx.Process(target=_catch_up_in_child, args=(server.address, server.authkey, go, queue))
        child.start()
        try:
            first = queue.get(timeout=60)
            clock.advance(0.2)
            go.set()
            missed, after = queue.get(timeout=60), queue.get(timeout=60)
        finally:
            child.join(timeout=30)
            if child.is_alive():
                child.kill()
    assert first == 0
    assert [s for s, _, _ in missed] == [3, 4, 5, 6]  # frames 1-6 were exposed; the newest four
    for seq, t, total in missed:
        assert t == pytest.approx(seq / 30.0) and total == int(direct.render_frame(seq).image.sum())
    assert after == [7]


# --- snapshot ---------------------------------------------------------------------------------
@pytest.fixture
def empty_lab(tmp_path):
    src = sample_lab_path()
    shutil.copy(src / "lab.yaml", tmp_path / "lab.yaml")
    shutil.copytree(src / "drivers", tmp_path / "drivers")
    (tmp_path / "object_library").mkdir()
    return load_lab(tmp_path)


@pytest.mark.parametrize("camera", ["fixed", "mobile"])
def test_snapshot_falls_back_to_the_builtin_block(empty_lab, tmp_path, camera):
    out = tmp_path / "shots" / f"{camera}.png"
    info = snapshot(empty_lab, camera=camera, t=1.0, out=out, seed=4)
    img = cv2.imread(str(out))
    assert img.shape == (480, 640, 3)
    assert info["object"] == "test_block" and info["object_source"] == "built-in" and "empty" in info["note"]
    assert info["object_pixels"] > 500 and max(info["marker_pixels"].values()) > 50
    assert info["table_position_mm"][0] == pytest.approx(300.0 + 8.0)
    again = tmp_path / "again.png"
    snapshot(empty_lab, camera=camera, t=1.0, out=again, seed=4)
    assert np.array_equal(cv2.imread(str(again)), img)


def test_snapshot_bad_input(empty_lab, tmp_path):
    with pytest.raises(UserInputError, match="no object"):
        snapshot(empty_lab, camera="fixed", t=0.0, out=tmp_path / "x.png", object_name="nope")
    with pytest.raises(UserInputError):
        snapshot(empty_lab, camera="fixed", t=-1.0, out=tmp_path / "x.png")
    with pytest.raises(UserInputError):
        snapshot(empty_lab, camera="fixed", t=0.0, out=tmp_path / "x.jpg")


def test_snapshot_cli_on_the_sample_lab(tmp_path):
    from click.testing import CliRunner

    from labctl.cli import cli

    out = tmp_path / "fixed.png"
    res = CliRunner().invoke(cli, ["--lab", str(sample_lab_path()), "sim", "snapshot", "--camera", "fixed",
                                   "--t", "2", "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    assert cv2.imread(str(out)).shape == (480, 640, 3)
    assert Path(out).stat().st_size > 10_000


def test_mobile_camera_rides_the_robot_emulator(lab):
    from labctl.geometry import matrix_to_rotvec

    vl = _virtual_lab(lab, seed=3)
    home = home_flange_pose(lab)
    assert np.allclose(vl.world.T_w_c("mobile", 0.0)[:3, 3], lab.robot.home_mm)
    rv = matrix_to_rotvec(home[:3, :3])
    target = home[:3, 3] + [100.0, 50.0, -150.0]
    args = " ".join(f"{v:.9f}" for v in (*target, *rv))
    vl.robot_emu.receive(f"#1 SEG 7 {args} 2.0\n".encode())
    assert b"ok" in vl.robot_emu.read_output()
    for k in range(1, 13):  # heartbeats every 0.2 s keep the controller's watchdog quiet
        vl.step_to(0.2 * k)
        vl.robot_emu.receive(f"#{k + 1} HB\n".encode())
        if k == 5:
            mid = vl.world.T_w_c("mobile", 1.0)
    vl.step_to(2.5)
    end = vl.world.T_w_c("mobile", 2.5)
    T_f_c2 = hand_eye(lab.mobile_camera)
    assert np.allclose(end, vl.robot_emu.flange_pose_at(2.5) @ T_f_c2)
    assert np.allclose(end[:3, :3], (home @ T_f_c2)[:3, :3], atol=1e-9)
    assert np.allclose((end @ invert(T_f_c2))[:3, 3], target, atol=1e-6)
    # a quintic is symmetric: halfway in time is halfway in space
    assert np.allclose((mid @ invert(T_f_c2))[:3, 3], (home[:3, 3] + target) / 2, atol=1e-6)
    vl.cameras["mobile"].open()
    assert vl.cameras["mobile"].grab().image.shape == (480, 640, 3)


def test_object_window_holds_every_red_pixel_of_the_full_frame(lab, block):
    # the fixed camera's tracker reads only the red markers: the object's window must hold all of them,
    # with the full frame's pixels there, while the table moves under the camera
    world = SimWorld.from_lab(lab, obj=block, placement=Placement(0, 0.4, (5.0, -7.0)),
                              table_position=lambda t: (60.0 + 40.0 * t, 150.0 + 25.0 * t, 0.0))
    for t in (0.0, 2.5, 5.0):
        full = world.render("fixed", t, np.random.default_rng(3)).image
        win = world.render("fixed", t, np.random.default_rng(3), window="object").image
        x0, y0, x1, y1 = world.object_window("fixed", [(world.T_w_c1, world.meshes_at(t))])
        assert 0 < x1 - x0 < 200 and 0 < y1 - y0 < 200
        assert np.array_equal(win[y0:y1, x0:x1], full[y0:y1, x0:x1])
        img = full.astype(int)
        red = (img[..., 2] - img[..., 1] > 40)
        ys, xs = np.nonzero(red)
        assert len(ys) > 20
        assert xs.min() >= x0 and xs.max() < x1 and ys.min() >= y0 and ys.max() < y1
    with pytest.raises(WorldError):
        world.render("fixed", 0.0, window="everything")


def test_live_sim_lab_fixed_camera_serves_the_object_window_the_tracker_reads(lab):
    # labctl run's simulated lab renders the fixed camera as the virtual run does (the object's window, no
    # anti-aliasing, flat table grey outside): inside the window the frame is the whole frame rendered
    # independently with the same noise, and the tracker's marker centroids are the whole frame's
    from labctl.runtime.simlab import LiveSimLab, ServedLab
    from labctl.vision import detect_markers

    assert ServedLab.fixed_object_window is False  # the served lab stands in for real cameras: whole frames
    with LiveSimLab(lab, {"seed": 4, "trajectory": "line", "speed_mm_s": 8.0}) as live:
        cam = live.sim.cameras["fixed"]
        assert (cam.window, cam.supersample) == ("object", 1)
        world = live.world
        for seq in (0, 45, 90):
            frame = cam.render_frame(seq)
            t = cam.frame_time(seq)
            full = world.render("fixed", t, np.random.default_rng([cam.seed, 1, seq]), supersample=1).image
            x0, y0, x1, y1 = world.object_window("fixed", [(world.T_w_c("fixed", t), world.meshes_at(t))])
            assert x1 - x0 > 20 and y1 - y0 > 20
            assert np.array_equal(frame.image[y0:y1, x0:x1], full[y0:y1, x0:x1])
            outside = np.ones(full.shape[:2], bool)
            outside[y0:y1, x0:x1] = False
            assert len(np.unique(frame.image[outside].reshape(-1, 3), axis=0)) < len(
                np.unique(full[outside].reshape(-1, 3), axis=0))  # no texture there: nothing a tracker reads
            got = sorted(tuple(np.round(mk.centroid, 6)) for mk in detect_markers(frame.image, refine=False))
            want = sorted(tuple(np.round(mk.centroid, 6)) for mk in detect_markers(full, refine=False))
            assert got == want and got


def test_sim_lab_serves_its_ports_before_it_builds_the_world(lab):
    # a live run's table and robot connect while the simulated lab reads its object and builds the world:
    # on_ports comes with both emulators on their ptys and no world yet; a scene given as a function is made after
    seen, made = [], []

    def on_ports(sim):
        seen.append((sim.world, sorted(sim.endpoints()), sim.grbl is not None, sim.robot_emu is not None))

    def scene():
        made.append(len(seen))
        return Scene.test_block(lab)

    sim = SimLab.build(lab, RealClock(), ports="pty", scene=scene, on_ports=on_ports)
    try:
        assert seen == [(None, ["robot", "table"], True, True)] and made == [1]
        assert sim.world is not None and set(sim.cameras) == {"fixed", "mobile"}
        assert all(Path(p).exists() for p in sim.endpoints().values())
    finally:
        sim.close()
