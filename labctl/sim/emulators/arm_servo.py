"""The reference robot controller's arm: joint state and the joint-space check of a task-space segment.

An arm's Cartesian servo mode (UR ``servoL``, ABB EGM, KUKA RSI in Cartesian mode) follows a task-space
trajectory by solving inverse kinematics at every servo tick from the configuration it has. This module
does the same for a whole segment before it is accepted: it samples the segment every ``check_dt_s``
(the servo tick, a setting of ``drivers/robot.yaml``), solves every sample in the configuration branch
the arm is in (shoulder, elbow, wrist: :meth:`labctl.planning.arm.ArmModel.configuration`), each joint on
the turn nearest the previous sample, and refuses the segment (dialect 1.3, docs/protocols/robot.md §6)
when, in this order over the whole segment:

* E30 — some sample has no solution in any branch (outside the arm's reachable set: beyond its reach,
  or the wrist point inside the cylinder of radius |d4| round the base axis);
* E31 — some joint leaves its limits;
* E32 — some sample lies within the set margin of a singularity (``singularity_margins``: shoulder
  distance in mm, |sin q3| for the elbow, |sin q5| for the wrist);
* E33 — the path needs a configuration change: some sample is reachable only in another branch, or a
  joint jumps by more than ``PATH_STEP_RAD`` between two samples;
* E34 — some joint's speed or acceleration (finite differences over the samples) exceeds its limit.

For a UR-type arm (Universal Robots' DH pattern) the samples are solved in closed form, all at once
(numpy over the samples, the standard derivation of :meth:`ArmModel.closed_form` restricted to one
branch), which is what keeps the check well inside a frame time (docs/notes/robot.md, 2026-12-02).
Another arm goes through :meth:`ArmModel.follow` (Pinocchio, sample by sample). Units: mm, s, rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...geometry import invert
from ...planning.arm import PATH_STEP_RAD, ArmModel

# dialect 1.3's refusals, in the order they are checked (docs/protocols/robot.md §6)
E_REACH, E_JOINT_LIMIT, E_SINGULAR, E_CONFIGURATION, E_JOINT_RATE = 30, 31, 32, 33, 34


@dataclass(frozen=True)
class ArmPolicy:
    """How strictly the controller keeps its arm away from trouble (``drivers/robot.yaml``, ``arm_*``):
    singularity margins (mm from the shoulder cylinder; |sin q3|; |sin q5|), the joints' acceleration
    limits (rad/s²) and the check's sampling interval (s)."""

    shoulder_mm: float
    elbow: float
    wrist: float
    qdd_max: np.ndarray
    check_dt_s: float

    @classmethod
    def from_config(cls, cfg) -> ArmPolicy:
        """From a :class:`labctl.config.RobotConfig` (degrees at that edge)."""
        return cls(float(cfg.arm_shoulder_margin_mm), float(cfg.arm_elbow_margin), float(cfg.arm_wrist_margin),
                   np.radians(np.asarray(cfg.arm_joint_accel_deg_s2, float)), float(cfg.arm_check_dt_s))


def _rz(theta: np.ndarray) -> np.ndarray:
    """Batched 3×3 rotations about z."""
    c, s = np.cos(theta), np.sin(theta)
    R = np.zeros((len(theta), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def _dh_batch(theta: np.ndarray, d: float, a: float, alpha: float) -> np.ndarray:
    """Batched standard DH link transforms Rz(θ)·Tz(d)·Tx(a)·Rx(α) (N×4×4)."""
    ct, st, ca, sa = np.cos(theta), np.sin(theta), math.cos(alpha), math.sin(alpha)
    T = np.zeros((len(theta), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2], T[:, 0, 3] = ct, -st * ca, st * sa, a * ct
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2], T[:, 1, 3] = st, ct * ca, -ct * sa, a * st
    T[:, 2, 1], T[:, 2, 2], T[:, 2, 3] = sa, ca, d
    T[:, 3, 3] = 1.0
    return T


def _inv_batch(T: np.ndarray) -> np.ndarray:
    """Batched inverse of rigid transforms."""
    out = np.zeros_like(T)
    Rt = np.transpose(T[:, :3, :3], (0, 2, 1))
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def base_flange(model: ArmModel, T_w_F: np.ndarray) -> np.ndarray:
    """``T_base_flange`` (the arm's own flange in its base, N×4×4) of commanded poses ``T_w_F`` (N×4×4)."""
    return invert(model.T_w_base)[None] @ np.asarray(T_w_F, float) @ invert(model.T_flange_tool)[None]


def ur_branch_ik(model: ArmModel, T_w_F: np.ndarray, branch: tuple[int, int, int], *,
                 in_base: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A UR-type arm's closed-form solution in one ``branch`` (shoulder, elbow, wrist, each ±1) for every
    pose of ``T_w_F`` (N×4×4, mm; ``T_base_flange`` already when ``in_base``): (N×6 joints in (−π, π],
    N valid flags). Invalid where the branch has no solution (out of reach, inside the shoulder cylinder)
    or the wrist is exactly singular."""
    d, a, al = model.d, model.a, model.alpha
    T = np.asarray(T_w_F, float) if in_base else base_flange(model, T_w_F)
    n = len(T)
    s_sh, s_el, s_wr = branch
    p5 = T[:, :3, 3] - d[5] * T[:, :3, 2]
    r = np.hypot(p5[:, 0], p5[:, 1])
    ok = r > abs(d[3])
    psi = np.arctan2(p5[:, 1], p5[:, 0])
    phi = np.arccos(np.clip(d[3] / np.where(ok, r, 1.0), -1.0, 1.0))
    q1 = psi + s_sh * phi + math.pi / 2
    s1, c1 = np.sin(q1), np.cos(q1)
    c5 = (T[:, 0, 3] * s1 - T[:, 1, 3] * c1 - d[3]) / d[5]
    ok &= np.abs(c5) <= 1.0
    q5 = s_wr * np.arccos(np.clip(c5, -1.0, 1.0))
    s5 = np.sin(q5)
    ok &= np.abs(s5) > 1e-9
    s5 = np.where(np.abs(s5) > 1e-9, s5, 1.0)
    Ti = _inv_batch(T)
    X, Y = Ti[:, :3, 0], Ti[:, :3, 1]
    q6 = np.arctan2((-X[:, 1] * s1 + Y[:, 1] * c1) / s5, (X[:, 0] * s1 - Y[:, 0] * c1) / s5)
    A56 = _dh_batch(q5, d[4], a[4], al[4]) @ _dh_batch(q6, d[5], a[5], al[5])
    T14 = _inv_batch(_dh_batch(q1, d[0], a[0], al[0])) @ T @ _inv_batch(A56)
    p3 = T14 @ np.array([0.0, -d[3], 0.0, 1.0])
    L = np.hypot(p3[:, 0], p3[:, 1])
    c3 = (L * L - a[1] ** 2 - a[2] ** 2) / (2 * a[1] * a[2])
    ok &= (np.abs(c3) <= 1.0) & (L > 1e-9)
    q3 = s_el * np.arccos(np.clip(c3, -1.0, 1.0))
    Ls = np.where(L > 1e-9, L, 1.0)
    q2 = -np.arctan2(p3[:, 1], -p3[:, 0]) + np.arcsin(np.clip(a[2] * np.sin(q3) / Ls, -1.0, 1.0))
    T13 = _dh_batch(q2, d[1], a[1], al[1]) @ _dh_batch(q3, d[2], a[2], al[2])
    T34 = _inv_batch(T13) @ T14
    q4 = np.arctan2(T34[:, 1, 0], T34[:, 0, 0])
    q = np.stack([q1, q2, q3, q4, q5, q6], axis=1)
    q = np.remainder(q + math.pi, 2 * math.pi) - math.pi
    return q.reshape(n, 6), ok


BRANCHES = [(s, e, w) for s in (1, -1) for e in (1, -1) for w in (1, -1)]


class ArmServo:
    """The arm behind the reference controller: its kinematic model and the controller's policy."""

    def __init__(self, model: ArmModel, policy: ArmPolicy):
        self.model = model
        self.policy = policy
        self.closed_form = model.ur_type

    def initial(self, T_w_F: np.ndarray) -> np.ndarray:
        """The configuration the arm starts in at ``T_w_F``: the IK solution nearest the arm file's
        ``home_deg`` (ValueError if the pose is out of the arm's reach)."""
        sols = self.model.ik_solutions(T_w_F)
        if not sols:
            raise ValueError(f"the {self.model.name}'s start pose is out of its reach")
        return sols[0]

    def _solve(self, Ts: np.ndarray, q_start: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every pose in the branch of ``q_start``, each joint on the turn nearest the previous sample:
        (N×6 joints, N valid flags, N flags 'reachable in some branch')."""
        branch = self.model.configuration(q_start)
        Tb = base_flange(self.model, Ts)
        q, ok = ur_branch_ik(self.model, Tb, branch, in_base=True)
        anywhere = ok.copy()
        filled = np.vstack([q_start[None, :], q])
        if not ok.all():
            bad = ~ok
            for other in BRANCHES:
                if other != branch:
                    anywhere[bad] |= ur_branch_ik(self.model, Tb[bad], other, in_base=True)[1]
            for i in np.flatnonzero(bad) + 1:  # carry the last valid sample over invalid ones
                filled[i] = filled[i - 1]
        # unwrap from q_start: each step into (−π, π], so every joint stays on the turn it is on
        steps = np.remainder(np.diff(filled, axis=0) + math.pi, 2 * math.pi) - math.pi
        qs = q_start[None, :] + np.cumsum(steps, axis=0)
        return qs, ok, anywhere

    def joints(self, T_w_F: np.ndarray, q_near: np.ndarray) -> np.ndarray:
        """The configuration at ``T_w_F`` in the branch of ``q_near``, each joint nearest it (exact to the
        closed form's round-off); ``q_near`` itself where that branch has no solution."""
        if self.closed_form:
            qs, ok, _ = self._solve(np.asarray(T_w_F, float)[None], np.asarray(q_near, float))
            return qs[0] if ok[0] else np.asarray(q_near, float)
        res = self.model.ik(T_w_F, q_near)
        return res.q if res.converged else np.asarray(q_near, float)

    def check(self, ts: np.ndarray, Ts: np.ndarray, q_start: np.ndarray) -> tuple[int, np.ndarray]:
        """(0 or the refusal code, N×6 joints) of the segment whose poses ``Ts`` (N×4×4) are sampled at
        times ``ts`` (N, s, evenly spaced, the first at the segment's start), from configuration
        ``q_start``. The joints are meaningful only when the code is 0."""
        m, pol = self.model, self.policy
        q_start = np.asarray(q_start, float)
        if self.closed_form:
            qs, ok, anywhere = self._solve(Ts, q_start)
        else:
            follow = m.follow(Ts, q_start)
            qs = follow.qs
            if not follow.ok:  # the configurations before the failure (follow's first row is q_start), then held
                done = follow.qs[1:]
                qs = np.vstack([done, np.repeat((done[-1] if len(done) else q_start)[None], len(Ts) - len(done), 0)])
            ok = np.ones(len(Ts), bool)
            if not follow.ok:
                ok[follow.failed_at:] = False
            anywhere = ok.copy()
            if follow.reason == "unreachable":
                anywhere[follow.failed_at] = m.reachable(Ts[follow.failed_at])
        if not anywhere.all():
            return E_REACH, qs
        good = qs[ok]
        if np.any(good < m.q_min - 1e-9) or np.any(good > m.q_max + 1e-9):
            return E_JOINT_LIMIT, qs
        if self._near_singular(Ts[ok], good):
            return E_SINGULAR, qs
        if not ok.all():
            return E_CONFIGURATION, qs
        steps = np.abs(np.diff(np.vstack([q_start[None], qs]), axis=0))
        if np.any(steps > PATH_STEP_RAD):
            return E_CONFIGURATION, qs
        if len(ts) >= 2:
            dt = float(ts[1] - ts[0])
            qd = np.diff(qs, axis=0) / dt
            if np.any(np.abs(qd) > m.qd_max * (1 + 1e-6)):
                return E_JOINT_RATE, qs
            if len(qd) >= 2 and np.any(np.abs(np.diff(qd, axis=0)) / dt > pol.qdd_max * (1 + 1e-6)):
                return E_JOINT_RATE, qs
        return 0, qs

    def _near_singular(self, Ts: np.ndarray, qs: np.ndarray) -> bool:
        """Some sample within the policy's margin of the shoulder, elbow or wrist singularity (vectorised
        :meth:`ArmModel.singularity_margins`)."""
        m, pol = self.model, self.policy
        if len(qs) == 0:
            return False
        if np.any(np.abs(np.sin(qs[:, 2] + m.offset[2])) < pol.elbow):
            return True
        if np.any(np.abs(np.sin(qs[:, 4] + m.offset[4])) < pol.wrist):
            return True
        T = base_flange(m, Ts)
        p5 = T[:, :3, 3] - m.d[5] * T[:, :3, 2]
        r2 = p5[:, 0] ** 2 + p5[:, 1] ** 2
        shoulder = np.sqrt(np.maximum(r2 - m.d[3] ** 2, 0.0))
        return bool(np.any(shoulder < pol.shoulder_mm))


def sample_times(T: float, dt: float) -> np.ndarray:
    """Evenly spaced times over [0, T] (s), both ends included, at most ``dt`` apart (at least 3)."""
    n = max(int(math.ceil(T / dt)), 2)
    return np.linspace(0.0, T, n + 1)


def rotvecs_to_matrices(phi: np.ndarray) -> np.ndarray:
    """Batched Rodrigues: N×3 rotation vectors (rad) to N×3×3 matrices."""
    th = np.linalg.norm(phi, axis=1)
    safe = np.where(th > 1e-15, th, 1.0)
    k = phi / safe[:, None]
    K = np.zeros((len(phi), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], (1 - np.cos(th))[:, None, None]
    R = np.eye(3)[None] + s * K + c * (K @ K)
    R[th <= 1e-15] = np.eye(3)
    return R


def poses(p: np.ndarray, R0: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """N×4×4 poses from positions (N×3, mm) and rotations R0·exp([φ]×) (φ N×3, rad)."""
    T = np.zeros((len(p), 4, 4))
    T[:, :3, :3] = R0[None] @ rotvecs_to_matrices(phi)
    T[:, :3, 3] = p
    T[:, 3, 3] = 1.0
    return T
