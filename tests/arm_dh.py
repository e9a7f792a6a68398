"""The UR10e's forward kinematics written out by hand from Universal Robots' published standard DH table
(the numbers of drivers/arms/ur10e.yaml), at the sample lab's mount read from drivers/robot.yaml: an
oracle for the reference controller's joints that shares no code with labctl's arm model."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]

# Universal Robots, "DH parameters for calculations of kinematics and dynamics", UR10e (mm, rad)
UR10E_D = (180.7, 0.0, 0.0, 174.15, 119.85, 116.55)
UR10E_A = (0.0, -612.7, -571.55, 0.0, 0.0, 0.0)
UR10E_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)


def sample_mount() -> np.ndarray:
    """``T_w_base`` of the sample lab's arm: drivers/robot.yaml's ``arm_base_xyz_mm`` (its rpy is zero)."""
    cfg = yaml.safe_load((ROOT / "drivers" / "robot.yaml").read_text())
    assert cfg["arm"] == "arms/ur10e.yaml" and cfg["arm_base_rpy_deg"] == [0.0, 0.0, 0.0]
    T = np.eye(4)
    T[:3, 3] = cfg["arm_base_xyz_mm"]
    return T


def ur10e_fk(q_rad, T_w_base: np.ndarray) -> np.ndarray:
    """``T_w_F`` = T_w_base · A1(q1) ⋯ A6(q6), A = Rz(θ)·Tz(d)·Tx(a)·Rx(α) (the tool is the flange)."""
    T = np.array(T_w_base, float)
    for th, d, a, al in zip(q_rad, UR10E_D, UR10E_A, UR10E_ALPHA):
        ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(al), math.sin(al)
        T = T @ np.array([[ct, -st * ca, st * sa, a * ct],
                          [st, ct * ca, -ct * sa, a * st],
                          [0.0, sa, ca, d],
                          [0.0, 0.0, 0.0, 1.0]])
    return T


def rotvec_matrix(rv) -> np.ndarray:
    """Rodrigues' formula (rad)."""
    rv = np.asarray(rv, float)
    th = float(np.linalg.norm(rv))
    if th < 1e-15:
        return np.eye(3)
    k = rv / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def rotation_angle(R: np.ndarray) -> float:
    """The angle of a rotation matrix (rad)."""
    return math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1) / 2)))
