"""Ellipses: the conic ``aX² + bXY + cY² + dX + eY + f = 0`` and the paper's weighted fit.

Implements He et al. (ICRA 1996) §3.1, eqs. 1–2: the five ellipse parameters minimise
``Σ wᵢ Q(Xᵢ, Yᵢ)²`` over boundary points, where the weights ``wᵢ`` compensate for the
non-uniform spacing of the points along the boundary. The minimisation is the direct,
ellipse-specific least squares of Fitzgibbon, Pilu & Fisher (IEEE T-PAMI 21(5), 1999) under
the constraint ``4ac − b² = 1``, in the numerically stable form of Halíř & Flusser (WSCG 1998),
on Hartley-normalised coordinates (centroid at the origin, RMS distance √2). A few
re-weighting passes divide each ``wᵢ`` by ``|∇Q(Xᵢ, Yᵢ)|²`` (Sampson's first-order
approximation of the geometric distance), which removes most of the algebraic fit's
shrinking bias on short arcs while staying a weighted least-squares fit of eq. 2.

Coordinates are whatever the points are in (usually pixels); angles in radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


class EllipseFitError(ValueError):
    """The points do not determine an ellipse (too few, collinear, non-finite, or a hyperbola)."""


@dataclass(frozen=True)
class Ellipse:
    """An ellipse by centre (x, y), semi-axes (major ≥ minor), major-axis angle from +x (rad,
    in (−π/2, π/2]) and the unit-norm conic (a, b, c, d, e, f) with a + c > 0."""

    center: np.ndarray
    axes: tuple[float, float]
    angle: float
    conic: np.ndarray

    # --- constructors ----------------------------------------------------------------------
    @classmethod
    def from_conic(cls, conic) -> Ellipse:
        """Ellipse from conic coefficients (a, b, c, d, e, f); raises EllipseFitError if the
        conic is not a real, non-degenerate ellipse."""
        try:
            q = [float(v) for v in (conic.tolist() if isinstance(conic, np.ndarray) else conic)]
        except (TypeError, ValueError):
            raise EllipseFitError("conic must be 6 finite coefficients") from None
        if len(q) != 6 or not all(math.isfinite(v) for v in q):
            raise EllipseFitError("conic must be 6 finite coefficients")
        norm = math.sqrt(sum(v * v for v in q))
        if norm == 0.0:
            raise EllipseFitError("conic is all zero")
        sign = 1.0 if q[0] + q[2] >= 0 else -1.0
        a, b, c, d, e, f = (sign * v / norm for v in q)
        det2 = 4.0 * a * c - b * b
        if not det2 > 1e-14 * (a * a + c * c + b * b):
            raise EllipseFitError("conic is not an ellipse (4ac − b² ≤ 0)")
        x0 = (b * e - 2.0 * c * d) / det2
        y0 = (b * d - 2.0 * a * e) / det2
        f0 = f + 0.5 * (d * x0 + e * y0)  # Q at the centre; negative for a real ellipse
        if not f0 < 0:
            raise EllipseFitError("conic is an imaginary or point ellipse")
        # eigenvalues of [[a, b/2], [b/2, c]] in closed form
        half_tr = 0.5 * (a + c)
        rad = math.hypot(0.5 * (a - c), 0.5 * b)
        lam_small, lam_big = half_tr - rad, half_tr + rad
        if not lam_small > 0:
            raise EllipseFitError("conic is not an ellipse")
        major = math.sqrt(-f0 / lam_small)
        minor = math.sqrt(-f0 / lam_big)
        if not (math.isfinite(major) and minor > 0):
            raise EllipseFitError("conic gives non-finite axes")
        # direction of the smaller eigenvalue, wrapped into (−π/2, π/2]
        angle = 0.5 * math.atan2(b, a - c) + 0.5 * math.pi
        if angle > 0.5 * math.pi:
            angle -= math.pi
        return cls(np.array([x0, y0]), (major, minor), angle, np.array([a, b, c, d, e, f]))

    @classmethod
    def from_params(cls, center, axes, angle: float) -> Ellipse:
        """Ellipse from centre, the two semi-axes (any order, > 0) and the angle (rad) of the
        first axis from +x."""
        cx, cy = (float(v) for v in np.asarray(center, dtype=float).ravel()[:2])
        a1, a2 = (float(v) for v in axes)
        if not (a1 > 0 and a2 > 0 and np.isfinite(a1) and np.isfinite(a2) and np.isfinite(angle)):
            raise EllipseFitError("ellipse axes must be finite and positive")
        if a2 > a1:
            a1, a2, angle = a2, a1, angle + 0.5 * np.pi
        ca, sa = np.cos(angle), np.sin(angle)
        # (x', y') = R(−θ)(p − c);  x'²/a1² + y'²/a2² = 1
        A = ca * ca / a1**2 + sa * sa / a2**2
        B = 2.0 * ca * sa * (1.0 / a1**2 - 1.0 / a2**2)
        C = sa * sa / a1**2 + ca * ca / a2**2
        D = -2.0 * A * cx - B * cy
        E = -B * cx - 2.0 * C * cy
        F = A * cx * cx + B * cx * cy + C * cy * cy - 1.0
        return cls.from_conic([A, B, C, D, E, F])

    # --- derived ---------------------------------------------------------------------------
    @property
    def matrix(self) -> np.ndarray:
        """Symmetric 3×3 conic matrix M with [x y 1] M [x y 1]ᵀ = Q(x, y)."""
        a, b, c, d, e, f = self.conic
        return np.array([[a, b / 2, d / 2], [b / 2, c, e / 2], [d / 2, e / 2, f]])

    @property
    def area(self) -> float:
        return float(np.pi * self.axes[0] * self.axes[1])

    def points(self, n: int = 64, t0: float = 0.0, t1: float = 2.0 * np.pi) -> np.ndarray:
        """``n`` points (n×2) at parameter angles t ∈ [t0, t1) of x = c + R(θ)(A cos t, B sin t)."""
        t = np.linspace(t0, t1, n, endpoint=abs(t1 - t0 - 2 * np.pi) > 1e-12)
        ca, sa = np.cos(self.angle), np.sin(self.angle)
        x = self.axes[0] * np.cos(t)
        y = self.axes[1] * np.sin(t)
        return np.column_stack([self.center[0] + ca * x - sa * y, self.center[1] + sa * x + ca * y])

    def sampson_distances(self, points) -> np.ndarray:
        """First-order geometric distance |Q| / |∇Q| of each point to the ellipse (same units)."""
        p = np.asarray(points, dtype=float)
        a, b, c, d, e, f = self.conic
        x, y = p[:, 0], p[:, 1]
        q = a * x * x + b * x * y + c * y * y + d * x + e * y + f
        gx = 2 * a * x + b * y + d
        gy = b * x + 2 * c * y + e
        return np.abs(q) / np.maximum(np.hypot(gx, gy), 1e-300)

    def to_dict(self) -> dict:
        return {"center": [float(v) for v in self.center], "axes": [float(v) for v in self.axes],
                "angle_rad": float(self.angle), "conic": [float(v) for v in self.conic]}


def _validate(points, weights) -> tuple[np.ndarray, np.ndarray]:
    try:
        p = np.asarray(points, dtype=float)
    except (TypeError, ValueError):
        raise EllipseFitError("points must be an N×2 numeric array") from None
    if p.ndim != 2 or p.shape[1] != 2:
        raise EllipseFitError(f"points must be N×2, got shape {p.shape}")
    if p.shape[0] < 5:
        raise EllipseFitError(f"an ellipse needs at least 5 points, got {p.shape[0]}")
    if not np.isfinite(p).all():
        raise EllipseFitError("points contain NaN or infinity")
    if weights is None:
        w = np.ones(p.shape[0])
    else:
        w = np.asarray(weights, dtype=float).ravel()
        if w.shape[0] != p.shape[0]:
            raise EllipseFitError("weights must have one entry per point")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise EllipseFitError("weights must be finite and non-negative")
        if np.count_nonzero(w) < 5:
            raise EllipseFitError("fewer than 5 points have a positive weight")
    return p, w


def _inv3(m: list[list[float]]) -> list[list[float]] | None:
    """Inverse of a 3×3 matrix (nested lists) by its adjugate; None if (nearly) singular."""
    (a, b, c), (d, e, f), (g, h, i) = m
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * A + b * B + c * C
    scale = max(abs(a), abs(b), abs(c), abs(d), abs(e), abs(f), abs(g), abs(h), abs(i)) ** 3
    if not abs(det) > 1e-10 * scale:
        return None
    r = 1.0 / det
    return [[A * r, (c * h - b * i) * r, (b * f - c * e) * r],
            [B * r, (a * i - c * g) * r, (c * d - a * f) * r],
            [C * r, (b * g - a * h) * r, (a * e - b * d) * r]]


def _real_eigenvalues3(m: list[list[float]]) -> list[float]:
    """Real roots of the characteristic cubic of a 3×3 matrix (closed form, Cardano/Viète)."""
    (a, b, c), (d, e, f), (g, h, i) = m
    p2 = -(a + e + i)
    p1 = (a * e - b * d) + (a * i - c * g) + (e * i - f * h)
    p0 = -(a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g))
    shift = p2 / 3.0
    p = p1 - p2 * p2 / 3.0
    q = 2.0 * p2**3 / 27.0 - p2 * p1 / 3.0 + p0
    disc = 0.25 * q * q + p**3 / 27.0
    if disc > 0:
        s = math.sqrt(disc)
        return [math.copysign(abs(-0.5 * q + s) ** (1 / 3), -0.5 * q + s)
                + math.copysign(abs(-0.5 * q - s) ** (1 / 3), -0.5 * q - s) - shift]
    if p == 0.0:
        return [-shift]
    rr = 2.0 * math.sqrt(-p / 3.0)
    arg = max(-1.0, min(1.0, 3.0 * q / (p * rr)))
    phi = math.acos(arg) / 3.0
    return [rr * math.cos(phi - 2.0 * math.pi * k / 3.0) - shift for k in range(3)]


def _null_vector3(m: list[list[float]], lam: float) -> list[float]:
    """Unit vector spanning the null space of (m − λI): the largest cross product of two rows."""
    r0 = [m[0][0] - lam, m[0][1], m[0][2]]
    r1 = [m[1][0], m[1][1] - lam, m[1][2]]
    r2 = [m[2][0], m[2][1], m[2][2] - lam]
    best, best_n = [0.0, 0.0, 0.0], 0.0
    for u, v in ((r0, r1), (r0, r2), (r1, r2)):
        cr = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]
        n = cr[0] * cr[0] + cr[1] * cr[1] + cr[2] * cr[2]
        if n > best_n:
            best, best_n = cr, n
    if best_n == 0.0:
        return best
    s = 1.0 / math.sqrt(best_n)
    return [best[0] * s, best[1] * s, best[2] * s]


def _direct_fit(design: np.ndarray, wk: np.ndarray) -> np.ndarray:
    """Halíř–Flusser direct ellipse fit (constraint 4ac − b² = 1) on the design matrix
    [x², xy, y², x, y, 1] with row weights ``wk``."""
    S = (design * wk[:, None]).T @ design
    S1, S2, S3 = S[:3, :3], S[:3, 3:], S[3:, 3:]
    scale = float(np.abs(S3).max())
    if not (scale > 0 and abs(cv2.determinant(S3)) > 1e-10 * scale**3):
        raise EllipseFitError("degenerate point set (collinear or too few distinct points)")
    T = -cv2.invert(S3)[1] @ S2.T
    Mc = _C1_INV @ (S1 + S2 @ T)
    best = None
    evals, evecs = cv2.eigenNonSymmetric(Mc)
    if evecs is not None and evecs.shape == (3, 3):
        cands = [(abs(lam), v) for lam, v in zip(evals.ravel().tolist(), evecs.tolist(), strict=True)
                 if 4.0 * v[0] * v[2] - v[1] * v[1] > 0]
        if cands:
            best = min(cands)[1]
    if best is None:  # OpenCV assumes real eigenvalues; fall back to the closed-form cubic
        mc = Mc.tolist()
        best_abs = math.inf
        for lam in _real_eigenvalues3(mc):
            v = _null_vector3(mc, lam)
            if 4.0 * v[0] * v[2] - v[1] * v[1] > 0 and abs(lam) < best_abs:
                best, best_abs = v, abs(lam)
    if best is None:
        raise EllipseFitError("no ellipse fits these points (degenerate or hyperbolic set)")
    upper = np.array(best)
    return np.concatenate([upper, T @ upper])


# C1⁻¹ for the constraint matrix C1 = [[0, 0, 2], [0, −1, 0], [2, 0, 0]] (4ac − b² = 1)
_C1_INV = np.array([[0.0, 0.0, 0.5], [0.0, -1.0, 0.0], [0.5, 0.0, 0.0]])


def _is_ellipse(th: np.ndarray) -> bool:
    a, b, c = th[0], th[1], th[2]
    return bool(np.all(np.isfinite(th)) and 4.0 * a * c - b * b > 1e-12 * float(th @ th))


def _is_arc(th: np.ndarray) -> bool:
    """True if the points (centred at their weighted mean, RMS radius √2) are an arc rather than
    a closed boundary: on a closed, evenly weighted boundary the mean is the ellipse's centre
    (central symmetry); a missing sector of 2π/16 already moves it by ≈ 0.065 of the radius."""
    a, b, c, d, e, _ = th.tolist()
    det2 = 4.0 * a * c - b * b
    x0 = (b * e - 2.0 * c * d) / det2
    y0 = (b * d - 2.0 * a * e) / det2
    return x0 * x0 + y0 * y0 > 0.03**2 * 2.0


def fit_ellipse(points, weights=None, *, refine_iterations: int | None = None) -> Ellipse:
    """Weighted least-squares ellipse through 2-D ``points`` (N×2, N ≥ 5).

    Step 1 minimises the paper's eq. 2, ``Σ wᵢ Q(Xᵢ, Yᵢ)²`` with Q of eq. 1, subject to the
    ellipse constraint 4ac − b² = 1 (direct fit: Fitzgibbon et al. 1999; Halíř & Flusser 1998),
    in Hartley-normalised coordinates. Step 2 refines it with up to ``refine_iterations``
    Gauss–Newton steps on eq. 2 with each wᵢ divided by |∇Q(Xᵢ, Yᵢ)|² (the Sampson distance,
    a first-order geometric distance that removes the algebraic fit's bias on arcs); a step
    that would leave the set of ellipses is not taken. ``refine_iterations=None`` (default)
    refines with 3 steps only when the points leave an angular gap (an arc): on a closed,
    densely sampled boundary the direct fit is already unbiased to well below the noise and the
    refinement costs ~3× the fit. ``weights`` (N, ≥ 0; default all 1)
    are the paper's wᵢ, e.g. the boundary arc length each point stands for.

    Returns the :class:`Ellipse` in the input's coordinates. Raises :class:`EllipseFitError`
    for fewer than 5 points, non-finite input, collinear or otherwise degenerate point sets.
    """
    p, w = _validate(points, weights)
    wk = w * (1.0 / float(w.sum()))
    mean = wk @ p
    centred = p - mean
    rms = math.sqrt(float(wk @ (centred * centred).sum(axis=1)))
    if not rms > 0:
        raise EllipseFitError("all points coincide")
    scale = math.sqrt(2.0) / rms
    xy = centred * scale
    x, y = xy[:, 0], xy[:, 1]
    design = np.empty((x.shape[0], 6))
    design[:, 0] = x * x
    design[:, 1] = x * y
    design[:, 2] = y * y
    design[:, 3] = x
    design[:, 4] = y
    design[:, 5] = 1.0
    th = _direct_fit(design, wk)
    th /= math.sqrt(float(th @ th))
    if refine_iterations is None:
        refine_iterations = 3 if _is_arc(th) else 0
    if refine_iterations > 0:
        sw = np.sqrt(wk)
        # ∂(gx, gy)/∂θ for gx = 2ax + by + d, gy = bx + 2cy + e
        dgx = np.zeros_like(design)
        dgx[:, 0] = 2 * x
        dgx[:, 1] = y
        dgx[:, 3] = 1.0
        dgy = np.zeros_like(design)
        dgy[:, 1] = x
        dgy[:, 2] = 2 * y
        dgy[:, 4] = 1.0
        for _ in range(refine_iterations):
            a, b, c, d, e, _f = th.tolist()
            q = design @ th
            gx = 2 * a * x + b * y + d
            gy = b * x + 2 * c * y + e
            ig = 1.0 / np.sqrt(np.maximum(gx * gx + gy * gy, 1e-300))
            r = sw * q * ig
            J = design * (sw * ig)[:, None] - (r * ig * ig)[:, None] * (gx[:, None] * dgx + gy[:, None] * dgy)
            A = J.T @ J + np.outer(th, th)  # r is scale-free in θ: fix the gauge along θ
            solved, step = cv2.solve(A, J.T @ r, flags=cv2.DECOMP_CHOLESKY)
            if not solved:
                break
            step = step.ravel()
            new = th - step
            new /= math.sqrt(float(new @ new))
            if not _is_ellipse(new):
                break
            done = float(step @ step) < 1e-18
            th = new
            if done:
                break
    # back to input coordinates: x_n = s (x − m)  →  M_in = Hᵀ M_n H
    a, b, c, d, e, f = th.tolist()
    mx, my = float(mean[0]), float(mean[1])
    s = scale
    # expand Q_n(s(x − mx), s(y − my)) symbolically
    A2, B2, C2 = a * s * s, b * s * s, c * s * s
    D2 = -2 * A2 * mx - B2 * my + d * s
    E2 = -B2 * mx - 2 * C2 * my + e * s
    F2 = A2 * mx * mx + B2 * mx * my + C2 * my * my - d * s * mx - e * s * my + f
    return Ellipse.from_conic([A2, B2, C2, D2, E2, F2])


def ellipse_from_cv_box(box) -> Ellipse:
    """Ellipse from an OpenCV RotatedRect ``((cx, cy), (width, height), angle_deg)`` as returned
    by ``cv2.fitEllipse*`` (full axes; the width axis at ``angle_deg``)."""
    (cx, cy), (wd, ht), ang = box
    return Ellipse.from_params((cx, cy), (0.5 * wd, 0.5 * ht), np.deg2rad(ang))
