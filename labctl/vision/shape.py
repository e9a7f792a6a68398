"""2D shape of a standard view: silhouette, Freeman chain code, eccentricity, angle-of-sight signature.

Paper §3.4 (He, Hujic, Mills & Benhabib, ICRA 1996): "the silhouette of the object is extracted,
the resulting chain-coded contour of the object is used to compute the global eccentricity
measure and the shape signature", matched by minimum distance.

The shape signature is the *angle-of-sight* (AOS) signature of Tchoukanov, Safaee-Rad, Smith &
Benhabib, "The angle-of-sight signature for two-dimensional shape analysis of manufactured
objects", Pattern Recognition 25(11):1289–1305, 1992. Its idea (from the paper's abstract): each
boundary point is described by the *angle under which a chord of the shape is seen from that
point*, recorded against the point's position along the boundary; the chord length selects the
amount of smoothing, and several chord lengths give a multi-scale representation. No public
implementation exists; the exact definition used here is:

* the outer contour is oriented counter-clockwise (positive shoelace area in pixel coordinates)
  and resampled to ``N`` points ``p_0 … p_{N-1}`` equally spaced in arc length (computed at
  4N points and averaged in runs of 4, against sampling-phase jitter at corners);
* for each scale ``k`` (a number of samples, i.e. a fixed fraction ``k/N`` of the perimeter) the
  chord of sight of ``p_i`` is ``p_{i-k} p_{i+k}`` and the angle of sight is the angle it subtends
  at ``p_i`` measured through the shape's interior::

      θ_k(i) = atan2( b × a , b · a )  mod 2π,   a = p_{i-k} − p_i,  b = p_{i+k} − p_i

  so a straight boundary gives π, a convex corner less than π and a concave one more than π;
* the signature is the ``S × N`` array ``θ_k(i)`` for ``k ∈ scales``.

It is invariant to translation, rotation and scale (angles of arc-length-normalised chords), and
a different starting point only shifts it circularly; :func:`signature_distance` removes that
shift by circular cross-correlation (FFT), so the distance is invariant to the starting point
and to in-plane rotation. The paper's shape-specific single chord of sight (chosen from the
characteristic ellipse) is replaced by the family of chords sliding with the point, which needs
no choice of a reference chord and so no ambiguity when the ellipse is a circle.

The global eccentricity is that of the characteristic ellipse, i.e. the ellipse with the
region's central second moments: ``ε = sqrt(1 − λ_min/λ_max)`` of the 2×2 second-moment matrix.

Two baselines for comparison (benchmark only): Hu's seven moment invariants
(``cv2.matchShapes``) and centroid-distance Fourier descriptors (Zhang & Lu 2002).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

N_SAMPLES = 128
AOS_SCALES = (4, 8, 16, 32)  # chord half-lengths in samples: 1/32 … 1/4 of the perimeter
N_FOURIER = 24
OVERSAMPLE = 4

# Freeman directions 0..7, counter-clockwise from +x in a y-up frame; in image coordinates
# (rows down) direction 2 is "up" = −row.
_FREEMAN_STEPS = np.array([(1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1), (0, 1), (1, 1)])
_STEP_TO_CODE = {tuple(s): i for i, s in enumerate(_FREEMAN_STEPS)}


BORDER_PX = 6  # width of the image border taken as background
BACKGROUND_MARGIN = 12.0  # grey levels above the background's 99.5th percentile that count as object


class ShapeError(ValueError):
    """No usable silhouette in an image (empty, touching the border, too small)."""


# --- silhouette ------------------------------------------------------------------------
def silhouette_mask(image: np.ndarray, *, min_area_px: int = 200, red_is_object: bool = True,
                    max_levels: int = 3) -> np.ndarray:
    """Object silhouette (bool H×W) of a standard-view image against the darker background.

    Otsu threshold on grey level (objects are lighter than the table), lowered to just above the
    background seen at the image border when that is lower (faces in shadow), red marker pixels
    counted as object, largest connected component kept and its holes filled. A view taken
    nearly horizontally (a marker on a side face) shows a dark void above the table's horizon;
    Otsu then separates void from table+object and the component touches the border, so the
    threshold is recomputed (Otsu again) on the pixels above it, up to ``max_levels`` times.
    Raises :class:`ShapeError` if nothing object-like is found or it touches the image border
    at every level (part of the object outside the view).
    """
    img = np.asarray(image)
    if img.ndim == 2:
        gray: np.ndarray = img.astype(np.uint8)
        red = np.zeros(gray.shape, bool)
    else:
        gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        b, g, r = (img[..., i].astype(np.int16) for i in range(3))
        red = (r > g + 50) & (r > b + 50) if red_is_object else np.zeros(gray.shape, bool)
    blur = cv2.medianBlur(gray, 5)  # kills sensor noise without moving edges (a Gaussian would spread them)
    values = blur.ravel()
    # The image border is background (the object is centred and must be wholly in view): anything
    # clearly brighter than the brightest background there is object, even a face in shadow that
    # Otsu would put with the table.
    ring = np.concatenate([blur[:BORDER_PX].ravel(), blur[-BORDER_PX:].ravel(),
                           blur[:, :BORDER_PX].ravel(), blur[:, -BORDER_PX:].ravel()])
    t_background = float(np.percentile(ring, 99.5)) + BACKGROUND_MARGIN
    error = ShapeError("no silhouette found in the image")
    for _ in range(max(1, max_levels)):
        if values.size < min_area_px:
            break
        t, _ = cv2.threshold(values.reshape(1, -1), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        fg = (blur > min(t, t_background)) | red
        try:
            return _largest_filled(fg, min_area_px)
        except ShapeError as exc:
            error = exc
        values = values[values > t]
    raise error


def _largest_filled(fg: np.ndarray, min_area_px: int) -> np.ndarray:
    fg = fg.astype(np.uint8)
    contours, _ = cv2.findContours(fg, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        raise ShapeError("no silhouette found in the image")
    c = max(contours, key=cv2.contourArea)
    if cv2.contourArea(c) < min_area_px:
        raise ShapeError(f"silhouette too small ({cv2.contourArea(c):.0f} px² < {min_area_px})")
    h, w = fg.shape
    x, y, cw, ch = cv2.boundingRect(c)
    if x <= 0 or y <= 0 or x + cw >= w or y + ch >= h:
        raise ShapeError("the silhouette touches the image border: the object is not fully in view")
    out = np.zeros_like(fg)
    cv2.drawContours(out, [c], -1, 1, thickness=cv2.FILLED)
    return out.astype(bool)


def outer_contour(mask: np.ndarray) -> np.ndarray:
    """Outer boundary pixels (N, 2) int as (x=col, y=row) of the largest region, 8-connected, closed."""
    m = np.asarray(mask).astype(np.uint8)
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        raise ShapeError("empty mask")
    return max(contours, key=cv2.contourArea).reshape(-1, 2).astype(np.int64)


# --- Freeman chain code ----------------------------------------------------------------
def freeman_chain_code(contour: np.ndarray) -> np.ndarray:
    """8-direction Freeman chain code (uint8, length N) of a closed 8-connected pixel contour.

    Code c means a step ``_FREEMAN_STEPS[c]`` in (col, row); 0 = +x, 2 = up (−row), counter-
    clockwise in the y-up convention (Freeman 1961). The last code closes the contour.
    """
    pts = np.asarray(contour, dtype=np.int64)
    steps = np.roll(pts, -1, axis=0) - pts
    if np.any(np.abs(steps).max(axis=1) != 1):
        raise ShapeError("contour is not 8-connected")
    return np.array([_STEP_TO_CODE[(int(dx), int(dy))] for dx, dy in steps], dtype=np.uint8)


def chain_to_contour(start: tuple[int, int], code: np.ndarray) -> np.ndarray:
    """Inverse of :func:`freeman_chain_code`: pixel points (N, 2) from a start point and codes."""
    steps = _FREEMAN_STEPS[np.asarray(code, dtype=np.int64)]
    pts = np.asarray(start, dtype=np.int64) + np.vstack([[0, 0], np.cumsum(steps, axis=0)[:-1]])
    return pts


def chain_perimeter(code: np.ndarray) -> float:
    """Perimeter (px) of a chain-coded contour: 1 per even code, √2 per odd code."""
    code = np.asarray(code)
    odd = int(np.count_nonzero(code % 2))
    return float(len(code) - odd + odd * np.sqrt(2.0))


# --- global measures -------------------------------------------------------------------
def second_moments(mask: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Area (px²), centroid (x, y) and 2×2 central second-moment matrix (px²) of a region."""
    m = cv2.moments(np.asarray(mask).astype(np.uint8), binaryImage=True)
    if m["m00"] <= 0:
        raise ShapeError("empty region")
    c = np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])
    cov = np.array([[m["mu20"], m["mu11"]], [m["mu11"], m["mu02"]]]) / m["m00"]
    return float(m["m00"]), c, cov


def eccentricity(mask: np.ndarray) -> float:
    """Eccentricity ε ∈ [0, 1) of the characteristic ellipse (same second moments as the region).

    ``ε = sqrt(1 − λ_min/λ_max)`` of the central second-moment matrix (Tchoukanov et al. 1992,
    the global measure of the two-level matching, paper §3.4). Invariant to translation,
    rotation and scale.
    """
    _, _, cov = second_moments(mask)
    lam = np.linalg.eigvalsh(cov)
    if lam[1] <= 0:
        raise ShapeError("degenerate region")
    return float(np.sqrt(max(0.0, 1.0 - lam[0] / lam[1])))


# --- contour resampling and signatures -------------------------------------------------
def resample_closed(contour: np.ndarray, n: int = N_SAMPLES) -> np.ndarray:
    """``n`` points (float, (n, 2)) equally spaced in arc length on a closed polyline, CCW.

    Orientation is normalised to positive shoelace area in the given coordinates, so the
    interior lies to the left of the direction of travel.
    """
    p = np.asarray(contour, dtype=float)
    if len(p) < 3:
        raise ShapeError("contour has fewer than 3 points")
    x, y = p[:, 0], p[:, 1]
    if np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y) < 0:
        p = p[::-1]
    closed = np.vstack([p, p[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        raise ShapeError("contour has zero length")
    t = np.arange(n) * (s[-1] / n)
    return np.column_stack([np.interp(t, s, closed[:, 0]), np.interp(t, s, closed[:, 1])])


def angle_of_sight_signature(points: np.ndarray, scales=AOS_SCALES, oversample: int = OVERSAMPLE) -> np.ndarray:
    """Angle-of-sight signature ``θ_k(i)`` (rad, (len(scales), N)) of a closed CCW contour.

    See the module docstring for the definition (Tchoukanov et al. 1992, our sliding-chord
    variant). Straight boundary → π; convex corner < π; concave > π. ``points`` are resampled
    to ``oversample·N`` points (N = ``N_SAMPLES``), θ is computed with chords ``oversample·k``
    and averaged over each run of ``oversample`` samples, so a corner falling between two
    samples (sampling phase) barely changes the signature.
    """
    p = resample_closed(points, N_SAMPLES * oversample)
    out = np.empty((len(scales), len(p)))
    for j, k in enumerate(scales):
        a = np.roll(p, k * oversample, axis=0) - p  # p_{i-k} - p_i
        b = np.roll(p, -k * oversample, axis=0) - p  # p_{i+k} - p_i
        cross = b[:, 0] * a[:, 1] - b[:, 1] * a[:, 0]
        dot = np.sum(a * b, axis=1)
        out[j] = np.mod(np.arctan2(cross, dot), 2 * np.pi)
    return out.reshape(len(scales), N_SAMPLES, oversample).mean(axis=2)


def signature_distance(query: np.ndarray, library: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RMS angle difference (rad) minimised over circular shifts, against a batch of signatures.

    ``query`` (S, N), ``library`` (V, S, N). Returns ``(dist (V,), shift (V,))`` where ``shift``
    is the start-point offset (samples) that aligns library view v to the query. Computed as
    ``‖a‖² + ‖b‖² − 2·max_s Σ_k (a_k ⋆ b_k)(s)`` with the cross-correlation by FFT, so it is
    invariant to the contour's starting point and hence to in-plane rotation.
    """
    q = np.asarray(query, dtype=float)
    lib = np.asarray(library, dtype=float)
    n = q.shape[-1]
    fq = np.fft.rfft(q, axis=-1)
    fl = np.fft.rfft(lib, axis=-1)
    corr = np.fft.irfft(np.sum(fl * np.conj(fq)[None], axis=1), n=n, axis=-1)  # (V, N)
    shift = np.argmax(corr, axis=1)
    best = corr[np.arange(len(lib)), shift]
    sq = np.sum(q * q) + np.sum(lib * lib, axis=(1, 2)) - 2.0 * best
    return np.sqrt(np.maximum(sq, 0.0) / q.size), shift


def centroid_distance_fd(points: np.ndarray, n_coeff: int = N_FOURIER) -> np.ndarray:
    """Centroid-distance Fourier descriptor (baseline): |FFT(r)|_1..n / |FFT(r)|_0.

    ``r(i) = ‖p_i − centroid‖`` on arc-length-resampled points; magnitudes make it invariant to
    start point and rotation, division by the DC term to scale (Zhang & Lu, 2002).
    """
    p = np.asarray(points, dtype=float)
    r = np.linalg.norm(p - p.mean(axis=0), axis=1)
    f = np.abs(np.fft.rfft(r))
    return f[1 : n_coeff + 1] / max(f[0], 1e-12)


def hu_moments(mask: np.ndarray) -> np.ndarray:
    """Hu's seven moment invariants of a region (baseline; cv2.HuMoments)."""
    return cv2.HuMoments(cv2.moments(np.asarray(mask).astype(np.uint8), binaryImage=True)).ravel()


def hu_distance(hu_a: np.ndarray, hu_b: np.ndarray) -> np.ndarray:
    """``cv2.matchShapes`` CONTOURS_MATCH_I1 distance on precomputed Hu moments (vectorised over rows of b)."""
    a = np.asarray(hu_a, dtype=float)
    b = np.atleast_2d(np.asarray(hu_b, dtype=float))
    eps = 1e-5
    ma = np.where(np.abs(a) > eps, np.sign(a) * np.log10(np.abs(a) + 1e-300), np.nan)
    mb = np.where(np.abs(b) > eps, np.sign(b) * np.log10(np.abs(b) + 1e-300), np.nan)
    valid = ~np.isnan(ma)[None] & ~np.isnan(mb)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.abs(1.0 / ma[None] - 1.0 / mb)
    return np.where(valid, d, 0.0).sum(axis=1)


# --- the feature vector of one standard view -------------------------------------------
@dataclass
class ShapeFeatures:
    """Features of one standard view (paper §3.4). Sizes in mm at the stand-off distance."""

    eccentricity: float
    size_mm: float  # sqrt(area) converted with the stand-off scale
    perimeter_mm: float
    chain_start: tuple[int, int]
    chain_code: np.ndarray  # uint8 Freeman codes of the outer contour
    aos: np.ndarray  # (S, N) rad
    fd: np.ndarray  # (N_FOURIER,) centroid-distance Fourier descriptor (baseline)
    hu: np.ndarray  # (7,) Hu moments (baseline)
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-ready dict of the features (chain code as a digit string); inverse of :meth:`from_dict`."""
        return {
            "eccentricity": self.eccentricity, "size_mm": self.size_mm, "perimeter_mm": self.perimeter_mm,
            "chain_start": list(self.chain_start),
            "chain_code": "".join(str(int(c)) for c in self.chain_code),
            "aos": np.round(self.aos, 6).tolist(), "fd": self.fd.tolist(), "hu": self.hu.tolist(),
            "aos_scales": list(AOS_SCALES), **self.extra,
        }

    @classmethod
    def from_dict(cls, d: dict) -> ShapeFeatures:
        """Features from :meth:`to_dict` output; raises ValueError on a malformed signature, chain code or start."""
        code = np.frombuffer(str(d["chain_code"]).encode("ascii"), dtype=np.uint8) - ord("0")
        aos = np.asarray(d["aos"], dtype=float)
        if aos.ndim != 2 or aos.shape[0] != len(AOS_SCALES) or aos.shape[1] != N_SAMPLES:
            raise ValueError(f"angle-of-sight signature has shape {aos.shape}, expected "
                             f"({len(AOS_SCALES)}, {N_SAMPLES})")
        if code.size and (code.max() > 7):
            raise ValueError("chain code has digits outside 0..7")
        start = list(d["chain_start"])
        if len(start) != 2:
            raise ValueError(f"chain start must be a pixel (column, row), got {start!r}")
        return cls(
            eccentricity=float(d["eccentricity"]), size_mm=float(d["size_mm"]),
            perimeter_mm=float(d["perimeter_mm"]), chain_start=(int(start[0]), int(start[1])),
            chain_code=code.astype(np.uint8), aos=aos, fd=np.asarray(d["fd"], float), hu=np.asarray(d["hu"], float),
        )


def features_from_mask(mask: np.ndarray, mm_per_px: float) -> ShapeFeatures:
    """All features of a silhouette mask; ``mm_per_px`` is the metric scale at the stand-off.

    The stand-off is known in a standard view (paper §3.4, §4.3), so the silhouette's metric
    size is an extra discriminant: ``size_mm = sqrt(area_px)·mm_per_px``.
    """
    if not mm_per_px > 0:
        raise ValueError("mm_per_px must be positive")
    contour = outer_contour(mask)
    code = freeman_chain_code(contour)
    area, _, _ = second_moments(mask)
    pts = resample_closed(contour)
    return ShapeFeatures(
        eccentricity=eccentricity(mask), size_mm=float(np.sqrt(area) * mm_per_px),
        perimeter_mm=chain_perimeter(code) * mm_per_px, chain_start=(int(contour[0, 0]), int(contour[0, 1])),
        chain_code=code, aos=angle_of_sight_signature(contour), fd=centroid_distance_fd(pts), hu=hu_moments(mask),
    )


def features_from_image(image: np.ndarray, mm_per_px: float) -> ShapeFeatures:
    """Silhouette extraction then :func:`features_from_mask` (raises :class:`ShapeError`)."""
    return features_from_mask(silhouette_mask(image), mm_per_px)
