"""Learning the marker colour window from an image of the lab's own markers.

The HSV window of :func:`labctl.vision.find_markers` (paper §4.1's marker thresholding) is
policy that depends on the paint, the lighting and the camera's white balance. Given one image
of the markers under the lab's lighting, :func:`learn_marker_colour` measures it:

1. saturated pixels (saturation ≥ 0.2, value ≥ 0.06) are histogrammed by hue (2° bins,
   weighted by saturation) within ``search_deg`` of the nominal hue (default red, 0°);
2. the marker hue is the histogram's peak; marker pixels are the saturated pixels within
   ±25° of it that form compact blobs (≥ ``min_area_px``), eroded by one pixel so mixed edge
   pixels do not widen the window;
3. the hue window spans their 0.5 … 99.5 % circular hue percentiles plus a margin (at least
   ±8° about the peak); the minimum saturation is 60 % of their 2 % saturation percentile
   (at least 0.15), the minimum value 60 % of their 2 % value percentile (at least 0.04).
"""

from __future__ import annotations

import cv2
import numpy as np

from .markers import _as_bgr


class ColourLearnError(ValueError):
    """No marker-like colour found in the image."""


def learn_marker_colour(image_bgr, *, nominal_hue_deg: float = 0.0, search_deg: float = 60.0,
                        min_area_px: int = 12, margin_deg: float = 4.0) -> dict:
    """The marker colour window measured on ``image_bgr`` (see the module doc). Returns
    {"hue_range_deg": (lo, hi) (lo may be negative: the window straddles 0°), "min_saturation",
    "min_value", "peak_hue_deg", "pixels", "blobs"}. Raises :class:`ColourLearnError`."""
    img = _as_bgr(image_bgr)
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV_FULL)
    h = hsv[..., 0].astype(np.float32) * np.float32(360.0 / 256.0)
    s = hsv[..., 1].astype(np.float32) / np.float32(255.0)
    v = hsv[..., 2].astype(np.float32) / np.float32(255.0)
    rel = (h - nominal_hue_deg + 180.0) % 360.0 - 180.0  # hue relative to the nominal, (−180, 180]
    sat = (s >= 0.2) & (v >= 0.06) & (np.abs(rel) <= search_deg)
    if np.count_nonzero(sat) < min_area_px:
        raise ColourLearnError(f"no saturated colour within ±{search_deg:g}° of hue {nominal_hue_deg:g}° "
                               "(is a marker in view and lit?)")
    bins = np.arange(-search_deg, search_deg + 2.0, 2.0)
    hist, _ = np.histogram(rel[sat], bins=bins, weights=s[sat])
    hist = np.convolve(hist, [0.25, 0.5, 0.25], mode="same")
    peak = float(0.5 * (bins[np.argmax(hist)] + bins[np.argmax(hist) + 1]))
    near = sat & (np.abs(rel - peak) <= 25.0)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(near.astype(np.uint8), connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_area_px
    if not keep.any():
        raise ColourLearnError(f"no blob of the marker colour (hue {peak + nominal_hue_deg:.0f}°) has "
                               f"{min_area_px} px or more")
    blobs = keep[labels].astype(np.uint8)
    core = cv2.erode(blobs, np.ones((3, 3), np.uint8))
    if np.count_nonzero(core) < min_area_px:
        core = blobs
    sel = core > 0
    hr, ss, vv = rel[sel], s[sel], v[sel]
    lo = min(float(np.percentile(hr, 0.5)) - margin_deg, peak - 8.0)
    hi = max(float(np.percentile(hr, 99.5)) + margin_deg, peak + 8.0)
    lo, hi = lo + nominal_hue_deg, hi + nominal_hue_deg
    if lo >= 180.0 or (lo >= 0.0 and hi > 360.0):
        lo, hi = lo - 360.0, hi - 360.0
    return {
        "hue_range_deg": (round(lo, 1), round(hi, 1)),
        "min_saturation": round(max(0.15, 0.6 * float(np.percentile(ss, 2))), 3),
        "min_value": round(max(0.04, 0.6 * float(np.percentile(vv, 2))), 3),
        "peak_hue_deg": round((peak + nominal_hue_deg) % 360.0, 1),
        "pixels": int(np.count_nonzero(sel)),
        "blobs": int(np.count_nonzero(keep)),
    }
