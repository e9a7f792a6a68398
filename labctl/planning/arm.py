"""A six-joint arm's kinematics: forward kinematics, inverse kinematics from a seed, singularity margins and
the joint speeds of a Cartesian path (numpy in, numpy out).

The model is built from an arm data file (:class:`labctl.config.arm.ArmConfig`: standard DH, as Universal
Robots and most makers publish it) on Pinocchio, chosen by measurement (docs/notes/robot.md, "Choosing the
kinematics library"). Millimetres and radians inside, poses ``T_<to>_<from>``:

* ``T_w_base``: the arm's base in the world W;
* the arm's own flange (DH frame 6) in its base: the DH chain;
* ``T_flange_tool``: the frame labctl commands (labctl's flange F) in the arm's flange.

So ``fk(q)`` is ``T_w_F`` = T_w_base · DH(q) · T_flange_tool, the pose the robot controller is asked for.

Inverse kinematics is damped least squares on Pinocchio's frame Jacobian from a seed configuration: from
the previous configuration along a path it converges to the nearest solution, as an arm's Cartesian servo
does, so a path that would need another configuration shows up as a failure or a flip of
:meth:`ArmModel.configuration`, never as a silent jump.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import UserInputError
from ..geometry import invert, make_T, rot_x, rot_y, rot_z

LENGTH_SCALE_MM = 1000.0  # rad ↔ mm weight of the IK error: 1 mrad of rotation counts as 1 mm
POS_TOL_MM = 1e-4
ROT_TOL_RAD = 1e-7
DAMPING = 1e-10  # λ² of the damped least squares, on the scaled (m, rad) error
MAX_STEP_RAD = math.pi  # largest joint change of one iteration (smaller clamps cost convergence: notes)
PATH_STEP_RAD = math.radians(5.0)  # a larger joint change between two path samples is a configuration jump

_I6 = np.eye(6)
_I6.setflags(write=False)  # the damping's identity, scaled into a new array each iteration


def _rpy(rpy_rad) -> np.ndarray:
    r, p, y = rpy_rad
    return rot_z(y) @ rot_y(p) @ rot_x(r)


def dh_transform(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    """Standard DH link transform Rz(θ)·Tz(d)·Tx(a)·Rx(α) (4×4)."""
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0.0, sa, ca, d],
                     [0.0, 0.0, 0.0, 1.0]])


@dataclass
class IKResult:
    """One inverse-kinematics solve: the configuration reached, whether it meets the pose, and its errors."""

    q: np.ndarray
    converged: bool
    pos_err_mm: float
    rot_err_rad: float
    iterations: int
    within_limits: bool

    @property
    def ok(self) -> bool:
        """Converged to the pose within the joint limits."""
        return self.converged and self.within_limits


@dataclass
class PathFollow:
    """A Cartesian path followed in joint space from a start configuration.

    ``qs`` holds the configurations up to the first failure (all of them when ``ok``); ``failed_at``
    is the index of the first pose the arm could not follow and ``reason`` why: ``unreachable`` (no
    convergence from the previous configuration), ``joint_limit``, ``configuration`` (the shoulder,
    elbow or wrist branch flips, or a joint jumps by more than ``PATH_STEP_RAD`` between samples)."""

    qs: np.ndarray
    ok: bool
    failed_at: int | None = None
    reason: str | None = None


class ArmModel:
    """A six-joint arm in standard DH form at its mount in the world (see the module's docstring)."""

    def __init__(self, name: str, d_mm, a_mm, alpha_rad, *, offset_rad=None, q_min, q_max, qd_max, home,
                 T_w_base=None, T_flange_tool=None):
        try:
            import pinocchio as pin
        except ImportError:
            raise UserInputError("the arm model needs Pinocchio: pip install 'labctl[arm]'") from None

        self.name = name
        self.d = np.asarray(d_mm, float)
        self.a = np.asarray(a_mm, float)
        self.alpha = np.asarray(alpha_rad, float)
        self.offset = np.zeros(6) if offset_rad is None else np.asarray(offset_rad, float)
        self.q_min, self.q_max = np.asarray(q_min, float), np.asarray(q_max, float)
        self.qd_max = np.asarray(qd_max, float)
        self.home = np.asarray(home, float)
        self.T_w_base = np.eye(4) if T_w_base is None else np.asarray(T_w_base, float)
        self.T_flange_tool = np.eye(4) if T_flange_tool is None else np.asarray(T_flange_tool, float)
        self._T_base_w, self._T_tool_flange = invert(self.T_w_base), invert(self.T_flange_tool)  # fixed: once
        self._pin = pin
        model = pin.Model()
        parent, M = 0, pin.SE3(self.T_w_base[:3, :3], self.T_w_base[:3, 3])
        for i in range(6):
            parent = model.addJoint(parent, pin.JointModelRZ(), M, f"joint{i + 1}")
            L = rot_z_T(self.offset[i]) @ make_T(rot_x(self.alpha[i]), [self.a[i], 0.0, self.d[i]])
            M = pin.SE3(L[:3, :3], L[:3, 3])
        model.lowerPositionLimit, model.upperPositionLimit = self.q_min.copy(), self.q_max.copy()
        flange = model.addFrame(pin.Frame("flange", parent, 0, M, pin.FrameType.OP_FRAME))
        Mt = M * pin.SE3(self.T_flange_tool[:3, :3], self.T_flange_tool[:3, 3])
        self._tool = model.addFrame(pin.Frame("tool", parent, flange, Mt, pin.FrameType.OP_FRAME))
        self._model, self._data = model, model.createData()
        self._W = np.diag([1.0 / LENGTH_SCALE_MM] * 3 + [1.0] * 3)

    @classmethod
    def from_config(cls, cfg) -> ArmModel:
        """From an :class:`labctl.config.arm.ArmConfig` (mm and degrees)."""
        rad = lambda v: np.radians(np.asarray(v, float))  # noqa: E731
        return cls(cfg.name, cfg.dh_d_mm, cfg.dh_a_mm, rad(cfg.dh_alpha_deg), offset_rad=rad(cfg.dh_offset_deg),
                   q_min=rad(cfg.joint_min_deg), q_max=rad(cfg.joint_max_deg), qd_max=rad(cfg.joint_speed_deg_s),
                   home=rad(cfg.home_deg), T_w_base=make_T(_rpy(rad(cfg.base_rpy_deg)), cfg.base_xyz_mm),
                   T_flange_tool=make_T(_rpy(rad(cfg.tool_rpy_deg)), cfg.tool_xyz_mm))

    # --- forward ----------------------------------------------------------------------------
    def fk(self, q) -> np.ndarray:
        """``T_w_F``: the commanded frame in the world at configuration ``q`` (4×4, mm)."""
        pin = self._pin
        q = np.asarray(q, float)
        pin.forwardKinematics(self._model, self._data, q)
        return pin.updateFramePlacement(self._model, self._data, self._tool).homogeneous

    def fk_flange(self, q) -> np.ndarray:
        """``T_base_flange``: the arm's own flange (DH frame 6) in its base, without mount or tool (4×4, mm)."""
        return self._T_base_w @ self.fk(q) @ self._T_tool_flange

    def jacobian(self, q) -> np.ndarray:
        """The 6×6 geometric Jacobian of the commanded frame, world-aligned: rows vx vy vz (mm/rad), ωx ωy ωz."""
        pin = self._pin
        q = np.asarray(q, float)
        return pin.computeFrameJacobian(self._model, self._data, q, self._tool, pin.LOCAL_WORLD_ALIGNED)

    def drift(self, q, qd) -> np.ndarray:
        """J̇(q, q̇)·q̇: the commanded frame's acceleration [a (mm/s²); α (rad/s²)], world-aligned, at joint rates
        ``qd`` (rad/s) with no joint acceleration (Pinocchio's classical acceleration), so that
        q̈ = J⁻¹·([a; α] − drift) for a path's own acceleration."""
        pin = self._pin
        q, qd = np.asarray(q, float), np.asarray(qd, float)
        pin.forwardKinematics(self._model, self._data, q, qd, np.zeros(6))
        acc = pin.getFrameClassicalAcceleration(self._model, self._data, self._tool, pin.LOCAL_WORLD_ALIGNED)
        return np.concatenate([acc.linear, acc.angular])

    # --- singularities ----------------------------------------------------------------------
    def manipulability(self, q) -> float:
        """Yoshikawa's index √det(J·Jᵀ) with the linear rows in metres: 0 at a singularity."""
        J = self._W @ self.jacobian(q)
        return float(math.sqrt(max(np.linalg.det(J @ J.T), 0.0)))

    def wrist_point(self, q, T_w_F=None) -> np.ndarray:
        """The origin of DH frame 5 in the arm's base (mm): the point the shoulder singularity is about
        (``T_w_F``: ``fk(q)`` when the caller has it)."""
        T = self.fk_flange(q) if T_w_F is None else self._T_base_w @ T_w_F @ self._T_tool_flange
        return T[:3, 3] - self.d[5] * T[:3, 2]

    def singularity_margins(self, q) -> dict[str, float]:
        """Distances to the three singularities of a UR-type arm (parallel joints 2–4):
        ``shoulder_mm`` — the wrist point's distance from the cylinder of radius |d4| round the base axis
        (√(r² − d4²); 0 on it, where joint 1 is undetermined), ``elbow`` |sin q3| (arm stretched or folded),
        ``wrist`` |sin q5| (joints 4 and 6 aligned)."""
        p = self.wrist_point(q)
        r2 = float(p[0] ** 2 + p[1] ** 2)
        return {"shoulder_mm": math.sqrt(max(r2 - self.d[3] ** 2, 0.0)),
                "elbow": abs(math.sin(float(q[2]) + self.offset[2])),
                "wrist": abs(math.sin(float(q[4]) + self.offset[4]))}

    def configuration(self, q, T_w_F=None) -> tuple[int, int, int]:
        """The (shoulder, elbow, wrist) branch, each ±1: which of the up to eight IK solutions ``q`` is.

        Shoulder: the side of joint 1 about the wrist point's azimuth (the ± of the closed-form solution);
        elbow: the sign of sin q3; wrist: the sign of sin q5. Within one branch the arm moves without
        passing a singularity; changing branch means passing one. ``T_w_F``: ``fk(q)`` when the caller has it."""
        p = self.wrist_point(q, T_w_F)
        psi = math.atan2(p[1], p[0])
        side = math.remainder(float(q[0]) + self.offset[0] - psi - math.pi / 2, 2 * math.pi)
        sgn = lambda x: 1 if x >= 0 else -1  # noqa: E731
        return sgn(side), sgn(math.sin(float(q[2]) + self.offset[2])), sgn(math.sin(float(q[4]) + self.offset[4]))

    # --- inverse ----------------------------------------------------------------------------
    def within_limits(self, q) -> bool:
        """Every joint inside its limits."""
        q = np.asarray(q, float)
        return bool(np.all(q >= self.q_min - 1e-12) and np.all(q <= self.q_max + 1e-12))

    def ik(self, T_w_F, seed, *, max_iter: int = 100) -> IKResult:
        """The configuration nearest ``seed`` that puts the commanded frame at ``T_w_F`` (damped least squares).

        From a nearby seed (the previous configuration of a path) this is the arm's own solution, with no
        change of configuration; from a far seed it may find any of the up to eight. Each joint of the
        result is the turn of it nearest the seed (the same pose: joints are 2π-periodic)."""
        pin = self._pin
        T = np.asarray(T_w_F, float)
        goal = pin.SE3(T[:3, :3], T[:3, 3])
        q = np.array(seed, float)
        model, data, fid, W = self._model, self._data, self._tool, self._W
        it = 0
        while True:
            pin.computeJointJacobians(model, data, q)  # forward kinematics included
            cur = pin.updateFramePlacement(model, data, fid)
            diff = cur.actInv(goal)
            err = pin.log6(diff).vector
            ep, er = err[:3], err[3:]  # norms as np.linalg.norm takes them (√ of the dot), without its overhead
            converged = math.sqrt(ep.dot(ep)) < POS_TOL_MM and math.sqrt(er.dot(er)) < ROT_TOL_RAD
            if converged or it == max_iter:
                break
            it += 1
            J = W @ pin.Jlog6(diff) @ pin.getFrameJacobian(model, data, fid, pin.LOCAL)
            e = W @ err
            # Levenberg–Marquardt with Sugihara's damping (½‖e‖² + a floor): wide steps far away, Newton near
            dq = np.linalg.solve(J.T @ J + (0.5 * float(e @ e) + DAMPING) * _I6, J.T @ e)
            big = float(np.abs(dq).max())
            q = q + (dq * (MAX_STEP_RAD / big) if big > MAX_STEP_RAD else dq)
        dp, er = cur.translation - goal.translation, err[3:]
        pos_err = math.sqrt(dp.dot(dp))
        rot_err = math.sqrt(er.dot(er))  # log6's angular part: the rotation angle left
        seed = np.asarray(seed, float)
        q = seed + np.remainder(q - seed + math.pi, 2 * math.pi) - math.pi  # the same pose, each joint nearest the seed
        return IKResult(q, converged, pos_err, rot_err, it, self.within_limits(q))

    def closed_form(self, T_w_F) -> list[np.ndarray]:
        """A UR-type arm's closed-form solutions (up to eight, joints in (−π, π], not limit-checked), each
        verified by forward kinematics; ``[]`` for another arm. Joint 1 from the wrist point's azimuth,
        joint 5 from the flange's offset along joint 1's axis, joint 6 from the flange's orientation, then
        the planar 3R of joints 2–4 (the standard derivation for this geometry)."""
        if not self.ur_type:
            return []
        d, a = self.d, self.a
        T = invert(self.T_w_base) @ np.asarray(T_w_F, float) @ invert(self.T_flange_tool)
        p5 = T[:3, 3] - d[5] * T[:3, 2]
        r = math.hypot(p5[0], p5[1])
        if r <= abs(d[3]):
            return []
        psi, phi = math.atan2(p5[1], p5[0]), math.acos(d[3] / r)
        Ti = invert(T)
        out = []
        for q1 in (psi + phi + math.pi / 2, psi - phi + math.pi / 2):
            s1, c1 = math.sin(q1), math.cos(q1)
            c5 = (T[0, 3] * s1 - T[1, 3] * c1 - d[3]) / d[5]
            if abs(c5) > 1.0:
                continue
            for q5 in (math.acos(c5), -math.acos(c5)):
                s5 = math.sin(q5)
                if abs(s5) < 1e-9:
                    continue  # wrist singular: joints 4 and 6 undetermined
                X, Y = Ti[:3, 0], Ti[:3, 1]
                q6 = math.atan2((-X[1] * s1 + Y[1] * c1) / s5, (X[0] * s1 - Y[0] * c1) / s5)
                T14 = invert(dh_transform(q1, d[0], a[0], self.alpha[0])) @ T @ invert(
                    dh_transform(q5, d[4], a[4], self.alpha[4]) @ dh_transform(q6, d[5], a[5], self.alpha[5]))
                p3 = T14 @ np.array([0.0, -d[3], 0.0, 1.0])
                L = math.hypot(p3[0], p3[1])
                c3 = (L * L - a[1] ** 2 - a[2] ** 2) / (2 * a[1] * a[2])
                if abs(c3) > 1.0 or L < 1e-9:
                    continue
                for q3 in (math.acos(c3), -math.acos(c3)):
                    q2 = -math.atan2(p3[1], -p3[0]) + math.asin(a[2] * math.sin(q3) / L)
                    T13 = dh_transform(q2, d[1], a[1], self.alpha[1]) @ dh_transform(q3, d[2], a[2], self.alpha[2])
                    T34 = invert(T13) @ T14
                    q4 = math.atan2(T34[1, 0], T34[0, 0])
                    q = np.array([math.remainder(x, 2 * math.pi) for x in (q1, q2, q3, q4, q5, q6)])
                    if np.allclose(self.fk(q), T_w_F, atol=1e-6):
                        out.append(q)
        return out

    def _seeds(self, T_w_F, n_seeds: int, rng) -> list[np.ndarray]:
        """``home``, a UR-type arm's closed-form solutions (:meth:`closed_form`), then random seeds up to
        ``n_seeds``; IK from each polishes it and applies the joint limits."""
        rng = np.random.default_rng(0) if rng is None else rng
        seeds = [self.home, *self.closed_form(T_w_F)]
        lo, hi = np.maximum(self.q_min, -math.pi), np.minimum(self.q_max, math.pi)
        seeds += [rng.uniform(lo, hi) for _ in range(max(n_seeds - len(seeds), 0))]
        return seeds

    def ik_solutions(self, T_w_F, *, n_seeds: int = 24, rng=None) -> list[np.ndarray]:
        """The distinct solutions within the joint limits found from the seeds of :meth:`_seeds`, nearest
        ``home`` first (one per configuration branch and turn of each joint)."""
        found: list[np.ndarray] = []
        for seed in self._seeds(T_w_F, n_seeds, rng):
            res = self.ik(T_w_F, seed)
            if res.ok and not any(np.max(np.abs(res.q - f)) < 1e-5 for f in found):
                found.append(res.q)
        return sorted(found, key=lambda q: float(np.max(np.abs(q - self.home))))

    def reachable(self, T_w_F, *, n_seeds: int = 24, rng=None) -> bool:
        """Some configuration within the joint limits reaches ``T_w_F`` (IK from the seeds of :meth:`_seeds`)."""
        if self.out_of_reach(T_w_F):
            return False
        return any(self.ik(T_w_F, s).ok for s in self._seeds(T_w_F, n_seeds, rng))

    @property
    def ur_type(self) -> bool:
        """The DH table has Universal Robots' pattern (parallel joints 2–4, wrist offsets d4 d5 d6)."""
        ur_alpha = np.array([math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0])
        return bool(np.allclose(self.alpha, ur_alpha) and np.allclose(self.a[[0, 3, 4, 5]], 0.0)
                    and np.allclose(self.d[[1, 2]], 0.0) and np.allclose(self.offset, 0.0))

    def out_of_reach(self, T_w_F) -> bool:
        """Certainly unreachable, by a necessary condition on a UR-type arm's wrist point (DH frame 5's origin):
        at least |d4| from the base axis, and within |a2| + |a3| + d5 of the shoulder. False when not sure
        (or not a UR-type arm): only :meth:`reachable` decides."""
        if not self.ur_type:
            return False
        T = invert(self.T_w_base) @ np.asarray(T_w_F, float) @ invert(self.T_flange_tool)
        p = T[:3, 3] - self.d[5] * T[:3, 2]
        r2 = float(p[0] ** 2 + p[1] ** 2)
        if r2 < self.d[3] ** 2 * (1 - 1e-9):
            return True
        rho, h = math.sqrt(r2 - min(r2, self.d[3] ** 2)), float(p[2]) - self.d[0]
        return math.hypot(rho, h) > abs(self.a[1]) + abs(self.a[2]) + abs(self.d[4]) + 1e-6

    # --- paths ------------------------------------------------------------------------------
    def follow(self, poses, q0, *, max_step_rad: float = PATH_STEP_RAD) -> PathFollow:
        """Follow ``poses`` (N×4×4 ``T_w_F``) in joint space from ``q0``, each solved from the previous one."""
        q = np.asarray(q0, float)
        branch = self.configuration(q)
        qs = [q]
        for i, T in enumerate(poses):
            res = self.ik(T, q)
            if not res.converged:
                return PathFollow(np.array(qs), False, i, "unreachable")
            if not res.within_limits:
                return PathFollow(np.array(qs), False, i, "joint_limit")
            if np.max(np.abs(res.q - q)) > max_step_rad or self.configuration(res.q) != branch:
                return PathFollow(np.array(qs), False, i, "configuration")
            q = res.q
            qs.append(q)
        return PathFollow(np.array(qs[1:]) if len(qs) > 1 else np.empty((0, 6)), True)

    def joint_speed_ratio(self, qs, t) -> np.ndarray:
        """Each joint's peak speed over its limit along configurations ``qs`` (N×6) sampled at times ``t`` (s):
        finite differences, so ≤ 1 means the arm keeps up."""
        qs, t = np.asarray(qs, float), np.asarray(t, float)
        if len(qs) < 2:
            return np.zeros(6)
        dt = np.diff(t)
        keep = dt > 1e-9
        speed = np.abs(np.diff(qs, axis=0))[keep] / dt[keep, None]
        return speed.max(axis=0) / self.qd_max if len(speed) else np.zeros(6)


def rot_z_T(theta: float) -> np.ndarray:
    """Rotation about z by ``theta`` as a 4×4 transform."""
    return make_T(rot_z(theta), np.zeros(3))
