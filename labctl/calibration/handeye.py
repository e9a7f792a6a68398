"""Hand-eye calibration AX = XB by the Tsai–Lenz method, in numpy.

Implements R. Y. Tsai and R. K. Lenz, "A new technique for fully autonomous and efficient 3D
robotics hand/eye calibration", IEEE Trans. Robotics and Automation 5(3), 1989, §III: the
rotation from the modified Rodrigues vectors of every station pair (eq. 9–12), then the
translation by linear least squares (eq. 13–15).

Frames: robot base B (= world W in labctl), flange F, camera C (the mobile camera C2), target
T fixed in B. Inputs are the flange poses ``T_b_f[i]`` reported by the robot and the target
poses ``T_c_t[i]`` measured by the camera at the same stations; the result is
``X = T_f_c`` (camera in the flange frame), the same quantity as OpenCV's
``calibrateHandEye(R_gripper2base, t_gripper2base, R_target2cam, t_target2cam)``.
"""

from __future__ import annotations

import itertools

import numpy as np

from ..geometry import (
    CameraModel,
    apply,
    invert,
    make_T,
    matrix_to_rotvec,
    orthonormalize,
    rotation_angle,
    rotvec_to_matrix,
)

MIN_STATIONS = 3
MIN_AXIS_SPREAD_DEG = 5.0  # the motions' rotation axes must span at least this angle


class HandEyeInputError(ValueError):
    """The station set cannot determine X (too few, non-finite, degenerate motions)."""


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _check_poses(name: str, Ts) -> np.ndarray:
    A = np.asarray(Ts, dtype=float)
    if A.ndim != 3 or A.shape[1:] != (4, 4):
        raise HandEyeInputError(f"{name}: expected a list of 4×4 poses, got shape {A.shape}")
    if not np.all(np.isfinite(A)):
        raise HandEyeInputError(f"{name}: a pose is not finite (NaN or inf)")
    for i, T in enumerate(A):
        if abs(np.linalg.det(T[:3, :3]) - 1.0) > 1e-3 or np.abs(T[:3, :3] @ T[:3, :3].T - np.eye(3)).max() > 1e-3:
            raise HandEyeInputError(f"{name}[{i}]: not a rigid transform (rotation part is not orthonormal)")
    return A


def motion_pairs(T_b_f, T_c_t) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Relative motions (A, B) of every station pair i < j with A·X = X·B:
    ``A = T_b_f[j]⁻¹ T_b_f[i]`` (flange motion), ``B = T_c_t[j] T_c_t[i]⁻¹`` (camera motion)."""
    As, Bs = [], []
    for i, j in itertools.combinations(range(len(T_b_f)), 2):
        As.append(invert(T_b_f[j]) @ T_b_f[i])
        Bs.append(T_c_t[j] @ invert(T_c_t[i]))
    return As, Bs


def axis_spread_deg(rotations) -> float:
    """Largest angle (deg, folded to ≤ 90°) between the rotation axes of significant motions;
    a pure rotation about one axis gives 0, which leaves X undetermined (Tsai–Lenz §IV)."""
    axes = []
    for R in rotations:
        rv = matrix_to_rotvec(R)
        if np.linalg.norm(rv) > np.radians(1.0):
            axes.append(rv / np.linalg.norm(rv))
    best = 0.0
    for a, b in itertools.combinations(axes, 2):
        best = max(best, float(np.degrees(np.arccos(min(1.0, abs(float(a @ b)))))))
    return best


def tsai_lenz(T_b_f, T_c_t) -> np.ndarray:
    """Hand-eye transform ``X = T_f_c`` from N ≥ 3 stations (Tsai & Lenz 1989, eq. 9–15).

    ``T_b_f``: (N, 4, 4) flange poses in the robot base; ``T_c_t``: (N, 4, 4) target poses in
    the camera. mm and rad. Raises :class:`HandEyeInputError` for too few stations or motions
    whose rotation axes are all parallel (X is then not observable).
    """
    Tf = _check_poses("T_b_f", T_b_f)
    Tc = _check_poses("T_c_t", T_c_t)
    if len(Tf) != len(Tc):
        raise HandEyeInputError(f"{len(Tf)} flange poses but {len(Tc)} target poses")
    if len(Tf) < MIN_STATIONS:
        raise HandEyeInputError(f"hand-eye calibration needs at least {MIN_STATIONS} stations, got {len(Tf)}")
    As, Bs = motion_pairs(Tf, Tc)
    spread = axis_spread_deg([A[:3, :3] for A in As])
    if spread < MIN_AXIS_SPREAD_DEG:
        raise HandEyeInputError(
            f"degenerate robot poses: all rotations are about one axis (axes spread {spread:.1f}°, "
            f"need ≥ {MIN_AXIS_SPREAD_DEG:.0f}°); rotate the flange about two different axes")

    # rotation: skew(Pg + Pc) Pcg' = Pc − Pg with P = 2 sin(θ/2) n (eq. 9–12)
    M_rows, v_rows = [], []
    for A, B in zip(As, Bs):
        rg, rc = matrix_to_rotvec(A[:3, :3]), matrix_to_rotvec(B[:3, :3])
        tg, tc = np.linalg.norm(rg), np.linalg.norm(rc)
        if tg < 1e-9 or tc < 1e-9:
            continue
        pg = 2.0 * np.sin(tg / 2.0) * rg / tg
        pc = 2.0 * np.sin(tc / 2.0) * rc / tc
        M_rows.append(_skew(pg + pc))
        v_rows.append(pc - pg)
    M, v = np.vstack(M_rows), np.concatenate(v_rows)
    p_prime, *_ = np.linalg.lstsq(M, v, rcond=None)
    p = 2.0 * p_prime / np.sqrt(1.0 + p_prime @ p_prime)
    n2 = p @ p
    R = (1.0 - n2 / 2.0) * np.eye(3) + 0.5 * (np.outer(p, p) + np.sqrt(max(4.0 - n2, 0.0)) * _skew(p))
    R = orthonormalize(R)

    # translation: (R_A − I) t = R t_B − t_A (eq. 13–15)
    C = np.vstack([A[:3, :3] - np.eye(3) for A in As])
    d = np.concatenate([R @ B[:3, 3] - A[:3, 3] for A, B in zip(As, Bs)])
    t, *_ = np.linalg.lstsq(C, d, rcond=None)
    X = make_T(R, t)
    if not np.all(np.isfinite(X)):
        raise HandEyeInputError("hand-eye calibration failed: the stations do not determine X")
    return X


def refine_hand_eye(camera: CameraModel, X0: np.ndarray, T_b_t0: np.ndarray, T_b_f, points_t, pixels, *,
                    free_intrinsics: bool = True) -> tuple[CameraModel, np.ndarray, np.ndarray, np.ndarray]:
    """Reprojection refinement of X (and of f, κ1, sx) after Tsai–Lenz.

    Minimises, over every station i and target dot j, the pixel distance between the observed
    dot and ``camera.project((T_b_f[i]·X)⁻¹ · T_b_t · P_j)`` — the robot's known motions fix the
    scale that a single view leaves correlated with f (Tsai 1987 §V, f/Tz coupling). Parameters:
    X, the target pose ``T_b_t`` and, with ``free_intrinsics``, f, κ1, sx (Cx, Cy stay). Starts
    from Tsai–Lenz's X0 and the averaged ``T_b_t0``. ``points_t[i]`` (N_i, 3) mm in the target
    frame, ``pixels[i]`` (N_i, 2). Returns (camera, X, T_b_t, residuals (ΣN_i, 2) px).
    """
    Tf = [np.asarray(T, float) for T in T_b_f]
    P = [np.asarray(p, float) for p in points_t]
    px = [np.asarray(p, float) for p in pixels]

    def unpack(q):
        X = make_T(X0[:3, :3] @ rotvec_to_matrix(q[0:3]), X0[:3, 3] + q[3:6])
        Tt = make_T(T_b_t0[:3, :3] @ rotvec_to_matrix(q[6:9]), T_b_t0[:3, 3] + q[9:12])
        cam = camera
        if free_intrinsics:
            cam = camera.with_(f=float(camera.f * (1 + q[12])), kappa1=float(camera.kappa1 + q[13] * 1e-4),
                               sx=float(camera.sx * (1 + q[14])))
        return cam, X, Tt

    def residuals(q):
        cam, X, Tt = unpack(q)
        out = []
        for T, Pi, pi in zip(Tf, P, px):
            out.append(cam.project(apply(invert(T @ X) @ Tt, Pi)) - pi)
        r = np.vstack(out).ravel()
        return np.where(np.isfinite(r), r, 1e6)

    from scipy.optimize import least_squares

    n = 15 if free_intrinsics else 12
    sol = least_squares(residuals, np.zeros(n), method="lm", x_scale=[1e-3] * 3 + [1.0] * 3 + [1e-3] * 3
                        + [1.0] * 3 + ([1e-3, 1.0, 1e-4] if free_intrinsics else []))
    cam, X, Tt = unpack(sol.x)
    return cam, X, Tt, sol.fun.reshape(-1, 2)


def target_in_base(T_b_f, T_c_t, X: np.ndarray) -> np.ndarray:
    """The fixed target's pose ``T_b_t`` implied by every station, averaged (rotation by the
    chordal mean, translation by the mean): ``T_b_t = T_b_f · X · T_c_t``."""
    Ts = [Tf @ X @ Tc for Tf, Tc in zip(T_b_f, T_c_t)]
    R = orthonormalize(np.sum([T[:3, :3] for T in Ts], axis=0))
    return make_T(R, np.mean([T[:3, 3] for T in Ts], axis=0))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in mm) between two poses."""
    rot = np.degrees(rotation_angle(T_est[:3, :3].T @ T_true[:3, :3]))
    return float(rot), float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
