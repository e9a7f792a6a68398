"""Annotated marker images like the paper's Fig. 5(a): fitted ellipse, its axes and centres.

Pure drawing: a BGR image in, a new BGR image out (the input is not modified).
"""

from __future__ import annotations

import cv2
import numpy as np

from .circle_pose import CirclePose
from .ellipse import Ellipse

_SHIFT = 4  # OpenCV sub-pixel drawing: coordinates in 1/16 px
_ONE = 1 << _SHIFT


def _pt(xy) -> tuple[int, int]:
    return int(round(float(xy[0]) * _ONE)), int(round(float(xy[1]) * _ONE))


def annotate_marker(image_bgr: np.ndarray, ellipse: Ellipse, *, boundary=None, label: str | None = None,
                    circle_centre_px=None, scale: int = 1) -> np.ndarray:
    """Draw ``ellipse`` (image pixels), its major (green) and minor (blue) axes, its centre
    (yellow cross), the optional boundary points (white dots), the image of the circle's true
    centre (magenta ring, ``circle_centre_px``) and a text ``label``. ``scale`` enlarges the
    image first (nearest neighbour) so that sub-pixel detail stays visible."""
    img = np.ascontiguousarray(image_bgr).copy()
    if scale > 1:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)

    def s(xy):  # image pixel → drawing coordinates (pixel centres at +0.5 after upscaling)
        return _pt(((float(xy[0]) + 0.5) * scale - 0.5, (float(xy[1]) + 0.5) * scale - 0.5))

    c = ellipse.center
    major, minor = ellipse.axes
    u = np.array([np.cos(ellipse.angle), np.sin(ellipse.angle)])
    v = np.array([-u[1], u[0]])
    axes_px = (int(round(major * scale * _ONE)), int(round(minor * scale * _ONE)))
    if boundary is not None:
        for p in np.asarray(boundary, float):
            cv2.circle(img, s(p), _ONE // 3, (255, 255, 255), -1, cv2.LINE_AA, _SHIFT)
    cv2.ellipse(img, s(c), axes_px, float(np.degrees(ellipse.angle)), 0, 360, (0, 255, 255), 1, cv2.LINE_AA, _SHIFT)
    cv2.line(img, s(c - major * u), s(c + major * u), (0, 200, 0), 1, cv2.LINE_AA, _SHIFT)
    cv2.line(img, s(c - minor * v), s(c + minor * v), (255, 120, 0), 1, cv2.LINE_AA, _SHIFT)
    arm = 3.0 / max(scale, 1)
    cv2.line(img, s(c - (arm, 0)), s(c + (arm, 0)), (0, 255, 255), 1, cv2.LINE_AA, _SHIFT)
    cv2.line(img, s(c - (0, arm)), s(c + (0, arm)), (0, 255, 255), 1, cv2.LINE_AA, _SHIFT)
    if circle_centre_px is not None and np.all(np.isfinite(circle_centre_px)):
        cv2.circle(img, s(circle_centre_px), 3 * _ONE, (255, 0, 255), 1, cv2.LINE_AA, _SHIFT)
    if label:
        x, y = int((c[0] + major + 4) * scale), int((c[1] - major) * scale)
        y = max(y, 14)
        x = min(x, img.shape[1] - 8 * len(label))
        cv2.putText(img, label, (max(x, 2), y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(img, label, (max(x, 2), y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def circle_centre_pixel(pose: CirclePose, camera) -> np.ndarray:
    """Where the circle's true centre projects (distorted pixels of ``camera``)."""
    return np.asarray(camera.project(pose.center), float)
