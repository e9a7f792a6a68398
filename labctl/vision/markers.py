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

import math
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np

from .ellipse import Ellipse, EllipseFitError, _fit


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


@lru_cache(maxsize=32)
def _hsv_ranges(hue_range_deg: tuple[float, float], min_saturation: float, min_value: float):
    """(cvtColor code, [(lower, upper) inRange bounds]) for an HSV colour window; cached, since
    the same window is used frame after frame."""
    lo, hi = hue_range_deg
    s_min = int(math.ceil(255.0 * min_saturation))
    v_min = int(math.ceil(255.0 * min_value))
    if hi - lo >= 360.0:
        return cv2.COLOR_BGR2HSV_FULL, [((0, s_min, v_min), (255, 255, 255))]
    lo, hi = lo % 360.0, (lo % 360.0) + (hi - lo)
    code = cv2.COLOR_BGR2HSV_FULL
    if hi >= 360.0:
        # the window wraps through 0° (red): read the BGR image as RGB, which maps hue h to
        # 240° − h and moves the window away from the wrap, so one inRange suffices
        code = cv2.COLOR_RGB2HSV_FULL
        lo, hi = 240.0 - hi, 240.0 - lo
        lo, hi = lo % 360.0, (lo % 360.0) + (hi - lo)
    h_lo = int(math.ceil(lo * 256.0 / 360.0))
    h_hi = int(math.floor(hi * 256.0 / 360.0))
    if h_hi <= 255:
        return code, [((h_lo, s_min, v_min), (h_hi, 255, 255))]
    return code, [((h_lo, s_min, v_min), (255, 255, 255)), ((0, s_min, v_min), (h_hi - 256, 255, 255))]


def _red_mask(img: np.ndarray, hue_range_deg, min_saturation: float, min_value: float) -> np.ndarray:
    lo, hi = (float(v) for v in hue_range_deg)
    code, bounds = _hsv_ranges((lo, hi), float(min_saturation), float(min_value))
    hsv = cv2.cvtColor(img, code)
    mask = cv2.inRange(hsv, *bounds[0])
    if len(bounds) > 1:
        mask = cv2.bitwise_or(mask, cv2.inRange(hsv, *bounds[1]))
    return mask


def red_mask(image_bgr: np.ndarray, hue_range_deg=(-15.0, 15.0), min_saturation: float = 0.45,
             min_value: float = 0.15) -> np.ndarray:
    """Binary mask (uint8 0/255) of pixels whose HSV hue lies in ``hue_range_deg`` (degrees,
    may straddle 0°, e.g. (−15, 15) for red), saturation ≥ ``min_saturation`` and value ≥
    ``min_value`` (both 0–1). Hue and saturation do not change under shading."""
    return _red_mask(_as_bgr(image_bgr), hue_range_deg, min_saturation, min_value)


_SCAN = 6  # pixels per area-rule scan across an edge (3 on each side of the crossing)
_SCAN_SUMS = np.zeros((_SCAN, 3), np.float32)  # profile → (sum, first − last, first + last)
_SCAN_SUMS[:, 0] = 1.0
_SCAN_SUMS[0, 1:] = 1.0
_SCAN_SUMS[-1, 1:] = (-1.0, 1.0)
_K5 = np.ones((5, 5), np.uint8)  # 3×3 dilated twice
_NEAR_PX = 4  # a blob's neighbourhood: its pixels dilated by 4 (covers every scan's outer plateau)
_K_NEAR = np.ones((2 * _NEAR_PX + 1, 2 * _NEAR_PX + 1), np.uint8)
_PAD = _NEAR_PX + _SCAN // 2  # crop margin: the coverage is zero in its outer _SCAN // 2 pixels


def _boundary(c: np.ndarray, center: tuple[float, float], quad: np.ndarray, padded: bool = False):
    """Weighted sub-pixel boundary points of the blob in coverage image ``c`` (float32, ROI
    pixels), paper §3.1: every row and column crossing the 50 % level gives one point by the
    area rule over a 6-px scan, (start − ½) + Σc, kept only where the scan runs from plateau
    (> 0.8) to plateau (< 0.2). Rows take the edge where it is closer to vertical, columns where
    it is closer to horizontal, judged by the normal of a rough ellipse (``center``, symmetric
    2×2 matrix ``quad`` of its quadratic form in (x − x0, y − y0)). Weight wᵢ = arc length
    per point = 1/|cos(scan, normal)| ∈ [1, √2] (the paper's non-uniform sampling weights, eq. 2).

    Vectorised over rows and columns at once on the flat image. ``c`` must be zero in its outer
    ``_SCAN // 2`` pixels (then every scan stays in its own row / column) unless ``padded`` is
    False, when such a margin is added here. Returns (points N×2 as (x, y) relative to
    ``center``, weights N)."""
    half = _SCAN // 2
    cp = c if padded else cv2.copyMakeBorder(c, half, half, half, half, cv2.BORDER_CONSTANT, value=0.0)
    margin = 0 if padded else half
    w = cp.shape[1]
    size = cp.size
    flat = cp.ravel()
    inside = flat > 0.5
    # flat index t of each scan's first pixel: a row scan covers t … t + 5 and crosses 50 %
    # between t + 2 and t + 3; a column scan covers t, t + w, … t + 5w. The zero margin keeps
    # every scan inside its own row / column.
    kr = np.flatnonzero(inside[half:] != inside[half - 1:-1])
    kc = np.flatnonzero(inside[half * w:] != inside[(half - 1) * w:-w])
    nr = kr.shape[0]
    n = nr + kc.shape[0]
    if n == 0:
        return np.empty((0, 2)), np.empty(0)
    # all row scans / column scans as strided views of the flat image (no copies)
    item = flat.itemsize
    row_scans = np.ndarray((size - _SCAN + 1, _SCAN), flat.dtype, flat, 0, (item, item))
    col_scans = np.ndarray((size - (_SCAN - 1) * w, _SCAN), flat.dtype, flat, 0, (item, item * w))
    prof = np.concatenate((row_scans[kr], col_scans[kc])) @ _SCAN_SUMS  # per scan: Σc, first − last, first + last
    total, drop, ends = prof[:, 0], prof[:, 1], prof[:, 2]
    # the edge's position along the scan from its first pixel: Σc − ½ for a falling edge
    # (marker first), _SCAN − ½ − Σc for a rising one
    offset = (total - 0.5 * _SCAN) * np.sign(drop) + 0.5 * (_SCAN - 1)
    # plateau to plateau, max(first, last) > 0.8 and min(first, last) < 0.2, else another edge
    # or a tip is inside the scan
    clean = np.abs(drop) - np.abs(ends - 1.0) > 0.6
    pts = np.empty((n, 2))
    pts[:, 1], pts[:, 0] = np.divmod(np.concatenate((kr, kc)), w)
    pts[:nr, 0] += offset[:nr]
    pts[nr:, 1] += offset[nr:]
    pts -= (margin + center[0], margin + center[1])  # relative to the rough centre
    # rough normal ∝ ∇Q; rows keep |nx| > |ny|, columns |ny| > |nx|
    normal2 = np.square(pts @ quad)
    norm2 = normal2[:, 0] + normal2[:, 1]
    along2 = np.concatenate((normal2[:nr, 0], normal2[nr:, 1]))
    keep = clean & (along2 + along2 > norm2)
    return pts[keep], np.sqrt(norm2[keep] / along2[keep])


def _levels(roi: np.ndarray, blob: np.ndarray, near: np.ndarray) -> tuple[tuple, tuple] | None:
    """Inside and outside colours (BGR means) of one blob (uint8 mask): over its core (eroded
    twice by 3×3) and over the ring 3…4 px around it (``near`` minus the blob dilated twice),
    i.e. over clean pixels well inside and well outside the anti-aliased edge."""
    core = cv2.erode(blob, _K5)
    if cv2.countNonZero(core) < 3:
        core = cv2.erode(blob, _K3)
        if cv2.countNonZero(core) < 3:
            core = blob
    ring = cv2.subtract(near, cv2.dilate(blob, _K5))
    if not cv2.countNonZero(ring):
        return None
    return cv2.mean(roi, mask=core)[:3], cv2.mean(roi, mask=ring)[:3]


def _sampson_rms(conic: list[float], pts: np.ndarray, weights: np.ndarray) -> float:
    """Weighted RMS first-order geometric distance |Q|/|∇Q| of ``pts`` to ``conic`` (px)."""
    a, b, c, d, e, f = conic
    x, y = pts[:, 0], pts[:, 1]
    gx = (2.0 * a) * x + b * y + d
    gy = b * x + (2.0 * c) * y + e
    q = 0.5 * (gx * x + gy * y + d * x + e * y) + f  # Q = ½ (x·∇Q + d x + e y) + f
    d2 = q * q / np.maximum(gx * gx + gy * gy, 1e-300)
    return math.sqrt(float(weights @ d2) / float(weights.sum()))


def _analyse_blob(img: np.ndarray, labels: np.ndarray, label: int, bbox, label_origin,
                  max_fit_rms_px: float, refine: bool) -> Marker | None:
    """Measure one connected component: ``bbox`` (x, y, w, h) in ``labels``' pixels, whose
    top-left pixel is ``label_origin`` in the full image ``img``. All work is on a small crop
    (the blob's bounding box plus the scan length)."""
    x, y, w, h = bbox
    lx, ly = label_origin
    H, W = img.shape[:2]
    pad = _PAD
    gx, gy = x + lx, y + ly  # blob bbox in image pixels
    touches = bool(gx <= 0 or gy <= 0 or gx + w >= W or gy + h >= H)
    bbox_img = (int(gx), int(gy), int(gx + w), int(gy + h))
    if not refine:  # tracker mode (paper §4.1): centroid and moment ellipse of the thresholded blob
        blob = (labels[y:y + h, x:x + w] == label).view(np.uint8)
        mb = cv2.moments(blob)  # 0/1 values: the binary moments, without binaryImage's cost
        rough = _moment_conic(mb, gx, gy)
        if rough is None:
            return None
        try:
            ell = Ellipse.from_conic(rough)
        except EllipseFitError:
            return None
        centroid = (mb["m10"] / mb["m00"] + gx, mb["m01"] / mb["m00"] + gy)
        return Marker(centroid, ell, float(mb["m00"]), np.empty((0, 2)), np.empty(0), bbox_img, touches, float("nan"))
    x0, y0 = max(gx - pad, 0), max(gy - pad, 0)
    x1, y1 = min(gx + w + pad, W), min(gy + h + pad, H)
    part = labels[y:y + h, x:x + w]
    if part.dtype != np.uint8:  # a label image: this label's pixels as 0/255
        part = cv2.compare(part, label, cv2.CMP_EQ)  # type: ignore[call-overload]  # cv2 stubs omit scalar src2
    blob = cv2.copyMakeBorder(part, gy - y0, y1 - gy - h, gx - x0, x1 - gx - w, cv2.BORDER_CONSTANT, value=0)
    roi = img[y0:y1, x0:x1]
    near = cv2.dilate(blob, _K_NEAR)  # the blob's neighbourhood: other blobs in the crop must not add edges
    levels = _levels(roi, blob, near)
    if levels is None:
        return None
    (bi, gi, ri), (bo, go, ro) = levels
    contrast = (bi - bo, gi - go, ri - ro)
    c2 = contrast[0] ** 2 + contrast[1] ** 2 + contrast[2] ** 2
    if not c2 >= 100.0:  # under 10 grey levels of colour contrast: no measurable edge
        return None
    # coverage: each pixel's colour projected on the outside→inside colour difference
    # ÷ 255: the neighbourhood mask it is multiplied by is 0/255
    k = 1.0 / (255.0 * c2)
    g0, g1, g2 = contrast[0] * k, contrast[1] * k, contrast[2] * k
    project = np.array([[g0, g1, g2, -(g0 * bo + g1 * go + g2 * ro)]], np.float32)
    c = cv2.transform(roi.astype(np.float32), project)
    np.multiply(c, near, out=c)
    m = cv2.moments(cv2.threshold(cv2.threshold(c, 1.0, 1.0, cv2.THRESH_TRUNC)[1], 0.0, 0.0, cv2.THRESH_TOZERO)[1])
    area = m["m00"]
    if area < 3:
        return None
    cx, cy = m["m10"] / area, m["m01"] / area
    # rough ellipse: the coverage's second moments; its quadratic form ∝ covariance⁻¹
    mu20, mu11, mu02 = m["mu20"], m["mu11"], m["mu02"]
    if not mu20 * mu02 - mu11 * mu11 > 1e-12 * (mu20 * mu20 + mu02 * mu02):
        return None
    unclipped = x0 == gx - pad and y0 == gy - pad and x1 == gx + w + pad and y1 == gy + h + pad
    rel, wts = _boundary(c, (cx, cy), np.array([[mu02, -mu11], [-mu11, mu20]]), padded=unclipped)
    ox, oy = cx + x0, cy + y0  # the rough centre in image pixels
    if touches:  # drop points near the image edge: the boundary there is the frame, not the marker
        gp = rel + (ox, oy)
        inner = (gp[:, 0] > 1.5) & (gp[:, 1] > 1.5) & (gp[:, 0] < W - 2.5) & (gp[:, 1] < H - 2.5)
        rel, wts = rel[inner], wts[inner]
    if len(rel) < 6:
        return None
    try:  # fit relative to the rough centre (well conditioned), then move to image pixels
        # RMS boundary radius of the rough ellipse ≈ √(2 (μ20 + μ02) / m00)
        conic, rms = _fit(rel, wts, 3 if touches else 0, origin=(0.0, 0.0), scale=math.sqrt(area / (mu20 + mu02)))
    except EllipseFitError:
        return None
    if touches:  # after the Sampson refinement the fit's own first-order residual is not available
        rms = _sampson_rms(conic, rel, wts)
    if not (rms <= max_fit_rms_px):
        return None
    try:
        ell = Ellipse.from_conic(_shift_conic(conic, ox, oy))
    except EllipseFitError:
        return None
    if not touches:  # the blob must look like its ellipse (not two touching discs, not a bar)
        ratio = area / ell.area
        if not 0.8 < ratio < 1.2:
            return None
    rel += (ox, oy)
    return Marker((ox, oy), ell, area, rel, wts, bbox_img, touches, rms)


_K3 = np.ones((3, 3), np.uint8)


def _moment_conic(m: dict, dx: float, dy: float) -> list[float] | None:
    """Conic of the ellipse with the same area, centroid and second moments as a region
    (cv2.moments), shifted by (dx, dy): (p − μ)ᵀ Σ⁻¹ (p − μ) = 4 for a uniform ellipse."""
    m00 = m["m00"]
    if not m00 > 0:
        return None
    sxx, sxy, syy = m["mu20"] / m00, m["mu11"] / m00, m["mu02"] / m00
    det = sxx * syy - sxy * sxy
    if not det > 1e-6 * max(sxx, syy, 1e-300) ** 2 or not det > 1e-12:
        return None
    a, b, c = syy / det, -2.0 * sxy / det, sxx / det
    mx, my = m["m10"] / m00 + dx, m["m01"] / m00 + dy
    return [a, b, c, -2.0 * a * mx - b * my, -b * mx - 2.0 * c * my,
            a * mx * mx + b * mx * my + c * my * my - 4.0]


def _shift_conic(q, dx: float, dy: float) -> list[float]:
    """Conic of the same curve after translating coordinates by (dx, dy): Q'(x) = Q(x − d)."""
    a, b, c, d, e, f = q
    d2 = d - 2 * a * dx - b * dy
    e2 = e - b * dx - 2 * c * dy
    f2 = a * dx * dx + b * dx * dy + c * dy * dy - d * dx - e * dy + f
    return [a, b, c, d2, e2, f2]


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
    mask = _red_mask(sub, hue_range_deg, min_saturation, min_value)
    sh, sw = mask.shape
    # label only the bounding box of all red pixels: labelling costs per pixel, markers are small
    bx, by, bw, bh = cv2.boundingRect(mask)
    if bw == 0 or bh == 0:
        return []
    ox, oy = ox + bx, oy + by
    crop = mask[by:by + bh, bx:bx + bw]
    if len(cv2.findContours(crop, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)[0]) == 1:
        # one 8-connected blob (the usual tracking window): it is the whole crop, no labelling needed
        labels, order = crop, [255]
        stats: dict[int, tuple[int, int, int, int, int]] | np.ndarray = {255: (0, 0, bw, bh, cv2.countNonZero(crop))}
    else:
        n, labels, stats, _ = cv2.connectedComponentsWithStats(crop, connectivity=8)
        order = (np.argsort(-stats[1:, cv2.CC_STAT_AREA]) + 1).tolist() if n > 1 else []
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
