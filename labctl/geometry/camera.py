"""The camera model: pinhole plus Tsai's radial lens distortion.

Implements the model of R. Y. Tsai, "A versatile camera calibration technique for
high-accuracy 3D machine vision metrology using off-the-shelf TV cameras and lenses",
IEEE J. Robotics and Automation 3(4), 1987, §II (eqs. 1–5), with the parameter names of
that paper and of Reg Willson's reference implementation:

* ``f``      effective focal length (mm)
* ``kappa1`` radial distortion κ1 (1/mm²); it *undistorts* distorted sensor coordinates:
  ``Xu = Xd·(1 + κ1·r²)``, ``r² = Xd² + Yd²``
* ``sx``     horizontal scale uncertainty factor (dimensionless)
* ``cx, cy`` image centre Cx, Cy (frame-buffer pixels)
* ``dx, dy`` centre-to-centre distance of sensor elements in x and y (mm)
* ``ncx``    number of sensor elements in x; ``nfx`` number of pixels in a frame-buffer line
* ``width, height`` image size (pixels)

With ``dpx = dx·Ncx/Nfx`` and ``dpy = dy`` the frame-buffer coordinates are
``Xf = sx·Xd/dpx + Cx`` and ``Yf = Yd/dpy + Cy`` (Tsai eq. 4). Camera frame: +z along the
optical axis, +x along image columns, +y along image rows. Points in mm, pixels in px.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from .transforms import apply


@dataclass(frozen=True)
class CameraModel:
    """Tsai camera model: pinhole intrinsics plus radial distortion κ1 (Tsai 1987 §II); fields as in the module doc."""

    f: float
    kappa1: float
    sx: float
    cx: float
    cy: float
    dx: float
    dy: float
    ncx: float
    nfx: float
    width: int = 640
    height: int = 480

    # --- derived -----------------------------------------------------------------------
    @property
    def dpx(self) -> float:
        """Effective x size of a frame-buffer pixel on the sensor (mm)."""
        return self.dx * self.ncx / self.nfx

    @property
    def dpy(self) -> float:
        """Effective y size of a frame-buffer pixel on the sensor (mm); ``dpy = dy``."""
        return self.dy

    @property
    def K(self) -> np.ndarray:
        """3×3 pinhole matrix acting on *undistorted* image coordinates (px)."""
        return np.array(
            [[self.f * self.sx / self.dpx, 0.0, self.cx], [0.0, self.f / self.dpy, self.cy], [0.0, 0.0, 1.0]]
        )

    def with_(self, **changes) -> CameraModel:
        """A copy of this model with the given fields replaced."""
        return replace(self, **changes)

    # --- sensor <-> pixel ------------------------------------------------------------
    def _pixels_to_distorted_mm(self, px: np.ndarray) -> np.ndarray:
        px = np.asarray(px, dtype=float)
        xd = (px[..., 0] - self.cx) * self.dpx / self.sx
        yd = (px[..., 1] - self.cy) * self.dpy
        return np.stack([xd, yd], axis=-1)

    def _distorted_mm_to_pixels(self, d: np.ndarray) -> np.ndarray:
        return np.stack([self.sx * d[..., 0] / self.dpx + self.cx, d[..., 1] / self.dpy + self.cy], axis=-1)

    def _undistort_mm(self, d: np.ndarray) -> np.ndarray:
        r2 = np.sum(d * d, axis=-1, keepdims=True)
        return d * (1.0 + self.kappa1 * r2)

    def _distort_mm(self, u: np.ndarray) -> np.ndarray:
        """Invert ``u = d·(1 + κ1·|d|²)`` for ``d``: Newton on the radial cubic κ1·r³ + r − ru = 0."""
        u = np.asarray(u, dtype=float)
        if self.kappa1 == 0.0:
            return u.copy()
        ru = np.linalg.norm(u, axis=-1)
        r = ru.copy()
        for _ in range(50):
            g = self.kappa1 * r**3 + r - ru
            dg = 3.0 * self.kappa1 * r**2 + 1.0
            step = g / np.where(np.abs(dg) < 1e-12, 1e-12, dg)
            r = r - step
            if np.all(np.abs(step) < 1e-15 * np.maximum(1.0, ru)):
                break
        scale = np.divide(r, ru, out=np.ones_like(ru), where=ru > 0)
        return u * scale[..., None]

    # --- public API --------------------------------------------------------------------
    def project(self, points_c: np.ndarray) -> np.ndarray:
        """Project camera-frame points (…, 3) in mm to distorted frame-buffer pixels (…, 2).

        Points must be in front of the camera (z > 0); others give non-finite pixels.
        """
        p = np.asarray(points_c, dtype=float)
        z = p[..., 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.f * p[..., :2] / np.where(z > 0, z, np.nan)
        return self._distorted_mm_to_pixels(self._distort_mm(u))

    def project_world(self, T_c_w: np.ndarray, points_w: np.ndarray) -> np.ndarray:
        """Project world points given the world-to-camera transform ``T_c_w``."""
        return self.project(apply(T_c_w, points_w))

    def undistort_pixels(self, px: np.ndarray) -> np.ndarray:
        """Distorted frame-buffer pixels → ideal (undistorted) pixels under :attr:`K`."""
        u = self._undistort_mm(self._pixels_to_distorted_mm(px))
        return self._distorted_mm_to_pixels(u)

    def distort_pixels(self, px_ideal: np.ndarray) -> np.ndarray:
        """Ideal pixels under :attr:`K` → distorted frame-buffer pixels (inverse of the above)."""
        u = self._pixels_to_distorted_mm(px_ideal)
        return self._distorted_mm_to_pixels(self._distort_mm(u))

    def normalized(self, px: np.ndarray) -> np.ndarray:
        """Distorted pixels → normalised image coordinates (x/z, y/z), shape (…, 2)."""
        return self._undistort_mm(self._pixels_to_distorted_mm(px)) / self.f

    def backproject(self, px: np.ndarray) -> np.ndarray:
        """Distorted pixels → unit ray directions in the camera frame, shape (…, 3)."""
        n = self.normalized(px)
        rays = np.concatenate([n, np.ones(n.shape[:-1] + (1,))], axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def contains(self, px: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels ``px`` (..., 2) lying at least ``margin`` px inside the image."""
        px = np.asarray(px, dtype=float)
        return (
            (px[..., 0] >= margin)
            & (px[..., 0] <= self.width - 1 - margin)
            & (px[..., 1] >= margin)
            & (px[..., 1] <= self.height - 1 - margin)
        )

    # --- OpenCV ----------------------------------------------------------------------
    def to_opencv(self) -> tuple[np.ndarray, np.ndarray, float]:
        """OpenCV ``(K, dist, max_error_px)`` equivalent of this model.

        OpenCV's distortion maps *undistorted* normalised coordinates to distorted ones; Tsai's
        κ1 maps the other way, so the two agree exactly only when κ1 = 0. Otherwise ``dist``
        = (k1, k2, 0, 0, k3) is a least-squares fit over the image, and ``max_error_px`` says
        how far it strays (typically below 0.01 px for lenses like the paper's).
        """
        K = self.K
        if self.kappa1 == 0.0:
            return K, np.zeros(5), 0.0
        u, v = np.meshgrid(np.linspace(0, self.width - 1, 33), np.linspace(0, self.height - 1, 25))
        px = np.stack([u.ravel(), v.ravel()], axis=-1)
        n = self.normalized(px)  # undistorted normalised
        d = np.stack([(px[:, 0] - K[0, 2]) / K[0, 0], (px[:, 1] - K[1, 2]) / K[1, 1]], axis=-1)
        r2 = np.sum(n * n, axis=1)
        # d = n (1 + k1 r² + k2 r⁴ + k3 r⁶)  →  linear in k
        Ax = np.column_stack([n[:, 0] * r2, n[:, 0] * r2**2, n[:, 0] * r2**3])
        Ay = np.column_stack([n[:, 1] * r2, n[:, 1] * r2**2, n[:, 1] * r2**3])
        A = np.vstack([Ax, Ay])
        b = np.concatenate([d[:, 0] - n[:, 0], d[:, 1] - n[:, 1]])
        k = np.linalg.lstsq(A, b, rcond=None)[0]
        dist = np.array([k[0], k[1], 0.0, 0.0, k[2]])
        poly = 1 + k[0] * r2 + k[1] * r2**2 + k[2] * r2**3
        d_fit = n * poly[:, None]
        px_fit = np.stack([d_fit[:, 0] * K[0, 0] + K[0, 2], d_fit[:, 1] * K[1, 1] + K[1, 2]], axis=-1)
        err = float(np.max(np.linalg.norm(px_fit - px, axis=1)))
        return K, dist, err

    @classmethod
    def from_opencv(
        cls,
        K: np.ndarray,
        dist,
        *,
        dx: float,
        dy: float,
        ncx: float,
        nfx: float,
        width: int,
        height: int,
    ) -> tuple[CameraModel, float]:
        """Tsai model from OpenCV ``K`` and ``dist`` given the sensor's element sizes.

        Returns ``(model, max_error_px)``. Exact (error 0) when ``dist`` is all zero;
        otherwise κ1 is fitted over the image and the worst pixel disagreement is returned.
        Skew and tangential terms are not representable and count towards the error.
        """
        K = np.asarray(K, dtype=float)
        dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).ravel()
        dpx = dx * ncx / nfx
        f = float(K[1, 1] * dy)
        sx = float(K[0, 0] * dpx / f)
        base = cls(f=f, kappa1=0.0, sx=sx, cx=float(K[0, 2]), cy=float(K[1, 2]), dx=dx, dy=dy, ncx=ncx, nfx=nfx,
                   width=width, height=height)
        if not np.any(dist):
            return base, 0.0
        import cv2

        u, v = np.meshgrid(np.linspace(0, width - 1, 33), np.linspace(0, height - 1, 25))
        px = np.stack([u.ravel(), v.ravel()], axis=-1)
        n = cv2.undistortPoints(px.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
        dmm = base._pixels_to_distorted_mm(px)
        umm = n * f
        r2 = np.sum(dmm * dmm, axis=1)
        # umm = dmm (1 + κ1 r²)  →  least squares for κ1
        a = (dmm * r2[:, None]).ravel()
        b = (umm - dmm).ravel()
        kappa1 = float(a @ b / (a @ a))
        model = base.with_(kappa1=kappa1)
        err = float(np.max(np.linalg.norm(model.distort_pixels(n * [K[0, 0], K[1, 1]] + K[:2, 2]) - px, axis=1)))
        return model, err

    # --- serialisation -----------------------------------------------------------------
    def to_dict(self) -> dict:
        """Plain-float dict of the fields (for YAML/JSON); inverse of :meth:`from_dict`."""
        return {k: (float(v) if isinstance(v, float | np.floating) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> CameraModel:
        """Model from a dict of fields; keys that are not fields are ignored."""
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})
