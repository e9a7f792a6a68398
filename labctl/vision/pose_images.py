"""Pose the red markers of one or two images of a calibrated camera (paper §3.1–3.3).

The whole single-camera pipeline behind ``labctl vision pose``: detect the markers (§3.1), fit
their ellipses and compute both circle-pose candidates of each (§3.2), and, given a second image
of the same marker after a known kind of motion, resolve the pose duality (§3.3). Arrays in,
results out: reading files, the camera file and writing the annotated PNG stay with the caller.
Poses are in the camera frame C (mm); pixels in the image (x right, y down).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .annotate import annotate_marker, circle_centre_pixel
from .circle_pose import CirclePoseError, MarkerPoses, marker_poses
from .duality import DEFAULT_MIN_MARGIN_RAD, DualityResult, resolve_duality_noise_aware
from .ellipse import EllipseFitError
from .markers import RED, Marker, MarkerThresholds, find_markers
from .response import Response

__all__ = ["ImagePoseError", "PosedImages", "annotate_posed", "pose_images"]


class ImagePoseError(ValueError):
    """An image that cannot be posed: its index in the input and one line saying why."""

    def __init__(self, index: int, message: str):
        self.index = index
        super().__init__(message)


@dataclass
class PosedImages:
    """Each image's markers with their two circle-pose candidates (camera frame, mm), and the duality
    resolution across the two images (None for one image)."""

    per_image: list[list[tuple[Marker, MarkerPoses]]]
    duality: DualityResult | None = None
    motion: str | None = None

    def to_dict(self, names: list[str]) -> dict:
        """Plain data, one entry per image named by ``names`` (the caller's file names)."""
        out: dict = {"images": [{"image": name, "markers": [{**m.to_dict(), **cands.to_dict()} for m, cands in posed]}
                                for name, posed in zip(names, self.per_image, strict=True)]}
        if self.duality is not None:
            out["duality"] = {**self.duality.to_dict(), "motion": self.motion}
        return out


def pose_images(images: list[np.ndarray], camera, radius_mm: float, *, motion: str = "translation",
                plane_normal=None, min_margin_rad: float = DEFAULT_MIN_MARGIN_RAD,
                thresholds: MarkerThresholds = RED, response: Response | str = "linear") -> PosedImages:
    """Detect, fit and pose every marker of each BGR image (``camera``: a :class:`~labctl.geometry.Camera`,
    marker radius ``radius_mm``); with two images, resolve the duality of their one marker under
    ``motion`` ("translation", or "planar" with ``plane_normal`` in C). Raises :class:`ImagePoseError`
    naming the image: wrong size, no marker, more than one marker for the duality, or a marker whose
    ellipse gives no pose."""
    if not 1 <= len(images) <= 2:
        raise ValueError(f"one or two images, got {len(images)}")
    if motion == "planar" and plane_normal is None:
        raise ValueError("planar motion needs the motion plane's normal")
    per_image = []
    for i, img in enumerate(images):
        if img.shape[1] != camera.width or img.shape[0] != camera.height:
            raise ImagePoseError(i, f"image is {img.shape[1]}×{img.shape[0]}, camera file says "
                                    f"{camera.width}×{camera.height}")
        search = find_markers(img, thresholds=thresholds, response=response)
        if not search.markers:
            raise ImagePoseError(i, f"no marker found: {search.reason}")
        if len(images) == 2 and len(search.markers) > 1:
            raise ImagePoseError(i, f"{len(search.markers)} markers found; resolving the duality needs exactly one")
        posed = []
        for m in search.markers:
            try:
                posed.append((m, marker_poses(m, camera, radius_mm)))
            except (CirclePoseError, EllipseFitError) as exc:
                raise ImagePoseError(i, f"marker at {m.centroid[0]:.1f}, {m.centroid[1]:.1f}: {exc}") from None
        per_image.append(posed)
    if len(images) == 1:
        return PosedImages(per_image)
    res = resolve_duality_noise_aware(per_image[0][0][1], per_image[1][0][1], motion=motion,
                                      plane_normal=plane_normal, min_margin_rad=min_margin_rad)
    return PosedImages(per_image, res, motion)


def annotate_posed(image: np.ndarray, posed: PosedImages, camera) -> np.ndarray:
    """The last image of ``posed`` (BGR ``image``) annotated as in the paper's Fig. 5(a): each marker's
    ellipse and boundary, its pose's depth (the duality's choice if resolved, else the first candidate)
    and where the circle's centre projects; suspect detections are labelled with their flags."""
    drawn = image
    for k, (m, cands) in enumerate(posed.per_image[-1]):
        pose = posed.duality.best if posed.duality is not None else cands.candidates[0]
        tag = f"#{k} z={pose.center[2]:.0f}mm"
        if posed.duality is not None:
            d = posed.duality
            tag += " (ambiguous)" if d.ambiguous else f" margin {math.degrees(d.margin_rad):.2f} deg"
        if not m.trusted:
            tag += " SUSPECT: " + (",".join(m.quality.flags) if m.quality is not None else "not sub-pixel")
        drawn = annotate_marker(drawn, m.ellipse, boundary=m.boundary, label=tag,
                                circle_centre_px=circle_centre_pixel(pose, camera))
    return drawn
