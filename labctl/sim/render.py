"""A CPU rasteriser for the simulated lab's cameras (numpy + OpenCV, no GPU, no system packages).

Renders what a camera with Tsai's model (pinhole + radial κ1, Tsai 1987 §II) sees of triangle
meshes resting on the table plane z = 0 of the world W:

* **Distortion is exact.** Every output pixel is a *distorted* frame-buffer pixel; its ray is
  ``camera.normalized(pixel)`` (Tsai's undistortion is closed-form), cached per camera. Triangles
  are straight-edged in normalised coordinates, so coverage and depth are tested there.
* **Occlusion by a z-buffer.** Each front-facing triangle is expanded to the pixels of its
  (distorted) bounding box in one vectorised batch; edge functions decide coverage, the
  triangle's plane gives the inverse depth along each pixel's ray, and ``np.maximum.at`` keeps
  the nearest surface per pixel. No painter's sort.
* **Lambert shading** per face from a directional light plus ambient.
* **Markers are true circles** (the paper's premarking, He et al. 1996 §2): per pixel, the ray
  is intersected with the marker plane and the signed distance to the circle (mm) is turned into
  an analytic coverage ``clip(0.5 − d/|∇d|, 0, 1)`` with ``∇d`` in pixels, so the 50 % contour is
  the projected circle to first order (sub-pixel exact); markers only show where their plane is
  the nearest surface.
* **The table** is a dark, textured plane (an optical breadboard: grain, blotches, tapped holes)
  that moves with the NC table; objects are light grey so silhouettes separate.
* **Anti-aliased silhouettes** (``supersample`` > 1): pixels on a boundary between surfaces are
  resolved with ``s×s`` sub-samples against the triangles of their 3×3 neighbourhood.
* **Sensor noise** (Gaussian, σ in grey levels, seeded from the caller's generator) and optional
  **motion blur** (the mean of sub-frames over the exposure).

Frames: vertices and markers in W (mm); ``T_w_c`` maps camera to world. Pixel (u, v) has its
centre at integer coordinates, as in :class:`labctl.geometry.CameraModel`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import cast

import cv2
import numpy as np

from ..fsutil import cached_arrays, file_digest
from ..geometry import CameraModel, invert
from ..geometry import camera as _camera_module
from .effects import (
    CameraEffects,
    blinn_phong,
    camera_pipeline,
    expand_window,
    shadow_factor,
    shadow_mask,
    shadow_polygons_w,
)

_NEAR_MM = 1.0
_EDGE_EPS = 1e-7  # normalised units (~0.0002 px): closes cracks on shared edges
_AMBIENT = 0.55  # faces turned from the light stay well above the dark table (silhouettes)
DEFAULT_LIGHT_DIR_W = (0.35, -0.25, 1.0)  # from the scene towards the light


class RenderError(ValueError):
    """Bad input to the renderer (non-finite pose, malformed mesh, wrong shapes)."""


@dataclass
class MarkerDisc:
    """A flat circular marker: centre (3,) mm, outward unit normal (3,), radius mm, BGR colour."""

    center: np.ndarray
    normal: np.ndarray
    radius: float
    colour_bgr: tuple = (40, 40, 200)


@dataclass
class Mesh:
    """A triangle mesh in the WORLD frame (mm) with outward (counter-clockwise) winding."""

    vertices: np.ndarray
    faces: np.ndarray
    colour_bgr: tuple = (185, 185, 185)
    markers: list[MarkerDisc] = field(default_factory=list)


@dataclass(frozen=True)
class TableSurface:
    """The table top: the plane z = 0 of W, textured; ``origin_w`` (mm) moves the texture with the table."""

    origin_w: tuple[float, float] = (0.0, 0.0)
    brightness: float = 1.0
    texture_seed: int = 7


@dataclass
class RenderResult:
    """A rendered frame and, on request, its ground truth.

    ``image`` H×W×3 uint8 BGR; ``mask`` H×W bool, pixels whose nearest surface is a mesh;
    ``depth`` H×W float32, distance along the optical axis (mm, inf where nothing is hit);
    ``markers_c`` the true (centre, unit normal) of every marker in the camera frame, in mesh and
    marker order; ``marker_pixels`` how many pixels of each marker are visible (coverage ≥ 0.5).
    """

    image: np.ndarray
    mask: np.ndarray | None = None
    depth: np.ndarray | None = None
    markers_c: list[tuple[np.ndarray, np.ndarray]] | None = None
    marker_pixels: list[int] | None = None


# --------------------------------------------------------------------------------------------
# caches: per-camera pixel rays, per-pose table geometry, the table texture
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _PixelRays:
    nx: np.ndarray  # (H*W,) float32 normalised x/z of each pixel's ray
    ny: np.ndarray
    nx64: np.ndarray  # (H, W) float64, for the markers' sub-pixel geometry
    ny64: np.ndarray
    jac: np.ndarray  # (4, H*W) float32 d(nx, ny)/d(u, v): nx_u, ny_u, nx_v, ny_v, for sub-pixel samples


# rays (and table geometry) of a window camera (:func:`_window_camera`): slices of the full camera's, so
# a window renders bit-for-bit the pixels the full frame would have there; keyed by the window camera
_window_rays: dict[CameraModel, _PixelRays] = {}


def _pixel_rays(camera: CameraModel) -> _PixelRays:
    rays = _window_rays.get(camera)
    return rays if rays is not None else _full_pixel_rays(camera)


_RAY_FIELDS = ("nx", "ny", "nx64", "ny64", "jac")


@lru_cache(maxsize=8)
def _full_pixel_rays(camera: CameraModel) -> _PixelRays:
    # ~0.4 s a camera (the distortion inverted at every pixel), on every start of a simulated lab: read from
    # the disk cache, keyed by the camera's fields and the code that computes them, so bit for bit the same
    key = ("pixel_rays", dataclasses.astuple(camera), np.__version__,
           file_digest(__file__, cast(str, _camera_module.__file__)))
    def compute() -> dict:
        rays = _compute_pixel_rays(camera)
        return {k: getattr(rays, k) for k in _RAY_FIELDS}

    return _PixelRays(**cached_arrays("render", key, _RAY_FIELDS, compute))


def _compute_pixel_rays(camera: CameraModel) -> _PixelRays:
    u, v = np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float))
    px = np.stack([u, v], axis=-1)
    n = camera.normalized(px)
    d_u = camera.normalized(px + [0.5, 0.0]) - camera.normalized(px - [0.5, 0.0])
    d_v = camera.normalized(px + [0.0, 0.5]) - camera.normalized(px - [0.0, 0.5])
    jac = np.stack([d_u[..., 0].ravel(), d_u[..., 1].ravel(), d_v[..., 0].ravel(), d_v[..., 1].ravel()])
    return _PixelRays(
        nx=np.ascontiguousarray(n[..., 0].ravel(), dtype=np.float32),
        ny=np.ascontiguousarray(n[..., 1].ravel(), dtype=np.float32),
        nx64=np.ascontiguousarray(n[..., 0]),
        ny64=np.ascontiguousarray(n[..., 1]),
        jac=np.ascontiguousarray(jac, dtype=np.float32),
    )


_TEXTURE_MM_PER_TEXEL = 1.0
_TEXTURE_SIZE = 1024  # texels; the texture tiles (periodic) so the plane is endless


@lru_cache(maxsize=4)
def _table_grey(seed: int) -> np.ndarray:
    """A dark breadboard texture, (2N, 2N) float32 grey levels, 1 mm per texel, periodic with period N."""
    # ~1 s of FFTs on every start of a simulated lab: read from the disk cache, keyed by the seed and this
    # file (the code that draws it), so bit for bit the texture drawn below
    key = ("table_grey", seed, _TEXTURE_SIZE, _TEXTURE_MM_PER_TEXEL, np.__version__, file_digest(__file__))
    return cached_arrays("render", key, ("grey",), lambda: {"grey": _draw_table_grey(seed)})["grey"]


def _draw_table_grey(seed: int) -> np.ndarray:
    n = _TEXTURE_SIZE
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(n)
    fr = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)

    def band(sigma_texels: float) -> np.ndarray:
        white = rng.standard_normal((n, n))
        smooth = np.real(np.fft.ifft2(np.fft.fft2(white) * np.exp(-0.5 * (fr * 2 * np.pi * sigma_texels) ** 2)))
        return smooth / (smooth.std() + 1e-12)

    grey = 52.0 + 7.0 * band(40.0) + 4.0 * band(3.0) + 2.5 * rng.standard_normal((n, n))
    # tapped holes every 25 mm, 3 mm radius: darker dots
    yy, xx = np.mgrid[0:n, 0:n] * _TEXTURE_MM_PER_TEXEL
    d = np.hypot((xx + 12.5) % 25.0 - 12.5, (yy + 12.5) % 25.0 - 12.5)
    grey = np.clip(grey - 22.0 * np.clip(3.5 - d, 0.0, 1.0), 8.0, 110.0)
    # two periods each way, centred on the table's zero: lookups never wrap (BORDER_REFLECT is faster)
    return np.tile(grey, (2, 2)).astype(np.float32)


@lru_cache(maxsize=8)
def _table_texture(seed: int, shade_milli: int, contrast_milli: int = 1000) -> np.ndarray:
    """The texture lit (shade in thousandths), uint8; ``contrast_milli`` scales its deviations from
    its mean (thousandths; 1000: the texture as drawn)."""
    grey = _table_grey(seed)
    if contrast_milli != 1000:
        mean = np.float32(grey.mean())
        grey = np.clip(mean + (grey - mean) * np.float32(contrast_milli / 1000.0), 0.0, 255.0)
    return np.ascontiguousarray(np.clip(np.round(grey * (shade_milli / 1000.0)), 0, 255).astype(np.uint8))


@dataclass(frozen=True)
class _TableGeometry:
    map_x: np.ndarray  # (H, W) float32 texture column of each pixel's hit (before the table offset)
    map_y: np.ndarray
    invz: np.ndarray  # (H*W,) float32 1/depth of the plane along each ray (0: ray misses the plane)
    hit: np.ndarray  # (H, W) bool
    all_hit: bool


_table_cache: dict[tuple, _TableGeometry] = {}


def _table_geometry(camera: CameraModel, T_w_c: np.ndarray) -> _TableGeometry:
    if camera in _window_parent:  # a window: a slice of the full camera's geometry (not cached: windows move)
        parent, (x0, y0, x1, y1) = _window_parent[camera]
        full = _table_geometry(parent, T_w_c)
        hit_mask = full.hit[y0:y1, x0:x1]
        return _TableGeometry(
            map_x=full.map_x[y0:y1, x0:x1], map_y=full.map_y[y0:y1, x0:x1],
            invz=full.invz.reshape(parent.height, parent.width)[y0:y1, x0:x1].ravel(),
            hit=hit_mask, all_hit=bool(full.all_hit or hit_mask.all()))
    key = (camera, T_w_c.tobytes())
    hit = _table_cache.get(key)
    if hit is not None:
        return hit
    rays = _pixel_rays(camera)
    R, o = T_w_c[:3, :3], T_w_c[:3, 3]
    x, y = rays.nx64, rays.ny64
    dz = R[2, 0] * x + R[2, 1] * y + R[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o[2] / dz  # depth along the optical axis where the ray meets z = 0
    hit_mask = np.isfinite(s) & (s > _NEAR_MM)
    s = np.where(hit_mask, s, 0.0)
    wx = o[0] + s * (R[0, 0] * x + R[0, 1] * y + R[0, 2])
    wy = o[1] + s * (R[1, 0] * x + R[1, 1] * y + R[1, 2])
    # texture rows run along −y of W so the texture reads like a map from above
    geometry = _TableGeometry(
        map_x=(wx / _TEXTURE_MM_PER_TEXEL + _TEXTURE_SIZE).astype(np.float32),
        map_y=(-wy / _TEXTURE_MM_PER_TEXEL + _TEXTURE_SIZE).astype(np.float32),
        invz=np.where(hit_mask, 1.0 / np.where(hit_mask, s, 1.0), 0.0).astype(np.float32).ravel(),
        hit=hit_mask,
        all_hit=bool(hit_mask.all()),
    )
    if len(_table_cache) > 16:
        _table_cache.clear()
    _table_cache[key] = geometry
    return geometry


_window_parent: dict[CameraModel, tuple[CameraModel, tuple[int, int, int, int]]] = {}


def _window_camera(camera: CameraModel, roi: tuple[int, int, int, int]) -> CameraModel:
    """The camera that sees only pixels [x0, x1) × [y0, y1) of ``camera`` (same Tsai model, shifted
    centre), with its rays and table geometry registered as slices of the full camera's."""
    x0, y0, x1, y1 = roi
    win = camera.with_(cx=camera.cx - x0, cy=camera.cy - y0, width=x1 - x0, height=y1 - y0)
    if win not in _window_rays:
        full = _full_pixel_rays(camera)
        sl = (slice(y0, y1), slice(x0, x1))
        jac = full.jac.reshape(4, camera.height, camera.width)[:, y0:y1, x0:x1].reshape(4, -1)
        if len(_window_rays) > 256:  # windows follow a moving object: keep the registry bounded
            _window_rays.clear()
            _window_parent.clear()
        _window_rays[win] = _PixelRays(
            nx=np.ascontiguousarray(full.nx.reshape(camera.height, camera.width)[sl]).ravel(),
            ny=np.ascontiguousarray(full.ny.reshape(camera.height, camera.width)[sl]).ravel(),
            nx64=np.ascontiguousarray(full.nx64[sl]), ny64=np.ascontiguousarray(full.ny64[sl]),
            jac=np.ascontiguousarray(jac))
        _window_parent[win] = (camera, (x0, y0, x1, y1))
    return win


_NOISE_MARGIN = 256


@lru_cache(maxsize=4)
def _noise_bank(height: int, width: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian sensor noise (grey levels, rounded) larger than a frame, as its positive and
    negative parts (uint8); each frame adds a random window: ``clip(clip(I + n⁺) − n⁻)`` equals
    ``clip(I + n)`` because only one part is non-zero per pixel.

    Drawing a fresh 640×480×3 field costs more than the rest of a frame; a random window into
    a fixed field (256² offsets) keeps the per-pixel statistics and varies from frame to frame.
    The field itself (~0.1–0.2 s CPU on every start of a simulated lab) comes from the disk cache, keyed by
    its inputs and this file, so bit for bit the field drawn here.
    """
    key = ("noise_bank", height, width, repr(float(sigma)), np.__version__, file_digest(__file__))
    out = cached_arrays("render", key, ("pos", "neg"), lambda: dict(zip(("pos", "neg"),
                                                                        _draw_noise_bank(height, width, sigma))))
    return out["pos"], out["neg"]


def _draw_noise_bank(height: int, width: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(20240611)
    shape = (height + _NOISE_MARGIN, width + _NOISE_MARGIN, 3)
    n = np.round(rng.standard_normal(shape) * sigma)
    return (np.clip(n, 0, 255).astype(np.uint8), np.clip(-n, 0, 255).astype(np.uint8))


# --------------------------------------------------------------------------------------------
# the core rasteriser
# --------------------------------------------------------------------------------------------
@dataclass
class _Layer:
    colour: np.ndarray  # (H, W, 3) uint8, noiseless
    tri_id: np.ndarray  # (H*W,) int32, -1 where no triangle is nearest
    invz: np.ndarray  # (H*W,) float32 nearest surface's inverse depth (0: nothing)
    marker_pixels: list[int]


def _check_pose(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise RenderError("camera pose T_w_c must be a finite 4×4 matrix")
    return T


def _gather_meshes(meshes: Sequence[Mesh]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Concatenate meshes: triangle corners (M, 3, 3) in W, per-triangle base colour (M, 3)."""
    corners, colours = [], []
    for m in meshes:
        V = np.asarray(m.vertices, dtype=float)
        F = np.asarray(m.faces)
        if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
            raise RenderError("mesh vertices must be (N, 3) and faces (M, 3)")
        if len(F) == 0:
            continue
        if not np.all(np.isfinite(V)) or F.min() < 0 or F.max() >= len(V):
            raise RenderError("mesh has non-finite vertices or face indices out of range")
        corners.append(V[F])
        colours.append(np.broadcast_to(np.asarray(m.colour_bgr, dtype=np.float32), (len(F), 3)))
    if not corners:
        return np.zeros((0, 3, 3)), np.zeros((0, 3), np.float32), np.zeros(0, int)
    return np.concatenate(corners), np.concatenate(colours), np.zeros(0, int)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (…, 3) arrays: the same products and differences as ``np.cross``
    (bit-identical) without its axis juggling, which costs more than the arithmetic for small meshes."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _lambert(normals_w: np.ndarray, light_w: np.ndarray) -> np.ndarray:
    return _AMBIENT + (1.0 - _AMBIENT) * np.clip(normals_w @ light_w, 0.0, 1.0)


def _triangle_setup(camera: CameraModel, Pc: np.ndarray):
    """Front-facing triangles' coefficient rows and distorted-pixel bounding boxes.

    ``Pc`` (M, 3, 3) corners in the camera frame. Returns (index of kept triangles,
    coefficients (K, 4, 3) float32 of [edge0, edge1, edge2, inverse depth] as linear functions
    of the normalised ray (x, y, 1), integer boxes (K, 4) x0, y0, x1, y1).
    """
    A, B, C = Pc[:, 0], Pc[:, 1], Pc[:, 2]
    n = _cross(B - A, C - A)
    d = np.einsum("ij,ij->i", n, A)
    keep = (d < 0) & (Pc[:, :, 2].min(axis=1) > _NEAR_MM)  # front-facing, in front of the camera
    idx = np.nonzero(keep)[0]
    if len(idx) == 0:
        return idx, np.zeros((0, 4, 3), np.float32), np.zeros((0, 4), int)
    Pc, n, d = Pc[idx], n[idx], d[idx]
    q = Pc[:, :, :2] / Pc[:, :, 2:3]  # normalised image corners (K, 3, 2)
    coef = np.empty((len(idx), 4, 3))
    area = (q[:, 1, 0] - q[:, 0, 0]) * (q[:, 2, 1] - q[:, 0, 1]) - (q[:, 1, 1] - q[:, 0, 1]) * (q[:, 2, 0] - q[:, 0, 0])
    sign = np.sign(area)
    for e in range(3):
        p0, p1 = q[:, e], q[:, (e + 1) % 3]
        ex, ey = p1[:, 0] - p0[:, 0], p1[:, 1] - p0[:, 1]
        length = np.hypot(ex, ey)
        length = np.where(length > 0, length, 1.0)
        s = sign / length
        coef[:, e, 0] = -ey * s
        coef[:, e, 1] = ex * s
        coef[:, e, 2] = (ey * p0[:, 0] - ex * p0[:, 1]) * s
    coef[:, 3, :] = n / d[:, None]  # 1/z = n·(x, y, 1) / (n·A)
    # bounding box in distorted pixels from corners and edge points (edges bow under distortion)
    if camera.kappa1 == 0.0:  # straight edges: the corners bound the triangle
        pts = Pc
    else:
        ts = np.array([0.0, 0.25, 0.5, 0.75])
        pts = np.concatenate([Pc[:, e:e + 1] * (1 - ts)[None, :, None] + Pc[:, (e + 1) % 3:(e + 1) % 3 + 1]
                              * ts[None, :, None] for e in range(3)], axis=1)
    px = camera.project(pts)
    lo = np.floor(np.nanmin(px, axis=1)) - 1
    hi = np.ceil(np.nanmax(px, axis=1)) + 1
    box = np.empty((len(idx), 4))
    box[:, 0] = np.clip(lo[:, 0], 0, camera.width - 1)
    box[:, 1] = np.clip(lo[:, 1], 0, camera.height - 1)
    box[:, 2] = np.clip(hi[:, 0], -1, camera.width - 1)
    box[:, 3] = np.clip(hi[:, 1], -1, camera.height - 1)
    empty = (area == 0) | (hi[:, 0] < 0) | (hi[:, 1] < 0) | (lo[:, 0] > camera.width - 1) \
        | (lo[:, 1] > camera.height - 1) | ~np.all(np.isfinite(px), axis=(1, 2))
    box[empty] = [0, 0, -1, -1]
    return idx, coef.astype(np.float32), box.astype(np.int64)


def _row_spans(camera: CameraModel, coef: np.ndarray, box: np.ndarray):
    """Candidate pixel spans per (triangle, image row): a tight superset of each triangle's pixels.

    Along one row of its box, each edge function is nearly linear in the column (exactly so
    without distortion); it is evaluated at the row's two ends and middle, the covered interval
    solved from the chord and widened by the chord's deviation (distortion bowing) plus 1.5 px.
    Returns (triangle index, row, first column, count) per row, int arrays.
    """
    W = camera.width
    rays = _pixel_rays(camera)
    h = np.maximum(box[:, 3] - box[:, 1] + 1, 0)
    n_rows = int(h.sum())
    tri = np.repeat(np.arange(len(coef)), h)
    row = np.repeat(box[:, 1], h) + (np.arange(n_rows) - np.repeat(np.cumsum(h) - h, h))
    xl, xr = box[tri, 0], box[tri, 2]
    xm = (xl + xr) // 2
    c = coef[tri, :3, :]  # (R, 3 edges, 3)

    def edge_at(col):
        p = row * W + col
        return c[:, :, 0] * rays.nx[p][:, None] + c[:, :, 1] * rays.ny[p][:, None] + c[:, :, 2]

    el, er, em = edge_at(xl), edge_at(xr), edge_at(xm)
    width = np.maximum(xr - xl, 1).astype(np.float64)[:, None]
    slope = (er - el) / width  # per pixel
    tm = ((xm - xl)[:, None] / width)
    bow = np.abs(em - (el + tm * (er - el)))
    lo = np.full(el.shape, -np.inf)
    hi = np.full(el.shape, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        root = xl[:, None] - el / slope  # column where the chord crosses zero
        pad = 1.5 + np.where(slope != 0, bow / np.abs(slope), 0.0)
    pos, neg = slope > 0, slope < 0
    lo = np.where(pos, root - pad, lo)
    hi = np.where(neg, root + pad, hi)
    flat_out = (slope == 0) & (np.maximum(el, er) + bow < -_EDGE_EPS)
    first = np.maximum(np.ceil(np.max(lo, axis=1)), xl)
    last = np.minimum(np.floor(np.min(hi, axis=1)), xr)
    count = np.where(flat_out.any(axis=1), 0, np.maximum(last - first + 1, 0))
    keep = count > 0
    return tri[keep], row[keep], first[keep].astype(np.int64), count[keep].astype(np.int64)


def _rasterise(camera: CameraModel, coef: np.ndarray, box: np.ndarray, invz: np.ndarray):
    """Z-buffer the triangles (``invz`` updated in place).

    Returns (pixel index, triangle index) of every pixel a triangle wins, so callers touch only
    those pixels.
    """
    W = camera.width
    tri_r, row, first, count = _row_spans(camera, coef, box)
    total = int(count.sum())
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    start = np.cumsum(count) - count
    pix = np.arange(total, dtype=np.int64) + np.repeat(row * W + first - start, count)
    tri = np.repeat(tri_r, count)
    rays = _pixel_rays(camera)
    x = rays.nx[pix]
    y = rays.ny[pix]
    g = coef.reshape(len(coef), 12).T[:, tri]  # (12, total) contiguous rows
    inside = g[0] * x + g[1] * y + g[2] >= -_EDGE_EPS
    inside &= g[3] * x + g[4] * y + g[5] >= -_EDGE_EPS
    inside &= g[6] * x + g[7] * y + g[8] >= -_EDGE_EPS
    iz = g[9] * x + g[10] * y + g[11]
    inside &= iz > 0
    pix, tri, iz = pix[inside], tri[inside], iz[inside]
    np.maximum.at(invz, pix, iz)
    win = iz >= invz[pix]
    return pix[win], tri[win]


def _central_gradient_norm(d: np.ndarray) -> np.ndarray:
    """|∇d| per pixel by central differences (one-sided on the border)."""
    gx = np.empty_like(d)
    gy = np.empty_like(d)
    gx[:, 1:-1] = (d[:, 2:] - d[:, :-2]) * 0.5
    gx[:, 0] = d[:, 1] - d[:, 0]
    gx[:, -1] = d[:, -1] - d[:, -2]
    gy[1:-1] = (d[2:] - d[:-2]) * 0.5
    gy[0] = d[1] - d[0]
    gy[-1] = d[-1] - d[-2]
    return np.sqrt(gx * gx + gy * gy)


_RING = np.linspace(0, 2 * np.pi, 48, endpoint=False)


def _marker_pass(camera: CameraModel, T_c_w: np.ndarray, light_w: np.ndarray, markers: list[MarkerDisc],
                 colour: np.ndarray, invz: np.ndarray, fx: CameraEffects | None = None) -> list[int]:
    """Blend each marker disc into ``colour`` (H×W×3 uint8, in place) with analytic edge coverage.

    Per pixel of the disc's box: intersect the pixel's ray with the marker plane, take the signed
    distance d (mm) of the hit from the circle, and cover ``clip(0.5 − d/|∇d|, 0, 1)`` with ∇d in
    pixels; only where the marker plane is the nearest surface (within 0.5 mm or 0.1 %).
    """
    rays = _pixel_rays(camera)
    H, W = camera.height, camera.width
    zbuf = invz.reshape(H, W)
    counts = [0] * len(markers)
    if not markers:
        return counts
    R, t = T_c_w[:3, :3], T_c_w[:3, 3]
    centres = np.array([np.asarray(mk.center, dtype=float) for mk in markers]) @ R.T + t
    normals_w = np.array([np.asarray(mk.normal, dtype=float) for mk in markers])
    normals_w /= np.linalg.norm(normals_w, axis=1, keepdims=True)
    normals = normals_w @ R.T
    radii = np.array([float(mk.radius) for mk in markers])
    facing = (centres[:, 2] > _NEAR_MM + radii) & (np.einsum("ij,ij->i", normals, centres) < 0)
    idx = np.nonzero(facing)[0]
    if len(idx) == 0:
        return counts
    # disc boundaries → pixel boxes, all markers in one projection
    helper = np.where(np.abs(normals[idx, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = _cross(normals[idx], np.broadcast_to(helper, normals[idx].shape))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = _cross(normals[idx], e1)
    ring = (centres[idx, None, :] + radii[idx, None, None]
            * (np.cos(_RING)[None, :, None] * e1[:, None, :] + np.sin(_RING)[None, :, None] * e2[:, None, :]))
    ring_px = camera.project(ring)
    shades = _lambert(normals_w[idx], light_w)
    spec = None
    if fx is not None and fx.specular > 0:  # Blinn-Phong at the marker's centre (camera frame: eye at 0)
        spec = blinn_phong(normals[idx], centres[idx], np.zeros(3), R @ light_w, fx.specular, fx.shininess)
    for j, i in enumerate(idx):
        px = ring_px[j]
        if not np.all(np.isfinite(px)):
            continue
        x0 = int(max(np.floor(px[:, 0].min()) - 3, 0))
        y0 = int(max(np.floor(px[:, 1].min()) - 3, 0))
        x1 = int(min(np.ceil(px[:, 0].max()) + 3, W - 1))
        y1 = int(min(np.ceil(px[:, 1].max()) + 3, H - 1))
        if x1 - x0 < 2 or y1 - y0 < 2:
            continue
        c, nrm = centres[i], normals[i]
        x = rays.nx64[y0:y1 + 1, x0:x1 + 1]
        y = rays.ny64[y0:y1 + 1, x0:x1 + 1]
        denom = nrm[0] * x + nrm[1] * y + nrm[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (nrm @ c) / denom
        ok = np.isfinite(z) & (z > _NEAR_MM)
        z = np.where(ok, z, 0.0)
        dist = np.sqrt((z * x - c[0]) ** 2 + (z * y - c[1]) ** 2 + (z - c[2]) ** 2) - radii[i]
        grad = np.maximum(_central_gradient_norm(dist), 1e-9)
        cov = np.clip(0.5 - dist / grad, 0.0, 1.0)
        # visible only where the marker plane is (within tolerance) the nearest surface
        zb = zbuf[y0:y1 + 1, x0:x1 + 1]
        with np.errstate(divide="ignore"):
            z_near = np.where(zb > 0, 1.0 / zb, np.inf)
        cov = np.where(ok & (z <= z_near + np.maximum(0.5, 1e-3 * z)), cov, 0.0).astype(np.float32)
        mcol = np.asarray(markers[i].colour_bgr, dtype=np.float32) * np.float32(shades[j])
        if spec is not None:
            mcol = np.minimum(mcol + np.float32(spec[j]), np.float32(255.0))
        patch = colour[y0:y1 + 1, x0:x1 + 1].astype(np.float32)
        patch += cov[..., None] * (mcol - patch)
        colour[y0:y1 + 1, x0:x1 + 1] = np.round(patch).astype(np.uint8)
        counts[i] = int(np.count_nonzero(cov >= 0.5))
    return counts


def _edge_supersample(camera: CameraModel, s: int, coef: np.ndarray, tri_colour: np.ndarray,
                      colour: np.ndarray, tri_id: np.ndarray, table_roi: np.ndarray, roi: tuple) -> None:
    """Anti-alias boundaries: re-render pixels on an object/table or crease edge with s×s sub-samples.

    Only ``roi`` (rows r0:r1, columns c0:c1; the mesh pixels' box plus one) is scanned;
    ``table_roi`` is the table image there. Each boundary pixel's sub-samples are tested against
    the triangles seen in its 3×3 neighbourhood (nearest wins, as in the z-buffer).
    """
    H, W = camera.height, camera.width
    r0, r1, c0, c1 = roi
    ids = tri_id.reshape(H, W)[r0:r1, c0:c1]
    obj = ids >= 0
    col = colour[r0:r1, c0:c1].astype(np.int16)
    grey = col[..., 0] + col[..., 1] + col[..., 2]
    # boundary: object/table, or two faces whose shades differ visibly
    dh = (obj[:, 1:] != obj[:, :-1]) | (obj[:, 1:] & obj[:, :-1] & (np.abs(grey[:, 1:] - grey[:, :-1]) > 6))
    dv = (obj[1:, :] != obj[:-1, :]) | (obj[1:, :] & obj[:-1, :] & (np.abs(grey[1:, :] - grey[:-1, :]) > 6))
    edge = np.zeros(ids.shape, bool)
    edge[:, 1:] |= dh
    edge[:, :-1] |= dh
    edge[1:, :] |= dv
    edge[:-1, :] |= dv
    ey, ex = np.nonzero(edge)
    if len(ey) == 0:
        return
    bg = table_roi[ey, ex].astype(np.float32)  # (E, 3) the table behind, sampled at the pixel centre
    # candidate surfaces: the ids of the 3×3 neighbourhood (one gather from the padded id image)
    pad = np.pad(ids, 1, constant_values=-1)
    pw = pad.shape[1]
    offsets = np.array([dy * pw + dx for dy in range(3) for dx in range(3)])
    cand = pad.ravel()[(ey * pw + ex)[:, None] + offsets[None, :]]  # (E, 9)
    # distinct candidates first, duplicates and "no triangle" (-1) last; drop all-empty columns
    cand = -np.sort(-cand, axis=1)
    cand[:, 1:][cand[:, 1:] == cand[:, :-1]] = -1
    cand = -np.sort(-cand, axis=1)
    cand = cand[:, : max(int(np.count_nonzero(cand >= 0, axis=1).max()), 1)]
    # sub-sample rays: the pixel's ray plus the local Jacobian times the sub-pixel offset
    # (the distortion's curvature over a third of a pixel is far below float precision here)
    ey, ex = ey + r0, ex + c0
    pix = ey * W + ex
    rays = _pixel_rays(camera)
    off = ((np.arange(s) + 0.5) / s - 0.5).astype(np.float32)
    ou, ov = (a.ravel()[None, :] for a in np.meshgrid(off, off))
    jx_u, jy_u, jx_v, jy_v = (rays.jac[k, pix][:, None] for k in range(4))
    xs = rays.nx[pix][:, None] + jx_u * ou + jx_v * ov  # (E, S)
    ys = rays.ny[pix][:, None] + jy_u * ou + jy_v * ov
    flat = coef.reshape(len(coef), 12)
    best_iz = np.full(xs.shape, -np.inf, np.float32)
    best_tri = np.full(xs.shape, -1, np.int64)
    for j in range(cand.shape[1]):  # loop over the distinct candidates: no reductions over tiny axes
        t = cand[:, j]
        g = flat[np.maximum(t, 0)].T[:, :, None]  # (12, E, 1)
        ok = g[0] * xs + g[1] * ys + g[2] >= -_EDGE_EPS
        ok &= g[3] * xs + g[4] * ys + g[5] >= -_EDGE_EPS
        ok &= g[6] * xs + g[7] * ys + g[8] >= -_EDGE_EPS
        iz = g[9] * xs + g[10] * ys + g[11]
        ok &= (iz > 0) & (iz > best_iz) & (t >= 0)[:, None]
        best_iz = np.where(ok, iz, best_iz)
        best_tri = np.where(ok, t[:, None], best_tri)
    sub_colour = np.where((best_tri >= 0)[..., None], tri_colour[np.maximum(best_tri, 0)], bg[:, None, :])
    colour[ey, ex] = np.round(sub_colour.mean(axis=1)).astype(np.uint8)


def _cast_shadow(grey: np.ndarray, camera: CameraModel, T_w_c: np.ndarray, geo: _TableGeometry,
                 groups_w: Sequence[np.ndarray], light_w: np.ndarray, strength: float) -> None:
    """Darken the table image ``grey`` (H×W uint8, in place) where the meshes' shadow falls.

    Each group of triangle corners (one mesh: the object, the arm) casts its own shadow
    (:func:`~labctl.sim.effects.shadow_mask`, in table mm), so a large caster does not coarsen a small
    one's mask; a pixel's coverage is the largest of them. Each is sampled at each pixel's table point
    (the texture lookup's own map, so a window gets exactly the full frame's values), only inside the
    image box of its bounds; radiance there × (1 − c·(1 − f)), c the coverage, f the shadowed/lit
    ratio of the table's Lambert shading.
    """
    H, W = grey.shape
    cover_all: np.ndarray | None = None
    box_all = [W, H, 0, 0]
    T_c_w = invert(T_w_c)
    for corners_w in groups_w:
        if not len(corners_w):
            continue
        sm = shadow_mask(shadow_polygons_w(corners_w, light_w))
        if sm is None:
            continue
        x0, y0, x1, y1 = sm.bounds
        gx, gy = np.meshgrid(np.linspace(x0, x1, 5), np.linspace(y0, y1, 5))
        pts_w = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
        P = pts_w @ T_c_w[:3, :3].T + T_c_w[:3, 3]
        if np.all(P[:, 2] > _NEAR_MM):
            px = camera.project(P)
            if not np.all(np.isfinite(px)):
                continue
            c0, r0 = (int(max(np.floor(v) - 2, 0)) for v in px.min(axis=0))
            c1, r1 = (int(min(np.ceil(v) + 3, n)) for v, n in zip(px.max(axis=0), (W, H)))
        else:  # part of the shadow behind the camera: test every pixel
            c0, r0, c1, r1 = 0, 0, W, H
        if c1 <= c0 or r1 <= r0:
            continue
        unit = np.float32(_TEXTURE_MM_PER_TEXEL)
        wx = geo.map_x[r0:r1, c0:c1] * unit - np.float32(_TEXTURE_SIZE * _TEXTURE_MM_PER_TEXEL)
        wy = np.float32(_TEXTURE_SIZE * _TEXTURE_MM_PER_TEXEL) - geo.map_y[r0:r1, c0:c1] * unit
        cover = sm.sample(wx, wy)
        if cover_all is None:
            cover_all = np.zeros((H, W), np.float32)
        np.maximum(cover_all[r0:r1, c0:c1], cover, out=cover_all[r0:r1, c0:c1])
        box_all = [min(box_all[0], c0), min(box_all[1], r0), max(box_all[2], c1), max(box_all[3], r1)]
    if cover_all is None:
        return
    c0, r0, c1, r1 = box_all
    f = np.float32(shadow_factor(light_w, _AMBIENT, strength))
    patch = grey[r0:r1, c0:c1]
    patch[...] = np.round(patch * (np.float32(1.0) - cover_all[r0:r1, c0:c1] * (np.float32(1.0) - f))).astype(np.uint8)


def _render_noiseless(camera: CameraModel, T_w_c: np.ndarray, meshes: Sequence[Mesh], table, light_w: np.ndarray,
                      supersample: int, fx: CameraEffects | None = None):
    H, W = camera.height, camera.width
    T_c_w = invert(T_w_c)
    corners_w, base_colour, _ = _gather_meshes(meshes)
    # table layer (uint8 BGR)
    if table is False or table is None:
        colour: np.ndarray = np.zeros((H, W, 3), np.uint8)
        invz = np.zeros(H * W, np.float32)
    else:
        surface = table if isinstance(table, TableSurface) else TableSurface()
        geo = _table_geometry(camera, T_w_c)
        shade = surface.brightness * float(_lambert(np.array([[0.0, 0.0, 1.0]]), light_w)[0])
        contrast = 1000 if fx is None else int(round(1000 * fx.texture))
        tex = _table_texture(surface.texture_seed, int(round(1000 * shade)), contrast)
        ox, oy = surface.origin_w
        map_x, map_y = geo.map_x, geo.map_y
        if ox or oy:
            map_x = map_x - np.float32(ox / _TEXTURE_MM_PER_TEXEL)
            map_y = map_y + np.float32(oy / _TEXTURE_MM_PER_TEXEL)
        grey = cv2.remap(tex, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        if fx is not None and fx.shadows > 0 and len(corners_w):
            _cast_shadow(grey, camera, T_w_c, geo, [_gather_meshes([m])[0] for m in meshes], light_w, fx.shadows)
        if not geo.all_hit:
            grey[~geo.hit] = 0
        colour = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
        invz = geo.invz.copy()
    flat = colour.reshape(H * W, 3)
    tri_id = np.full(H * W, -1, np.int32)
    if len(corners_w):
        Pc = corners_w @ T_c_w[:3, :3].T + T_c_w[:3, 3]
        idx, coef, box = _triangle_setup(camera, Pc)
        if len(idx):
            cw = corners_w[idx]
            nw = _cross(cw[:, 1] - cw[:, 0], cw[:, 2] - cw[:, 0])
            nw /= np.maximum(np.linalg.norm(nw, axis=1, keepdims=True), 1e-300)
            tri_colour = (base_colour[idx] * _lambert(nw, light_w)[:, None]).astype(np.float32)
            if fx is not None and fx.specular > 0:  # per face, viewed from its centroid
                spec = blinn_phong(nw, cw.mean(axis=1), T_w_c[:3, 3], light_w, fx.specular, fx.shininess)
                tri_colour = np.minimum(tri_colour + spec[:, None].astype(np.float32), np.float32(255.0))
            win_pix, win_tri = _rasterise(camera, coef, box, invz)
            if len(win_pix):
                tri_id[win_pix] = win_tri
                ys, xs = np.divmod(win_pix, W)
                roi = (max(int(ys.min()) - 1, 0), min(int(ys.max()) + 2, H),
                       max(int(xs.min()) - 1, 0), min(int(xs.max()) + 2, W))
                table_roi = colour[roi[0]:roi[1], roi[2]:roi[3]].copy() if supersample > 1 else None
                flat[win_pix] = np.round(tri_colour).astype(np.uint8)[win_tri]
                if supersample > 1:
                    _edge_supersample(camera, supersample, coef, tri_colour, colour, tri_id,
                                      cast(np.ndarray, table_roi), roi)  # copied above when supersample > 1
    markers = [mk for m in meshes for mk in m.markers]
    counts = _marker_pass(camera, T_c_w, light_w, markers, colour, invz, fx) if markers else []
    return _Layer(colour=colour, tri_id=tri_id, invz=invz, marker_pixels=counts), T_c_w, markers


def _window_fill(table, light_w: np.ndarray, fx: CameraEffects | None = None) -> int:
    """Grey level outside a window: the lit table texture's mean (0 without a table), as the
    camera encodes it."""
    if table is False or table is None:
        fill = 0
    else:
        surface = table if isinstance(table, TableSurface) else TableSurface()
        shade = surface.brightness * float(_lambert(np.array([[0.0, 0.0, 1.0]]), light_w)[0])
        contrast = 1000 if fx is None else int(round(1000 * fx.texture))
        fill = _texture_mean(surface.texture_seed, int(round(1000 * shade)), contrast)
    if fx is not None and fx.encode_lut is not None:
        fill = int(fx.encode_lut[fill])
    return fill


@lru_cache(maxsize=8)
def _texture_mean(seed: int, shade_milli: int, contrast_milli: int = 1000) -> int:
    return int(round(float(_table_texture(seed, shade_milli, contrast_milli).mean())))


def render(
    camera: CameraModel,
    T_w_c: np.ndarray,
    meshes: Sequence[Mesh],
    *,
    table: bool | TableSurface = True,
    light_dir_w=DEFAULT_LIGHT_DIR_W,
    noise_sigma: float = 2.0,
    rng: np.random.Generator | None = None,
    exposure_motion: Sequence[tuple[np.ndarray, Sequence[Mesh]]] | None = None,
    truth: bool = False,
    supersample: int = 3,
    window: tuple[int, int, int, int] | None = None,
    effects: CameraEffects | None = None,
) -> RenderResult:
    """Render what ``camera`` at pose ``T_w_c`` (camera → world, mm) sees of ``meshes`` (world frame).

    ``table``: True for the default textured table plane z = 0, a :class:`TableSurface` to place
    its texture, False for a black void. ``light_dir_w``: direction from the scene to the light
    (W). ``noise_sigma``: Gaussian sensor noise (grey levels), drawn from ``rng`` (None: a
    generator seeded with 0, so renders are always reproducible). ``exposure_motion``: further
    ``(T_w_c, meshes)`` states over the exposure; the image is the mean of all sub-frames (motion
    blur); ground truth refers to the main state. ``truth``: also return mask, depth and marker
    poses. ``supersample``: s×s sub-samples on surface boundaries (1 turns anti-aliasing off;
    marker edges are always analytic). ``window`` (x0, y0, x1, y1) px, ends exclusive: render only
    those pixels, bit-for-bit as the full frame has them there (same rays, z-buffer and noise
    draws from ``rng``); the rest of the image is the lit table's mean grey without noise. For a
    consumer that reads only the window (the fixed camera's tracker looks for red markers, which
    are all on the object); not with ``truth``. ``effects``: a realistic camera and scene
    (:class:`~labctl.sim.effects.CameraEffects`: cast shadows, specular highlights, table
    texture, then on the noisy linear frame Bayer demosaicing, the response curve and JPEG);
    None or all off renders exactly as without. With Bayer or JPEG a window is rendered larger
    and on the 16 px grid, so its pixels still equal the full frame's.

    Geometry: Tsai's camera model (Tsai 1987 §II) applied per pixel; markers are the circular
    premarks of He et al. 1996 §2.
    """
    T_w_c = _check_pose(T_w_c)
    if not np.isfinite(noise_sigma) or noise_sigma < 0:
        raise RenderError(f"noise_sigma must be a finite non-negative number, got {noise_sigma}")
    supersample = int(supersample)
    if supersample < 1:
        raise RenderError(f"supersample must be ≥ 1, got {supersample}")
    light_w = np.asarray(light_dir_w, dtype=float).reshape(3)
    if not np.all(np.isfinite(light_w)) or np.linalg.norm(light_w) == 0:
        raise RenderError("light_dir_w must be a finite non-zero vector")
    light_w = light_w / np.linalg.norm(light_w)
    fx = effects if effects is not None and effects.any else None
    H, W = camera.height, camera.width
    full_camera, wx0, wy0 = camera, 0, 0
    if window is not None:
        if truth:
            raise RenderError("a windowed render has no ground truth (render the full frame)")
        try:
            wx0, wy0, wx1, wy1 = (int(v) for v in window)
        except (TypeError, ValueError):
            raise RenderError(f"window must be (x0, y0, x1, y1) px, got {window!r}") from None
        wx0, wy0, wx1, wy1 = max(wx0, 0), max(wy0, 0), min(wx1, W), min(wy1, H)
        if wx1 - wx0 < 3 or wy1 - wy0 < 3:  # nothing (or a sliver) to draw: the mean grey, the noise draws kept
            wx0, wy0, wx1, wy1 = 0, 0, 3, 3
        keep = (wx0, wy0, wx1, wy1)
        if fx is not None and fx.needs_neighbourhood:
            wx0, wy0, wx1, wy1 = expand_window(keep, W, H)
        camera = _window_camera(full_camera, (wx0, wy0, wx1, wy1))
    h, w = camera.height, camera.width

    layer, T_c_w, markers = _render_noiseless(camera, T_w_c, meshes, table, light_w, supersample, fx)
    img = layer.colour
    if exposure_motion:
        acc = img.astype(np.float32)
        for T_sub, meshes_sub in exposure_motion:
            sub, _, _ = _render_noiseless(camera, _check_pose(T_sub), meshes_sub, table, light_w, supersample, fx)
            acc += sub.colour
        img = acc / np.float32(1 + len(exposure_motion))
    if noise_sigma > 0:
        rng = rng if rng is not None else np.random.default_rng(0)
        pos, neg = _noise_bank(H, W, float(noise_sigma))  # the full frame's bank: a window takes its part
        oy = int(rng.integers(0, pos.shape[0] - H + 1)) + wy0
        ox = int(rng.integers(0, pos.shape[1] - W + 1)) + wx0
        if img.dtype != np.uint8:
            img = cv2.convertScaleAbs(img)  # rounds and saturates; values are never negative
        image = cv2.subtract(cv2.add(img, pos[oy:oy + h, ox:ox + w]), neg[oy:oy + h, ox:ox + w])
    elif img.dtype != np.uint8:
        image = cv2.convertScaleAbs(img)
    else:
        image = img
    if fx is not None:
        image = camera_pipeline(image, fx)
    if window is not None:
        full = np.empty((H, W, 3), np.uint8)
        full[...] = _window_fill(table, light_w, fx)
        kx0, ky0, kx1, ky1 = keep
        full[ky0:ky1, kx0:kx1] = image[ky0 - wy0:ky1 - wy0, kx0 - wx0:kx1 - wx0]
        image = full
    result = RenderResult(image=image)
    if truth:
        result.mask = (layer.tri_id >= 0).reshape(H, W)
        with np.errstate(divide="ignore"):
            result.depth = np.where(layer.invz > 0, 1.0 / layer.invz, np.inf).astype(np.float32).reshape(H, W)
        result.markers_c = [
            (T_c_w[:3, :3] @ np.asarray(mk.center, float) + T_c_w[:3, 3],
             T_c_w[:3, :3] @ (np.asarray(mk.normal, float) / np.linalg.norm(mk.normal)))
            for mk in markers
        ]
        result.marker_pixels = layer.marker_pixels
    return result
