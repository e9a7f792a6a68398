"""What both workers know before a run starts: the lab, its calibration, the library, the limits.

Each worker builds its own :class:`RunContext` from the lab workspace (as the paper's two PCs
each had their own copy of the calibration and the library); nothing here opens a device.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..calibration.store import Calibration, load_calibration
from ..config import CameraConfig, Lab
from ..errors import UserInputError
from ..geometry import CameraModel, apply, invert
from ..library.matching import LibraryIndex
from ..library.storage import library_angle, load_library
from ..planning import Limits
from ..planning.limits import planning_limits
from ..vision import MarkerThresholds


def marker_thresholds(camera_cfg: CameraConfig) -> MarkerThresholds:
    """The marker colour window of a camera, from its driver file (``marker_hue_deg``, ``marker_min_saturation``)."""
    lo, hi = camera_cfg.marker_hue_deg
    return MarkerThresholds(hue_range_deg=(lo, hi), min_saturation=camera_cfg.marker_min_saturation)


@dataclass
class RunContext:
    """Everything a run reads once: the lab, its calibration, the object library and its index, and the robot's
    limits."""
    lab: Lab
    calibration: Calibration
    library: dict  # name -> LibraryObject
    names: list[str]  # object id on the host link = index in this list (sorted names)
    index: LibraryIndex
    limits: Limits
    # the library's own initial viewing angle (library.yaml, paper §4.1), None: lab.yaml's
    initial_angle_deg: float | None = None
    # marker radii used in the library, largest first (small faces carry smaller markers)
    marker_radii_mm: tuple[float, ...] = ()

    @classmethod
    def load(cls, lab: Lab) -> RunContext:
        """Load the calibration and the library of ``lab``; raises UserInputError when either is missing or empty."""
        calibration = load_calibration(lab.root)
        library = load_library(lab.library_dir)
        if not library:
            raise UserInputError(f"the object library {lab.library_dir} is empty (teach objects first)")
        names = sorted(library)
        radii = tuple(sorted({float(mk.radius) for o in library.values() for mk in o.markers}, reverse=True))
        return cls(lab, calibration, library, names, LibraryIndex.from_library(library),
                   planning_limits(lab.robot, lab.config.run.robot_stop_budget_s),
                   library_angle(lab.library_dir, lab.config.viewing.initial_angle_deg), radii)

    @property
    def root(self) -> Path:
        """The lab workspace folder."""
        return self.lab.root

    @property
    def fixed_camera(self) -> CameraModel:
        """The fixed camera C1's model (calibrated)."""
        return self.calibration.fixed_camera

    @property
    def mobile_camera(self) -> CameraModel:
        """The mobile camera C2's model (calibrated)."""
        return self.calibration.mobile_camera

    @property
    def T_f_c2(self) -> np.ndarray:
        """Hand-eye pose of the mobile camera in the flange frame (4×4, mm)."""
        return self.calibration.T_f_c2

    @property
    def plane_height_mm(self) -> float:
        """Height (mm, W) of the plane the fixed camera's centroids are mapped onto."""
        return self.lab.config.tracking.plane_height_mm

    def fixed_pixel_to_plane(self, px) -> np.ndarray:
        """Fixed-camera pixel → (x, y) mm in W on the tracking plane z = plane_height_mm."""
        T = self.calibration.T_w_c1
        ray_w = T[:3, :3] @ self.fixed_camera.backproject(np.asarray(px, dtype=float))
        origin = T[:3, 3]
        s = (self.plane_height_mm - origin[2]) / ray_w[2]
        return (origin + s * ray_w)[:2]

    def plane_to_fixed_pixel(self, xy) -> np.ndarray:
        """(x, y) mm in W on the tracking plane → the fixed camera's pixel."""
        p_w = np.array([xy[0], xy[1], self.plane_height_mm])
        return self.fixed_camera.project(apply(invert(self.calibration.T_w_c1), p_w))

    def displacement_scale(self, z_mm: float) -> float:
        """Displacements tracked on the plane z = h0, rescaled to a point at height z (pinhole,
        camera looking down from height H): (H − z)/(H − h0)."""
        H = float(self.calibration.T_w_c1[2, 3])
        return (H - z_mm) / (H - self.plane_height_mm)
