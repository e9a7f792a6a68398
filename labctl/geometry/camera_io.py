"""Camera files: labctl's calibration YAML and ROS ``camera_info`` YAML.

* labctl: ``camera: {f, kappa1, sx, cx, cy, dx, dy, ncx, nfx, width, height}`` (Tsai model),
  optionally with a pose (``T_w_c`` or ``T_f_c``) and fit statistics beside it.
* ROS ``sensor_msgs/CameraInfo`` YAML (camera_calibration_parsers): ``image_width``,
  ``image_height``, ``camera_matrix``, ``distortion_model: plumb_bob``,
  ``distortion_coefficients``, ``rectification_matrix``, ``projection_matrix``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from .camera import CameraModel


def camera_info_dict(cam: CameraModel, name: str = "camera") -> dict:
    """ROS camera_info YAML content for ``cam`` (plumb_bob, fitted where κ1 ≠ 0)."""
    K, dist, _ = cam.to_opencv()
    P = np.hstack([K, np.zeros((3, 1))])

    def mat(rows, cols, a):
        return {"rows": rows, "cols": cols, "data": [float(v) for v in np.ravel(a)]}

    return {
        "image_width": int(cam.width),
        "image_height": int(cam.height),
        "camera_name": name,
        "camera_matrix": mat(3, 3, K),
        "distortion_model": "plumb_bob",
        "distortion_coefficients": mat(1, 5, dist),
        "rectification_matrix": mat(3, 3, np.eye(3)),
        "projection_matrix": mat(3, 4, P),
    }


def camera_from_info(info: dict, *, dx: float = 0.01, dy: float | None = None) -> CameraModel:
    """Tsai model from a ROS camera_info mapping. The sensor pitch is not in camera_info;
    ``dx``/``dy`` (mm) only scale f, the projection does not depend on them."""
    K = np.asarray(info["camera_matrix"]["data"], dtype=float).reshape(3, 3)
    dist = np.asarray(info.get("distortion_coefficients", {}).get("data", [0, 0, 0, 0, 0]), dtype=float)
    w, h = int(info["image_width"]), int(info["image_height"])
    cam, _ = CameraModel.from_opencv(K, dist, dx=dx, dy=dy or dx, ncx=w, nfx=w, width=w, height=h)
    return cam


def load_camera_file(path: Path | str) -> CameraModel:
    """Read a camera from a labctl calibration YAML or a ROS camera_info YAML.

    Raises ``ValueError`` with a one-line reason if the file is neither.
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read camera file: {str(exc).splitlines()[0]}") from None
    if isinstance(data, dict) and isinstance(data.get("camera"), dict):
        try:
            return CameraModel.from_dict(data["camera"])
        except TypeError as exc:
            raise ValueError(f"{path}: camera: {exc}") from None
    if isinstance(data, dict) and "camera_matrix" in data and "image_width" in data:
        try:
            return camera_from_info(data)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: not a valid camera_info file: {exc}") from None
    raise ValueError(f"{path}: not a camera file (expected a 'camera:' mapping or ROS camera_info keys)")
