"""The simulated lab's world: where the table, the object and both cameras are at time t.

Frames (docs/architecture.md): world W with the table top at z = 0; table frame T at the NC
table's carriage (``T_w_t = origin_w + machine position``); object O resting on the table in one
of its stable poses (He et al. 1996 §5.2: the object rides the X-Y table); fixed camera C1 at
``T_w_c1``; robot base B (= W in the sample lab), flange F, mobile camera
``T_w_c2(t) = T_w_b · T_b_f(t) · T_f_c2`` (§5.1: the camera rides the robot's wrist).

The robot arm (:mod:`labctl.sim.arm`), when the lab has one, is drawn in both cameras: its links follow
the flange by inverse kinematics; the mobile camera leaves out the wrist it is mounted on.

The world holds no clock: it is asked "what is seen at t". The table's and the robot's motion
come from callables (the GRBL emulator's ``position_at``, a robot emulator's ``flange_pose_at``),
so one world serves both virtual-time trials and live runs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Self

import numpy as np

from ..geometry import CameraModel, apply, invert, look_at, make_T, rot_z, rotate
from .arm import ARM_COLOUR_BGR, MOBILE_SKIP_LINKS, ArmBody, body_hides, camera_body
from .effects import CameraEffects
from .render import DEFAULT_LIGHT_DIR_W, MarkerDisc, Mesh, RenderResult, TableSurface, render

if TYPE_CHECKING:
    from ..library.placement import Marker
    from ..library.storage import LibraryObject

CAMERA_ROLES = ("fixed", "mobile")


class WorldError(ValueError):
    """A world asked for something it cannot do (unknown camera role, bad placement, bad object)."""


@dataclass(frozen=True)
class SimMarker:
    """A marker on an object, in the object frame O: centre (mm), outward unit normal, radius (mm)."""

    id: int
    center: np.ndarray
    normal: np.ndarray
    radius: float


@dataclass
class SimObject:
    """What the world needs of an object: its mesh (O frame, mm), markers and stable poses.

    ``stable_poses`` lists ``(T_s_o, probability)``: ``T_s_o`` places O resting on the plane
    z = 0 of a support frame S (as ``trimesh.poses.compute_stable_poses`` returns them).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    markers: list[SimMarker]
    stable_poses: list[tuple[np.ndarray, float]]
    colour_bgr: tuple = (185, 185, 185)

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, dtype=float)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or not np.all(np.isfinite(self.vertices)):
            raise WorldError(f"{self.name}: vertices must be a finite (N, 3) array")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise WorldError(f"{self.name}: faces must be a non-empty (M, 3) array")
        if not self.stable_poses:
            raise WorldError(f"{self.name}: no stable poses")

    @classmethod
    def from_library(cls, obj: LibraryObject) -> SimObject:
        """Adapt a library object (its ``.name``, ``.mesh`` (trimesh), ``.markers``, ``.stable_poses``)."""
        markers = [SimMarker(int(m.id), np.asarray(m.center, float), np.asarray(m.normal, float),
                             float(m.radius)) for m in obj.markers]
        poses = [(np.asarray(T, float), float(p)) for T, p in obj.stable_poses]
        V, F = obj.mesh_arrays()  # the cached arrays when the model was read before: no trimesh import
        return cls(obj.name, V, F, markers, poses)

    @classmethod
    def from_trimesh(cls, name: str, mesh, markers: Sequence[SimMarker | Marker] = (), stable_poses=None) -> SimObject:
        """From a trimesh mesh (mm, O frame); stable poses computed by trimesh when not given."""
        if stable_poses is None:
            transforms, probs = mesh.compute_stable_poses()
            stable_poses = list(zip(transforms, probs))
        sim_markers = [m if isinstance(m, SimMarker) else
                       SimMarker(int(m.id), np.asarray(m.center, float), np.asarray(m.normal, float),
                                 float(m.radius)) for m in markers]
        return cls(name, np.asarray(mesh.vertices), np.asarray(mesh.faces), sim_markers,
                   [(np.asarray(T, float), float(p)) for T, p in stable_poses])


def builtin_test_object(marker_radius_mm: float = 8.0) -> SimObject:
    """A 40×40×35 mm block (the paper's smallest object size) with a marker centred on every face.

    Used when the lab's object library is empty, so the simulated lab works out of the box.
    """
    import trimesh

    size = np.array([40.0, 40.0, 35.0])
    mesh = trimesh.creation.box(size)
    markers: list[SimMarker] = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            n = np.zeros(3)
            n[axis] = sign
            markers.append(SimMarker(len(markers), n * size[axis] / 2, n, marker_radius_mm))
    return SimObject.from_trimesh("test_block", mesh, markers)


@dataclass(frozen=True)
class Placement:
    """How the object lies on the table: stable pose index, yaw about the table's z (rad), offset in T (mm)."""

    pose_index: int
    yaw: float
    offset_xy: tuple[float, float]

    def T_t_o(self, obj: SimObject) -> np.ndarray:
        """Object pose in the table frame T: ``Rz(yaw)`` and the offset applied to the stable pose."""
        if not 0 <= self.pose_index < len(obj.stable_poses):
            raise WorldError(f"{obj.name} has {len(obj.stable_poses)} stable poses, not index {self.pose_index}")
        T_s_o = obj.stable_poses[self.pose_index][0]
        return make_T(rot_z(self.yaw), (self.offset_xy[0], self.offset_xy[1], 0.0)) @ T_s_o


def random_placement(obj: SimObject, rng: np.random.Generator, *, pose_index: int | None = None,
                     yaw: float | None = None, offset_xy=None, max_offset_mm: float = 30.0) -> Placement:
    """Draw a placement: the stable pose with its probability, yaw uniform on [0, 2π), offset uniform in a square."""
    if pose_index is None:
        p = np.array([max(pr, 0.0) for _, pr in obj.stable_poses], dtype=float)
        p = p / p.sum() if p.sum() > 0 else np.full(len(p), 1.0 / len(p))
        pose_index = int(rng.choice(len(p), p=p))
    if yaw is None:
        yaw = float(rng.uniform(0.0, 2.0 * np.pi))
    if offset_xy is None:
        offset_xy = tuple(float(v) for v in rng.uniform(-max_offset_mm, max_offset_mm, 2))
    return Placement(int(pose_index), float(yaw), (float(offset_xy[0]), float(offset_xy[1])))


@dataclass
class CameraRig:
    """One camera of the world: its true model, sensor noise (grey levels) and exposure (s, 0: no blur).

    With an exposure, ``blur_samples`` (rounded down to even, plus the middle) sub-frames spread
    over it are averaged; the frame's time stamp is the exposure's middle. ``effects``: what a
    realistic camera and scene add (:class:`~labctl.sim.effects.CameraEffects`; None: nothing)."""

    model: CameraModel
    noise_sigma: float = 2.0
    exposure_s: float = 0.0
    blur_samples: int = 4
    effects: CameraEffects | None = None


@dataclass
class WorldTruth:
    """Ground truth at time t (W frame, mm)."""

    t: float
    object_name: str | None
    placement: Placement | None
    T_w_t: np.ndarray
    T_w_o: np.ndarray | None
    markers_w: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)  # (id, centre, normal)
    T_w_c1: np.ndarray | None = None
    T_w_c2: np.ndarray | None = None

    def to_dict(self) -> dict:
        """The scene's state as plain data (time, object, placement, poses rounded to 1e-6)."""
        r = lambda a: None if a is None else np.round(np.asarray(a, float), 6).tolist()
        return {
            "t": self.t, "object": self.object_name,
            "placement": None if self.placement is None else {
                "pose_index": self.placement.pose_index, "yaw_rad": self.placement.yaw,
                "offset_xy_mm": list(self.placement.offset_xy)},
            "T_w_t": r(self.T_w_t), "T_w_o": r(self.T_w_o),
            "markers_w": [{"id": i, "center": r(c), "normal": r(n)} for i, c, n in self.markers_w],
            "T_w_c1": r(self.T_w_c1), "T_w_c2": r(self.T_w_c2),
        }


def _constant(value):
    return lambda t: value


class SimWorld:
    """The simulated lab at any time t: table, object, cameras and light (see the module doc).

    ``table_position(t) -> (x, y, z)`` machine position of the table (mm; the GRBL emulator's
    ``position_at``); ``flange_pose_at(t) -> T_b_f`` (4×4, mm). Both default to constants.
    """

    def __init__(self, *, fixed: CameraRig, mobile: CameraRig, T_w_c1: np.ndarray, T_f_c2: np.ndarray,
                 T_w_b: np.ndarray | None = None, table_origin_w=(0.0, 0.0, 0.0),
                 table_position: Callable[[float], Sequence[float] | np.ndarray] | None = None,
                 flange_pose_at: Callable[[float], np.ndarray] | None = None,
                 obj: SimObject | None = None, placement: Placement | None = None,
                 light_dir_w=DEFAULT_LIGHT_DIR_W, supersample: int = 3, arm: ArmBody | None = None):
        self.arm = arm
        self.rigs = {"fixed": fixed, "mobile": mobile}
        self.T_w_c1 = np.asarray(T_w_c1, float)
        self.T_f_c2 = np.asarray(T_f_c2, float)
        self.T_w_b = np.eye(4) if T_w_b is None else np.asarray(T_w_b, float)
        self.table_origin_w = np.asarray(table_origin_w, float).reshape(3)
        self.table_position = table_position or _constant((0.0, 0.0, 0.0))
        self.flange_pose_at = flange_pose_at or _constant(np.eye(4))
        self.light_dir_w = light_dir_w
        self.supersample = supersample
        self.obj: SimObject | None = None
        self.placement: Placement | None = None
        self._mesh_o: Mesh | None = None
        if obj is not None:
            self.place(obj, placement if placement is not None else Placement(0, 0.0, (0.0, 0.0)))

    # --- scene ------------------------------------------------------------------------------
    def place(self, obj: SimObject, placement: Placement) -> None:
        """Put ``obj`` on the table as ``placement`` says (replaces any object already there)."""
        T_t_o = placement.T_t_o(obj)
        self.obj, self.placement = obj, placement
        self._T_t_o = T_t_o
        # the object in T is fixed: transform once, move rigidly with the table afterwards
        verts_t = apply(T_t_o, obj.vertices)
        markers_t = [(m.id, apply(T_t_o, m.center), rotate(T_t_o, m.normal), m.radius) for m in obj.markers]
        self._verts_t, self._markers_t = verts_t, markers_t

    def clear(self) -> None:
        """Take the object off the table."""
        self.obj = self.placement = None

    def T_w_t(self, t: float) -> np.ndarray:
        """Table frame at time t: its machine zero at ``table_origin_w`` plus the carriage position (x, y)."""
        p = np.asarray(self.table_position(t), float).reshape(-1)
        return make_T(None, self.table_origin_w + np.array([p[0], p[1], 0.0]))

    def T_w_o(self, t: float) -> np.ndarray | None:
        """Pose of the object frame in W at time ``t`` (s), or None with no object on the table."""
        return None if self.obj is None else self.T_w_t(t) @ self._T_t_o

    def T_w_c(self, role: str, t: float) -> np.ndarray:
        """Pose of the ``fixed`` (C1) or ``mobile`` (C2) camera at time t."""
        if role == "fixed":
            return self.T_w_c1
        if role == "mobile":
            return self.T_w_b @ np.asarray(self.flange_pose_at(t), float) @ self.T_f_c2
        raise WorldError(f"unknown camera role {role!r}; expected one of {CAMERA_ROLES}")

    def meshes_at(self, t: float) -> list[Mesh]:
        """The scene's meshes in W at time t (the object, translated with the table)."""
        if self.obj is None:
            return []
        shift = self.T_w_t(t)[:3, 3]
        markers = [MarkerDisc(c + shift, n, r) for _, c, n, r in self._markers_t]
        return [Mesh(self._verts_t + shift, self.obj.faces, self.obj.colour_bgr, markers)]

    def T_w_F(self, t: float) -> np.ndarray:
        """The flange in W at time ``t`` (s): the robot base's pose times the controller's flange pose."""
        return self.T_w_b @ np.asarray(self.flange_pose_at(t), float)

    def arm_q(self, t: float) -> np.ndarray | None:
        """The arm's joint angles (rad) at time ``t`` (s), following the flange; None without an arm."""
        return None if self.arm is None else self.arm.q_at(t, self.T_w_F)

    def arm_meshes(self, role: str, t: float, window: tuple | None = None) -> list[Mesh]:
        """The arm's links in W as camera ``role`` sees them at ``t`` (s): all of them and the mobile camera's
        body for the fixed camera, without the wrist it rides on for the mobile one; only the links that may
        show in the view (or in its pixel ``window``) unless the camera's effects cast shadows; [] without
        an arm."""
        if self.arm is None:
            return []
        q = self.arm.q_at(t, self.T_w_F)
        fx = self.rigs[role].effects
        # links out of view may still cast a shadow into it: cull only without cast shadows
        view = None if fx is not None and fx.shadows > 0 else (self.rigs[role].model, self.T_w_c(role, t), window)
        if role == "mobile":
            V, F = self.arm.mesh(q, skip_last=MOBILE_SKIP_LINKS, view=view)
            return [Mesh(V, F, ARM_COLOUR_BGR)] if len(F) else []
        V, F = self.arm.mesh(q, view=view)
        Vc, Fc = camera_body(self.T_w_c("mobile", t))
        return [Mesh(np.concatenate([V, Vc]), np.concatenate([F, Fc + len(V)]), ARM_COLOUR_BGR)]

    def arm_hides_markers(self, role: str, t: float) -> tuple[int, int]:
        """Of the markers facing camera ``role`` at ``t`` (s), how many there are and how many the arm hides
        (their centre's sight line passes through a link, or the mobile camera's body): ground truth of the arm's
        occlusions."""
        if self.arm is None or self.obj is None:
            return 0, 0
        eye = self.T_w_c(role, t)[:3, 3]
        truth = self.truth(t)
        facing = [c for _, c, n in truth.markers_w if float(np.dot(n, eye - c)) > 0]
        if not facing:
            return 0, 0
        if role == "mobile":
            hidden = self.arm.hides(self.arm.q_at(t, self.T_w_F), eye, np.array(facing), skip_last=MOBILE_SKIP_LINKS)
        else:  # the links and the mobile camera's body
            hidden = self.arm.hides(self.arm.q_at(t, self.T_w_F), eye, np.array(facing)) \
                | body_hides(self.T_w_c("mobile", t), eye, np.array(facing))
        return len(facing), int(hidden.sum())

    def table_surface(self, t: float) -> TableSurface:
        """The table's surface at time ``t`` (s): its origin in W (mm) for the renderer."""
        o = self.T_w_t(t)[:3, 3]
        return TableSurface(origin_w=(float(o[0]), float(o[1])))

    # --- seeing -----------------------------------------------------------------------------
    def render(self, role: str, t: float, rng: np.random.Generator | None = None, *,
               truth: bool = False, window: str | tuple | None = None,
               supersample: int | None = None) -> RenderResult:
        """What camera ``role`` sees at time ``t`` (s), noise from ``rng``; optionally with ground truth.

        ``window="object"`` renders only the object's image footprint (:meth:`object_window`), the
        rest of the frame a flat table grey: the same pixels there and the same noise draws, for a
        consumer that only looks at the object (the fixed camera's marker tracker, He et al. 1996
        §4.1); a tuple (x0, y0, x1, y1) px gives the window directly. ``supersample`` overrides
        the world's anti-aliasing for this frame (1: none; a marker tracker needs none, the
        silhouette matcher does).
        """
        rig = self.rigs.get(role)
        if rig is None:
            raise WorldError(f"unknown camera role {role!r}; expected one of {CAMERA_ROLES}")
        T_w_c = self.T_w_c(role, t)
        meshes = self.meshes_at(t)
        blur = None
        offsets: list[float] = []
        if rig.exposure_s > 0 and rig.blur_samples > 1:
            # sub-frames symmetric about t over the exposure (t is the exposure's middle)
            m = max(rig.blur_samples // 2, 1)
            offsets = [sign * rig.exposure_s / 2 * j / m for j in range(1, m + 1) for sign in (-1.0, 1.0)]
            blur = [(self.T_w_c(role, t + dt), self.meshes_at(t + dt)) for dt in offsets]
        if isinstance(window, str):
            if window != "object":
                raise WorldError(f"unknown window {window!r}; expected 'object' or (x0, y0, x1, y1)")
            states = [(T_w_c, meshes)] + (blur or [])
            window = self.object_window(role, states)  # the object's footprint: the arm only where it crosses it
        if self.arm is not None:  # the arm occludes, but the window stays the object's
            win = window if isinstance(window, tuple) else None
            meshes = meshes + self.arm_meshes(role, t, win)
            if blur is not None:
                blur = [(T, ms + self.arm_meshes(role, t + dt, win)) for (T, ms), dt in zip(blur, offsets)]
        return render(rig.model, T_w_c, meshes, table=self.table_surface(t), light_dir_w=self.light_dir_w,
                      noise_sigma=rig.noise_sigma, rng=rng, exposure_motion=blur, truth=truth,
                      supersample=self.supersample if supersample is None else supersample, window=window,
                      effects=rig.effects)

    _WINDOW_MARGIN_PX = 8  # > the marker pass's 3 px and the anti-aliasing's 1 px, plus distortion's bow

    def object_window(self, role: str, states) -> tuple[int, int, int, int] | None:
        """Pixel box (x0, y0, x1, y1), ends exclusive, holding every vertex of the meshes of ``states``
        ``[(T_w_c, meshes), ...]`` as camera ``role`` sees them, plus a margin; None (the full
        frame) when a vertex is behind the camera or cannot be projected; (0, 0, 0, 0) without meshes.
        """
        cam = self.rigs[role].model
        pts = []
        for T_w_c, meshes in states:
            for mesh in meshes:
                T_c_w = invert(T_w_c)
                P = np.asarray(mesh.vertices, float) @ T_c_w[:3, :3].T + T_c_w[:3, 3]
                if not np.all(P[:, 2] > 1.0):
                    return None
                pts.append(cam.project(P))
        if not pts:
            return (0, 0, 0, 0)
        px = np.concatenate(pts)
        if not np.all(np.isfinite(px)):
            return None
        m = self._WINDOW_MARGIN_PX
        lo = np.floor(px.min(axis=0)) - m
        hi = np.ceil(px.max(axis=0)) + m + 1
        return (int(max(lo[0], 0)), int(max(lo[1], 0)), int(min(hi[0], cam.width)), int(min(hi[1], cam.height)))

    def truth(self, t: float) -> WorldTruth:
        """Ground truth at time t: object identity and pose, marker poses, table and camera poses (W)."""
        T_w_t = self.T_w_t(t)
        markers = []
        if self.obj is not None:
            markers = [(i, apply(T_w_t, c), rotate(T_w_t, n)) for i, c, n, _ in self._markers_t]
        return WorldTruth(t=float(t), object_name=None if self.obj is None else self.obj.name,
                          placement=self.placement, T_w_t=T_w_t, T_w_o=self.T_w_o(t), markers_w=markers,
                          T_w_c1=self.T_w_c1, T_w_c2=self.T_w_c("mobile", t))

    # --- construction from a lab ------------------------------------------------------------
    @classmethod
    def from_lab(cls, lab, *, obj: SimObject | None = None, placement: Placement | None = None,
                 table_position: Callable[[float], Sequence[float] | np.ndarray] | None = None,
                 flange_pose_at: Callable[[float], np.ndarray] | None = None,
                 exposure_s: float = 0.0, supersample: int = 3, arm: bool = True,
                 arm_joints_at: Callable[[float], np.ndarray] | None = None) -> Self:
        """The world of a lab's driver files (their *sim* ground-truth fields, via :mod:`labctl.sim.truth`).

        Defaults: the table held at the centre of its travel, the robot at home looking at the
        table's centre (:func:`home_flange_pose`). ``arm``: draw the lab's arm (``lab.arm``, when its file
        gives link radii) in both cameras; ``arm_joints_at(t)``: its joints (rad) at time ``t`` (s) as its
        controller keeps them (default: the body follows ``flange_pose_at`` by IK).
        """
        from .effects import effects_from_lab
        from .truth import camera_model, fixed_camera_pose, hand_eye

        T_f_c2 = hand_eye(lab.mobile_camera)
        if table_position is None:
            centre = (lab.table.travel_mm[0] / 2.0, lab.table.travel_mm[1] / 2.0, 0.0)
            table_position = _constant(centre)
        if flange_pose_at is None:
            flange_pose_at = _constant(home_flange_pose(lab, T_f_c2))
        return cls(
            fixed=CameraRig(camera_model(lab.fixed_camera), lab.fixed_camera.noise_sigma, exposure_s,
                            effects=effects_from_lab(lab, lab.fixed_camera)),
            mobile=CameraRig(camera_model(lab.mobile_camera), lab.mobile_camera.noise_sigma, exposure_s,
                             effects=effects_from_lab(lab, lab.mobile_camera)),
            T_w_c1=fixed_camera_pose(lab.fixed_camera), T_f_c2=T_f_c2, table_origin_w=lab.table.origin_w_mm,
            table_position=table_position, flange_pose_at=flange_pose_at, obj=obj, placement=placement,
            supersample=supersample, arm=ArmBody.from_config(lab.arm, arm_joints_at) if arm else None,
        )


def table_centre_w(lab) -> np.ndarray:
    """The centre of the table's travel area in W (mm, z = 0)."""
    o = np.asarray(lab.table.origin_w_mm, float)
    return o + np.array([lab.table.travel_mm[0] / 2.0, lab.table.travel_mm[1] / 2.0, 0.0]) * [1, 1, 0]


def home_flange_pose(lab, T_f_c2: np.ndarray | None = None, target_w=None) -> np.ndarray:
    """``T_b_f`` that puts the mobile camera at the robot's home position looking at ``target_w``
    (default: the table centre), image up towards +y of W. Robot base B = W in the sample lab."""
    from .truth import hand_eye

    T_f_c2 = hand_eye(lab.mobile_camera) if T_f_c2 is None else T_f_c2
    target = table_centre_w(lab) if target_w is None else np.asarray(target_w, float)
    T_w_c2 = look_at(np.asarray(lab.robot.home_mm, float), target, up=(0.0, 1.0, 0.0))
    return T_w_c2 @ invert(T_f_c2)
