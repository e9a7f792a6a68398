"""The simulated lab's ground truth, derived from the driver files.

These are what the simulator renders with; calibration estimates them and tests compare
against them. Real drivers never read them.
"""

from __future__ import annotations

import numpy as np

from ..config import CameraConfig
from ..geometry import CameraModel, look_at, make_T, rpy_willson


def camera_model(cfg: CameraConfig) -> CameraModel:
    """The true (sim) or nominal (hardware) Tsai model of a camera from its driver file."""
    lens = cfg.lens
    return CameraModel(
        f=lens.f_mm, kappa1=lens.kappa1, sx=lens.sx,
        cx=lens.cx if lens.cx is not None else (cfg.width - 1) / 2.0,
        cy=lens.cy if lens.cy is not None else (cfg.height - 1) / 2.0,
        dx=lens.dx_mm, dy=lens.dy_mm, ncx=lens.ncx, nfx=lens.nfx, width=cfg.width, height=cfg.height,
    )


def fixed_camera_pose(cfg: CameraConfig) -> np.ndarray:
    """True ``T_w_c1`` of the fixed overhead camera: at ``eye_w_mm`` looking at ``target_w_mm``.

    Image rows run along −y of the world, columns along +x (up vector +y).
    """
    if cfg.eye_w_mm is None or cfg.target_w_mm is None:
        raise ValueError("the fixed camera's driver file needs eye_w_mm and target_w_mm in the sim")
    return look_at(cfg.eye_w_mm, cfg.target_w_mm, up=(0.0, 1.0, 0.0))


def hand_eye(cfg: CameraConfig) -> np.ndarray:
    """True hand-eye transform ``T_f_c2`` (mobile camera C2 in the robot flange frame F)."""
    rx, ry, rz = np.radians(cfg.hand_eye_rpy_deg)
    return make_T(rpy_willson(rx, ry, rz), cfg.hand_eye_mm)
