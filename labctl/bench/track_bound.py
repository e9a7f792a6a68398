"""The best achievable 5-s prediction from the same measurements: Cramér-Rao bound and ML fit.

Independent of the filters on purpose (it imports neither :mod:`labctl.tracking.tracker` nor
:mod:`labctl.tracking.models`): each trajectory family the lab runs (paper §5.2;
``labctl.drivers.programs``) is written as a deterministic path with a handful of unknown
parameters θ, measured with white Gaussian noise σ per axis at the camera's frame times.
Two references for the position predicted ``horizon`` seconds past the last frame:

* :func:`crb_prediction_cov` — the Cramér-Rao bound: ``g I(θ)⁻¹ gᵀ`` with the Fisher
  information ``I = JᵀJ/σ²`` (J the Jacobian of the measured positions, g of the predicted one;
  central differences) — no unbiased estimator of θ does better.
* :func:`ml_prediction` — the maximum-likelihood fit of the true model (``scipy.optimize.
  least_squares``, Levenberg-Marquardt, started at the truth so it finds the global optimum's
  basin), then the model extrapolated. Run on the very measurements a filter saw, it gives a
  paired Monte-Carlo reference.

Families (table-plane mm, s; Bar-Shalom, Li & Kirubarajan 2001, §11.7 for the turn model):

* ``line``: ``p(t) = p0 + v t``; θ = (x0, y0, vx, vy).
* ``arc`` / ``circle``: constant speed and turn rate ω; θ = (x0, y0, vx0, vy0, ω). The same model;
  they differ in radius (:data:`RADII`).
* ``zigzag``: straight legs with an instantaneous corner at an unknown time t_c (position
  continuous); θ = (xc, yc, v1x, v1y, v2x, v2y, t_c). The prediction extends the current leg:
  no estimator can foresee the next corner, so the bound is for the motion now under way.
* ``zigzag_stop``: the same legs as the table drives them: GRBL slows into a corner this sharp
  (its junction speed for the lab's 97° turn is ~2 mm/s at 200 mm/s², so taken as 0) and speeds up
  out of it at the table's acceleration ``a`` (known: the table's setting); t_c is when it stands at
  the corner; θ = (xc, yc, v1x, v1y, v2x, v2y, t_c, a), ``a`` not estimated. Not in :data:`FAMILIES`
  (the prediction acceptance is on the instant corner): a diagnostic of how far the lab's corners are from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

FAMILIES = ("line", "arc", "circle", "zigzag")
ZIGZAGS = ("zigzag", "zigzag_stop")
SPEEDS = (4.0, 12.0, 50.0, 100.0)
RADII = {"arc": 200.0, "circle": 80.0}  # circle: the lab's program radius; arc: a gentler curve
ZIGZAG_TURN_RAD = np.arctan2(40.0, 50.0) - np.arctan2(-80.0, 50.0)  # the lab program's leg-to-leg turn (~97°)


def _turn_offsets(v: np.ndarray, w: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Displacement (N, 2) after ``t`` of a turn at rate ``w`` starting with velocity ``v``; exact as w → 0."""
    wt = w * t
    small = np.abs(wt) < 1e-4
    safe = np.where(small, 1.0, wt)
    s = np.where(small, 1.0 - wt**2 / 6.0, np.sin(safe) / safe)  # sin(wt)/(wt)
    c = np.where(small, wt / 2.0 - wt**3 / 24.0, (1.0 - np.cos(safe)) / safe)  # (1-cos wt)/(wt)
    return np.column_stack([t * (s * v[0] - c * v[1]), t * (c * v[0] + s * v[1])])


def _stop_leg(v: np.ndarray, a: float, s: np.ndarray, sign: float) -> np.ndarray:
    """Offsets (N, 2) from a corner of a leg at velocity ``v`` that stops (sign −1) or starts (+1) there at ``a``.

    ``s`` ≥ 0 is the time from (−1) or to (+1) the corner: the distance along the leg is ``a s²/2`` while
    ``s < |v|/a``, then grows at ``|v|``.
    """
    speed = float(np.hypot(*v))
    ramp = speed / a
    dist = np.where(s < ramp, 0.5 * a * s * s, speed * (s - 0.5 * ramp))
    return sign * np.outer(dist, v / speed)


def positions(family: str, theta, t) -> np.ndarray:
    """Positions (N, 2) mm of ``family`` with parameters ``theta`` at times ``t`` (s); see the module doc."""
    th = np.asarray(theta, dtype=float)
    t = np.atleast_1d(np.asarray(t, dtype=float))
    if family == "line":
        return th[:2] + np.outer(t, th[2:4])
    if family in ("arc", "circle"):
        return th[:2] + _turn_offsets(th[2:4], th[4], t)
    if family == "zigzag":
        d = (t - th[6])[:, None]
        return th[:2] + np.where(d < 0.0, d * th[2:4], d * th[4:6])
    if family == "zigzag_stop":
        d, a = t - th[6], th[7]
        into, out_of = _stop_leg(th[2:4], a, np.maximum(-d, 0.0), -1.0), _stop_leg(th[4:6], a, np.maximum(d, 0.0), 1.0)
        return th[:2] + into + out_of
    raise ValueError(f"unknown family {family!r} (have {', '.join(FAMILIES + ZIGZAGS[1:])})")


@dataclass(frozen=True)
class Scenario:
    """One true path: ``family`` with parameters ``theta``; frames at ``times`` (s) measured with ``sigma_mm``."""

    family: str
    speed_mm_s: float
    theta: np.ndarray
    times: np.ndarray
    sigma_mm: float

    def truth(self, t) -> np.ndarray:
        """Noise-free positions (N, 2) mm of the true path at times ``t`` (s)."""
        return positions(self.family, self.theta, t)

    def current_motion(self, t_now: float, t_future) -> np.ndarray:
        """Positions (N, 2) at ``t_future`` of the motion under way at ``t_now`` (the zigzag's leg, extended)."""
        if self.family in ZIGZAGS and t_now < self.theta[6]:
            th = self.theta
            return positions("line", np.r_[th[:2] - th[6] * th[2:4], th[2:4]], t_future)
        return self.truth(t_future)

    def measure(self, rng: np.random.Generator) -> np.ndarray:
        """Noisy centroids (N, 2) at :attr:`times`."""
        return self.truth(self.times) + rng.normal(0.0, self.sigma_mm, (len(self.times), 2))


def make_scenario(family: str, speed_mm_s: float, duration_s: float, *, rate_hz: float = 30.0,
                  sigma_mm: float = 0.7, heading_rad: float = 0.3, corner_s: float = 2.0,
                  start=(0.0, 0.0), table_accel_mm_s2: float | None = None,
                  curvature_mm_inv: float | None = None) -> Scenario:
    """A :class:`Scenario` of ``family`` at constant path speed, frames every ``1/rate_hz`` s from 0 to ``duration_s``.

    Arcs and circles turn counter-clockwise at ``speed/RADII[family]`` (or at ``speed·curvature_mm_inv``, signed:
    negative turns clockwise); the zigzag runs along
    ``heading_rad`` and turns by the lab program's corner angle at ``corner_s``; ``zigzag_stop`` stands
    at the corner at ``corner_s`` and accelerates at ``table_accel_mm_s2`` (mm/s²).
    """
    if family not in FAMILIES + ZIGZAGS:
        raise ValueError(f"unknown family {family!r} (have {', '.join(FAMILIES + ZIGZAGS[1:])})")
    times = np.arange(0.0, duration_s + 1e-9, 1.0 / rate_hz)
    u = np.array([np.cos(heading_rad), np.sin(heading_rad)])
    v = speed_mm_s * u
    p0 = np.asarray(start, dtype=float)
    if family == "line":
        theta = np.r_[p0, v]
    elif family in ("arc", "circle"):
        kappa = 1.0 / RADII[family] if curvature_mm_inv is None else float(curvature_mm_inv)
        theta = np.r_[p0, v, speed_mm_s * kappa]
    else:
        h2 = heading_rad - ZIGZAG_TURN_RAD
        theta = np.r_[p0 + corner_s * v, v, speed_mm_s * np.cos(h2), speed_mm_s * np.sin(h2), corner_s]
        if family == "zigzag_stop":
            if table_accel_mm_s2 is None:
                raise ValueError("zigzag_stop needs the table's acceleration (table_accel_mm_s2)")
            theta = np.r_[theta, table_accel_mm_s2]
    return Scenario(family, float(speed_mm_s), theta, times, float(sigma_mm))


def _jacobian(family: str, theta: np.ndarray, t: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """d positions(t) / dθ, (2N, P), by central differences of step ``scale``·1e-5 (not over a known ``a``)."""
    cols = []
    for k in range(len(theta) - (family == "zigzag_stop")):
        h = 1e-5 * scale[k]
        e = np.zeros_like(theta)
        e[k] = h
        cols.append(((positions(family, theta + e, t) - positions(family, theta - e, t)) / (2 * h)).reshape(-1))
    return np.column_stack(cols)


def _scales(family: str, theta: np.ndarray) -> np.ndarray:
    s = np.maximum(np.abs(theta), 1.0)
    if family in ("arc", "circle"):
        s[4] = max(abs(theta[4]), 1e-3)
    return s


def crb_prediction_cov(scn: Scenario, n_frames: int, horizon_s: float, keep=None) -> np.ndarray:
    """Cramér-Rao bound (2, 2) mm² on the position ``horizon_s`` past frame ``n_frames - 1``, from frames 0..n-1.

    ``keep``: a mask over :attr:`Scenario.times`, the frames measured (default all); frame ``n_frames - 1``
    must be one of them.

    For the zigzag the corner must lie among the frames used (else t_c is not identifiable; the
    bound is then that of the line model on those frames).
    """
    t = scn.times[:n_frames] if keep is None else scn.times[:n_frames][keep[:n_frames]]
    t_pred = np.array([t[-1] + horizon_s])
    fam, th = scn.family, scn.theta
    if fam in ZIGZAGS and t[-1] <= th[6]:
        fam, th = "line", np.r_[th[:2] - th[6] * th[2:4], th[2:4]]
    sc = _scales(fam, th)
    J = _jacobian(fam, th, t, sc)
    g = _jacobian(fam, th, t_pred, sc)
    info = J.T @ J / scn.sigma_mm**2
    return g @ np.linalg.solve(info, g.T)


def crb_prediction_rms(scn: Scenario, n_frames: int, horizon_s: float) -> float:
    """``sqrt(trace)`` of :func:`crb_prediction_cov`: the bound on the RMS 2-D prediction error (mm)."""
    return float(np.sqrt(np.trace(crb_prediction_cov(scn, n_frames, horizon_s))))


def ml_prediction(scn: Scenario, z: np.ndarray, n_frames: int, horizon_s: float, keep=None) -> np.ndarray:
    """ML fit of the true model to ``z[:n_frames]`` (those ``keep`` marks); its position ``horizon_s`` past the last
    frame (2,)."""
    t, zz = scn.times[:n_frames], z[:n_frames]
    if keep is not None:
        t, zz = t[keep[:n_frames]], zz[keep[:n_frames]]
    fam, th0 = scn.family, scn.theta.astype(float)
    if fam in ZIGZAGS and t[-1] <= th0[6]:
        fam, th0 = "line", np.r_[th0[:2] - th0[6] * th0[2:4], th0[2:4]]
    sc = _scales(fam, th0)

    def resid(u):
        return (positions(fam, u * sc, t) - zz).reshape(-1)

    if fam == "zigzag":
        # linear in the rest for a fixed t_c, only piecewise smooth in t_c: profile t_c on a 5 ms grid (±1 s)
        best: tuple[float, np.ndarray] | None = None
        for tc in th0[6] + np.linspace(-1.0, 1.0, 401):
            if not t[0] < tc < t[-1]:
                continue
            d = (t - tc)[:, None]
            A = np.zeros((2 * len(t), 6))  # rows x0, y0, x1, y1, ...; columns xc, yc, v1x, v1y, v2x, v2y
            A[0::2, 0] = A[1::2, 1] = 1.0
            A[0::2, 2], A[1::2, 3] = np.where(d < 0, d, 0.0)[:, 0], np.where(d < 0, d, 0.0)[:, 0]
            A[0::2, 4], A[1::2, 5] = np.where(d >= 0, d, 0.0)[:, 0], np.where(d >= 0, d, 0.0)[:, 0]
            sol, *_ = np.linalg.lstsq(A, zz.reshape(-1), rcond=None)
            cost = float(np.sum((A @ sol - zz.reshape(-1)) ** 2))
            if best is None or cost < best[0]:
                best = (cost, np.r_[sol, tc])
        if best is None:
            raise ValueError(f"no corner time within ±1 s of {th0[6]:g} s lies inside the fitted frames")
        th = best[1]
    elif fam == "zigzag_stop":  # started at the truth: LM stays in the right corner time's basin
        known = th0[7:]
        th = least_squares(lambda u: resid(np.r_[u, known / sc[7:]]), th0[:7] / sc[:7], method="lm").x * sc[:7]
        th = np.r_[th, known]
    else:
        th = least_squares(resid, th0 / sc, method="lm").x * sc
    return positions(fam, th, [t[-1] + horizon_s])[0]
