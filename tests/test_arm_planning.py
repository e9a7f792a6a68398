"""The planner plans for the arm: paths checked in joint space, slowed by exactly their peak joint-speed ratio,
re-planned where the box planner's path crosses the base axis, calibration stations the arm can fly, and the
bound that counts the joints. Oracles: the closed-form UR solutions (another algorithm than the planner's
damped least squares), the feasibility checker's replay of the reference controller at 4 ms, arithmetic."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("pinocchio")

from labctl.config import load_lab  # noqa: E402
from labctl.geometry import look_at, make_T  # noqa: E402
from labctl.planning.arm import ArmModel  # noqa: E402
from labctl.planning.arm_plan import ArmCheckSettings, ArmPlanner, StationReach, fit_plan  # noqa: E402
from labctl.planning.interception import Interception  # noqa: E402
from labctl.planning.limits import planning_limits  # noqa: E402
from labctl.planning.quintic import QuinticSegment, Trajectory  # noqa: E402
from labctl.planning.ruckig_interception import plan_interception_ruckig, plan_ruckig_arriving  # noqa: E402
from labctl.planning.ruckig_profile import JerkLimits  # noqa: E402
from labctl.planning.tti_bound import Leg, identity_bound, leg_min_time  # noqa: E402
from labctl.workspace import sample_lab_path  # noqa: E402


@pytest.fixture(scope="module")
def lab():
    return load_lab(sample_lab_path())


@pytest.fixture(scope="module")
def arm(lab):
    return ArmModel.from_config(lab.arm)


class _Still:
    """A target standing still at ``p`` in orientation ``R`` (G(t) with zero velocity and acceleration)."""

    def __init__(self, p, R):
        self.p, self.rotation = np.asarray(p, float), np.asarray(R, float)

    def __call__(self, times):
        n = len(np.atleast_1d(times))
        return np.tile(self.p, (n, 1)), np.zeros((n, 3)), np.zeros((n, 3))


def _down(p, yaw=0.0):
    """A flange pose at ``p`` looking straight down, turned ``yaw`` about the vertical."""
    R = look_at(np.asarray(p, float), np.asarray(p, float) + [0.0, 0.0, -1.0], up=(math.cos(yaw), math.sin(yaw), 0.0))
    return make_T(R[:3, :3], p)


def _branch_solution(arm, T, branch, near):
    """The closed-form solution of ``T`` in ``branch`` nearest ``near`` (each joint's turn nearest it), or None."""
    best = None
    for q in arm.closed_form(T):
        q = near + np.remainder(q - near + math.pi, 2 * math.pi) - math.pi
        if arm.configuration(q) == branch and (best is None or np.max(np.abs(q - near)) < np.max(np.abs(best - near))):
            best = q
    return best


STEP_RAD = math.radians(5.0)


def _closed_form_follows(arm, poses, q0, max_step_rad=STEP_RAD) -> bool:
    """An independent follow: at every pose a closed-form solution in ``q0``'s branch, each within a few degrees
    of the previous one."""
    q, branch = np.asarray(q0, float), arm.configuration(q0)
    for T in poses:
        nxt = _branch_solution(arm, T, branch, q)
        if nxt is None or np.max(np.abs(nxt - q)) > max_step_rad or not arm.within_limits(nxt):
            return False
        q = nxt
    return True


def _sampled(traj, t0, t1, dt=0.004):
    ts = np.arange(t0, t1 + 1e-12, dt)
    return ts, [make_T(traj.orientation(t), traj.state(t)[0]) for t in ts]


# --- slowed by exactly the peak ratio ---------------------------------------------------------------
def test_a_plan_at_ratio_1_3_is_stretched_by_exactly_1_3_and_the_result_keeps_within_the_joint_speeds(lab, arm):
    limits = planning_limits(lab.robot)
    A, B = _down([900.0, 300.0, 700.0]), _down([400.0, 500.0, 600.0], yaw=0.8)
    q0 = ArmPlanner(arm).configuration_at(A)
    assert q0 is not None
    state = (A[:3, 3], np.zeros(3), np.zeros(3))
    G = _Still(B[:3, 3], B[:3, :3])
    plan = plan_interception_ruckig(state, 0.0, G, limits, 10.0, R0=A[:3, :3])
    assert plan.reachable
    r0 = ArmPlanner(arm).check(plan.trajectory, 0.0, plan.t_hit, q0).ratio
    # the same arm with its joints slower by r0/1.3: the earliest plan is then exactly 1.3 times too fast
    slow = ArmModel.from_config(lab.arm)
    slow.qd_max = arm.qd_max * r0 / 1.3
    planner = ArmPlanner(slow)
    first = planner.check(plan.trajectory, 0.0, plan.t_hit, q0)
    assert first.ok and first.ratio == pytest.approx(1.3, rel=1e-9)
    asked: list[float] = []

    def plan_at(T, slow):
        assert slow == 1.0  # only the speeds bind
        asked.append(T)
        return plan_ruckig_arriving(state, 0.0, G, T, limits, R0=A[:3, :3])

    fit = fit_plan(plan, 0.0, lambda p: planner.check(p.trajectory, 0.0, p.t_hit, q0), plan_at)
    assert asked[0] == pytest.approx(1.3 * plan.t_hit, rel=1e-12)
    assert fit.plan.reachable and fit.path is not None and fit.path.ratio <= 1.0
    assert fit.stretch >= 1.3 - 1e-12 and fit.plan.t_hit == pytest.approx(fit.stretch * plan.t_hit, rel=1e-6)
    # independent: the flown path at 4 ms by closed-form solutions, its finite-difference joint speeds
    ts, poses = _sampled(fit.plan.trajectory, 0.0, fit.plan.t_hit)
    fol = slow.follow(poses, q0)
    assert fol.ok and _closed_form_follows(slow, poses, q0)
    assert float(np.max(slow.joint_speed_ratio(fol.qs, ts))) <= 1.0
    # ... where the earliest plan was over them
    ts0, poses0 = _sampled(plan.trajectory, 0.0, plan.t_hit)
    assert float(np.max(slow.joint_speed_ratio(slow.follow(poses0, q0).qs, ts0))) > 1.2


def test_a_plan_within_the_joint_speeds_is_sent_as_planned(lab, arm):
    limits = planning_limits(lab.robot)
    A, B = _down([900.0, 300.0, 700.0]), _down([880.0, 320.0, 690.0])
    q0 = ArmPlanner(arm).configuration_at(A)
    plan = plan_interception_ruckig((A[:3, 3], np.zeros(3), np.zeros(3)), 0.0, _Still(B[:3, 3], B[:3, :3]), limits,
                                    10.0, R0=A[:3, :3])
    planner = ArmPlanner(arm)
    fit = fit_plan(plan, 0.0, lambda p: planner.check(p.trajectory, 0.0, p.t_hit, q0),
                   lambda T, slow: pytest.fail("re-planned a feasible plan"))
    assert fit.plan is plan and fit.stretch == 1.0 and fit.path.ratio < 1.0


# --- a path across the base axis ----------------------------------------------------------------------
def test_a_straight_path_over_the_base_axis_is_refused_and_the_closed_form_agrees(lab, arm):
    base = arm.T_w_base[:3, 3]
    # a flange looking down at 0.9 m, sliding over the arm's base from one side to the other
    A, B = _down(base + [450.0, 120.0, 550.0]), _down(base + [-450.0, 120.0, 550.0])
    seg = QuinticSegment(0.0, 4.0, A[:3, 3], np.zeros(3), np.zeros(3), B[:3, 3], np.zeros(3), np.zeros(3),
                         R0=A[:3, :3], R1=B[:3, :3])
    traj = Trajectory((seg,))
    ts, poses = _sampled(traj, 0.0, 4.0, 0.02)
    assert any(not arm.closed_form(T) for T in poses)  # the oracle: the wrist point enters the base's cylinder
    planner = ArmPlanner(arm)
    q0 = planner.configuration_at(A)
    path = planner.check(traj, 0.0, 4.0, q0)
    assert not path.ok and path.reason in ("unreachable", "configuration", "singularity")
    fit = fit_plan(Interception(4.0, traj, None, "ok", _Still(B[:3, 3], B[:3, :3])), 0.0,
                   lambda p: planner.check(p.trajectory, 0.0, p.t_hit, q0), lambda T, slow: pytest.fail("stretched"))
    assert not fit.plan.reachable and fit.plan.code.startswith("arm_")


def test_a_singularity_margin_refuses_a_path_the_follower_alone_would_take(arm):
    """A short move whose wrist point stays outside the base's cylinder, but nearer it than the shoulder margin,
    is refused; with a margin below its distance it passes."""
    A, B = _down([900.0, 300.0, 700.0]), _down([880.0, 320.0, 690.0])
    seg = Trajectory((QuinticSegment(0.0, 1.0, A[:3, 3], np.zeros(3), np.zeros(3), B[:3, 3], np.zeros(3),
                                     np.zeros(3), R0=A[:3, :3], R1=B[:3, :3]),))
    q0 = ArmPlanner(arm).configuration_at(A)
    # the oracle: the wrist point's distance outside the cylinder of radius d4, from forward kinematics
    T_base_F = np.linalg.inv(arm.T_w_base) @ arm.fk(q0)
    p5 = T_base_F[:3, 3] - arm.d[5] * T_base_F[:3, 2]
    margin = math.sqrt(p5[0] ** 2 + p5[1] ** 2 - arm.d[3] ** 2)
    path = ArmPlanner(arm, ArmCheckSettings(shoulder_margin_mm=margin + 30.0)).check(seg, 0.0, 1.0, q0)
    assert not path.ok and path.reason == "singularity"
    assert ArmPlanner(arm, ArmCheckSettings(shoulder_margin_mm=margin - 30.0)).check(seg, 0.0, 1.0, q0).ok


# --- a whole run where the box planner's path crosses the base axis -----------------------------------
def _run_checked(lab, tmp_path, arm_at_base, trajectory="arc", seed=0):
    from labctl.decisions.context import RunContext
    from labctl.experiments.arm_feasibility import check_trial, read_events, recover_trajectory
    from labctl.records import RunRecord
    from labctl.runtime.virtual import TrialSpec, simulate_run
    from labctl.sim.world import home_flange_pose

    rec = RunRecord.create(tmp_path / "runs", {"command": "test"})
    res = simulate_run(lab, RunContext.load(lab), TrialSpec(trajectory, 8.0, None, seed), rec)
    rec.finish(res)
    events = read_events(rec.path / "events.jsonl")
    traj = recover_trajectory(events, lab)  # the reference controller's own trajectory of the recorded segments
    q0 = ArmPlanner(arm_at_base).configuration_at(home_flange_pose(lab))
    return res, events, check_trial(arm_at_base, traj, q0, "t", {})


def test_the_arm_at_the_base_frame_flies_a_run_the_box_planner_could_not(lab, tmp_path):
    """With the arm at labctl's old base frame (0, 0, 0) the box planner's paths to the standard view cross the
    base axis or over-speed joint 1 (docs/notes/robot.md); planning for the arm, the same trial is flown within
    the joints' speeds, checked by replaying the reference controller at 4 ms."""
    at0 = dataclasses.replace(lab.arm, base_xyz_mm=(0.0, 0.0, 0.0))
    arm0 = ArmModel.from_config(at0)
    res, events, feas = _run_checked(dataclasses.replace(lab, arm=at0), tmp_path / "arm", arm0)
    assert res["correct"] is True, res
    assert feas.followed and feas.n_reachable == feas.n_targets and max(feas.speed_ratio) <= 1.0, feas
    plans = [e for e in events if e["event"] == "arm_plan"]
    assert plans and any(e["stretch"] > 1.0 for e in plans)  # slowed somewhere, by its ratio
    res_box, _, feas_box = _run_checked(dataclasses.replace(lab, arm=None), tmp_path / "box", arm0)
    assert not feas_box.within_speeds  # the same trial planned in the box: the arm could not have flown it


# --- calibration stations ----------------------------------------------------------------------------
def test_calibration_stations_are_flown_by_the_arm_checked_by_the_closed_form(lab, arm):
    from labctl.calibration.run import lab_target, make_plan, nominal_for
    from labctl.planning.rotation import exp_so3, log_so3

    nominal = dataclasses.replace(nominal_for(lab), reach=StationReach(ArmPlanner(arm)))
    plan = make_plan(lab_target(lab.calibration_dir), nominal, "all")
    assert not plan.problems and len(plan.stations) >= 10 and len(plan.registration) == 5
    poses = [*plan.stations, *(T for _, T in plan.registration)]
    q = arm.ik(poses[0], arm.home).q
    assert arm.configuration(q) == arm.configuration(arm.home)
    for T0, T1 in zip(poses, poses[1:]):
        phi = log_so3(T0[:3, :3].T @ T1[:3, :3])
        path = [make_T(T0[:3, :3] @ exp_so3(phi * u), T0[:3, 3] + u * (T1[:3, 3] - T0[:3, 3]))
                for u in np.linspace(0.0, 1.0, 80)[1:]]
        assert _closed_form_follows(arm, path, q)
        q = _branch_solution(arm, T1, arm.configuration(q), q)


# --- the bound ---------------------------------------------------------------------------------------
def test_the_bound_rises_when_the_joints_bind():
    qd = (math.radians(120.0),) * 2 + (math.radians(180.0),) * 4
    short = dict(p0=(0.0, 0.0, 500.0), p1=(10.0, 0.0, 500.0))
    leg = Leg("standard", **short, q0=(0.0,) * 6, q1=(math.radians(90.0), 0.0, 0.0, 0.0, 0.0, math.radians(-90.0)))
    cart = leg_min_time(leg, 500.0, 3000.0)
    assert cart < 0.2
    assert leg_min_time(leg, 500.0, 3000.0, qd_max=qd) == pytest.approx(0.75)  # 90° at 120 °/s
    bounds = [identity_bound(0.3, [leg], 3, 0.033, v_max=500.0, a_max=3000.0, qd_max=q)["bound_s"] for q in (None, qd)]
    assert bounds[1] - bounds[0] == pytest.approx(0.75 - cart)
    # a long Cartesian leg with little joint motion keeps its Cartesian bound
    far = Leg("initial1", (0.0, 0.0, 500.0), (800.0, 0.0, 500.0), q0=(0.0,) * 6, q1=(0.01,) + (0.0,) * 5)
    assert leg_min_time(far, 500.0, 3000.0, qd_max=qd) == leg_min_time(far, 500.0, 3000.0)


# --- joint accelerations ------------------------------------------------------------------------------
def _omega(R0, R1, h):
    """ω (rad/s, world axes) of a rotation going from R0 to R1 in h seconds: vee(log(R1·R0ᵀ)) / h."""
    from labctl.planning.rotation import log_so3
    return log_so3(R1 @ R0.T) / h


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=18, max_size=18))
def test_joint_accelerations_agree_with_the_published_kinematics(lab, arm, x):
    """q̈ = J⁻¹·([a; α] − J̇q̇) (ArmModel.jacobian, .drift) against the task-space acceleration of a joint motion
    q(t) = q0 + q̇0·t + ½q̈0·t², differentiated numerically through the hand-written UR10e chain (tests/arm_dh.py)."""
    from arm_dh import sample_mount, ur10e_fk

    x = np.asarray(x)
    q0 = arm.home + np.array([0.4, 0.4, 0.4, 0.6, 0.6, 0.6]) * x[:6]  # near home: away from the singularities
    qd0, qdd0 = 1.5 * x[6:12], 20.0 * x[12:]  # rad/s, rad/s²: a joint's speed and the controller's 26 rad/s² scale
    mount = sample_mount()
    h = 1e-3
    T = [ur10e_fk(q0 + qd0 * t + 0.5 * qdd0 * t * t, mount) for t in (-2 * h, -h, 0.0, h, 2 * h)]
    a = (T[3][:3, 3] - 2 * T[2][:3, 3] + T[1][:3, 3]) / h ** 2
    alpha = (_omega(T[2][:3, :3], T[4][:3, :3], 2 * h) - _omega(T[0][:3, :3], T[2][:3, :3], 2 * h)) / (2 * h)
    qdd = np.linalg.solve(arm.jacobian(q0), np.concatenate([a, alpha]) - arm.drift(q0, qd0))
    assert np.allclose(qdd, qdd0, atol=0.02 + 0.002 * np.abs(qdd0).max()), (qdd, qdd0)


def test_a_leg_within_the_joint_speeds_but_over_an_acceleration_is_slowed_until_the_controller_takes_it(lab, arm):
    """The reference controller (sim.emulators.arm_servo) refuses with E34 a leg whose joint accelerations it does
    not allow, though every joint speed is within its limit; the planner, told the controller's accelerations,
    slows the leg by √ of its acceleration ratio, and the controller then takes it."""
    from labctl.sim.emulators.arm_servo import E_JOINT_RATE
    from labctl.sim.lab import arm_servo

    limits = planning_limits(lab.robot)
    A, B = _down([900.0, 300.0, 700.0]), _down([650.0, 450.0, 650.0])
    q0 = ArmPlanner(arm).configuration_at(A)
    state = (A[:3, 3], np.zeros(3), np.zeros(3))
    G = _Still(B[:3, 3], B[:3, :3])
    plan = plan_interception_ruckig(state, 0.0, G, limits, 10.0, R0=A[:3, :3])
    probe = ArmPlanner(arm, ArmCheckSettings(qdd_max=(1.0,) * 6)).check(plan.trajectory, 0.0, plan.t_hit, q0)
    assert probe.ok and probe.ratios.max() < 0.9  # the speeds alone pass it
    need = probe.accel_ratios * 0.95  # each joint's peak acceleration, rad/s²
    qdd_max = tuple(float(v) for v in np.maximum(need / 1.5, 1.0))  # the controller allows 1/1.5 of what it asks
    servo = arm_servo(lab)
    servo = type(servo)(servo.model, dataclasses.replace(servo.policy, qdd_max=np.asarray(qdd_max)))
    ts, poses = _sampled(plan.trajectory, 0.0, plan.t_hit)
    assert servo.check(ts, np.array(poses), q0)[0] == E_JOINT_RATE
    planner = ArmPlanner(arm, ArmCheckSettings(qdd_max=qdd_max))
    fit = fit_plan(plan, 0.0, lambda p: planner.check(p.trajectory, 0.0, p.t_hit, q0),
                   lambda T, slow: plan_ruckig_arriving(state, 0.0, G, T, limits, R0=A[:3, :3],
                                                        jerk=JerkLimits.from_limits(limits).slowed(slow)))
    assert fit.plan.reachable and fit.stretch > 1.1 and fit.path is not None and fit.path.ratio <= 1.0
    ts, poses = _sampled(fit.plan.trajectory, 0.0, fit.plan.t_hit)
    assert servo.check(ts, np.array(poses), q0)[0] == 0
