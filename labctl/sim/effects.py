"""Realistic-camera effects of the simulated lab: what a real camera and a
real scene add to the clean render of :mod:`labctl.sim.render`.

The renderer's grey levels are *linear* radiance (0–255 full scale). :class:`CameraEffects`
adds, when asked:

* **cast shadows** of the object on the table from the directional light (the mesh projected
  along the light onto z = 0, rasterised in table millimetres, sampled where the renderer maps
  pixels to the table; a 1 mm penumbra for a lamp of finite size);
* **specular highlights**: a Blinn-Phong term ``ks·(n·h)^shininess`` (white light, linear) on
  every lit face and marker, the view vector taken at the face's centroid (faces are flat; it
  turns by ~1° across a face at 1 m);
* **table texture strength**: the breadboard texture's contrast about its mean;
* the **sensor and camera pipeline** on the noisy linear frame: a Bayer mosaic (RGGB) and
  OpenCV's demosaicing, the camera's **response** (``linear`` | ``srgb`` | ``gamma G`` | LUT,
  as :mod:`labctl.vision.response` reads it back), and **JPEG** at a quality (4:2:0).

All functions are pure (numpy in, numpy out); units mm and grey levels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, cast

import cv2
import numpy as np

from ..vision.response import Response, parse_response

if TYPE_CHECKING:
    from ..config import Lab
    from ..config.devices import CameraConfig

BAYER_CODES = {
    # RGGB sensor (R at even row, even column); OpenCV names the pattern by the second row
    "bilinear": cv2.COLOR_BayerBG2BGR,
    "vng": cv2.COLOR_BayerBG2BGR_VNG,
    "ea": cv2.COLOR_BayerBG2BGR_EA,
}
PENUMBRA_MM = 1.0  # soft shadow edge: a lamp of finite size ~2 m away, objects tens of mm tall
_SHADOW_GRID_MM = 0.25  # shadow mask resolution (≪ a fixed-camera pixel, ~0.9 mm)
# a window with Bayer or JPEG on is rendered this much larger, on the 16 px MCU grid, so its inner
# pixels see the same neighbourhood (demosaic 5×5, JPEG 16×16 blocks + chroma upsampling) as the full frame
NEIGHBOURHOOD_MARGIN_PX = 16


class EffectsError(ValueError):
    """A camera-effects setting that cannot be used."""


@dataclass(frozen=True)
class CameraEffects:
    """What a simulated camera adds to the clean linear render (all off by default).

    ``response`` the camera's response (a :class:`~labctl.vision.response.Response`, or a driver
    file's spec, parsed on construction; None or linear: none); ``shadows`` the fraction of the
    direct light the object blocks on the table (0 off … 1 only ambient light in the shadow);
    ``specular`` Blinn-Phong strength (fraction of
    full scale at n·h = 1) and ``shininess`` its exponent; ``texture`` table texture contrast (1:
    the default breadboard); ``bayer`` demosaicing (None, ``bilinear``, ``vng``, ``ea``);
    ``jpeg_quality`` 1–100 or None; ``defocus_px`` a lens out of focus, the blur disc's radius (px; 0: in
    focus), a pillbox on the linear frame before the mosaic (after the sensor noise: a simplification that
    smooths the noise a little).
    """

    response: Response | str | float | list[float] | None = None
    shadows: float = 0.0
    specular: float = 0.0
    shininess: float = 40.0
    texture: float = 1.0
    bayer: str | None = None
    jpeg_quality: int | None = None
    defocus_px: float = 0.0
    _enc: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        if not 0.0 <= self.shadows <= 1.0:
            raise EffectsError(f"shadows must be within 0–1, got {self.shadows}")
        if not (np.isfinite(self.specular) and self.specular >= 0):
            raise EffectsError(f"specular must be ≥ 0, got {self.specular}")
        if not (np.isfinite(self.shininess) and self.shininess >= 1):
            raise EffectsError(f"shininess must be ≥ 1, got {self.shininess}")
        if not (np.isfinite(self.texture) and 0 <= self.texture <= 4):
            raise EffectsError(f"texture must be within 0–4, got {self.texture}")
        if self.bayer is not None and self.bayer not in BAYER_CODES:
            raise EffectsError(f"bayer must be one of {sorted(BAYER_CODES)} or null, got {self.bayer!r}")
        if self.jpeg_quality is not None and not 1 <= int(self.jpeg_quality) <= 100:
            raise EffectsError(f"jpeg_quality must be within 1–100, got {self.jpeg_quality}")
        if not (np.isfinite(self.defocus_px) and 0.0 <= self.defocus_px <= 8.0):
            raise EffectsError(f"defocus_px must be within 0–8, got {self.defocus_px}")
        r = self.response
        if r is not None and not isinstance(r, Response):
            r = parse_response(r)
            object.__setattr__(self, "response", r)
        if r is not None and not r.is_linear:
            object.__setattr__(self, "_enc", encoding_lut(r))

    @property
    def any(self) -> bool:
        """True when any effect is on (else the renderer takes its plain path, bit-identical)."""
        return bool(self._enc is not None or self.shadows > 0 or self.specular > 0 or self.texture != 1.0
                    or self.bayer or self.jpeg_quality or self.defocus_px > 0)

    @property
    def needs_neighbourhood(self) -> bool:
        """Effects whose output pixel depends on its neighbours (a window must be rendered larger)."""
        return bool(self.bayer or self.jpeg_quality or self.defocus_px > 0)

    @property
    def encode_lut(self) -> np.ndarray | None:
        """uint8 LUT from linear grey level to the camera's code (None for a linear camera)."""
        return self._enc


def encoding_lut(response: Response) -> np.ndarray:
    """The camera's forward response as a 256-entry uint8 LUT: linear grey level v (0–255) →
    the code c whose linear value ``response.lut[c]`` is nearest along the curve (the inverse of
    the piecewise-linear code → radiance map, rounded)."""
    x = np.arange(256) / 255.0
    codes = np.interp(x, response.lut.astype(float), np.arange(256, dtype=float))
    return np.clip(np.round(codes), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------------------
# scene effects
# ------------------------------------------------------------------------------------------
def blinn_phong(normals: np.ndarray, points: np.ndarray, eye: np.ndarray, light: np.ndarray,
                strength: float, shininess: float) -> np.ndarray:
    """Specular term (grey levels, 0–255 scale) of flat surfaces: ``255·ks·max(n·h, 0)^s`` where
    n·l > 0, h = (l + v)/|l + v|, v from each surface point to the eye.

    ``normals`` (N, 3) unit, ``points`` (N, 3) mm (face centroids or marker centres), ``eye`` (3,)
    mm, ``light`` (3,) unit direction towards the light; all in one frame."""
    v = np.asarray(eye, float)[None, :] - np.asarray(points, float)
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    h = v + np.asarray(light, float)[None, :]
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    nh = np.clip(np.einsum("ij,ij->i", normals, h), 0.0, 1.0)
    lit = (normals @ np.asarray(light, float)) > 0
    return np.where(lit, 255.0 * strength * nh ** shininess, 0.0)


def shadow_polygons_w(corners_w: np.ndarray, light_w: np.ndarray) -> np.ndarray:
    """Triangles (K, 3, 2) in the table plane z = 0 (mm, W) that make up the cast shadow of a closed
    mesh lit from direction ``light_w`` (unit, towards the light, z > 0): its light-facing
    triangles projected along the light, ``p − (p_z / l_z)·l``. Their union is the shadow."""
    c = np.asarray(corners_w, float)
    if len(c) == 0 or light_w[2] <= 1e-6:
        return np.zeros((0, 3, 2))
    n = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    c = c[(n @ light_w) > 0]
    c = c[(c[:, :, 2] > 1e-6).any(axis=1)]  # a face lying on the table casts nothing
    p = c[:, :, :2] - (c[:, :, 2:3] / light_w[2]) * light_w[None, None, :2]
    return p


@dataclass(frozen=True)
class ShadowMask:
    """The shadow in table millimetres: ``mask`` float32 (rows along +y), coverage 0–1; cell (i, j)
    is centred at ``(x0 + j·res, y0 + i·res)`` mm of W."""

    mask: np.ndarray
    x0: float
    y0: float
    res: float

    def sample(self, wx: np.ndarray, wy: np.ndarray) -> np.ndarray:
        """Coverage (float32) at W points (mm), bilinear; 0 outside."""
        mx = ((wx - self.x0) / self.res).astype(np.float32)
        my = ((wy - self.y0) / self.res).astype(np.float32)
        return cv2.remap(self.mask, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of the grid's first and last cell centres on the table (mm)."""
        h, w = self.mask.shape
        return self.x0, self.y0, self.x0 + (w - 1) * self.res, self.y0 + (h - 1) * self.res


def shadow_mask(triangles_xy: np.ndarray, *, penumbra_mm: float = PENUMBRA_MM,
                grid_mm: float = _SHADOW_GRID_MM) -> ShadowMask | None:
    """Rasterise the union of shadow triangles (K, 3, 2) mm into a :class:`ShadowMask` (each
    triangle filled anti-aliased, sub-cell exact to 1/16 cell; blurred by the penumbra).

    Rasterised relative to the first vertex and cached: an object riding the table casts the same
    shadow, translated, every frame, and the mask does not depend on where it was first drawn."""
    if len(triangles_xy) == 0:
        return None
    origin = triangles_xy[0, 0].copy()
    rel = triangles_xy - origin
    key = (np.round(rel, 9).tobytes(), float(penumbra_mm), float(grid_mm))
    hit = _shadow_cache.get(key)
    if hit is None:
        hit = _rasterise_shadow(rel, penumbra_mm, grid_mm)
        if len(_shadow_cache) >= 32:
            _shadow_cache.clear()
        _shadow_cache[key] = hit
    m, lo, res = hit
    return ShadowMask(m, float(lo[0] + origin[0]), float(lo[1] + origin[1]), res)


_shadow_cache: dict[tuple, tuple[np.ndarray, np.ndarray, float]] = {}


def _rasterise_shadow(tris: np.ndarray, penumbra_mm: float, grid_mm: float):
    pad = 3.0 * penumbra_mm + 2.0 * grid_mm
    lo = tris.reshape(-1, 2).min(axis=0) - pad
    hi = tris.reshape(-1, 2).max(axis=0) + pad
    res = max(grid_mm, float((hi - lo).max()) / 1500.0)  # keep the grid bounded for large objects
    w, h = (np.ceil((hi - lo) / res).astype(int) + 1)
    mask = np.zeros((int(h), int(w)), np.uint8)
    pts = np.round((tris - lo) / res * 16.0).astype(np.int32)
    for tri in pts:
        cv2.fillConvexPoly(mask, tri, 255, lineType=cv2.LINE_AA, shift=4)
    m: np.ndarray = mask.astype(np.float32) * np.float32(1.0 / 255.0)
    if penumbra_mm > 0:
        m = cv2.GaussianBlur(m, (0, 0), penumbra_mm / 2.0 / res)
    m.flags.writeable = False
    return m, lo, res


def shadow_factor(light_w: np.ndarray, ambient: float, strength: float) -> float:
    """Table radiance in full shadow ÷ lit (Lambert, table normal +z): ambient plus the unblocked
    share of the direct light, over ambient plus all of it."""
    direct = (1.0 - ambient) * max(float(light_w[2]), 0.0)
    return (ambient + direct * (1.0 - strength)) / (ambient + direct)


# ------------------------------------------------------------------------------------------
# the camera pipeline on a noisy linear frame
# ------------------------------------------------------------------------------------------
def bayer_mosaic(image: np.ndarray) -> np.ndarray:
    """The RGGB raw frame a colour sensor records of a BGR image (H×W uint8 → H×W uint8); the
    pattern is anchored at pixel (0, 0), so a crop must start on even coordinates to match."""
    raw = np.empty(image.shape[:2], image.dtype)
    raw[0::2, 0::2] = image[0::2, 0::2, 2]
    raw[0::2, 1::2] = image[0::2, 1::2, 1]
    raw[1::2, 0::2] = image[1::2, 0::2, 1]
    raw[1::2, 1::2] = image[1::2, 1::2, 0]
    return raw


def pillbox_kernel(radius_px: float, supersample: int = 8) -> np.ndarray:
    """A defocused lens's point-spread function: a uniform disc of ``radius_px``, each tap its pixel's
    covered area (``supersample``² sub-samples), normalised to sum 1 (float32, (2⌈r⌉+1)²)."""
    r = float(radius_px)
    n = int(math.ceil(r))
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    ax = (np.arange(-n, n + 1)[:, None] + sub[None, :]).ravel()
    inside = (ax[:, None] ** 2 + ax[None, :] ** 2 <= r * r).astype(np.float64)
    k = inside.reshape(2 * n + 1, supersample, 2 * n + 1, supersample).sum(axis=(1, 3))
    return (k / k.sum()).astype(np.float32)


def camera_pipeline(image: np.ndarray, fx: CameraEffects) -> np.ndarray:
    """Noisy linear BGR uint8 frame → what the camera delivers: Bayer mosaic and demosaic (in the
    linear domain, as a camera's ISP does), the response curve, then JPEG encode/decode."""
    out = image
    if fx.defocus_px > 0:
        out = cv2.filter2D(out, -1, pillbox_kernel(fx.defocus_px), borderType=cv2.BORDER_REFLECT)
    if fx.bayer:
        out = cv2.cvtColor(bayer_mosaic(out), BAYER_CODES[fx.bayer])
    if fx.encode_lut is not None:
        out = cv2.LUT(out, fx.encode_lut)
    if fx.jpeg_quality:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(fx.jpeg_quality)])
        if not ok:
            raise EffectsError("JPEG encoding failed")
        out = cast(np.ndarray, cv2.imdecode(buf, cv2.IMREAD_COLOR))  # a JPEG just encoded decodes
    return out


def expand_window(window: tuple[int, int, int, int], width: int, height: int) -> tuple[int, int, int, int]:
    """The render window for a ``window`` (x0, y0, x1, y1) when effects read neighbours: grown by
    :data:`NEIGHBOURHOOD_MARGIN_PX` and snapped outwards to the 16 px JPEG MCU grid (also even:
    the Bayer phase), clipped to the frame."""
    x0, y0, x1, y1 = window
    m, g = NEIGHBOURHOOD_MARGIN_PX, 16
    return (max((x0 - m) // g * g, 0), max((y0 - m) // g * g, 0),
            min(-(-(x1 + m) // g) * g, width), min(-(-(y1 + m) // g) * g, height))


# ------------------------------------------------------------------------------------------
# from the lab
# ------------------------------------------------------------------------------------------
def effects_from_lab(lab: Lab, camera_cfg: CameraConfig) -> CameraEffects | None:
    """The effects of a simulated camera: lab.yaml's ``sim.camera`` settings (preset + overrides,
    :class:`labctl.config.lab.SimCameraConfig`) and the camera driver file's ``response``
    (the curve vision linearises with), unless ``sim.camera.response`` gives the simulated sensor another
    one (a lab whose driver file is wrong). None when nothing is on."""
    settings = lab.config.sim.camera.settings()
    sensor = lab.config.sim.camera.response
    fx = CameraEffects(response=camera_cfg.response if sensor is None else sensor, **settings)
    return fx if fx.any else None
