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
    quality: MarkerQuality | None = None  # None in the tracker's centroid-only mode

    @property
    def trusted(self) -> bool:
        """A sub-pixel marker with no quality flag (see :class:`MarkerQuality`)."""
        return self.quality is not None and self.quality.trusted

    def to_dict(self) -> dict:
        """JSON-ready dict of the marker (px), its ellipse and, if measured, its quality."""
        out = {"centroid_px": [float(v) for v in self.centroid], "area_px": float(self.area),
               "bbox": list(self.bbox), "touches_border": bool(self.touches_border),
               "fit_rms_px": float(self.fit_rms_px), "boundary_points": int(len(self.boundary)),
               "ellipse": self.ellipse.to_dict()}
        if self.quality is not None:
            out["quality"] = self.quality.to_dict()
        return out


def _check_image(image) -> np.ndarray:
    img = np.asarray(image) if image is not None else None
    if img is None or img.ndim != 3 or img.shape[2] != 3 or img.size == 0:
        shape = None if img is None else img.shape
        raise MarkerImageError(f"expected an H×W×3 BGR image, got shape {shape}")
    if img.dtype != np.uint8 and not np.issubdtype(img.dtype, np.number):
        raise MarkerImageError(f"unsupported image dtype {img.dtype}")
    return img


def _as_bgr(image) -> np.ndarray:
    """8-bit BGR for the colour threshold: uint8 as is, uint16 scaled by 1/257 (full range, not
    clipped), floats in [0, 1] scaled by 255 (otherwise taken as 0–255)."""
    img = _check_image(image)
    if img.dtype == np.uint16:
        return cv2.convertScaleAbs(img, alpha=1.0 / 257.0)
    if img.dtype != np.uint8:
        if not np.issubdtype(img.dtype, np.number):
            raise MarkerImageError(f"unsupported image dtype {img.dtype}")
        f = np.nan_to_num(img.astype(np.float64), nan=0.0, posinf=255.0, neginf=0.0)
        if f.max(initial=0.0) <= 1.0:
            f = f * 255.0
        img = np.clip(np.rint(f), 0, 255).astype(np.uint8)
    return img


@lru_cache(maxsize=32)
@dataclass(frozen=True)
class MarkerThresholds:
    """The marker colour's HSV window, the one place its keywords live: hue (degrees, may straddle 0°, e.g.
    (−15, 15) for red), minimum saturation and minimum value (0–1). A camera's own come from its driver file
    (``marker_hue_deg``, ``marker_min_saturation``)."""

    hue_range_deg: tuple[float, float] = (-15.0, 15.0)
    min_saturation: float = 0.45
    min_value: float = 0.15


#: red markers under the lab's lights (the detector's defaults)
RED = MarkerThresholds()


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


def red_mask(image_bgr: np.ndarray, thresholds: MarkerThresholds = RED) -> np.ndarray:
    """Binary mask (uint8 0/255) of pixels whose HSV hue lies in ``thresholds.hue_range_deg`` (degrees,
    may straddle 0°, e.g. (−15, 15) for red), saturation ≥ ``min_saturation`` and value ≥
    ``min_value`` (both 0–1). Hue and saturation do not change under shading."""
    return _red_mask(_as_bgr(image_bgr), thresholds.hue_range_deg, thresholds.min_saturation, thresholds.min_value)


@dataclass(frozen=True)
class MarkerQuality:
    """How far a marker can be trusted (paper §3.1's fit, judged).

    ``arc_coverage``: fraction of the ellipse's perimeter (24 equal-angle sectors in its own
    frame) that has inlier boundary points; ``residual_rel``: inlier RMS distance to the ellipse
    ÷ its minor semi-axis; ``inlier_fraction``: inlier share of the measured boundary (by arc
    length); ``solidity``: hole-filled blob area ÷ its convex hull area; ``edge_contrast``:
    median linear colour contrast across the edge (0–1 of full scale); ``flags``: why it is not
    trusted (empty: trusted). Flags: ``border`` (cut by the image edge), ``partial`` (under 85 %
    of the rim measured: occluded, shadowed or cut), ``rough`` (residual over 4 % of the minor
    semi-axis), ``outliers`` (under 75 % of the boundary fits the ellipse), ``low_contrast``
    (edge contrast under 0.04), ``blurred`` (a quarter of the edge transitions wider than
    max(3 px, 0.2 × minor semi-axis) and the blur could not be modelled: motion or defocus smears
    the shape), ``merged`` (the colour blob is much larger than its ellipse: a neighbour touches it).

    The blur the edge was measured through (:func:`_psf_cov`): ``blur_var_px2``, the
    point-spread function's second moment (px², half the trace of its covariance; 0 for a sharp
    edge), ``blur_shift_px``, the mean outward correction applied for it (the curvature bias
    σ²κ/2), ``motion_px``, the smear length when the motion refit ran (else 0). A blur that was
    modelled this way is no flag; it widens the pose covariance instead (``marker_poses``).
    ``edge_skew``: median skewness of the edge spread (:func:`_edge_skew`); on a blurred edge a
    lean above :data:`RESPONSE_SKEW_LIMIT` raises ``response_mismatch`` (the frame is not encoded
    as the camera's declared response says: declare or learn it). ``response_unknown_px``: for a camera
    whose response nobody declared (read as linear by default), how far the rim would move were the frame
    gamma 2.2-encoded instead (:data:`UNDECLARED_ALTERNATIVE_GAMMA`: the mean change of the edge along its
    normal, px); it enters the pose covariance (``marker_poses``), so pose stays conservative until the
    response is declared or learned (0 for a declared response)."""

    arc_coverage: float
    residual_rel: float
    inlier_fraction: float
    solidity: float
    edge_contrast: float
    flags: tuple[str, ...] = ()
    blur_var_px2: float = 0.0
    blur_shift_px: float = 0.0
    motion_px: float = 0.0
    edge_skew: float = 0.0
    blur_unmodelled_px: float = 0.0
    response_unknown_px: float = 0.0

    @property
    def trusted(self) -> bool:
        """True when no flag is raised."""
        return not self.flags

    def to_dict(self) -> dict:
        """JSON-ready dict of the quality measures, flags and ``trusted``."""
        return {"arc_coverage": round(float(self.arc_coverage), 4), "residual_rel": float(self.residual_rel),
                "inlier_fraction": round(float(self.inlier_fraction), 4), "solidity": round(float(self.solidity), 4),
                "edge_contrast": float(self.edge_contrast), "flags": list(self.flags), "trusted": self.trusted,
                "blur_var_px2": round(float(self.blur_var_px2), 4),
                "blur_shift_px": round(float(self.blur_shift_px), 4), "motion_px": round(float(self.motion_px), 3),
                "edge_skew": round(float(self.edge_skew), 3),
                "blur_unmodelled_px": round(float(self.blur_unmodelled_px), 4),
                "response_unknown_px": round(float(self.response_unknown_px), 4)}


_SCAN_HALF = 4  # px: scans run 8 px across the edge (covers 2–3 px of blur), shorter on small blobs
_SCAN_HALF_MAX = 9  # px: how far scans may grow on a blurred edge
_SECTORS = 24
_K5 = np.ones((5, 5), np.uint8)
_K9 = np.ones((9, 9), np.uint8)
_PAD = _SCAN_HALF_MAX + 4  # crop margin around a blob: scans reach half + 2 px out, the ring 4 px


def _outward_normals(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit outward normals of a closed contour (N×2) from the chord over ±3 points, and each
    point's arc length (mean of its two steps: 1 or √2 on an 8-connected contour)."""
    fwd = np.roll(pts, -3, axis=0) - np.roll(pts, 3, axis=0)
    x, y = pts[:, 0], pts[:, 1]
    area2 = float(x @ np.roll(y, -1) - y @ np.roll(x, -1))  # > 0: counter-clockwise in image axes
    n = np.stack([fwd[:, 1], -fwd[:, 0]], axis=1) * (1.0 if area2 > 0 else -1.0)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    step = np.linalg.norm(np.roll(pts, -1, axis=0) - pts, axis=1)
    return n, 0.5 * (step + np.roll(step, 1))


def _hull_support(pts: np.ndarray, contour: np.ndarray, max_edge: float) -> np.ndarray:
    """True for contour points on the convex hull (within 1.5 px of it) and not on a long
    straight hull edge (longer than ``max_edge`` px: an occluder's chord, a bar's side or a
    cut): the points that can belong to a convex, smooth rim. Highlight notches, shadow bites
    and the necks of merged neighbours are concave and drop out."""
    idx = np.sort(cv2.convexHull(contour, returnPoints=False).ravel())
    if idx.size < 3:
        return np.zeros(len(pts), bool)
    seg = np.searchsorted(idx, np.arange(len(pts)), side="right") - 1  # hull edge k: idx[k] → idx[k + 1]
    a = pts[idx[seg % idx.size]]
    b = pts[idx[(seg + 1) % idx.size]]
    ab = b - a
    length = np.linalg.norm(ab, axis=1)
    d = np.abs(ab[:, 0] * (pts[:, 1] - a[:, 1]) - ab[:, 1] * (pts[:, 0] - a[:, 0])) / np.maximum(length, 1e-9)
    return (d <= 1.5) & (length <= max_edge)


def _straight(pts: np.ndarray, kept: np.ndarray, m: int, tol: float = 0.2) -> np.ndarray:
    """True for boundary points (closed contour order, N×2) whose window of ``m`` neighbours
    on either side is a straight line to within ``tol`` px RMS: an occluder's edge, a cut, a
    bar's side. A rim arc of the same length bends by far more (the window is chosen so)."""
    n = len(pts)
    if n < 2 * m + 1 or m < 3:
        return np.zeros(n, bool)
    k = kept.astype(np.float64)
    x, y = pts[:, 0] * k, pts[:, 1] * k
    cols = np.stack([k, x, y, x * pts[:, 0], y * pts[:, 1], x * pts[:, 1]], axis=1)
    ext = np.concatenate([cols[-m:], cols, cols[:m + 1]])
    c = np.cumsum(ext, axis=0)
    win = c[2 * m + 1:2 * m + 1 + n] - c[:n]  # sums over [i − m, i + m]
    cnt = np.maximum(win[:, 0], 1.0)
    mx, my = win[:, 1] / cnt, win[:, 2] / cnt
    sxx = win[:, 3] / cnt - mx * mx
    syy = win[:, 4] / cnt - my * my
    sxy = win[:, 5] / cnt - mx * my
    half_tr = 0.5 * (sxx + syy)
    small = half_tr - np.sqrt(np.maximum(0.25 * (sxx - syy) ** 2 + sxy * sxy, 0.0))
    return kept & (win[:, 0] >= 1.5 * m) & (small < tol * tol)


def _scans(signal: np.ndarray, seeds: np.ndarray, normals: np.ndarray, half: int, shift=None):
    """Pixel scans across the edge at each seed (N×2 int, crop pixels): along the row where the
    outward normal is closer to horizontal, along the column otherwise, in the outward direction,
    over offsets k = −half+1 … half (+ ``shift``) from the seed. Returns (row?, sign, k₀ per
    scan, N×S samples)."""
    row = np.abs(normals[:, 0]) >= np.abs(normals[:, 1])
    sgn = np.where(row, np.sign(normals[:, 0]), np.sign(normals[:, 1])).astype(np.int64)
    sgn[sgn == 0] = 1
    k0 = np.full(len(seeds), 1 - half, np.int64) if shift is None else 1 - half + shift
    k = k0[:, None] + np.arange(2 * half)
    H, W = signal.shape
    xs = np.clip(seeds[:, 0:1] + np.where(row, sgn, 0)[:, None] * k, 0, W - 1)
    ys = np.clip(seeds[:, 1:2] + np.where(row, 0, sgn)[:, None] * k, 0, H - 1)
    return row, sgn, k0, signal[ys, xs]


def _transition_width(prof: np.ndarray) -> np.ndarray:
    """Pixels of each scan between 10 % and 90 % of the way from its outside to its inside level."""
    p = 2 if prof.shape[1] >= 6 else 1
    lo, hi = prof[:, -p:].mean(axis=1), prof[:, :p].mean(axis=1)
    c = (prof - lo[:, None]) / np.maximum(hi - lo, 1e-6)[:, None]
    return np.count_nonzero((c > 0.1) & (c < 0.9), axis=1)


# second moment (px²) of a perfectly sharp edge's sampled profile: the pixel's own footprint plus the
# sampling of the difference (0.19 measured on exact-coverage discs, 0.16–0.20 over obliquities 0–50°)
_SHARP_EDGE_VAR_PX2 = 0.19
# the response check (:func:`_edge_skew`) needs ramps this wide (px²; a sharp edge has one or two
# intermediate pixels, too few to show a lean) ...
_SKEW_MIN_BLUR_PX2 = 0.5
# ... and flags ``response_mismatch`` above this median skewness (green channel, 8 px scans centred on the edge).
# Measured on both oracles (10 images per condition, 2026-12-02): right response −0.12…+0.12 (defocus r 2–3 px
# ≤ 0.04, motion 8 px and webcam-like JPEG/Bayer the widest); gamma 2.2 + defocus read as linear +0.15…+0.22;
# a gamma frame that is also JPEG-compressed and smeared (mild combination) +0.00…+0.12, mostly *not* caught.
# Only a frame read as linear (the default a lab may have kept) is tested: the sim's realistic-camera frames
# (sRGB declared, JPEG 80, Bayer) lean +0.11 with their right response, so a declared curve is believed
RESPONSE_SKEW_LIMIT = 0.13
# a camera whose response nobody declared is read as linear; the rim is also measured as if the frame were encoded
# with this gamma (the common encoding: sRGB is within a few % of it), and the difference is carried as an error
UNDECLARED_ALTERNATIVE_GAMMA = 2.2
# blur below this (px², a pillbox radius of ~0.9 px) is left uncorrected: its curvature bias is
# under 0.01 px on any marker that passes the size gates
_MIN_CORRECTED_BLUR_PX2 = 0.2
# share of the colour signal's blur (trace) the green channel must show for the blur to count as optical.
# Measured (2026-12-02, 10 blurred images per condition on each oracle): defocus r 2–3 px, gamma + defocus and
# motion smears 1.00–1.07 on both; webcam-like and mild combinations (Bayer, JPEG) 0.82–0.95; the sim's
# realistic-camera side marker 0.49. At 0.7 or 0.9 the seed-1008 realistic run changed its target marker
# (tests/test_sim_effects.py::test_realistic_run_falls_back_…: 90° pose error, then "still ambiguous")
_OPTICAL_BLUR_SHARE = 0.97


def _psf_cov(prof: np.ndarray, along: np.ndarray, nrm: np.ndarray) -> np.ndarray:
    """2×2 covariance (px², image axes) of the blur a marker's edge profiles show: per scan, the
    variance of the profile's derivative (the line-spread function) along the scan, scaled to the
    edge normal nᵢ by |s·n|² and less the sharp edge's own :data:`_SHARP_EDGE_VAR_PX2`, is nᵢᵀ Σ nᵢ;
    Σ by least squares over the scans (once more without those beyond 3 robust σ), made positive
    semi-definite. A pillbox of radius r gives (r²/4) I, a box smear of length L along u (L²/12) uuᵀ."""
    p = 2 if prof.shape[1] >= 6 else 1
    inside, outside = prof[:, :p].mean(axis=1), prof[:, -p:].mean(axis=1)
    c = (prof - outside[:, None]) / np.maximum(inside - outside, 1e-6)[:, None]
    d = np.clip(c[:, :-1] - c[:, 1:], 0.0, None)
    sd = np.maximum(d.sum(axis=1), 1e-9)
    x = np.arange(d.shape[1]) + 0.5
    mu = (d * x).sum(axis=1) / sd
    y = (d * (x[None, :] - mu[:, None]) ** 2).sum(axis=1) / sd * along * along - _SHARP_EDGE_VAR_PX2
    A = np.stack([nrm[:, 0] ** 2, 2.0 * nrm[:, 0] * nrm[:, 1], nrm[:, 1] ** 2], axis=1)
    keep = np.ones(len(y), bool)
    sol = np.zeros(3)
    for _ in range(2):
        if np.count_nonzero(keep) < 6:
            return np.zeros((2, 2))
        sol = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
        r = y - A @ sol
        keep = np.abs(r) <= 3.0 * 1.48 * float(np.median(np.abs(r[keep]))) + 1e-6
    lam, vec = np.linalg.eigh(np.array([[sol[0], sol[1]], [sol[1], sol[2]]]))
    return (vec * np.clip(lam, 0.0, None)) @ vec.T


def _edge_normals(conic, pts: np.ndarray) -> np.ndarray:
    """Outward unit normals (N×2) of the conic (Q < 0 inside) at ``pts``."""
    a, b, c, d, e, _ = conic
    x, y = pts[:, 0], pts[:, 1]
    g = np.stack([2 * a * x + b * y + d, b * x + 2 * c * y + e], axis=1)
    return g / np.maximum(np.hypot(g[:, 0], g[:, 1]), 1e-300)[:, None]


def _edge_skew(prof: np.ndarray) -> float:
    """Median skewness of the edge profiles' derivatives (the line-spread functions along each scan).
    A symmetric blur seen through the right response gives a symmetric spread (skewness ≈ 0); a
    gamma-encoded frame read as linear stretches the bright side of every ramp and compresses the
    dark one, so the spread leans the same way on every scan. NaN for fewer than 8 scans."""
    if prof.shape[0] < 8:
        return float("nan")
    p = 2 if prof.shape[1] >= 6 else 1
    inside, outside = prof[:, :p].mean(axis=1), prof[:, -p:].mean(axis=1)
    c = (prof - outside[:, None]) / np.maximum(inside - outside, 1e-6)[:, None]
    d = np.clip(c[:, :-1] - c[:, 1:], 0.0, None)
    sd = np.maximum(d.sum(axis=1), 1e-9)
    x = np.arange(d.shape[1]) + 0.5
    mu = (d * x).sum(axis=1) / sd
    r = x[None, :] - mu[:, None]
    v = np.maximum((d * r * r).sum(axis=1) / sd, 1e-9)
    return float(np.median((d * r ** 3).sum(axis=1) / sd / v ** 1.5))


def _curvature_shift(conic, pts: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Outward displacement (N×2 px) that undoes the inward bias of a blurred curved edge: an edge
    of curvature κ read by the area rule through a blur of covariance Σ sits ½ κ tᵀΣt inside the
    true one (t the edge's tangent; first order in σκ: the blur's spread *along* the edge is what
    bends the reading, its spread across the edge only widens the ramp). κ and the outward normal
    from the implicit conic Q (Q < 0 inside) at each point."""
    a, b, c, d, e, _ = conic
    x, y = pts[:, 0], pts[:, 1]
    qx, qy = 2 * a * x + b * y + d, b * x + 2 * c * y + e
    g2 = np.maximum(qx * qx + qy * qy, 1e-300)
    kappa = np.abs(2 * a * qy * qy - 2 * b * qx * qy + 2 * c * qx * qx) / g2 ** 1.5
    tx, ty = -qy / np.sqrt(g2), qx / np.sqrt(g2)
    var_t = cov[0, 0] * tx * tx + 2.0 * cov[0, 1] * tx * ty + cov[1, 1] * ty * ty
    step = 0.5 * var_t * kappa / np.sqrt(g2)
    return np.stack([qx * step, qy * step], axis=1)


def _edge_offsets(prof: np.ndarray, k0: np.ndarray, contrast: float):
    """Edge position along each scan by the area rule with locally normalised plateaus.

    Each scan is normalised by its *own* inside and outside levels (means of its first and last
    two pixels), c = (s − out)/(in − out), which removes shading, shadows and smooth background
    changes; the edge then sits at (k₀ − ½) + Σc along the scan (exact for a straight edge at
    any sub-pixel phase and angle up to 45°, and for any symmetric blur whose transition fits
    the scan). A scan is kept when its local contrast is at least 20 % of the blob's and its
    normalised samples stay within [−0.45, 1.45] (no second edge inside). Returns (offset from
    the seed in px along the scan, kept, local contrast)."""
    p = 2 if prof.shape[1] >= 6 else 1
    inside = prof[:, :p].mean(axis=1)
    outside = prof[:, -p:].mean(axis=1)
    local = inside - outside
    safe = np.where(np.abs(local) > 1e-6, local, 1e-6)
    c = (prof - outside[:, None]) / safe[:, None]
    offset = (k0 - 0.5) + c.sum(axis=1)
    sm = 0.5 * c[:, 1:-1] + 0.25 * (c[:, :-2] + c[:, 2:])
    kept = (local > 0.2 * contrast) & (sm.min(axis=1) > -0.45) & (sm.max(axis=1) < 1.45)
    return offset, kept, local


def _sampson(conic, pts: np.ndarray) -> np.ndarray:
    """Signed first-order geometric distance Q/|∇Q| of each point to the conic (px)."""
    a, b, c, d, e, f = conic
    x, y = pts[:, 0], pts[:, 1]
    gx = 2.0 * a * x + b * y + d
    gy = b * x + 2.0 * c * y + e
    q = a * x * x + b * x * y + c * y * y + d * x + e * y + f
    return q / np.sqrt(np.maximum(gx * gx + gy * gy, 1e-300))


def _robust_fit(pts: np.ndarray, w: np.ndarray, start: np.ndarray, scale: float):
    """Weighted ellipse fit (paper eq. 2) with outlier rejection, in two stages so the inlier
    set cannot creep along an occluder's edge: (1) fit the ``start`` points (those that can be
    rim), trimming any farther than max(3σ, 0.35 px) (σ = 1.48 × median absolute distance) and
    refitting until stable; (2) admit every point within max(2.5σ₁, 0.25 px) of that fit (σ₁ of
    stage 1's inliers). Returns (conic of the stage-1 fit, final inlier mask)."""
    inl = start.copy()
    conic = None
    sigma = 0.0
    for _ in range(6):
        if np.count_nonzero(inl) < 6:
            break
        conic, _ = _fit(pts[inl], w[inl], 0, origin=(0.0, 0.0), scale=scale)
        if not _conic_is_ellipse(conic):
            raise EllipseFitError("hyperbolic fit")
        d = np.abs(_sampson(conic, pts))
        sigma = 1.4826 * float(np.median(d[inl]))
        new = inl & (d <= max(3.0 * sigma, 0.35))
        if np.array_equal(new, inl):
            break
        inl = new
    if conic is None or np.count_nonzero(inl) < 6:
        raise EllipseFitError("too few consistent boundary points")
    d = np.abs(_sampson(conic, pts))
    return conic, inl | (d <= max(2.5 * sigma, 0.25))


def _conic_is_ellipse(q) -> bool:
    a, b, c = q[0], q[1], q[2]
    return bool(np.all(np.isfinite(q)) and 4.0 * a * c - b * b > 0)


def _arc_coverage(ell: Ellipse, pts: np.ndarray) -> float:
    """Fraction of :data:`_SECTORS` equal sectors of the ellipse's eccentric angle holding points."""
    (a, b), th = ell.axes, ell.angle
    d = pts - ell.center
    ct, st = math.cos(th), math.sin(th)
    u = (d[:, 0] * ct + d[:, 1] * st) / a
    v = (-d[:, 0] * st + d[:, 1] * ct) / b
    k = ((np.arctan2(v, u) + np.pi) * (_SECTORS / (2 * np.pi))).astype(int) % _SECTORS
    return np.unique(k).size / _SECTORS


class _Reject(Exception):
    """A blob that is no marker: the reason goes into the search report."""


def _analyse_contour(img8: np.ndarray, linear_crop, contour: np.ndarray, touches: bool,
                     min_axis_ratio: float, max_residual_rel: float, check_response: bool = False,
                     response_unknown: bool = False) -> Marker:
    """Sub-pixel boundary, robust fit and quality of one hole-filled colour blob (its external
    ``contour`` in image pixels), paper §3.1. Works on a crop around the blob. ``check_response``:
    test the edges for a response other than the (linear) one they were read with; ``response_unknown``:
    nobody declared that (linear) response, so measure how far the rim moves under the alternative one."""
    H, W = img8.shape[:2]
    bx, by, bw, bh = cv2.boundingRect(contour)
    x0, y0 = max(bx - _PAD, 0), max(by - _PAD, 0)
    x1, y1 = min(bx + bw + _PAD, W), min(by + bh + _PAD, H)
    pts = contour[:, 0, :].astype(np.float64) - (x0, y0)
    filled = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.drawContours(filled, [contour], -1, 255, -1, offset=(-x0, -y0))
    mfill = cv2.moments(filled, binaryImage=True)
    area_fill = mfill["m00"]
    rough = _moment_conic(mfill, 0.0, 0.0)
    if rough is None:
        raise _Reject("degenerate blob")
    try:
        rough_ell = Ellipse.from_conic(rough)
    except EllipseFitError:
        raise _Reject("degenerate blob") from None
    ra, rb = rough_ell.axes
    hull_area = cv2.contourArea(cv2.convexHull(contour))
    solidity = float(cv2.contourArea(contour) / hull_area) if hull_area > 0 else 0.0
    lin = linear_crop(y0, y1, x0, x1)
    # inside / outside colours: medians over the core and over a ring 3–4 px outside the blob
    core = cv2.erode(filled, _K5)
    if cv2.countNonZero(core) < 4:
        core = filled
    ring = cv2.subtract(cv2.dilate(filled, _K9), cv2.dilate(filled, _K5))
    if not cv2.countNonZero(ring):
        raise _Reject("no background around the blob")
    ci = np.median(lin[core > 0], axis=0)
    co = np.median(lin[ring > 0], axis=0)
    # the signal: colour along the inside−outside difference, made blind to the outside colour's
    # own direction, so shading, shadows, texture and highlights of the background (which scale
    # or add to grey) leave it unchanged
    diff = ci - co
    dn = float(np.linalg.norm(diff))
    if not dn > 1e-6:
        raise _Reject("no colour contrast at the edge")
    # two candidate signals: the full colour difference (sharpest: carries luminance, which
    # JPEG and Bayer keep at full resolution), and its part orthogonal to the background's own
    # colour (blind to background texture, shadows and highlights, which scale or add to
    # grey); take the one with the better contrast against the ring's spread
    on = float(np.linalg.norm(co))
    ring_px = lin[ring > 0]
    best: tuple[float, np.ndarray] | None = None
    for cand in (diff, diff - (diff @ co) / (on * on) * co if on > 1e-6 else diff):
        n_ = float(np.linalg.norm(cand))
        if not n_ > 0.05 * dn:
            continue
        u = cand / n_
        cnr = float(diff @ u) / (float(np.std(ring_px @ u)) + 0.004)
        if best is None or cnr > best[0] * 1.15:
            best = (cnr, u)
    if best is None:
        raise _Reject("no colour direction separates the marker from its surround")
    d = best[1].astype(np.float32)
    contrast = float(diff @ d)
    if not contrast > 0.01:
        raise _Reject("no colour contrast at the edge")
    signal = cv2.transform(lin, d.reshape(1, 3))
    normals, _ = _outward_normals(pts)
    max_edge = 3.2 * math.sqrt(ra * ra / max(rb, 0.5))
    support = _hull_support(pts, contour - (x0, y0), max_edge)
    if touches:  # the image edge is no marker edge
        gx, gy = pts[:, 0] + x0, pts[:, 1] + y0
        support &= (gx > 2.5) & (gy > 2.5) & (gx < W - 3.5) & (gy < H - 3.5)
    half = int(min(_SCAN_HALF, max(2, math.floor(1.0 + rb))))
    seeds = contour[:, 0, :].astype(np.int64) - (x0, y0)
    row, sgn, k0, prof = _scans(signal, seeds, normals, half)
    off, kept, local = _edge_offsets(prof, k0, contrast)
    if np.count_nonzero(kept) >= 8:
        # a blurred edge (defocus, motion) whose transition reaches the plateaus biases the area
        # rule: lengthen the scans to cover it (as far as the blob's size allows)
        width = float(np.median(_transition_width(prof[kept])))
        # ... or a smear along one direction, which widens only the ramps whose normal is along it (the
        # median misses it, and the short scans' plateaus then sit on the ramp: the rim reads 0.2–0.5 px
        # out along the smear, i.e. a frontal marker tilts by degrees); a box of length L has variance L²/12
        n_first = normals[kept]
        a_first = np.maximum(np.abs(n_first[:, 0]), np.abs(n_first[:, 1]))
        lam = float(np.linalg.eigvalsh(_psf_cov(prof[kept], a_first, n_first))[1])
        if 12.0 * lam > (2 * half - 5) ** 2:
            # only an optical smear, which the green channel shows too (JPEG chroma widens the colour signal alone)
            gp = _scans(-lin[..., 1], seeds, normals, half)[3]
            lam = min(lam, float(np.linalg.eigvalsh(_psf_cov(gp[kept], a_first, n_first))[1]))
            width = max(width, math.sqrt(12.0 * lam))
        longer = int(min(_SCAN_HALF_MAX, max(2, math.floor(1.0 + rb)), math.ceil(0.5 * width) + 3))
        if width > 2 * half - 5 and longer > half:
            half = longer
            row, sgn, k0, prof = _scans(signal, seeds, normals, half)
            off, kept, local = _edge_offsets(prof, k0, contrast)
    # second pass centred on the edge found: a symmetric scan removes the truncation bias
    shift = np.clip(np.rint(off - 0.5).astype(np.int64), -2, 2)
    if np.any(shift):
        row, sgn, k0, prof = _scans(signal, seeds, normals, half, shift)
        off, kept2, local = _edge_offsets(prof, k0, contrast)
        kept &= kept2
    kept &= np.abs(off - 0.5) < 2.0
    scan_at = (seeds, normals, half, shift if np.any(shift) else None)  # the final scans (the response's error)
    step = np.where(row[:, None], np.stack([sgn, 0 * sgn], 1), np.stack([0 * sgn, sgn], 1))
    edge = seeds + off[:, None] * step
    # one point per scan line: 8-connected contours can put two seeds on one row or column
    key = np.stack([row, seeds[:, 1] * row + seeds[:, 0] * ~row, sgn, np.rint(4 * off * sgn
                    + 4 * (seeds[:, 0] * row + seeds[:, 1] * ~row))], 1)
    _, first = np.unique(key, axis=0, return_index=True)
    once = np.zeros(len(seeds), bool)
    once[first] = True
    kept &= once
    along = np.maximum(np.abs(normals[:, 0]), np.abs(normals[:, 1]))
    kept &= along > 0.5  # a degenerate normal (a one-pixel spur) has no scan direction
    arc = 1.0 / np.maximum(along, 0.5)  # arc length per scan (eq. 2 weights)
    if touches:  # scans at the image edge measure the frame, not the marker: not part of the rim
        gx, gy = edge[:, 0] + x0, edge[:, 1] + y0
        in_frame = (gx > 1.5) & (gy > 1.5) & (gx < W - 2.5) & (gy < H - 2.5)
        kept &= in_frame
        once &= in_frame
    n_kept = int(np.count_nonzero(kept))
    if n_kept < 8:
        raise _Reject("too few clean edge profiles")
    m_win = int(math.ceil(0.5 * math.sqrt(8.0 * ra * ra / max(rb, 0.5))))
    support &= ~_straight(edge, kept, m_win)
    p = edge[kept]
    w = arc[kept]
    start = support[kept]
    if np.count_nonzero(start) < 8:
        start = np.ones(len(p), bool)
    cx, cy = mfill["m10"] / area_fill, mfill["m01"] / area_fill
    rel = p - (cx, cy)
    scale = math.sqrt(2.0) / max(math.sqrt(ra * rb), 1.0)
    try:
        _, inl = _robust_fit(rel, w, start, scale)
        conic, _ = _fit(rel[inl], w[inl], None, origin=(0.0, 0.0), scale=scale)
        if not _conic_is_ellipse(conic):
            raise EllipseFitError("hyperbolic fit")
        ell = Ellipse.from_conic(_shift_conic(conic, cx + x0, cy + y0))
    except EllipseFitError:
        raise _Reject("boundary is not an ellipse") from None
    a, b = ell.axes
    if not (b / a >= min_axis_ratio):
        raise _Reject(f"too elongated (axis ratio {b / a:.2f} < {min_axis_ratio:.2f})")
    bpts = rel[inl] + (cx + x0, cy + y0)
    bw_ = w[inl]
    resid = _sampson(ell.conic, bpts)
    rms = math.sqrt(float(bw_ @ (resid * resid)) / float(bw_.sum()))
    residual_rel = rms / b
    if residual_rel > max_residual_rel:
        raise _Reject(f"not elliptical (boundary residual {residual_rel:.2f} of the minor axis)")
    coverage = _arc_coverage(ell, bpts)
    if coverage < 0.5:
        raise _Reject(f"too little elliptical rim ({100 * coverage:.0f} %)")
    inlier_fraction = float(bw_.sum() / arc[once].sum())
    widths = _transition_width(prof[kept])
    blur_px = float(np.percentile(widths, 75))
    edge_contrast = float(np.median(local[kept][inl]))
    flags = []
    if touches:
        flags.append("border")
    if coverage < 0.85:
        flags.append("partial")
    if residual_rel > 0.04:
        flags.append("rough")
    if inlier_fraction < 0.75:
        flags.append("outliers")
    if edge_contrast < 0.04:
        flags.append("low_contrast")
    redo, motion_px = None, 0.0
    if blur_px > 3.0:  # a wide ramp: if it is a motion smear, measure the edge where the smear leaves it
        redo = _motion_refit(signal, contrast, prof, kept, row, sgn, seeds, normals, arc, off, ell, (x0, y0), (cx, cy),
                             scale, support & kept)
        if redo is not None:
            ell, bpts, bw_, motion_px = redo
            resid = _sampson(ell.conic, bpts)
            rms = math.sqrt(float(bw_ @ (resid * resid)) / float(bw_.sum()))
    n_fit = _edge_normals(ell.conic, edge[kept] + (x0, y0))
    psf = _psf_cov(prof[kept], along[kept], n_fit)
    blur_var = 0.5 * float(np.trace(psf))
    optical = False
    colour_only = False  # a blur the colour signal shows and the green channel mostly does not
    if blur_var > _MIN_CORRECTED_BLUR_PX2:
        # an optical blur (defocus, motion) widens every channel alike; JPEG's 4:2:0 chroma and demosaicing
        # widen the colour signal only, and not as a convolution of linear radiance, so the curvature model
        # does not hold for them: corrected only when the green channel (the marker dark, the surround
        # bright; luminance-like, kept at full resolution) shows the whole blur too (_OPTICAL_BLUR_SHARE)
        _, _, _, gprof = _scans(-lin[..., 1], seeds, normals, half, shift if np.any(shift) else None)
        psf_g = _psf_cov(gprof[kept], along[kept], n_fit)
        optical = float(np.trace(psf_g)) >= _OPTICAL_BLUR_SHARE * float(np.trace(psf))
        if optical and np.trace(psf_g) < np.trace(psf):
            psf = psf_g
        blur_var = 0.5 * float(np.trace(psf))
        colour_only = not optical
    unmodelled_px = 0.0
    if colour_only:
        # a colour-only blur (JPEG chroma, demosaicing) is not corrected: the curvature bias it would imply,
        # ½κ tᵀΣt of the colour signal's Σ, is left as an error of that size (it enters the pose covariance)
        unmodelled_px = float(np.mean(np.hypot(*_curvature_shift(ell.conic, bpts, psf).T)))
    shift_px = 0.0
    if redo is None and blur_var > _MIN_CORRECTED_BLUR_PX2 and optical:
        # the area rule reads a blurred curved edge ½κ tᵀΣt inside the true rim (0.2 % of the range on a
        # 25 px marker at a 3 px defocus radius; an anisotropic blur, a short smear, also stretches the
        # ellipse, i.e. tilts a frontal marker by degrees): move each point back, refit
        moved = _curvature_shift(ell.conic, bpts, psf)
        try:
            conic2, _ = _fit(bpts + moved - (cx + x0, cy + y0), bw_, None, origin=(0.0, 0.0), scale=scale)
            if _conic_is_ellipse(conic2):
                ell = Ellipse.from_conic(_shift_conic(conic2, cx + x0, cy + y0))
                bpts = bpts + moved
                shift_px = float(np.mean(np.hypot(moved[:, 0], moved[:, 1])))
                resid = _sampson(ell.conic, bpts)
                rms = math.sqrt(float(bw_ @ (resid * resid)) / float(bw_.sum()))
        except EllipseFitError:
            pass
    # a blur is modelled (motion refit, or the curvature correction while first order holds: σ ≤ ¼ of the
    # minor semi-axis); one that is not, wide against the marker, smears its shape: flagged
    modelled = redo is not None or (shift_px > 0.0 and math.sqrt(blur_var) <= 0.25 * ell.axes[1])
    if colour_only and math.sqrt(0.5 * float(np.trace(psf_g))) <= 0.25 * b:
        # ... a colour-only blur widens the colour ramps, not the shape: what an optical smear there is, the
        # green channel shows (luminance-like, full resolution in JPEG); within the first-order limit its
        # bias is small and the colour signal's is in the covariance (blur_unmodelled_px): not flagged
        blur_px = 0.0
    if blur_px > max(3.0, 0.2 * b) and not modelled:
        flags.append("blurred")
    if area_fill > 1.3 * ell.area + 2.0 * math.pi * (a + b) * 0.5:
        flags.append("merged")
    skew = 0.0
    if check_response and blur_var >= _SKEW_MIN_BLUR_PX2:
        # the lean is read on the green channel (the marker dark, the surround bright): JPEG's chroma, which
        # the colour signal carries, was filtered in encoded values and leans by itself; luminance was not
        # over the short scans (8 px), centred on each edge found: longer ones add the noise of their tails
        # ... oriented so that the side brighter in green is the one a gamma stretches (a red marker is usually
        # darker in green than its surround; on a dark part it is brighter, and the lean then changes sign)
        half_s = min(half, _SCAN_HALF)
        centre_s = np.clip(np.rint(off - 0.5).astype(np.int64), -_SCAN_HALF_MAX, _SCAN_HALF_MAX)
        polarity = -1.0 if ci[1] <= co[1] else 1.0
        _, _, _, gprof = _scans(polarity * lin[..., 1], seeds, normals, half_s, centre_s)
        skew = -polarity * _edge_skew(gprof[kept])
    if skew > RESPONSE_SKEW_LIMIT:
        # the edges lean as a gamma-encoded frame linearised as linear does: the declared response is wrong,
        # and every edge (so the range) is biased by it
        flags.append("response_mismatch")
    unknown_px = _response_unknown_px(lin, d, ci, co, scan_at, k0, off, kept) if response_unknown else 0.0
    quality = MarkerQuality(coverage, residual_rel, inlier_fraction, solidity, edge_contrast, tuple(flags),
                            blur_var, shift_px, motion_px, skew, unmodelled_px, unknown_px)
    return Marker(tuple(ell.center), ell, float(ell.area), bpts, bw_, (int(bx), int(by), int(bx + bw), int(by + bh)),
                  touches, rms, quality)


def _response_unknown_px(lin, d, ci, co, scan_at, k0, off, kept) -> float:
    """How far (px, along the edge normal, mean over the rim's scans) the area-rule edge moves when the crop
    ``lin``, read as linear, is read as :data:`UNDECLARED_ALTERNATIVE_GAMMA`-encoded instead: the final scans
    (``scan_at``: seeds, normals, half-length, shift) of the same colour signal ``d``, each profile normalised
    by its own plateaus. This is the error the rim carries if the undeclared camera encodes so."""
    g = UNDECLARED_ALTERNATIVE_GAMMA
    contrast = float((np.power(np.clip(ci, 0.0, None), g) - np.power(np.clip(co, 0.0, None), g)) @ d)
    if not contrast > 1e-4:
        return 0.0
    alt = cv2.transform(np.power(np.clip(lin, 0.0, None), np.float32(g)).astype(np.float32), d.reshape(1, 3))
    seeds, normals, half, shift = scan_at
    _, _, k0_alt, prof = _scans(alt, seeds, normals, half, shift)
    off_alt, kept_alt = _edge_offsets(prof, k0_alt, contrast)[:2]
    both = kept & kept_alt
    if np.count_nonzero(both) < 8:
        return 0.0
    along = np.maximum(np.abs(normals[both, 0]), np.abs(normals[both, 1]))
    return float(abs(np.mean((off_alt[both] - off[both]) * along)))


def _half_level_offsets(prof: np.ndarray, k0: np.ndarray, near: np.ndarray, reach: np.ndarray, contrast: float):
    """Where each scan (inside → outside) crosses half-way between its plateaus, for a ramp of
    half-width ``reach`` (px along the scan) around ``near`` (px from the seed): plateaus = means of
    the samples 0.5–2.5 px beyond the ramp on either side (no farther, so a highlight or a neighbour
    inside does not count), the crossing = the least-squares line through the ramp's samples
    between 15 % and 85 % (it averages the noise a two-sample crossing would follow), at 0.5. For a
    ramp this is the 50 % level, which a box blur leaves on the true edge wherever the chord along
    the blur is long enough. Returns (offset px from the seed, kept: contrast ≥ 20 % of the blob's,
    no second edge, ≥ 3 ramp samples)."""
    k = (k0[:, None] + np.arange(prof.shape[1])).astype(np.float64)
    rel = k - near[:, None]
    r = reach[:, None]
    win_in = (rel <= -r - 0.5) & (rel >= -r - 2.5)
    win_out = (rel >= r + 0.5) & (rel <= r + 2.5)
    n_in, n_out = win_in.sum(axis=1), win_out.sum(axis=1)
    inside = (prof * win_in).sum(axis=1) / np.maximum(n_in, 1)
    outside = (prof * win_out).sum(axis=1) / np.maximum(n_out, 1)
    local = inside - outside
    c = (prof - outside[:, None]) / np.where(np.abs(local) > 1e-6, local, 1e-6)[:, None]
    ramp = np.abs(rel) < r + 0.5
    w = (ramp & (c > 0.15) & (c < 0.85)).astype(np.float64)
    sw = w.sum(axis=1)
    safe = np.maximum(sw, 1.0)
    mk = (w * k).sum(axis=1) / safe
    mc = (w * c).sum(axis=1) / safe
    skc = (w * (k - mk[:, None]) * (c - mc[:, None])).sum(axis=1)
    skk = (w * (k - mk[:, None]) ** 2).sum(axis=1)
    slope = skc / np.maximum(skk, 1e-9)
    pos = mk + (0.5 - mc) / np.where(slope < -1e-3, slope, -1e-3)
    span = (rel >= -r - 2.5) & (rel <= r + 2.5)
    cs = np.where(span, c, 0.5)
    sm = 0.5 * cs[:, 1:-1] + 0.25 * (cs[:, :-2] + cs[:, 2:])
    kept = ((local > 0.2 * contrast) & (n_in >= 1) & (n_out >= 1) & (sm.min(axis=1) > -0.45)
            & (sm.max(axis=1) < 1.45) & (sw >= 2) & (slope < -0.05))
    return pos, kept


def _motion_refit(signal, contrast, prof, kept, row, sgn, seeds, normals, arc, off, ell, origin, centre, scale, start):
    """Boundary of a motion-smeared marker (paper §3.1's fit, made to survive a blur): returns
    (ellipse, boundary points, weights, smear length L px) in image px, or None when the blur looks isotropic
    (defocus) or too little rim is left.

    A box blur of length L along u turns each edge into a ramp of width L·|u·n| across it (n the
    edge normal); its 50 % level stays on the true edge wherever the disc's chord along u is at
    least L/2 long, and falls inside it only near the two points whose normal is ⊥ u. So: u and L
    from the ramp widths (width² · (s·n)² ≈ nᵀ(L² uuᵀ + w₀² I)n, s the scan direction; fitted by
    least squares), each point at its scan's half-level, points whose chord along u (on the
    current ellipse) is under L/2 + 1 px dropped, and the robust fit redone."""
    # samples strictly between 10 % and 90 % of a ramp of width w: ≈ 0.8 w − 1
    widths = (_transition_width(prof).astype(np.float64) + 1.0) / 0.8
    s_dir = np.where(row[:, None], np.stack([sgn, 0 * sgn], 1), np.stack([0 * sgn, sgn], 1)).astype(np.float64)
    cos_sn = np.abs(np.sum(s_dir * normals, axis=1))
    m = kept & (cos_sn > 0.5)
    if np.count_nonzero(m) < 12:
        return None
    nx, ny = normals[m, 0], normals[m, 1]
    y = (widths[m] * cos_sn[m]) ** 2
    A = np.stack([nx * nx, 2 * nx * ny, ny * ny], axis=1)
    sol, *_ = np.linalg.lstsq(A, y, rcond=None)
    lam, vec = np.linalg.eigh(np.array([[sol[0], sol[1]], [sol[1], sol[2]]]))
    # motion: an anisotropic ramp ≥ 3 px that is not smaller than the isotropic width √λ0 of the ramps.
    # Where the isotropic part dominates (demosaicing, JPEG 4:2:0 chroma, defocus: ~6.5 px against 3.5 px
    # anisotropic on a small oblique marker in realistic-camera frames), the area rule stays (it is unbiased
    # for a symmetric blur) and the half-level refit only added scatter (normal σ 0.53° → 0.70°)
    if not (lam[1] > 0 and lam[1] - max(lam[0], 0.0) > max(9.0, lam[0])):
        return None
    L = math.sqrt(lam[1] - max(lam[0], 0.0))
    u = vec[:, 1]
    # rescan at full length, centred on the first estimate, so both plateaus lie beyond the ramp
    shift = np.clip(np.rint(off - 0.5).astype(np.int64), -6, 6)
    _, _, k0, prof = _scans(signal, seeds, normals, _SCAN_HALF_MAX, shift)
    reach = np.clip(0.5 * L * np.abs(normals @ u) / np.maximum(cos_sn, 0.5) + 1.0, 1.5, 7.0)
    pos, ok2 = _half_level_offsets(prof, k0, off, reach, contrast)
    ok = kept & ok2 & (np.abs(pos - off) < 1.5)
    edge = seeds + np.where(ok, pos, off)[:, None] * s_dir
    # chord of the current ellipse along u through each point
    gx, gy = edge[:, 0] + origin[0], edge[:, 1] + origin[1]
    a_, b_, c_, d_, e_, f_ = ell.conic
    qa = a_ * u[0] ** 2 + b_ * u[0] * u[1] + c_ * u[1] ** 2
    qb = 2 * a_ * gx * u[0] + b_ * (gx * u[1] + gy * u[0]) + 2 * c_ * gy * u[1] + d_ * u[0] + e_ * u[1]
    qc = a_ * gx * gx + b_ * gx * gy + c_ * gy * gy + d_ * gx + e_ * gy + f_
    chord = np.sqrt(np.maximum(qb * qb - 4 * qa * qc, 0.0)) / max(qa, 1e-300)
    ok &= chord >= 0.5 * L + 1.0
    if np.count_nonzero(ok) < 12:
        return None
    rel = edge[ok] - centre
    w = arc[ok]
    st = start[ok]
    if np.count_nonzero(st) < 8:
        st = np.ones(len(rel), bool)
    try:
        _, inl = _robust_fit(rel, w, st, scale)
        conic, _ = _fit(rel[inl], w[inl], None, origin=(0.0, 0.0), scale=scale)
        if not _conic_is_ellipse(conic):
            return None
        new = Ellipse.from_conic(_shift_conic(conic, centre[0] + origin[0], centre[1] + origin[1]))
    except EllipseFitError:
        return None
    pts = rel[inl] + (centre[0] + origin[0], centre[1] + origin[1])
    if _arc_coverage(new, pts) < 0.5:
        return None
    return new, pts, w[inl], L


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


def _centroid_blob(labels: np.ndarray, label: int, bbox, label_origin, shape) -> Marker | None:
    """Tracker mode (paper §4.1): centroid and moment ellipse of one thresholded blob (``bbox``
    (x, y, w, h) in ``labels``' pixels, whose top-left pixel is ``label_origin`` in an image of
    ``shape``); no boundary points, no quality."""
    x, y, w, h = bbox
    lx, ly = label_origin
    H, W = shape[:2]
    gx, gy = x + lx, y + ly
    touches = bool(gx <= 0 or gy <= 0 or gx + w >= W or gy + h >= H)
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
    return Marker(centroid, ell, float(mb["m00"]), np.empty((0, 2)), np.empty(0),
                  (int(gx), int(gy), int(gx + w), int(gy + h)), touches, float("nan"))


@dataclass(frozen=True)
class MarkerSearch:
    """Result of :func:`find_markers`: ``markers`` (largest first); ``rejected``: (bbox, reason)
    of each colour blob that was not taken as a marker; ``reason``: why ``markers`` is empty
    (None when it is not)."""

    markers: list[Marker]
    rejected: list[tuple[tuple[int, int, int, int], str]] = field(default_factory=list)
    reason: str | None = None

    def to_dict(self) -> dict:
        """JSON-ready dict of the markers found, the reason if none, and the rejected blobs (bbox, reason)."""
        return {"markers": [m.to_dict() for m in self.markers], "reason": self.reason,
                "rejected": [{"bbox": list(b), "reason": r} for b, r in self.rejected]}


def _clip_window(window, W: int, H: int) -> tuple[int, int, int, int] | None:
    """``window`` (x0, y0, x1, y1; pixels, None: the whole image) clipped to a W×H image, or None
    when less than 3×3 pixels of it are inside. Raises MarkerImageError for a malformed window."""
    if window is None:
        return 0, 0, W, H
    try:
        wx0, wy0, wx1, wy1 = (int(round(float(v))) for v in window)
    except (TypeError, ValueError):
        raise MarkerImageError(f"window must be (x0, y0, x1, y1), got {window!r}") from None
    wx0, wy0, wx1, wy1 = max(wx0, 0), max(wy0, 0), min(wx1, W), min(wy1, H)
    if wx1 - wx0 < 3 or wy1 - wy0 < 3:
        return None
    return wx0, wy0, wx1, wy1


def _hue_distance(h: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Degrees from hue ``h`` (0–360) to the window [lo, hi] (circular; 0 inside)."""
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    d = np.abs((h - mid + 180.0) % 360.0 - 180.0)
    return np.maximum(d - half, 0.0)


def why_no_marker(image_bgr, *, thresholds: MarkerThresholds = RED, min_area_px: int = 12) -> str:
    """One sentence on why an image holds no pixels of the marker colour window: too dark, too
    pale (saturation), or no pixels in the hue window with the nearest saturated hue seen."""
    hue_range_deg, min_saturation, min_value = thresholds.hue_range_deg, thresholds.min_saturation, thresholds.min_value
    img = _as_bgr(image_bgr)[::2, ::2]  # every 4th pixel is plenty for a diagnosis
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV_FULL).reshape(-1, 3).astype(np.float32)
    h, s, v = hsv[:, 0] * (360.0 / 256.0), hsv[:, 1] / 255.0, hsv[:, 2] / 255.0
    lo, hi = (float(x) for x in hue_range_deg)
    n_min = max(int(math.ceil(min_area_px / 4.0)), 2)
    in_hue = (_hue_distance(h, lo, hi) == 0) & (s >= 0.15) & (v >= 0.02)
    window = f"hue {lo:g}…{hi:g}°, saturation ≥ {min_saturation:g}, value ≥ {min_value:g}"
    if np.count_nonzero(in_hue & (s >= min_saturation)) >= n_min and \
            np.count_nonzero(in_hue & (s >= min_saturation) & (v >= min_value)) < n_min:
        top = float(np.percentile(v[in_hue & (s >= min_saturation)], 99))
        return (f"too dark: pixels of the marker hue reach value {top:.2f} < {min_value:g} "
                "(raise exposure or gain, or lower min_value)")
    if np.count_nonzero(in_hue & (v >= min_value)) >= n_min and \
            np.count_nonzero(in_hue & (v >= min_value) & (s >= min_saturation)) < n_min:
        top = float(np.percentile(s[in_hue & (v >= min_value)], 99))
        return (f"too pale: pixels of the marker hue reach saturation {top:.2f} < {min_saturation:g} "
                "(low contrast, glare or a white-balance cast? `labctl vision learn-color` measures the window)")
    sat = (s >= min_saturation) & (v >= min_value)
    if np.count_nonzero(sat) < n_min:
        vmax = float(np.percentile(v, 99))
        if vmax < min_value:
            return f"too dark: the image's 99th-percentile value is {vmax:.2f} < {min_value:g}"
        return f"no pixels in the colour window ({window}) and no saturated colour in the image"
    hist = np.bincount((h[sat] / 2.0).astype(int) % 180, minlength=180)
    hues = (np.arange(180) + 0.5) * 2.0
    # significant colours: local peaks of the (circularly smoothed) histogram holding ≥ n_min px
    # and ≥ 10 % of the largest peak; report the one nearest the window
    sm = hist + 0.5 * (np.roll(hist, 1) + np.roll(hist, -1))
    peak = (sm >= np.roll(sm, 1)) & (sm >= np.roll(sm, -1)) & (hist >= n_min) & (sm >= 0.1 * sm.max())
    if not peak.any():
        peak = hist == hist.max()
    dist = np.where(peak, _hue_distance(hues, lo, hi), np.inf)
    k = int(np.argmin(dist))
    return (f"no pixels in the colour window ({window}); the nearest saturated colour seen is hue "
            f"{hues[k]:.0f}° (≈{int(sm[k]) * 4} px), {dist[k]:.0f}° outside it "
            "(`labctl vision learn-color` measures the window)")


def find_markers(image_bgr, *, thresholds: MarkerThresholds = RED, window=None, min_area_px: int = 12,
                 keep_border: bool = False, max_fit_rms_px: float = 1.5, max_markers: int = 32, response="linear",
                 min_axis_ratio: float = 0.2, max_residual_rel: float = 0.12,
                 response_declared: bool = True) -> MarkerSearch:
    """Find circular markers of the configured colour in a BGR image, with each one's quality
    and, when none is found, the reason (paper §3.1 and §4.1's marker thresholding).

    1. **Colour threshold** in HSV (``thresholds``: ``hue_range_deg``, may straddle 0°; ``min_saturation``,
       ``min_value`` 0–1): shading scales R, G, B together and leaves hue and saturation alone.
    2. **Blobs** are the external contours of the mask, i.e. of the *hole-filled* mask, so a
       highlight or a speck inside a marker does not cut it. Blobs smaller than
       ``min_area_px``, cut by the image (unless ``keep_border``) or by ``window``
       (x0, y0, x1, y1) are skipped.
    3. **Linearise** each blob's crop by the camera's ``response`` (:mod:`.response`:
       ``linear``, ``srgb``, ``gamma G`` or a LUT), so pixel values are linear in coverage. A linear
       response nobody declared (``response_declared=False``: the driver file's default) is also tried as
       gamma 2.2; the rim's change is each marker's ``quality.response_unknown_px``, an error in its pose
       covariance.
    4. **Sub-pixel edge** along the outward normal at every contour pixel: a colour signal blind
       to the background's own colour direction, each profile normalised by its *own* inside and
       outside plateaus, the edge by the area rule (twice, the second window centred on the
       first answer). Profiles without two plateaus (a neighbour, a highlight, a shadow edge
       crossing) are dropped.
    5. **Robust fit** (paper eq. 2, arc-length weights): start from the points on the blob's
       convex hull away from long straight hull edges (occluder chords, bar sides), then keep
       points within 3σ (robust σ) and refit; arcs get the Sampson refinement.
    6. **Gates**: axis ratio ≥ ``min_axis_ratio`` (bars), inlier residual ≤ ``max_residual_rel``
       of the minor semi-axis and ≤ ``max_fit_rms_px``, rim coverage ≥ 50 %; what passes
       carries a :class:`MarkerQuality` with flags for partial or suspect markers.
    7. **Motion smear**: where the edge ramps are wider than 3 px and anisotropic (a box blur along
       one direction), the rim is re-measured at each ramp's half level away from the points whose
       normal is ⊥ the blur, and refitted (:func:`_motion_refit`).

    A dim frame whose mask fragments is searched again on a 3×3 mean, and the two answers are
    merged per marker (:func:`_merge_searches`). A 16-bit image is scaled (not clipped) for the
    threshold and linearised at full depth.
    Raises :class:`MarkerImageError` only for an array that is not an image.
    """
    from .response import parse_response

    raw = _check_image(image_bgr)
    img = _as_bgr(raw)
    resp = parse_response(response)
    src = raw if raw.dtype == np.uint16 else img
    H, W = img.shape[:2]
    clipped = _clip_window(window, W, H)
    if clipped is None:
        return MarkerSearch([], [], "the search window is outside the image")
    ox, oy, x1, y1 = clipped
    sub = img[oy:y1, ox:x1]
    hue_range_deg, min_saturation, min_value = thresholds.hue_range_deg, thresholds.min_saturation, thresholds.min_value
    mask = _red_mask(sub, hue_range_deg, min_saturation, min_value)
    sh, sw = mask.shape
    bx, by, bw, bh = cv2.boundingRect(mask)
    if bw == 0 or bh == 0:
        return MarkerSearch([], [], why_no_marker(sub, thresholds=thresholds, min_area_px=min_area_px))

    def linear_crop(y0, y1, x0, x1):
        return resp.linearise(src[y0:y1, x0:x1])

    def search(mask):
        contours = cv2.findContours(mask[by:by + bh, bx:bx + bw], cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE,
                                    offset=(bx + ox, by + oy))[0]
        sized = sorted(((cv2.contourArea(c) + 0.5 * len(c), c) for c in contours), key=lambda ac: -ac[0])
        found: list[Marker] = []
        rejected: list = []
        for area, c in sized:
            if area < min_area_px:
                break
            x, y, w, h = cv2.boundingRect(c)
            box = (int(x), int(y), int(x + w), int(y + h))
            at_image_edge = x <= 0 or y <= 0 or x + w >= W or y + h >= H
            at_window_edge = x - ox <= 0 or y - oy <= 0 or x + w - ox >= sw or y + h - oy >= sh
            if at_window_edge and not at_image_edge:
                rejected.append((box, "cut by the search window"))
                continue
            if at_image_edge and not keep_border:
                rejected.append((box, "cut by the image border"))
                continue
            try:
                mk = _analyse_contour(img, linear_crop, c, at_image_edge, min_axis_ratio, max_residual_rel,
                                      resp.is_linear, resp.is_linear and not response_declared)
                if not mk.fit_rms_px <= max_fit_rms_px:
                    raise _Reject(f"boundary residual {mk.fit_rms_px:.2f} px > {max_fit_rms_px:g} px")
            except _Reject as exc:
                rejected.append((box, str(exc)))
                continue
            found.append(mk)
            if len(found) >= max_markers:
                break
        return found, rejected, (sized[0][0] if sized else 0.0), len(sized)

    found, rejected, largest, n_blobs = search(mask)
    if not any(m.trusted for m in found) and n_blobs > 1:
        # a noisy, dim image breaks a marker's colour mask into fragments: threshold a 3×3 mean
        # instead (the sub-pixel edge still reads the original pixels)
        found2, rejected2, largest2, _ = search(_red_mask(cv2.blur(sub, (3, 3)), hue_range_deg, min_saturation,
                                                          min_value))
        found, rejected = _merge_searches(found, rejected, found2, rejected2)
        largest = max(largest, largest2)
    if n_blobs > 1 and any(m.quality is not None and {"partial", "outliers"} & set(m.quality.flags) for m in found):
        # a thin occluder (a wire, a cable, a clamp's edge) across a marker cuts its colour blob in two; a 5×5
        # closing bridges a dark band up to ~4 px wide, so the rim is fitted whole, the band's scans dropped
        # as outliers (a red neighbour it merges comes out flagged and loses to the plain search's marker)
        found2, rejected2, _, _ = search(cv2.morphologyEx(mask, cv2.MORPH_CLOSE, _K5))
        found, rejected = _merge_searches(found, rejected, found2, rejected2)
    found.sort(key=lambda m: -m.area)
    reason = None
    if not found:
        if rejected:
            kinds: dict[str, int] = {}
            for _, r in rejected:
                kinds[r] = kinds.get(r, 0) + 1
            reason = "rejected by shape: " + "; ".join(f"{r}" + (f" (×{n})" if n > 1 else "") for r, n in kinds.items())
        else:
            reason = f"too small: the largest blob of the marker colour has {largest:.0f} px < {min_area_px} px"
    return MarkerSearch(found, rejected, reason)


def _rank(m: Marker) -> tuple:
    """Order of preference between two answers for one marker: trusted, fewer flags, larger."""
    flags = m.quality.flags if m.quality is not None else ("no_quality",)
    return (not flags, -len(flags), m.area)


def _merge_searches(found, rejected, found2, rejected2):
    """Markers of two searches of one frame (the colour mask as is, and of a 3×3 mean): a marker
    of either, and where two overlap (one's centre inside the other's ellipse) the better one by
    :func:`_rank`. A noisy mask breaks a marker into fragments, each small and flagged, while the
    smoothed mask keeps it whole; a fragment must not hide the whole marker (dim frames)."""
    def inside(p, m):
        return m.ellipse.conic @ np.array([p[0] ** 2, p[0] * p[1], p[1] ** 2, p[0], p[1], 1.0]) <= 0.0

    out = list(found)
    for m2 in found2:
        clash = [m for m in out if inside(m2.ellipse.center, m) or inside(m.ellipse.center, m2)]
        if not clash:
            out.append(m2)
        elif all(_rank(m2) > _rank(m) for m in clash):
            out = [m for m in out if not any(m is c for c in clash)] + [m2]
    # the blobs not taken: those of the search whose markers were kept (of the first when both)
    only_second = bool(out) and not any(m is f for m in out for f in found)
    return out, rejected2 if only_second else rejected


def detect_markers(image_bgr, *, thresholds: MarkerThresholds = RED, window=None, min_area_px: int = 12,
                   keep_border: bool = False, max_fit_rms_px: float = 1.5, max_markers: int = 32, refine: bool = True,
                   response="linear", include_suspect: bool = False, response_declared: bool = True) -> list[Marker]:
    """The trusted markers of :func:`find_markers` (sorted by decreasing area, possibly empty);
    with ``include_suspect`` also those carrying a quality flag (partial, rough, …), and with
    ``keep_border`` those cut by the image edge (flagged ``border``).

    ``refine=False`` is the tracker's centroid-only mode (paper §4.1): the centroid, area and
    moment ellipse of each thresholded blob (8-connected), no boundary, no shape check, no
    quality. Raises :class:`MarkerImageError` only for an array that is not an image.
    """
    if refine:
        every = find_markers(image_bgr, thresholds=thresholds, window=window, min_area_px=min_area_px,
                             keep_border=keep_border,
                             max_fit_rms_px=max_fit_rms_px, max_markers=max_markers, response=response,
                             response_declared=response_declared).markers
        if include_suspect:
            return every
        return [m for m in every if m.trusted
                or (keep_border and m.quality is not None and set(m.quality.flags) <= {"border", "partial"})]
    img = _as_bgr(image_bgr)
    H, W = img.shape[:2]
    clipped = _clip_window(window, W, H)
    if clipped is None:
        return []
    ox, oy, x1, y1 = clipped
    sub = img[oy:y1, ox:x1]
    mask = _red_mask(sub, thresholds.hue_range_deg, thresholds.min_saturation, thresholds.min_value)
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
        stats: dict[int, tuple[int, ...]] | np.ndarray = {255: (0, 0, bw, bh, cv2.countNonZero(crop))}
    else:
        n, labels, cc_stats, _ = cv2.connectedComponentsWithStats(crop, connectivity=8)
        stats = cc_stats
        order = (np.argsort(-cc_stats[1:, cv2.CC_STAT_AREA]) + 1).tolist() if n > 1 else []
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
        marker = _centroid_blob(labels, label, (x, y, w, h), (ox, oy), img.shape)
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


def red_blob_centroid(image, near_px=None, *, thresholds: MarkerThresholds = RED, min_area_px: int = 4,
                      max_jump_px: float = 60.0):
    """Centroid (px, image x right / y down) of the red blob nearest ``near_px`` (or the largest when
    ``near_px`` is None), or None when no blob of ``min_area_px`` is within ``max_jump_px`` of it.

    The paper's fixed-camera front end (§5.2): a red filter, then the blob's centroid. Used when
    no blob passes as an ellipse — a marker on a vertical face is a thin sliver from overhead.
    """
    mask = red_mask(image, thresholds)
    n, _, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    ok = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= min_area_px]
    if not ok:
        return None
    if near_px is None:
        return centroids[max(ok, key=lambda i: stats[i, cv2.CC_STAT_AREA])]
    near = np.asarray(near_px, dtype=float)
    best = min(ok, key=lambda i: float(np.hypot(*(centroids[i] - near))))
    return centroids[best] if np.hypot(*(centroids[best] - near)) <= max_jump_px else None
