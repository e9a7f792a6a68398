"""Tsai's camera calibration (1987) from known 3D points and their image pixels.

Implements R. Y. Tsai, "A versatile camera calibration technique for high-accuracy 3D machine
vision metrology using off-the-shelf TV cameras and lenses", IEEE J. Robotics and Automation
3(4), 1987, in numpy/scipy, with the stages and names of Reg Willson's reference implementation
(v3.0b3):

* non-coplanar points, §IV.B: the radial alignment constraint (RAC, eq. 15/16) gives R, Tx, Ty
  and the scale factor sx from a linear system of 7 unknowns; then f and Tz from a linear system
  ignoring distortion (eq. 17 analogue); then a nonlinear refinement of f, Tz and κ1;
* coplanar points, §IV.A: the RAC with 5 unknowns (sx known), Ty from eq. 12/13, the third
  rotation row from orthonormality, then the same f/Tz/κ1 stages;
* a full optimisation of every parameter, image centre Cx, Cy included, of the pixel residual
  (Willson's ``ncc_full_optimization`` / ``cc_full_optimization``; sx is left out in the
  coplanar case, where it is not observable);
* OpenCV's ``calibrateCamera`` as a side-by-side baseline (:func:`calibrate_opencv`).

Frames: world points ``points_w`` (N, 3) in mm; pixels (N, 2) are distorted frame-buffer
coordinates. The result's ``T_c_w`` maps world points into the camera frame (Tsai's R, T).
The projection itself is :class:`labctl.geometry.CameraModel` (Tsai eq. 1–5).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..geometry import CameraModel, make_T, orthonormalize, rpy_from_matrix_willson, rpy_willson

MIN_POINTS_NONCOPLANAR = 11
MIN_POINTS_COPLANAR = 8
COPLANAR_TOL = 1e-6  # smallest/largest singular value of the centred points below this: a plane


class CalibrationInputError(ValueError):
    """The points cannot be calibrated (too few, non-finite, wrong geometry). Message: one line."""


@dataclass(frozen=True)
class Sensor:
    """What is known about the camera before calibration (Tsai §II): element sizes and counts,
    the nominal image centre (px) and the image size."""

    ncx: float
    nfx: float
    dx: float
    dy: float
    cx: float
    cy: float
    width: int = 640
    height: int = 480
    sx: float = 1.0  # used as known in the coplanar case

    def camera(self, f: float = 1.0, kappa1: float = 0.0, sx: float | None = None) -> CameraModel:
        """A camera model of this sensor with the given ``f`` (mm), ``kappa1`` (1/mm²) and ``sx``."""
        return CameraModel(f=f, kappa1=kappa1, sx=self.sx if sx is None else sx, cx=self.cx, cy=self.cy,
                           dx=self.dx, dy=self.dy, ncx=self.ncx, nfx=self.nfx, width=self.width,
                           height=self.height)

    @classmethod
    def of(cls, cam: CameraModel) -> Sensor:
        """The sensor of a (nominal) camera model: its element sizes, centre and size."""
        return cls(ncx=cam.ncx, nfx=cam.nfx, dx=cam.dx, dy=cam.dy, cx=cam.cx, cy=cam.cy,
                   width=cam.width, height=cam.height, sx=cam.sx)


@dataclass(frozen=True)
class TsaiResult:
    """A calibrated camera: intrinsics ``camera``, extrinsics ``T_c_w`` (world → camera)."""

    camera: CameraModel
    T_c_w: np.ndarray
    method: str
    residuals_px: np.ndarray = field(repr=False)  # (N, 2) projected − observed

    @property
    def rms_px(self) -> float:
        """Root-mean-square reprojection residual (px)."""
        return float(np.sqrt(np.mean(np.sum(self.residuals_px**2, axis=1))))

    @property
    def max_px(self) -> float:
        """Largest reprojection residual (px)."""
        return float(np.max(np.linalg.norm(self.residuals_px, axis=1)))

    @property
    def n_points(self) -> int:
        """Number of calibration points used."""
        return int(len(self.residuals_px))

    def summary(self) -> dict:
        """Plain-data summary: the issue's JSON keys plus OpenCV's K and distortion equivalent."""
        cam = self.camera
        K, dist, fit_err = cam.to_opencv()
        return {
            "method": self.method,
            "n_points": self.n_points,
            "f_mm": cam.f,
            "kappa1": cam.kappa1,
            "cx": cam.cx,
            "cy": cam.cy,
            "sx": cam.sx,
            "R": self.T_c_w[:3, :3].tolist(),
            "T": self.T_c_w[:3, 3].tolist(),
            "rpy_rad": list(rpy_from_matrix_willson(self.T_c_w[:3, :3])),
            "rms_px": self.rms_px,
            "max_px": self.max_px,
            "K": K.tolist(),
            "dist": dist.tolist(),
            "opencv_equivalent_max_err_px": fit_err,
            "camera": cam.to_dict(),
        }


# --- input checks ---------------------------------------------------------------------------
def check_points(points_w: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate shapes and finiteness; return float arrays (N, 3) and (N, 2)."""
    P = np.asarray(points_w, dtype=float)
    p = np.asarray(pixels, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or p.ndim != 2 or p.shape[1] != 2 or len(P) != len(p):
        raise CalibrationInputError(f"expected N×3 world points and N×2 pixels, got {P.shape} and {p.shape}")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(p))):
        bad = int(np.flatnonzero(~(np.isfinite(P).all(1) & np.isfinite(p).all(1)))[0])
        raise CalibrationInputError(f"point {bad + 1} is not finite (NaN or inf)")
    return P, p


def is_coplanar(points_w: np.ndarray, tol: float = COPLANAR_TOL) -> bool:
    """True when the points lie on one plane (relative thickness below ``tol``)."""
    P = np.asarray(points_w, dtype=float)
    s = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    return bool(s[0] == 0 or s[-1] / s[0] < tol)


def plane_frame(points_w: np.ndarray) -> np.ndarray:
    """``T_w_p`` of a frame whose z = 0 plane holds the (coplanar) points; identity if they
    already lie on z = 0."""
    P = np.asarray(points_w, dtype=float)
    if np.allclose(P[:, 2], 0.0, atol=1e-9 * max(1.0, float(np.abs(P).max()))):
        return np.eye(4)
    c = P.mean(axis=0)
    _, _, Vt = np.linalg.svd(P - c)
    R = Vt.copy()
    if np.linalg.det(R) < 0:
        R[2] = -R[2]
    return make_T(R.T, c)


# --- stages --------------------------------------------------------------------------------
def _sensor_coords(pixels: np.ndarray, cam: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """Distorted sensor coordinates Xd, Yd (mm) of frame-buffer pixels (Tsai eq. 4, inverted)."""
    d = cam._pixels_to_distorted_mm(pixels)
    return d[:, 0], d[:, 1]


def _far_point(Xd: np.ndarray, Yd: np.ndarray) -> int:
    return int(np.argmax(Xd**2 + Yd**2))


def _rac_noncoplanar(P: np.ndarray, px: np.ndarray, sensor: Sensor):
    """RAC stage for non-coplanar points (Tsai §IV.B, stage 1): R, Tx, Ty, sx."""
    cam1 = sensor.camera(sx=1.0)
    Xd, Yd = _sensor_coords(px, cam1)
    xw, yw, zw = P.T
    A = np.column_stack([Yd * xw, Yd * yw, Yd * zw, Yd, -Xd * xw, -Xd * yw, -Xd * zw])
    U, *_ = np.linalg.lstsq(A, Xd, rcond=None)
    ty_abs = 1.0 / np.sqrt(U[4] ** 2 + U[5] ** 2 + U[6] ** 2)
    sx = ty_abs * np.sqrt(U[0] ** 2 + U[1] ** 2 + U[2] ** 2)
    # sign of Ty: with Ty > 0 the far point's camera x, y must share the signs of Xd, Yd (Tsai §IV.B)
    i = _far_point(Xd, Yd)
    Ty = ty_abs
    r123, tx, r456 = U[:3] * Ty / sx, U[3] * Ty / sx, U[4:7] * Ty
    x, y = r123 @ P[i] + tx, r456 @ P[i] + Ty
    if not (np.sign(x) == np.sign(Xd[i]) and np.sign(y) == np.sign(Yd[i])):
        Ty = -ty_abs
        r123, tx, r456 = U[:3] * Ty / sx, U[3] * Ty / sx, U[4:7] * Ty
    return _rotation_via_rpy(r123, r456), float(tx), float(Ty), float(sx)


def _rotation_via_rpy(row1: np.ndarray, row2: np.ndarray) -> np.ndarray:
    """An orthonormal R from the two (nearly orthonormal) rows the RAC gives: read Willson's
    roll-pitch-yaw angles from r1, r2, r3, r4, r5, r6 and r7 = (row1 × row2)_x, rebuild R."""
    r1, r2, r3 = row1
    r4, r5, r6 = row2
    r7 = r2 * r6 - r3 * r5
    rz = np.arctan2(r4, r1)
    sg, cg = np.sin(rz), np.cos(rz)
    ry = np.arctan2(-r7, r1 * cg + r4 * sg)
    rx = np.arctan2(r3 * sg - r6 * cg, r5 * cg - r2 * sg)
    return rpy_willson(rx, ry, rz)


def _rac_coplanar(P: np.ndarray, px: np.ndarray, sensor: Sensor):
    """RAC stage for coplanar points on z = 0 (Tsai §IV.A, stage 1, eq. 12–13): R, Tx, Ty."""
    Xd, Yd = _sensor_coords(px, sensor.camera())
    xw, yw = P[:, 0], P[:, 1]
    A = np.column_stack([Yd * xw, Yd * yw, Yd, -Xd * xw, -Xd * yw])
    U, *_ = np.linalg.lstsq(A, Xd, rcond=None)
    u1, u2, u3, u4, u5 = U
    sr = u1**2 + u2**2 + u4**2 + u5**2
    det = u1 * u5 - u4 * u2
    if abs(det) > 1e-12 * sr:
        ty2 = (sr - np.sqrt(max(sr**2 - 4.0 * det**2, 0.0))) / (2.0 * det**2)
    else:  # a full row or column of the 2×2 is zero
        ty2 = 1.0 / max(u1**2 + u2**2, u4**2 + u5**2)
    ty_abs = np.sqrt(ty2)
    i = _far_point(Xd, Yd)

    def rows(Ty):
        r1, r2, tx, r4, r5 = u1 * Ty, u2 * Ty, u3 * Ty, u4 * Ty, u5 * Ty
        return r1, r2, tx, r4, r5

    Ty = ty_abs
    r1, r2, tx, r4, r5 = rows(Ty)
    x, y = r1 * xw[i] + r2 * yw[i] + tx, r4 * xw[i] + r5 * yw[i] + Ty
    if not (np.sign(x) == np.sign(Xd[i]) and np.sign(y) == np.sign(Yd[i])):
        Ty = -ty_abs
        r1, r2, tx, r4, r5 = rows(Ty)
    r3 = np.sqrt(max(1.0 - r1**2 - r2**2, 0.0))
    r6 = -np.sign(r1 * r4 + r2 * r5) * np.sqrt(max(1.0 - r4**2 - r5**2, 0.0))
    row1, row2 = np.array([r1, r2, r3]), np.array([r4, r5, r6])
    R = orthonormalize(np.vstack([row1, row2, np.cross(row1, row2)]))
    return R, float(tx), float(Ty)


def _approx_f_tz(P, px, cam: CameraModel, R, Ty):
    """Stage 2 linear estimate of f and Tz ignoring distortion (Tsai eq. 17 analogue)."""
    _, Yd = _sensor_coords(px, cam)
    y = P @ R[1] + Ty
    w = P @ R[2]
    A = np.column_stack([y, -Yd])
    (f, tz), *_ = np.linalg.lstsq(A, w * Yd, rcond=None)
    return float(f), float(tz)


def _flip_for_negative_f(R):
    """Tsai §IV.A: a negative f means the wrong sign was chosen for r3/r6; flip them."""
    F = R.copy()
    F[0, 2], F[1, 2], F[2, 0], F[2, 1] = -F[0, 2], -F[1, 2], -F[2, 0], -F[2, 1]
    return F


def _refine_f_tz_kappa(P, px, cam: CameraModel, R, tx, ty, f0, tz0):
    """Stage 3: nonlinear least squares of f, Tz, κ1 on the undistorted sensor plane (mm),
    as Willson's ``ncc_compute_exact_f_and_Tz``; R, Tx, Ty held."""
    Xd, Yd = _sensor_coords(px, cam)
    r2 = Xd**2 + Yd**2
    xc = P @ R[0] + tx
    yc = P @ R[1] + ty
    wc = P @ R[2]

    def res(q):
        f, tz, k = q
        zc = wc + tz
        return np.concatenate([Xd * (1 + k * r2) - f * xc / zc, Yd * (1 + k * r2) - f * yc / zc])

    sol = least_squares(res, [f0, tz0, 0.0], method="lm", x_scale=[abs(f0), abs(tz0), 1e-4])
    return (float(v) for v in sol.x)


def _residuals_px(cam: CameraModel, T_c_w, P, px) -> np.ndarray:
    return cam.project_world(T_c_w, P) - px


def _full_refine(P, px, cam: CameraModel, T_c_w, *, free_sx: bool, free_center: bool):
    """Minimise the pixel residual over R (Willson roll-pitch-yaw), T, f, κ1 and optionally sx,
    Cx, Cy (Willson's ``*_full_optimization``; LM on the distorted image plane)."""
    rpy = rpy_from_matrix_willson(T_c_w[:3, :3])
    q0 = [*rpy, *T_c_w[:3, 3], cam.f, cam.kappa1]
    scale = [1e-3, 1e-3, 1e-3, 1.0, 1.0, abs(T_c_w[2, 3]) * 1e-3, cam.f * 1e-3, 1e-5]
    if free_sx:
        q0.append(cam.sx)
        scale.append(1e-4)
    if free_center:
        q0 += [cam.cx, cam.cy]
        scale += [1.0, 1.0]

    def unpack(q):
        i = 8
        sx = cam.sx
        if free_sx:
            sx = q[i]
            i += 1
        cx, cy = (q[i], q[i + 1]) if free_center else (cam.cx, cam.cy)
        c = cam.with_(f=float(q[6]), kappa1=float(q[7]), sx=float(sx), cx=float(cx), cy=float(cy))
        return c, make_T(rpy_willson(*q[:3]), q[3:6])

    def res(q):
        c, T = unpack(q)
        r = _residuals_px(c, T, P, px).ravel()
        return np.where(np.isfinite(r), r, 1e6)

    sol = least_squares(res, np.asarray(q0, dtype=float), method="lm", x_scale=np.asarray(scale))
    return unpack(sol.x)


def _tsai_basic(P, px, sensor: Sensor, coplanar: bool):
    if coplanar:
        R, tx, ty = _rac_coplanar(P, px, sensor)
        sx = sensor.sx
    else:
        R, tx, ty, sx = _rac_noncoplanar(P, px, sensor)
    cam = sensor.camera(sx=sx)
    f, tz = _approx_f_tz(P, px, cam, R, ty)
    if f < 0:
        R = _flip_for_negative_f(R)
        f, tz = _approx_f_tz(P, px, cam, R, ty)
    f, tz, k = _refine_f_tz_kappa(P, px, cam, R, tx, ty, f, tz)
    return cam.with_(f=f, kappa1=k), make_T(R, [tx, ty, tz])


# --- public API ------------------------------------------------------------------------------
def calibrate(points_w, pixels, sensor: Sensor, *, coplanar: bool = False, full: bool = False) -> TsaiResult:
    """Tsai calibration of one view of known points.

    ``points_w`` (N, 3) mm, ``pixels`` (N, 2) px. ``coplanar`` selects Tsai §IV.A (the points
    must lie on one plane; sx is taken from ``sensor``), otherwise §IV.B (the points must not be
    coplanar). Without ``full`` the image centre stays at ``sensor.cx, cy`` and the result is
    Tsai's basic method (RAC → f, Tz → f, Tz, κ1). With ``full`` every parameter, Cx and Cy
    included, is then optimised on the pixel residual. Raises :class:`CalibrationInputError`.
    """
    P, px = check_points(points_w, pixels)
    planar = is_coplanar(P)
    need = MIN_POINTS_COPLANAR if coplanar else MIN_POINTS_NONCOPLANAR
    if len(P) < need:
        kind = "coplanar" if coplanar else "non-coplanar"
        raise CalibrationInputError(f"{kind} Tsai calibration needs at least {need} points, got {len(P)}")
    if planar and not coplanar:
        raise CalibrationInputError("all points lie on one plane: use the coplanar method (--coplanar)")
    if coplanar and not planar:
        raise CalibrationInputError("the points are not coplanar: drop --coplanar")
    if np.min(np.linalg.norm(px - px.mean(0), axis=1).max()) < 1e-6:
        raise CalibrationInputError("all pixels coincide")
    T_w_p = plane_frame(P) if coplanar else np.eye(4)
    Pp = (P - T_w_p[:3, 3]) @ T_w_p[:3, :3] if coplanar else P
    with np.errstate(all="ignore"):
        cam, T_c_p = _tsai_basic(Pp, px, sensor, coplanar)
        method = ("coplanar" if coplanar else "noncoplanar") + "-basic"
        if full:
            cam, T_c_p = _full_refine(Pp, px, cam, T_c_p, free_sx=not coplanar, free_center=True)
            method = method.replace("basic", "full")
    T_c_w = T_c_p @ np.linalg.inv(T_w_p) if coplanar else T_c_p
    T_c_w[3] = [0, 0, 0, 1]
    r = _residuals_px(cam, T_c_w, P, px)
    if not (np.all(np.isfinite(r)) and cam.f > 0 and T_c_w[2, 3] > 0):
        raise CalibrationInputError("calibration failed: the points do not determine a camera (degenerate layout)")
    return TsaiResult(camera=cam, T_c_w=T_c_w, method=method, residuals_px=r)


def refine_pose(camera: CameraModel, T_c_w0: np.ndarray, points_w, pixels) -> TsaiResult:
    """Extrinsics only: pose ``T_c_w`` minimising the pixel residual with the intrinsics held
    (Tsai's model, eq. 1–5; used for the hand-eye stations). ``T_c_w0`` is the starting pose."""
    P, px = check_points(points_w, pixels)
    rpy = rpy_from_matrix_willson(T_c_w0[:3, :3])

    def T_of(q):
        return make_T(rpy_willson(*q[:3]), q[3:6])

    def res(q):
        r = _residuals_px(camera, T_of(q), P, px).ravel()
        return np.where(np.isfinite(r), r, 1e6)

    q0 = np.array([*rpy, *T_c_w0[:3, 3]])
    sol = least_squares(res, q0, method="lm", x_scale=[1e-3, 1e-3, 1e-3, 1.0, 1.0, 1.0])
    T = T_of(sol.x)
    return TsaiResult(camera=camera, T_c_w=T, method="pose", residuals_px=_residuals_px(camera, T, P, px))


def calibrate_opencv(points_w, pixels, sensor: Sensor, K0: np.ndarray | None = None) -> dict:
    """OpenCV ``calibrateCamera`` on one view as a baseline (k1 only, no tangential terms).

    A non-planar rig needs an initial K (``CALIB_USE_INTRINSIC_GUESS``); default: the nominal
    centre and the focal length of the basic Tsai fit. Returns ``rms_px, K, dist, R, T``.
    """
    import cv2

    P, px = check_points(points_w, pixels)
    if K0 is None:
        planar = is_coplanar(P)
        base = calibrate(P, px, sensor, coplanar=planar, full=False)
        K0 = base.camera.K
        K0[0, 2], K0[1, 2] = sensor.cx, sensor.cy
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        [P.astype(np.float32)], [px.astype(np.float32)], (int(sensor.width), int(sensor.height)),
        np.asarray(K0, dtype=float).copy(), np.zeros(5), flags=flags, criteria=crit)
    R, _ = cv2.Rodrigues(rvecs[0])
    proj, _ = cv2.projectPoints(P.reshape(-1, 1, 3), rvecs[0], tvecs[0], K, dist)
    e = proj.reshape(-1, 2) - px
    return {"rms_px": float(np.sqrt(np.mean(np.sum(e**2, axis=1)))), "K": K.tolist(),
            "dist": dist.ravel().tolist(), "R": R.tolist(), "T": tvecs[0].ravel().tolist()}
