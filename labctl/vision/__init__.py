"""labctl.vision: marker detection, ellipse fitting, circle pose and its duality (paper §3.1–3.3).

Pure functions on images and arrays; no devices, no clocks.
"""

from .circle_pose import CirclePose, CirclePoseError, circle_poses, marker_pose_candidates
from .duality import DualityResult, resolve_duality, resolve_duality_detailed
from .ellipse import Ellipse, EllipseFitError, ellipse_from_cv_box, fit_ellipse
from .markers import Marker, MarkerImageError, detect_markers, detect_markers_windowed, red_mask

__all__ = [
    "CirclePose", "CirclePoseError", "DualityResult", "Ellipse", "EllipseFitError", "Marker", "MarkerImageError",
    "circle_poses", "detect_markers", "detect_markers_windowed", "ellipse_from_cv_box", "fit_ellipse",
    "marker_pose_candidates", "red_mask", "resolve_duality", "resolve_duality_detailed",
]
