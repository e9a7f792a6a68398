"""Time-optimal interception of a moving target path with one task-space quintic (paper §4.3).

Croft, Fenton & Benhabib (1995), "Time-optimal interception of objects moving along predictable
paths", as used by the paper: from the robot's current state ``(p0, v0, a0)`` at ``t0``, find the
earliest ``t`` at which a quintic that respects the velocity and acceleration limits and stays in
the workspace arrives on the target path G(t) with G's own velocity and acceleration (so the
camera is riding along with the view when it arrives). The segment's duration is ``t - t0``, so
the search is one-dimensional in ``t``: a geometric coarse grid over the horizon (sampled limit
checks, all candidates at once in numpy), one round of 32 refining the first feasible
bracket, a closer look at near misses (local minima of a constraint score, for narrow feasible windows),
then the exact :func:`~labctl.planning.safety.check_segment` on the result. Re-planning
(:func:`replan`) restarts the same search from the current trajectory's state at ``t_now``, so
position, velocity and acceleration are continuous at the splice. Units: mm, s, rad; world frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

from .limits import Limits, LimitViolation, PlanningError
from .quintic import QuinticSegment, Trajectory, basis, quintic_coefficients
from .rotation import log_so3
from .safety import check_segment

if TYPE_CHECKING:
    from .ruckig_interception import RuckigTrajectory

TargetFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


@runtime_checkable
class OrientedTarget(Protocol):
    """A target G(t) that also fixes the end orientation (world ← commanded frame), as
    :class:`labctl.planning.targets.TargetPath` does; a plain ``TargetFn`` leaves the orientation free."""

    rotation: np.ndarray

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration of the target at times ``t`` (s)."""
        ...


def end_rotation(G: TargetFn) -> np.ndarray | None:
    """The orientation ``G`` asks to end in, or None for a target that fixes only a position."""
    if isinstance(G, OrientedTarget) and G.rotation is not None:
        return np.asarray(G.rotation, dtype=float)
    return None

_SAMPLES = 33
_BASIS_T = np.ascontiguousarray(np.vstack(basis(np.linspace(0.0, 1.0, _SAMPLES))).T)  # (6, 3S): p, p', p''
_BV_T = np.ascontiguousarray(_BASIS_T[:, _SAMPLES : 2 * _SAMPLES])
_MARGIN = 1e-3  # relative margin of the sampled checks; the exact check decides in the end
_U = np.linspace(0.0, 1.0, _SAMPLES)
_H2_8 = (1.0 / (_SAMPLES - 1)) ** 2 / 8.0
# the margin tapers to 0 at both ends: the start state (and G's state) may sit right at a limit
_TAPER = _MARGIN * np.minimum(1.0, 16.0 * _U * (1.0 - _U))


@dataclass(frozen=True)
class Interception:
    """Result of an interception plan.

    ``t_hit``: time (s) the robot arrives on G (None if unreachable); ``trajectory``: the checked
    segments from the start state (interception, then any follow segments); ``reason``/``code``:
    why it is unreachable (``"outside_box"``, ``"below_floor"``, ``"too_slow"``,
    ``"start_outside_box"``) or ``"ok"``;
    ``target``: the G that was planned for (its ``pose(t_hit)`` is the viewing pose).
    """

    t_hit: float | None
    trajectory: Trajectory | RuckigTrajectory | None  # a RuckigTrajectory from plan_interception_ruckig
    reason: str | None = None
    code: str = "ok"
    target: TargetFn | None = None

    @property
    def reachable(self) -> bool:
        """True if the robot can reach G (``t_hit`` is set)."""
        return self.t_hit is not None


def _as_state(state0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    try:
        p0, v0, a0 = (np.asarray(x, dtype=float).reshape(3) for x in state0)
    except (TypeError, ValueError) as exc:
        raise PlanningError(f"start state must be three 3-vectors (p, v, a): {exc}") from None
    if not (np.all(np.isfinite(p0)) and np.all(np.isfinite(v0)) and np.all(np.isfinite(a0))):
        raise PlanningError("start state has non-finite values")
    return p0, v0, a0

def _checked_start(state0, t0: float, horizon_s: float, t_min: float, limits: Limits, G):
    """The start state ``(p0, v0, a0)`` of an interception search, or an unreachable
    :class:`Interception` if the robot starts outside the workspace box; PlanningError on a bad
    state or horizon. Shared by the quintic and the ruckig planners."""
    p0, v0, a0 = _as_state(state0)
    if not (np.isfinite(t0) and np.isfinite(horizon_s) and horizon_s > t_min > 0):
        raise PlanningError(f"need finite t0 and horizon_s > t_min > 0, got t0={t0!r}, horizon_s={horizon_s!r}")
    if not limits.contains(p0):
        return Interception(None, None, f"the robot is outside the workspace box at {np.round(p0, 1).tolist()} mm",
                            "start_outside_box", G)
    return p0, v0, a0



def _score(p0, v0, a0, gp, gv, ga, Ts, limits: Limits, rot=None) -> tuple[np.ndarray, np.ndarray]:
    """Sampled constraint score of the quintics to each (gp, gv, ga)[k] taking Ts[k]; feasible where ≤ 0.

    The score is the worst normalised excess over all constraints (box excess per 100 mm, speed,
    acceleration and rotation rate relative to their limits, each with the sampling margin), so
    a dip towards zero between grid points flags a narrow feasible window. Also returns the
    mask of G-in-box.
    """
    b = quintic_coefficients(p0, v0, a0, gp, gv, ga, Ts)  # (K, 6, 3)
    S = _SAMPLES
    X = b.transpose(0, 2, 1) @ _BASIS_T  # (K, 3, 3S): sampled p(u), then p'(u), then p''(u), per axis
    P = X[:, :, :S]
    # between samples h apart a position extremum can overshoot the best sample by h²/8·|p''|
    slack = _H2_8 * np.abs(X[:, :, 2 * S :]).max(axis=2)  # (K, 3)
    low, high = P.min(axis=2) - slack, P.max(axis=2) + slack
    box_excess = np.maximum(limits.box_min - low, high - limits.box_max).max(axis=1)
    g_excess = np.maximum(limits.box_min - gp, gp - limits.box_max).max(axis=1)
    D = np.sqrt(np.einsum("kds,kds->ks", X[:, :, S:], X[:, :, S:])).reshape(len(Ts), 2, S)  # (K, 2, S): |p'|, |p''|
    v_excess = (D[:, 0] / (limits.v_max * Ts)[:, None] + _TAPER).max(axis=1) - 1
    a_excess = (D[:, 1] / (limits.a_max * Ts * Ts)[:, None] + _TAPER).max(axis=1) - 1
    score = np.maximum(np.maximum(box_excess, g_excess) / 100.0, np.maximum(v_excess, a_excess))
    if rot is not None:
        w0, dw0, r1 = rot
        z = np.zeros(3)
        rc = quintic_coefficients(z, w0, dw0, r1, z, z, Ts)
        W = rc.transpose(0, 2, 1) @ _BV_T  # (K, 3, S): dr/du
        w = np.sqrt(np.einsum("kds,kds->ks", W, W))
        score = np.maximum(score, (w / (limits.w_max * Ts)[:, None] + _TAPER).max(axis=1) - 1)
    return score, g_excess <= 0


_SLIVER = 0.05  # a local minimum of the score below this is searched for a narrow feasible window


@lru_cache(maxsize=64)
def _grid(t_min: float, horizon_s: float, n: int) -> np.ndarray:
    g = np.geomspace(t_min, horizon_s, n)
    g.flags.writeable = False
    return g


def _segment(t0, T, p0, v0, a0, G, rot_args) -> QuinticSegment:
    gp, gv, ga = G(np.array([t0 + T]))
    R0, R1, w0, dw0 = rot_args
    return QuinticSegment(t0, T, p0, v0, a0, gp[0], gv[0], ga[0], R0=R0, R1=R1, w0=w0, dw0=dw0)


def _unreachable_reason(in_box_any: bool, gp: np.ndarray, limits: Limits, horizon_s: float) -> tuple[str, str]:
    if not in_box_any:
        if np.all(gp[:, 2] < limits.box_min[2]):
            return "below_floor", (f"target path is below the workspace floor (z < {limits.box_min[2]:.0f} mm) "
                                   f"for the whole {horizon_s:.1f} s horizon")
        return "outside_box", f"target path stays outside the workspace box for the whole {horizon_s:.1f} s horizon"
    return "too_slow", f"no limit-respecting quintic reaches the target path within {horizon_s:.1f} s"


def _follow_segments(start: QuinticSegment, G: TargetFn, limits: Limits, follow_s: float, step_s: float):
    segs = []
    t = start.t1
    R = start.R1
    while follow_s > 0 and t < start.t1 + follow_s - 1e-9:
        T = min(step_s, start.t1 + follow_s - t)
        gp, gv, ga = G(np.array([t, t + T]))
        seg = QuinticSegment(t, T, gp[0], gv[0], ga[0], gp[1], gv[1], ga[1], R0=R, R1=R)
        try:
            segs.append(check_segment(seg, limits))
        except LimitViolation:
            break  # G leaves the workspace: stop following where it is still safe
        t += T
    return segs


def plan_interception(state0, t0: float, G: TargetFn, limits: Limits, horizon_s: float = 10.0, *,
                      R0=None, w0=None, dw0=None, follow_s: float = 0.0, follow_step_s: float = 0.5,
                      t_min: float = 0.02, n_coarse: int = 64) -> Interception:
    """Earliest arrival on G(t) by one limit-respecting quintic from ``state0 = (p, v, a)`` at ``t0``.

    Paper §4.3 / Croft, Fenton & Benhabib 1995. ``G(times) -> (pos, vel, acc)`` (N, 3) in W.
    Searches arrival times in ``[t0 + t_min, t0 + horizon_s]``. With ``R0`` (current tool rotation,
    world ← tool) and a G that has a ``rotation`` attribute, the orientation is slerped along the
    same segment (quintic in rotation-vector space from body rate ``w0``/``dw0`` to rest) and the
    rotation rate is checked against ``limits.w_max``. ``follow_s`` appends checked segments that
    ride along G after the hit. Returns an :class:`Interception`; unreachable targets come back
    with ``t_hit=None`` and a reason, never as an exception.
    """
    start = _checked_start(state0, t0, horizon_s, t_min, limits, G)
    if isinstance(start, Interception):
        return start
    p0, v0, a0 = start
    rot = None
    rot_args: tuple = (None, None, None, None)
    R1 = end_rotation(G)
    if R0 is not None and R1 is not None:
        R0 = np.asarray(R0, dtype=float)
        w0 = np.zeros(3) if w0 is None else np.asarray(w0, dtype=float).reshape(3)
        dw0 = np.zeros(3) if dw0 is None else np.asarray(dw0, dtype=float).reshape(3)
        rot = (w0, dw0, log_so3(R0.T @ R1))
        rot_args = (R0, R1, w0, dw0)

    Ts = _grid(float(t_min), float(horizon_s), int(n_coarse))
    gp, gv, ga = G(t0 + Ts)
    score, in_box = _score(p0, v0, a0, gp, gv, ga, Ts, limits, rot)

    def score_at(cand):
        cp, cv, ca = G(t0 + cand)
        return _score(p0, v0, a0, cp, cv, ca, cand, limits, rot)[0]

    def refine_edge(lo, hi):  # lo infeasible (or 0), hi feasible: close in on the earliest feasible time
        cand = np.linspace(lo, hi, 33)[1:]  # one round: the coarse ratio 1.1 → 0.3 % resolution
        j = int(np.argmax(score_at(cand) <= 0.0))  # cand[-1] == hi is feasible
        return cand[j]

    def exact(T_feasible):  # the exact check decides; the sampled score may be a hair optimistic
        for bump in (0.0, 0.0005, 0.001, 0.002, 0.004, 0.008, 0.016, 0.032):
            T = T_feasible * (1.0 + bump)
            seg = _segment(t0, T, p0, v0, a0, G, rot_args)
            try:
                return check_segment(seg, limits)
            except LimitViolation:
                continue
        return None

    n = len(Ts)
    for k in range(n):
        lo = Ts[k - 1] if k > 0 else 0.0
        if score[k] <= 0.0:
            seg = exact(refine_edge(lo, Ts[k]))
        elif score[k] < _SLIVER and (k == 0 or score[k] <= score[k - 1]) and (k == n - 1 or score[k] <= score[k + 1]):
            # a near miss: look for a feasible sliver between the neighbouring grid points
            hi = Ts[k + 1] if k + 1 < n else Ts[k]
            seg = None
            for _ in range(2):
                cand = np.linspace(lo, hi, 17)[1:-1]
                sc = score_at(cand)
                if np.any(sc <= 0.0):
                    j = int(np.argmax(sc <= 0.0))
                    seg = exact(refine_edge(cand[j - 1] if j > 0 else lo, cand[j]))
                    break
                j = int(np.argmin(sc))
                lo, hi = (cand[j - 1] if j > 0 else lo), (cand[j + 1] if j + 1 < len(cand) else hi)
        else:
            continue
        if seg is not None:
            segs = [seg, *_follow_segments(seg, G, limits, follow_s, follow_step_s)]
            return Interception(seg.t1, Trajectory(tuple(segs)), None, "ok", G)
    code, reason = _unreachable_reason(bool(in_box.any()), gp, limits, horizon_s)
    return Interception(None, None, reason, code, G)


def _omega(seg: QuinticSegment, t: float) -> np.ndarray:
    """Body angular velocity (rad/s) of a segment that carries an orientation."""
    w = seg.angular_velocity(t)
    if w is None:
        raise PlanningError("a segment without orientation has no angular velocity")
    return w


def _rotation_state(traj: Trajectory, t: float):
    seg = traj.segment_at(t)
    if seg.rot_coeffs is None:
        R = traj.orientation(t)
        return R, None, None
    R = seg.orientation(t)
    w = _omega(seg, t)
    h = 1e-4 * seg.duration
    ta, tb = max(seg.t0, t - h), min(seg.t1, t + h)
    dw = (_omega(seg, tb) - _omega(seg, ta)) / (tb - ta) if tb > ta else np.zeros(3)
    return R, w, dw


def replan(current: Trajectory, t_now: float, new_G: TargetFn, limits: Limits, horizon_s: float = 10.0,
           **kwargs) -> Interception:
    """Re-plan the unexecuted motion from ``current``'s state at ``t_now`` towards a new G (paper §4.3).

    The new first segment starts at ``t_now`` from exactly ``current.state(t_now)`` (and its
    orientation and body angular velocity, angular acceleration by a central difference), so
    position, velocity and acceleration are continuous at the splice. If the new G is
    unreachable the caller should keep executing ``current``.
    """
    p, v, a = current.state(t_now)
    R, w, dw = _rotation_state(current, t_now)
    if R is not None:
        kwargs.setdefault("R0", R)
        kwargs.setdefault("w0", w)
        kwargs.setdefault("dw0", dw)
    return plan_interception((p, v, a), t_now, new_G, limits, horizon_s, **kwargs)


def shortest_quintic(p0, v0, a0, p1, v1, a1, limits: Limits, t0: float = 0.0, max_duration_s: float = 120.0,
                     R0=None, R1=None) -> QuinticSegment:
    """The shortest-duration quintic between two fixed states that meets the box and v/a limits.

    A search on the duration T (coarse geometric grid, refinement, exact check), as in the paper's
    time-optimal quintics (§4.3). Raises :class:`PlanningError` if no duration up to
    ``max_duration_s`` works (e.g. an end state outside the box or faster than ``v_max``).
    """
    end = tuple(np.asarray(x, dtype=float).reshape(3) for x in (p1, v1, a1))

    class _Fixed:
        rotation = None if R1 is None else np.asarray(R1, dtype=float)

        def __call__(self, times):
            n = len(np.atleast_1d(times))
            return tuple(np.tile(x, (n, 1)) for x in end)

    res = plan_interception((p0, v0, a0), t0, _Fixed(), limits, max_duration_s, R0=R0, t_min=1e-3, n_coarse=128)
    if not res.reachable or not isinstance(res.trajectory, Trajectory):
        raise PlanningError(f"no quintic within {max_duration_s:.0f} s meets the limits ({res.code})")
    return res.trajectory.segments[0]


def plan_quintic_arriving(state0, t0: float, G: TargetFn, T: float, limits: Limits, *, R0=None) -> Interception:
    """One limit-checked quintic from ``state0`` (at rest in orientation ``R0``) at ``t0`` arriving on G at
    ``t0 + T`` (s): a slower flight than :func:`plan_interception`'s earliest, as when a segment is stretched
    for the arm's joint speeds (rotation from rest, as that planner's from a start without a rate)."""
    start = _checked_start(state0, t0, max(T, 0.02) * 2.0, 0.01, limits, G)
    if isinstance(start, Interception):
        return start
    p0, v0, a0 = start
    R1 = end_rotation(G)
    rot_args: tuple = (None, None, None, None)
    if R0 is not None and R1 is not None:
        rot_args = (np.asarray(R0, dtype=float), R1, np.zeros(3), np.zeros(3))
    seg = _segment(t0, T, p0, v0, a0, G, rot_args)
    try:
        seg = check_segment(seg, limits)
    except LimitViolation as exc:
        return Interception(None, None, f"the quintic lasting {T:.3f} s breaks a limit: {exc}", "too_slow", G)
    return Interception(seg.t1, Trajectory((seg,)), None, "ok", G)
