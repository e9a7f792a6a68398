"""Synthetic marker images with known ground truth, for tests and benchmarks.

Renders a red disc of known radius and pose on a light face as a camera sees it: exact
perspective (and the camera's radial distortion), anti-aliasing by supersampling each pixel
the disc's edge crosses, optional shading, and Gaussian sensor noise. Pure: numpy in, numpy out;
randomness only through the ``rng`` passed in.
"""

from __future__ import annotations

import numpy as np

from ..geometry.camera import CameraModel

DISC_BGR = (38.0, 32.0, 196.0)
FACE_BGR = (200.0, 206.0, 212.0)


def disc_frame(normal) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane with unit ``normal``."""
    n = np.asarray(normal, dtype=float)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = np.cross(n, helper)
    b1 /= np.linalg.norm(b1)
    return b1, np.cross(n, b1)


def disc_outline(center, normal, radius: float, n: int = 256) -> np.ndarray:
    """``n`` points (n×3, mm) on the rim of the disc."""
    b1, b2 = disc_frame(normal)
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.asarray(center, float) + radius * (np.cos(t)[:, None] * b1 + np.sin(t)[:, None] * b2)


def disc_coverage(camera: CameraModel, center, normal, radius: float, supersample: int = 12) -> np.ndarray:
    """Fraction of each pixel covered by the disc (float H×W in [0, 1]).

    ``center`` (mm) and unit ``normal`` in the camera frame; pixels are the camera's distorted
    frame-buffer pixels. Pixels whose footprint the rim crosses are supersampled
    ``supersample``² times; the others are 0 or 1.
    """
    cov = np.zeros((camera.height, camera.width))
    x0, y0, block = _coverage_roi(camera, center, normal, radius, supersample)
    cov[y0:y0 + block.shape[0], x0:x0 + block.shape[1]] = block
    return cov


def _coverage_roi(camera: CameraModel, center, normal, radius: float, supersample: int):
    """(x0, y0, coverage block) of the disc's bounding box."""
    H, W = camera.height, camera.width
    center = np.asarray(center, float)
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    rim = camera.project(disc_outline(center, n, radius, 360))
    if not np.all(np.isfinite(rim)):
        raise ValueError("disc must lie in front of the camera")
    x0, y0 = np.floor(rim.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(rim.max(axis=0)).astype(int) + 3
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
    if x1 <= x0 or y1 <= y0:
        return 0, 0, np.zeros((0, 0))
    Kinv = np.linalg.inv(camera.K)
    d_plane = float(n @ center)

    def radial_mm(px):  # in-plane distance from the centre of the ray through each pixel
        u = camera.undistort_pixels(px) if camera.kappa1 != 0.0 else px
        rays = np.concatenate([u, np.ones(u.shape[:-1] + (1,))], axis=-1) @ Kinv.T
        t = d_plane / (rays @ n)
        return np.linalg.norm(rays * t[..., None] - center, axis=-1), t, rays

    yy, xx = np.mgrid[y0:y1, x0:x1]
    px = np.stack([xx, yy], axis=-1).astype(float)
    rho, t, rays = radial_mm(px)
    # footprint of one pixel on the plane (mm), generous: slant range / (f · cos incidence)
    cos_inc = np.abs(rays @ n) / np.linalg.norm(rays, axis=-1)
    foot = t * np.linalg.norm(rays, axis=-1) / (camera.K[1, 1] * np.maximum(cos_inc, 1e-3))
    edge = np.abs(rho - radius) < 1.0 * foot + 1e-9
    block = (rho < radius).astype(float)
    ey, ex = np.nonzero(edge)
    if ey.size:
        s = supersample
        offs = (np.arange(s) + 0.5) / s - 0.5
        oy, ox = np.meshgrid(offs, offs, indexing="ij")
        sub = np.stack([ox.ravel(), oy.ravel()], axis=-1)
        pts = px[ey, ex][:, None, :] + sub[None, :, :]
        r_sub, _, _ = radial_mm(pts)
        block[ey, ex] = (r_sub <= radius).mean(axis=1)
    return int(x0), int(y0), block


def render_disc(camera: CameraModel, center, normal, radius: float = 10.0, *, rng=None,
                noise_sigma: float = 2.0, disc_bgr=DISC_BGR, face_bgr=FACE_BGR, shading: float = 1.0,
                supersample: int = 12) -> np.ndarray:
    """A uint8 BGR image (camera.height × camera.width) of a red disc on a light face.

    ``shading`` scales all colours (a dimmer face); ``noise_sigma`` is the sensor noise in grey
    levels (Gaussian, per channel, from ``rng``).
    """
    x0, y0, block = _coverage_roi(camera, center, normal, radius, supersample)
    face = shading * np.asarray(face_bgr, np.float32)
    disc = shading * np.asarray(disc_bgr, np.float32)
    img = np.empty((camera.height, camera.width, 3), np.float32)
    img[:] = face
    cov = block.astype(np.float32)[..., None]
    img[y0:y0 + block.shape[0], x0:x0 + block.shape[1]] = cov * disc + (1.0 - cov) * face
    if noise_sigma > 0:
        rng = np.random.default_rng() if rng is None else rng
        img += np.float32(noise_sigma) * rng.standard_normal(img.shape, dtype=np.float32)
    np.clip(img, 0.0, 255.0, out=img)
    img += 0.5
    return img.astype(np.uint8)


def random_disc_pose(rng, camera: CameraModel, *, range_mm=(300.0, 1200.0), obliquity_deg=(0.0, 70.0),
                     radius: float = 10.0, margin_px: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """A random disc pose (centre mm, unit normal towards the camera) fully inside the image:
    distance from the camera uniform in ``range_mm``, obliquity (angle between the normal and
    the line of sight) uniform in ``obliquity_deg``, azimuth uniform."""
    for _ in range(1000):
        rng_mm = rng.uniform(*range_mm)
        px = np.array([rng.uniform(0, camera.width - 1), rng.uniform(0, camera.height - 1)])
        ray = camera.backproject(px)
        center = rng_mm * ray
        sight = -ray
        ob = np.deg2rad(rng.uniform(*obliquity_deg))
        b1, b2 = disc_frame(sight)
        az = rng.uniform(0, 2 * np.pi)
        normal = np.cos(ob) * sight + np.sin(ob) * (np.cos(az) * b1 + np.sin(az) * b2)
        rim = camera.project(disc_outline(center, normal, radius, 64))
        if np.all(camera.contains(rim, margin=margin_px)):
            return center, normal
    raise ValueError("could not place a disc inside the image")


def issue_camera(kappa1: float = 0.0, width: int = 640, height: int = 480, focal_px: float = 2500.0) -> CameraModel:
    """The issue's test camera: 640×480, 2500 px focal length, centred principal point."""
    dx = 0.01
    return CameraModel(f=focal_px * dx, kappa1=kappa1, sx=1.0, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0,
                       dx=dx, dy=dx, ncx=width, nfx=width, width=width, height=height)
