"""``labctl vision pose`` end to end on synthetic images."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import yaml

from labctl.cli import main
from labctl.geometry.camera_io import camera_info_dict
from labctl.vision.synthetic import issue_camera, render_disc

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


def _run(capsys, *args):
    with pytest.raises(SystemExit) as exc:
        main(list(args))
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


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
