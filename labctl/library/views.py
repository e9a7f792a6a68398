"""Standard views (paper §3, §3.4): the image seen along a marker's normal at the stand-off distance.

A marker's outward normal defines a *standard-viewing axis*; the standard view is taken with
the optical axis on that normal, the camera ``standoff_mm`` from the marker centre. The image
itself comes from a ``render_view(T_o_c) -> BGR image`` callable injected by the caller (the
simulated lab's renderer, the robot camera on hardware, or :func:`silhouette_renderer` in
tests), so this module never imports the simulator or a device.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:  # only annotations: loading a library for a run imports no trimesh
    import trimesh

from ..geometry import CameraModel, invert, make_T, rotvec_to_matrix
from ..vision.shape import ShapeError, ShapeFeatures, features_from_image, silhouette_mask
from .placement import Marker

RenderView = Callable[[np.ndarray], np.ndarray]


@dataclass
class StandardView:
    """One standard view of an object: the marker it looks along, its features, its image."""

    marker_id: int
    features: ShapeFeatures
    image: np.ndarray | None = None  # BGR, kept in memory while teaching; loaded lazily otherwise


def marker_frame(marker: Marker) -> np.ndarray:
    """``T_o_m``: marker frame M in O — origin at the centre, z = outward normal, x fixed by a rule.

    The in-plane axis is the projection of O's x axis (or y when the normal is near x), so
    the frame is a deterministic function of the marker.
    """
    n = np.asarray(marker.normal, float)
    a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    x = a - n * (a @ n)
    x /= np.linalg.norm(x)
    return make_T(np.column_stack([x, np.cross(n, x), n]), marker.center)


def standard_view_pose(marker: Marker, standoff_mm: float) -> np.ndarray:
    """``T_o_c`` of the standard view: camera on the normal at ``standoff_mm``, looking at the centre.

    Camera +z = −normal; camera +x = the marker frame's x (so the view's in-plane rotation is fixed).
    """
    T_o_m = marker_frame(marker)
    R = T_o_m[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # rotate π about the marker x axis
    return make_T(R, marker.center + standoff_mm * np.asarray(marker.normal, float))


def perturbed_view_pose(T_o_c: np.ndarray, target_o: np.ndarray, rng: np.random.Generator, *,
                        standoff_error: float = 0.03, axis_error_deg: float = 2.0,
                        in_plane: bool = True) -> np.ndarray:
    """A standard-view pose as a real run would reach it (benchmark of paper §3.4):

    random in-plane rotation about the optical axis, stand-off scaled by ``1 ± standoff_error``
    (uniform), and the optical axis tilted by up to ``axis_error_deg`` about a random axis
    perpendicular to it, pivoting on ``target_o`` (the marker centre, mm in O).
    """
    T = np.array(T_o_c, dtype=float)
    target = np.asarray(target_o, float)
    if in_plane:
        T[:3, :3] = T[:3, :3] @ rotvec_to_matrix([0, 0, rng.uniform(-np.pi, np.pi)])
    offset = T[:3, 3] - target
    offset *= 1.0 + rng.uniform(-standoff_error, standoff_error)
    phi = rng.uniform(0, 2 * np.pi)
    axis_c = np.array([np.cos(phi), np.sin(phi), 0.0])
    R_tilt = rotvec_to_matrix(T[:3, :3] @ axis_c * np.radians(rng.uniform(0, axis_error_deg)))
    T[:3, :3] = R_tilt @ T[:3, :3]
    T[:3, 3] = target + R_tilt @ offset
    return T


def resting_pose_for_view(stable_poses: list[tuple[np.ndarray, float]], T_o_c: np.ndarray, *, yaw_rad: float = 0.0,
                          choice: str = "upright", rng: np.random.Generator | None = None,
                          min_camera_height_mm: float = 1.0) -> np.ndarray | None:
    """``T_w_o``: the object resting on the table (z = 0 of W) in a stable pose that shows the view.

    The standard view of a marker is taken of the object lying on the table (paper §3.4, §5.2),
    so the object is put in one of its stable poses ``(T_s_o, p)`` (lowest point on z = 0, centre
    of mass over the origin), turned by ``yaw_rad`` about the vertical, and the camera at
    ``T_o_c`` must then be at least ``min_camera_height_mm`` above the table. ``choice``:
    ``"upright"`` — the pose in which the camera looks down most steeply (the marker faces up
    as much as possible; ties to the most probable pose), used when teaching; ``"random"`` —
    a pose drawn with its probability among those that put the camera above the table (what a
    run meets). Returns None when no stable pose puts the camera above the table.
    """
    T_o_c = np.asarray(T_o_c, float)
    ok_l, elev_l, prob_l = [], [], []
    for T_s_o, p in stable_poses:
        cam_w = T_s_o[:3, :3] @ T_o_c[:3, 3] + T_s_o[:3, 3]
        ok_l.append(cam_w[2] >= min_camera_height_mm)
        elev_l.append(float(-(T_s_o[:3, :3] @ T_o_c[:3, 2])[2]))  # upward component of the view-to-camera axis
        prob_l.append(float(p))
    ok, elev, prob = np.array(ok_l), np.array(elev_l), np.array(prob_l)
    if not ok.any():
        return None
    idx = np.flatnonzero(ok)
    if choice == "upright":
        top = elev[idx].max()
        tied = idx[elev[idx] >= top - 1e-6]
        k = int(tied[np.argmax(prob[tied])])
    elif choice == "random":
        rng = rng if rng is not None else np.random.default_rng(0)
        w = prob[idx] + 1e-9
        k = int(rng.choice(idx, p=w / w.sum()))
    else:
        raise ValueError(f"unknown pose choice {choice!r} (upright, random)")
    return make_T(rotvec_to_matrix([0.0, 0.0, yaw_rad])) @ np.asarray(stable_poses[k][0], float)


def mm_per_px(camera: CameraModel, standoff_mm: float) -> float:
    """Metric scale (mm per pixel) in the plane at the stand-off distance: ``Z / f_x``."""
    return float(standoff_mm / camera.K[0, 0])


def build_standard_views(markers: list[Marker], render_view: RenderView, *, standoff_mm: float,
                         scale_mm_per_px: float, progress: Callable[[int], None] | None = None,
                         on_crop: Callable[[int, str], None] | None = None,
                         on_fail: Callable[[int, str], None] | None = None) -> list[StandardView]:
    """Render and describe the standard view of every marker (paper §3.4).

    Raises :class:`labctl.vision.shape.ShapeError` if a view shows no complete silhouette, unless
    ``on_fail(marker_id, reason)`` is given: then that marker gets no view and is reported there.
    A view that is complete as taught but would leave the image at some in-plane rotation raises
    too, unless ``on_crop(marker_id, reason)`` is given: then it is reported there and kept.
    """
    views = []
    for m in markers:
        img = render_view(standard_view_pose(m, standoff_mm))
        try:
            mask = silhouette_mask(img)
        except ShapeError as exc:
            if on_fail is None:
                raise
            on_fail(m.id, str(exc))
            continue
        try:
            check_fits_any_rotation(mask)
        except ShapeError as exc:
            if on_crop is None:
                raise
            on_crop(m.id, str(exc))
        views.append(StandardView(m.id, features_from_image(img, scale_mm_per_px), img))
        if progress is not None:
            progress(1)
    return views


def check_fits_any_rotation(mask: np.ndarray, margin_px: int = 4) -> None:
    """Raise :class:`ShapeError` unless the silhouette stays in the image for any in-plane rotation.

    A standard view is reached with an arbitrary rotation about the optical axis, so the object
    must lie within the circle inscribed in the image around its centre.
    """
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    r = np.sqrt((xs - (w - 1) / 2) ** 2 + (ys - (h - 1) / 2) ** 2).max()
    limit = min(w, h) / 2 - margin_px
    if r > limit:
        raise ShapeError(f"the object reaches {r:.0f} px from the view centre (limit {limit:.0f} px for any "
                         "in-plane rotation): too large for the standard view at this stand-off")


def silhouette_renderer(camera: CameraModel, mesh: trimesh.Trimesh, markers: Sequence[Marker] = (), *,
                        table_grey: int = 60, object_grey: int = 185, noise_sigma: float = 2.0,
                        rng: np.random.Generator | None = None) -> RenderView:
    """A quick flat-shaded renderer ``T_o_c -> BGR image`` (for tests and fast sweeps).

    Projects every triangle with the camera's full Tsai model and fills it; markers facing the
    camera are drawn as red projected circles. No occlusion ordering is needed for a binary
    silhouette. The simulated lab's renderer (``labctl.sim.render``) is the faithful one.
    """
    V = np.asarray(mesh.vertices, float)
    F = np.asarray(mesh.faces)
    rng = rng if rng is not None else np.random.default_rng(0)

    def render_view(T_o_c: np.ndarray) -> np.ndarray:
        T_c_o = invert(T_o_c)
        px = camera.project(V @ T_c_o[:3, :3].T + T_c_o[:3, 3])
        img = np.full((camera.height, camera.width, 3), table_grey, np.uint8)
        tris = np.round(px[F] * 16).astype(np.int32)
        for t in tris:
            cv2.fillConvexPoly(img, t, (object_grey,) * 3, lineType=cv2.LINE_8, shift=4)
        for m in markers:
            to_cam = T_o_c[:3, 3] - m.center
            if to_cam @ m.normal <= 0:
                continue
            T_o_m = marker_frame(m)
            a = np.linspace(0, 2 * np.pi, 48, endpoint=False)
            rim = m.center + m.radius * (np.cos(a)[:, None] * T_o_m[:3, 0] + np.sin(a)[:, None] * T_o_m[:3, 1])
            pr = camera.project(rim @ T_c_o[:3, :3].T + T_c_o[:3, 3])
            cv2.fillPoly(img, [np.round(pr * 16).astype(np.int32)], (40, 40, 200), shift=4)
        if noise_sigma > 0:
            img = np.clip(img + rng.normal(0, noise_sigma, img.shape), 0, 255).astype(np.uint8)
        return img

    return render_view


def contact_sheet(images: list[np.ndarray], labels: list[str], *, thumb: int = 240, cols: int = 4,
                  sublabels: list[str] | None = None, highlight: list[bool] | None = None) -> np.ndarray:
    """Grid of labelled thumbnails of the standard views (BGR): ``labels`` on top, ``sublabels``
    (face, ambiguity group) at the bottom, an orange frame round views marked in ``highlight``."""
    if not images:
        return np.zeros((thumb, thumb, 3), np.uint8)
    rows = (len(images) + cols - 1) // cols
    ncol = min(cols, len(images))
    sheet = np.full((rows * thumb, ncol * thumb, 3), 255, np.uint8)
    for k, (img, lab) in enumerate(zip(images, labels, strict=True)):
        h, w = img.shape[:2]
        s = thumb / max(h, w)
        t = cv2.resize(img, (max(1, int(w * s)), max(1, int(h * s))), interpolation=cv2.INTER_AREA)
        r, c = divmod(k, cols)
        y0, x0 = r * thumb + (thumb - t.shape[0]) // 2, c * thumb + (thumb - t.shape[1]) // 2
        sheet[y0:y0 + t.shape[0], x0:x0 + t.shape[1]] = t
        cv2.putText(sheet, lab, (c * thumb + 6, r * thumb + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 160, 0), 1,
                    cv2.LINE_AA)
        if sublabels:
            cv2.putText(sheet, sublabels[k], (c * thumb + 6, (r + 1) * thumb - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                        (0, 200, 255), 1, cv2.LINE_AA)
        if highlight and highlight[k]:
            cv2.rectangle(sheet, (c * thumb + 1, r * thumb + 1), ((c + 1) * thumb - 2, (r + 1) * thumb - 2),
                          (0, 140, 255), 3)
    return sheet
