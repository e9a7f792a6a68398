"""Resolving the two-fold ambiguity of a circle's pose from two images (He et al. 1996, §3.3).

Each image of one circular marker gives two candidate normals (§3.2). Between the two images
the object moved with a known kind of motion:

* **translation** — the true normal is the same in both images; the false ones differ
  (the false normal mirrors the true one about the line of sight, which changes).
* **planar motion** with known plane normal p — the true normal's component along p is the
  same in both images (the object only rotates about p and translates in the plane).

Vectors of both images must be compared in one frame. When the camera itself moved between
the images, pass ``R_first_second`` (3×3, maps vectors of the second image's camera frame into
the first's, i.e. R_{c1←c2}); ``plane_normal`` is given in the first image's camera frame. With
poses already expressed in a common (e.g. world) frame, leave ``R_first_second`` as None.

The choice is reported with its margin: how much worse (rad) the best hypothesis for the other
candidate of the second image is. Below ``min_margin_rad`` the answer is "ambiguous", e.g.
when the marker faces the camera squarely and the two candidates merge, or when the motion
was along the line of sight and left both candidates unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .circle_pose import CirclePose

DEFAULT_MIN_MARGIN_RAD = math.radians(0.1)


@dataclass(frozen=True)
class DualityResult:
    """``pose``: the second image's true pose, or None when ambiguous; ``best``: the better
    candidate regardless; ``index``: its index (0/1) in the second pair; ``margin_rad``: score
    gap between the two candidates of the second image (rad, ≥ 0); ``scores_rad``: each
    candidate's mismatch with the first image (rad)."""

    pose: CirclePose | None
    best: CirclePose
    index: int
    margin_rad: float
    scores_rad: tuple[float, float]
    ambiguous: bool
    threshold_rad: float = DEFAULT_MIN_MARGIN_RAD  # the margin it had to reach
    suspect: bool = False  # a marker behind it carries a quality flag: never silently trusted

    def to_dict(self) -> dict:
        """JSON-ready dict of the resolution: chosen index, margin, threshold and scores (deg), chosen pose."""
        return {"resolved": not self.ambiguous, "index": self.index, "margin_deg": math.degrees(self.margin_rad),
                "threshold_deg": math.degrees(self.threshold_rad), "suspect": self.suspect,
                "scores_deg": [math.degrees(s) for s in self.scores_rad], "pose": self.best.to_dict()}


def _angle(u: np.ndarray, v: np.ndarray) -> float:
    return math.atan2(float(np.linalg.norm(np.cross(u, v))), float(u @ v))


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float).ravel()
    n = float(np.linalg.norm(v)) if v.shape == (3,) else float("nan")
    if not (math.isfinite(n) and n > 0):
        raise ValueError("expected a finite, non-zero 3-vector")
    return v / n


def resolve_duality_detailed(first, second, motion: str = "translation", plane_normal=None, *,
                             R_first_second=None, min_margin_rad: float = DEFAULT_MIN_MARGIN_RAD) -> DualityResult:
    """Pick the true pose of the *second* image from two candidate pairs (paper §3.3).

    ``first``, ``second``: the (CirclePose, CirclePose) pairs of :func:`circle_poses` for the
    two images. ``motion``: ``"translation"`` (true normals equal) or ``"planar"`` (true
    normals have equal components along ``plane_normal``, a 3-vector in the first image's
    frame). ``R_first_second`` rotates second-frame vectors into the first frame (default:
    the frames coincide). Each candidate j of the second image scores the smallest mismatch
    (rad) with either candidate of the first; the margin is the gap between the two scores.
    Ambiguous when the margin is below ``min_margin_rad``.
    """
    if len(first) != 2 or len(second) != 2:
        raise ValueError("first and second must each be a pair of CirclePose candidates")
    R = np.eye(3) if R_first_second is None else np.asarray(R_first_second, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError("R_first_second must be a finite 3×3 rotation")
    n1 = [_unit(p.normal) for p in first]
    n2 = [R @ _unit(p.normal) for p in second]
    if motion == "translation":
        def mismatch(a, b):
            return _angle(a, b)
    elif motion == "planar":
        if plane_normal is None:
            raise ValueError("planar motion needs plane_normal")
        pn = _unit(plane_normal)

        def mismatch(a, b):  # difference of elevation above the motion plane (rad)
            return abs(math.asin(max(-1.0, min(1.0, float(a @ pn)))) - math.asin(max(-1.0, min(1.0, float(b @ pn)))))
    else:
        raise ValueError(f"motion must be 'translation' or 'planar', got {motion!r}")
    scores = tuple(min(mismatch(a, b) for a in n1) for b in n2)
    index = 0 if scores[0] <= scores[1] else 1
    margin = abs(scores[1] - scores[0])
    ambiguous = not (margin >= min_margin_rad)
    best = second[index]
    return DualityResult(None if ambiguous else best, best, index, margin, scores, ambiguous, min_margin_rad)


DEFAULT_K_SIGMA = 3.0


def resolve_duality_noise_aware(first, second, motion: str = "translation", plane_normal=None, *,
                                R_first_second=None, k_sigma: float = DEFAULT_K_SIGMA,
                                min_margin_rad: float = DEFAULT_MIN_MARGIN_RAD) -> DualityResult:
    """Pick the true pose of the second image from two :class:`~.circle_pose.MarkerPoses`
    (paper §3.3), deciding only when the margin stands out of the noise.

    Under noise each candidate's score (its mismatch with the first image) wanders by about
    σ = √(σ₁² + σ₂²), σᵢ the larger normal standard deviation of image i's candidates (their
    covariances, :func:`~.circle_pose.marker_poses`), and the margin — the difference of two such
    scores — by about √2 σ. The choice is made only when the margin exceeds
    max(``k_sigma`` · √2 σ, ``min_margin_rad``); otherwise the result is ambiguous. ``suspect``
    is set when either marker carries a quality flag. Other arguments as
    :func:`resolve_duality_detailed`.
    """
    s1 = max(first.normal_sigma_rad)
    s2 = max(second.normal_sigma_rad)
    sigma = math.sqrt(s1 * s1 + s2 * s2)
    threshold = max(k_sigma * math.sqrt(2.0) * sigma, min_margin_rad)
    if not math.isfinite(threshold):
        threshold = math.inf
    res = resolve_duality_detailed(first.candidates, second.candidates, motion, plane_normal,
                                   R_first_second=R_first_second, min_margin_rad=threshold)
    suspect = not (first.trusted and second.trusted)
    return DualityResult(res.pose, res.best, res.index, res.margin_rad, res.scores_rad, res.ambiguous, threshold,
                         suspect)


def resolve_duality(first, second, motion: str = "translation", plane_normal=None, *,
                    R_first_second=None, min_margin_rad: float = DEFAULT_MIN_MARGIN_RAD) -> CirclePose | None:
    """The true :class:`CirclePose` of the second image, or None when ambiguous (paper §3.3).
    See :func:`resolve_duality_detailed` for the arguments and the margin."""
    return resolve_duality_detailed(first, second, motion, plane_normal, R_first_second=R_first_second,
                                    min_margin_rad=min_margin_rad).pose


# floors of the per-image covariances in the pair test: the propagated covariances are of the
# boundary noise only; a normal is never known better than 0.05°, a centre than 0.02 mm
CONSISTENCY_NORMAL_FLOOR_RAD = math.radians(0.05)
CONSISTENCY_CENTRE_FLOOR_MM = 0.02
DEFAULT_CONSISTENCY_K = 4.0


@dataclass(frozen=True)
class PairConsistency:
    """Whether two images' poses of one marker agree with the known motion between them.

    ``consistent``: the best pairing of candidates agrees within ``k_sigma``; ``pair``: that
    pairing (index in the first, index in the second); ``normal_z`` / ``centre_z``: its
    Mahalanobis distances (σ units; centre_z is 0 when no displacement was given)."""

    consistent: bool
    pair: tuple[int, int]
    normal_z: float
    centre_z: float
    k_sigma: float

    def to_dict(self) -> dict:
        """JSON-ready dict: whether the pair is consistent, the chosen pair, z-scores and ``k_sigma``."""
        return {"consistent": self.consistent, "pair": list(self.pair), "normal_z": self.normal_z,
                "centre_z": self.centre_z, "k_sigma": self.k_sigma}


def _mahalanobis(d: np.ndarray, cov: np.ndarray, floor: float) -> float:
    s = np.asarray(cov, float) + np.eye(3) * floor * floor
    try:
        return math.sqrt(max(float(d @ np.linalg.solve(s, d)), 0.0))
    except np.linalg.LinAlgError:
        return math.inf


def pose_pair_consistency(first, second, *, displacement_mm=None, R_first_second=None,
                          k_sigma: float = DEFAULT_CONSISTENCY_K) -> PairConsistency:
    """Check two :class:`~.circle_pose.MarkerPoses` of one marker against the known motion
    between the images (paper §3.3's two views, used as a cross-check of §3.2's poses).

    One image cannot tell a smooth systematic error (an uncalibrated lens bends the image of a
    marker into another ellipse) from the truth; two images can, because the error differs
    between them while the motion is known. For each pairing (i, j) of candidates: the normals,
    expressed in the first frame (``R_first_second`` = R_{c1←c2}, default identity), must agree
    — translation keeps a normal — and, when ``displacement_mm`` (the expected
    R_{c1←c2} c₂ − c₁, mm, first camera frame: the marker's motion less the camera's) is given,
    the centres must have moved by it. Agreement is judged by the Mahalanobis distance under the
    sum of both poses' covariances (with floors :data:`CONSISTENCY_NORMAL_FLOOR_RAD`,
    :data:`CONSISTENCY_CENTRE_FLOOR_MM`); the pair is consistent when the best pairing has both
    distances ≤ ``k_sigma``. Translation-only motion (normals kept) is assumed."""
    R = np.eye(3) if R_first_second is None else np.asarray(R_first_second, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError("R_first_second must be a finite 3×3 rotation")
    disp = None if displacement_mm is None else np.asarray(displacement_mm, dtype=float).reshape(3)
    best: tuple[float, tuple[int, int], float, float] | None = None
    for i in range(2):
        for j in range(2):
            n1, n2 = np.asarray(first.candidates[i].normal, float), R @ np.asarray(second.candidates[j].normal, float)
            zn = _mahalanobis(n2 - n1, first.normal_cov[i] + R @ second.normal_cov[j] @ R.T,
                              CONSISTENCY_NORMAL_FLOOR_RAD)
            zc = 0.0
            if disp is not None:
                c1 = np.asarray(first.candidates[i].center, float)
                c2 = R @ np.asarray(second.candidates[j].center, float)
                zc = _mahalanobis(c2 - c1 - disp, first.center_cov[i] + R @ second.center_cov[j] @ R.T,
                                  CONSISTENCY_CENTRE_FLOOR_MM)
            key = max(zn, zc)
            if best is None or key < best[0]:
                best = (key, (i, j), zn, zc)
    assert best is not None  # four pairings were scored
    key, pair, zn, zc = best
    return PairConsistency(bool(key <= k_sigma), pair, zn, zc, float(k_sigma))
