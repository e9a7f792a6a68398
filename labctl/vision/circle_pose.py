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

import cv2
import numpy as np

from .ellipse import Ellipse, fit_ellipse


class CirclePoseError(ValueError):
    """The ellipse and camera do not define a real circle in front of the camera."""


@dataclass(frozen=True)
class CirclePose:
    """A circle's centre (mm, camera frame, z > 0) and unit normal pointing towards the camera
    (normal · centre < 0)."""

    center: np.ndarray
    normal: np.ndarray

    def to_dict(self) -> dict:
        return {"center_mm": [float(v) for v in self.center], "normal": [float(v) for v in self.normal]}


def _cone_matrix(ellipse: Ellipse, K) -> np.ndarray:
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3) or not math.isfinite(float(K.sum())):
        raise CirclePoseError("K must be a finite 3×3 camera matrix")
    Q = K.T @ ellipse.matrix @ K  # pixel x = K X  →  Xᵀ (Kᵀ C K) X = 0
    scale = math.sqrt(float(np.vdot(Q, Q)))
    if not (scale > 0 and math.isfinite(scale)):
        raise CirclePoseError("degenerate cone")
    return Q / scale


def circle_poses(ellipse: Ellipse, radius: float, K) -> tuple[CirclePose, CirclePose]:
    """Both candidate poses of a circle of ``radius`` (mm) whose image is ``ellipse``.

    ``ellipse`` is in undistorted pixels, ``K`` the 3×3 pinhole matrix. Returns two
    :class:`CirclePose` (centre in mm in the camera frame with z > 0, unit normal towards the
    camera). Closed-form cone/plane solution of Safaee-Rad et al. (1992), paper §3.2. When the
    circle faces the camera squarely the two candidates coincide. Raises
    :class:`CirclePoseError` if the cone is not a real elliptic cone.
    """
    try:
        radius = float(radius)
    except (TypeError, ValueError):
        raise CirclePoseError(f"radius must be a number of mm, got {radius!r}") from None
    if not (math.isfinite(radius) and radius > 0):
        raise CirclePoseError(f"radius must be a positive number of mm, got {radius!r}")
    Q = _cone_matrix(ellipse, K)
    ok, lam, V = cv2.eigen(Q)  # descending eigenvalues; eigenvectors as rows
    if not ok:
        raise CirclePoseError("eigen-decomposition of the cone failed")
    lam_c, lam_b, lam_a = lam.ravel().tolist()
    cols = V.tolist()[::-1]
    if lam_b < 0:  # one positive, two negative eigenvalues: flip the quadric's sign
        l1, l2, l3 = -lam_a, -lam_b, -lam_c
        e1, e3 = cols[0], cols[2]
    else:
        l1, l2, l3 = lam_c, lam_b, lam_a
        e1, e3 = cols[2], cols[0]
    if not (l2 > 0 > l3 and math.isfinite(l1)):
        raise CirclePoseError("the ellipse does not define a real elliptic cone")
    span = l1 - l3
    g = math.sqrt(max(l1 - l2, 0.0) / span)
    h = math.sqrt(max(l2 - l3, 0.0) / span)
    gamma = l1 * g * g + l3 * h * h
    poses = []
    for sign in (1.0, -1.0):
        # canonical frame: n = (s g, 0, h), u = (0, 1, 0), v = n × u = (−h, 0, s g)
        beta = sign * g * h * (l3 - l1)
        k2 = (beta / l2) ** 2 - gamma / l2
        if not k2 > 0:
            raise CirclePoseError("the cone has no circular section (degenerate ellipse)")
        d = radius / math.sqrt(k2)
        bl = beta / l2
        n = [sign * g * e1[i] + h * e3[i] for i in range(3)]
        # centre = d (n − (β/λ2) v) with v = −h e1 + s g e3
        c = [d * (n[i] - bl * (-h * e1[i] + sign * g * e3[i])) for i in range(3)]
        if c[2] < 0:
            c = [-v for v in c]
        if n[0] * c[0] + n[1] * c[1] + n[2] * c[2] > 0:
            n = [-v for v in n]
        norm = math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        if not (norm > 0 and all(math.isfinite(v) for v in c)):
            raise CirclePoseError("non-finite circle pose")
        poses.append(CirclePose(np.array(c), np.array([n[0] / norm, n[1] / norm, n[2] / norm])))
    return poses[0], poses[1]


def marker_pose_candidates(marker, camera, radius: float) -> tuple[CirclePose, CirclePose]:
    """Both pose candidates of a detected marker (:class:`labctl.vision.Marker`).

    Undistorts the marker's sub-pixel boundary points with ``camera.undistort_pixels``
    (a :class:`labctl.geometry.CameraModel`), refits the ellipse there with the marker's
    weights (paper §3.1), and solves the cone/plane problem with ``camera.K`` (paper §3.2).
    Centres in mm in the camera frame.
    """
    boundary = np.asarray(marker.boundary, dtype=float)
    points = camera.undistort_pixels(boundary) if camera.kappa1 != 0.0 else boundary
    ellipse = fit_ellipse(points, marker.weights)
    return circle_poses(ellipse, radius, camera.K)
