"""Target paths for the mobile camera: G(t) for the initial view and the standard-view pose.

Paper §4.3: "Given the predicted trajectory of an object's travel through the robot's
workspace, a corresponding camera placement trajectory {G(t)} can be determined, via a constant
transformation, to represent potential viewing-points." The constant transformation is the
initial viewing pose (§5.3: about 1 m from the marker at a 63° viewing angle). The
standard-viewing location puts the optical axis on the marker normal at a stand-off distance
(§3.3, §4.3). World frame W, table plane z = 0, mm, rad (degrees only in ``*_deg`` arguments).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..geometry import look_at, make_T
from .limits import PlanningError

MarkerPath = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]
"""``path(times) -> (pos, vel, acc)`` each (N, 2): the marker's (predicted) table-plane motion."""


@dataclass(frozen=True)
class TargetPath:
    """G(t): a commanded point that keeps a constant offset from a moving marker and a constant rotation.

    ``G(t) = [m(t), marker_z_mm] + offset_w`` where ``m`` is ``marker_path``; the commanded frame's
    rotation (world ← commanded frame) is ``rotation`` at all times, so G's angular velocity is 0.
    """

    marker_path: MarkerPath
    offset_w: np.ndarray
    rotation: np.ndarray
    marker_z_mm: float = 0.0

    def __call__(self, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, velocities, accelerations of G, each (N, 3), at ``times`` (s)."""
        mp, mv, ma = self.marker_path(np.atleast_1d(np.asarray(times, dtype=float)))
        n = mp.shape[0]
        p = np.empty((n, 3))
        p[:, :2] = mp
        p[:, 2] = self.marker_z_mm
        p += self.offset_w
        v = np.zeros((n, 3))
        v[:, :2] = mv
        a = np.zeros((n, 3))
        a[:, :2] = ma
        return p, v, a

    def marker(self, times) -> np.ndarray:
        """The marker's 3D position (N, 3) at ``times``."""
        mp, _, _ = self.marker_path(np.atleast_1d(np.asarray(times, dtype=float)))
        return np.column_stack([mp, np.full(len(mp), self.marker_z_mm)])

    def pose(self, t: float) -> np.ndarray:
        """``T_w_x`` (4×4) of the commanded frame at time ``t``."""
        return make_T(self.rotation, self(t)[0][0])


def _flange_offset(R_w_c: np.ndarray, T_f_c) -> tuple[np.ndarray, np.ndarray]:
    """Rotation of the flange and the camera→flange offset in W, for a camera rotation ``R_w_c``."""
    if T_f_c is None:
        return R_w_c, np.zeros(3)
    T_f_c = np.asarray(T_f_c, dtype=float)
    R_c_f = T_f_c[:3, :3].T
    t_c_f = -R_c_f @ T_f_c[:3, 3]
    return R_w_c @ R_c_f, R_w_c @ t_c_f


def camera_placement_trajectory(predict: MarkerPath, distance_mm: float, angle_deg: float,
                                azimuth_deg: float = -90.0, marker_z_mm: float = 0.0,
                                T_f_c=None) -> TargetPath:
    """G(t) for the initial view (paper §4.3, §5.3): the predicted marker path composed with a constant pose.

    The camera sits ``distance_mm`` from the marker, at elevation ``angle_deg`` above the table
    plane, on the side given by ``azimuth_deg`` (0 = +x of W, -90 = -y), looking at the marker
    (optical axis +z, image "up" towards world +z). ``predict(times)`` gives the marker's
    table-plane position/velocity/acceleration (e.g. ``MarkerTracker.predicted_path()``) at
    height ``marker_z_mm``. With ``T_f_c`` (hand-eye, camera in flange) G is the flange's path.
    """
    if not (np.isfinite(distance_mm) and distance_mm > 0):
        raise PlanningError(f"viewing distance must be positive, got {distance_mm!r}")
    if not (np.isfinite(angle_deg) and 0 < angle_deg <= 90):
        raise PlanningError(f"viewing angle must be in (0, 90] degrees, got {angle_deg!r}")
    el, az = np.deg2rad(angle_deg), np.deg2rad(azimuth_deg)
    offset = distance_mm * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    R_w_c = look_at(offset, np.zeros(3))[:3, :3]
    R, extra = _flange_offset(R_w_c, T_f_c)
    return TargetPath(predict, offset + extra, R, float(marker_z_mm))


def standard_view_pose(marker_center_w, marker_normal_w, standoff_mm: float, current_R) -> np.ndarray:
    """``T_w_c`` of the standard view: camera ``standoff_mm`` out along the marker normal, looking along −normal.

    Paper §3.3/§4.3: the optical axis is aligned with the marker's standard-viewing axis. The
    roll about that axis is the one that rotates least from ``current_R`` (world ← camera):
    maximising ``trace(current_Rᵀ · R(φ))`` over the roll φ has the closed form used here.
    """
    c = np.asarray(marker_center_w, dtype=float).reshape(3)
    n = np.asarray(marker_normal_w, dtype=float).reshape(3)
    Rc = np.asarray(current_R, dtype=float).reshape(3, 3)
    norm = float(np.linalg.norm(n))
    if not (np.all(np.isfinite(c)) and np.isfinite(norm) and norm > 1e-9 and np.all(np.isfinite(Rc))):
        raise PlanningError("standard view needs a finite marker centre, a non-zero normal and a finite rotation")
    if not (np.isfinite(standoff_mm) and standoff_mm > 0):
        raise PlanningError(f"stand-off must be positive, got {standoff_mm!r}")
    n = n / norm
    z = -n
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    base = np.column_stack([x, np.cross(z, x), z])
    M = Rc.T @ base
    phi = np.arctan2(M[0, 1] - M[1, 0], M[0, 0] + M[1, 1])
    cph, sph = np.cos(phi), np.sin(phi)
    roll = np.array([[cph, -sph, 0.0], [sph, cph, 0.0], [0.0, 0.0, 1.0]])
    return make_T(base @ roll, c + standoff_mm * n)


@dataclass(frozen=True)
class _CarriedMarker:
    """A marker carried by the table: known at ``center_xy`` at ``t_ref``, moved since by ``table_path(t) − ref_xy``
    (``ref_xy`` None: ``table_path(t_ref)``, the path extended back to ``t_ref``)."""

    table_path: MarkerPath
    t_ref: float
    center_xy: np.ndarray
    ref_xy: np.ndarray | None = None

    def __call__(self, times):
        p, v, a = self.table_path(times)
        p_ref = self.table_path(np.array([self.t_ref]))[0][0] if self.ref_xy is None else self.ref_xy
        return p - p_ref + self.center_xy, v, a


def standard_view_path(table_path: MarkerPath, t_ref: float, marker_center_w, marker_normal_w,
                       standoff_mm: float, current_R, T_f_c=None, table_xy_at_ref=None) -> TargetPath:
    """G(t) of the standard view for a marker that rides the table (paper §4.3, standard-viewing location).

    The marker centre measured at ``t_ref`` translates with the table's predicted motion
    ``table_path``; the view pose (:func:`standard_view_pose`) translates with it. ``table_xy_at_ref`` (mm, table
    plane, ``table_path``'s frame): the point of ``table_path`` the motion since ``t_ref`` is counted from, when it
    is known otherwise (the motion measured since, ``PredictorPlanner._table_since``); without it ``table_path``
    extended back to ``t_ref``, which misses the marker by the path's turns since then (a zigzag's corners).
    """
    T = standard_view_pose(marker_center_w, marker_normal_w, standoff_mm, current_R)
    c = np.asarray(marker_center_w, dtype=float).reshape(3)
    R, extra = _flange_offset(T[:3, :3], T_f_c)
    ref = None if table_xy_at_ref is None else np.asarray(table_xy_at_ref, dtype=float).reshape(2)
    carried = _CarriedMarker(table_path, float(t_ref), c[:2].copy(), ref)
    return TargetPath(carried, T[:3, 3] - c + extra, R, float(c[2]))


def prediction_margin_mm(cov, n_sigma: float = 3.0) -> float:
    """Radius (mm) of the circle that holds the ``n_sigma`` error ellipse of a predicted marker position.

    ``cov`` is the prediction's 2×2 table-plane covariance (mm², e.g. ``MarkerTracker.predict``):
    ``n_sigma · sqrt(λ_max)``. The planner commits to an interception only once this is small
    at the arrival horizon, and sizes the initial view's margin with it (paper §4.2-4.3).
    """
    c = np.asarray(cov, dtype=float).reshape(2, 2)
    if not np.all(np.isfinite(c)):
        raise PlanningError("prediction covariance must be finite")
    lam = float(np.max(np.linalg.eigvalsh(0.5 * (c + c.T))))
    return float(n_sigma) * float(np.sqrt(max(lam, 0.0)))


def view_holds_marker(camera, T_w_c: np.ndarray, marker_w, margin_mm: float, fill: float = 0.5) -> bool:
    """Whether a camera at ``T_w_c`` (4×4, W ← camera) sees the marker point ``marker_w`` (mm, W) inside the
    central ``fill`` of its image on each axis, with the prediction's ``margin_mm`` (its 3-σ radius on the table
    plane, projected at the marker's depth) to spare. ``camera``: a :class:`labctl.geometry.CameraModel`.
    The rule :func:`viewing_distance_with_margin` sizes the initial view by, checked for one pose.
    """
    p_c = np.linalg.inv(np.asarray(T_w_c, dtype=float)) @ np.append(np.asarray(marker_w, dtype=float), 1.0)
    if not p_c[2] > 0:
        return False
    px = camera.project(p_c[:3])
    slack = max(float(margin_mm), 0.0) * np.diag(camera.K)[:2] / float(p_c[2])
    half = 0.5 * np.array([camera.width, camera.height], dtype=float)
    return bool(np.all(np.abs(px - (half - 0.5)) + slack <= fill * half))


def viewing_distance_with_margin(distance_mm: float, margin_mm: float, half_fov_rad: float,
                                 marker_radius_mm: float = 0.0, fill: float = 0.5) -> float:
    """The initial viewing distance (mm), lengthened if the prediction is too uncertain for it.

    A marker anywhere within ``margin_mm`` of the predicted point (plus its own radius) must stay
    inside the central ``fill`` of the mobile camera's half field of view ``half_fov_rad``, so the
    distance is at least ``(margin + radius) / (fill · tan(half_fov))``; never shorter than asked.
    """
    if not (np.isfinite(half_fov_rad) and 0.0 < half_fov_rad < np.pi / 2 and 0.0 < fill <= 1.0):
        raise PlanningError(f"half field of view must be in (0, 90°) and fill in (0, 1], "
                            f"got {half_fov_rad!r}, {fill!r}")
    need = (max(float(margin_mm), 0.0) + max(float(marker_radius_mm), 0.0)) / (fill * np.tan(half_fov_rad))
    return float(max(float(distance_mm), need))
