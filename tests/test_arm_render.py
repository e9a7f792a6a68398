"""The arm in the simulated cameras, against an independent forward kinematics of the UR10e.

The oracle here is Universal Robots' published DH table for the UR10e (standard DH, mm) written out in this
file and chained by hand — not :class:`labctl.planning.arm.ArmModel` — at the sample lab's mount
(600, -200, 350) mm, with the link radii the arm file declares. A pixel whose ray passes well inside a link
must be arm-coloured in the fixed camera's noiseless image; one whose ray passes well clear of every link
and of the mobile camera's body must be exactly the armless image's.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from labctl.config import load_lab
from labctl.geometry import invert, look_at
from labctl.sim.truth import hand_eye
from labctl.sim.world import SimWorld, builtin_test_object
from labctl.workspace import sample_lab_path

# Universal Robots, "DH parameters for calculations of kinematics and dynamics", UR10e (mm, rad)
UR10E_D = (180.7, 0.0, 0.0, 174.15, 119.85, 116.55)
UR10E_A = (0.0, -612.7, -571.55, 0.0, 0.0, 0.0)
UR10E_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
MOUNT = np.array([600.0, -200.0, 350.0])


def dh(theta, d, a, alpha):
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1.0]])


def ur10e_chain(q):
    """The flange pose in W and the link axes [(start, end)] (each DH step's d then a move), by hand."""
    T = np.eye(4)
    T[:3, 3] = MOUNT
    axes = []
    for i in range(6):
        p0 = T[:3, 3].copy()
        Td = T @ dh(q[i], UR10E_D[i], 0.0, 0.0)
        if UR10E_D[i]:
            axes.append((i, p0, Td[:3, 3].copy()))
        T = T @ dh(q[i], UR10E_D[i], UR10E_A[i], UR10E_ALPHA[i])
        if UR10E_A[i]:
            axes.append((i, Td[:3, 3].copy(), T[:3, 3].copy()))
    return T, axes


def ray_segment_distance(o, dirs, p0, p1, n=150):
    """Distance (mm) from each ray o + s·dir (s > 0) to the segment p0–p1, by sampling the segment."""
    pts = p0 + np.linspace(0.0, 1.0, n)[:, None] * (p1 - p0)  # (n, 3)
    rel = pts - o  # (n, 3)
    along = np.clip(rel @ dirs.T, 0.0, None)  # (n, R)
    foot = o + along.T[:, :, None] * dirs[:, None, :]  # (R, n, 3)
    return np.min(np.linalg.norm(foot - pts[None], axis=2), axis=1)


@pytest.fixture(scope="module")
def lab():
    return load_lab(sample_lab_path())


def _world(lab, T_w_F, arm=True):
    w = SimWorld.from_lab(lab, obj=builtin_test_object(), flange_pose_at=lambda t: T_w_F, arm=arm)
    for rig in w.rigs.values():
        rig.noise_sigma = 0.0
    return w


# configurations in the home branch (shoulder, elbow, wrist as the arm's home) that reach over the table
CONFIGS_DEG = [(-66.8, -106.0, 115.1, -97.4, -90.3, -66.8), (-50.0, -80.0, 100.0, -110.0, -90.0, 20.0),
               (-80.0, -120.0, 100.0, -70.0, -100.0, 0.0)]


@pytest.mark.parametrize("q_deg", CONFIGS_DEG)
def test_arm_pixels_where_the_independent_fk_projects(lab, q_deg):
    q = np.radians(q_deg)
    T_w_F, axes = ur10e_chain(q)
    world = _world(lab, T_w_F)
    assert world.arm is not None
    # the world followed the flange to the same configuration (joint-space oracle too)
    assert np.allclose(world.arm_q(0.0), q, atol=1e-6)
    radii = lab.arm.link_radius_mm
    img = world.render("fixed", 0.0).image.astype(int)
    bare = _world(lab, T_w_F, arm=False).render("fixed", 0.0).image.astype(int)
    cam, T_w_c = world.rigs["fixed"].model, world.T_w_c1
    v, u = np.mgrid[2:cam.height - 2:8, 2:cam.width - 2:8]
    px = np.stack([u.ravel(), v.ravel()], axis=1).astype(float)
    nrm = cam.normalized(px)
    dirs = np.column_stack([nrm, np.ones(len(nrm))]) @ T_w_c[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    o = T_w_c[:3, 3]
    margin = np.full(len(px), np.inf)  # (distance to the link axis) − radius, the nearest link
    for i, p0, p1 in axes:
        margin = np.minimum(margin, ray_segment_distance(o, dirs, p0, p1) - radii[i])
    cam_c = (T_w_F @ hand_eye(lab.mobile_camera))[:3, 3]
    body = ray_segment_distance(o, dirs, cam_c, cam_c + 1e-6) < 130.0  # the mobile camera's body round it
    inside = margin < -0.1 * np.asarray(radii).min()  # well inside a link: beyond the 12-gon's facets
    clear = (margin > 6.0) & ~body  # well clear of every link (and of the camera body)
    ui, vi = px[:, 0].astype(int), px[:, 1].astype(int)
    assert inside.sum() > 200, "the configuration should put the arm in the fixed camera's view"
    arm_px, bare_px = img[vi[inside], ui[inside]], bare[vi[inside], ui[inside]]
    # arm-coloured: the dark neutral grey under Lambert shading (B ≈ G ≈ R), not what the table shows there
    assert np.all(np.abs(arm_px[:, 0] - arm_px[:, 2]) <= 6) and np.all(arm_px[:, 2] <= 100)
    assert np.all(arm_px.max(axis=1) >= 40)
    assert np.mean(np.any(arm_px != bare_px, axis=1)) > 0.95
    # and nowhere else: every clear pixel is exactly the armless image
    assert np.array_equal(img[vi[clear], ui[clear]], bare[vi[clear], ui[clear]])


def test_arm_hides_the_marker_the_render_hides(lab):
    """The world's occlusion truth (sight lines through capsules) agrees with the rendered marker pixels."""
    Tfc = hand_eye(lab.mobile_camera)
    centre = np.array([300.0, 200.0, 0.0])
    for height, expect_hidden in ((830.0, True), (None, False)):
        T_w_F = (look_at(centre + [0, 0, height], centre, up=(0, 1, 0)) @ invert(Tfc)) if height else None
        world = SimWorld.from_lab(lab, obj=builtin_test_object(), **({"flange_pose_at": lambda t, T=T_w_F: T}
                                                                    if height else {}))
        facing, hidden = world.arm_hides_markers("fixed", 0.0)
        shown = world.render("fixed", 0.0, truth=True).marker_pixels
        bare = SimWorld.from_lab(lab, obj=builtin_test_object(), arm=False,
                                 **({"flange_pose_at": lambda t, T=T_w_F: T} if height else {}))
        shown_bare = bare.render("fixed", 0.0, truth=True).marker_pixels
        assert facing == 1
        assert (hidden == 1) is expect_hidden
        top = int(np.argmax(shown_bare))
        assert shown_bare[top] > 50
        assert (shown[top] < 0.2 * shown_bare[top]) is expect_hidden


def _views(lab):
    """Mobile-camera poses the planner flies: home, straight above the table's centre, and 63° initial views
    from round the object (1 m away)."""
    Tfc = hand_eye(lab.mobile_camera)
    out = [None]
    for target in ([300.0, 200.0, 20.0], [200.0, 150.0, 20.0], [420.0, 260.0, 20.0]):
        c = np.array(target)
        out.append(look_at(c + [0, 0, 820.0], c, up=(0, 1, 0)) @ invert(Tfc))
        for az in (-150.0, -90.0, -30.0, 0.0):
            a, el = math.radians(az), math.radians(63.0)
            eye = c + 1000.0 * np.array([math.cos(el) * math.cos(a), math.cos(el) * math.sin(a), math.sin(el)])
            out.append(look_at(eye, c, up=(0, 0, 1)) @ invert(Tfc))
    return out


def test_mobile_camera_does_not_see_its_own_wrist(lab):
    checked = 0
    for T in _views(lab):
        kw = {} if T is None else {"flange_pose_at": lambda t, T=T: T}
        world = SimWorld.from_lab(lab, obj=builtin_test_object(), **kw)
        world.rigs["mobile"].noise_sigma = 0.0
        q = world.arm_q(0.0)
        if not np.allclose(world.arm.model.fk(q), world.T_w_F(0.0), atol=1e-3):
            continue  # out of the arm's reach from this branch: not a view the arm can fly
        bare = SimWorld.from_lab(lab, obj=builtin_test_object(), arm=False, **kw)
        bare.rigs["mobile"].noise_sigma = 0.0
        a, b = world.render("mobile", 0.0), bare.render("mobile", 0.0)
        assert np.array_equal(a.image, b.image)
        # the wrist it rides on, if it were drawn, lies behind its optical centre: never in its own image
        T_c_w = invert(world.T_w_c("mobile", 0.0))
        V, _ = world.arm.mesh(q)
        assert V.size and np.all((V @ T_c_w[:3, :3].T + T_c_w[:3, 3])[-74 * 2:, 2] < 0.0)
        checked += 1
    assert checked >= 8


def test_the_drawn_arm_is_the_controllers_arm(lab):
    """In a simulated lab the drawn arm takes the controller emulator's joints as it flies a segment: the same
    configuration (not an IK of its own), whose flange by the independent UR10e chain is the controller's flange
    at every frame time, at rest and in motion."""
    from labctl.sim.clock import VirtualClock
    from labctl.sim.lab import Scene, SimLab
    from labctl.sim.world import home_flange_pose

    clock = VirtualClock(0.0)
    sim = SimLab.build(lab, clock, scene=Scene.test_block(lab, 0))
    sim.open()
    emu, world = sim.robot_emu, sim.world
    T0 = home_flange_pose(lab)
    T1 = T0.copy()
    T1[:3, 3] += [60.0, -40.0, 30.0]
    t0, t1 = sim.robot.segment(T1, 1.0, 1)
    q_start = None
    for t in np.linspace(t0 - 0.1, t1 + 0.2, 13):
        clock.sleep_until(max(t, clock.now()))
        sim.advance(clock.now())
        sim.robot.heartbeat()  # fed, as a run feeds it: the controller's watchdog would stop the arm
        t = clock.now()
        q = world.arm_q(t)
        assert np.array_equal(q, emu.joints_at(t))
        T_hand, _ = ur10e_chain(q)
        assert np.allclose(T_hand, world.T_w_F(t), atol=1e-6)
        q_start = q if q_start is None else q_start
    assert np.max(np.abs(q - q_start)) > 0.02  # it moved
    assert np.allclose(world.T_w_F(clock.now())[:3, 3], T1[:3, 3], atol=1e-6)


def test_occlusion_truth_against_sampled_distances(lab):
    """:meth:`ArmBody.hides` (every link at once) against sight lines sampled by hand: a point whose sight line
    passes well inside a link is hidden, one well clear of every link is not."""
    q = np.radians(CONFIGS_DEG[0])
    world = _world(lab, ur10e_chain(q)[0])
    eye = world.T_w_c1[:3, 3]
    _, axes = ur10e_chain(q)
    rng = np.random.default_rng(3)
    # points round the links' axes and scattered below them, towards the table
    pts = np.array([p0 + rng.uniform(0, 1) * (p1 - p0) + rng.normal(0, 80.0, 3) - [0, 0, 300.0]
                    for _, p0, p1 in axes for _ in range(15)])
    hidden = world.arm.hides(q, eye, pts)
    radii = np.asarray(lab.arm.link_radius_mm, float)
    sight = eye + np.linspace(0.0, 1.0, 600)[None, :, None] * (pts - eye)[:, None, :]  # (N, 600, 3), < 3 mm apart
    margin = np.full(len(pts), np.inf)
    for i, p0, p1 in axes:  # each sample's distance to the link's axis (projection clamped to its ends)
        ax = p1 - p0
        s_ = np.clip(((sight - p0) @ ax) / (ax @ ax), 0.0, 1.0)
        d = np.linalg.norm(sight - (p0 + s_[..., None] * ax), axis=2).min(axis=1)
        margin = np.minimum(margin, d - radii[i])
    inside, clear = margin < -6.0, margin > 6.0
    assert inside.sum() > 10 and clear.sum() > 10
    assert hidden[inside].all() and not hidden[clear].any()
