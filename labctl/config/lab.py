"""The lab workspace: ``lab.yaml`` plus the driver files it names.

A workspace is a folder holding ``lab.yaml``, ``drivers/``, ``calibration/``,
``object_library/`` and ``runs/`` (README "The lab workspace"). :func:`load_lab` resolves and validates it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

from .arm import ArmConfig, load_arm
from .devices import ROLE_TYPES, CameraConfig, HostLinkConfig, RobotConfig, TableConfig
from .schema import ConfigError, NonNegative, Positive, PositiveInt, Range, defaulted_keys, from_mapping, read_yaml

LAB_FILE = "lab.yaml"


@dataclass(frozen=True)
class DriverFiles:
    """Paths of the driver files, relative to the lab folder (``table: null``: no table)."""

    table: str | None = "drivers/table.yaml"  # null: no table (parts arrive on a conveyor labctl does not drive)
    robot: str = "drivers/robot.yaml"
    fixed_camera: str = "drivers/fixed_camera.yaml"
    mobile_camera: str = "drivers/mobile_camera.yaml"
    host_link: str = "drivers/host_link.yaml"


@dataclass(frozen=True)
class MarkerConfig:
    """Marker size (mm) and the size ladder for faces too small for ``radius_mm``."""

    radius_mm: Positive = 8.0
    # faces too small for radius_mm get smaller markers, radius_mm·size_ratio^k, down to the one whose
    # face-on image at the initial viewing distance is min_image_diameter_px across
    min_image_diameter_px: Positive = 16.0
    size_ratio: Positive = 0.8

    def validate(self):
        """Range check of the marker sizes: ``(key, message)`` or None."""
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


#: the named table programs labctl drives (``--trajectory``; G-code by :func:`labctl.drivers.programs.program`):
#: the one list of their names — :class:`FamilyPrior` and :class:`TrajectoryStarts` have a field for each
TRAJECTORIES = ("line", "arc", "circle", "zigzag")


@dataclass(frozen=True)
class TrajectoryStarts:
    """Where the table's carriage starts each named program (mm, GRBL machine coordinates, x and y).

    A run first brings the table there and waits (live) or powers the simulated carriage up there
    (virtual), so the object then crosses the fixed camera's field while the run takes place. The
    defaults are for the sample lab's 600 × 400 mm travel with the fixed camera over its centre
    (300, 200): the 300-mm line runs 150 → 450 mm along the centre line, the arc and the circle of
    80 mm radius turn about (200, 280), the zigzag's ±40 mm legs straddle y = 170. A lab whose camera
    looks elsewhere moves them here (``--trajectory external`` parts start at ``line``'s).
    """

    line: tuple[float, float] = (150.0, 200.0)
    arc: tuple[float, float] = (200.0, 200.0)
    circle: tuple[float, float] = (200.0, 200.0)
    zigzag: tuple[float, float] = (150.0, 170.0)

    def get(self, name: str) -> tuple[float, float] | None:
        """The start of trajectory ``name``, or None if it is not a named program (a G-code file, external)."""
        return dataclasses.asdict(self).get(name)


@dataclass(frozen=True)
class LibraryConfig:
    """Teaching policy (``labctl teach-object``, ``labctl library check``)."""

    # a part whose random placements show a tracked, visible marker less often than this fails that share
    # of its runs for want of a marker: teach-object refuses it (exit 1) unless --accept-partial
    min_coverage: Annotated[float, Range(ge=0, le=1)] = 0.9
    # resting poses (after merging those the part's symmetry makes alike) less likely than this are left
    # out: trimesh's quasi-static estimate is no finer, and each pose costs teaching time
    pose_probability_floor: Annotated[float, Range(ge=0, lt=1)] = 0.005


@dataclass(frozen=True)
class FamilyPrior:
    """The IMM's prior probability of a curve (its CT mode) per trajectory family labctl drives the table along.

    Paper §5.1: the object's motions are "induced via programmed movement of the NC table" along
    predictable paths, so when labctl itself runs a named program (``--trajectory line|arc|circle|
    zigzag``) the tracker is told the program's *family* (not its geometry): lines and zigzags
    (straight legs) strongly favour the CV mode, arcs and circles the CT mode; the other mode stays
    in the IMM. Motion labctl does not drive (``--trajectory external``, a G-code file, no table)
    keeps the family-blind ``tracking.curve_prior``. Values by measurement (`labctl bench planning`,
    docs/notes/planning.md "Prediction at the estimation bound", third round).
    """

    line: Annotated[float, Range(gt=0, lt=1)] = 0.001
    arc: Annotated[float, Range(gt=0, lt=1)] = 0.99
    circle: Annotated[float, Range(gt=0, lt=1)] = 0.99
    zigzag: Annotated[float, Range(gt=0, lt=1)] = 0.001


@dataclass(frozen=True)
class TrackingConfig:
    """Fixed-camera tracking (paper §5.2): motion model, noise (mm), gate (σ), search window (px), commit policy."""

    model: Literal["cv", "ct", "ca", "imm"] = "imm"  # chosen by measurement: docs/notes/planning.md
    # sqrt of the white-acceleration spectral density (mm/s^1.5); near 0: the table's programs are exact paths. At
    # 0.01 the 5-s covariance after 4 s on a line was 1.06x the CRB, on a 100 mm/s circle 1.4x across the track;
    # at 1e-4 1.00x (docs/notes/planning.md, sixth round)
    process_noise: NonNegative = 1e-4
    # imm: prior probability of a curve (CT mode) against a line; minimax over the confusable line/circle
    # cells of `labctl bench planning` (docs/notes/planning.md, "Prediction at the estimation bound")
    curve_prior: Annotated[float, Range(gt=0, lt=1)] = 0.05
    # ... and when labctl drives the table along a named program, the prior of that program's family instead
    family_prior: FamilyPrior = field(default_factory=FamilyPrior)
    # ... and the table's corners as GRBL drives them: to rest at a sharp corner and up to speed again at the
    # table's acceleration (tracker ``stop_accel_mm_s2``). Off by measurement: at the bound on one corner (bench)
    # but 91 → 88 of 100 zigzag trials at 100 mm/s, whose legs end before the next corner's slow-down
    # (docs/notes/planning.md, "The table's own corners, modelled")
    stop_corners: bool = False
    measurement_noise_mm: Positive = 0.7
    gate_sigma: Positive = 4.0
    window_px: PositiveInt = 48
    # a gap in the sightings (the arm crossing the fixed camera's view) is bridged on the prediction for at most
    # this long: the one-step window stays at the predicted pixel and the track is kept; beyond it the track is
    # lost (the wait stage starts again; a later stage coasts). 1 s: the window's ±24 px (±22 mm) holds a
    # prediction that missed a 90° corner at 12 mm/s (the sample sweep's top speed) for ~1.3 s, and the arm hides
    # the marker for at most 8 frames (0.27 s) in the sample sweep (docs/notes/sim.md, "The arm in the cameras")
    max_bridge_s: Positive = 1.0
    plane_height_mm: NonNegative = 30.0  # height of the plane the fixed camera's centroids are mapped onto
    min_track_s: Positive = 1.0  # plan the interception after tracking this long at the latest
    commit_min_updates: PositiveInt = 3  # ... and never from fewer filter updates than this
    # ... or sooner, once the 3-sigma error at commit_horizon_s is this small: 40 mm still fits the central half
    # of the mobile camera's view at the initial distance (viewing_distance_with_margin), and the plan is
    # re-planned as the filter converges (10 mm waited ~0.25 s longer for nothing measurable). null: no gate,
    # the interception starts at commit_min_updates and the re-plans (run.replan_every_s) bring the aim in
    commit_margin_mm: Positive | None = 40.0
    # about the first leg's duration: ~0.6 s flown + ~0.1 s for its command at 9600 bps with ruckig segments;
    # the margin it gives also widens the initial view (viewing_distance_with_margin)
    commit_horizon_s: Positive = 0.8

    def curve_prior_for(self, family: str | None) -> float:
        """The IMM's curve prior for motion of ``family`` (a trajectory labctl drives the table along).

        ``family_prior``'s value for a named program family; ``curve_prior`` (family-blind) for None,
        ``external`` or anything else (a G-code file: its shape is not known to be one family).
        """
        if family is not None and family in TRAJECTORIES:
            return float(getattr(self.family_prior, family))
        return float(self.curve_prior)


@dataclass(frozen=True)
class RunConfig:
    """One run's settings: trajectory, speed (mm/s), timeout (s), matching, predictor policy (paper §5.2–5.3)."""

    trajectory: str = "line"
    speed_mm_s: Positive = 8.0
    # where the table starts each named program (mm): the object then crosses the fixed camera's field
    trajectory_start_mm: TrajectoryStarts = field(default_factory=TrajectoryStarts)
    timeout_s: Positive = 90.0
    ambiguity_threshold: float | None = None  # None: the library's own default
    max_views: PositiveInt = 3
    # marker-height gate (labctl.library.marker_height): the standard view measures its marker's
    # height above the table; a shape candidate none of whose views can rest its marker within
    # height_gate_mm + height_gate_sigmas·σ + height_gate_depth_frac·(vertical distance to the marker) of it
    # is dropped (the height only narrows the shape's candidates). height_gate_mm: the library's own error
    # (hand-placed markers), 0 turns the gate off; depth_frac: the apparent-size bias (realistic-camera
    # preset: ≤ 0.65 % of the distance measured; docs/notes/library.md)
    height_gate_mm: NonNegative = 1.5
    height_gate_sigmas: NonNegative = 4.0
    height_gate_depth_frac: NonNegative = 0.008
    second_image_azimuth_deg: float = 25.0  # camera moves this far round the marker between the two images
    # ... sideways round it (the paper's) or up towards the top, where an upward marker's standard view is
    second_image_move: Literal["azimuth", "elevation"] = "azimuth"
    second_image_elevation_deg: Positive = 5.0  # the step up (on the 1 m sphere: twice the path of a step round)
    fps: Positive = 30.0
    # the newest fixed-camera frames the predictor tracks after a busy spell: a robot command's round trip at
    # 9600 bps (~0.15-0.2 s) blocks its loop for 5-6 frames, which latest-frame grabbing lost (1: the newest only)
    catch_up_frames: PositiveInt = 8
    # the predictor's policy (paper §5.2–5.3)
    max_viewpoints: PositiveInt = 4  # viewpoints tried for a usable marker pose before the run fails
    next_viewpoint_deg: float = 120.0  # azimuth step round the object to the next viewpoint
    recognizer_timeout_s: Positive = 10.0  # a view the recognizer has not answered within this fails the run
    plan_horizon_s: Positive = 15.0  # how far ahead an interception is searched for
    replan_every_s: Positive = 0.25  # re-plan with the newest prediction at most this often ...
    replan_until_s: NonNegative = 0.4  # ... and not in the last this-many seconds before arrival
    # an initial view that already holds the marker in its central half is not re-aimed to arrive later
    initial_view_hold: bool = True
    # a view's image is requested at the controller's promised arrival (the SEG/SEGNOW/GO reply's t1, dialect
    # §5), not when its @DONE has crossed the line (~12 ms at 9600 bps plus the tick that reads it); nothing
    # derived from the image is used until that @DONE arrives, and an image whose @DONE does not come within
    # the grace is discarded and the arrival checked with STATUS as before (docs/notes/planning.md
    # "2026-12-02 (c)"). false: the image waits for the @DONE
    image_at_arrival: bool = True
    # for a controller on its own clock, the arrival is mapped to the host's as (its reply read) + (t1 − t0):
    # never early, since the controller replies after it starts; this margin covers the two clocks' rates
    # (100 ppm of a ≤ 10-s leg: 1 ms) and the host's time stamp of the reply (1 ms)
    arrival_clock_margin_s: NonNegative = 0.002
    # a live run that drives the table gives up early, with the cause, instead of waiting out timeout_s
    # (labctl.runtime.early_end; --trajectory external waits, a part may come at any time):
    # no fixed-camera marker for no_marker_s while waiting: the sample lab's programs start the object in the
    # fixed camera's field and it is first seen 0.8 s in; 15 s also lets an object that starts 120 mm outside a
    # smaller field enter it at 8 mm/s (null: wait out timeout_s)
    no_marker_s: Positive | None = 15.0
    # the table program ended (every line acknowledged, GRBL Idle) and no identity within after_program_s:
    # the object stands still from then on; 20 s is four median times to identity (4.5 s) for the views
    # already under way to finish on a still object (null: wait out timeout_s)
    after_program_s: Positive | None = 20.0
    spare_novelty_deg: NonNegative = 20.0  # a spare marker facing within this of a viewed face is not worth a view
    # which spare marker to view next: the one whose standard view is nearest, or the most novel face
    spare_order: Literal["nearest", "novel"] = "nearest"
    # the robot must be able to brake to rest within this many seconds from any point of a planned move
    # (at rest within 0.5 s of a stop command): caps the planned speed at a_stop·budget (null: no cap)
    robot_stop_budget_s: Positive | None = None
    # the robot's segment profile (docs/protocols/robot.md §5): ruckig's time-optimal jerk-limited segments
    # (dialect 1.2; a controller that does not list ruckig gets quintic), or the paper's quintic (faithful
    # reproduction). ruckig by measurement: 4.47 s vs 5.06 s median time to identity, 240/240 vs 239/240
    # correct, same seeds (docs/notes/planning.md "ruckig profile")
    profile: Literal["quintic", "ruckig"] = "ruckig"
    # a lab whose robot is an arm (drivers/robot.yaml arm:) has every planned path checked in its joint space
    # before it is sent (planning.arm_plan; docs/notes/robot.md "The planner plans for the arm"): sampled every
    # arm_check_dt_s (20 ms: 2.4° of a joint at 120 °/s, well inside the follower's 5° step, ~5 ms a plan);
    # each joint planned to at most arm_speed_fraction of its data-sheet speed (the check samples the path, the
    # controller and an independent check see every instant: 5 % for what lies between samples); the
    # singularity margins: the wrist point at least arm_shoulder_margin_mm outside the cylinder round the base
    # axis, |sin q3| (elbow) and |sin q5| (wrist) at least theirs (0.05: 3° from stretched or aligned, where
    # the joint rates of a slow Cartesian move grow twentyfold)
    arm_check_dt_s: Positive = 0.02
    arm_speed_fraction: Annotated[float, Range(gt=0, le=1)] = 0.95
    arm_shoulder_margin_mm: NonNegative = 50.0
    arm_elbow_margin: Annotated[float, Range(ge=0, lt=1)] = 0.05
    arm_wrist_margin: Annotated[float, Range(ge=0, lt=1)] = 0.05


SIM_CAMERA_PRESETS = ("none", "realistic")


@dataclass(frozen=True)
class SimCameraConfig:
    """What the simulated cameras add to the clean render (``labctl.sim.effects``).

    ``preset`` picks a combination (``realistic``: shadows 0.8, specular 0.12 at shininess 60,
    texture 1.5, Bayer bilinear, JPEG 80); any field set here overrides the preset's. The
    response curve is each camera's own ``response:`` in its driver file (what vision linearises
    with), so the two agree, unless ``response`` gives the simulated sensor its own (to stage a camera
    file that is wrong). Off by default: frames exactly as without this section.
    """

    preset: Literal["none", "realistic"] = "none"
    shadows: Annotated[float, Range(ge=0, le=1)] | None = None  # share of the direct light the object blocks
    specular: NonNegative | None = None  # Blinn-Phong strength (fraction of full scale at n·h = 1)
    shininess: Annotated[float, Range(ge=1)] | None = None  # Blinn-Phong exponent
    texture: Annotated[float, Range(ge=0, le=4)] | None = None  # table texture contrast (1: as drawn)
    bayer: Literal["none", "bilinear", "vng", "ea"] | None = None  # RGGB mosaic + OpenCV demosaicing
    jpeg_quality: Annotated[int, Range(ge=0, le=100)] | None = None  # 0: no JPEG (null: the preset's)
    defocus_px: Annotated[float, Range(ge=0, le=8)] | None = None  # lens blur disc radius, px (0: in focus)
    # the simulated sensor's own encoding when it is not what the driver files say (a lab whose camera file is
    # wrong, e.g. a gamma camera left at `response: linear`); null: the driver file's, so the two agree
    response: str | float | list[float] | None = None

    def validate(self):
        """The sensor's own ``response``, when given, is a curve a camera driver file could name."""
        if self.response is None:
            return None
        from .devices import CameraConfig

        problem = CameraConfig(response=self.response).validate()
        return None if problem is None else ("response", problem[1])

    def settings(self) -> dict:
        """The effective settings: the preset's, overridden by the fields given here (plain values)."""
        base = dict(SIM_PRESET_SETTINGS.get(self.preset, {}))
        for name in ("shadows", "specular", "shininess", "texture", "bayer", "jpeg_quality", "defocus_px"):
            value = getattr(self, name)
            if value is not None:
                base[name] = value
        if base.get("bayer") == "none":
            base["bayer"] = None
        if base.get("jpeg_quality") == 0:
            base["jpeg_quality"] = None
        return base


# the presets' settings (labctl.sim.effects builds the renderer's effects from them)
SIM_PRESET_SETTINGS: dict[str, dict] = {
    "none": {},
    # a colour industrial / webcam-class camera over a lit bench: the object's shadow, a glint on
    # faces near the mirror angle, a stronger table grain, RGGB demosaicing and the JPEG a USB or IP
    # camera streams (the sRGB response is the driver files' `response: srgb`, see `labctl init --preset`)
    "realistic": dict(shadows=0.8, specular=0.12, shininess=60.0, texture=1.5, bayer="bilinear", jpeg_quality=80),
}


@dataclass(frozen=True)
class SimConfig:
    """Settings of the simulated lab only (ignored on hardware)."""

    camera: SimCameraConfig = field(default_factory=SimCameraConfig)


@dataclass(frozen=True)
class LiveViewConfig:
    """The live view of a run (``labctl run --view``): where its page listens, and the fixed camera's snapshots.

    The page reads only the run's record folder; the fixed camera's frames reach it as a downscaled JPEG
    the predictor's process writes at most every ``fixed_snapshot_period_s`` (``live/fixed.jpg``)."""

    host: str = "127.0.0.1"  # the page is for this PC; a wider address needs the printed key all the same
    port: Annotated[int, Range(ge=0, le=65535)] = 8765  # 0: any free port
    poll_s: Positive = 0.25  # how often the page asks for news
    fixed_snapshot_period_s: Annotated[float, Range(ge=0.5)] = 0.5  # at most 2 Hz, off the predictor's loop
    fixed_snapshot_width: Annotated[int, Range(ge=32, le=1280)] = 320  # px, the snapshot's width


@dataclass(frozen=True)
class LabConfig:
    """The lab's ``lab.yaml``: name, driver files, marker, viewing, tracking, run and simulator settings."""

    name: str = "lab"
    drivers: DriverFiles = field(default_factory=DriverFiles)
    marker: MarkerConfig = field(default_factory=MarkerConfig)
    viewing: ViewingConfig = field(default_factory=ViewingConfig)
    library: LibraryConfig = field(default_factory=LibraryConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    run: RunConfig = field(default_factory=RunConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    view: LiveViewConfig = field(default_factory=LiveViewConfig)


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
    # the robot's arm (its driver file's ``arm:``), loaded and checked; None: a flange in a task-space box
    arm: ArmConfig | None = None
    # the keys each file left out (its values are the code's defaults): "lab" for lab.yaml, else the role
    defaulted: dict[str, tuple[str, ...]] = field(default_factory=dict)
    # the sample lab used because no workspace was found: read, never written (records go to the user's folder)
    read_only: bool = False

    @property
    def calibration_dir(self) -> Path:
        """The lab's ``calibration/`` folder."""
        return self.root / "calibration"

    @property
    def library_dir(self) -> Path:
        """The lab's ``object_library/`` folder."""
        return self.root / "object_library"

    @property
    def is_packaged(self) -> bool:
        """True for the sample lab inside an installed labctl, or used because no workspace was found
        (never written to)."""
        return self.read_only or (self.root.name == "sample_lab" and (self.root.parent / "__init__.py").is_file())

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

    def response_declared(self, role: str) -> bool:
        """Whether the camera ``role``'s response is known: its driver file says who stated it
        (``response_source``: declared or learned), or names a curve other than the default ``linear``,
        or it is a simulated camera that renders with its file's response (lab.yaml ``sim.camera.response``
        unset). A ``linear`` nobody stated is undeclared: pose then uses a conservative covariance."""
        cfg = getattr(self, role if role.endswith("_camera") else f"{role}_camera")
        if cfg.response_source is not None:
            return True
        r = cfg.response
        if not (isinstance(r, str) and r.strip().lower() == "linear") and not (
                isinstance(r, int | float) and not isinstance(r, bool) and float(r) == 1.0):
            return True
        return cfg.kind == "sim" and self.config.sim.camera.response is None


def user_data_dir() -> Path:
    """labctl's per-user data folder (XDG base directories): records of runs outside any workspace."""
    import os

    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "labctl"


def load_lab(root: Path | str) -> Lab:
    """Load and validate the workspace at ``root``; raise :class:`ConfigError` on any problem."""
    root = Path(root).resolve()
    lab_file = root / LAB_FILE
    raw = read_yaml(lab_file)
    config = from_mapping(LabConfig, raw, lab_file)
    defaulted = {"lab": tuple(defaulted_keys(LabConfig, raw))}
    devices: dict[str, Any] = {}
    paths: dict[str, Path] = {}
    for role, cls in ROLE_TYPES.items():
        rel = getattr(config.drivers, role)
        if rel is None:  # only the table may be null (its field alone is typed optional)
            devices[role] = None
            continue
        path = (root / rel).resolve()
        if not path.is_file():
            raise ConfigError(lab_file, f"drivers.{role}", f"driver file not found: {rel}")
        raw = read_yaml(path)
        devices[role] = from_mapping(cls, raw, path)
        defaulted[role] = tuple(defaulted_keys(cls, raw))
        paths[role] = path
    arm = None
    if devices["robot"].arm is not None:
        arm_path = (paths["robot"].parent / devices["robot"].arm).resolve()
        if not arm_path.is_file():
            raise ConfigError(paths["robot"], "arm", f"arm file not found: {devices['robot'].arm}")
        arm = load_arm(arm_path, base_xyz_mm=devices["robot"].arm_base_xyz_mm,
                       base_rpy_deg=devices["robot"].arm_base_rpy_deg)
        paths["arm"] = arm_path
    return Lab(root=root, config=config, driver_paths=paths, defaulted=defaulted, arm=arm, **devices)
