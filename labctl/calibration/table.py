"""Table registration: the NC table's machine-zero frame in the world, from a marker seen by
the calibrated fixed camera at commanded table positions.

The marker (a dark dot on a plate fixed to the carriage at table coordinates ``q``, its top
``h`` mm above the table plane) is observed at commanded positions ``p_i``; each sighting is
back-projected onto the plane z = h of W (the table plane is z = 0 of W). The sightings obey
``m_i = o + A·p_i`` with A the 2×2 image of the table's axes; a least-squares fit gives o and A,
whose normalised, orthogonalised columns are the table's X and Y axes in W (as the paper's
object-motion simulator is registered to the world, He et al. 1996 §5). mm and rad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import CameraModel, apply, make_T


class TableRegistrationError(ValueError):
    """The sightings cannot determine the table frame (too few, collinear, non-finite)."""


@dataclass(frozen=True)
class TableRegistration:
    """NC table registration: ``T_w_table`` (machine zero → world W, mm), axis scales, skew (deg), residuals (mm)."""

    T_w_table: np.ndarray  # 4×4, machine zero of the table in W
    scale: tuple[float, float]  # measured mm per commanded mm along X and Y (1 for a true table)
    skew_deg: float  # deviation of the measured axes from perpendicular
    residuals_mm: np.ndarray  # (N, 2) fit residuals in the table plane

    @property
    def rms_mm(self) -> float:
        """Root-mean-square fit residual (mm) in the table plane."""
        return float(np.sqrt(np.mean(np.sum(self.residuals_mm**2, axis=1))))


def pixel_to_plane(camera: CameraModel, T_w_c: np.ndarray, pixels: np.ndarray, z_w: float) -> np.ndarray:
    """World points (N, 3) where the rays of distorted ``pixels`` meet the plane z = ``z_w`` of W."""
    rays_c = camera.backproject(np.asarray(pixels, float).reshape(-1, 2))
    d = rays_c @ T_w_c[:3, :3].T
    o = T_w_c[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (z_w - o[2]) / d[:, 2]
    s = np.where(s > 0, s, np.nan)
    return o + s[:, None] * d


def fit_table_frame(commanded_xy: np.ndarray, marker_w: np.ndarray, marker_at_table_xy=(0.0, 0.0), *,
                    marker_height_mm: float | None = None) -> TableRegistration:
    """Table frame from commanded positions (N, 2) mm and the marker's world points (N, 3) mm.

    Solves ``m_i = o + A p_i`` (least squares), takes X = A[:, 0]/|A[:, 0]|, Y ⟂ X in the plane
    spanned by A, z up; the origin is o minus the marker's own offset on the carriage. The
    table plane is z = 0 of W, or with ``marker_height_mm`` (the marker's height above the table
    top) z = mean(marker z) − that height.
    """
    p = np.asarray(commanded_xy, float).reshape(-1, 2)
    m = np.asarray(marker_w, float).reshape(-1, 3)
    if len(p) != len(m):
        raise TableRegistrationError(f"{len(p)} table positions but {len(m)} sightings")
    if len(p) < 3:
        raise TableRegistrationError(f"table registration needs at least 3 positions, got {len(p)}")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(m))):
        raise TableRegistrationError("a sighting is not finite (the marker ray misses the table plane)")
    pc = p - p.mean(axis=0)
    s = np.linalg.svd(pc, compute_uv=False)
    if s[-1] < 1e-6 * max(s[0], 1e-12) or s[0] == 0:
        raise TableRegistrationError("the commanded table positions are collinear: X and Y are not both observed")
    M = np.column_stack([np.ones(len(p)), p])
    coef, *_ = np.linalg.lstsq(M, m[:, :2], rcond=None)  # rows: o, A[:,0], A[:,1] (transposed)
    o2, ax2, ay2 = coef[0], coef[1], coef[2]
    ex = np.array([*ax2, 0.0]) / np.linalg.norm(ax2)
    ez = np.array([0.0, 0.0, 1.0])
    ey = np.cross(ez, ex)
    if ey[:2] @ ay2 < 0:
        raise TableRegistrationError("the table's Y axis appears mirrored (left-handed table frame)")
    skew = float(np.degrees(np.arcsin(np.clip(ex[:2] @ ay2 / np.linalg.norm(ay2), -1, 1))))
    R = np.column_stack([ex, ey, ez])
    q = np.array([*marker_at_table_xy, 0.0])
    origin = np.array([*o2, 0.0]) - R @ q
    T = make_T(R, origin)
    pred = M @ coef
    # by default the table plane is z = 0 of W (W defined on it); else it sits under the marker
    T[2, 3] = 0.0 if marker_height_mm is None else float(np.mean(m[:, 2]) - marker_height_mm)
    return TableRegistration(T_w_table=T, scale=(float(np.linalg.norm(ax2)), float(np.linalg.norm(ay2))),
                             skew_deg=skew, residuals_mm=m[:, :2] - pred)


def table_point_w(T_w_table: np.ndarray, table_xy, q_xyz=(0.0, 0.0, 0.0)) -> np.ndarray:
    """World position of carriage point ``q_xyz`` with the table at commanded ``table_xy``."""
    return apply(T_w_table, np.array([table_xy[0] + q_xyz[0], table_xy[1] + q_xyz[1], q_xyz[2]]))
