"""Red marker detection with sub-pixel, weighted boundary points (He et al. 1996, §3.1, §4.1).

Pipeline for one BGR image (pixels are the image's own, i.e. distorted, frame-buffer pixels):

1. **Colour threshold** in HSV (hue window around red, minimum saturation, minimum value), so
   that shading — which scales R, G and B together — leaves hue and saturation unchanged.
2. **Connected components** (8-connected). Blobs that are too small, cut by the image (or
   search-window) border, or not elliptical are rejected.
3. **Sub-pixel boundary.** Per blob, a linear "redness" image is normalised
   by the blob's own inside and outside levels into a coverage image c ∈ [0, 1] (linear in the
   fraction of the pixel the marker covers, so anti-aliasing and shading do not bias it).
   The "redness" is the projection of each pixel's BGR colour on the difference between the
   blob's inside and outside colours (means over its core and a ring around it), so any
   configured marker colour works. Each
   row (where the boundary is closer to vertical) and each column (closer to horizontal) that
   crosses the 50 % level gives one boundary point by the *area* rule: along a 6-pixel scan
   across the edge the edge sits at (start − ½) + Σ c, which is exact for a straight edge at
   any sub-pixel phase and angle up to 45° (no interpolation bias). Each point's weight wᵢ is
   the boundary arc length it stands for (1/|cos| of the angle between scan and edge normal):
   the paper's weights for non-uniform sampling (eq. 2).
4. **Ellipse fit** of the boundary points with those weights (:func:`fit_ellipse`).

The windowed mode searches only a rectangle around a predicted position (the tracker's
one-step-ahead window, paper §4.1) and falls back to the full frame when nothing is found.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .ellipse import Ellipse, EllipseFitError, fit_ellipse


class MarkerImageError(ValueError):
    """The image cannot be searched (not an H×W×3 uint8/float array, or empty)."""


@dataclass(frozen=True)
class Marker:
    """One detected marker: ``centroid`` (x, y) px (coverage-weighted, sub-pixel), ``ellipse``
    fitted to ``boundary`` (N×2 sub-pixel points) with ``weights`` (arc length per point),
    ``area`` (px², coverage sum), ``bbox`` (x0, y0, x1, y1) and ``touches_border`` (the blob
    reaches the image edge, so its boundary is incomplete). All in the image's own pixels."""

    centroid: tuple[float, float]
    ellipse: Ellipse
    area: float
    boundary: np.ndarray = field(repr=False)
    weights: np.ndarray = field(repr=False)
    bbox: tuple[int, int, int, int]
    touches_border: bool = False
    fit_rms_px: float = 0.0

    def to_dict(self) -> dict:
        return {"centroid_px": [float(v) for v in self.centroid], "area_px": float(self.area),
                "bbox": list(self.bbox), "touches_border": bool(self.touches_border),
                "fit_rms_px": float(self.fit_rms_px), "boundary_points": int(len(self.boundary)),
                "ellipse": self.ellipse.to_dict()}


def _as_bgr(image) -> np.ndarray:
    img = np.asarray(image) if image is not None else None
    if img is None or img.ndim != 3 or img.shape[2] != 3 or img.size == 0:
        shape = None if img is None else img.shape
        raise MarkerImageError(f"expected an H×W×3 BGR image, got shape {shape}")
    if img.dtype != np.uint8:
        if not np.issubdtype(img.dtype, np.number):
            raise MarkerImageError(f"unsupported image dtype {img.dtype}")
        f = np.nan_to_num(img.astype(np.float64), nan=0.0, posinf=255.0, neginf=0.0)
        if f.max(initial=0.0) <= 1.0:
            f = f * 255.0
        img = np.clip(np.rint(f), 0, 255).astype(np.uint8)
    return img


def red_mask(image_bgr: np.ndarray, hue_range_deg=(-15.0, 15.0), min_saturation: float = 0.45,
             min_value: float = 0.15) -> np.ndarray:
    """Binary mask (uint8 0/255) of pixels whose HSV hue lies in ``hue_range_deg`` (degrees,
    may straddle 0°, e.g. (−15, 15) for red), saturation ≥ ``min_saturation`` and value ≥
    ``min_value`` (both 0–1). Hue and saturation do not change under shading."""
    img = _as_bgr(image_bgr)
    lo, hi = (float(v) for v in hue_range_deg)
    s_min = int(np.ceil(255.0 * float(min_saturation)))
    v_min = int(np.ceil(255.0 * float(min_value)))
    if hi - lo >= 360.0:
        hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV_FULL)
        return cv2.inRange(hsv, (0, s_min, v_min), (255, 255, 255))
    lo, hi = lo % 360.0, (lo % 360.0) + (hi - lo)
    if hi >= 360.0:
        # the window wraps through 0° (red): read the BGR image as RGB, which maps hue h to
        # 240° − h and moves the window away from the wrap, so one inRange suffices
        hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV_FULL)
        lo, hi = 240.0 - hi, 240.0 - lo
        lo, hi = lo % 360.0, (lo % 360.0) + (hi - lo)
    else:
        hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV_FULL)
    h_lo = int(np.ceil(lo * 256.0 / 360.0))
    h_hi = int(np.floor(hi * 256.0 / 360.0))
    if h_hi <= 255:
        return cv2.inRange(hsv, (h_lo, s_min, v_min), (h_hi, 255, 255))
    a = cv2.inRange(hsv, (h_lo, s_min, v_min), (255, 255, 255))
    b = cv2.inRange(hsv, (0, s_min, v_min), (h_hi - 256, 255, 255))
    return cv2.bitwise_or(a, b)


_SCAN = 6  # pixels per area-rule scan across an edge (3 on each side of the crossing)


def _edge_points(c: np.ndarray, axis: int):
    """Sub-pixel 50 % crossings of coverage image ``c`` along ``axis`` (1: rows, 0: columns)
    by the area rule. Returns (positions N×2 as (x, y) in ``c``'s pixels, clean N bool)."""
    if axis == 0:
        pts, ok = _edge_points(c.T, 1)
        return pts[:, ::-1], ok
    inside = c > 0.5
    rows, cols = np.nonzero(inside[:, 1:] != inside[:, :-1])  # crossing between cols j and j+1
    if rows.size == 0:
        return np.empty((0, 2)), np.empty(0, bool)
    width = c.shape[1]
    start = cols - (_SCAN // 2 - 1)
    ok = (start >= 0) & (start + _SCAN <= width)
    start = np.clip(start, 0, max(width - _SCAN, 0))
    idx = start[:, None] + np.arange(_SCAN)[None, :]
    idx = np.minimum(idx, width - 1)
    prof = c[rows[:, None], idx]
    total = prof.sum(axis=1)
    falling = inside[rows, cols]  # marker on the left of the crossing
    pos = np.where(falling, start - 0.5 + total, start + _SCAN - 0.5 - total)
    # the scan must run from plateau to plateau (else another edge or a tip is inside it)
    first, last = prof[:, 0], prof[:, -1]
    ok &= np.where(falling, (first > 0.8) & (last < 0.2), (first < 0.2) & (last > 0.8))
    return np.column_stack([pos, rows.astype(float)]), ok


def _boundary(c: np.ndarray, ellipse0: Ellipse) -> tuple[np.ndarray, np.ndarray]:
    """Weighted sub-pixel boundary points of the blob in coverage image ``c`` (ROI pixels)."""
    A = ellipse0.matrix[:2, :2]
    ctr = ellipse0.center
    out_p, out_w = [], []
    for axis in (1, 0):
        pts, ok = _edge_points(c, axis)
        if not np.any(ok):
            continue
        pts = pts[ok]
        normal = (pts - ctr) @ A  # ∝ ∇Q of the rough ellipse
        nn = np.hypot(normal[:, 0], normal[:, 1])
        along = np.abs(normal[:, 0 if axis == 1 else 1]) / np.maximum(nn, 1e-12)
        # rows take the edge where it is closer to vertical, columns where closer to horizontal
        keep = along > np.sqrt(0.5) if axis == 1 else along >= np.sqrt(0.5)
        out_p.append(pts[keep])
        out_w.append(1.0 / along[keep])
    if not out_p:
        return np.empty((0, 2)), np.empty(0)
    return np.concatenate(out_p), np.concatenate(out_w)


def _levels(roi: np.ndarray, blob: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Inside and outside colours (BGR means) of one blob: its core and a ring around it."""
    core = cv2.erode(blob, _K3, iterations=2)
    if np.count_nonzero(core) < 3:
        core = cv2.erode(blob, _K3, iterations=1)
    if np.count_nonzero(core) < 3:
        core = blob
    ring = cv2.dilate(blob, _K3, iterations=4) & ~cv2.dilate(blob, _K3, iterations=2)
    if not (np.count_nonzero(core) and np.count_nonzero(ring)):
        return None
    # means over clean pixels (core well inside, ring well outside); cv2.mean is fast
    return np.array(cv2.mean(roi, mask=core)[:3]), np.array(cv2.mean(roi, mask=ring)[:3])


def _analyse_blob(img: np.ndarray, labels: np.ndarray, label: int, bbox, label_origin,
                  max_fit_rms_px: float, refine: bool) -> Marker | None:
    """Measure one connected component: ``bbox`` (x, y, w, h) in ``labels``' pixels, whose
    top-left pixel is ``label_origin`` in the full image ``img``."""
    x, y, w, h = bbox
    lx, ly = label_origin
    H, W = img.shape[:2]
    pad = _SCAN
    gx, gy = x + lx, y + ly  # blob bbox in image pixels
    x0, y0 = max(gx - pad, 0), max(gy - pad, 0)
    x1, y1 = min(gx + w + pad, W), min(gy + h + pad, H)
    blob = np.zeros((y1 - y0, x1 - x0), np.uint8)
    blob[gy - y0:gy - y0 + h, gx - x0:gx - x0 + w] = labels[y:y + h, x:x + w] == label
    touches = bool(gx <= 0 or gy <= 0 or gx + w >= W or gy + h >= H)
    bbox_img = (int(gx), int(gy), int(gx + w), int(gy + h))
    mb = cv2.moments(blob, binaryImage=True)
    if not refine:  # tracker mode (paper §4.1): centroid and moment ellipse of the thresholded blob
        rough = _moment_ellipse(mb)
        if rough is None:
            return None
        centroid = (mb["m10"] / mb["m00"] + x0, mb["m01"] / mb["m00"] + y0)
        ell = Ellipse.from_conic(_shift_conic(rough.conic, x0, y0))
        return Marker(centroid, ell, float(mb["m00"]), np.empty((0, 2)), np.empty(0), bbox_img, touches, float("nan"))
    roi = img[y0:y1, x0:x1].astype(np.float32)
    levels = _levels(roi, blob)
    if levels is None:
        return None
    col_in, col_out = levels
    contrast = col_in - col_out
    c2 = float(contrast @ contrast)
    if not c2 >= 100.0:  # under 10 grey levels of colour contrast: no measurable edge
        return None
    # coverage: each pixel's colour projected on the outside→inside colour difference
    c = (roi - col_out.astype(np.float32)) @ (contrast / c2).astype(np.float32)
    # keep only this blob's neighbourhood (other blobs in the ROI must not add edges)
    near = cv2.dilate(blob, _K3, iterations=pad)
    c[near == 0] = 0.0
    cc = np.clip(c, 0.0, 1.0)
    m = cv2.moments(cc)
    if m["m00"] < 3:
        return None
    area = float(m["m00"])
    centroid = (m["m10"] / area + x0, m["m01"] / area + y0)
    rough = _moment_ellipse(mb)
    if rough is None:
        return None
    pts, wts = _boundary(c, rough)
    if touches:  # drop points near the image edge: the boundary there is the frame, not the marker
        g = pts + (x0, y0)
        inner = (g[:, 0] > 1.5) & (g[:, 1] > 1.5) & (g[:, 0] < W - 2.5) & (g[:, 1] < H - 2.5)
        pts, wts = pts[inner], wts[inner]
    if len(pts) < 6:
        return None
    try:
        ell_roi = fit_ellipse(pts, wts, refine_iterations=3 if touches else 0)
    except EllipseFitError:
        return None
    d = ell_roi.sampson_distances(pts)
    rms = float(np.sqrt((wts @ (d * d)) / wts.sum()))
    if not (rms <= max_fit_rms_px):
        return None
    if not touches:  # the blob must look like its ellipse (not two touching discs, not a bar)
        ratio = area / ell_roi.area
        if not 0.8 < ratio < 1.2:
            return None
    ell = Ellipse.from_conic(_shift_conic(ell_roi.conic, x0, y0))
    return Marker(centroid, ell, area, pts + (x0, y0), wts, bbox_img, touches, rms)


_K3 = np.ones((3, 3), np.uint8)


def _moment_ellipse(m: dict) -> Ellipse | None:
    """Ellipse with the same area, centroid and second moments as a region (cv2.moments)."""
    if not m["m00"] > 0:
        return None
    mu = (m["m10"] / m["m00"], m["m01"] / m["m00"])
    a, b, c = m["mu20"] / m["m00"], m["mu11"] / m["m00"], m["mu02"] / m["m00"]
    half_tr, rad = 0.5 * (a + c), float(np.hypot(0.5 * (a - c), b))
    lo, hi = half_tr - rad, half_tr + rad
    if not lo > 1e-6:
        return None
    angle = 0.5 * float(np.arctan2(2.0 * b, a - c))
    try:
        return Ellipse.from_params(mu, (2.0 * np.sqrt(hi), 2.0 * np.sqrt(lo)), angle)
    except EllipseFitError:
        return None


def _shift_conic(q: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Conic of the same curve after translating coordinates by (dx, dy): Q'(x) = Q(x − d)."""
    a, b, c, d, e, f = q.tolist()
    d2 = d - 2 * a * dx - b * dy
    e2 = e - b * dx - 2 * c * dy
    f2 = a * dx * dx + b * dx * dy + c * dy * dy - d * dx - e * dy + f
    return np.array([a, b, c, d2, e2, f2])


def detect_markers(image_bgr, *, hue_range_deg=(-15.0, 15.0), min_saturation: float = 0.45,
                   min_value: float = 0.15, window=None, min_area_px: int = 12, keep_border: bool = False,
                   max_fit_rms_px: float = 0.6, max_markers: int = 32, refine: bool = True) -> list[Marker]:
    """Find red circular markers in a BGR image (paper §3.1 and §4.1's marker thresholding).

    ``hue_range_deg`` / ``min_saturation`` / ``min_value``: the HSV colour window (the camera's
    configured marker colour). ``window`` = (x0, y0, x1, y1) px restricts the search to that
    rectangle (the tracker's one-step-ahead window); blobs cut by its edge are rejected like
    blobs cut by the image border. ``keep_border=True`` keeps markers that reach the image
    edge (flagged ``touches_border``, ellipse fitted to the remaining arc). Blobs smaller than
    ``min_area_px``, non-elliptical ones (boundary RMS distance to the fitted ellipse above
    ``max_fit_rms_px``, or area unlike the ellipse's) are dropped. ``refine=False`` is the
    tracker's centroid-only mode (paper §4.1): the centroid, area and moment ellipse of the
    thresholded pixels, no boundary points, no shape check.

    Returns markers sorted by decreasing area (possibly empty). Raises
    :class:`MarkerImageError` only for an array that is not an image.
    """
    img = _as_bgr(image_bgr)
    H, W = img.shape[:2]
    ox = oy = 0
    sub = img
    if window is not None:
        try:
            wx0, wy0, wx1, wy1 = (int(round(float(v))) for v in window)
        except (TypeError, ValueError):
            raise MarkerImageError(f"window must be (x0, y0, x1, y1), got {window!r}") from None
        wx0, wy0 = max(wx0, 0), max(wy0, 0)
        wx1, wy1 = min(wx1, W), min(wy1, H)
        if wx1 - wx0 < 3 or wy1 - wy0 < 3:
            return []
        sub = img[wy0:wy1, wx0:wx1]
        ox, oy = wx0, wy0
    mask = red_mask(sub, hue_range_deg, min_saturation, min_value)
    sh, sw = mask.shape
    # label only the bounding box of all red pixels: labelling costs per pixel, markers are small
    bx, by, bw, bh = cv2.boundingRect(mask)
    if bw == 0 or bh == 0:
        return []
    ox, oy = ox + bx, oy + by
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask[by:by + bh, bx:bx + bw], connectivity=8)
    order = np.argsort(-stats[1:, cv2.CC_STAT_AREA]) + 1 if n > 1 else []
    found: list[Marker] = []
    for label in order:
        x, y, w, h, area = (int(v) for v in stats[label])
        if area < min_area_px:
            break
        at_image_edge = x + ox <= 0 or y + oy <= 0 or x + w + ox >= W or y + h + oy >= H
        at_window_edge = x + bx <= 0 or y + by <= 0 or x + bx + w >= sw or y + by + h >= sh
        if at_window_edge and not at_image_edge:
            continue  # cut by the search window: not measurable here
        if at_image_edge and not keep_border:
            continue
        marker = _analyse_blob(img, labels, label, (x, y, w, h), (ox, oy), max_fit_rms_px, refine)
        if marker is not None:
            found.append(marker)
            if len(found) >= max_markers:
                break
    return found


def detect_markers_windowed(image_bgr, predicted_xy, half_size_px: float, **kw) -> list[Marker]:
    """:func:`detect_markers` in the square window of half-size ``half_size_px`` around
    ``predicted_xy`` (the tracker's one-step-ahead prediction, paper §4.1); if nothing is found
    there (the marker was lost or left the window), search the full frame instead."""
    kw.pop("window", None)
    try:
        px, py = (float(v) for v in predicted_xy)
        half = float(half_size_px)
    except (TypeError, ValueError):
        px = py = half = float("nan")
    if np.isfinite(px) and np.isfinite(py) and np.isfinite(half) and half > 0:
        found = detect_markers(image_bgr, window=(px - half, py - half, px + half + 1, py + half + 1), **kw)
        if found:
            return found
    return detect_markers(image_bgr, **kw)
