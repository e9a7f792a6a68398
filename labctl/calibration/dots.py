"""Dot detection with sub-pixel centres, identification against the target model, and the
perspective-bias correction of a dot's centroid.

* Detection: dark dots are holes in the light regions of an Otsu-thresholded image, with a
  minimum contrast to their surroundings (so the dark, textured table yields none); each centre
  is the grey-level centroid ``Σ w·x / Σ w`` with ``w = (background − I) / (background − dot)`` clipped to [0, 1], which
  uses the partial coverage of boundary pixels (sub-pixel).
* Identification: a few coloured fiducial dots (told apart by chroma, which foreshortening does
  not change) fix the correspondence; every assignment of the detected fiducials to the model's
  is tried with a PnP pose under the nominal camera, the assignment under which most model dots
  land on a detected dot wins, and one PnP over all matches re-matches the grid.
* Bias: the centroid of a projected circle is not the projection of its centre (Heikkilä 2000,
  "Geometric camera calibration using circular control points", IEEE PAMI 22(10), §3). With
  the current camera estimate the circle's image is sampled densely, its area centroid minus
  the projected centre is the bias, and the measured centroid is corrected by it.

Pixels are distorted frame-buffer pixels; model points in mm in the target frame.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..geometry import CameraModel, apply, make_T


class DotError(ValueError):
    """The dots could not be found or identified in an image (one line)."""


@dataclass(frozen=True)
class Blobs:
    """Dots found by :func:`detect_dots`: sub-pixel centres (N, 2) px, areas (N,) px² and chroma (N,)."""

    centers: np.ndarray  # (N, 2) px, grey-level centroids
    areas: np.ndarray  # (N,) px², weighted area of the dot
    chroma: np.ndarray  # (N,) (max − min)/max of the dot core's mean BGR (0 for grey dots)


def detect_dots(image: np.ndarray, *, min_area: float = 8.0, max_area: float = 5000.0,
                min_circularity: float = 0.6, min_contrast: float = 40.0) -> Blobs:
    """Dark circular dots on light surfaces in a BGR or grey uint8 image (pixels, sub-pixel).

    A dot must be at least ``min_contrast`` grey levels darker than the surface around it, which
    keeps the table's own texture (tapped holes, blotches) out."""
    img = np.asarray(image)
    bgr = img if img.ndim == 3 else None
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8 or img.ndim != 2:
        raise DotError("expected an 8-bit grey or BGR image")
    grey = img.astype(np.float32)
    thr, light = cv2.threshold(cv2.GaussianBlur(img, (3, 3), 0), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    contours, hier = cv2.findContours(light, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    if hier is None:
        return Blobs(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    H, W = img.shape
    centers, areas, chroma = [], [], []
    for i, c in enumerate(contours):
        if hier[0, i, 3] < 0:  # an outer boundary of a light region, not a hole in it
            continue
        area = cv2.contourArea(c)
        per = cv2.arcLength(c, True)
        if area < min_area or area > max_area or per <= 0 or 4 * np.pi * area / per**2 < min_circularity:
            continue
        x, y, w, h = cv2.boundingRect(c)
        pad = 4
        x0, y0, x1, y1 = max(x - pad, 0), max(y - pad, 0), min(x + w + pad, W), min(y + h + pad, H)
        if x0 == 0 or y0 == 0 or x1 == W or y1 == H:
            continue  # touches the image border: centroid would be cut
        roi = grey[y0:y1, x0:x1]
        hole = np.zeros(roi.shape, np.uint8)
        cv2.drawContours(hole, [c - [x0, y0]], -1, 255, thickness=cv2.FILLED)
        k = np.ones((3, 3), np.uint8)
        inner = cv2.dilate(hole, k, iterations=2) > 0
        ring = (cv2.dilate(hole, k, iterations=4) > 0) & ~inner
        core = cv2.erode(hole, k, iterations=1) > 0
        if not ring.any():
            continue
        bg = float(np.median(roi[ring]))
        fg = float(np.median(roi[core])) if core.sum() >= 3 else float(roi[hole > 0].min())
        if bg - fg < min_contrast:
            continue
        wgt = np.clip((bg - roi) / (bg - fg), 0.0, 1.0) * inner
        s = wgt.sum()
        if s <= 0:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        centers.append([float((wgt * xx).sum() / s), float((wgt * yy).sum() / s)])
        areas.append(float(s))
        if bgr is not None:
            sel = core if core.sum() >= 3 else hole > 0
            mean = bgr[y0:y1, x0:x1][sel].astype(float).mean(axis=0)
            chroma.append(float((mean.max() - mean.min()) / max(mean.max(), 1.0)))
        else:
            chroma.append(0.0)
    return Blobs(np.array(centers).reshape(-1, 2), np.array(areas), np.array(chroma))


def identify(blobs: Blobs, model_pts: np.ndarray, fiducial_idx: np.ndarray, camera: CameraModel,
             *, min_chroma: float = 0.35, match_frac: float = 0.3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Correspondences between detected blobs and model dots.

    ``model_pts`` (N, 3) target frame; ``fiducial_idx`` the model indices of the coloured dots;
    ``camera`` the nominal camera (for PnP). Returns (model indices, blob indices, initial
    ``T_c_t``). Raises :class:`DotError` if the fiducials are not all seen or no assignment
    explains the image.
    """
    nf = len(fiducial_idx)
    cand = np.flatnonzero(blobs.chroma >= min_chroma)
    if len(cand) != nf:
        raise DotError(f"expected {nf} coloured fiducial dots, found {len(cand)}: is the whole target in view?")
    if len(blobs.centers) < 6:
        raise DotError(f"only {len(blobs.centers)} dots detected")
    K = camera.K
    ideal = camera.undistort_pixels(blobs.centers)
    tree = cKDTree(blobs.centers)
    spacing = float(np.median(tree.query(blobs.centers, k=2)[0][:, 1]))
    fid_model = model_pts[fiducial_idx].astype(np.float64)

    def match(T):
        pc = apply(T, model_pts)
        if np.any(pc[:, 2] <= 0):
            return None
        d, j = tree.query(camera.project(pc))
        hit = d < match_frac * spacing
        return (int(hit.sum()), -float(np.sum(d[hit]))), np.flatnonzero(hit), j[hit]

    best = None
    for perm in itertools.permutations(cand):
        ok, rvec, tvec = cv2.solvePnP(fid_model, ideal[list(perm)].astype(np.float64), K, None,
                                      flags=cv2.SOLVEPNP_SQPNP)
        if not ok or not np.all(np.isfinite(tvec)) or tvec[2, 0] <= 0:
            continue
        T = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
        m = match(T)
        if m is not None and (best is None or m[0] > best[0]):
            best = (*m, T)
    if best is None or best[0][0] < max(8, len(model_pts) // 3):
        raise DotError("could not identify the target's dots (no fiducial assignment explains the image)")
    # one PnP over every match, then match again: catches dots the fiducials' pose missed
    _, mi, bi, T = best
    ok, rvec, tvec = cv2.solvePnP(model_pts[mi].astype(np.float64), ideal[bi].astype(np.float64), K, None,
                                  flags=cv2.SOLVEPNP_SQPNP)
    if ok:
        T2 = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
        m = match(T2)
        if m is not None and m[0] >= best[0]:
            _, mi, bi = m
            T = T2
    _, first = np.unique(bi, return_index=True)  # one model dot per blob
    return mi[first], bi[first], T


def circle_centroid_bias(camera: CameraModel, T_c_t: np.ndarray, centers_t: np.ndarray, normals_t: np.ndarray,
                         radii: np.ndarray, n: int = 72) -> np.ndarray:
    """Bias (N, 2) px of each dot's image centroid: area centroid of the projected circle (a
    dense polygon, lens distortion included) minus the projection of the circle's centre."""
    centers_t = np.asarray(centers_t, float)
    normals_t = np.asarray(normals_t, float)
    th = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    out = np.zeros((len(centers_t), 2))
    for i, (c, nrm, r) in enumerate(zip(centers_t, normals_t, radii)):
        e1 = np.cross(nrm, [1.0, 0.0, 0.0] if abs(nrm[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(nrm, e1)
        ring = c + r * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
        p = camera.project(apply(T_c_t, ring))
        x, y = p[:, 0], p[:, 1]
        xn, yn = np.roll(x, -1), np.roll(y, -1)
        cross = x * yn - xn * y
        a = cross.sum() / 2.0
        cx = ((x + xn) * cross).sum() / (6.0 * a)
        cy = ((y + yn) * cross).sum() / (6.0 * a)
        out[i] = np.array([cx, cy]) - camera.project(apply(T_c_t, c[None]))[0]
    return out
