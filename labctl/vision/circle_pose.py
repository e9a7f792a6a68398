"""3-D pose of a circle of known radius from its image ellipse (He et al. 1996, §3.2).

The ellipse and the camera's centre define an oblique elliptic cone. Reducing the cone to its
canonical frame (the eigenvectors of its quadric) gives the planes that cut it in circles in
closed form (Safaee-Rad, Tchoukanov, Smith & Benhabib, "Three-dimensional location estimation
of circular features for machine vision", IEEE T-RA 8(5), 1992): with eigenvalues
λ1 ≥ λ2 > 0 > λ3 and eigenvectors e1, e2, e3 the two candidate normals are

    n± = ± √((λ1 − λ2)/(λ1 − λ3)) · e1 + √((λ2 − λ3)/(λ1 − λ3)) · e3.

In each candidate plane the section is the circle λ2 (p² + q²) + 2 d β q + γ d² = 0 (plane
coordinates p along e2, q along n × e2, plane offset d), whose radius is proportional to d;
the known radius fixes d and the centre, taking the solution in front of the camera (z > 0).
The ellipse's centre is *not* the image of the circle's centre; it is never used as one.

Frames and units: camera frame (+z optical axis, +x columns, +y rows), mm; the ellipse is
in undistorted pixels under the camera matrix K.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .ellipse import Ellipse, EllipseFitError, _fit, _null_vector3, _validate

if TYPE_CHECKING:
    from ..geometry import CameraModel
    from .markers import Marker


class CirclePoseError(ValueError):
    """The ellipse and camera do not define a real circle in front of the camera."""


@dataclass(frozen=True)
class CirclePose:
    """A circle's centre (mm, camera frame, z > 0) and unit normal pointing towards the camera
    (normal · centre < 0)."""

    center: np.ndarray
    normal: np.ndarray

    def __eq__(self, other) -> bool:  # element-wise arrays: compare by value, not truth of an array
        if not isinstance(other, CirclePose):
            return NotImplemented
        return bool(np.array_equal(self.center, other.center) and np.array_equal(self.normal, other.normal))

    def to_dict(self) -> dict:
        """JSON-ready dict: ``center_mm`` (camera frame, mm) and unit ``normal``."""
        return {"center_mm": [float(v) for v in self.center], "normal": [float(v) for v in self.normal]}


def _check_radius(radius) -> float:
    try:
        radius = float(radius)
    except (TypeError, ValueError):
        raise CirclePoseError(f"radius must be a number of mm, got {radius!r}") from None
    if not (math.isfinite(radius) and radius > 0):
        raise CirclePoseError(f"radius must be a positive number of mm, got {radius!r}")
    return radius


def _camera_matrix(K) -> list[list[float]]:
    try:
        K = np.asarray(K, dtype=float)
    except (TypeError, ValueError):
        raise CirclePoseError("K must be a finite 3×3 camera matrix") from None
    if K.shape != (3, 3) or not math.isfinite(float(K.sum())):
        raise CirclePoseError("K must be a finite 3×3 camera matrix")
    return K.tolist()


def _cone(conic, K: list[list[float]]) -> list[list[float]]:
    """Cone quadric Q = Kᵀ C K (pixel x = K X, so Xᵀ Q X = 0 on the cone), C the conic matrix
    of ``conic`` (a, b, c, d, e, f); unrolled 3×3 algebra, upper triangle returned as a full
    symmetric nested list."""
    a, b, c, d, e, f = conic
    b2, d2, e2 = 0.5 * b, 0.5 * d, 0.5 * e
    (k00, k01, k02), (k10, k11, k12), (k20, k21, k22) = K
    # C K, column by column
    ck00, ck10, ck20 = a * k00 + b2 * k10 + d2 * k20, b2 * k00 + c * k10 + e2 * k20, d2 * k00 + e2 * k10 + f * k20
    ck01, ck11, ck21 = a * k01 + b2 * k11 + d2 * k21, b2 * k01 + c * k11 + e2 * k21, d2 * k01 + e2 * k11 + f * k21
    ck02, ck12, ck22 = a * k02 + b2 * k12 + d2 * k22, b2 * k02 + c * k12 + e2 * k22, d2 * k02 + e2 * k12 + f * k22
    q00 = k00 * ck00 + k10 * ck10 + k20 * ck20
    q01 = k00 * ck01 + k10 * ck11 + k20 * ck21
    q02 = k00 * ck02 + k10 * ck12 + k20 * ck22
    q11 = k01 * ck01 + k11 * ck11 + k21 * ck21
    q12 = k01 * ck02 + k11 * ck12 + k21 * ck22
    q22 = k02 * ck02 + k12 * ck12 + k22 * ck22
    return [[q00, q01, q02], [q01, q11, q12], [q02, q12, q22]]


def _cone_frame(Q: list[list[float]]):
    """Canonical frame of a real elliptic cone: eigenvalues λ1 ≥ λ2 > 0 > λ3 of ±Q/|Q| and the
    unit eigenvectors e1, e3. λ3 (the isolated one) comes from the closed-form cubic, e3 from
    the null space of Q − λ3 I (well conditioned: λ3 is far from λ1, λ2), and λ1, λ2, e1 from
    the 2×2 problem in the plane ⊥ e3, which stays exact when λ1 ≈ λ2 (a frontal circle)."""
    (q00, q01, q02), (_, q11, q12), (_, _, q22) = Q
    norm = math.sqrt(q00 * q00 + q11 * q11 + q22 * q22 + 2.0 * (q01 * q01 + q02 * q02 + q12 * q12))
    if not (norm > 0 and math.isfinite(norm)):
        raise CirclePoseError("degenerate cone")
    det = q00 * (q11 * q22 - q12 * q12) - q01 * (q01 * q22 - q12 * q02) + q02 * (q01 * q12 - q11 * q02)
    s = (-1.0 if det > 0 else 1.0) / norm  # signature (+, +, −) has det < 0
    q00, q01, q02, q11, q12, q22 = (s * q00, s * q01, s * q02, s * q11, s * q12, s * q22)
    # smallest eigenvalue of the symmetric matrix (trigonometric form of the cubic)
    m = (q00 + q11 + q22) / 3.0
    off = q01 * q01 + q02 * q02 + q12 * q12
    a0, a1, a2 = q00 - m, q11 - m, q22 - m
    p = math.sqrt((a0 * a0 + a1 * a1 + a2 * a2 + 2.0 * off) / 6.0)
    if not p > 0:
        raise CirclePoseError("the ellipse does not define a real elliptic cone")
    half_det_b = 0.5 * (a0 * (a1 * a2 - q12 * q12) - q01 * (q01 * a2 - q12 * q02) + q02 * (q01 * q12 - a1 * q02)) / p**3
    phi = math.acos(max(-1.0, min(1.0, half_det_b))) / 3.0
    lam3 = m + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    e3 = _null_vector3([[q00, q01, q02], [q01, q11, q12], [q02, q12, q22]], lam3)
    x3, y3, z3 = e3
    if x3 == y3 == z3 == 0.0:
        raise CirclePoseError("the ellipse does not define a real elliptic cone")
    # orthonormal u, v spanning the plane ⊥ e3 (u from the axis least aligned with e3)
    if abs(x3) <= abs(y3) and abs(x3) <= abs(z3):
        u = (0.0, z3, -y3)
    elif abs(y3) <= abs(z3):
        u = (-z3, 0.0, x3)
    else:
        u = (y3, -x3, 0.0)
    un = 1.0 / math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
    u = (u[0] * un, u[1] * un, u[2] * un)
    v = (y3 * u[2] - z3 * u[1], z3 * u[0] - x3 * u[2], x3 * u[1] - y3 * u[0])

    def quad(a, b):  # aᵀ Q b
        return (a[0] * (q00 * b[0] + q01 * b[1] + q02 * b[2]) + a[1] * (q01 * b[0] + q11 * b[1] + q12 * b[2])
                + a[2] * (q02 * b[0] + q12 * b[1] + q22 * b[2]))

    l3 = quad(e3, e3)  # Rayleigh quotient: accurate to O(ε²) given e3
    quu, quv, qvv = quad(u, u), quad(u, v), quad(v, v)
    mid, rad = 0.5 * (quu + qvv), math.hypot(0.5 * (quu - qvv), quv)
    l1, l2 = mid + rad, mid - rad
    theta = 0.5 * math.atan2(2.0 * quv, quu - qvv)  # eigenvector of the larger 2×2 eigenvalue
    ct, st = math.cos(theta), math.sin(theta)
    e1 = [ct * u[0] + st * v[0], ct * u[1] + st * v[1], ct * u[2] + st * v[2]]
    return l1, l2, l3, e1, e3


def _poses_from_cone(Q: list[list[float]], radius: float) -> tuple[CirclePose, CirclePose]:
    """Both circle poses of ``radius`` on the cone ``Q`` (camera frame), Safaee-Rad et al. 1992."""
    l1, l2, l3, e1, e3 = _cone_frame(Q)
    if not (l2 > 0 > l3 and math.isfinite(l1)):
        raise CirclePoseError("the ellipse does not define a real elliptic cone")
    span = l1 - l3
    g = math.sqrt(max(l1 - l2, 0.0) / span)
    h = math.sqrt(max(l2 - l3, 0.0) / span)
    gamma = l1 * g * g + l3 * h * h
    x1, y1, z1 = e1
    x3, y3, z3 = e3
    poses = []
    for sign in (1.0, -1.0):
        # canonical frame: n = (s g, 0, h), u = (0, 1, 0), v = n × u = (−h, 0, s g)
        beta = sign * g * h * (l3 - l1)
        bl = beta / l2
        k2 = bl * bl - gamma / l2
        if not k2 > 0:
            raise CirclePoseError("the cone has no circular section (degenerate ellipse)")
        d = radius / math.sqrt(k2)
        sg = sign * g
        nx, ny, nz = sg * x1 + h * x3, sg * y1 + h * y3, sg * z1 + h * z3
        # centre = d (n − (β/λ2) v) with v = −h e1 + s g e3
        cx = d * (nx - bl * (-h * x1 + sg * x3))
        cy = d * (ny - bl * (-h * y1 + sg * y3))
        cz = d * (nz - bl * (-h * z1 + sg * z3))
        if cz < 0:
            cx, cy, cz = -cx, -cy, -cz
        nn = math.sqrt(nx * nx + ny * ny + nz * nz)
        if nx * cx + ny * cy + nz * cz > 0:
            nn = -nn
        if not (nn != 0 and math.isfinite(cx + cy + cz + nn)):
            raise CirclePoseError("non-finite circle pose")
        poses.append(CirclePose(np.array((cx, cy, cz)), np.array((nx / nn, ny / nn, nz / nn))))
    return poses[0], poses[1]


def circle_poses(ellipse: Ellipse, radius: float, K) -> tuple[CirclePose, CirclePose]:
    """Both candidate poses of a circle of ``radius`` (mm) whose image is ``ellipse``.

    ``ellipse`` is in undistorted pixels, ``K`` the 3×3 pinhole matrix. Returns two
    :class:`CirclePose` (centre in mm in the camera frame with z > 0, unit normal towards the
    camera). Closed-form cone/plane solution of Safaee-Rad et al. (1992), paper §3.2. When the
    circle faces the camera squarely the two candidates coincide. Raises
    :class:`CirclePoseError` if the cone is not a real elliptic cone.
    """
    radius = _check_radius(radius)
    return _poses_from_cone(_cone(ellipse.conic.tolist(), _camera_matrix(K)), radius)


def _undistorted_boundary(marker, camera):
    """(boundary N×2, weights N, K as nested lists) of a marker in undistorted pixels: Tsai's κ1
    model of ``camera`` (the same mapping as ``camera.undistort_pixels``), taken relative to the
    principal point when κ1 ≠ 0 (then K loses its c; the fit is translation invariant)."""
    boundary, weights = marker.boundary, marker.weights
    if not (isinstance(boundary, np.ndarray) and boundary.dtype == np.float64 and boundary.ndim == 2
            and boundary.shape[1] == 2 and boundary.shape[0] >= 5 and isinstance(weights, np.ndarray)
            and weights.dtype == np.float64 and weights.shape == (boundary.shape[0],)):
        boundary, weights = _validate(boundary, weights)
    K = camera.K.tolist()
    kappa1 = camera.kappa1
    if kappa1 != 0.0:
        # Tsai: x_u − c = (x_d − c)(1 + κ1 r²), r² in mm on the sensor (camera.undistort_pixels)
        sx, sy = camera.dpx / camera.sx, camera.dpy
        boundary = boundary - (K[0][2], K[1][2])
        boundary *= (1.0 + np.square(boundary) @ (kappa1 * sx * sx, kappa1 * sy * sy))[:, None]
        K = [[K[0][0], K[0][1], 0.0], [K[1][0], K[1][1], 0.0], K[2]]
    return boundary, weights, K


def marker_pose_candidates(marker, camera, radius: float) -> tuple[CirclePose, CirclePose]:
    """Both pose candidates of a detected marker (:class:`labctl.vision.Marker`).

    Undistorts the marker's sub-pixel boundary points (Tsai's κ1 model of ``camera``, a
    :class:`labctl.geometry.CameraModel`: the same mapping as ``camera.undistort_pixels``),
    refits the ellipse there with the marker's weights (paper §3.1), and solves the cone/plane
    problem with ``camera.K`` (paper §3.2). Centres in mm in the camera frame. Raises
    :class:`EllipseFitError` for a degenerate boundary, :class:`CirclePoseError` for no pose.
    """
    radius = _check_radius(radius)
    boundary, weights, K = _undistorted_boundary(marker, camera)
    # normalise about a boundary point (one radius off the centre: well conditioned, and cheaper
    # than the weighted centroid)
    conic = _fit(boundary, weights, None, origin=boundary[0].tolist())[0]
    return _poses_from_cone(_cone(conic, K), radius)


# Boundary residuals are correlated along the rim (blur, demosaicing, JPEG blocks span several
# points), so N points carry fewer than N independent errors: the point-noise covariance is
# inflated by this factor (≈ correlation length in points), and the per-point σ has a floor.
NOISE_INFLATION = 2.0
POINT_SIGMA_FLOOR_PX = 0.05
# Unmodelled lens (Tsai κ1 = 0, i.e. no distortion was calibrated): the assumed 1σ radial distortion at the
# image's half-diagonal, px (0.5 % of it on a 640×480 image; a plain machine-vision or webcam lens bends the
# corner by 0.5–3 %). Its effect on a marker is exactly the family x → c + (x − c)(1 + k r²), so it enters
# the covariance as one more sigma point, large for a marker far off-axis and near-frontal (its tilt is read
# from a ~1 % stretch there), small near the axis. See :func:`marker_poses`.
UNMODELLED_LENS_SIGMA_PX = 2.0
# A blur the detector modelled (defocus: the curvature correction σ²κ/2; motion: the half-level refit) leaves a
# systematic error the residual does not show: a uniform offset of the rim along its normal. 1σ of it, px: this
# share of the correction applied (its first-order model and the measured σ² are each good to ~15–30 %) ...
BLUR_SHIFT_SIGMA_FRACTION = 0.5
# ... plus this much per px of motion smear (the refit's axes are 0.07 px off in median at a 10 px smear) ...
MOTION_OFFSET_SIGMA_PER_PX = 0.01
# ... plus this share of the curvature bias a colour-only blur (JPEG chroma, demosaicing: not corrected) would
# imply if it were optical: the whole of it, since the error left is somewhere between none and that bias
UNMODELLED_BLUR_SIGMA_FRACTION = 1.0
# ... plus this share of the rim's move were an undeclared (read as linear) camera gamma-encoded instead
# (``MarkerQuality.response_unknown_px``): the whole of it, the error left being between none and that move; it
# adds to the other rim offsets (they are not independent of it: one offset, the sum), so until the response is
# declared or learned a marker whose pose that move could make gross comes out ``uncertain_*``: not fit for pose
RESPONSE_UNKNOWN_SIGMA_FRACTION = 1.0
# a pose whose normal σ exceeds this is flagged ``uncertain_normal``: a sixth of the 3° gross error, since
# highlights and blur add systematic errors of up to ~6 σ (measured on the degradation suite)
MAX_TRUSTED_NORMAL_SIGMA_RAD = math.radians(0.5)
# ... and one whose centre σ exceeds this fraction of its range ``uncertain_centre``: likewise a sixth of the
# gross centre error (2 % of the range); an unmodelled lens scales a marker's image by ~1 % off-axis
MAX_TRUSTED_CENTRE_SIGMA_FRACTION = 0.02 / 6.0
# flags that leave a marker fit for tracking (its centre): an ill-defined tilt does not move the centre, and its
# normal covariance says how ill-defined it is; every other flag (shape, blur, response, centre σ) refuses it
TRACKING_TOLERATED_FLAGS = frozenset({"uncertain_normal"})


@dataclass(frozen=True)
class MarkerPoses:
    """Both pose candidates of one marker with their uncertainty (paper §3.2).

    ``candidates``: the two :class:`CirclePose`; ``normal_sigma_rad``: each candidate's normal
    standard deviation (rad, √trace of its 3×3 covariance); ``normal_cov`` / ``center_cov``:
    2×3×3 covariances (unit-less / mm², camera frame) propagated from the ellipse's covariance
    (boundary-point noise σ from the fit residual, inflated by :data:`NOISE_INFLATION`);
    ``flags``: the marker's quality flags, plus ``uncertain_normal`` when a normal's σ exceeds
    :data:`MAX_TRUSTED_NORMAL_SIGMA_RAD` and ``uncertain_centre`` when a centre's σ exceeds
    :data:`MAX_TRUSTED_CENTRE_SIGMA_FRACTION` of its range; ``trusted``: no flag. :attr:`fit_for`
    says which uses the marker serves: a near-frontal marker (§3.2: its tilt is read from a < 1 %
    anisotropy) is kept for tracking with its honest, large normal covariance instead of refused."""

    candidates: tuple[CirclePose, CirclePose]
    normal_sigma_rad: tuple[float, float]
    normal_cov: np.ndarray
    center_cov: np.ndarray
    trusted: bool = True
    flags: tuple[str, ...] = ()

    @property
    def fit_for(self) -> tuple[str, ...]:
        """The uses this marker is good enough for: ``"tracking"`` (its centre: the fixed camera's
        Kalman filter, range, interception; every flag but :data:`TRACKING_TOLERATED_FLAGS` refuses it),
        ``"pose"`` and ``"standard_view"`` (its normal too: trusted; the standard view also needs the
        pair's duality resolved, §3.3). Empty: refused."""
        if self.trusted:
            return ("tracking", "pose", "standard_view")
        if set(self.flags) <= TRACKING_TOLERATED_FLAGS:
            return ("tracking",)
        return ()

    def to_dict(self) -> dict:
        """JSON-ready dict of the candidates, their normal σ (deg) and centre σ (mm), ``trusted``, ``flags``
        and ``fit_for``."""
        return {"candidates": [c.to_dict() for c in self.candidates],
                "normal_sigma_deg": [math.degrees(s) for s in self.normal_sigma_rad],
                "center_sigma_mm": [float(math.sqrt(max(np.trace(c), 0.0))) for c in self.center_cov],
                "trusted": self.trusted, "flags": list(self.flags), "fit_for": list(self.fit_for)}


def _lens_sigma_point(boundary, weights, K, radius: float, base, sigma_px: float, camera: CameraModel):
    """Half the change (normal, centre) of each candidate when the boundary is bent by ±1σ of an
    unmodelled radial distortion: x → c + (x − c)(1 ± k r²), k = ``sigma_px`` / r_ref³ (px⁻², r_ref
    the image's half-diagonal, c the principal point), refitted and posed again. None when a bent
    boundary gives no pose (the caller counts that as a huge error)."""
    cx, cy = K[0][2], K[1][2]  # 0 when the boundary was already taken about the principal point
    width, height = float(camera.width), float(camera.height)
    k = sigma_px / (0.5 * math.hypot(width, height)) ** 3
    rel = boundary - (cx, cy)
    r2 = np.square(rel).sum(axis=1)
    Kc = [[K[0][0], K[0][1], 0.0], [K[1][0], K[1][1], 0.0], K[2]]  # K for points about the principal point
    out = []
    for sgn in (1.0, -1.0):
        bent = rel * (1.0 + sgn * k * r2)[:, None]
        try:
            conic = _fit(bent, weights, None, origin=bent[0].tolist())[0]
            out.append(_poses_from_cone(_cone(conic, Kc), radius))
        except (CirclePoseError, EllipseFitError, ValueError):
            return None
    deltas = []
    for j in range(2):
        ref = base[j].normal
        plus = max(out[0], key=lambda c: float(c.normal @ ref))
        minus = max(out[1], key=lambda c: float(c.normal @ ref))
        deltas.append((0.5 * (plus.normal - minus.normal), 0.5 * (plus.center - minus.center)))
    return deltas


def _offset_sigma_point(boundary, weights, K, radius: float, sigma_px: float):
    """Half the change (normal, centre) of each candidate when every boundary point moves ±``sigma_px``
    along the fitted ellipse's outward normal (a blur's residual bias: the rim read uniformly too far
    in or out), refitted and posed; None when a moved boundary gives no pose."""
    conic = _fit(boundary, weights, None, origin=boundary[0].tolist())[0]
    a, b, c, d, e, _ = conic
    x, y = boundary[:, 0], boundary[:, 1]
    gx, gy = 2 * a * x + b * y + d, b * x + 2 * c * y + e
    g = np.sqrt(np.maximum(gx * gx + gy * gy, 1e-300))
    nrm = np.stack([gx / g, gy / g], axis=1)
    out = []
    for sgn in (1.0, -1.0):
        moved = boundary + sgn * sigma_px * nrm
        try:
            conic2 = _fit(moved, weights, None, origin=moved[0].tolist())[0]
            out.append(_poses_from_cone(_cone(conic2, K), radius))
        except (CirclePoseError, EllipseFitError, ValueError):
            return None
    return out


def marker_poses(marker: Marker, camera: CameraModel, radius: float, *,
                 lens_sigma_px: float | None = None) -> MarkerPoses:
    """Both pose candidates of a marker (as :func:`marker_pose_candidates`) with their covariance.

    The ellipse's five parameters (centre, semi-axes, angle) get the covariance σ² (JᵀJ)⁻¹ of a
    least-squares fit, J the Jacobian of the points' geometric (Sampson) distances, σ² the
    weighted mean squared residual (floor :data:`POINT_SIGMA_FLOOR_PX`) × :data:`NOISE_INFLATION`.
    It is propagated to each candidate's normal and centre by central differences along its
    principal axes (sigma points).

    Model error: a camera with no distortion term (``camera.kappa1 == 0``: its lens was not
    calibrated) may bend the image of a marker into another, equally good ellipse, which no fit
    residual shows. ``lens_sigma_px`` (default :data:`UNMODELLED_LENS_SIGMA_PX` when κ1 = 0, else
    0) is the assumed 1σ radial distortion at the image's half-diagonal; its effect on each
    candidate (one more sigma point: the boundary bent by ±1σ of Tsai's radial model, refitted
    and posed) is added to both covariances. It grows with the marker's distance from the
    principal point (the local stretch is ∝ r²), so off-axis markers of an uncalibrated camera
    get honest, larger normal σ (``uncertain_normal``, ambiguous duality) instead of confident
    wrong poses. Pass 0 for a camera known to be an exact pinhole. Raises as
    :func:`marker_pose_candidates`.
    """
    radius = _check_radius(radius)
    if lens_sigma_px is None:
        lens_sigma_px = UNMODELLED_LENS_SIGMA_PX if camera.kappa1 == 0.0 else 0.0
    lens_sigma_px = float(lens_sigma_px)
    if not (math.isfinite(lens_sigma_px) and lens_sigma_px >= 0.0):
        raise ValueError(f"lens_sigma_px must be a number of px ≥ 0, got {lens_sigma_px!r}")
    boundary, weights, K = _undistorted_boundary(marker, camera)
    conic = _fit(boundary, weights, None, origin=boundary[0].tolist())[0]
    base = _poses_from_cone(_cone(conic, K), radius)
    ell = Ellipse.from_conic(conic)
    params = np.array([ell.center[0], ell.center[1], ell.axes[0], ell.axes[1], ell.angle])

    def distances(p):
        e = Ellipse.from_params(p[:2], p[2:4], p[4])
        a, b, c, d, ee, f = e.conic
        x, y = boundary[:, 0], boundary[:, 1]
        gx, gy = 2 * a * x + b * y + d, b * x + 2 * c * y + ee
        return (a * x * x + b * x * y + c * y * y + d * x + ee * y + f) / np.sqrt(np.maximum(gx * gx + gy * gy,
                                                                                              1e-300))

    r0 = distances(params)
    steps = np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-4])
    J = np.empty((len(r0), 5))
    for k in range(5):
        dp = np.zeros(5)
        dp[k] = steps[k]
        J[:, k] = (distances(params + dp) - distances(params - dp)) / (2 * steps[k])
    sigma2 = max(float(weights @ (r0 * r0)) / float(weights.sum()), POINT_SIGMA_FLOOR_PX**2) * NOISE_INFLATION
    try:
        cov = sigma2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.diag(np.full(5, np.inf))
    lam, vec = np.linalg.eigh(0.5 * (cov + cov.T))
    ncov = np.zeros((2, 3, 3))
    ccov = np.zeros((2, 3, 3))
    if not np.all(np.isfinite(lam)):
        ncov[:] = np.eye(3)
        ccov[:] = np.eye(3) * 1e6
    else:
        for k in range(5):
            dp = math.sqrt(max(float(lam[k]), 0.0)) * vec[:, k]
            dp[4] = max(-0.5 * math.pi, min(0.5 * math.pi, dp[4]))  # the angle of a near-circle is free
            out = []
            for sgn in (1.0, -1.0):
                p = params + sgn * dp
                try:
                    pair = _poses_from_cone(_cone(Ellipse.from_params(p[:2], p[2:4], p[4]).conic.tolist(), K), radius)
                except (CirclePoseError, EllipseFitError, ValueError):
                    pair = None
                out.append(pair)
            for j in range(2):
                if out[0] is None or out[1] is None:
                    ncov[j] += np.eye(3)
                    ccov[j] += np.eye(3) * 1e4
                    continue
                ref = base[j].normal
                plus = max(out[0], key=lambda c: float(c.normal @ ref))
                minus = max(out[1], key=lambda c: float(c.normal @ ref))
                dn = 0.5 * (plus.normal - minus.normal)
                dc = 0.5 * (plus.center - minus.center)
                ncov[j] += np.outer(dn, dn)
                ccov[j] += np.outer(dc, dc)
    if lens_sigma_px > 0.0:
        lens = _lens_sigma_point(boundary, weights, K, radius, base, lens_sigma_px, camera)
        for j in range(2):
            if lens is None:
                ncov[j] += np.eye(3)
                ccov[j] += np.eye(3) * 1e4
            else:
                dn, dc = lens[j]
                ncov[j] += np.outer(dn, dn)
                ccov[j] += np.outer(dc, dc)
    q = marker.quality
    blur_sigma = 0.0 if q is None else (BLUR_SHIFT_SIGMA_FRACTION * q.blur_shift_px
                                        + MOTION_OFFSET_SIGMA_PER_PX * q.motion_px
                                        + UNMODELLED_BLUR_SIGMA_FRACTION * q.blur_unmodelled_px
                                        + RESPONSE_UNKNOWN_SIGMA_FRACTION * q.response_unknown_px)
    if blur_sigma > 0.0:
        moved = _offset_sigma_point(boundary, weights, K, radius, blur_sigma)
        for j in range(2):
            if moved is None:
                ncov[j] += np.eye(3)
                ccov[j] += np.eye(3) * 1e4
                continue
            plus = max(moved[0], key=lambda c: float(c.normal @ base[j].normal))
            minus = max(moved[1], key=lambda c: float(c.normal @ base[j].normal))
            dn, dc = 0.5 * (plus.normal - minus.normal), 0.5 * (plus.center - minus.center)
            ncov[j] += np.outer(dn, dn)
            ccov[j] += np.outer(dc, dc)
    sig0, sig1 = (float(math.sqrt(max(np.trace(c), 0.0))) for c in ncov)
    sig = (sig0, sig1)
    flags = tuple(q.flags) if q is not None else ("no_quality",)
    if not max(sig) <= MAX_TRUSTED_NORMAL_SIGMA_RAD:  # e.g. a marker facing the camera: its tilt is ill-defined
        flags += ("uncertain_normal",)
    if not all(math.sqrt(max(float(np.trace(ccov[j])), 0.0)) <= MAX_TRUSTED_CENTRE_SIGMA_FRACTION
               * float(np.linalg.norm(base[j].center)) for j in range(2)):
        flags += ("uncertain_centre",)
    trusted = not flags
    return MarkerPoses(base, sig, ncov, ccov, trusted, flags)
