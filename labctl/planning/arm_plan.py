"""A planned Cartesian path checked in the arm's joint space before it is sent (paper §4.3, §5.1).

The planner plans in task space (quintic or ruckig segments of the flange F in the world W, mm, s, rad); the
arm flies them through inverse kinematics from its own configuration, as an arm's Cartesian servo mode does
(docs/notes/robot.md, "A real arm"). :class:`ArmPlanner` keeps that view of the arm: it follows a planned
trajectory's poses from the configuration the arm will have at its start (:meth:`ArmModel.follow`, IK from
the previous sample), then checks every sample

* reachable and within the joint limits, with no change of configuration branch (``follow``'s own checks);
* away from the singularities by the settings' margins (:meth:`ArmModel.singularity_margins`);
* each joint's speed within ``speed_fraction`` of its limit: the exact joint rates q̇ = J(q)⁻¹·[v; ω] of the
  trajectory's own velocity and angular velocity at each sample (no finite-difference underestimate);
* with the controller's joint accelerations known (``qdd_max``), each joint's acceleration within the same
  fraction of it: q̈ = J⁻¹·([a; α] − J̇q̇), the path's own acceleration less the drift of the joint rates
  (:meth:`ArmModel.drift`). A controller that checks accelerations (the reference's E34) refuses a path the
  speeds alone would pass: a 50 mm/s run asked joint 3 for 1.12–1.3× its 1500 °/s² (docs/notes/robot.md).

The ratio ``r`` over the path, the larger of the peak joint-speed ratio and the square root of the peak
acceleration ratio (a path slowed by r has its rates divided by r and its accelerations by about r²), is what
the planner slows a segment by (its duration × r).
Numbers in, numbers out: no clocks or devices.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..geometry import invert, make_T
from .arm import PATH_STEP_RAD, ArmModel
from .interception import Interception
from .quintic import Trajectory
from .rotation import exp_so3, log_so3
from .ruckig_interception import RuckigTrajectory


@dataclass(frozen=True)
class ArmCheckSettings:
    """How a path is checked in joint space (lab.yaml ``run.arm_*``): sample step (s), the share of each
    joint's speed (and acceleration) limit a plan may use, the singularity margins (shoulder mm; elbow |sin q3|;
    wrist |sin q5|), and the controller's joint accelerations (rad/s², 6; None: not checked)."""

    dt_s: float = 0.02
    speed_fraction: float = 0.95
    shoulder_margin_mm: float = 50.0
    elbow_margin: float = 0.05
    wrist_margin: float = 0.05
    qdd_max: tuple[float, ...] | None = None

    @classmethod
    def from_run(cls, run, robot=None) -> ArmCheckSettings:
        """From a :class:`labctl.config.lab.RunConfig`'s ``arm_*`` settings, and the joint accelerations the
        lab's robot controller allows (``drivers/robot.yaml`` ``arm_joint_accel_deg_s2``) if ``robot`` is given."""
        qdd = None if robot is None else tuple(math.radians(float(a)) for a in robot.arm_joint_accel_deg_s2)
        return cls(run.arm_check_dt_s, run.arm_speed_fraction, run.arm_shoulder_margin_mm, run.arm_elbow_margin,
                   run.arm_wrist_margin, qdd)


@dataclass
class JointPath:
    """A trajectory as the arm flies it: sample times ``t`` (s, the plan's time line), configurations ``qs``
    (N×6 rad), and the verdict. ``ok``: followable within the limits and margins (its speed may still be
    over: see ``ratio``); ``reason``: ``unreachable``, ``joint_limit``, ``configuration`` or ``singularity``;
    ``ratios``: each joint's peak |q̇_i| / (speed_fraction · q̇max_i) over the samples; ``accel_ratios``: each
    joint's peak |q̈_i| / (speed_fraction · q̈max_i) (zeros when accelerations are not checked); ``ratio``: the
    factor the segment must be slowed by, max(max ratios, √max accel_ratios) — above 1 it is too fast."""

    t: np.ndarray
    qs: np.ndarray
    ok: bool
    reason: str | None = None
    ratio: float = 0.0
    ratios: np.ndarray = field(default_factory=lambda: np.zeros(6))
    accel_ratios: np.ndarray = field(default_factory=lambda: np.zeros(6))

    @property
    def feasible(self) -> bool:
        """Followable and within every joint's speed (and acceleration, where checked)."""
        return self.ok and self.ratio <= 1.0

    def q_at(self, t: float) -> np.ndarray:
        """The sampled configuration nearest ``t`` (s) at or before it (the first before the path, the last
        after it): the seed of an IK for the pose at ``t``."""
        k = int(np.searchsorted(self.t, float(t), side="right")) - 1
        return self.qs[min(max(k, 0), len(self.qs) - 1)]

    @property
    def q_end(self) -> np.ndarray:
        """The configuration at the path's end (its last sample)."""
        return self.qs[-1]


def _sample(traj: Trajectory | RuckigTrajectory, t) -> tuple[np.ndarray, np.ndarray]:
    """The flange pose ``T_w_F`` (4×4) and twist [v (mm/s); ω (rad/s)] (6,, world axes; ω 0 where no rotation is
    planned) of ``traj`` at time ``t`` (s): a ruckig segment evaluated once."""
    twist = np.zeros(6)
    if isinstance(traj, RuckigTrajectory):
        p, v, _, R, w = traj.plan.state(traj._tau(t))
    else:
        seg = traj.segment_at(t)
        p, v, _ = seg.state(t)
        R = traj.orientation(t)
        w = seg.angular_velocity(t) if seg.rot_coeffs is not None and t < seg.t1 else None
    twist[:3] = v
    if w is not None:
        twist[3:] = w
    return make_T(R, p), twist


#: a joint whose sampled acceleration reaches this share of its limit is refined between samples (the samples
#: see ≥ 0.87 of the peak, so below it the refined peak stays under the limit) ...
ACCEL_REFINE_FROM = 0.6
#: ... at this many steps an interval (4 ms at the 20-ms samples: the reference controller's own check step)
ACCEL_SUBSTEPS = 5
#: the step (s) of the central difference that gives a path's acceleration [a; α] from its twist: far below the
#: ~10 ms over which a jerk-limited segment's acceleration changes, far above the twist's round-off
_RATE_STEP_S = 1e-4


def _twist_rate(traj: Trajectory | RuckigTrajectory, t: float, t0: float, t1: float) -> np.ndarray:
    """The time derivative of ``traj``'s twist at ``t`` (s): [a (mm/s²); α (rad/s²)], world axes, by a central
    difference inside [t0, t1] (one-sided at its ends, so that what lies outside the leg does not enter)."""
    lo, hi = max(t - _RATE_STEP_S, t0), min(t + _RATE_STEP_S, t1)
    if hi <= lo:
        return np.zeros(6)
    return (_sample(traj, hi)[1] - _sample(traj, lo)[1]) / (hi - lo)


class ArmPlanner:
    """The arm's side of planning: its configuration at a pose, a trajectory checked in joint space, and the
    joint-space time of a move (for choosing views). ``model`` is the arm at its mount."""

    def __init__(self, model: ArmModel, settings: ArmCheckSettings | None = None):
        self.model = model
        self.settings = settings or ArmCheckSettings()
        self._T_base_w = invert(model.T_w_base)
        self._T_tool_flange = invert(model.T_flange_tool)

    def configuration_at(self, T_w_F, seed=None) -> np.ndarray | None:
        """The configuration that puts F at ``T_w_F``, by IK from ``seed`` (default the arm's home, so the
        arm's home branch); None if that does not converge within the limits, then the reachable solution
        nearest home."""
        model = self.model
        res = model.ik(T_w_F, model.home if seed is None else seed)
        if res.ok:
            return res.q
        sols = model.ik_solutions(T_w_F)
        return sols[0] if sols else None

    def singular(self, q, T_w_F=None) -> bool:
        """``q`` (at flange pose ``T_w_F``, if known: saves a forward kinematics) is within a margin of a
        singularity: shoulder (the wrist point's distance outside the cylinder of radius |d4| round the base
        axis), elbow |sin q3|, wrist |sin q5| (:meth:`ArmModel.singularity_margins`)."""
        s, model = self.settings, self.model
        if abs(math.sin(float(q[2]) + model.offset[2])) < s.elbow_margin or \
                abs(math.sin(float(q[4]) + model.offset[4])) < s.wrist_margin:
            return True
        T = self._T_base_w @ (model.fk(q) if T_w_F is None else T_w_F) @ self._T_tool_flange
        p5 = T[:3, 3] - model.d[5] * T[:3, 2]
        r2 = float(p5[0] ** 2 + p5[1] ** 2)
        return math.sqrt(max(r2 - model.d[3] ** 2, 0.0)) < s.shoulder_margin_mm

    def check(self, traj: Trajectory | RuckigTrajectory, t0: float, t1: float, q0) -> JointPath:
        """Follow ``traj`` from ``t0`` to ``t1`` (s) in joint space from ``q0`` (the configuration at ``t0``), every
        ``dt_s`` and at ``t1``, and judge it (module docstring). Each sample is solved by IK from the previous
        configuration moved on by its joint rates (so one or two iterations); as :meth:`ArmModel.follow`, a
        sample that does not converge is ``unreachable``, one past a limit ``joint_limit``, and a change of
        branch or a joint step over :data:`~labctl.planning.arm.PATH_STEP_RAD` ``configuration``."""
        model, s = self.model, self.settings
        n = max(int(math.ceil((t1 - t0) / s.dt_s - 1e-9)), 1)
        ts = np.linspace(t0, t1, n + 1)
        q = np.asarray(q0, float)
        branch = model.configuration(q)
        seed = q
        qs = np.zeros((len(ts), 6))
        qds, qdds = np.zeros((len(ts), 6)), np.zeros((len(ts), 6))
        for k, t in enumerate(ts):  # each sample evaluated when reached: a path refused early costs no more
            T, tw = _sample(traj, t)
            res = model.ik(T, seed)
            reason = None if res.converged else "unreachable"
            if reason is None and not res.within_limits:
                reason = "joint_limit"
            jump = reason is None and float(np.max(np.abs(res.q - q))) > PATH_STEP_RAD
            if reason is None and (jump or model.configuration(res.q, T) != branch):
                reason = "configuration"
            if reason is None and self.singular(res.q, T):
                reason = "singularity"
            if reason is None:
                try:
                    J = model.jacobian(res.q)
                    qd = np.linalg.solve(J, tw)
                except np.linalg.LinAlgError:
                    reason = "singularity"
            if reason is not None:
                return JointPath(ts[:k], qs[:k] if k else q[None], False, reason)
            q = qs[k] = res.q
            qds[k] = qd
            if s.qdd_max is not None:
                qdds[k] = np.linalg.solve(J, _twist_rate(traj, t, t0, t1) - model.drift(q, qd))
            if k + 1 < len(ts):
                seed = q + qd * (ts[k + 1] - ts[k])
        ratios = np.abs(qds).max(axis=0) / (s.speed_fraction * model.qd_max)
        accel = np.zeros(6) if s.qdd_max is None else self._accel_ratios(traj, ts, qs, qds, qdds, t0, t1)
        return JointPath(ts, qs, True, None, max(float(ratios.max()), math.sqrt(float(accel.max()))), ratios, accel)

    def _accel_ratios(self, traj, ts, qs, qds, qdds, t0: float, t1: float) -> np.ndarray:
        """Each joint's peak |q̈_i| / (speed_fraction · q̈max_i) over the path. The samples' own accelerations,
        refined where they come near the limit: round each joint's two largest samples, every
        ``dt_s / ACCEL_SUBSTEPS`` with q from the sample's rates (q + q̇·δ, ~1e-4 rad off over 20 ms), since a
        jerk-limited peak falls between samples (the 20-ms samples saw 0.87 of the 2-ms peak on a 0.4-s leg)."""
        model, s = self.model, self.settings
        limit = s.speed_fraction * np.asarray(s.qdd_max, float)
        coarse = np.abs(qdds) / limit
        peak = coarse.max(axis=0)
        centres = {int(k) for i in np.flatnonzero(peak >= ACCEL_REFINE_FROM) for k in np.argsort(coarse[:, i])[-2:]}
        for k in sorted(centres):
            for j in (k - 1, k):  # the intervals either side of sample k
                if j < 0 or j + 1 >= len(ts):
                    continue
                for t in np.linspace(ts[j], ts[j + 1], ACCEL_SUBSTEPS + 1)[1:-1]:
                    qa = qs[j] + qds[j] * (t - ts[j])
                    J = model.jacobian(qa)
                    qd = np.linalg.solve(J, _sample(traj, t)[1])
                    qdd = np.linalg.solve(J, _twist_rate(traj, t, t0, t1) - model.drift(qa, qd))
                    peak = np.maximum(peak, np.abs(qdd) / limit)
        return peak

    def joint_time_s(self, q0, T_w_F) -> float:
        """Least time (s) the joints need from ``q0`` to the configuration nearest it at ``T_w_F`` (IK from
        ``q0``): max_i |Δq_i| / q̇max_i; inf if IK from ``q0`` does not reach it within the limits, or the
        configuration branch differs or it is within a singularity margin."""
        model = self.model
        res = model.ik(T_w_F, q0)
        if not res.ok or model.configuration(res.q) != model.configuration(q0) or self.singular(res.q):
            return math.inf
        return joint_time_s(q0, res.q, model.qd_max)


def joint_time_s(q0, q1, qd_max) -> float:
    """max_i |q1_i − q0_i| / qd_max_i (s): no joint moves faster than its limit, so no move between the two
    configurations is shorter."""
    return float(np.max(np.abs(np.asarray(q1, float) - np.asarray(q0, float)) / np.asarray(qd_max, float)))


class StationReach:
    """Calibration stations as the arm flies them (:class:`labctl.calibration.procedure.StationReach`): the first
    pose in the arm's home branch (IK from its home configuration), then each straight move to the next (position
    linear, rotation slerped, sampled every ``step_mm`` / ``step_rad``) followed in joint space, every sample
    within the joint limits and margins and in the same branch. Prefixes already flown are remembered, so a
    planner that grows a sequence pose by pose pays one move per question."""

    def __init__(self, planner: ArmPlanner, *, step_mm: float = 20.0, step_rad: float = math.radians(2.0)):
        self.planner, self.step_mm, self.step_rad = planner, step_mm, step_rad
        # a prefix's poses → the configuration at its last pose (None: not flown): a calibration plans its stations
        # once before opening the devices and again after, when a slow plan would leave the robot's watchdog unfed
        self._flown: dict[bytes, np.ndarray | None] = {}

    def _move(self, T0: np.ndarray, T1: np.ndarray, q0: np.ndarray) -> np.ndarray | None:
        phi = log_so3(T0[:3, :3].T @ T1[:3, :3])
        d = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
        n = max(int(math.ceil(max(d / self.step_mm, float(np.linalg.norm(phi)) / self.step_rad))), 1)
        poses = [make_T(T0[:3, :3] @ exp_so3(phi * u), T0[:3, 3] + u * (T1[:3, 3] - T0[:3, 3]))
                 for u in np.linspace(0.0, 1.0, n + 1)[1:]]
        fol = self.planner.model.follow(poses, q0)
        if not fol.ok or any(self.planner.singular(q) for q in fol.qs):
            return None
        return fol.qs[-1]

    def __call__(self, poses) -> bool:
        """True if the arm flies through ``poses`` (``T_w_F``, 4×4 mm) in order (class docstring)."""
        model = self.planner.model
        key = b""
        q: np.ndarray | None = None
        prev: np.ndarray | None = None
        for T in poses:
            T = np.asarray(T, float)
            key += T.tobytes()
            if key in self._flown:
                q, prev = self._flown[key], T
            elif q is None or prev is None:
                res = model.ik(T, model.home)
                ok = res.ok and model.configuration(res.q) == model.configuration(model.home) \
                    and not self.planner.singular(res.q)
                q, prev = res.q if ok else None, T
                self._flown[key] = q
            else:
                q, prev = self._move(prev, T, q), T
                self._flown[key] = q
            if q is None:
                return False
        return True


#: a segment over the joints' speeds is slowed by its peak ratio and checked again at most this often: a stretched
#: ruckig segment keeps its start state, so it is not an exact time scaling of the earliest one
STRETCH_TRIES = 4


@dataclass
class ArmFit:
    """A plan as the arm can fly it: the plan (unreachable, with the reason, if none), its joint path, and how
    much longer than the earliest arrival it was made (``stretch``, 1: not slowed)."""

    plan: Interception
    path: JointPath | None
    stretch: float = 1.0


def fit_plan(plan: Interception, t0: float, check: Callable[[Interception], JointPath],
             plan_at: Callable[[float, float], Interception], tries: int = STRETCH_TRIES) -> ArmFit:
    """``plan`` (starting at ``t0``, s) made flyable by the arm: ``check`` follows a plan in joint space; a path
    whose ratio r (peak joint speed, or the square root of peak joint acceleration, against its share of the
    limit) exceeds 1 is re-planned by ``plan_at(T, slow)`` to last exactly r times as long (T = r · (t_hit − t0))
    — where the accelerations bind, with its acceleration and jerk limits time-scaled by ``slow`` (the product of
    those square roots so far; :meth:`~labctl.planning.ruckig_profile.JerkLimits.slowed`) — and checked again,
    up to ``tries`` times; one that is not followable (out of reach, a joint limit, a singularity margin, a
    change of configuration) comes back unreachable with ``arm_<reason>``, so the caller chooses another view."""
    G = plan.target
    stretch, slow = 1.0, 1.0
    for _ in range(tries):
        assert plan.t_hit is not None and plan.trajectory is not None  # only reachable plans are checked
        path = check(plan)
        if not path.ok:
            return ArmFit(Interception(None, None, f"the arm cannot fly the path: {path.reason}",
                                       f"arm_{path.reason}", G), path, stretch)
        if path.ratio <= 1.0:
            return ArmFit(plan, path, stretch)
        stretch *= path.ratio
        slow *= max(math.sqrt(float(path.accel_ratios.max())), 1.0)
        plan = plan_at((plan.t_hit - t0) * path.ratio, slow)
        if not plan.reachable:
            return ArmFit(plan, None, stretch)
    return ArmFit(Interception(None, None, "the arm's joints stay over speed on the slowed path", "arm_speed", G),
                  None, stretch)
