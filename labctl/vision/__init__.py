"""labctl.vision: marker detection, ellipse fitting, circle pose and its duality (paper §3.1–3.3).

Pure functions on images and arrays; no devices, no clocks.
"""

from .circle_pose import CirclePose, CirclePoseError, MarkerPoses, circle_poses, marker_pose_candidates, marker_poses
from .duality import (
    DualityResult,
    PairConsistency,
    pose_pair_consistency,
    resolve_duality,
    resolve_duality_detailed,
    resolve_duality_noise_aware,
)
from .ellipse import Ellipse, EllipseFitError, ellipse_from_cv_box, fit_ellipse
from .markers import (
    Marker,
    MarkerImageError,
    MarkerQuality,
    MarkerSearch,
    MarkerThresholds,
    detect_markers,
    detect_markers_windowed,
    find_markers,
    red_blob_centroid,
    red_mask,
    why_no_marker,
)
from .response import Response, ResponseError, parse_response

__all__ = [
    "CirclePose", "CirclePoseError", "DualityResult", "Ellipse", "EllipseFitError", "Marker", "MarkerImageError",
    "MarkerPoses", "MarkerQuality", "MarkerSearch", "MarkerThresholds", "marker_poses", "resolve_duality_noise_aware",
    "Response", "ResponseError", "find_markers", "parse_response", "why_no_marker",
    "circle_poses", "detect_markers", "detect_markers_windowed", "ellipse_from_cv_box", "fit_ellipse",
    "marker_pose_candidates",
    "PairConsistency", "pose_pair_consistency", "red_blob_centroid", "red_mask", "resolve_duality",
    "resolve_duality_detailed",
]
