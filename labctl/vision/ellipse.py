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
            q = conic.tolist() if isinstance(conic, np.ndarray) else [float(v) for v in conic]
            if len(q) != 6:
                raise ValueError
            a, b, c, d, e, f = q
            norm2 = float(a * a + b * b + c * c + d * d + e * e + f * f)
        except (TypeError, ValueError):
            raise EllipseFitError("conic must be 6 finite coefficients") from None
        if not math.isfinite(norm2):
            raise EllipseFitError("conic must be 6 finite coefficients")
        if norm2 == 0.0:
            raise EllipseFitError("conic is all zero")
        r = (1.0 if a + c >= 0 else -1.0) / math.sqrt(norm2)
        a, b, c, d, e, f = a * r, b * r, c * r, d * r, e * r, f * r
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
        """Area π·A·B of the ellipse (units² of its points)."""
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
        """JSON-ready dict: centre, semi-axes, angle (rad) and conic coefficients."""
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
    (a, b, c), (d, e, f), (g, h, i) = m
    a -= lam
    e -= lam
    i -= lam
    # cross products r0×r1, r0×r2, r1×r2 of the rows (a b c), (d e f), (g h i)
    c01 = (b * f - c * e, c * d - a * f, a * e - b * d)
    c02 = (b * i - c * h, c * g - a * i, a * h - b * g)
    c12 = (e * i - f * h, f * g - d * i, d * h - e * g)
    n01 = c01[0] * c01[0] + c01[1] * c01[1] + c01[2] * c01[2]
    n02 = c02[0] * c02[0] + c02[1] * c02[1] + c02[2] * c02[2]
    n12 = c12[0] * c12[0] + c12[1] * c12[1] + c12[2] * c12[2]
    if n01 >= n02 and n01 >= n12:
        v, n = c01, n01
    elif n02 >= n12:
        v, n = c02, n02
    else:
        v, n = c12, n12
    if not n > 0:
        return [0.0, 0.0, 0.0]
    s = 1.0 / math.sqrt(n)
    return [v[0] * s, v[1] * s, v[2] * s]


# degree of scatter-matrix entry (i, j) for the design row [x², xy, y², x, y, 1]
_DEGREE = np.add.outer([2, 2, 2, 1, 1, 0], [2, 2, 2, 1, 1, 0]).astype(float)


def _moment_matrix(p: np.ndarray, w: np.ndarray, origin=None,
                   scale: float | None = None) -> tuple[list[list[float]], float, float, float]:
    """Weighted scatter matrix S = Σ wᵢ Dᵢ Dᵢᵀ of the design rows Dᵢ = [x², xy, y², x, y, 1] in
    Hartley-style normalised coordinates s·(p − origin). ``origin``: the weighted centroid
    (default) or any point near the centre; ``scale`` s: by default such that the RMS distance
    from the origin is √2, or a given value of about √2 / radius. The fit is invariant to both
    (and to the overall weight scale, so S is not divided by Σw); they only condition the
    numbers. Returns (S as nested lists, origin x, origin y, s)."""
    if origin is None:
        wsum = float(w.sum())
        if not wsum > 0:
            raise EllipseFitError("weights sum to zero")
        mx, my = ((w @ p) * (1.0 / wsum)).tolist()
    else:
        mx, my = origin
        if not (math.isfinite(mx) and math.isfinite(my)):
            raise EllipseFitError("points contain NaN or infinity")
    rows = np.empty((6, p.shape[0]))
    c = rows[3:5]
    np.subtract(p.T, ((mx,), (my,)), out=c)
    if scale is not None:
        c *= scale
    x, y = c
    np.multiply(x, x, out=rows[0])
    np.multiply(x, y, out=rows[1])
    np.multiply(y, y, out=rows[2])
    rows[5] = 1.0
    S = (rows * w) @ rows.T
    if scale is None:
        wsum = float(S[5, 5])
        var = float(S[0, 5] + S[2, 5]) / wsum if wsum > 0 else math.nan  # mean squared distance from the origin
        if not (var > 0 and math.isfinite(var)):
            raise EllipseFitError("all points coincide (or are not finite)")
        scale = math.sqrt(2.0 / var)
        S *= np.power(scale, _DEGREE)  # entry (i, j) scales with s^(deg_i + deg_j)
    S = S.tolist()
    if not (S[5][5] > 0 and math.isfinite(S[0][5] + S[2][5]) and S[0][5] + S[2][5] > 0):
        raise EllipseFitError("all points coincide, are not finite or have no weight")
    return S, mx, my, scale


def _direct_fit(S: list[list[float]]) -> tuple[list[float], float]:
    """Halíř–Flusser direct ellipse fit (constraint 4ac − b² = 1) from the 6×6 weighted scatter
    matrix ``S`` of the design rows [x², xy, y², x, y, 1]: the unit-norm conic θ in S's
    coordinates and its objective θᵀSθ (the weighted mean squared algebraic residual).
    Unrolled float algebra: at 3×3 it is cheaper than array calls."""
    (s00, s01, s02, s03, s04, s05), (_, s11, s12, s13, s14, s15), (_, _, s22, s23, s24, s25), \
        (_, _, _, s33, s34, s35), (_, _, _, _, s44, s45), (_, _, _, _, _, s55) = S
    # S3⁻¹ (symmetric) by the adjugate
    A00, A01, A02 = s44 * s55 - s45 * s45, s35 * s45 - s34 * s55, s34 * s45 - s35 * s44
    A11, A12, A22 = s33 * s55 - s35 * s35, s34 * s35 - s33 * s45, s33 * s44 - s34 * s34
    det = s33 * A00 + s34 * A01 + s35 * A02
    big = max(abs(s33), abs(s34), abs(s35), abs(s44), abs(s45), abs(s55))
    if not abs(det) > 1e-10 * big**3:
        raise EllipseFitError("degenerate point set (collinear or too few distinct points)")
    r = -1.0 / det
    # T = −S3⁻¹ S2ᵀ: the linear part (d, e, f) = T (a, b, c); S2 rows are (s_i3, s_i4, s_i5)
    t00 = r * (A00 * s03 + A01 * s04 + A02 * s05)
    t01 = r * (A00 * s13 + A01 * s14 + A02 * s15)
    t02 = r * (A00 * s23 + A01 * s24 + A02 * s25)
    t10 = r * (A01 * s03 + A11 * s04 + A12 * s05)
    t11 = r * (A01 * s13 + A11 * s14 + A12 * s15)
    t12 = r * (A01 * s23 + A11 * s24 + A12 * s25)
    t20 = r * (A02 * s03 + A12 * s04 + A22 * s05)
    t21 = r * (A02 * s13 + A12 * s14 + A22 * s15)
    t22 = r * (A02 * s23 + A12 * s24 + A22 * s25)
    # M = S1 + S2 T (symmetric: the Schur complement of S3)
    m00 = s00 + s03 * t00 + s04 * t10 + s05 * t20
    m01 = s01 + s03 * t01 + s04 * t11 + s05 * t21
    m02 = s02 + s03 * t02 + s04 * t12 + s05 * t22
    m11 = s11 + s13 * t01 + s14 * t11 + s15 * t21
    m12 = s12 + s13 * t02 + s14 * t12 + s15 * t22
    m22 = s22 + s23 * t02 + s24 * t12 + s25 * t22
    # C1⁻¹ M with C1 = [[0, 0, 2], [0, −1, 0], [2, 0, 0]]
    Mc = [[0.5 * m02, 0.5 * m12, 0.5 * m22], [-m01, -m11, -m12], [0.5 * m00, 0.5 * m01, 0.5 * m02]]
    best, best_lam = None, 0.0
    # the ellipse is the eigenvector with 4ac − b² > 0; in exact arithmetic it belongs to the
    # only non-negative eigenvalue, so try the largest first
    lams = sorted(_real_eigenvalues3(Mc), reverse=True)
    best_abs = math.inf
    for lam in lams:
        v = _null_vector3(Mc, lam)
        if 4.0 * v[0] * v[2] - v[1] * v[1] > 0 and abs(lam) < best_abs:
            best, best_abs, best_lam = v, abs(lam), lam
            if lam >= 0:
                break
    if best is None:
        raise EllipseFitError("no ellipse fits these points (degenerate or hyperbolic set)")
    a, b, c = best
    d = t00 * a + t01 * b + t02 * c
    e = t10 * a + t11 * b + t12 * c
    f = t20 * a + t21 * b + t22 * c
    norm2 = a * a + b * b + c * c + d * d + e * e + f * f
    if not (norm2 > 0 and math.isfinite(norm2)):
        raise EllipseFitError("no ellipse fits these points (degenerate set)")
    # objective θᵀSθ = λ (4ac − b²) for the eigenvector (Schur complement: vᵀMv = λ vᵀC1v)
    objective = max(best_lam * (4.0 * a * c - b * b), 0.0) / norm2
    r = 1.0 / math.sqrt(norm2)
    return [a * r, b * r, c * r, d * r, e * r, f * r], objective


def _is_ellipse(th: np.ndarray) -> bool:
    a, b, c = th[0], th[1], th[2]
    return bool(np.all(np.isfinite(th)) and 4.0 * a * c - b * b > 1e-12 * float(th @ th))


def _is_arc(th, S: list[list[float]]) -> bool:
    """True if the points are an arc rather than a closed boundary: on a closed, evenly weighted
    boundary the weighted mean is the ellipse's centre (central symmetry); a missing sector of
    2π/16 already moves it by ≈ 0.065 of the RMS radius. ``th`` and the scatter matrix ``S``
    in the same normalised coordinates (S[3][5] / S[5][5], S[4][5] / S[5][5] are the weighted
    mean)."""
    a, b, c, d, e, _ = th
    det2 = 4.0 * a * c - b * b
    wsum = S[5][5]
    mx, my = S[3][5] / wsum, S[4][5] / wsum
    dx = (b * e - 2.0 * c * d) / det2 - mx
    dy = (b * d - 2.0 * a * e) / det2 - my
    rms2 = (S[0][5] + S[2][5]) / wsum - mx * mx - my * my  # mean squared distance from the mean
    return dx * dx + dy * dy > 0.03**2 * rms2


def _sampson_refine(p: np.ndarray, wk: np.ndarray, mx: float, my: float, s: float, th: list[float],
                    iterations: int) -> list[float]:
    """Up to ``iterations`` Gauss–Newton steps on eq. 2 with wᵢ/|∇Q|² (Sampson distance) from
    the unit conic ``th`` in the normalised coordinates s·(p − mean)."""
    xy = (p - (mx, my)) * s
    x, y = xy[:, 0], xy[:, 1]
    design = np.empty((x.shape[0], 6))
    design[:, 0] = x * x
    design[:, 1] = x * y
    design[:, 2] = y * y
    design[:, 3] = x
    design[:, 4] = y
    design[:, 5] = 1.0
    theta = np.array(th)
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
    for _ in range(iterations):
        a, b, c, d, e, _f = theta.tolist()
        q = design @ theta
        gx = 2 * a * x + b * y + d
        gy = b * x + 2 * c * y + e
        ig = 1.0 / np.sqrt(np.maximum(gx * gx + gy * gy, 1e-300))
        r = sw * q * ig
        J = design * (sw * ig)[:, None] - (r * ig * ig)[:, None] * (gx[:, None] * dgx + gy[:, None] * dgy)
        A = J.T @ J + np.outer(theta, theta)  # r is scale-free in θ: fix the gauge along θ
        solved, step = cv2.solve(A, J.T @ r, flags=cv2.DECOMP_CHOLESKY)
        if not solved:
            break
        step = step.ravel()
        new = theta - step
        new /= math.sqrt(float(new @ new))
        if not _is_ellipse(new):
            break
        done = float(step @ step) < 1e-18
        theta = new
        if done:
            break
    return theta.tolist()


def _fit(p: np.ndarray, w: np.ndarray, refine_iterations: int | None = None, origin=None,
         scale: float | None = None) -> tuple[list[float], float]:
    """Core of :func:`fit_ellipse` on already validated float arrays (N×2 points, N weights
    with a positive sum; ``origin``/``scale``: optional normalisation, see
    :func:`_moment_matrix`). Returns the conic (a, b, c, d, e, f) of the fitted ellipse in
    ``p``'s coordinates (not normalised) and, for the direct fit, the first-order RMS distance
    of the points to it, √(Σ wᵢQᵢ² / Σ wᵢ|∇Qᵢ|²) (same units as ``p``; NaN after a Sampson
    refinement). Raises :class:`EllipseFitError` for degenerate sets."""
    S, mx, my, s = _moment_matrix(p, w, origin, scale)
    th, objective = _direct_fit(S)
    if refine_iterations is None:
        refine_iterations = 3 if _is_arc(th, S) else 0
    if refine_iterations > 0:
        wk = w * (1.0 / float(w.sum()))
        th = _sampson_refine(p, wk, mx, my, s, th, refine_iterations)
        a, b, c, d, e, f = th
        rms = math.nan
    else:
        a, b, c, d, e, f = th
        # Σ wᵢ|∇Qᵢ|² from the moments up to second order
        sxx, sxy, syy, sx, sy, s1 = S[0][5], S[1][5], S[2][5], S[3][5], S[4][5], S[5][5]
        grad2 = ((4 * a * a + b * b) * sxx + 4 * b * (a + c) * sxy + (b * b + 4 * c * c) * syy
                 + (d * d + e * e) * s1 + 2 * d * (2 * a * sx + b * sy) + 2 * e * (b * sx + 2 * c * sy))
        rms = math.sqrt(objective / grad2) / s if grad2 > 0 else math.inf
    # back to input coordinates: Q_n(s(x − mx), s(y − my)) expanded symbolically
    A2, B2, C2 = a * s * s, b * s * s, c * s * s
    D2 = -2 * A2 * mx - B2 * my + d * s
    E2 = -B2 * mx - 2 * C2 * my + e * s
    F2 = A2 * mx * mx + B2 * mx * my + C2 * my * my - d * s * mx - e * s * my + f
    return [A2, B2, C2, D2, E2, F2], rms


def _fit_conic(p: np.ndarray, w: np.ndarray, refine_iterations: int | None = None) -> list[float]:
    """Conic (a, b, c, d, e, f) of :func:`_fit`, for validated arrays."""
    return _fit(p, w, refine_iterations)[0]


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
    return Ellipse.from_conic(_fit_conic(p, w, refine_iterations))


def ellipse_from_cv_box(box) -> Ellipse:
    """Ellipse from an OpenCV RotatedRect ``((cx, cy), (width, height), angle_deg)`` as returned
    by ``cv2.fitEllipse*`` (full axes; the width axis at ``angle_deg``)."""
    (cx, cy), (wd, ht), ang = box
    return Ellipse.from_params((cx, cy), (0.5 * wd, 0.5 * ht), np.deg2rad(ang))
