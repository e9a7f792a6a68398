"""An arm's kinematic data file (``drivers/arms/<arm>.yaml``): DH table, joint limits, base pose, tool.

Units at this edge: millimetres and degrees; :class:`labctl.planning.arm.ArmModel` turns them into
millimetres and radians. A second arm is a second file, not code.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from .schema import Range, from_mapping, read_yaml

Six = tuple[float, float, float, float, float, float]
Three = tuple[float, float, float]
PositiveSix = tuple[Annotated[float, Range(gt=0)], Annotated[float, Range(gt=0)], Annotated[float, Range(gt=0)],
                    Annotated[float, Range(gt=0)], Annotated[float, Range(gt=0)], Annotated[float, Range(gt=0)]]


@dataclass(frozen=True)
class ArmConfig:
    """A six-joint arm in standard Denavit–Hartenberg form, T_i = Rz(θ_i + offset_i)·Tz(d_i)·Tx(a_i)·Rx(α_i).

    ``base_*``: the pose of the arm's base frame in the world, ``T_w_base`` (rotation Rz(yaw)·Ry(pitch)·Rx(roll)
    of ``rpy_deg`` = roll, pitch, yaw). ``tool_*``: the frame labctl commands (its flange F; the mobile
    camera is the hand-eye transform beyond it) in the arm's own flange frame, ``T_flange_F``.
    ``home_deg``: the configuration the arm is kept near (the first IK seed; the branch it starts in).
    ``link_radius_mm``: the radius of each DH row's link, as the simulated cameras draw it (capsules)."""

    name: str
    dh_d_mm: Six
    dh_a_mm: Six
    dh_alpha_deg: Six
    joint_min_deg: Six
    joint_max_deg: Six
    joint_speed_deg_s: PositiveSix
    home_deg: Six
    convention: Literal["standard_dh"] = "standard_dh"
    dh_offset_deg: Six = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    base_xyz_mm: Three = (0.0, 0.0, 0.0)
    base_rpy_deg: Three = (0.0, 0.0, 0.0)
    tool_xyz_mm: Three = (0.0, 0.0, 0.0)
    tool_rpy_deg: Three = (0.0, 0.0, 0.0)
    source: str = ""  # where the numbers come from (data sheet, DH page)
    # each DH row's link radius (mm), for drawing the arm in the simulated cameras (labctl.sim.arm); null: not drawn
    link_radius_mm: PositiveSix | None = None

    def validate(self):
        """Each joint's minimum below its maximum, the home inside them: ``(key, message)`` or None."""
        if any(lo >= hi for lo, hi in zip(self.joint_min_deg, self.joint_max_deg)):
            return "joint_min_deg", "each joint's minimum must be below its maximum"
        if not all(lo <= h <= hi for lo, h, hi in zip(self.joint_min_deg, self.home_deg, self.joint_max_deg)):
            return "home_deg", f"home {list(self.home_deg)} is outside the joint limits"
        return None


def load_arm(path: Path | str, *, base_xyz_mm: Three | None = None, base_rpy_deg: Three | None = None) -> ArmConfig:
    """Read and check an arm file; ``base_*`` override the file's mount (the mount finder tries many)."""
    import dataclasses

    path = Path(path)
    cfg = from_mapping(ArmConfig, read_yaml(path), path)
    changes = {k: tuple(float(x) for x in v) for k, v in (("base_xyz_mm", base_xyz_mm), ("base_rpy_deg", base_rpy_deg))
               if v is not None}
    return dataclasses.replace(cfg, **changes) if changes else cfg
