"""The viewed marker's height above the table, measured in the standard view itself.

A standard view (paper §3.4) looks along the marker's normal from ``viewing.standoff_mm``: the
marker is a near-circle of ~50 px at the image centre, the best-conditioned marker image of the
whole run. Its pose (:func:`labctl.vision.marker_poses`, camera frame C) carried into the world
frame W by the camera pose the robot reports gives the marker centre's height above the table,
and the pose's centre covariance gives that height's standard deviation. Library views whose
marker cannot rest at that height in any stable pose of their object are not the object seen
(:func:`labctl.library.matching.height_gate`): standard views of plates that differ only in
thickness are the same rectangle, their marker heights are not.

The heights planned from the initial marker pose (1 m away, oblique, ~15 px markers) were off by
up to 13 mm under the realistic camera; this measurement does not depend on them.

Functional core: numpy in, numpy out; no clocks or devices.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..vision import CirclePoseError, EllipseFitError, detect_markers, marker_poses


@dataclass(frozen=True)
class MarkerHeight:
    """``height_mm`` of the marker centre above the table (mm, W's z minus the table's);
    ``sigma_mm`` its standard deviation from the pose covariance (mm); ``radius_mm`` the marker
    size it was solved with (the one whose distance agrees with the stand-off); ``depth_vertical_mm``
    the vertical component of the camera-to-marker vector (mm): a relative error of the distance
    (the marker's apparent size) moves the height by that fraction of it."""

    height_mm: float
    sigma_mm: float
    radius_mm: float
    depth_vertical_mm: float = 0.0

    def tolerance_mm(self, floor_mm: float, k_sigma: float, depth_frac: float) -> float:
        """How far (mm) a library view's marker height may lie from this one and still be the marker
        seen: ``floor_mm`` (the library's own error: markers placed by hand, resting poses) +
        ``k_sigma``·σ (image noise) + ``depth_frac``·``depth_vertical_mm`` (a bias of the apparent
        marker size: blur, demosaicing, JPEG or a focal-length error make the distance off by a
        fraction, which the covariance does not see). 0 when ``floor_mm`` is 0 (the gate is off)."""
        if floor_mm <= 0 or not np.isfinite(self.sigma_mm):
            return 0.0
        return float(floor_mm + k_sigma * self.sigma_mm + depth_frac * abs(self.depth_vertical_mm))


def measure_marker_height(image: np.ndarray, camera, T_w_c: np.ndarray, radii_mm: Sequence[float], *,
                          z_table_mm: float = 0.0, standoff_mm: float | None = None,
                          **detect_kw) -> MarkerHeight | None:
    """Height above the table of the marker nearest the centre of a standard view, or None.

    ``camera`` the mobile camera model (K, distortion); ``T_w_c`` its pose (camera → world, mm);
    ``radii_mm`` the marker radii the library uses: an ellipse fixes a circle's distance only up
    to its radius, so the radius whose distance lies nearest ``standoff_mm`` is taken (sizes are
    ≥ 1.25× apart, the stand-off is held to a few %; without a stand-off, the first radius).
    ``detect_kw`` go to :func:`labctl.vision.detect_markers` (colour ``thresholds``, response).
    None when no trusted marker is found or its pose cannot be solved.
    """
    markers = detect_markers(image, **detect_kw)
    if not markers or not len(radii_mm):
        return None
    h, w = image.shape[:2]
    mk = min(markers, key=lambda m: float(np.hypot(m.centroid[0] - w / 2.0, m.centroid[1] - h / 2.0)))
    best = None
    for r in radii_mm:
        try:
            mp = marker_poses(mk, camera, float(r))
        except (CirclePoseError, EllipseFitError, ValueError):
            continue
        # face-on, the two candidates share their centre; the normal closest to the optical axis is the one seen
        k = int(np.argmin([float(p.normal[2]) for p in mp.candidates]))
        c = np.asarray(mp.candidates[k].center, float)
        misfit = abs(float(np.linalg.norm(c)) - standoff_mm) if standoff_mm else 0.0
        if best is None or misfit < best[0]:
            best = (misfit, float(r), c, np.asarray(mp.center_cov[k], float))
        if not standoff_mm:
            break
    if best is None:
        return None
    _, r, c, cov = best
    R, t = np.asarray(T_w_c, float)[:3, :3], np.asarray(T_w_c, float)[:3, 3]
    z = float(R[2] @ c + t[2]) - float(z_table_mm)
    var = float(R[2] @ cov @ R[2])
    sigma = float(np.sqrt(var)) if np.isfinite(var) and var >= 0 else float("inf")
    return MarkerHeight(z, sigma, r, float(R[2] @ c))
