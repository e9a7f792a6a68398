"""Calibration files in ``calibration/``: write them atomically, read them back.

* ``fixed_camera.yaml``: ``camera:`` (:meth:`CameraModel.to_dict`), ``T_w_c:`` 4×4 (fixed
  camera C1 in the world W), ``stats:`` (rms_px, method, n_points, created, …).
* ``mobile_camera.yaml``: ``camera:``, ``T_f_c:`` 4×4 (hand-eye X: camera C2 in the robot
  flange F), ``stats:``.
* ``table.yaml``: ``T_w_table:`` 4×4 (the NC table's machine-zero frame in W), ``stats:``.

:func:`labctl.geometry.camera_io.load_camera_file` reads the camera files too. ROS
``camera_info`` YAML is written beside them on request (:func:`save_ros_camera_info`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from ..errors import LabctlError
from ..fsutil import atomic_write_text
from ..geometry import CameraModel
from ..geometry.camera_io import camera_info_dict

FIXED_FILE = "fixed_camera.yaml"
MOBILE_FILE = "mobile_camera.yaml"
TABLE_FILE = "table.yaml"
CALIBRATION_DIR = "calibration"


class CalibrationFileError(LabctlError):
    """A calibration file is missing, malformed or implausible (bad input: exit status 2; names the file)."""

    exit_code = 2


def _plain(v):
    if isinstance(v, np.ndarray):
        return [_plain(x) for x in v.tolist()]
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    return v


def _dump(header: str, data: dict) -> str:
    return header + yaml.safe_dump(_plain(data), sort_keys=False, default_flow_style=None, width=200)


def _matrix(T) -> list[list[float]]:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError("expected a finite 4×4 transform")
    return [[float(x) for x in row] for row in T]


def fixed_camera_text(camera: CameraModel, T_w_c: np.ndarray, stats: dict) -> str:
    """YAML text of ``fixed_camera.yaml``: C1's Tsai model, ``T_w_c`` (C1 → world W, mm) and ``stats``."""
    return _dump("# Fixed camera C1 (labctl calibrate): Tsai model and pose T_w_c (C1 -> world W), mm.\n",
                 {"camera": camera.to_dict(), "T_w_c": _matrix(T_w_c), "stats": stats})


def mobile_camera_text(camera: CameraModel, T_f_c: np.ndarray, stats: dict) -> str:
    """YAML text of ``mobile_camera.yaml``: C2's Tsai model, hand-eye ``T_f_c`` (C2 → flange F, mm), ``stats``."""
    return _dump("# Mobile camera C2 (labctl calibrate): Tsai model and hand-eye X = T_f_c (C2 -> flange F), mm.\n",
                 {"camera": camera.to_dict(), "T_f_c": _matrix(T_f_c), "stats": stats})


def table_text(T_w_table: np.ndarray, stats: dict) -> str:
    """YAML text of ``table.yaml``: ``T_w_table`` (table machine zero → world W, mm) and ``stats``."""
    return _dump("# NC table registration (labctl calibrate): machine-zero frame in the world W, mm.\n",
                 {"T_w_table": _matrix(T_w_table), "stats": stats})


def ros_camera_info_text(camera: CameraModel, name: str) -> str:
    """YAML text of a ROS ``camera_info`` for ``camera`` (plumb_bob distortion fitted to κ1)."""
    return _dump(f"# ROS camera_info for {name} (plumb_bob fitted to Tsai's kappa1 by labctl).\n",
                 camera_info_dict(camera, name))


def write_files(cal_dir: Path | str, files: dict[str, str]) -> list[Path]:
    """Write each ``name -> text`` atomically into ``cal_dir``; returns the paths written."""
    cal_dir = Path(cal_dir)
    out = []
    for name, text in files.items():
        atomic_write_text(cal_dir / name, text)
        out.append(cal_dir / name)
    return out


def save_ros_camera_info(cal_dir: Path | str, camera: CameraModel, name: str) -> Path:
    """Write ``cal_dir/NAME_info.yaml`` (ROS ``camera_info``) atomically; returns its path."""
    path = Path(cal_dir) / f"{name}_info.yaml"
    atomic_write_text(path, ros_camera_info_text(camera, name))
    return path


# --- reading ---------------------------------------------------------------------------------
def _read(path: Path) -> dict:
    if not path.is_file():
        raise CalibrationFileError(f"calibration file missing: {path} (run `labctl calibrate`)")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise CalibrationFileError(f"{path}: cannot read: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise CalibrationFileError(f"{path}: expected a YAML mapping")
    return data


def _T(path: Path, data: dict, key: str) -> np.ndarray:
    try:
        T = np.asarray(data[key], dtype=float)
    except KeyError:
        raise CalibrationFileError(f"{path}: missing key {key!r}") from None
    except (TypeError, ValueError):
        raise CalibrationFileError(f"{path}: {key} is not a numeric 4×4 matrix") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise CalibrationFileError(f"{path}: {key} must be a finite 4×4 matrix")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or abs(np.linalg.det(R) - 1) > 1e-6:
        raise CalibrationFileError(f"{path}: {key} is not a rigid transform")
    return T


def _camera(path: Path, data: dict) -> CameraModel:
    cam = data.get("camera")
    if not isinstance(cam, dict):
        raise CalibrationFileError(f"{path}: missing 'camera:' mapping")
    try:
        model = CameraModel.from_dict(cam)
    except TypeError as exc:
        raise CalibrationFileError(f"{path}: camera: {exc}") from None
    for name in ("f", "kappa1", "sx", "cx", "cy", "dx", "dy", "ncx", "nfx", "width", "height"):
        value = getattr(model, name)
        if not isinstance(value, int | float) or isinstance(value, bool) or not np.isfinite(value):
            raise CalibrationFileError(f"{path}: camera.{name}: expected a finite number, got {value!r}")
        if name not in ("kappa1", "cx", "cy") and not value > 0:
            raise CalibrationFileError(f"{path}: camera.{name}: expected a number > 0, got {value!r}")
    return model


def load_fixed_camera(cal_dir: Path | str) -> tuple[CameraModel, np.ndarray, dict]:
    """(camera, T_w_c1, stats) from ``fixed_camera.yaml``."""
    path = Path(cal_dir) / FIXED_FILE
    d = _read(path)
    return _camera(path, d), _T(path, d, "T_w_c"), dict(d.get("stats") or {})


def load_mobile_camera(cal_dir: Path | str) -> tuple[CameraModel, np.ndarray, dict]:
    """(camera, T_f_c2, stats) from ``mobile_camera.yaml``."""
    path = Path(cal_dir) / MOBILE_FILE
    d = _read(path)
    return _camera(path, d), _T(path, d, "T_f_c"), dict(d.get("stats") or {})


def load_table(cal_dir: Path | str) -> tuple[np.ndarray, dict]:
    """(T_w_table, stats) from ``table.yaml``."""
    path = Path(cal_dir) / TABLE_FILE
    d = _read(path)
    return _T(path, d, "T_w_table"), dict(d.get("stats") or {})


@dataclass(frozen=True)
class Calibration:
    """Everything ``labctl calibrate`` produces, as the rest of labctl uses it."""

    fixed_camera: CameraModel
    T_w_c1: np.ndarray
    mobile_camera: CameraModel
    T_f_c2: np.ndarray
    T_w_table: np.ndarray
    stats: dict = field(default_factory=dict)


def load_calibration(lab_root: Path | str) -> Calibration:
    """Read ``<lab_root>/calibration/{fixed_camera,mobile_camera,table}.yaml``.

    Raises :class:`CalibrationFileError` naming the first missing or malformed file.
    """
    cal_dir = Path(lab_root) / CALIBRATION_DIR
    c1, T_w_c1, s1 = load_fixed_camera(cal_dir)
    c2, T_f_c2, s2 = load_mobile_camera(cal_dir)
    T_w_table, s3 = load_table(cal_dir)
    # plausibility: the fixed camera looks down at the table, so the table's origin is in front of it
    origin_c1 = np.linalg.inv(T_w_c1) @ T_w_table[:, 3]
    if not origin_c1[2] > 0:
        raise CalibrationFileError(f"{cal_dir / FIXED_FILE}: T_w_c puts the table behind the fixed camera "
                                   f"(table origin at z = {origin_c1[2]:.0f} mm in the camera frame); "
                                   "recalibrate or check the file")
    return Calibration(fixed_camera=c1, T_w_c1=T_w_c1, mobile_camera=c2, T_f_c2=T_f_c2, T_w_table=T_w_table,
                       stats={"fixed_camera": s1, "mobile_camera": s2, "table": s3})
