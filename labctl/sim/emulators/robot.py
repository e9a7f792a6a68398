"""The reference robot controller of docs/protocols/robot.md (dialect 1.2; 1.3 with an arm), on an injectable clock.

Task-space segments are quintic polynomials (the paper's time-optimal task-space quintics,
§4.2): position p(τ) per axis and orientation R(τ) = R0·exp([φ(τ)]×) with φ a quintic vector
from 0 to log(R0ᵀR1), each from the current state (position, velocity, acceleration; rotation
and true angular velocity) to the target with the requested end velocities and zero end
acceleration over the given duration. Before a segment is accepted the controller checks,
exactly (critical points of the polynomials, :mod:`labctl.planning.safety`): the path inside the
workspace box, the braking rest point (each axis at ``a_stop = a_max/√3``) inside the box at
every instant, peak speed and acceleration, and the peak *true* angular speed.
Dialect 1.2 adds the ``ruckig`` profile: the time-optimal jerk-limited trajectory from the
current state (p, v, a; R, ω) to the target, computed by the controller itself with ruckig
(:mod:`labctl.planning.ruckig_profile`) and checked exactly by the same rules on each of its
cubic intervals. Dialect 1.3: when the robot's driver file names an arm
(:class:`labctl.sim.emulators.arm_servo.ArmServo`), the controller keeps its joint state, follows every
accepted segment through inverse kinematics from its current configuration (an arm's Cartesian servo
mode), refuses before moving a segment the arm cannot fly (E30–E34) and reports the joints in STATUS.
STOP, the watchdog and the end of a segment that ends moving brake with that
ramp, so the arm never leaves the box. ``STOP`` latches ``stopped`` and the watchdog
``watchdog`` until ``CLEAR``.
Units: mm, s, rad.

The class is written to be subclassed (tests/ build deliberately broken controllers from it):
the line parser (:meth:`RobotEmulator._parse_line`), the watchdog deadline
(:meth:`RobotEmulator._watchdog_due`), the stop ramp (:meth:`RobotEmulator._make_ramp`) and the
segment checks (:meth:`RobotEmulator._check`, :meth:`RobotEmulator._check_ruckig`) are separate methods.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from ...drivers.robot_protocol import (
    ERROR_CODES,
    MAX_LINE,
    Request,
    add_checksum,
    canonical_rotvec,
    fmt_fixed,
    fmt_num,
    parse_number,
    parse_request,
)
from ...geometry import make_T, matrix_to_rotvec, rotvec_to_matrix
from ...planning.limits import ANGULAR_STOP_PER_S  # angular braking: w_max to rest in 0.25 s
from ...planning.quintic import _derivative, _norm_max, _poly_range
from ...planning.rotation import right_jacobian
from ...planning.ruckig_profile import JERK_PER_ACCEL, JerkLimits, RuckigPlan, check_ruckig, plan_ruckig
from ...planning.safety import stop_envelope_range
from .arm_servo import ArmServo, poses, sample_times

if TYPE_CHECKING:
    from ...config import RobotConfig

NAME = "labctl-robot"
DIALECT = "1.4"  # 1.4: SET, the session's segment defaults (a controller without an arm skips 1.3)
ARM_DIALECT = "1.4"  # a controller with an arm: from 1.3 joints in STATUS, the arm's refusals E30–E34
PROFILES = ("quintic", "ruckig")
LIMIT_KEYS = ("vmax", "amax", "jmax", "wmax")  # a ruckig segment's own limits (1.2), at most the controller's
PROFILES_BEFORE = {"1.0": ("quintic",), "1.1": ("quintic",)}  # what a session of an older version lists
JOINT_DECIMALS = 4  # STATUS joints (1.3), degrees
IDENT = f"{NAME} {DIALECT}"
QUEUE_SIZE = 8
MAX_DURATION_S = 60.0
HOME_MIN_S = 1.0
HOME_RPY = (math.pi, 0.0, 0.0)  # flange z pointing down at the table
REL_TOL = 1e-6  # relative slack on the v/a/ω limits (round-off of a state spliced right at a limit)
BOX_TOL_MM = 1e-6
_VERSION = re.compile(r"^\d+\.\d+$")


def quintic_coeffs(p0, v0, a0, p1, v1, a1, T: float) -> np.ndarray:
    """Coefficients c[0..5] (rows) of p(τ)=Σ c_k τ^k meeting position/velocity/acceleration at τ=0 and τ=T.

    Works per column for vector quantities. Paper §4.2 (task-space quintic polynomials).
    """
    p0, v0, a0, p1, v1, a1 = (np.asarray(x, float) for x in (p0, v0, a0, p1, v1, a1))
    T2, T3, T4, T5 = T * T, T ** 3, T ** 4, T ** 5
    c0, c1, c2 = p0, v0, a0 / 2.0
    h = p1 - p0
    c3 = (20 * h - (8 * v1 + 12 * v0) * T - (3 * a0 - a1) * T2) / (2 * T3)
    c4 = (-30 * h + (14 * v1 + 16 * v0) * T + (3 * a0 - 2 * a1) * T2) / (2 * T4)
    c5 = (12 * h - 6 * (v1 + v0) * T - (a0 - a1) * T2) / (2 * T5)
    return np.stack([c0, c1, c2, c3, c4, c5])


_K = np.arange(6)
_FALLING = {d: np.array([math.factorial(k) / math.factorial(k - d) if k >= d else 0.0 for k in range(6)])
            for d in range(6)}


def poly_eval(c: np.ndarray, tau: float, deriv: int = 0) -> np.ndarray:
    """Value (deriv 0), velocity (1) or acceleration (2) of a quintic at τ."""
    return (_FALLING[deriv] * float(tau) ** np.maximum(_K - deriv, 0)) @ c


def _normalised(c: np.ndarray, T: float) -> np.ndarray:
    """τ-coefficients → coefficients in u = τ/T ∈ [0, 1]."""
    return c * (T ** np.arange(6))[:, None]


def true_angular_velocity(R0: np.ndarray, rot: np.ndarray, tau: float) -> np.ndarray:
    """Base-frame angular velocity (rad/s) of R(τ) = R0·exp([φ(τ)]×): R(τ)·J_r(φ)·φ̇ (exact, not φ̇)."""
    phi = poly_eval(rot, tau)
    return R0 @ rotvec_to_matrix(phi) @ right_jacobian(phi) @ poly_eval(rot, tau, 1)


def max_angular_speed(R0: np.ndarray, rot: np.ndarray, T: float) -> float:
    """Largest true angular speed ‖ω(τ)‖ over [0, T] (rad/s).

    ‖φ̇‖ bounds it from above (every singular value of J_r is ≤ 1; exact from the critical points of
    ‖φ̇‖²); if that bound is within ``w_max`` nothing more is needed, so the caller passes it first.
    Otherwise: 129 samples, each local maximum refined by a bounded Brent search to 1e-12 s.
    """
    from scipy.optimize import minimize_scalar

    taus = np.linspace(0.0, T, 129)
    speeds = np.array([np.linalg.norm(true_angular_velocity(R0, rot, t)) for t in taus])
    best = float(speeds.max())
    for i in range(len(taus)):
        left = speeds[i - 1] if i > 0 else -1.0
        right = speeds[i + 1] if i + 1 < len(taus) else -1.0
        if speeds[i] >= left and speeds[i] >= right:
            lo, hi = taus[max(i - 1, 0)], taus[min(i + 1, len(taus) - 1)]
            res = minimize_scalar(lambda t: -np.linalg.norm(true_angular_velocity(R0, rot, t)), bounds=(lo, hi),
                                  method="bounded", options={"xatol": 1e-12})
            best = max(best, float(-res.fun))
    return best


@dataclass
class Segment:
    """One quintic segment from t0 to t1 (controller time). ``seg_id`` 0 is HOME."""

    seg_id: int
    t0: float
    t1: float
    pos: np.ndarray  # 6×3 coefficients in τ
    R0: np.ndarray
    rot: np.ndarray  # 6×3 coefficients of φ in τ
    done_reported: bool = False
    commanded: bool = True  # a host's motion (SEG, SEGNOW, HOME), not a stop ramp
    joints: tuple[np.ndarray, np.ndarray] | None = None  # the arm's (times, N×6 configurations) along it

    def sampled(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(controller times, N×4×4 poses) every ≤ ``dt`` seconds over the segment, ends included."""
        ts = sample_times(self.t1 - self.t0, dt)
        powers = ts[:, None] ** _K[None, :]
        return self.t0 + ts, poses(powers @ self.pos, self.R0, powers @ self.rot)

    def position(self, t: float) -> np.ndarray:
        """Flange position (mm) at time t, clamped to the segment."""
        return poly_eval(self.pos, min(max(t - self.t0, 0.0), self.t1 - self.t0))

    def state(self, t: float):
        """(p, v, a, R, ω) at time t, clamped to the segment; ω is the true angular velocity (base frame)."""
        tau = min(max(t - self.t0, 0.0), self.t1 - self.t0)
        p = poly_eval(self.pos, tau)
        v = poly_eval(self.pos, tau, 1)
        a = poly_eval(self.pos, tau, 2)
        R = self.R0 @ rotvec_to_matrix(poly_eval(self.rot, tau))
        w = true_angular_velocity(self.R0, self.rot, tau)
        return p, v, a, R, w


@dataclass
class RuckigSegment:
    """One ``ruckig`` segment from t0 to t1 (controller time): the exact piecewise-cubic plan of
    :func:`labctl.planning.ruckig_profile.plan_ruckig`."""

    seg_id: int
    t0: float
    t1: float
    plan: RuckigPlan
    done_reported: bool = False
    commanded: bool = True
    joints: tuple[np.ndarray, np.ndarray] | None = None  # the arm's (times, N×6 configurations) along it

    def sampled(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(controller times, N×4×4 poses) every ≤ ``dt`` seconds over the segment, ends included."""
        ts = sample_times(self.t1 - self.t0, dt)
        return self.t0 + ts, poses(_piecewise_values(self.plan.position, ts), self.plan.R0,
                                   _piecewise_values(self.plan.rotation, ts))

    @property
    def R0(self) -> np.ndarray:
        """Start rotation (world ← flange)."""
        return self.plan.R0

    def position(self, t: float) -> np.ndarray:
        """Flange position (mm) at time t, clamped to the segment."""
        return self.plan.position.state(min(max(t - self.t0, 0.0), self.t1 - self.t0))[0]

    def state(self, t: float):
        """(p, v, a, R, ω) at time t, clamped to the segment; ω the true angular velocity (base frame)."""
        return self.plan.state(min(max(t - self.t0, 0.0), self.t1 - self.t0))


@dataclass
class StopRamp:
    """The stop ramp (docs/protocols/robot.md §Stopping): from (p, v, R, ω) at t0 each axis brakes at
    constant ``a_stop`` to rest, and the rotation at constant ``alpha`` about its fixed axis (base frame)."""

    t0: float
    p: np.ndarray
    v: np.ndarray
    R: np.ndarray
    w: np.ndarray
    a_stop: float
    alpha: float
    seg_id: int = -1
    done_reported: bool = True
    commanded: bool = False
    joints: tuple[np.ndarray, np.ndarray] | None = None

    def sampled(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(controller times, N×4×4 poses) every ≤ ``dt`` seconds over the ramp, ends included."""
        ts = self.t0 + sample_times(self.t1 - self.t0, dt)
        return ts, np.array([make_T(st[3], st[0]) for st in (self.state(t) for t in ts)])

    def __post_init__(self):
        self.t_axis = np.abs(self.v) / self.a_stop
        self.t_rot = float(np.linalg.norm(self.w)) / self.alpha
        self.t1 = self.t0 + max(float(self.t_axis.max()), self.t_rot)

    def position(self, t: float) -> np.ndarray:
        """Flange position (mm, base frame) at time ``t`` (s) while braking to rest."""
        ta = np.minimum(min(max(t - self.t0, 0.0), self.t1 - self.t0), self.t_axis)
        return self.p + self.v * ta - 0.5 * np.sign(self.v) * self.a_stop * ta * ta

    def state(self, t: float):
        """Position (mm), velocity (mm/s) and rotation at time ``t`` (s) while braking to rest."""
        tau = min(max(t - self.t0, 0.0), self.t1 - self.t0)
        ta = np.minimum(tau, self.t_axis)
        sgn = np.sign(self.v)
        p = self.p + self.v * ta - 0.5 * sgn * self.a_stop * ta * ta
        braking = tau < self.t_axis
        v = np.where(braking, self.v - sgn * self.a_stop * tau, 0.0)
        a = np.where(braking, -sgn * self.a_stop, 0.0)
        wn = float(np.linalg.norm(self.w))
        if wn == 0.0:
            return p, v, a, self.R.copy(), np.zeros(3)
        tr = min(tau, self.t_rot)
        theta = wn * tr - 0.5 * self.alpha * tr * tr
        axis = self.w / wn
        R = rotvec_to_matrix(axis * theta) @ self.R
        w = axis * max(wn - self.alpha * tau, 0.0)
        return p, v, a, R, w


class RobotEmulator:
    """The robot controller: ``receive(data, t)`` request bytes, ``read_output()`` reply bytes.

    ``start_pose`` (``T_base_flange``, default the home pose) is where the flange rests at boot; with an
    ``arm`` the controller speaks 1.3 and its arm starts in the IK solution nearest the arm file's
    ``home_deg`` there, or at ``start_joints`` (rad) when given (a bridge reads them from its arm)."""

    name = NAME
    dialect = DIALECT

    def __init__(self, clock: Callable[[], float], limits: RobotConfig | None = None, *, queue_size: int = QUEUE_SIZE,
                 start_pose: np.ndarray | None = None, arm: ArmServo | None = None,
                 start_joints: np.ndarray | None = None):
        from ...config import RobotConfig

        cfg = limits if limits is not None else RobotConfig()
        self.clock = clock
        self.box_min = np.asarray(cfg.workspace_min_mm, float)
        self.box_max = np.asarray(cfg.workspace_max_mm, float)
        self.v_max = float(cfg.v_max_mm_s)
        self.a_max = float(cfg.a_max_mm_s2)
        self.w_max = math.radians(cfg.w_max_deg_s)
        self.a_stop = self.a_max / math.sqrt(3.0)
        self.alpha_stop = ANGULAR_STOP_PER_S * self.w_max
        j_max = cfg.j_max_mm_s3
        self.j_max = float(j_max) if j_max else JERK_PER_ACCEL * self.a_max  # ruckig profile: LIMITS field 19
        self.watchdog_s = float(cfg.watchdog_s)
        self.home_T = make_T(_rpy(*HOME_RPY), cfg.home_mm)
        self.queue_size = queue_size
        self.now = float(clock())
        if start_joints is not None and arm is not None:  # an arm whose joints are known (a bridge): its pose
            start_pose = arm.model.fk(start_joints)
        T0 = self.home_T if start_pose is None else np.asarray(start_pose, float)
        self._rest_p = T0[:3, 3].copy()
        self._rest_R = T0[:3, :3].copy()
        self.arm = arm
        if arm is not None:
            self.dialect = ARM_DIALECT
            self._rest_q = arm.initial(T0) if start_joints is None else np.asarray(start_joints, float).copy()
        self.arm_check_s = 0.0  # time spent in the arm's segment checks (s), and how many
        self.arm_checks = 0
        self.segments: list = []  # scheduled and recent segments and ramps, in time order
        self._joints_memo: tuple | None = None  # (segment, its t1, its joints, time, configuration) last solved
        self._pose_memo: tuple | None = None  # (segment, its t1, time, T_base_flange) last evaluated
        self.history_s = 600.0
        self.last_request_t = self.now
        self.fault: str | None = None
        self.session = self.dialect  # until a HELLO says otherwise: the strictest behaviour
        self.seg_defaults: dict[str, Any] = {}  # SET (1.4): profile and limits of a segment naming no profile=
        self.held: tuple[int, Request] | None = None  # a SEG hold=1 (1.4): its id and request, run at GO
        self.last_segment_id = 0
        self.watchdog_trips = 0
        self.out = bytearray()
        self._line = bytearray()
        self._overlong = False
        self._write(f"@BOOT {self.name} {self.dialect}\n")

    def power_cycle(self) -> None:
        """Controller reset: the brakes stop the arm where it is; queue, fault and line are lost."""
        self.advance(max(self.now, self.clock()))
        p, _, _, R, _ = self.state_at(self.now)
        if self.arm is not None:
            self._rest_q = self.joints_at(self.now)
        self.segments = []
        self._rest_p, self._rest_R = p, R
        self.fault = None
        self.session = self.dialect
        self.seg_defaults = {}
        self.held = None
        self._line.clear()
        self._overlong = False
        self._write(f"@BOOT {self.name} {self.dialect}\n")

    # --- wire -------------------------------------------------------------------------------
    def _write(self, text: str) -> None:
        """Send lines, each with its ``*HH`` checksum."""
        for line in text.splitlines():
            self.out += (add_checksum(line) + "\n").encode("ascii")

    def read_output(self) -> bytes:
        """Bytes the controller has written since the last call, after advancing it to the clock's time."""
        self.advance(max(self.now, self.clock()))
        data = bytes(self.out)
        self.out.clear()
        return data

    def receive(self, data: bytes, t: float | None = None) -> None:
        """Bytes from the host, received at time ``t`` (s; default the clock's): each complete line is executed."""
        self.advance(max(self.now, self.clock() if t is None else t))
        for b in bytes(data):
            if b == 0x0A:
                line = self._line.decode("ascii", errors="replace")
                overlong = self._overlong
                self._line.clear()
                self._overlong = False
                if overlong:
                    self._write("@ERR E04 line too long\n")
                elif any(c > 0x7E or (c < 0x20 and c != 0x09) for c in line.encode("ascii", "replace")) \
                        or "\ufffd" in line:
                    self._write(f"@ERR E03 {ERROR_CODES[3]}\n")  # only printable ASCII (and tabs) in a line
                elif line.strip():
                    self._handle(line)
            elif b == 0x0D:
                continue  # '\r' is dropped wherever it appears and does not count towards the 240
            elif len(self._line) >= MAX_LINE:
                self._overlong = True
            else:
                self._line.append(b)

    # --- time -------------------------------------------------------------------------------
    def _watchdog_due(self) -> float:
        """Controller time at which the watchdog trips if no valid request arrives before."""
        return self.last_request_t + self.watchdog_s

    def advance(self, t: float) -> None:
        """Run the controller up to time t: segment completions (@DONE), stop ramps and the watchdog."""
        if t <= self.now:
            return
        while True:
            trip = self._watchdog_due()
            pending = [s for s in self.segments if not s.done_reported]
            next_done = min((s.t1 for s in pending), default=math.inf)
            if trip < next_done and trip <= t and self._commanded_at(trip) and self.fault is None:
                self.now = max(self.now, trip)
                self.watchdog_trips += 1
                self._stop_at(self.now)
                self.fault = "watchdog"
                self._write(f"@WATCHDOG {fmt_num(self.watchdog_s)}\n")
                continue
            if next_done <= t:
                self.now = max(self.now, next_done)
                for s in pending:
                    if s.t1 <= next_done:
                        s.done_reported = True
                        self._write(f"@DONE {s.seg_id}\n")
                        _, v, _, _, w = s.state(s.t1)
                        followed = any(o.t0 >= s.t1 and o is not s for o in self.segments)
                        if not followed and (np.linalg.norm(v) > 1e-9 or np.linalg.norm(w) > 1e-9):
                            self._stop_at(s.t1)  # no next segment to carry the end velocity: come to rest
                continue
            break
        self.now = t
        horizon = t - self.history_s
        while len(self.segments) > 1 and self.segments[0].t1 < horizon and self.segments[0].done_reported:
            self.segments.pop(0)

    def _moving_at(self, t: float) -> bool:
        return any(s.t0 <= t < s.t1 or s.t0 > t for s in self.segments)

    def _commanded_at(self, t: float) -> bool:
        """A host's segment runs or waits at t (the watchdog guards these, not a stop ramp)."""
        return any(s.commanded and (s.t0 <= t < s.t1 or s.t0 > t) for s in self.segments)

    @property
    def moving(self) -> bool:
        """The robot is moving at the clock's time (a segment running or braking)."""
        self.advance(max(self.now, self.clock()))
        return self._moving_at(self.now)

    def _segment_at(self, t: float):
        """The last segment started by time t (None before the first)."""
        seg = None
        for s in self.segments:
            if s.t0 <= t:
                seg = s
            else:
                break
        return seg

    def state_at(self, t: float):
        """(p, v, a, R, ω) of the flange at time t (mm, mm/s, mm/s², 3×3, rad/s; ω base frame)."""
        seg = self._segment_at(t)
        if seg is None:
            first = self.segments[0] if self.segments else None
            if first is not None and t < first.t0:
                p, _, _, R, _ = first.state(first.t0)
                return p, np.zeros(3), np.zeros(3), R, np.zeros(3)
            return self._rest_p.copy(), np.zeros(3), np.zeros(3), self._rest_R.copy(), np.zeros(3)
        p, v, a, R, w = seg.state(t)
        if t > seg.t1:  # at rest after the last segment
            v, a, w = np.zeros(3), np.zeros(3), np.zeros(3)
        return p, v, a, R, w

    def position_at(self, t: float) -> np.ndarray:
        """Flange position (mm) at time t: the position part of :meth:`state_at`, cheaply."""
        seg = self._segment_at(t)
        if seg is None:
            return self.state_at(t)[0]
        return seg.position(t)

    def flange_pose_at(self, t: float) -> np.ndarray:
        """``T_base_flange`` (4×4, mm) at time t (exact for t up to now; planned motion beyond)."""
        if t <= self.clock():
            self.advance(max(self.now, t))
        seg = self._segment_at(t)
        memo = self._pose_memo  # a frame asks for its time's pose several times (both cameras, the arm, truth)
        if seg is not None and memo is not None and memo[0] is seg and memo[1] == seg.t1 and memo[2] == t:
            return memo[3].copy()
        p, _, _, R, _ = self.state_at(t)
        T = make_T(R, p)
        if seg is not None:
            self._pose_memo = (seg, seg.t1, t, T.copy())
        return T

    def joints_at(self, t: float) -> np.ndarray:
        """The arm's configuration (6 joints, rad) at controller time ``t``: the segment's sampled joints
        nearest ``t``, solved exactly at its pose there in the same branch (ValueError without an arm)."""
        if self.arm is None:
            raise ValueError("this controller has no arm")
        seg = self._segment_at(t)
        if seg is None or seg.joints is None:
            first = self.segments[0] if self.segments else None
            if seg is None and first is not None and first.joints is not None:
                return first.joints[1][0].copy()
            return self._rest_q.copy()
        tc = min(max(t, seg.t0), seg.t1)
        memo = self._joints_memo  # at rest after a segment (most frames) the answer is the segment's last
        if memo is not None and memo[0] is seg and memo[1] == seg.t1 and memo[2] is seg.joints and memo[3] == tc:
            return memo[4].copy()
        ts, qs = seg.joints
        q_near = np.array([np.interp(tc, ts, qs[:, j]) for j in range(6)])
        p, _, _, R, _ = seg.state(tc)
        q = self.arm.joints(make_T(R, p), q_near)
        self._joints_memo = (seg, seg.t1, seg.joints, tc, q.copy())
        return q

    def configuration_at(self, t: float) -> np.ndarray:
        """:meth:`joints_at` after running the controller up to ``t`` when that is not in the future, as
        :meth:`flange_pose_at` does: the arm the simulated cameras draw (:class:`labctl.sim.arm.ArmBody`)."""
        if t <= self.clock():
            self.advance(max(self.now, t))
        return self.joints_at(t)

    def _arm_check(self, seg, t0: float) -> int:
        """0 if the arm can fly ``seg`` from its configuration at ``t0`` (its joints are then kept on the
        segment), else its 1.3 refusal (:meth:`labctl.sim.emulators.arm_servo.ArmServo.check`)."""
        if self.arm is None:
            return 0
        start = time.perf_counter()
        ts, Ts = seg.sampled(self.arm.policy.check_dt_s)
        code, qs = self.arm.check(ts, Ts, self.joints_at(t0))
        self.arm_check_s += time.perf_counter() - start
        self.arm_checks += 1
        if not code:
            seg.joints = (ts, qs)
        return code

    @property
    def segment_id(self) -> int:
        """Id of the running segment, else of the last one started (0 before any, and for HOME)."""
        sid = 0
        for s in self.segments:
            if s.t0 <= self.now and s.commanded:
                sid = s.seg_id
        return sid

    # --- motion -----------------------------------------------------------------------------
    def _cut_at(self, t: float) -> None:
        """Drop everything scheduled after t (a held segment too); the running segment ends at t (no @DONE)."""
        self.held = None
        kept = []
        for s in self.segments:
            if s.t0 >= t and not (s.t0 == t and s.t1 == t):
                continue
            kept.append(s)
        self.segments = kept
        for s in self.segments:
            if s.t1 > t:
                s.t1 = t
                s.done_reported = True

    def _check(self, seg: Segment, p0: np.ndarray) -> int:
        """0 if the segment may run, else its error code, first of E12, E13, E14, E10 (box: path, stop ramp).

        The dynamic limits come first: a segment the arm cannot follow has no meaningful stop point.

        The box is grown to hold the start point ``p0`` and its braking rest point (an arm outside, or
        heading out, may move back but not further out); the end point and its braking rest point must
        lie in the box itself. All maxima exact.
        """
        T = seg.t1 - seg.t0
        b = _normalised(seg.pos, T)
        if _norm_max(_derivative(b)) / T > self.v_max * (1 + REL_TOL):
            return 12
        if _norm_max(_derivative(_derivative(b))) / T ** 2 > self.a_max * (1 + REL_TOL):
            return 13
        limit = self.w_max * (1 + REL_TOL)
        if _norm_max(_derivative(_normalised(seg.rot, T))) / T > limit:  # ‖φ̇‖ ≥ ‖ω‖: only then look closer
            if max_angular_speed(seg.R0, seg.rot, T) > limit:
                return 14
        v0 = poly_eval(seg.pos, 0.0, 1)
        e0 = p0 + v0 * np.abs(v0) / (2 * self.a_stop)
        lo_box = np.minimum(np.minimum(self.box_min, p0), e0) - BOX_TOL_MM
        hi_box = np.maximum(np.maximum(self.box_max, p0), e0) + BOX_TOL_MM
        lo, hi = _poly_range(b)
        if np.any(lo < lo_box) or np.any(hi > hi_box):
            return 10
        p1 = poly_eval(seg.pos, T)
        if np.any(p1 < self.box_min - BOX_TOL_MM) or np.any(p1 > self.box_max + BOX_TOL_MM):
            return 10
        return 10 if self._stop_leaves_box(seg, b, lo_box, hi_box) else 0

    def _check_ruckig(self, plan: RuckigPlan, lim: JerkLimits) -> int:
        """0 if a ruckig segment may run, else its error code (:func:`labctl.planning.ruckig_profile.check_ruckig`:
        the quintic's rules, exactly, on each cubic interval)."""
        return check_ruckig(plan, lim)

    def _stop_leaves_box(self, seg: Segment, b: np.ndarray, lo_box: np.ndarray, hi_box: np.ndarray) -> bool:
        """Would the stop ramp from some instant of the segment end outside (grown box), or from its end
        outside the box itself? Exact (:func:`labctl.planning.safety.stop_envelope_range`)."""
        T = seg.t1 - seg.t0
        elo, ehi = stop_envelope_range(b, T, self.a_stop)
        if np.any(elo < lo_box) or np.any(ehi > hi_box):
            return True
        p1, v1 = poly_eval(seg.pos, T), poly_eval(seg.pos, T, 1)
        rest = p1 + v1 * np.abs(v1) / (2 * self.a_stop)
        return bool(np.any(rest < self.box_min - BOX_TOL_MM) or np.any(rest > self.box_max + BOX_TOL_MM))

    def _plan(self, seg_id: int, p1, R1, T: float, v1, w1, t0: float, start) -> Segment:
        """The quintic from ``start`` = (p, v, a, R, ω) at t0 to (p1, v1, 0; R1, w1) at t0 + T.

        φ̇(0) = R0ᵀω0 and φ̇(T) = J_r(φ1)⁻¹R1ᵀw1 make the true angular velocity exact at both ends."""
        p0, v0, a0, R0, w0 = start
        pos = quintic_coeffs(p0, v0, a0, p1, v1, np.zeros(3), T)
        phi1 = matrix_to_rotvec(R0.T @ R1)
        R1 = R0 @ rotvec_to_matrix(phi1)
        phidot1 = np.linalg.solve(right_jacobian(phi1), R1.T @ np.asarray(w1, float))
        rot = quintic_coeffs(np.zeros(3), R0.T @ w0, np.zeros(3), phi1, phidot1, np.zeros(3), T)
        return Segment(seg_id, t0, t0 + T, pos, R0, rot)

    def _make_ramp(self, t: float, p, v, R, w) -> StopRamp:
        return StopRamp(t, np.asarray(p, float), np.asarray(v, float), R, np.asarray(w, float), self.a_stop,
                        self.alpha_stop)

    def _stop_at(self, t: float) -> None:
        """Brake from the state at t (the documented stop ramp); the queue is discarded."""
        p, v, _, R, w = self.state_at(t)
        q0 = self.joints_at(t) if self.arm is not None else None
        self._cut_at(t)
        if np.linalg.norm(v) > 0.0 or np.linalg.norm(w) > 0.0:
            ramp = self._make_ramp(t, p, v, R, w)
            if self.arm is not None and q0 is not None:  # a stop is never refused: the arm follows it as best it can
                ts, Ts = ramp.sampled(self.arm.policy.check_dt_s)
                ramp.joints = (ts, self.arm.check(ts, Ts, q0)[1])
            self.segments.append(ramp)

    # --- commands ---------------------------------------------------------------------------
    def _reply(self, seq: int, fields: str = "") -> None:
        self._write(f"${seq} ok{(' ' + fields) if fields else ''}\n")

    def _error(self, seq: int, code: int) -> None:
        self._write(f"${seq} E{code:02d} {ERROR_CODES.get(code, 'error')}\n")

    def _parse_line(self, line: str) -> Request | int:
        return parse_request(line)

    def _handle(self, line: str) -> None:
        req = self._parse_line(line)
        if isinstance(req, int):
            seq = line.strip()[1:].split(" ", 1)[0] if line.strip().startswith("#") else ""
            if req == 5 and seq.isdigit() and len(seq) <= 5 and int(seq) <= 65535:
                self._error(int(seq), 5)  # the sender learns at once that its line was damaged
            else:
                self._write(f"@ERR E{req:02d} {ERROR_CODES[req]}\n")
            return
        self.last_request_t = self.now  # any request answered with its $seq (not E05) feeds the watchdog
        handler = getattr(self, "_cmd_" + req.command.lower(), None) if req.command.isalpha() else None
        if handler is None:
            self._error(req.seq, 1)
            return
        handler(req)

    def _no_args(self, req: Request) -> bool:
        if req.args:
            self._error(req.seq, 2)
            return False
        return True

    def _cmd_hello(self, req: Request) -> None:
        """``HELLO [version]``: the session speaks the lower of the host's version (1.0 when it names
        none: a 1.0 host) and the controller's; the reply names that version."""
        if len(req.args) > 1 or (req.args and not _VERSION.match(req.args[0])):
            self._error(req.seq, 2)
            return
        host = tuple(int(x) for x in req.args[0].split(".")) if req.args else (1, 0)
        mine = tuple(int(x) for x in self.dialect.split("."))
        session = min(host, mine)
        if session == (1, 3) and self.arm is None:  # 1.3 is the arm's: without one a 1.3 host gets 1.2's text
            session = (1, 2)
        self.session = ".".join(str(x) for x in session)
        self.seg_defaults = {}  # every HELLO starts a session without segment defaults (SET, 1.4)
        self.held = None
        fields = f"{self.name} {self.session} queue={self.queue_size}"
        if self.session != "1.0":  # the 1.0 reply ends at queue= (docs/protocols/robot.md §1)
            fields += f" profiles={','.join(self._profiles())}"
        if self._arm_session:
            fields += f" arm={self.arm.model.name}"  # type: ignore[union-attr]
        self._reply(req.seq, fields)

    @property
    def _arm_session(self) -> bool:
        """This session speaks 1.3 (the controller has an arm and the host speaks 1.3 or later)."""
        return self.arm is not None and tuple(int(x) for x in self.session.split(".")) >= (1, 3)

    def _profiles(self) -> tuple[str, ...]:
        """The profiles of this session: ``ruckig`` from dialect 1.2 on."""
        return PROFILES_BEFORE.get(self.session, PROFILES)

    def _cmd_hb(self, req: Request) -> None:
        if self._no_args(req):
            self._reply(req.seq)

    def _cmd_set(self, req: Request) -> None:
        """``SET [profile=P] [vmax= amax= jmax= wmax=]`` (1.4): the segment defaults of this session, replacing
        the previous ones (a bare ``SET``: quintic, as before any SET); a SEG or SEGNOW that names no
        ``profile=`` runs them. Limits only with ``profile=ruckig``, each at most the controller's (E16)."""
        if tuple(int(x) for x in self.session.split(".")) < (1, 4):
            self._error(req.seq, 1)  # an older session has no SET: exactly an older controller's answer
            return
        opts: dict[str, Any] = {}
        for word in req.args:
            key, eq, value = word.partition("=")
            key = key.lower()
            if not eq or key in opts or key not in ("profile", *LIMIT_KEYS):
                self._error(req.seq, 2)
                return
            if key == "profile":
                opts[key] = value.lower()
                continue
            number = parse_number(value)
            if number is None or number <= 0:
                self._error(req.seq, 2)
                return
            opts[key] = number
        profile = opts.setdefault("profile", "quintic")
        if profile != "ruckig" and len(opts) > 1:
            self._error(req.seq, 2)
            return
        if code := self._profile_refusal(profile, opts):
            self._error(req.seq, code)
            return
        self.seg_defaults = opts
        self._reply(req.seq)

    def _profile_refusal(self, profile: str, opts: dict[str, Any]) -> int:
        """0, or the error a segment's (or ``SET``'s) profile and limits get: E15 a profile this dialect has
        not, E16 limits above the controller's own."""
        if profile not in self._profiles():
            return 15
        return 16 if self._over_limits(opts) else 0

    def _over_limits(self, opts: dict[str, Any]) -> bool:
        """A segment limit (vmax amax jmax wmax in ``opts``) above the controller's own (E16)."""
        mine = {"vmax": self.v_max, "amax": self.a_max, "jmax": self.j_max, "wmax": math.degrees(self.w_max)}
        return any(opts.get(k, 0.0) > mine[k] * (1 + REL_TOL) for k in LIMIT_KEYS)

    def _cmd_clear(self, req: Request) -> None:
        if self._no_args(req):
            self.fault = None
            self._reply(req.seq)

    def _cmd_stop(self, req: Request) -> None:
        if not self._no_args(req):
            return
        self._stop_at(self.now)
        if self.fault is None and self.session != "1.0":  # a 1.0 host does not know it must CLEAR
            self.fault = "stopped"
        self._reply(req.seq)

    def _cmd_limits(self, req: Request) -> None:
        if not self._no_args(req):
            return
        home = [*self.home_T[:3, 3], *canonical_rotvec(matrix_to_rotvec(self.home_T[:3, :3]))]
        vals = [*self.box_min, *self.box_max, self.v_max, self.a_max, math.degrees(self.w_max), self.watchdog_s,
                self.a_stop, math.degrees(self.alpha_stop), *home]
        if self.session == "1.0":  # the 1.0 text's ten fields
            vals = vals[:10]
        if self.session not in PROFILES_BEFORE:  # 1.2: field 19, the jerk limit of the ruckig profile
            vals.append(self.j_max)
        self._reply(req.seq, " ".join(fmt_num(v) for v in vals))

    def _cmd_status(self, req: Request) -> None:
        if not self._no_args(req):
            return
        p, _, _, R, _ = self.state_at(self.now)
        rv = canonical_rotvec(matrix_to_rotvec(R))
        moving = 1 if self._moving_at(self.now) else 0
        queued = sum(1 for s in self.segments if s.t0 > self.now and s.commanded)
        fault = self.fault or "none"
        joints = ""
        if self._arm_session:  # 1.3: the six joint angles, degrees
            joints = " " + " ".join(fmt_fixed(math.degrees(q), JOINT_DECIMALS) for q in self.joints_at(self.now))
        self._reply(req.seq, " ".join(fmt_fixed(v) for v in (*p, *rv))
                    + f" {moving} {self.segment_id} {queued} {fmt_fixed(self.now)} {fault}{joints}")

    def _fault_code(self) -> int:
        return 40 if self.fault == "watchdog" else 41

    def _cmd_home(self, req: Request) -> None:
        if not self._no_args(req):
            return
        if self.fault:
            self._error(req.seq, self._fault_code())
            return
        self._stop_at(self.now)  # brake first (if moving); home starts where the arm comes to rest
        t0 = max([self.now, *(s.t1 for s in self.segments)])
        p0, _, _, R0, _ = self.state_at(t0)
        d = float(np.linalg.norm(self.home_T[:3, 3] - p0))
        theta = float(np.linalg.norm(matrix_to_rotvec(R0.T @ self.home_T[:3, :3])))
        # a rest-to-rest quintic peaks at 1.875·d/T in speed and 10/√3·d/T² in acceleration
        T = max(HOME_MIN_S, 1.875 * d / (0.5 * self.v_max), math.sqrt(10 / math.sqrt(3) * d / (0.5 * self.a_max)),
                1.875 * theta / (0.5 * self.w_max))
        seg = self._plan(0, self.home_T[:3, 3], self.home_T[:3, :3], T, np.zeros(3), np.zeros(3), t0,
                         (p0, np.zeros(3), np.zeros(3), R0, np.zeros(3)))
        code = self._check(seg, p0) or self._arm_check(seg, t0)
        if code:  # box: cannot happen (a straight rest-to-rest move into the box); the arm: it can
            self._error(req.seq, code)
            return
        self.segments.append(seg)
        self._reply(req.seq, f"{fmt_fixed(seg.t0)} {fmt_fixed(seg.t1)}")

    def _parse_segment(self, req: Request):
        """(id, numbers, options) or an error code. Options are the trailing ``key=value`` words:
        ``profile=`` (1.1); ``vmax= amax= jmax= wmax=`` (1.2, ruckig only: the segment's own limits, mm/s,
        mm/s², mm/s³, deg/s); 17 numbers (with the end acceleration) only for ruckig."""
        args = list(req.args)
        opts: dict[str, Any] = {}  # profile (str); vmax= amax= jmax= wmax= (str, float once parsed)
        while args and "=" in args[-1]:
            key, _, value = args.pop().partition("=")
            key = key.lower()
            older = key != "profile" and self.session in PROFILES_BEFORE  # limits are 1.2's
            if key == "hold":  # 1.4: SEG only, hold=1
                older = value != "1" or tuple(int(x) for x in self.session.split(".")) < (1, 4)
            if key in opts or key not in ("profile", "hold", *LIMIT_KEYS) or older:
                return 2
            opts[key] = value.lower() if key == "profile" else value
        default = "profile" not in opts and self.seg_defaults  # 1.4: no profile= runs the session's SET
        if default and any(k in opts for k in LIMIT_KEYS):
            return 2  # limits belong to a named profile or to SET
        opts.setdefault("profile", "quintic")
        ruckig = (self.seg_defaults["profile"] if default else opts["profile"]) == "ruckig"
        if len(args) not in ((8, 14, 17) if ruckig else (8, 14)):
            return 2
        for key in LIMIT_KEYS:
            if key in opts:
                number = parse_number(opts[key])
                if not ruckig or number is None or number <= 0:
                    return 2
                opts[key] = number
        if default:
            opts = {**self.seg_defaults, **({"hold": opts["hold"]} if "hold" in opts else {})}
        lowest = 0 if self.session == "1.0" else 1  # 1.1 reserves id 0 for HOME
        if not args[0].isdigit() or not lowest <= int(args[0]) <= 65535:
            return 2
        vals = [parse_number(a) for a in args[1:]]
        if any(v is None for v in vals):
            return 2
        return int(args[0]), vals, opts

    def _cmd_seg(self, req: Request, replace: bool = False) -> None:
        parsed = self._parse_segment(req)
        if isinstance(parsed, int):
            self._error(req.seq, parsed)
            return
        seg_id, vals, opts = parsed
        profile = opts["profile"]
        if self.fault:
            self._error(req.seq, self._fault_code())
            return
        if opts.pop("hold", None) is not None:  # 1.4: kept, not planned, until GO (a SEGNOW cannot hold)
            if replace:
                self._error(req.seq, 2)
                return
            self.held = (seg_id, Request(req.seq, req.command, tuple(a for a in req.args if a.lower() != "hold=1")))
            self._reply(req.seq)
            return
        T = vals[6]
        # ruckig: T is the least duration, 0 = as fast as the limits allow
        if not ((0.0 <= T if profile == "ruckig" else 0.0 < T) and T <= MAX_DURATION_S):
            self._error(req.seq, 11)
            return
        if code := self._profile_refusal(profile, opts):
            self._error(req.seq, code)
            return
        p1 = np.array(vals[0:3])
        R1 = rotvec_to_matrix(np.array(vals[3:6]))
        v1 = np.array(vals[7:10]) if len(vals) >= 13 else np.zeros(3)
        w1 = np.array(vals[10:13]) if len(vals) >= 13 else np.zeros(3)
        a1 = np.array(vals[13:16]) if len(vals) == 16 else np.zeros(3)
        ruckig = (self.jerk_limits(**{k: opts.get(k) for k in LIMIT_KEYS}), a1) if profile == "ruckig" else None
        self._queue_segment(req.seq, seg_id, p1, R1, T, v1, w1, replace=replace, ruckig=ruckig)

    def _cmd_go(self, req: Request) -> None:
        """``GO id`` (1.4): run the held segment ``id`` now, as if its ``SEG`` (without ``hold=1``) arrived now:
        queued behind what runs, checked, answered ``t0 t1`` or its refusal; E21 if none is held by that id."""
        if tuple(int(x) for x in self.session.split(".")) < (1, 4):
            self._error(req.seq, 1)
            return
        if len(req.args) != 1 or not req.args[0].isdigit():
            self._error(req.seq, 2)
            return
        if self.fault:
            self._error(req.seq, self._fault_code())
            return
        if self.held is None or self.held[0] != int(req.args[0]):
            self._error(req.seq, 21)
            return
        held = self.held[1]
        self.held = None
        self._cmd_seg(Request(req.seq, held.command, held.args))

    def _cmd_segnow(self, req: Request) -> None:
        self._cmd_seg(req, replace=True)

    def jerk_limits(self, vmax=None, amax=None, jmax=None, wmax=None) -> JerkLimits:
        """The limits a ruckig segment runs under: the segment's own (mm/s, mm/s², mm/s³, deg/s; at most
        the controller's) or the controller's; angular acceleration ``alpha_stop`` (LIMITS field 12)."""
        return JerkLimits(self.v_max if vmax is None else vmax, self.a_max if amax is None else amax,
                          self.j_max if jmax is None else jmax, self.w_max if wmax is None else math.radians(wmax),
                          self.alpha_stop, self.box_min, self.box_max, self.a_stop)

    def _queue_segment(self, seq, seg_id, p1, R1, T, v1, w1, replace: bool, ruckig=None) -> None:
        if replace:
            t0 = self.now
            start = self.state_at(t0)
        else:
            queued = sum(1 for s in self.segments if s.t0 > self.now)
            if queued >= self.queue_size:
                self._error(seq, 20)
                return
            last = max((s.t1 for s in self.segments), default=-math.inf)
            t0 = max(self.now, last)
            start = self._end_state() if last > self.now else self.state_at(self.now)
        seg: Segment | RuckigSegment | None
        if ruckig is not None:
            lim, a1 = ruckig
            plan = plan_ruckig(start, p1, R1, v1, w1, a1, T, lim)
            code = self._check_ruckig(plan, self.jerk_limits())  # safety: the controller's own limits
            seg = RuckigSegment(seg_id, t0, t0 + plan.duration, plan) if not code else None
        else:
            seg = self._plan(seg_id, p1, R1, T, v1, w1, t0, start)
            code = self._check(seg, start[0])
        if not code:
            code = self._arm_check(seg, t0)
        if code:
            self._error(seq, code)
            return
        seg = cast("Segment | RuckigSegment", seg)  # no error code: the segment was made
        if replace:
            self._cut_at(t0)
        self.segments.append(seg)
        self.last_segment_id = seg_id
        self._reply(seq, f"{fmt_fixed(seg.t0)} {fmt_fixed(seg.t1)}")

    def _end_state(self):
        last = max(self.segments, key=lambda s: s.t1)
        p, v, a, R, w = last.state(last.t1)
        return p, v, (a if isinstance(last, RuckigSegment) else np.zeros(3)), R, w


def _piecewise_values(pw, ts: np.ndarray) -> np.ndarray:
    """Values (N×D) of a :class:`labctl.planning.ruckig_profile.Piecewise` at the times ``ts`` (s, clamped)."""
    ts = np.clip(ts, 0.0, pw.duration)
    k = np.clip(np.searchsorted(pw.breaks, ts, side="right") - 1, 0, len(pw.coeffs) - 1)
    h = (ts - pw.breaks[k])[:, None]
    c = pw.coeffs[k]
    return c[:, 0] + h * (c[:, 1] + h * (c[:, 2] + h * c[:, 3]))


def _rpy(rx: float, ry: float, rz: float) -> np.ndarray:
    from ...geometry import rot_x, rot_y, rot_z

    return rot_z(rz) @ rot_y(ry) @ rot_x(rx)
