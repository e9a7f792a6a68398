"""A second, physically based oracle for marker vision: red disc markers rendered by Mitsuba 3.

Mitsuba 3 (EPFL's research renderer, on PyPI as ``mitsuba``; its CPU variant ``scalar_rgb`` needs
no GPU) was written by no one here, so the images it makes are ground truth the code under test
did not generate. This module imports neither ``labctl.vision`` nor ``labctl.sim``; it takes the
camera and the disc from :mod:`labctl.bench._vision_oracle` only as plain data (``Cam``: focal
length f px, image size, principal point at the image centre; ``Disc``: centre mm, unit normal,
radius mm, camera frame: +x columns, +y rows, +z optical axis).

Scene (mm): a red disc (Mitsuba ``disk``, ``plastic`` BSDF: a diffuse red base under a smooth
dielectric coat, so its highlights are the coat's Fresnel reflection) 0.02 mm in front of a
grey ``diffuse`` plane of the same orientation; optionally a dark ``cylinder`` (a wire or cable)
10 mm in front of the disc, across it (over a point within half a radius of its centre);
lit by a constant sky plus a directional light (the wire casts a shadow). Camera: Mitsuba's
``perspective`` pinhole, or ``thinlens`` for defocus: with aperture radius A and focus
distance z_f a point at depth z is spread over a disc of radius f·A·|1/z_f − 1/z| px, so z_f
is chosen to give the requested blur radius at the disc's depth.
Motion blur: the disc moves at ``motion_mm_s`` along a random direction in its plane during the
exposure ``exposure_s``; the shutter is integrated by rendering sub-frames along the path (a box
shutter; Mitsuba 3 has no animated shape transforms) and averaging them. Pixel filter ``box``
(each pixel integrates its own square: exact area coverage), ``multijitter`` sampler.

Only a crop around the marker is rendered (the rest of the frame is the plane's level, filled
from the crop's border); the camera pipeline then acts on the whole frame, in numpy/OpenCV:
auto-exposure (the plane at 0.5), RGGB Bayer mosaic, photon (Poisson) and read (Gaussian) noise,
bilinear demosaic, the response (``linear``, ``srgb``, ``gamma G``), 8-bit quantisation, JPEG.
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass

import cv2
import numpy as np

from . import _vision_oracle as oracle

AVAILABLE = importlib.util.find_spec("mitsuba") is not None
WHY_UNAVAILABLE = "mitsuba is not installed (pip install 'labctl[vision-oracle]')"

RED_RGB = (0.60, 0.05, 0.06)  # linear diffuse albedo of the marker paint (under its clear coat)
PLANE_RGB = (0.55, 0.56, 0.57)
WIRE_RGB = (0.04, 0.04, 0.04)
APERTURE_MM = 3.0  # thin-lens aperture radius used for defocus


@dataclass(frozen=True)
class Shot:
    """What the camera and scene do to one image (defaults: sharp, linear, a little read noise)."""

    defocus_px: float = 0.0       # thin-lens blur radius at the disc's depth, px
    motion_mm_s: float = 0.0      # the disc's speed in its own plane during the exposure
    exposure_s: float = 0.030
    wire_px: float = 0.0          # width in the image of a dark wire across the marker (0: none)
    response: str = "linear"      # the camera's encoding: linear, srgb, "gamma G"
    bayer: bool = False           # RGGB mosaic + bilinear demosaic
    photons: float | None = None  # full-well electrons (Poisson noise), None: none
    noise_std: float = 1.0        # read noise, grey levels of 255
    jpeg_quality: int | None = None
    spp: int = 64                 # samples per pixel (split over the motion sub-frames)


def _mi():
    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    return mi


def _frame(normal) -> np.ndarray:
    """A rotation whose third column is ``normal`` (unit): the disc's local frame in the camera frame."""
    n = np.asarray(normal, float)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = np.cross(helper, n)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(n, b1), n])


def _to_world(mi, R: np.ndarray, t, scale: float):
    M = np.eye(4)
    M[:3, :3] = R * scale
    M[:3, 3] = t
    return mi.ScalarTransform4f(M.tolist())


def _crop(cam: oracle.Cam, disc: oracle.Disc, margin: float) -> tuple[int, int, int, int]:
    rim = oracle.rim_pixels(oracle.Cam(f=cam.f, width=cam.width, height=cam.height), disc, 90)
    x0 = max(int(math.floor(rim[:, 0].min() - margin)), 0)
    y0 = max(int(math.floor(rim[:, 1].min() - margin)), 0)
    x1 = min(int(math.ceil(rim[:, 0].max() + margin)) + 1, cam.width)
    y1 = min(int(math.ceil(rim[:, 1].max() + margin)) + 1, cam.height)
    return x0, y0, x1, y1


def render_linear(cam: oracle.Cam, disc: oracle.Disc, shot: Shot, rng: np.random.Generator):
    """Mitsuba's linear RGB (H×W×3 float32, the plane at 0.5) of ``disc`` under ``shot``, and facts:
    ``motion_px`` (the smear length in the image), ``motion_dir`` (its unit image direction),
    ``defocus_px``, ``wire`` (the wire's image line: point and direction, or None)."""
    mi = _mi()
    c = np.asarray(disc.center, float)
    z = float(c[2])
    R = _frame(disc.normal)
    travel = shot.motion_mm_s * shot.exposure_s
    ang = rng.uniform(0.0, 2.0 * np.pi)
    move = travel * (math.cos(ang) * R[:, 0] + math.sin(ang) * R[:, 1])
    p0, p1 = cam.project(c - 0.5 * move), cam.project(c + 0.5 * move)
    motion_px = float(np.hypot(*(p1 - p0)))
    margin = shot.defocus_px + 0.5 * motion_px + 14.0
    x0, y0, x1, y1 = _crop(cam, disc, margin)
    sensor: dict = {
        "type": "perspective", "fov": math.degrees(2.0 * math.atan(0.5 * cam.width / cam.f)), "fov_axis": "x",
        "near_clip": 1.0, "far_clip": 1e5,
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, -1, 0]),
        "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height, "crop_offset_x": x0,
                 "crop_offset_y": y0, "crop_width": x1 - x0, "crop_height": y1 - y0,
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "multijitter", "sample_count": shot.spp},
    }
    if shot.defocus_px > 0:
        inv_zf = 1.0 / z + shot.defocus_px / (cam.f * APERTURE_MM)
        sensor.update(type="thinlens", aperture_radius=APERTURE_MM, focus_distance=1.0 / inv_zf)
    light_dir = -(np.asarray(disc.normal) * 0.8 + R[:, 0] * 0.45 + R[:, 1] * 0.3)
    scene: dict = {
        "type": "scene", "integrator": {"type": "direct"}, "sensor": sensor,
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.6, 0.6, 0.6]}},
        "sun": {"type": "directional", "direction": (light_dir / np.linalg.norm(light_dir)).tolist(),
                "irradiance": {"type": "rgb", "value": [1.2, 1.2, 1.2]}},
        "plane": {"type": "rectangle", "to_world": _to_world(mi, R, c, 400.0),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(PLANE_RGB)}}},
        "disc": {"type": "disk", "to_world": _to_world(mi, R, c + 0.02 * R[:, 2], disc.radius),
                 "bsdf": {"type": "plastic", "int_ior": 1.5,
                          "diffuse_reflectance": {"type": "rgb", "value": list(RED_RGB)}}},
    }
    wire = None
    if shot.wire_px > 0:
        zw = z - 10.0
        ray = c / np.linalg.norm(c)
        wa = rng.uniform(0.0, np.pi)
        across = np.array([math.cos(wa), math.sin(wa), 0.0])
        across -= ray * (across @ ray)
        across /= np.linalg.norm(across)
        # the wire passes in front of a random point of the disc (within half its radius of the centre)
        pa = rng.uniform(0.0, 2.0 * np.pi)
        q = c + rng.uniform(0.0, 0.5) * disc.radius * (math.cos(pa) * R[:, 0] + math.sin(pa) * R[:, 1])
        mid = q * (zw / float(q[2]))
        half = 4.0 * disc.radius
        scene["wire"] = {"type": "cylinder", "radius": 0.5 * shot.wire_px * zw / cam.f,
                         "p0": (mid - half * across).tolist(), "p1": (mid + half * across).tolist(),
                         "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(WIRE_RGB)}}}
        wire = (cam.project(mid), across[:2] / np.linalg.norm(across[:2]))
    sc = mi.load_dict(scene)
    n_sub = max(1, int(math.ceil(motion_px / 0.5))) if motion_px > 0 else 1
    spp = max(4, shot.spp // n_sub)
    acc = None
    params = mi.traverse(sc) if n_sub > 1 else None
    key = next((k for k in (params.keys() if params is not None else []) if "disc" in k and "to_world" in k), None)
    for k in range(n_sub):
        if params is not None and key is not None:
            s = (k + 0.5) / n_sub - 0.5
            params[key] = _to_world(mi, R, c + 0.02 * R[:, 2] + s * move, disc.radius)
            params.update()
        img = np.asarray(mi.render(sc, spp=spp, seed=int(rng.integers(2**31))), np.float32)
        acc = img if acc is None else acc + img
    assert acc is not None
    crop = acc / n_sub
    border = np.concatenate([crop[0], crop[-1], crop[:, 0], crop[:, -1]])
    level = np.median(border, axis=0)
    scale = 0.5 / max(float(level[1]), 1e-6)
    out = np.empty((cam.height, cam.width, 3), np.float32)
    out[:] = level * scale
    out[y0:y1, x0:x1] = crop * scale
    u = (p1 - p0) / motion_px if motion_px > 0 else np.zeros(2)
    return out, {"motion_px": motion_px, "motion_dir": u, "defocus_px": shot.defocus_px, "wire": wire,
                 "crop": (x0, y0, x1, y1), "subframes": n_sub}


def _encode(x: np.ndarray, response: str) -> np.ndarray:
    if response == "linear":
        return x
    if response == "srgb":
        return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)
    if response.startswith("gamma"):
        return np.power(np.maximum(x, 0.0), 1.0 / float(response.split()[1]))
    raise ValueError(f"unknown response {response!r}")


def camera_pipeline(rgb: np.ndarray, shot: Shot, rng: np.random.Generator) -> np.ndarray:
    """A webcam-like sensor on a linear RGB frame: Bayer, noise, demosaic, response, 8 bits, JPEG → BGR uint8."""
    x = np.clip(rgb, 0.0, None).astype(np.float32)
    H, W = x.shape[:2]
    if shot.bayer:
        raw = np.empty((H, W), np.float32)
        raw[0::2, 0::2] = x[0::2, 0::2, 0]
        raw[0::2, 1::2] = x[0::2, 1::2, 1]
        raw[1::2, 0::2] = x[1::2, 0::2, 1]
        raw[1::2, 1::2] = x[1::2, 1::2, 2]
        x = raw
    if shot.photons:
        x = rng.poisson(x * shot.photons).astype(np.float32) / np.float32(shot.photons)
    if shot.noise_std > 0:
        x = x + rng.standard_normal(x.shape).astype(np.float32) * np.float32(shot.noise_std / 255.0)
    if shot.bayer:
        raw16 = np.clip(np.rint(x * 65535.0), 0, 65535).astype(np.uint16)
        x = cv2.demosaicing(raw16, cv2.COLOR_BayerRG2RGB).astype(np.float32)[..., ::-1] / 65535.0
    enc = _encode(np.clip(x, 0.0, 1.0), shot.response)
    out = cv2.cvtColor(np.clip(enc * 255.0 + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
    if shot.jpeg_quality:
        _, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(shot.jpeg_quality)])
        dec = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        if dec is not None:
            out = dec
    return out


def render(cam: oracle.Cam, disc: oracle.Disc, shot: Shot, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """A uint8 BGR image of ``disc`` rendered by Mitsuba under ``shot``, and the facts of :func:`render_linear`."""
    lin, info = render_linear(cam, disc, shot, rng)
    return camera_pipeline(lin, shot, rng), info


def lab_camera(path) -> oracle.Cam:
    """The pinhole of a lab's camera calibration file (``calibration/<camera>.yaml``: Tsai f mm, dx mm,
    sx, image size), as the oracle's ``Cam`` (f in px, principal point at the image centre)."""
    import yaml

    with open(path) as fh:
        c = yaml.safe_load(fh)["camera"]
    return oracle.Cam(f=float(c["f"]) * float(c.get("sx", 1.0)) / float(c["dx"]), width=int(c["width"]),
                      height=int(c["height"]))
