"""The lab's calibration procedure: fixed camera, mobile camera + hand-eye, table registration.

The procedure talks to the lab only through a :class:`Rig` (three ways to take a picture), so
it runs the same on the simulated lab and on hardware; everything else is computation.

1. **Fixed camera C1** (Tsai 1987 §IV.B, mono-view non-coplanar, as the paper, He et al. 1996
   §5): one image of the dot target placed at its known pose ``T_w_t`` → intrinsics and
   ``T_w_c1 = T_w_t · T_c1_t⁻¹``.
2. **Mobile camera C2**: the robot carries it through stations around the target; Tsai at the
   first station gives the intrinsics; at every station the target pose ``T_c2_t`` is fitted with
   the intrinsics held; Tsai–Lenz (1989) on the flange poses and target poses gives X = ``T_f_c2``.
3. **Table**: the registration plate's dot is seen by C1 at commanded table positions
   (:mod:`.table`).

Dot centroids are corrected for the perspective bias of a circle's centroid, iterating with the
current estimate (:func:`.dots.circle_centroid_bias`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..geometry import CameraModel, apply, invert, look_at, make_T
from .dots import DotError, circle_centroid_bias, detect_dots, identify
from .handeye import pose_error, refine_hand_eye, target_in_base, tsai_lenz
from .table import TableRegistration, fit_table_frame, pixel_to_plane
from .target import RoofTarget
from .tsai import Sensor, TsaiResult, calibrate, refine_pose

BIAS_ITERATIONS = 2


class Rig(Protocol):
    """How the procedure gets pictures from the lab (BGR uint8 images)."""

    def fixed_image(self, T_w_t: np.ndarray) -> np.ndarray:
        """The fixed camera's image of the target placed at ``T_w_t``."""

    def mobile_image(self, T_b_f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Move the flange to ``T_b_f``; return (image, flange pose the robot reports)."""

    def table_image(self, table_xy: tuple[float, float]) -> np.ndarray:
        """Move the table to ``table_xy`` (mm, commanded); the fixed camera's image of the plate."""


@dataclass
class TargetView:
    """One calibrated view of the target: Tsai result (world = target frame) and what was used."""

    result: TsaiResult
    model_idx: np.ndarray
    pixels: np.ndarray  # bias-corrected centroids (N, 2)
    raw_pixels: np.ndarray


def _tsai_frame_shift(target: RoofTarget) -> np.ndarray:
    """Tsai's RAC needs the world origin away from the camera's y axis (Tsai 1987 §IV.B, Ty ≠ 0):
    a single target view is calibrated in a frame s whose origin lies beyond a corner of the
    target. Returns ``T_s_t``."""
    return make_T(None, [target.width_mm, target.length_mm, 0.0])


def observe_target(image: np.ndarray, target: RoofTarget, nominal: CameraModel):
    """Detect and identify the target's dots: (model indices, centroids (N, 2), initial T_c_t)."""
    solid = target.solid()
    blobs = detect_dots(image)
    mi, bi, T0 = identify(blobs, solid.dots, target.fiducial_indices, nominal)
    return mi, blobs.centers[bi], T0


def calibrate_on_target(images: list[np.ndarray], placements: list[np.ndarray], target: RoofTarget,
                        nominal: CameraModel, *, full: bool = False,
                        intrinsics: CameraModel | None = None) -> TargetView:
    """One Tsai calibration (Tsai 1987 §IV.B) from the target's dots in one or more images taken by
    the same, unmoved camera, the target at ``placements[k]`` (``T_w_t``) in image k; with
    ``intrinsics`` only the pose is fitted. The dots' centroid bias is removed iteratively with
    the current estimate. Returns the view; its result's ``T_c_w`` maps W into the camera."""
    solid = target.solid()
    obs = [observe_target(img, target, nominal) for img in images]
    P_w = np.vstack([apply(T, solid.dots[mi]) for (mi, _, _), T in zip(obs, placements)])
    n_w = np.vstack([solid.normals[mi] @ T[:3, :3].T for (mi, _, _), T in zip(obs, placements)])
    radii = np.concatenate([solid.radii[mi] for mi, _, _ in obs])
    raw = np.vstack([px for _, px, _ in obs])
    px = raw.copy()
    res = None
    for _ in range(BIAS_ITERATIONS + 1):
        if intrinsics is None:
            res = calibrate(P_w, px, Sensor.of(nominal), full=full)
        else:
            start = res.T_c_w if res is not None else obs[0][2] @ invert(placements[0])
            res = refine_pose(intrinsics, start, P_w, px)
        px = raw - circle_centroid_bias(res.camera, res.T_c_w, P_w, n_w, radii)
    res = TsaiResult(camera=res.camera, T_c_w=res.T_c_w, method=res.method,
                     residuals_px=res.camera.project_world(res.T_c_w, P_w) - px)
    return TargetView(result=res, model_idx=np.concatenate([mi for mi, _, _ in obs]), pixels=px, raw_pixels=raw)


def calibrate_single_view(image: np.ndarray, target: RoofTarget, nominal: CameraModel, *, full: bool = False,
                          intrinsics: CameraModel | None = None) -> tuple[TargetView, np.ndarray]:
    """:func:`calibrate_on_target` on one image in the target's own frame; returns (view, T_c_t)."""
    T_s_t = _tsai_frame_shift(target)
    view = calibrate_on_target([image], [T_s_t], target, nominal, full=full, intrinsics=intrinsics)
    return view, view.result.T_c_w @ T_s_t


# --- 1. fixed camera ----------------------------------------------------------------------------
@dataclass
class FixedCalibration:
    camera: CameraModel
    T_w_c1: np.ndarray
    view: TargetView


def calibrate_fixed(rig: Rig, target: RoofTarget, nominal: CameraModel, *, full: bool = False,
                    progress: Callable[[str], None] | None = None) -> FixedCalibration:
    """C1 from the target at every placement: one Tsai calibration over all the points in W."""
    images = []
    for k, T_w_t in enumerate(target.placements):
        images.append(rig.fixed_image(T_w_t))
        if progress:
            progress(f"fixed camera: placement {k + 1}/{len(target.placements)}")
    view = calibrate_on_target(images, target.placements, target, nominal, full=full)
    return FixedCalibration(camera=view.result.camera, T_w_c1=invert(view.result.T_c_w), view=view)


# --- 2. mobile camera + hand-eye ------------------------------------------------------------------
def plan_stations(target: RoofTarget, nominal: CameraModel, X_nominal: np.ndarray, *,
                  distance_mm: float = 1050.0, workspace=None, n: int = 10,
                  margin_px: float = 12.0) -> list[np.ndarray]:
    """Flange poses ``T_b_f`` looking at the target from ``distance_mm``: tilts up to ~30° at
    several azimuths with varied roll (Tsai–Lenz need rotations about different axes), each
    keeping every dot in view of the nominal camera and the flange inside ``workspace``
    ((min, max) corners, mm). The first station serves the intrinsics."""
    T_w_t = target.T_w_t
    aim = apply(T_w_t, [0.0, 0.0, 0.5 * target.ridge_height_mm])
    solid = target.solid().transformed(T_w_t)
    out = []
    for i in range(48):
        tilt = (0.0, 24.0, 16.0, 30.0, 20.0, 28.0, 12.0, 26.0)[i % 8]
        az = np.radians(37.0 + 137.508 * i)  # golden-angle spread of azimuths
        el = np.radians(tilt)
        eye = aim + distance_mm * np.array([np.sin(el) * np.cos(az), np.sin(el) * np.sin(az), np.cos(el)])
        roll = np.radians(((i * 29) % 40) - 20.0)
        up = np.array([np.sin(roll), np.cos(roll), 0.0])
        T_w_c = look_at(eye, aim, up=up)
        pix = nominal.project_world(invert(T_w_c), solid.dots)
        if not np.all(nominal.contains(pix, margin=margin_px)):
            continue
        T_b_f = T_w_c @ invert(X_nominal)
        if workspace is not None:
            lo, hi = (np.asarray(w, float) for w in workspace)
            if np.any(T_b_f[:3, 3] < lo) or np.any(T_b_f[:3, 3] > hi):
                continue
        out.append(T_b_f)
        if len(out) == n:
            break
    return out


@dataclass
class MobileCalibration:
    camera: CameraModel
    T_f_c2: np.ndarray
    intrinsics_view: TargetView
    station_views: list[TargetView]
    T_b_f: list[np.ndarray]
    T_c_t: list[np.ndarray]
    T_b_t: np.ndarray  # the target's pose implied by the robot + X (cross-check of its placement)
    T_f_c2_tsai_lenz: np.ndarray | None = None  # before the reprojection refinement
    T_f_c2_opencv: np.ndarray | None = None
    refined_residuals_px: np.ndarray | None = None
    skipped: list[int] = field(default_factory=list)


def calibrate_mobile(rig: Rig, target: RoofTarget, nominal: CameraModel, stations: list[np.ndarray], *,
                     full: bool = False, progress: Callable[[str], None] | None = None) -> MobileCalibration:
    """Intrinsics by Tsai at the first station, target poses at all, then X by Tsai–Lenz."""
    images, flanges = [], []
    for k, T_cmd in enumerate(stations):
        img, T_rep = rig.mobile_image(T_cmd)
        images.append(img)
        flanges.append(np.asarray(T_rep, float))
        if progress:
            progress(f"mobile camera: station {k + 1}/{len(stations)}")
    intr, _ = calibrate_single_view(images[0], target, nominal, full=full)
    cam = intr.result.camera
    views, T_c_t, used, skipped = [], [], [], []
    for k, img in enumerate(images):
        try:
            view, T = calibrate_single_view(img, target, nominal, intrinsics=cam)
        except DotError:
            skipped.append(k)
            continue
        views.append(view)
        T_c_t.append(T)
        used.append(flanges[k])
    X_tl = tsai_lenz(used, T_c_t)
    X_cv = _opencv_hand_eye(used, T_c_t)
    solid = target.solid()
    T_b_t0 = target_in_base(used, T_c_t, X_tl)
    cam, X, T_b_t, res = refine_hand_eye(cam, X_tl, T_b_t0, used, [solid.dots[v.model_idx] for v in views],
                                         [v.pixels for v in views])
    return MobileCalibration(camera=cam, T_f_c2=X, intrinsics_view=intr, station_views=views, T_b_f=used, T_c_t=T_c_t,
                             T_b_t=T_b_t, T_f_c2_tsai_lenz=X_tl, T_f_c2_opencv=X_cv, refined_residuals_px=res,
                             skipped=skipped)


def _opencv_hand_eye(T_b_f, T_c_t) -> np.ndarray | None:
    """cv2.calibrateHandEye (Tsai method) on the same data, as a cross-check (OpenCV 4.x only)."""
    try:
        import cv2

        R, t = cv2.calibrateHandEye([T[:3, :3] for T in T_b_f], [T[:3, 3] for T in T_b_f],
                                    [T[:3, :3] for T in T_c_t], [T[:3, 3] for T in T_c_t],
                                    method=cv2.CALIB_HAND_EYE_TSAI)
    except (AttributeError, ImportError):
        return None
    return make_T(R, np.ravel(t))


# --- 3. table registration ------------------------------------------------------------------------
def register_table(rig: Rig, target: RoofTarget, camera: CameraModel, T_w_c1: np.ndarray, *,
                   progress: Callable[[str], None] | None = None) -> TableRegistration:
    """Sight the plate's dot with C1 at each commanded position; fit the table frame."""
    plate = target.plate_solid()
    T_c_w = invert(T_w_c1)
    z = target.plate_thickness_mm
    sightings = []
    positions = [tuple(p) for p in target.table_positions_mm]
    for k, xy in enumerate(positions):
        blobs = detect_dots(rig.table_image(xy))
        min_area = 0.25 * np.pi * (target.plate_dot_radius_mm / _mm_per_px(camera, T_w_c1)) ** 2
        big = np.flatnonzero(blobs.areas >= min_area)
        if len(big) != 1:
            raise DotError(f"table position {xy}: expected one registration dot, found {len(big)}")
        px = blobs.centers[big[0]]
        m = pixel_to_plane(camera, T_w_c1, px[None], z)[0]
        for _ in range(BIAS_ITERATIONS):  # the dot lies flat at m: remove its centroid bias
            bias = circle_centroid_bias(camera, T_c_w, m[None], plate.normals, plate.radii)[0]
            m = pixel_to_plane(camera, T_w_c1, (px - bias)[None], z)[0]
        sightings.append(m)
        if progress:
            progress(f"table: position {k + 1}/{len(positions)}")
    return fit_table_frame(np.array(positions), np.array(sightings), target.plate_at_table_mm)


def _mm_per_px(camera: CameraModel, T_w_c: np.ndarray) -> float:
    """Approximate size (mm) of a pixel on the table plane at the image centre."""
    p = pixel_to_plane(camera, T_w_c, np.array([[camera.cx, camera.cy], [camera.cx + 1.0, camera.cy]]), 0.0)
    return float(np.linalg.norm(p[1] - p[0]))


# --- errors against ground truth (simulated lab) ---------------------------------------------------
def table_plane_error(cam: CameraModel, T_w_c: np.ndarray, cam_true: CameraModel, T_w_c_true: np.ndarray,
                      step_px: int = 16) -> dict:
    """World-point error on the table plane z = 0: each pixel of a grid over the image is
    back-projected with the truth and with the estimate; returns max/rms error (mm), the
    field of view (mm, the true footprint's width) and the max error as % of it."""
    u, v = np.meshgrid(np.arange(0, cam_true.width, step_px, dtype=float),
                       np.arange(0, cam_true.height, step_px, dtype=float))
    px = np.stack([u.ravel(), v.ravel()], axis=-1)
    pt = pixel_to_plane(cam_true, T_w_c_true, px, 0.0)
    pe = pixel_to_plane(cam, T_w_c, px, 0.0)
    e = np.linalg.norm(pe - pt, axis=1)
    fov = float(np.ptp(pt[:, 0]))
    fov = max(fov, float(np.ptp(pt[:, 1])))
    return {"max_mm": float(e.max()), "rms_mm": float(np.sqrt(np.mean(e**2))), "fov_mm": fov,
            "max_percent_of_fov": float(100.0 * e.max() / fov)}


def hand_eye_error(X: np.ndarray, X_true: np.ndarray) -> dict:
    rot, trans = pose_error(X, X_true)
    return {"rotation_deg": rot, "translation_mm": trans}
