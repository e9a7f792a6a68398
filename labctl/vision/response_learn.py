"""Measure a camera's response (``labctl vision learn-response``): the curve from 8-bit code to linear radiance.

Sub-pixel edges need linear pixel values (paper §3.1), so the response a driver file declares must be the
camera's. Two measurements, both pure functions (numpy in, a :class:`LearnedResponse` out):

* **Exposure series** (:func:`learn_from_exposures`): a few frames of one static scene at known exposure
  times, gain and white balance fixed. OpenCV's ``createCalibrateDebevec`` (Debevec & Malik 1997: the
  inverse response g and every sample's radiance by least squares with a smoothness term; a maintained
  library, not reimplemented here) gives radiance per code, up to a scale.
* **Grey step wedge** (:func:`learn_from_wedge`): one frame of printed patches of known reflectance; each
  patch's median code against its reflectance is the curve at those codes.

The curve is then named: ``linear``, ``srgb`` or ``gamma G`` when one of them explains the measurement, else the
256-entry LUT the driver file's ``response:`` also accepts (:mod:`.response`). A wedge's curve is named by its
distance to each (:func:`name_curve`, within :data:`POWER_LAW_TOLERANCE` over the codes reached); an exposure
series' by how well each explains the frames themselves (:func:`_name_by_consistency`), since Debevec's curve
is itself bent by its smoothness term near the top codes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .response import parse_response


class ResponseLearnError(ValueError):
    """Inputs from which no response can be measured (one line for the user)."""


# a named curve (linear, srgb, gamma G) is written when it is within this much of the measured one (radiance
# normalised to 1 at code 255) at every code the measurement reached. Debevec's curve from 6–13 frames is good to
# 0.5–2 % of full scale on plain numpy series and 1–4 % on Mitsuba frames of a disc on a plane (few radiance levels;
# worst near the top codes, where its weights vanish), measured 2026-12-02; the marker edge's sub-pixel reading
# errs by about that fraction of its ramp width
POWER_LAW_TOLERANCE = 0.03
# codes this close to 0 or 255 are left out of the fit: noise floor and clipping
_CODE_MARGIN = 8
# the exposure series: at least this many frames, and this ratio between the longest and shortest exposure
MIN_FRAMES = 3
MIN_EXPOSURE_SPAN = 4.0


@dataclass(frozen=True)
class LearnedResponse:
    """A measured response: ``curve`` the linear radiance of each code 0…255 (normalised to 1 at 255; float,
    monotone), ``codes`` the code range the measurement reached (lo, hi), ``spec`` what the driver file gets
    (``"linear"``, ``"srgb"``, ``"gamma G"`` or the 256-entry list), ``error`` the named curve's largest
    deviation from the measured one over ``codes`` (0 for a LUT), ``method`` ``exposures`` or ``wedge``."""

    curve: np.ndarray
    codes: tuple[int, int]
    spec: str | list[float]
    error: float
    method: str

    @property
    def gamma(self) -> float | None:
        """The fitted exponent for a ``gamma G`` (1 for linear), else None."""
        if self.spec == "linear":
            return 1.0
        if isinstance(self.spec, str) and self.spec.startswith("gamma"):
            return float(self.spec.split()[1])
        return None


def _monotone(curve: np.ndarray) -> np.ndarray:
    """``curve`` made non-decreasing (running maximum) and normalised to [0, 1] at codes 0 and 255."""
    c = np.maximum.accumulate(np.asarray(curve, float))
    c = c - c[0]
    if not c[-1] > 0:
        raise ResponseLearnError("the measured curve is flat: the frames do not differ in brightness")
    return c / c[-1]


def name_curve(curve: np.ndarray, codes: tuple[int, int], method: str,
               tolerance: float = POWER_LAW_TOLERANCE) -> LearnedResponse:
    """The simplest response that matches ``curve`` (radiance of each code, any scale) within ``tolerance``
    over ``codes`` (lo, hi), the codes the measurement reached: linear, srgb, or a power law ``gamma G`` (G and
    the scale by least squares on log radiance against log code, weighted by radiance; 0.2–5), the first in
    that order within one code step (1/255) of the least deviation; else the curve itself as a LUT. Each is
    compared after the best scale (the curve's own scale is unknown: an exposure series fixes it nowhere, and
    its top code is clipped); outside ``codes`` a LUT continues as the fitted power law."""
    lo, hi = codes
    raw = np.maximum.accumulate(np.maximum(np.asarray(curve, float), 0.0))
    x = np.arange(256) / 255.0
    sel = np.zeros(256, bool)
    sel[max(lo, 1):hi + 1] = True
    sel &= raw > 0
    if np.count_nonzero(sel) < 8:
        raise ResponseLearnError(f"the measurement reached only codes {lo}…{hi}: too few to tell a curve")
    lx, ly, w = np.log(x[sel]), np.log(raw[sel]), raw[sel] / raw[sel].max()
    A = np.stack([lx, np.ones_like(lx)], axis=1) * np.sqrt(w)[:, None]
    g_fit, log_s = np.linalg.lstsq(A, ly * np.sqrt(w), rcond=None)[0]
    g = round(float(np.clip(g_fit, 0.2, 5.0)), 2)
    scaled = raw / math.exp(log_s)  # the curve on the fitted power law's scale (1 at code 255)

    def fit(lut: np.ndarray) -> tuple[float, float]:
        c, m = scaled[sel], lut[sel]
        k = float(c @ m) / float(c @ c)  # the best scale for this candidate
        return float(np.max(np.abs(k * c - m))), k

    named = ("linear", "srgb", f"gamma {g:g}")
    luts = {spec: parse_response(spec).lut.astype(float) for spec in named}
    fits = {spec: fit(luts[spec]) for spec in named}
    # the simplest name that is as good as the fitted power law to within one 8-bit code step
    best = min(e for e, _ in fits.values())
    spec = next(sp for sp in named if fits[sp][0] <= best + 1.0 / 255.0)
    if fits[spec][0] <= tolerance:
        err, k = fits[spec]
        return LearnedResponse(_monotone(np.where(sel, k * scaled, luts[spec])), codes, spec, err, method)
    lut = _monotone(np.where((np.arange(256) >= lo) & (np.arange(256) <= hi), scaled, x ** g))
    return LearnedResponse(lut, codes, [round(float(v), 6) for v in lut], 0.0, method)


def learn_from_exposures(images: list[np.ndarray], times_s: list[float], *, samples: int = 400,
                         tolerance: float = POWER_LAW_TOLERANCE) -> LearnedResponse:
    """The response from frames of one static scene (same size, 8-bit BGR or grey) at exposure times
    ``times_s`` (s, > 0): OpenCV's Debevec calibration (``samples`` pixel sites spread over the middle frame's codes,
    smoothness 10), the
    three channels' curves combined per code by how often each channel reached it (white balance fixed:
    they share one curve), normalised, then named
    (:func:`name_curve`) over the codes the frames reached. Raises :class:`ResponseLearnError`."""
    if len(images) != len(times_s):
        raise ResponseLearnError(f"{len(images)} frames but {len(times_s)} exposure times")
    if len(images) < MIN_FRAMES:
        raise ResponseLearnError(f"{len(images)} frame(s): need at least {MIN_FRAMES} exposures of one scene")
    t = np.asarray(times_s, float)
    if not (np.all(np.isfinite(t)) and np.all(t > 0)):
        raise ResponseLearnError(f"exposure times must be positive seconds, got {list(times_s)}")
    if len(set(np.round(t, 12))) != len(t):
        raise ResponseLearnError("two frames have the same exposure time")
    if t.max() / t.min() < MIN_EXPOSURE_SPAN:
        raise ResponseLearnError(f"the exposures span only {t.max() / t.min():.1f}×: need ≥ {MIN_EXPOSURE_SPAN:g}× "
                                 "between the shortest and the longest")
    imgs = []
    for k, im in enumerate(images):
        a = np.asarray(im)
        if a.dtype != np.uint8 or a.ndim not in (2, 3):
            raise ResponseLearnError(f"frame {k + 1} is not an 8-bit image")
        imgs.append(cv2.cvtColor(a, cv2.COLOR_GRAY2BGR) if a.ndim == 2 else np.ascontiguousarray(a[..., :3]))
    if any(im.shape != imgs[0].shape for im in imgs):
        raise ResponseLearnError("the frames differ in size: they must show one scene from one camera")
    order = np.argsort(t)
    imgs = [imgs[i] for i in order]
    t = t[order]
    # the pixel sites Debevec solves for: spread evenly over the codes of the middle exposure (its own grid or
    # random choice would mostly sample the scene's large flat regions, a few radiances), laid out as a small
    # square image whose every pixel its grid then takes
    side = int(math.isqrt(samples))
    sites = _stratified_sites(imgs[len(imgs) // 2], side * side)
    stack = [im.reshape(-1, 3)[sites].reshape(side, side, 3) for im in imgs]
    crf = np.asarray(cv2.createCalibrateDebevec(samples=side * side, random=False).process(stack, t.astype(np.float32)),
                     float).reshape(256, 3)
    # each channel's curve holds only where that channel's pixels reached (elsewhere it is the smoothness term's
    # guess), and Debevec fixes every channel's log curve to 0 at code 128, so their scales agree: per code, the
    # channels' log curves weighted by how often each saw that code
    hist = np.stack([sum(np.bincount(im[..., k].ravel(), minlength=256) for im in imgs) for k in range(3)], axis=1)
    w = hist.astype(float)
    log_c = np.log(np.maximum(crf, 1e-12))
    total = w.sum(axis=1)
    seen_any = total > 0
    mixed = np.where(seen_any, (w * log_c).sum(axis=1) / np.maximum(total, 1.0), np.nan)
    codes_seen = np.nonzero(seen_any)[0]
    curve = np.exp(np.interp(np.arange(256), codes_seen, mixed[codes_seen]))
    # the codes the series reached, inside the noise and clipping margins
    seen = np.nonzero(total >= max(10, total.sum() // 20000))[0]
    lo, hi = int(max(seen.min(), _CODE_MARGIN)), int(min(seen.max(), 255 - _CODE_MARGIN))
    if hi - lo < 64:
        raise ResponseLearnError(f"the frames reach only codes {lo}…{hi}: use a scene with darker and brighter parts "
                                 "or a wider exposure range")
    measured = name_curve(curve, (lo, hi), "exposures", tolerance)
    return _name_by_consistency(measured, np.stack(stack).reshape(len(imgs), -1), t)


# a named curve explains an exposure series as well as the measured one when its frame-to-frame residual is at
# most this factor of the measured curve's (which has 256 free values and fits some of the series' noise too).
# Measured 2026-12-02 on the tests' patch series, 23 seeds: the true power law's residual is ≤ 1.01× Debevec's
# at G = 1.2, ≤ 1.10× at G = 2.8; one 0.1 off in G is ≥ 4.3× at G = 1.2, ≥ 1.47× at G = 2.5 and ~1.0× at G = 2.8
# (there the pairs' own G, good to 0.003, is what tells them apart)
CONSISTENCY_FACTOR = 1.25


def _name_by_consistency(measured: LearnedResponse, codes: np.ndarray, t: np.ndarray) -> LearnedResponse:
    """Name an exposure series' curve by how well each candidate explains the frames themselves, not by its
    distance to Debevec's curve (which its smoothness term bends where its weights vanish, near the top codes,
    by up to 5 % at G = 2.5–2.8). For every sample site seen unclipped (inside ``measured.codes``) in frames i
    and j, a response f must give log f(c_j) − log f(c_i) = log(t_j / t_i). Candidates: linear, srgb, the power
    law fitted to those pairs directly (1/G = Σ w Δlog c Δlog t / Σ w Δlog t², Δlog c regressed on the exact
    Δlog t; w the inverse variance of Δlog c under 8-bit quantisation), and the measured curve; the simplest
    whose weighted RMS residual is within :data:`CONSISTENCY_FACTOR` of the least is named. ``codes`` is
    frames × samples (uint8), ``t`` the sorted exposure times (s)."""
    lo, hi = measured.codes
    c = codes.astype(float)
    i, j = np.triu_indices(len(t), 1)
    ci, cj = c[i], c[j]
    ok = (ci >= max(lo, 1)) & (ci <= hi) & (cj >= max(lo, 1)) & (cj <= hi)
    if np.count_nonzero(ok) < 32:
        return measured
    dlt = np.broadcast_to(np.log(t[j] / t[i])[:, None], ci.shape)[ok]
    a, b = ci[ok].astype(int), cj[ok].astype(int)
    w = 1.0 / (1.0 / ci[ok] ** 2 + 1.0 / cj[ok] ** 2)
    dlc = np.log(b / a)
    inv_g = float(w @ (dlc * dlt)) / float(w @ (dlt * dlt))
    g = round(float(np.clip(1.0 / inv_g, 0.2, 5.0)), 2) if inv_g > 0 else None

    def residual(lut: np.ndarray) -> float:
        lf = np.log(np.maximum(lut, 1e-12))
        r = lf[b] - lf[a] - dlt
        return math.sqrt(float(w @ (r * r)) / float(w.sum()))

    named = ["linear", "srgb"] + ([f"gamma {g:g}"] if g is not None else [])
    luts = {spec: parse_response(spec).lut.astype(float) for spec in named}
    res = {spec: residual(luts[spec]) for spec in named}
    least = min(min(res.values()), residual(measured.curve))
    spec = next((sp for sp in named if res[sp] <= CONSISTENCY_FACTOR * least), None)
    if spec is None:
        return measured if not isinstance(measured.spec, str) else LearnedResponse(
            measured.curve, measured.codes, [round(float(v), 6) for v in measured.curve], 0.0, measured.method)
    sel = slice(max(lo, 1), hi + 1)
    err = float(np.max(np.abs(measured.curve[sel] - luts[spec][sel])))
    return LearnedResponse(luts[spec], measured.codes, spec, err, measured.method)


def _stratified_sites(image: np.ndarray, n: int) -> np.ndarray:
    """``n`` flat pixel indices of ``image`` (H×W×3 uint8) spread evenly over its grey codes (32 bins of the
    channel mean, as many from each as it has up to an equal share; a fixed seed, so the result is repeatable)."""
    grey = image.reshape(-1, 3).astype(np.int32).sum(axis=1) // 3
    rng = np.random.default_rng(0)
    bins = [np.nonzero(grey // 8 == b)[0] for b in range(32)]
    bins = [b for b in bins if b.size]
    picked: list[np.ndarray] = []
    left = n
    for k, idx in enumerate(sorted(bins, key=len)):
        share = left // (len(bins) - k)
        take = rng.choice(idx, size=min(share, idx.size), replace=False)
        picked.append(take)
        left -= take.size
    out = np.concatenate(picked)
    if out.size < n:  # a tiny image: repeat sites (Debevec weighs them alike)
        out = np.resize(out, n)
    return out


def wedge_codes(image: np.ndarray, box: tuple[int, int, int, int], n_patches: int) -> np.ndarray:
    """The median code (grey: mean of B, G, R) of each of ``n_patches`` equal cells along the longer side of
    ``box`` (x0, y0, x1, y1 px, ends exclusive) — a printed step wedge's patches, in order — using each
    cell's central half (the print's patch borders and the lens blur stay out)."""
    a = np.asarray(image)
    if a.dtype != np.uint8 or a.ndim not in (2, 3):
        raise ResponseLearnError("the wedge image is not an 8-bit image")
    grey = a.astype(float) if a.ndim == 2 else a[..., :3].astype(float).mean(axis=2)
    x0, y0, x1, y1 = (int(v) for v in box)
    H, W = grey.shape
    if not (0 <= x0 < x1 <= W and 0 <= y0 < y1 <= H):
        raise ResponseLearnError(f"the wedge box {box} is not inside the {W}×{H} image")
    if n_patches < 2:
        raise ResponseLearnError("a step wedge needs at least 2 patches")
    crop = grey[y0:y1, x0:x1]
    if crop.shape[1] < crop.shape[0]:
        crop = crop.T
    h, w = crop.shape
    if w < 4 * n_patches:
        raise ResponseLearnError(f"the wedge box is {w} px long: too short for {n_patches} patches")
    out = []
    for k in range(n_patches):
        a0, a1 = w * k / n_patches, w * (k + 1) / n_patches
        c0, c1 = int(math.ceil(a0 + 0.25 * (a1 - a0))), int(math.floor(a1 - 0.25 * (a1 - a0)))
        out.append(float(np.median(crop[h // 4:max(h - h // 4, h // 4 + 1), c0:max(c1, c0 + 1)])))
    return np.array(out)


def learn_from_wedge(codes: np.ndarray, reflectances: list[float], *,
                     tolerance: float = POWER_LAW_TOLERANCE) -> LearnedResponse:
    """The response from a grey step wedge: each patch's code (:func:`wedge_codes`) against its known
    reflectance (any scale: radiance is proportional to it under even light). The points are ordered by
    code and interpolated (linear in code) into a curve, normalised so the brightest patch's radiance
    sits on the power law through it, then named over the patches' code range (:func:`name_curve`)."""
    c = np.asarray(codes, float)
    r = np.asarray(reflectances, float)
    if c.shape != r.shape or c.size < 4:
        raise ResponseLearnError(f"need ≥ 4 patches with one reflectance each, got {c.size} codes and {r.size} "
                                 "reflectances")
    if not (np.all(np.isfinite(r)) and np.all(r > 0)):
        raise ResponseLearnError("reflectances must be positive numbers")
    order = np.argsort(c)
    c, r = c[order], r[order]
    if np.any(np.diff(r) < 0):
        raise ResponseLearnError("the patches' codes do not rise with their reflectance: check the patch order "
                                 "and that no patch is clipped")
    keep = (c > _CODE_MARGIN) & (c < 255 - _CODE_MARGIN)
    if np.count_nonzero(keep) < 4:
        raise ResponseLearnError("fewer than 4 patches lie between black and clipping: change the exposure")
    c, r = c[keep], r[keep]
    if c[-1] - c[0] < 64:
        raise ResponseLearnError(f"the patches reach only codes {c[0]:.0f}…{c[-1]:.0f}: too narrow a range")
    # radiance at code 255 is unknown: extend the brightest points' local power law to it
    x = c / 255.0
    g_top = float(np.log(r[-1] / r[-2]) / np.log(x[-1] / x[-2])) if x[-1] > x[-2] and r[-1] > r[-2] else 1.0
    g_top = float(np.clip(g_top, 0.2, 5.0))
    r = r / (r[-1] / x[-1] ** g_top)
    curve = np.interp(np.arange(256), np.concatenate([[0.0], c, [255.0]]), np.concatenate([[0.0], r, [1.0]]))
    return name_curve(curve, (int(math.ceil(c[0])), int(math.floor(c[-1]))), "wedge", tolerance)
