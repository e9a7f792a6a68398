"""``labctl bench vision``: marker detection, fit + pose and the ellipse fitters, timed against
baselines in the same run (medians), on synthetic 640×480 images of the issue's test scene; and
the degradation suite (:mod:`._vision_suite`: ours vs the plain OpenCV pipeline on
images of the independent renderer :mod:`._vision_oracle`), with its acceptance checks.

The suite's size is ``LABCTL_BENCH_VISION_PAIRS`` image pairs per case (default 25; 3 with
``--quick``); ``LABCTL_BENCH_VISION_ONLY`` restricts it to conditions containing that text.
``suite_acceptance`` lists as ``inconclusive`` a normal p95 or centre median above the baseline's
whose paired bootstrap interval contains 0 (too few pairs to tell), as ``failures`` one above it."""

from __future__ import annotations

import os
import statistics
import time

import cv2
import numpy as np

from ._timing import median_time, row


def _interleaved(cases: dict, repeat: int, warmup: int = 3) -> dict:
    """Median wall time (s) of each case, timed round-robin (one call of each per round)."""
    for fn in cases.values():
        for _ in range(warmup):
            fn()
    samples: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(repeat):
        for name, fn in cases.items():
            t0 = time.perf_counter()
            fn()
            samples[name].append(time.perf_counter() - t0)
    return {name: statistics.median(s) for name, s in samples.items()}


def run(quick: bool = False) -> dict:
    """Time marker detection, fit + pose and the ellipse fitters against baselines, then run the degradation suite."""
    from ..vision import (
        circle_poses,
        detect_markers,
        detect_markers_windowed,
        ellipse_from_cv_box,
        fit_ellipse,
        marker_pose_candidates,
    )
    from .synthetic_images import issue_camera, render_disc
    from .vision_baselines import centroid_inrange_moments

    repeat = 15 if quick else 200
    cam = issue_camera()
    rng = np.random.default_rng(1)
    center = np.array([40.0, -25.0, 900.0])
    sight = -center / np.linalg.norm(center)
    side = np.cross(sight, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    normal = np.cos(np.radians(45)) * sight + np.sin(np.radians(45)) * side
    img = render_disc(cam, center, normal, 10.0, rng=rng)
    marker = detect_markers(img)[0]
    predicted = (marker.centroid[0] + 3.0, marker.centroid[1] - 2.0)
    half = 48.0
    rows = []

    # interleaved: each round times every case once, so load on the shared machine hits the
    # numerator and denominator of each ratio alike
    cam_distorted = issue_camera(kappa1=2e-3)
    boundary32 = marker.boundary.astype(np.float32)
    K = cam.K
    cases = {
        "base": lambda: centroid_inrange_moments(img),
        "full": lambda: detect_markers(img),
        "full_c": lambda: detect_markers(img, refine=False),
        "win": lambda: detect_markers_windowed(img, predicted, half),
        "win_c": lambda: detect_markers_windowed(img, predicted, half, refine=False),
    }
    tm = _interleaved(cases, repeat)
    pose_cases = {
        "pose": lambda: marker_pose_candidates(marker, cam, 10.0),
        "pose_k": lambda: marker_pose_candidates(marker, cam_distorted, 10.0),
        "pose_cv": lambda: circle_poses(ellipse_from_cv_box(cv2.fitEllipse(boundary32)), 10.0, K),
        "cv_fit": lambda: cv2.fitEllipse(boundary32),
    }
    tm.update(_interleaved(pose_cases, repeat * 5))
    n_pts = len(marker.boundary)
    rows.append(row("detect full frame (sub-pixel boundary + fit)", tm["full"], "cv2.inRange+cv2.moments", tm["base"]))
    rows.append(row("detect full frame, centroid only", tm["full_c"], "cv2.inRange+cv2.moments", tm["base"]))
    rows.append(row(f"detect windowed ±{half:.0f} px (sub-pixel + fit)", tm["win"], "same, full frame", tm["full"]))
    rows.append(row(f"detect windowed ±{half:.0f} px, centroid only", tm["win_c"], "same, full frame", tm["full_c"]))
    rows.append(row(f"fit + pose of one marker ({n_pts} pts)", tm["pose"], "cv2.fitEllipse + same pose", tm["pose_cv"]))
    rows.append(row(f"fit + pose of one marker ({n_pts} pts), κ1 ≠ 0 (undistortion)", tm["pose_k"],
                    "cv2.fitEllipse + same pose", tm["pose_cv"]))
    rows.append(row(f"cv2.fitEllipse alone ({n_pts} pts)", tm["cv_fit"], "fit + pose (ours)", tm["pose"]))

    # the ellipse fitters on 360 noisy points (σ = 0.5 px): full boundary and half arc
    accuracy: dict[str, dict[str, dict[str, float]]] = {}
    for name, arc in (("full", 2 * np.pi), ("half arc", np.pi)):
        frng = np.random.default_rng(5)
        sets = []
        for _ in range(40 if quick else 300):
            from ..vision import Ellipse

            e = Ellipse.from_params(frng.uniform(200, 400, 2), (frng.uniform(15, 80), frng.uniform(8, 60)),
                                    frng.uniform(0, np.pi))
            t0 = frng.uniform(0, 2 * np.pi)
            sets.append((e, e.points(360, t0, t0 + arc) + frng.normal(0, 0.5, (360, 2))))
        fitters = {
            "labctl fit_ellipse": lambda p: fit_ellipse(p),
            "cv2.fitEllipse": lambda p: ellipse_from_cv_box(cv2.fitEllipse(p.astype(np.float32))),
            "cv2.fitEllipseAMS": lambda p: ellipse_from_cv_box(cv2.fitEllipseAMS(p.astype(np.float32))),
            "cv2.fitEllipseDirect": lambda p: ellipse_from_cv_box(cv2.fitEllipseDirect(p.astype(np.float32))),
        }
        accuracy[name] = {}
        pts0 = sets[0][1]
        def cv_fit(p=pts0):
            return cv2.fitEllipse(p.astype(np.float32))

        t_cv = median_time(cv_fit, repeat * 2)
        for fname, fn in fitters.items():
            errs = [np.linalg.norm(fn(p).center - e.center) for e, p in sets]
            accuracy[name][fname] = {"centre_rms_px": float(np.sqrt(np.mean(np.square(errs))))}
            def fit(p=pts0, fn=fn):
                return fn(p)

            t = median_time(fit, repeat * 2)
            rows.append(row(f"ellipse fit {name}, 360 pts: {fname}", t, "cv2.fitEllipse", t_cv))
    from ._vision_suite import acceptance, run_suite

    n_pairs = 3 if quick else int(os.environ.get("LABCTL_BENCH_VISION_PAIRS", "25"))
    suite = run_suite(n_pairs=n_pairs, only=os.environ.get("LABCTL_BENCH_VISION_ONLY") or None)
    return {
        "rows": rows,
        "suite_pairs_per_case": n_pairs,
        "suite": suite,
        "suite_acceptance": acceptance(suite),
        "windowed_speedup": tm["full"] / tm["win"],
        "windowed_speedup_centroid_only": tm["full_c"] / tm["win_c"],
        "fit_pose_median_us": tm["pose"] * 1e6,
        "fit_pose_distorted_median_us": tm["pose_k"] * 1e6,
        "ellipse_fit_centre_rms_px": accuracy,
    }
