"""``labctl vision pose`` end to end on synthetic images."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
import yaml
from cli_run import run_cli

from labctl.bench.synthetic_images import issue_camera, render_disc
from labctl.cli import main
from labctl.geometry.camera_io import camera_info_dict

CAM = issue_camera()


def _normal(center, deg):
    s = -center / np.linalg.norm(center)
    b = np.cross(s, [1.0, 0, 0])
    b /= np.linalg.norm(b)
    return np.cos(np.radians(deg)) * s + np.sin(np.radians(deg)) * b


@pytest.fixture
def scene(tmp_path):
    rng = np.random.default_rng(0)
    c1 = np.array([20.0, -10.0, 600.0])
    n = _normal(c1, 45)
    c2 = c1 + [30.0, 10.0, -5.0]
    cv2.imwrite(str(tmp_path / "a.png"), render_disc(CAM, c1, n, rng=rng))
    cv2.imwrite(str(tmp_path / "b.png"), render_disc(CAM, c2, n, rng=rng))
    (tmp_path / "cam.yaml").write_text(yaml.safe_dump({"camera": CAM.to_dict()}))
    (tmp_path / "ros.yaml").write_text(yaml.safe_dump(camera_info_dict(CAM)))
    cv2.imwrite(str(tmp_path / "empty.png"), np.full((480, 640, 3), 200, np.uint8))
    return tmp_path, c1, c2, n


_run = run_cli


def test_one_image_json(scene, capsys, monkeypatch):
    d, c1, _, n = scene
    monkeypatch.chdir(d)
    try:
        main(["vision", "pose", "a.png", "--radius", "10", "--camera", "cam.yaml", "--json"])
    except SystemExit as exc:
        assert not exc.code
    data = json.loads(capsys.readouterr().out)
    (marker,) = data["images"][0]["markers"]
    best = max(marker["candidates"], key=lambda c: np.dot(c["normal"], n))
    assert np.linalg.norm(np.subtract(best["center_mm"], c1)) < 0.5
    assert np.degrees(np.arccos(np.clip(np.dot(best["normal"], n), -1, 1))) < 0.3
    assert (d / "a_pose.png").is_file() and cv2.imread(str(d / "a_pose.png")).shape == (480, 640, 3)


def test_two_images_resolve_the_duality(scene, capsys):
    d, _, c2, n = scene
    out_png = d / "annotated.png"
    try:
        main(["vision", "pose", str(d / "a.png"), str(d / "b.png"), "--radius", "10", "--camera", str(d / "ros.yaml"),
              "--out", str(out_png), "--json"])
    except SystemExit as exc:
        assert not exc.code
    data = json.loads(capsys.readouterr().out)
    assert data["duality"]["resolved"]
    chosen = data["duality"]["pose"]
    assert np.degrees(np.arccos(np.clip(np.dot(chosen["normal"], n), -1, 1))) < 0.3
    assert np.linalg.norm(np.subtract(chosen["center_mm"], c2)) < 0.5
    assert out_png.is_file()


def test_errors_are_one_line_with_exit_2(scene, capsys):
    d = scene[0]
    cam = str(d / "cam.yaml")
    code, _, err = _run(capsys, "vision", "pose", str(d / "empty.png"), "--radius", "10", "--camera", cam)
    assert code == 2 and "no marker" in err and err.count("\n") == 1
    code, _, err = _run(capsys, "vision", "pose", str(d / "a.png"), "--radius", "10", "--camera", str(d / "a.png"))
    assert code == 2 and err.count("\n") == 1
    code, _, err = _run(capsys, "vision", "pose", str(d / "cam.yaml"), "--radius", "10", "--camera", cam)
    assert code == 2 and "cannot read image" in err
    code, _, err = _run(capsys, "vision", "pose", str(d / "a.png"), "--radius", "-1", "--camera", cam)
    assert code == 2 and "radius" in err


def test_no_marker_says_why(scene, capsys):
    d = scene[0]
    img = cv2.imread(str(d / "a.png"))
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV_FULL)
    hsv[..., 0] = (hsv[..., 0].astype(int) + 25) % 256  # the marker turns orange (hue +35°)
    cv2.imwrite(str(d / "orange.png"), cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR_FULL))
    code, _, err = _run(capsys, "vision", "pose", str(d / "orange.png"), "--radius", "10", "--camera",
                        str(d / "cam.yaml"))
    assert code == 2 and err.count("\n") == 1
    seen = int(err.split("nearest saturated colour seen is hue ")[1].split("°")[0])
    assert 30 <= seen <= 38  # the disc's hue, 358° + 35°


def test_learn_color_writes_the_window_into_the_driver_file(scene, tmp_path, capsys):
    from labctl.workspace import sample_lab_path

    d = scene[0]
    lab = tmp_path / "lab"
    shutil.copytree(sample_lab_path(), lab)
    img = cv2.imread(str(d / "a.png"))
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV_FULL)
    hsv[..., 0] = (hsv[..., 0].astype(int) + 25) % 256  # orange-red paint under this light
    cv2.imwrite(str(d / "orange.png"), cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR_FULL))
    driver = lab / "drivers" / "fixed_camera.yaml"
    before = driver.read_text()
    # dry run: measured, checked, nothing written
    code, out, err = _run(capsys, "--lab", str(lab), "--json", "vision", "learn-color", str(d / "orange.png"),
                          "--camera", "fixed", "--dry-run")
    assert code == 0, err
    res = json.loads(out)
    lo, hi = res["hue_range_deg"]
    assert lo < 35 < hi and hi - lo < 40 and res["markers_found"] == 1 and res["markers_found_before"] == 0
    assert driver.read_text() == before
    code, out, err = _run(capsys, "--lab", str(lab), "--json", "vision", "learn-color", str(d / "orange.png"),
                          "--camera", "fixed")
    assert code == 0 and json.loads(out)["written"]
    cfg = yaml.safe_load(driver.read_text())
    assert cfg["marker_hue_deg"] == [lo, hi] and cfg["marker_min_saturation"] == res["min_saturation"]
    assert "# Overhead camera C1" in driver.read_text()  # comments kept
    # an image without the colour: one line, exit 2, the file untouched
    written = driver.read_text()
    code, _, err = _run(capsys, "--lab", str(lab), "vision", "learn-color", str(d / "empty.png"), "--camera", "fixed")
    assert code == 2 and err.count("\n") == 1 and driver.read_text() == written


def test_pose_images_is_the_pipeline_in_vision(scene):
    """The pipeline lives in labctl.vision (arrays in, results out); the command only does files."""
    from labctl.vision.pose_images import ImagePoseError, annotate_posed, pose_images

    d, c1, c2, n = scene
    a, b = cv2.imread(str(d / "a.png")), cv2.imread(str(d / "b.png"))
    posed = pose_images([a, b], CAM, 10.0)
    assert posed.duality is not None and not posed.duality.ambiguous
    assert np.linalg.norm(posed.duality.best.center - c2) < 5.0  # the second image's marker, camera frame
    assert abs(float(np.dot(posed.duality.best.normal, n))) > np.cos(np.radians(2))
    assert annotate_posed(b, posed, CAM).shape == b.shape
    with pytest.raises(ImagePoseError) as err:
        pose_images([a, np.full_like(a, 200)], CAM, 10.0)
    assert err.value.index == 1 and "no marker" in str(err.value)


def test_a_response_that_does_not_match_the_frame_is_said_in_one_line(scene, capsys, monkeypatch):
    """A gamma-2.2 frame with a defocused marker (the project's oracle), posed as linear: the result
    says the response looks wrong; posed with --response 'gamma 2.2' it does not."""
    from labctl.bench import _vision_oracle as oracle

    d, *_ = scene
    monkeypatch.chdir(d)
    cam = oracle.Cam(f=CAM.f / CAM.dx)
    disc = oracle.random_pose(np.random.default_rng(4), cam, obliquity_deg=(30.0, 45.0))
    img, _ = oracle.render(cam, disc, oracle.Conditions(response="gamma 2.2", defocus_px=2.0), np.random.default_rng(5))
    cv2.imwrite("g.png", img)
    for response, warned in (("linear", True), ("gamma 2.2", False)):
        code, out, _ = _run(capsys, "vision", "pose", "g.png", "--radius", "10", "--camera", "cam.yaml",
                            "--response", response, "--json")
        assert code == 0
        data = json.loads(out)
        assert ("response_warning" in data) is warned
        if warned:
            assert "\n" not in data["response_warning"] and "--response linear" in data["response_warning"]
