"""The plain OpenCV marker pipeline, kept as the baseline our sub-pixel pipeline is measured
against: HSV threshold → ``cv2.findContours`` → ``cv2.fitEllipse`` on the pixel contour.

The contour runs through the centres of the boundary pixels, so its ellipse sits about half a
pixel inside the true edge; the pose solver then places the marker ~1 % too far.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..vision.ellipse import Ellipse, EllipseFitError, ellipse_from_cv_box
from ..vision.markers import RED, MarkerThresholds, red_mask


def opencv_marker_ellipse(image_bgr, *, thresholds: MarkerThresholds = RED) -> Ellipse | None:
    """Ellipse (image pixels) of the largest red blob by findContours + fitEllipse, or None."""
    mask = red_mask(image_bgr, thresholds)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    biggest = max(contours, key=cv2.contourArea)
    if len(biggest) < 5:
        return None
    try:
        return ellipse_from_cv_box(cv2.fitEllipse(biggest))
    except EllipseFitError:
        return None


def centroid_inrange_moments(image_bgr, *, thresholds: MarkerThresholds = RED):
    """The simplest tracker front end: cv2.inRange on HSV + cv2.moments of the whole mask.
    Returns the (x, y) centroid of all red pixels, or None."""
    mask = red_mask(image_bgr, thresholds)
    m = cv2.moments(mask, binaryImage=True)
    if m["m00"] == 0:
        return None
    return np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])
