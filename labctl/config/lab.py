"""The lab workspace: ``lab.yaml`` plus the driver files it names.

A workspace is a folder holding ``lab.yaml``, ``drivers/``, ``calibration/``,
``object_library/`` and ``runs/`` (README "The lab workspace"). :func:`load_lab` resolves and validates it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from .devices import ROLE_TYPES, CameraConfig, HostLinkConfig, RobotConfig, TableConfig
from .schema import ConfigError, NonNegative, Positive, PositiveInt, from_mapping, read_yaml

LAB_FILE = "lab.yaml"


@dataclass(frozen=True)
class DriverFiles:
    table: str | None = "drivers/table.yaml"  # null: no table (parts arrive on a conveyor labctl does not drive)
    robot: str = "drivers/robot.yaml"
    fixed_camera: str = "drivers/fixed_camera.yaml"
    mobile_camera: str = "drivers/mobile_camera.yaml"
    host_link: str = "drivers/host_link.yaml"


@dataclass(frozen=True)
class MarkerConfig:
    radius_mm: Positive = 8.0
    # faces too small for radius_mm get smaller markers, radius_mm·size_ratio^k, down to the one whose
    # face-on image at the initial viewing distance is min_image_diameter_px across (issue 15)
    min_image_diameter_px: Positive = 16.0
    size_ratio: Positive = 0.8

    def validate(self):
        if self.radius_mm <= 0:
            return "radius_mm", f"expected a positive radius, got {self.radius_mm}"
        if not self.min_image_diameter_px > 0:
            return "min_image_diameter_px", f"expected a positive size, got {self.min_image_diameter_px}"
        if not 0.5 <= self.size_ratio < 1:
            return "size_ratio", f"expected a ratio in [0.5, 1), got {self.size_ratio}"
        return None


@dataclass(frozen=True)
class ViewingConfig:
    """Paper §4.1, §5.3: initial view ~1 m from the marker at 63°; standard view along the normal."""

    initial_distance_mm: Positive = 1000.0
    initial_angle_deg: float = 63.0
    standoff_mm: Positive = 800.0
    max_obliquity_deg: float = 75.0  # a marker seen more obliquely than this does not count as visible


@dataclass(frozen=True)
class TrackingConfig:
    model: Literal["cv", "ct", "ca", "imm"] = "imm"  # chosen by measurement: docs/notes/planning.md
    process_noise: NonNegative = 0.01  # sqrt of the white-acceleration spectral density (mm/s^1.5); near 0: exact paths
    measurement_noise_mm: Positive = 0.7
    gate_sigma: Positive = 4.0
    window_px: PositiveInt = 48
    plane_height_mm: NonNegative = 30.0  # height of the plane the fixed camera's centroids are mapped onto
    min_track_s: Positive = 1.0  # plan the interception after tracking this long at the latest
    commit_margin_mm: Positive = 10.0  # ... or sooner, once the 3-sigma error at commit_horizon_s is this small
    commit_horizon_s: Positive = 1.5  # about the interception's duration


@dataclass(frozen=True)
class RunConfig:
    trajectory: str = "line"
    speed_mm_s: Positive = 8.0
    timeout_s: Positive = 90.0
    ambiguity_threshold: float | None = None  # None: the library's own default
    max_views: PositiveInt = 3
    second_image_azimuth_deg: float = 25.0  # camera moves this far round the marker between the two images
    fps: Positive = 30.0
    # the robot must be able to brake to rest within this many seconds from any point of a planned move
    # (issue 13: at rest within 0.5 s of a stop command): caps the planned speed at a_stop·budget (null: no cap)
    robot_stop_budget_s: Positive | None = None


@dataclass(frozen=True)
class LabConfig:
    name: str = "lab"
    drivers: DriverFiles = field(default_factory=DriverFiles)
    marker: MarkerConfig = field(default_factory=MarkerConfig)
    viewing: ViewingConfig = field(default_factory=ViewingConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    run: RunConfig = field(default_factory=RunConfig)


@dataclass(frozen=True)
class Lab:
    """A resolved workspace: its root, its config and every driver file, loaded and checked."""

    root: Path
    config: LabConfig
    table: TableConfig | None  # None: the lab has no table (``--trajectory external`` only)
    robot: RobotConfig
    fixed_camera: CameraConfig
    mobile_camera: CameraConfig
    host_link: HostLinkConfig
    driver_paths: dict[str, Path]

    @property
    def calibration_dir(self) -> Path:
        return self.root / "calibration"

    @property
    def library_dir(self) -> Path:
        return self.root / "object_library"

    @property
    def is_packaged(self) -> bool:
        """True for the sample lab inside an installed labctl (never written to)."""
        return self.root.name == "sample_lab" and (self.root.parent / "__init__.py").is_file()

    @property
    def runs_dir(self) -> Path:
        """``runs/`` of the workspace; for the packaged sample lab, the per-user data folder
        (``$XDG_DATA_HOME/labctl/runs``, default ``~/.local/share/labctl/runs``)."""
        if self.is_packaged:
            return user_data_dir() / "runs"
        return self.root / "runs"

    @property
    def kinds(self) -> dict[str, str]:
        """The driver kind of each device role the lab has (no ``table`` key when it has none)."""
        roles = ("table", "robot", "fixed_camera", "mobile_camera")
        return {r: getattr(self, r).kind for r in roles if getattr(self, r) is not None}

    @property
    def is_simulated(self) -> bool:
        """Every device is simulated (one simulated world serves them all)."""
        return all(k == "sim" for k in self.kinds.values())

    def mixed_kinds_problem(self) -> str | None:
        """Why this lab's mix of simulated and real devices cannot run together, or None.

        A simulated camera renders the simulated world, so what it watches must be simulated too:
        the fixed camera watches the table, the mobile camera rides the robot and watches the
        table. A real camera cannot see a simulated table or ride a simulated robot either."""
        k = self.kinds
        sim = {r for r, v in k.items() if v == "sim"}
        if not sim or len(sim) == len(k):
            return None
        watched = {"fixed_camera": ("table",), "mobile_camera": ("robot", "table")}
        for cam, needs in watched.items():
            moving = [r for r in needs if r in k]
            if cam in sim and any(r not in sim for r in moving):
                real = [r for r in moving if r not in sim]
                return (f"{cam} is simulated but the {' and '.join(real)} it watches "
                        f"{'is' if len(real) == 1 else 'are'} real: a simulated camera would show a static "
                        f"world (make every device kind: sim, or give {cam} a real kind)")
            if cam not in sim and any(r in sim for r in moving):
                fake = [r for r in moving if r in sim]
                return (f"{cam} is real ({k[cam]}) but the {' and '.join(fake)} it watches "
                        f"{'is' if len(fake) == 1 else 'are'} simulated: it would never see it move")
        return None


def user_data_dir() -> Path:
    """labctl's per-user data folder (XDG base directories): records of runs outside any workspace."""
    import os

    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "labctl"


def load_lab(root: Path | str) -> Lab:
    """Load and validate the workspace at ``root``; raise :class:`ConfigError` on any problem."""
    root = Path(root).resolve()
    lab_file = root / LAB_FILE
    config = from_mapping(LabConfig, read_yaml(lab_file), lab_file)
    devices, paths = {}, {}
    for role, cls in ROLE_TYPES.items():
        rel = getattr(config.drivers, role)
        if rel is None:  # only the table may be null (its field alone is typed optional)
            devices[role] = None
            continue
        path = (root / rel).resolve()
        if not path.is_file():
            raise ConfigError(lab_file, f"drivers.{role}", f"driver file not found: {rel}")
        devices[role] = from_mapping(cls, read_yaml(path), path)
        paths[role] = path
    return Lab(root=root, config=config, driver_paths=paths, **devices)
