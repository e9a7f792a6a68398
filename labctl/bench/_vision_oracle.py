"""An independent renderer of red circular markers as real cameras see them, with exact ground truth.

Independent of the code under test: it imports neither ``labctl.vision`` nor ``labctl.sim``
(``tests/test_vision_suite.py`` checks this), and shares no geometry with them. Its own
pinhole camera (focal length ``f`` px, principal point ``(cx, cy)``, optional radial distortion
``k_px`` in px⁻²: undistorted = c + (d − c)(1 + k_px |d − c|²), i.e. Tsai's κ1 model written in
pixels), its own ray–plane coverage by supersampling, and its own scene and sensor model.

Pipeline of :func:`render` (all radiometry linear in [0, 1] until the response encodes it):

1. **Scene**: background albedo (light grey, optionally textured), the disc (red albedo, its hue
   optionally rotated), optionally a neighbouring red bar or a lone bar, an occluder that
   hides a given fraction of the rim, a thin dark wire across the disc; exact area coverage
   of each pixel by each shape (supersampled: 4×4 everywhere, 16×16 on edge pixels).
2. **Light**: illumination colour (white-balance cast), a soft shadow edge across the marker,
   vignetting, a linear gradient, an additive specular highlight.
3. **Optics**: defocus (pillbox) or motion blur.
4. **Sensor**: exposure, Bayer mosaic, photon (Poisson) and read (Gaussian) noise, demosaic,
   clipping, response (``linear``, ``srgb``, ``gamma G``), contrast, 8-bit quantisation, JPEG,
   salt-and-pepper.

Units: px in the image, mm in the camera frame (+z optical axis, +x columns, +y rows).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

RED_RGB = (0.62, 0.06, 0.07)  # linear albedo of the marker paint
FACE_RGB = (0.55, 0.57, 0.58)  # linear albedo of the object face


@dataclass(frozen=True)
class Cam:
    """Pinhole camera of the oracle (px); ``k_px`` radial distortion in px⁻² (0: none)."""

    f: float = 2000.0
    width: int = 640
    height: int = 480
    k_px: float = 0.0

    @property
    def c(self) -> tuple[float, float]:
        """Principal point (cx, cy) in px: the image centre."""
        return (self.width - 1) / 2.0, (self.height - 1) / 2.0

    @property
    def K(self) -> np.ndarray:
        """3×3 pinhole matrix (px) of the undistorted image."""
        cx, cy = self.c
        return np.array([[self.f, 0.0, cx], [0.0, self.f, cy], [0.0, 0.0, 1.0]])

    def undistort(self, u: np.ndarray, v: np.ndarray):
        """Undistorted pixel coordinates of distorted ``u``, ``v``: offsets from ``c`` scaled by 1 + k_px·r²."""
        if self.k_px == 0.0:
            return u, v
        cx, cy = self.c
        du, dv = u - cx, v - cy
        s = 1.0 + self.k_px * (du * du + dv * dv)
        return cx + du * s, cy + dv * s

    def distort_points(self, pts: np.ndarray) -> np.ndarray:
        """Distorted pixels of undistorted ones (inverting the model by fixed-point iteration)."""
        if self.k_px == 0.0:
            return pts
        c = np.array(self.c)
        du = pts - c
        d = du.copy()
        for _ in range(30):
            d = du / (1.0 + self.k_px * np.sum(d * d, axis=-1, keepdims=True))
        return c + d

    def project(self, X: np.ndarray) -> np.ndarray:
        """Distorted pixels (..., 2) of camera-frame points ``X`` (..., 3) in mm."""
        X = np.asarray(X, float)
        cx, cy = self.c
        return self.distort_points(np.stack([self.f * X[..., 0] / X[..., 2] + cx,
                                             self.f * X[..., 1] / X[..., 2] + cy], axis=-1))


@dataclass(frozen=True)
class Disc:
    """Ground truth: centre (mm, camera frame), unit normal towards the camera, radius (mm)."""

    center: tuple[float, float, float]
    normal: tuple[float, float, float]
    radius: float = 10.0


@dataclass(frozen=True)
class Conditions:
    """What degrades the image (defaults: a clean, linear camera). Grey levels are of 255."""

    texture_std: float = 0.0          # background texture, grey levels (std, blurred 1.2 px noise)
    hue_shift_deg: float = 0.0        # rotate the marker's hue
    wb_gain_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)  # illumination colour cast
    shadow: float = 0.0               # shadow depth (0: none, 0.6: 60 % darker) across the marker
    vignetting: float = 0.0           # corner falloff fraction
    gradient: float = 0.0             # left-to-right illumination ramp (fraction)
    highlight: float = 0.0            # specular peak, grey levels (may exceed 255: clipped)
    occlusion: float = 0.0            # fraction of the rim hidden by a grey occluder
    wire_px: float = 0.0              # a dark wire this wide across the marker (over a point ≤ r/2 from its centre)
    bar_gap_px: float | None = None   # a 5×40 px red bar this far from the rim
    lone_bar: tuple[float, float] | None = None  # (w, h) px: no disc, only a red bar
    defocus_px: float = 0.0           # pillbox radius
    motion_px: float = 0.0            # motion blur length
    exposure: float = 1.0
    bayer: str | None = None          # None, or the demosaic: "bilinear", "vng", "ea"
    photons: float | None = None      # full-well electrons (Poisson noise), None: none
    noise_std: float = 1.0            # read noise, grey levels
    response: str = "linear"          # "linear", "srgb", "gamma 2.2"
    contrast: float = 1.0             # about mid-grey, in the encoded image
    jpeg_quality: int | None = None
    salt_pepper: float = 0.0          # fraction of pixels
    extra: dict = field(default_factory=dict)


def _rot_hue(rgb, deg: float):
    """Rotate a colour's hue about the grey axis by ``deg`` (Rodrigues about (1,1,1)/√3)."""
    if deg == 0.0:
        return np.asarray(rgb, float)
    k = np.ones(3) / math.sqrt(3.0)
    v = np.asarray(rgb, float)
    t = math.radians(deg)
    out = v * math.cos(t) + np.cross(k, v) * math.sin(t) + k * (k @ v) * (1.0 - math.cos(t))
    return np.clip(out, 0.002, 1.0)


def _plane_hits(cam: Cam, disc: Disc, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """True where the ray through distorted pixel (u, v) hits the disc."""
    uu, vv = cam.undistort(u, v)
    cx, cy = cam.c
    d = np.stack([(uu - cx) / cam.f, (vv - cy) / cam.f, np.ones_like(uu)], axis=-1)
    n = np.asarray(disc.normal, float)
    c = np.asarray(disc.center, float)
    t = (n @ c) / (d @ n)
    p = d * t[..., None] - c
    return np.einsum("...i,...i->...", p, p) <= disc.radius**2


def _coverage(inside, x0: int, y0: int, x1: int, y1: int, coarse: int = 4, fine: int = 16) -> np.ndarray:
    """Area coverage of the box [x0, x1) × [y0, y1) of pixels by the set ``inside(u, v)``:
    ``coarse``² samples per pixel, ``fine``² on pixels whose samples (or neighbours) disagree."""
    yy, xx = np.mgrid[y0:y1, x0:x1].astype(float)
    o = (np.arange(coarse) + 0.5) / coarse - 0.5
    su = xx[..., None, None] + o[None, None, None, :]
    sv = yy[..., None, None] + o[None, None, :, None]
    hit = inside(np.broadcast_to(su, su.shape[:2] + (coarse, coarse)),
                 np.broadcast_to(sv, sv.shape[:2] + (coarse, coarse)))
    cov = hit.mean(axis=(2, 3))
    edge = (cov > 0) & (cov < 1)
    edge = cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    ey, ex = np.nonzero(edge)
    if ey.size:
        of = (np.arange(fine) + 0.5) / fine - 0.5
        fu = xx[ey, ex][:, None, None] + of[None, None, :]
        fv = yy[ey, ex][:, None, None] + of[None, :, None]
        fu, fv = np.broadcast_arrays(fu, fv)
        cov[ey, ex] = inside(fu, fv).mean(axis=(1, 2))
    return cov


def rim_pixels(cam: Cam, disc: Disc, n: int = 360) -> np.ndarray:
    """``n`` image points (distorted px) of the disc's rim."""
    nrm = np.asarray(disc.normal, float)
    helper = np.array([1.0, 0.0, 0.0]) if abs(nrm[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = np.cross(nrm, helper)
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(nrm, b1)
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    rim = np.asarray(disc.center) + disc.radius * (np.cos(t)[:, None] * b1 + np.sin(t)[:, None] * b2)
    return cam.project(rim)


def disc_coverage(cam: Cam, disc: Disc) -> np.ndarray:
    """Exact (supersampled) fraction of each pixel covered by the disc, H×W."""
    rim = rim_pixels(cam, disc)
    x0, y0 = np.floor(rim.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(rim.max(axis=0)).astype(int) + 3
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, cam.width), min(y1, cam.height)
    cov = np.zeros((cam.height, cam.width))
    if x1 > x0 and y1 > y0:
        cov[y0:y1, x0:x1] = _coverage(lambda u, v: _plane_hits(cam, disc, u, v), x0, y0, x1, y1)
    return cov


def rect_coverage(cam: Cam, center, size, angle: float) -> np.ndarray:
    """Coverage of an image-space rectangle (centre px, (length, width) px, angle rad)."""
    (cx, cy), (L, Wd) = center, size
    ca, sa = math.cos(angle), math.sin(angle)

    def inside(u, v):
        du, dv = u - cx, v - cy
        return (np.abs(du * ca + dv * sa) <= L / 2) & (np.abs(-du * sa + dv * ca) <= Wd / 2)

    r = 0.5 * math.hypot(L, Wd) + 2
    x0, y0 = max(int(cx - r), 0), max(int(cy - r), 0)
    x1, y1 = min(int(cx + r) + 2, cam.width), min(int(cy + r) + 2, cam.height)
    cov = np.zeros((cam.height, cam.width))
    if x1 > x0 and y1 > y0:
        cov[y0:y1, x0:x1] = _coverage(inside, x0, y0, x1, y1)
    return cov


def halfplane_coverage(cam: Cam, point, normal, box) -> np.ndarray:
    """Coverage of the half-plane {(p − point)·normal > 0} inside ``box`` (x0, y0, x1, y1)."""
    (px, py), (nx, ny) = point, normal
    x0, y0, x1, y1 = box
    cov = np.zeros((cam.height, cam.width))
    cov[y0:y1, x0:x1] = _coverage(lambda u, v: (u - px) * nx + (v - py) * ny > 0, x0, y0, x1, y1)
    return cov


def _encode(x: np.ndarray, response: str) -> np.ndarray:
    if response == "linear":
        return x
    if response == "srgb":
        return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)
    if response.startswith("gamma"):
        g = float(response.split()[1])
        return np.power(np.maximum(x, 0.0), 1.0 / g)
    raise ValueError(f"unknown response {response!r}")


def render(cam: Cam, disc: Disc, cond: Conditions, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """A uint8 BGR image of ``disc`` under ``cond``, and facts about it: ``visible`` (fraction of
    the rim not occluded), ``marker`` (False for a lone bar)."""
    H, W = cam.height, cam.width
    info = {"visible": 1.0, "marker": cond.lone_bar is None}
    face = np.asarray(FACE_RGB, float)
    albedo = np.empty((H, W, 3), np.float32)
    albedo[:] = face
    if cond.texture_std > 0:
        tex: np.ndarray = cv2.GaussianBlur(rng.standard_normal((H, W)).astype(np.float32), (0, 0), 1.2)
        tex *= (cond.texture_std / 255.0) / max(float(tex.std()), 1e-6)
        albedo += tex[..., None]

    def paint(cov, colour):  # blend a shape of coverage ``cov`` into the albedo, on its bounding box only
        ys, xs = np.nonzero(cov)
        if ys.size:
            sl = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
            c = cov[sl][..., None].astype(np.float32)
            albedo[sl] = albedo[sl] * (1 - c) + np.asarray(colour, np.float32) * c
    red = _rot_hue(RED_RGB, cond.hue_shift_deg)
    rim = rim_pixels(cam, disc)
    center_px = rim.mean(axis=0)
    r_px = float(np.sqrt(np.mean(np.sum((rim - center_px) ** 2, axis=1))))
    if cond.lone_bar is None:
        paint(disc_coverage(cam, disc), red)
    else:
        w, h = cond.lone_bar
        paint(rect_coverage(cam, center_px, (h, w), rng.uniform(0, np.pi)), red)
        info["visible"] = 0.0
    if cond.bar_gap_px is not None:  # a 5×40 red bar beside the rim, tangent to it
        k = int(rng.integers(len(rim)))
        tang = rim[(k + 1) % len(rim)] - rim[k - 1]
        nrm = np.array([tang[1], -tang[0]]) / np.linalg.norm(tang)
        if nrm @ (rim[k] - center_px) < 0:
            nrm = -nrm
        # the rim's extent along nrm near this point: push the bar beyond every rim point
        reach = float(np.max((rim - rim[k]) @ nrm))
        bc = rim[k] + (reach + cond.bar_gap_px + 2.5) * nrm
        paint(rect_coverage(cam, bc, (40.0, 5.0), math.atan2(tang[1], tang[0])), red)
    if cond.occlusion > 0:  # a grey occluder in front, its edge a chord hiding that fraction of the rim
        ang = rng.uniform(0, 2 * np.pi)
        d = np.array([math.cos(ang), math.sin(ang)])
        proj = (rim - center_px) @ d
        cut = np.quantile(proj, 1.0 - cond.occlusion)
        pt = center_px + cut * d
        box = (max(int(rim[:, 0].min()) - 12, 0), max(int(rim[:, 1].min()) - 12, 0),
               min(int(rim[:, 0].max()) + 14, W), min(int(rim[:, 1].max()) + 14, H))
        paint(halfplane_coverage(cam, pt, d, box), (0.3, 0.3, 0.3))
        info["visible"] = 1.0 - cond.occlusion
    if cond.wire_px > 0:  # a thin dark occluder (cable, wire) across the disc
        k = int(rng.integers(len(rim)))
        over = center_px + rng.uniform(0.0, 0.5) * (rim[k] - center_px)
        paint(rect_coverage(cam, over, (4.0 * r_px + 20.0, cond.wire_px), rng.uniform(0, np.pi)), (0.05, 0.05, 0.05))
    lit = cond.shadow > 0 or cond.vignetting > 0 or cond.gradient > 0
    if lit or cond.highlight > 0:
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    light = np.ones((H, W), np.float32)
    if cond.shadow > 0:  # a soft (1.5 px) shadow edge through the marker, random direction
        ang = rng.uniform(0, 2 * np.pi)
        off = rng.uniform(-0.5, 0.5) * r_px
        s = (xx - center_px[0]) * math.cos(ang) + (yy - center_px[1]) * math.sin(ang) - off
        light *= 1.0 - cond.shadow * (0.5 * (1.0 + np.tanh(s / 1.5)))
    if cond.vignetting > 0:
        rr = ((xx - W / 2) ** 2 + (yy - H / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
        light *= 1.0 - cond.vignetting * rr
    if cond.gradient > 0:
        light *= 1.0 - cond.gradient * (xx / W)
    radiance = albedo * light[..., None] if lit else albedo
    if cond.wb_gain_rgb != (1.0, 1.0, 1.0):
        radiance *= np.asarray(cond.wb_gain_rgb, np.float32)
    if cond.highlight > 0:  # a specular spot on the marker (σ = r/4), near its rim
        a = rng.uniform(0, 2 * np.pi)
        hc = center_px + rng.uniform(0.3, 0.8) * r_px * np.array([math.cos(a), math.sin(a)])
        spot = np.exp(-((xx - hc[0]) ** 2 + (yy - hc[1]) ** 2) / (2 * (0.25 * r_px) ** 2))
        radiance += np.float32(cond.highlight / 255.0) * spot[..., None]
    img: np.ndarray = radiance * np.float32(cond.exposure) if cond.exposure != 1.0 else radiance
    if cond.defocus_px > 0:
        r = cond.defocus_px
        n = int(math.ceil(r)) + 1
        ker = _coverage(lambda u, v: u * u + v * v <= r * r, -n, -n, n + 1, n + 1).astype(np.float32)
        img = cv2.filter2D(img, -1, ker / ker.sum(), borderType=cv2.BORDER_REFLECT)
    if cond.motion_px > 0:
        L = cond.motion_px
        n = int(math.ceil(L / 2)) + 1
        ang = rng.uniform(0, np.pi)
        ker = _coverage(lambda u, v: (np.abs(u * math.cos(ang) + v * math.sin(ang)) <= L / 2)
                        & (np.abs(-u * math.sin(ang) + v * math.cos(ang)) <= 0.5), -n, -n, n + 1, n + 1)
        img = cv2.filter2D(img, -1, (ker / ker.sum()).astype(np.float32), borderType=cv2.BORDER_REFLECT)
    rgb = img  # channels R, G, B
    if cond.bayer:  # RGGB mosaic: each pixel keeps one channel
        raw = np.empty((H, W), np.float32)
        raw[0::2, 0::2] = rgb[0::2, 0::2, 0]
        raw[0::2, 1::2] = rgb[0::2, 1::2, 1]
        raw[1::2, 0::2] = rgb[1::2, 0::2, 1]
        raw[1::2, 1::2] = rgb[1::2, 1::2, 2]
        rgb = raw
    if cond.photons:
        rgb = rng.poisson(np.clip(rgb, 0, None) * cond.photons).astype(np.float32) / np.float32(cond.photons)
    if cond.noise_std > 0:
        rgb = rgb + rng.standard_normal(rgb.shape).astype(np.float32) * np.float32(cond.noise_std / 255.0)
    if cond.bayer:
        raw16 = np.clip(np.rint(rgb * 65535.0), 0, 65535).astype(np.uint16)
        code = {"bilinear": cv2.COLOR_BayerRG2RGB, "vng": cv2.COLOR_BayerRG2RGB_VNG,
                "ea": cv2.COLOR_BayerRG2RGB_EA}[cond.bayer]
        if cond.bayer == "vng":  # OpenCV's VNG takes 8 bits only
            rgb = cv2.demosaicing((raw16 >> 8).astype(np.uint8), code).astype(np.float32) / 255.0
        else:
            rgb = cv2.demosaicing(raw16, code).astype(np.float32) / 65535.0
        # OpenCV names Bayer patterns by the second row; both RG and BG variants give R in
        # channel 2 for a BGR result, so read back as BGR and flip to RGB
        rgb = rgb[..., ::-1]
    enc = _encode(np.clip(rgb, 0.0, 1.0, out=rgb), cond.response)
    if cond.contrast != 1.0:
        enc = 0.5 + cond.contrast * (enc - 0.5)
    enc *= np.float32(255.0)
    enc += np.float32(0.5)
    out = cv2.cvtColor(np.clip(enc, 0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
    if cond.jpeg_quality:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(cond.jpeg_quality)])
        out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if cond.salt_pepper > 0:
        hit = rng.random((H, W)) < cond.salt_pepper
        out[hit] = np.where(rng.random(int(hit.sum())) < 0.5, 0, 255).astype(np.uint8)[:, None]
    return out, info


def random_pose(rng: np.random.Generator, cam: Cam, *, range_mm=(600.0, 1200.0), obliquity_deg=(0.0, 70.0),
                radius: float = 10.0, margin_px: float = 30.0) -> Disc:
    """A disc at a uniform random range and obliquity, fully inside the image with a margin."""
    cx, cy = cam.c
    for _ in range(1000):
        z = rng.uniform(*range_mm)
        u = rng.uniform(margin_px + 40, cam.width - margin_px - 40)
        v = rng.uniform(margin_px + 40, cam.height - margin_px - 40)
        ray = np.array([(u - cx) / cam.f, (v - cy) / cam.f, 1.0])
        ray /= np.linalg.norm(ray)
        center = z * ray
        sight = -ray
        ob = math.radians(rng.uniform(*obliquity_deg))
        helper = np.array([1.0, 0.0, 0.0]) if abs(sight[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        b1 = np.cross(sight, helper)
        b1 /= np.linalg.norm(b1)
        b2 = np.cross(sight, b1)
        az = rng.uniform(0, 2 * np.pi)
        normal = math.cos(ob) * sight + math.sin(ob) * (math.cos(az) * b1 + math.sin(az) * b2)
        d = Disc(tuple(center), tuple(normal), radius)
        rim = rim_pixels(cam, d, 64)
        if (rim.min(axis=0) > margin_px).all() and (rim[:, 0] < cam.width - margin_px).all() \
                and (rim[:, 1] < cam.height - margin_px).all():
            return d
    raise ValueError("could not place a disc inside the image")


def translated(disc: Disc, shift_mm) -> Disc:
    """``disc`` with its centre moved by ``shift_mm`` (3-vector, mm, camera frame)."""
    return replace(disc, center=tuple(np.asarray(disc.center) + np.asarray(shift_mm, float)))
