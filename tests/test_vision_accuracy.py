"""The issue's accuracy targets on synthetic images with ground truth, side by side with the
plain OpenCV pipeline (findContours + fitEllipse + the same pose solver).

Images: 640×480, anti-aliased, σ = 2 grey levels of noise, a 10 mm red disc on a light face,
300–1200 mm from a 2500 px camera, 0–70° obliquity.
"""

from __future__ import annotations

import numpy as np
import pytest

from labctl.bench.synthetic_images import issue_camera, random_disc_pose, render_disc
from labctl.bench.vision_baselines import opencv_marker_ellipse
from labctl.vision import circle_poses, detect_markers, marker_pose_candidates

CASES = 160
RADIUS = 10.0


def _best(cands, normal):
    errs = [np.degrees(np.arccos(np.clip(c.normal @ normal, -1, 1))) for c in cands]
    k = int(np.argmin(errs))
    return errs[k], cands[k]


@pytest.fixture(scope="module")
def results():
    cam = issue_camera()
    rng = np.random.default_rng(2024)
    rows = []
    for _ in range(CASES):
        center, normal = random_disc_pose(rng, cam, range_mm=(300, 1200), obliquity_deg=(0, 70), radius=RADIUS)
        img = render_disc(cam, center, normal, RADIUS, rng=rng, noise_sigma=2.0)
        rng_mm = np.linalg.norm(center)
        obliquity = np.degrees(np.arccos(-normal @ center / rng_mm))
        found = detect_markers(img)
        assert len(found) == 1
        ours_n, ours = _best(marker_pose_candidates(found[0], cam, RADIUS), normal)
        cv_n, cv = _best(circle_poses(opencv_marker_ellipse(img), RADIUS, cam.K), normal)
        rows.append((obliquity, ours_n, 100 * np.linalg.norm(ours.center - center) / rng_mm,
                     cv_n, 100 * np.linalg.norm(cv.center - center) / rng_mm))
    return np.array(rows)


def test_normal_accuracy_at_obliquity_20_deg_and_more(results):
    r = results[results[:, 0] >= 20.0]
    assert len(r) > 80
    ours, cv = r[:, 1], r[:, 3]
    print(f"normal error (deg), ours median {np.median(ours):.3f} p95 {np.percentile(ours, 95):.3f}; "
          f"OpenCV median {np.median(cv):.3f} p95 {np.percentile(cv, 95):.3f}")
    assert np.median(ours) <= 0.25
    assert np.percentile(ours, 95) <= 0.75
    assert np.median(ours) < np.median(cv)
    assert np.percentile(ours, 95) < np.percentile(cv, 95)
    assert np.all(np.isfinite(ours))


def test_centre_accuracy_as_percent_of_range(results):
    ours, cv = results[:, 2], results[:, 4]
    print(f"centre error (% of range), ours median {np.median(ours):.3f} p95 {np.percentile(ours, 95):.3f}; "
          f"OpenCV median {np.median(cv):.3f} p95 {np.percentile(cv, 95):.3f}")
    assert np.median(ours) <= 0.3
    assert np.percentile(ours, 95) <= 0.6
    # the pixel-contour pipeline is about 1 % off (its ellipse sits half a pixel inside the edge)
    assert np.median(cv) > 0.5
    assert np.median(ours) < 0.2 * np.median(cv)
