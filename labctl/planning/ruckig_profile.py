"""The ``ruckig`` segment profile of the robot dialect 1.2 (docs/protocols/robot.md §5).

One segment is the time-optimal jerk-limited trajectory (ruckig, Berscheid & Kröger 2021) from
the controller's current state to a target state, in six degrees of freedom: the flange position
``p`` (3, mm) and the rotation vector ``φ`` of ``R(τ) = R0·exp([φ(τ)]×)`` (3, rad) relative to the
start rotation ``R0`` — the same orientation parametrisation as the quintic profile. Both the
controller (:mod:`labctl.sim.emulators.robot`) and the host's planner
(:mod:`labctl.planning.ruckig_interception`) build the segment with :func:`plan_ruckig`, so the
host knows exactly what the controller will run, and both check it with :func:`check_ruckig`.

**Per-axis limits from the direction of travel.** ruckig limits each degree of freedom on its own,
while the dialect limits the Euclidean norms ‖v‖ ≤ vmax and ‖a‖ ≤ amax. Each part (position,
rotation) gets per-axis shares ``s`` with ‖s‖ = 1 (:func:`axis_shares`): ``s_i ∝ max(|d_i|/‖d‖,
|v0_i|/vmax, |a0_i|/amax, |v1_i|/vmax, |a1_i|/amax, 0.001)`` (d = target − start; the start and end
velocities and accelerations count so that an axis already moving is not starved), and axis i is
limited to ``vmax·s_i``, ``amax·s_i``, ``jmax·s_i`` (rotation: ``wmax·s_i``, ``alpha·s_i``,
``alpha·jmax/amax·s_i``, alpha the controller's angular braking deceleration). As ‖s‖ = 1, any
motion within the per-axis limits is within the norm limits. ruckig is asked for *phase*
synchronisation: whenever the start and end states are parallel to d (every rest-to-rest move,
every splice along the line of travel) s = |d|/‖d‖ and all axes follow one 1-D profile along the
straight line — exactly the 1-D time-optimal move under the norm limits. Otherwise (a splice
across the line of travel, or a rare case where ruckig's phase synchronisation fails and *time*
synchronisation is used instead) the axes are synchronised in time only; the motion is then
within the limits but not time-optimal in the norm sense. :func:`check_ruckig` still checks the
norms exactly (an axis braking from above its share — ruckig's brake pre-phase — is the one case
the shares do not bound).

**Exact checks.** Every degree of freedom of a ruckig trajectory is piecewise cubic in time
(constant jerk per phase; an optional brake pre-phase; constant acceleration after its own
profile ends). :func:`pieces` merges all breakpoints, so on each interval every coordinate is one
cubic; each interval is checked as the controller checks a quintic — speed, acceleration,
‖φ̇‖ (≥ ‖ω‖) from the critical points of the polynomials, the path and the stop-ramp rest point
``p + v|v|/(2 a_stop)`` from the same candidates as :func:`labctl.planning.safety.stop_envelope_range`
(closed form here: v is quadratic, a linear) — so the same box rules hold (E10, the grown box of
the start). Units: mm, s, rad.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from .limits import ANGULAR_STOP_PER_S
from .quintic import _poly_range
from .rotation import exp_so3, log_so3, right_jacobian

#: default jerk limit per unit of a_max (1/s): 20·a_max per second (60 000 mm/s³ at a_max 3000) — within
#: what the paper's quintics already ask of the arm on the run's legs (their peak jerk, 60·d/T³ at the
#: fastest T, is 31 000–73 000 mm/s³ for 500–90 mm legs at a_max 2940: docs/notes/planning.md)
JERK_PER_ACCEL = 20.0
FLOOR = 1e-3  # smallest per-axis share of a norm limit (ruckig needs positive limits)
REL_TOL = 1e-6  # relative slack on rates (round-off of a state spliced right at a limit), as for quintics
BOX_TOL_MM = 1e-6
MAX_DURATION_S = 60.0
MIN_PIECE_S = 1e-12


@dataclass(frozen=True)
class JerkLimits:
    """Norm limits of one ruckig segment: linear (mm/s, mm/s², mm/s³), angular (rad/s, rad/s², rad/s³),
    the per-axis braking deceleration ``a_stop`` (mm/s²) and the workspace box (mm)."""

    v_max: float
    a_max: float
    j_max: float
    w_max: float
    alpha_max: float
    box_min: np.ndarray
    box_max: np.ndarray
    a_stop: float

    @property
    def jw_max(self) -> float:
        """Angular jerk limit (rad/s³): the angular acceleration limit scaled as jerk is to acceleration."""
        return self.alpha_max * self.j_max / self.a_max

    @classmethod
    def from_limits(cls, limits, j_max: float | None = None, alpha_max: float | None = None,
                    a_stop: float | None = None) -> JerkLimits:
        """From :class:`labctl.planning.limits.Limits`; ``j_max`` defaults to 20·a_max per second,
        ``alpha_max`` to 4·w_max per second (the reference controller's angular braking) and ``a_stop``
        to the limits' own (a_max/√3; pass the controller's when ``limits`` are a planner's reduced ones)."""
        return cls(float(limits.v_max), float(limits.a_max),
                   float(j_max if j_max is not None else JERK_PER_ACCEL * limits.a_max), float(limits.w_max),
                   float(alpha_max if alpha_max is not None else ANGULAR_STOP_PER_S * limits.w_max),
                   np.asarray(limits.box_min, float), np.asarray(limits.box_max, float),
                   float(a_stop if a_stop is not None else limits.a_stop))

    def slowed(self, r: float) -> JerkLimits:
        """The limits of this segment's motion time-scaled by ``r`` ≥ 1 (a/r², j/r³; speeds unchanged, they
        are caps): what slows a segment's accelerations by r² where stretching its duration alone need not
        (a longer ruckig segment may still accelerate at the limit, then cruise slower)."""
        return replace(self, a_max=self.a_max / r ** 2, j_max=self.j_max / r ** 3)

    def _values(self) -> dict[str, float]:
        return {"vmax": self.v_max, "amax": self.a_max, "jmax": self.j_max, "wmax": math.degrees(self.w_max)}

    def wire(self, base: JerkLimits | None = None) -> dict[str, float]:
        """The limits as a segment carries them (docs/protocols/robot.md §5, ``profile=ruckig``):
        ``vmax amax jmax`` (mm/s, mm/s², mm/s³) and ``wmax`` (deg/s), each rounded *down* to 0.1 — only
        those that differ from the controller's own ``base`` (short lines: 9600 bps). Plan with
        :meth:`rounded` so the host's plan is the controller's."""
        mine, theirs = self._values(), (base._values() if base is not None else {})
        return {k: _down(v) for k, v in mine.items() if k not in theirs or abs(v - theirs[k]) > 1e-9 * max(v, 1.0)}

    def rounded(self, base: JerkLimits | None = None) -> JerkLimits:
        """These limits as the controller runs them after :meth:`wire` (``base``: its own, for the rest)."""
        w = {**self._values(), **self.wire(base)}
        return JerkLimits(w["vmax"], w["amax"], w["jmax"], math.radians(w["wmax"]), self.alpha_max, self.box_min,
                          self.box_max, self.a_stop)


class ControllerLimitsConfig(Protocol):
    """The robot limits :func:`controller_limits` reads (as :class:`labctl.config.devices.RobotConfig` has them)."""

    @property
    def workspace_min_mm(self) -> Sequence[float]:
        """Lower corner of the workspace box (mm)."""

    @property
    def workspace_max_mm(self) -> Sequence[float]:
        """Upper corner of the workspace box (mm)."""

    @property
    def v_max_mm_s(self) -> float:
        """Speed limit (mm/s)."""

    @property
    def a_max_mm_s2(self) -> float:
        """Acceleration limit (mm/s²)."""

    @property
    def w_max_deg_s(self) -> float:
        """Angular speed limit (deg/s)."""

    @property
    def j_max_mm_s3(self) -> float | None:
        """Jerk limit of ruckig segments (mm/s³); None: 20·a_max per second."""


def controller_limits(robot_cfg: ControllerLimitsConfig) -> JerkLimits:
    """A controller's own ruckig limits from its :class:`labctl.config.devices.RobotConfig` (LIMITS fields 7–9,
    11, 12, 19): vmax, amax, ``j_max_mm_s3`` (default 20·amax per second), wmax, angular acceleration
    4·wmax per second (the reference's angular braking), a_stop = amax/√3 and the box."""
    a = float(robot_cfg.a_max_mm_s2)
    j = robot_cfg.j_max_mm_s3
    w = math.radians(float(robot_cfg.w_max_deg_s))
    return JerkLimits(float(robot_cfg.v_max_mm_s), a, float(j) if j else JERK_PER_ACCEL * a, w, ANGULAR_STOP_PER_S * w,
                      np.asarray(robot_cfg.workspace_min_mm, float), np.asarray(robot_cfg.workspace_max_mm, float),
                      a / math.sqrt(3.0))


def _down(x: float) -> float:
    """``x`` rounded down to 0.1 (a limit on the wire never exceeds the planner's)."""
    return math.floor(float(x) * 10.0 + 1e-9) / 10.0


def axis_shares(d, *rates) -> np.ndarray:
    """Per-axis shares ``s`` (‖s‖ = 1) of a norm limit: ``s_i ∝ max(|d_i|/‖d‖, |r_i| for r in rates, FLOOR)``.

    ``d``: displacement (any unit); ``rates``: start/end velocities and accelerations already divided by
    their norm limits (dimensionless). For d and rates parallel with ‖rate‖ ≤ 1 this is |d|/‖d‖ (up to
    the floor)."""
    d = np.asarray(d, float)
    n = float(np.linalg.norm(d))
    raw = np.abs(d) / n if n > 1e-9 else np.zeros(3)
    for r in rates:
        raw = np.maximum(raw, np.abs(np.asarray(r, float)))
    raw = np.maximum(raw, FLOOR)
    return raw / float(np.linalg.norm(raw))


@dataclass(frozen=True)
class Piecewise:
    """Piecewise cubics in time: ``breaks`` (K+1,) seconds from the segment's start, ``coeffs`` (K, 4, D)
    ascending in the local time τ − breaks[k] (position, then /1, /2, /6 of v, a, j)."""

    breaks: np.ndarray
    coeffs: np.ndarray

    @property
    def duration(self) -> float:
        """Length (s) of the piecewise trajectory."""
        return float(self.breaks[-1])

    def state(self, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(value, first, second derivative) at τ (s), clamped to [0, duration]."""
        tau = min(max(float(tau), 0.0), self.duration)
        k = min(max(int(np.searchsorted(self.breaks, tau, side="right")) - 1, 0), len(self.coeffs) - 1)
        h = tau - self.breaks[k]
        c = self.coeffs[k]
        p = c[0] + h * (c[1] + h * (c[2] + h * c[3]))
        v = c[1] + h * (2 * c[2] + 3 * h * c[3])
        a = 2 * c[2] + 6 * h * c[3]
        return p, v, a


def _dof_phases(profile) -> list[tuple[float, float, float, float, float]]:
    """One degree of freedom's phases ``(duration, p, v, a, j)`` in time order: brake pre-phase, accel
    pre-phase, the seven jerk phases (ruckig's ``Profile``, the order ``Trajectory.at_time`` uses)."""
    out = []
    for pre in (profile.brake, profile.accel):
        if pre.duration > 0:
            for i in range(len(pre.t)):
                if pre.t[i] > 0:
                    out.append((pre.t[i], pre.p[i], pre.v[i], pre.a[i], pre.j[i]))
    for i in range(7):
        if profile.t[i] > 0:
            out.append((profile.t[i], profile.p[i], profile.v[i], profile.a[i], profile.j[i]))
    return out


def pieces(traj, dofs: int) -> Piecewise:
    """The ruckig ``Trajectory`` as exact piecewise cubics over [0, duration] (all DoFs on merged breaks).

    After a DoF's own phases end it continues at constant acceleration (jerk 0), as
    ``Trajectory.at_time`` does."""
    T = float(traj.duration)
    per_dof = []
    cuts = {0.0, T}
    for d in range(dofs):
        prof = traj.profiles[0][d]
        t, rows = 0.0, []
        for dur, p, v, a, j in _dof_phases(prof):
            rows.append((t, p, v, a, j))
            t += dur
            if t < T:
                cuts.add(t)
        rows.append((t, prof.p[-1], prof.v[-1], prof.a[-1], 0.0))  # after its own profile
        per_dof.append(rows)
    breaks = np.array(sorted(c for c in cuts if 0.0 <= c <= T))
    keep = np.concatenate([[True], np.diff(breaks) > MIN_PIECE_S])
    breaks = breaks[keep]
    breaks[-1] = T
    if len(breaks) < 2:
        breaks = np.array([0.0, max(T, 0.0)])
    coeffs = np.zeros((len(breaks) - 1, 4, dofs))
    for d, rows in enumerate(per_dof):
        starts = np.array([r[0] for r in rows])
        for k in range(len(breaks) - 1):
            i = max(int(np.searchsorted(starts, breaks[k] + 0.5 * MIN_PIECE_S, side="right")) - 1, 0)
            t0, p, v, a, j = rows[i]
            h = breaks[k] - t0
            coeffs[k, 0, d] = p + h * (v + h * (a / 2 + h * j / 6))
            coeffs[k, 1, d] = v + h * (a + h * j / 2)
            coeffs[k, 2, d] = (a + h * j) / 2
            coeffs[k, 3, d] = j / 6
    return Piecewise(breaks, coeffs)


@dataclass(frozen=True)
class RuckigPlan:
    """A planned ruckig segment: position and φ pieces, the start rotation R0 (world ← flange) and
    the target rotation R1, duration (s). ``code`` 0 if ruckig found it, else the dialect's error."""

    pos: Piecewise | None
    rot: Piecewise | None
    R0: np.ndarray
    R1: np.ndarray
    duration: float
    code: int = 0

    @property
    def position(self) -> Piecewise:
        """The position pieces (mm); ValueError for a plan ruckig did not find (``code`` ≠ 0)."""
        if self.pos is None:
            raise ValueError(f"no ruckig trajectory (E{self.code:02d})")
        return self.pos

    @property
    def rotation(self) -> Piecewise:
        """The φ pieces (rad); ValueError for a plan ruckig did not find (``code`` ≠ 0)."""
        if self.rot is None:
            raise ValueError(f"no ruckig trajectory (E{self.code:02d})")
        return self.rot

    def state(self, tau: float):
        """(p, v, a, R, ω) at τ (s): ω the true angular velocity R·J_r(φ)·φ̇ (base frame)."""
        p, v, a = self.position.state(tau)
        phi, dphi, _ = self.rotation.state(tau)
        R = self.R0 @ exp_so3(phi)
        return p, v, a, R, R @ right_jacobian(phi) @ dphi


class _Solver:
    """Cached ruckig objects (allocation is the slow part), one set per process."""

    _inst: _Solver | None = None

    def __init__(self):
        from ruckig import InputParameter, Result, Ruckig, RuckigError, Synchronization, Trajectory

        self.otg = Ruckig(6)
        self.inp = InputParameter(6)
        self.Sync = Synchronization
        self.Error = RuckigError
        self.Trajectory = Trajectory
        self.ok = (Result.Working, Result.Finished)

    @classmethod
    def get(cls) -> _Solver:
        if cls._inst is None:
            cls._inst = _Solver()
        return cls._inst


def plan_ruckig(start, p1, R1, v1, w1, a1, T_min: float, lim: JerkLimits, *, full: bool = True) -> RuckigPlan:
    """The ruckig segment from ``start = (p0, v0, a0, R0, ω0)`` (mm, mm/s, mm/s², 3×3, rad/s base frame)
    to the target pose (``p1``, ``R1``) with end velocity ``v1``, angular velocity ``w1`` (base frame),
    end acceleration ``a1``, lasting at least ``T_min`` s (0: as fast as the limits allow).

    Position and φ (R = R0·exp([φ]×)) are six DoFs of one phase-synchronised ruckig call:
    φ(0) = 0, φ̇(0) = R0ᵀω0 (exact: J_r(0) = I), φ̈(0) = 0 (as for quintics: the angular acceleration
    is continuous across a joint only when it is zero there), φ(T) = log(R0ᵀR1) (the shorter way),
    φ̇(T) = J_r(φ1)⁻¹R1ᵀw1, φ̈(T) = 0. ``code`` is 17 if ruckig finds no trajectory for the state
    (e.g. an end velocity beyond a per-axis limit), 11 if it would last more than 60 s. With
    ``full=False`` only the duration is computed (``pos``/``rot`` None: a planner's quick look).
    """
    p0, v0, a0, R0, w0 = (np.asarray(x, float) for x in start)
    p1, v1, a1, w1 = (np.asarray(x, float).reshape(3) for x in (p1, v1, a1, w1))
    R1 = np.asarray(R1, float)
    phi1 = log_so3(R0.T @ R1)
    R1 = R0 @ exp_so3(phi1)
    dphi0 = R0.T @ w0
    dphi1 = np.linalg.solve(right_jacobian(phi1), R1.T @ w1)
    sp = axis_shares(p1 - p0, v0 / lim.v_max, a0 / lim.a_max, v1 / lim.v_max, a1 / lim.a_max)
    sr = axis_shares(phi1, dphi0 / lim.w_max, dphi1 / lim.w_max)
    solver = _Solver.get()
    inp = solver.inp
    inp.current_position = [*p0, 0.0, 0.0, 0.0]
    inp.current_velocity = [*v0, *dphi0]
    inp.current_acceleration = [*a0, 0.0, 0.0, 0.0]
    inp.target_position = [*p1, *phi1]
    inp.target_velocity = [*v1, *dphi1]
    inp.target_acceleration = [*a1, 0.0, 0.0, 0.0]
    inp.max_velocity = [*(lim.v_max * sp), *(lim.w_max * sr)]
    inp.max_acceleration = [*(lim.a_max * sp), *(lim.alpha_max * sr)]
    inp.max_jerk = [*(lim.j_max * sp), *(lim.jw_max * sr)]
    inp.minimum_duration = float(T_min) if T_min > 0 else None
    traj = solver.Trajectory(6)
    result = None
    # phase synchronisation first (straight lines, exact norms); if ruckig cannot, time synchronisation
    for sync in (solver.Sync.Phase, solver.Sync.Time):
        inp.synchronization = sync
        try:
            result = solver.otg.calculate(inp, traj)
        except (solver.Error, RuntimeError):  # an input ruckig cannot serve (e.g. an end velocity over a limit)
            result = None
        if result in solver.ok:
            break
    if result not in solver.ok:
        return RuckigPlan(None, None, R0, R1, math.nan, 17)
    if traj.duration > MAX_DURATION_S:
        return RuckigPlan(None, None, R0, R1, float(traj.duration), 11)
    if not full:
        return RuckigPlan(None, None, R0, R1, float(traj.duration), 0)
    pw = pieces(traj, 6)
    pos = Piecewise(pw.breaks, pw.coeffs[:, :, :3].copy())
    rot = Piecewise(pw.breaks, pw.coeffs[:, :, 3:].copy())
    return RuckigPlan(pos, rot, R0, R1, float(traj.duration), 0)


def _true_angular_max(plan: RuckigPlan, k: int, limit: float) -> float:
    """Largest true angular speed on interval k: 65 samples, each local maximum refined (bounded Brent, 1e-12 s)."""
    from scipy.optimize import minimize_scalar

    t0, t1 = plan.rotation.breaks[k], plan.rotation.breaks[k + 1]

    def speed(t):
        phi, dphi, _ = plan.rotation.state(t)
        return float(np.linalg.norm(right_jacobian(phi) @ dphi))

    ts = np.linspace(t0, t1, 65)
    sp = np.array([speed(t) for t in ts])
    best = float(sp.max())
    for i in range(len(ts)):
        if sp[i] >= (sp[i - 1] if i else -1) and sp[i] >= (sp[i + 1] if i + 1 < len(ts) else -1):
            lo, hi = ts[max(i - 1, 0)], ts[min(i + 1, len(ts) - 1)]
            res = minimize_scalar(lambda t: -speed(t), bounds=(lo, hi), method="bounded", options={"xatol": 1e-12})
            best = max(best, float(-res.fun))
        if best > limit:
            break
    return best


def _stack(pw: Piecewise) -> tuple[np.ndarray, np.ndarray]:
    """All intervals in normalised time u = τ/h ∈ [0, 1]: coefficients (4, K, D) and lengths h (K,)."""
    h = np.diff(pw.breaks)
    b = pw.coeffs * (h[:, None] ** np.arange(4))[:, :, None]  # (K, 4, D)
    return b.transpose(1, 0, 2), h


def _sq_norm_max(q: np.ndarray) -> np.ndarray:
    """Per interval, exact max over u ∈ [0, 1] of ‖q(u)‖² for quadratics ``q`` (3, K, D) (ascending)."""
    q0, q1, q2 = q
    sq = np.stack([np.sum(q0 * q0, -1), 2 * np.sum(q0 * q1, -1), np.sum(q1 * q1 + 2 * q0 * q2, -1),
                   2 * np.sum(q1 * q2, -1), np.sum(q2 * q2, -1)])  # (5, K): a quartic per interval
    return _poly_range(sq)[1]


def _unit_candidates(*roots: np.ndarray) -> np.ndarray:
    """Candidate u (M, …): 0, 1 and the given root arrays, non-finite or outside [0, 1] put at 0."""
    cands = [np.zeros_like(roots[0]), np.ones_like(roots[0]), *roots]
    u = np.stack(cands)
    return np.where(np.isfinite(u) & (u >= 0.0) & (u <= 1.0), u, 0.0)


def _quadratic_roots(c0, c1, c2) -> tuple[np.ndarray, np.ndarray]:
    """Both real roots of c0 + c1·u + c2·u² elementwise (NaN where none; the linear root where c2 ≈ 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.maximum(np.maximum(np.abs(c0), np.abs(c1)), np.abs(c2))
        lin = np.abs(c2) <= 1e-12 * scale
        disc = c1 * c1 - 4 * c2 * c0
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        r1 = np.where(lin, -c0 / c1, (-c1 + sq) / (2 * c2))
        r2 = np.where(lin, np.nan, (-c1 - sq) / (2 * c2))
    return r1, r2


def check_ruckig(plan: RuckigPlan, lim: JerkLimits) -> int:
    """0 if the controller may run ``plan``, else the dialect's error code, first of E12, E13, E14, E10.

    The rules of the quintic profile (docs/protocols/robot.md §6), applied exactly on every cubic
    interval (all intervals at once): max ‖v‖ ≤ vmax (‖v‖² a quartic: its critical points), max ‖a‖
    ≤ amax (a is linear, ‖a‖² convex: the interval ends), max ‖ω‖ ≤ wmax (‖φ̇‖ ≥ ‖ω‖; the true ω only
    where that bound exceeds the limit), the path (cubic: the roots of v) and the stop-ramp rest point
    e = x + v|v|/(2 a_stop) (extrema at the ends, the roots of v and of a = ±a_stop) inside the box
    grown to hold the start point and its own rest point, and the end point and its rest point
    inside the box.
    """
    if plan.code:
        return plan.code
    b, h = _stack(plan.position)  # (4, K, 3)
    dv = np.stack([b[1], 2 * b[2], 3 * b[3]])  # d/du, quadratic
    if np.any(np.sqrt(np.maximum(_sq_norm_max(dv), 0.0)) / h > lim.v_max * (1 + REL_TOL)):
        return 12
    a_ends = np.stack([2 * b[2], 2 * b[2] + 6 * b[3]]) / (h ** 2)[None, :, None]  # (2, K, 3)
    if np.linalg.norm(a_ends, axis=-1).max() > lim.a_max * (1 + REL_TOL):
        return 13
    r, hr = _stack(plan.rotation)
    wbound = np.sqrt(np.maximum(_sq_norm_max(np.stack([r[1], 2 * r[2], 3 * r[3]])), 0.0)) / hr
    wlim = lim.w_max * (1 + REL_TOL)
    for k in np.flatnonzero(wbound > wlim):
        if _true_angular_max(plan, int(k), wlim) > wlim:
            return 14
    p0, v0, _ = plan.position.state(0.0)
    e0 = p0 + v0 * np.abs(v0) / (2 * lim.a_stop)
    lo_box = np.minimum(np.minimum(lim.box_min, p0), e0) - BOX_TOL_MM
    hi_box = np.maximum(np.maximum(lim.box_max, p0), e0) + BOX_TOL_MM
    aT2 = lim.a_stop * (h ** 2)[:, None]  # (K, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        up, dn = (aT2 - 2 * b[2]) / (6 * b[3]), (-aT2 - 2 * b[2]) / (6 * b[3])
    u = _unit_candidates(*_quadratic_roots(dv[0], dv[1], dv[2]), up, dn)  # (M, K, 3)
    x = b[0] + u * (b[1] + u * (b[2] + u * b[3]))
    v = (dv[0] + u * (dv[1] + u * dv[2])) / h[:, None]
    e = x + v * np.abs(v) / (2 * lim.a_stop)
    lo = np.minimum(x, e).min(axis=(0, 1))
    hi = np.maximum(x, e).max(axis=(0, 1))
    if np.any(lo < lo_box) or np.any(hi > hi_box):
        return 10
    p1, v1, _ = plan.position.state(plan.duration)
    rest = p1 + v1 * np.abs(v1) / (2 * lim.a_stop)
    for q in (p1, rest):
        if np.any(q < lim.box_min - BOX_TOL_MM) or np.any(q > lim.box_max + BOX_TOL_MM):
            return 10
    return 0
