"""The simulated lab as the offline procedures see it: a calibration rig and a standard-view camera.

* :class:`SimCalibrationLab` — what ``labctl calibrate`` drives in the simulator: the emulators
  behind the real drivers and the simulated cameras, the calibration target riding the table.
* :func:`standard_view_renderer` — what ``teach-object`` and the recognition benchmark render: the
  object resting on the table, seen by the robot's mobile camera along a marker normal.

Both are adapters between procedures that may not import the simulator and :mod:`.render`.
"""

from __future__ import annotations

import numpy as np


def target_world(lab, target, *, table_position, flange_pose_at, supersample: int = 3, obj=None, placement=None,
                 arm_joints_at=None):
    """A :class:`~labctl.sim.world.SimWorld` of ``lab`` whose only object is the calibration
    ``target`` on its locating pins on the carriage, raised by ``world.spacer_mm`` (a light
    block under it): ``T_w_target = T_w_table(t) · (0, 0, spacer) · T_table_mount``.

    With ``obj``/``placement`` the world holds the run's object as well and can switch between
    the two scenes: ``world.set_scene(t, calibration, spacer_mm)`` takes effect for frames
    exposed at or after ``t`` (s, the world's clock), so a frame never shows a change made after
    its exposure (the served lab's control endpoint, :class:`labctl.runtime.simlab.ServedLab`).
    Without a change, the scene is ``world.calibration`` (default True) on ``world.spacer_mm``.
    ``arm_joints_at``: the controller's joints, which the drawn arm takes (:meth:`SimWorld.from_lab`).
    """
    import bisect
    import threading

    from .render import MarkerDisc, Mesh
    from .world import SimWorld

    class _World(SimWorld):
        spacer_mm = 0.0
        calibration = True
        _changes: list[tuple[float, bool, float]]  # (from t, calibration, spacer_mm), set on the instance below
        _changes_lock: threading.Lock

        def set_scene(self, t: float, calibration: bool, spacer_mm: float = 0.0) -> None:
            """From time ``t`` on: the target on a ``spacer_mm`` spacer (``calibration``) or the object."""
            with self._changes_lock:
                if self._changes and t < self._changes[-1][0]:
                    t = self._changes[-1][0]  # changes are in time order: never rewrite the past
                self._changes.append((float(t), bool(calibration), float(spacer_mm)))

        def scene_at(self, t: float) -> tuple[bool, float]:
            """``(calibration, spacer_mm)`` of the frame exposed at ``t``."""
            with self._changes_lock:
                i = bisect.bisect_right([c[0] for c in self._changes], t)
                if i == 0:
                    return self.calibration, self.spacer_mm
                return self._changes[i - 1][1:]

        def meshes_at(self, t):
            calibration, spacer = self.scene_at(t)
            if not calibration:
                return super().meshes_at(t)
            T = self.T_w_t(t) @ target.T_table_t((0.0, 0.0), spacer)
            s = target.solid().transformed(T)
            marks = [MarkerDisc(c, n, r, col) for c, n, r, col in zip(s.dots, s.normals, s.radii, target.dot_colours())]
            meshes = [Mesh(s.vertices, s.faces, tuple(target.plate_colour_bgr), marks)]
            if spacer > 0:  # the spacer: a grey block under the target's footprint
                import trimesh

                w, length = target.footprint_mm
                box = trimesh.creation.box([w, length, spacer])  # outward winding, centred
                V = np.asarray(box.vertices) + [0.0, 0.0, spacer / 2.0]
                Tm = self.T_w_t(t) @ target.T_table_mount
                meshes.append(Mesh(V @ Tm[:3, :3].T + Tm[:3, 3], np.asarray(box.faces), (120, 120, 120)))
            return meshes

    world = _World.from_lab(lab, table_position=table_position, flange_pose_at=flange_pose_at,
                            arm_joints_at=arm_joints_at, supersample=supersample, obj=obj, placement=placement)
    world._changes, world._changes_lock = [], threading.Lock()
    return world


class SimCalibrationLab:
    """The simulated lab for ``labctl calibrate``, in one process on a virtual clock.

    :meth:`labctl.sim.lab.SimLab.build` with the target on the carriage: the GRBL and robot
    emulators behind the real drivers (bytes in the real protocols on in-process ports, paced at
    the driver files' baud rates), both simulated cameras rendering a world in which the
    calibration target rides the table's carriage and the mobile camera the robot's flange.
    :meth:`place_target` is the simulator's hook for the procedure's prompt
    (:class:`labctl.calibration.procedure.Prompt`): it puts the target on the requested spacer.
    ``truth()`` is the ground truth the calibration is checked against (:mod:`.truth`, from the
    driver files; the calibration code never sees it).
    """

    def __init__(self, lab, target, seed: int = 0):
        from .clock import VirtualClock
        from .lab import Scene, SimLab

        self.lab, self.target = lab, target
        self.sim = sim = SimLab.build(lab, VirtualClock(0.0), scene=Scene(target=target), seed=seed)
        self.clock, self.grbl, self.robot_emu = sim.clock, sim.grbl, sim.robot_emu
        self.table, self.robot, self.world, self.cameras = sim.table, sim.robot, sim.world, sim.cameras
        self.prompts: list[float] = []

    def open(self) -> None:
        """Open every device and home the table (GRBL powers up locked until homed, as a lab is
        homed before it is calibrated; homing takes virtual time only)."""
        self.sim.open()
        self.table.home()

    def close(self) -> None:
        """Close every device of the rig."""
        self.sim.close()

    def place_target(self, spacer_mm: float, index: int, count: int) -> None:
        """The prompt's simulator hook: the target is now on a ``spacer_mm`` spacer."""
        self.prompts.append(float(spacer_mm))
        self.world.spacer_mm = float(spacer_mm)

    def truth(self) -> dict:
        """Ground truth: both true cameras, C1's pose, the hand-eye X and the table frame (W)."""
        from ..geometry import make_T
        from . import truth

        lab = self.lab
        return {"fixed_camera": truth.camera_model(lab.fixed_camera),
                "T_w_c1": truth.fixed_camera_pose(lab.fixed_camera),
                "mobile_camera": truth.camera_model(lab.mobile_camera), "T_f_c2": truth.hand_eye(lab.mobile_camera),
                "T_w_table": make_T(None, lab.table.origin_w_mm)}


def standard_view_renderer(camera, *, noise_sigma: float = 2.0, rng=None, table_origin=(0.0, 0.0),
                       pose_choice: str = "upright", random_yaw: bool = False):
    """``(mesh_o, markers, stable_poses=None) -> render_view(T_o_c) -> BGR`` with ``labctl.sim.render``.

    Renders what the robot's mobile camera sees in the simulated lab: the object rests on the
    table in a stable pose that puts the camera above the table
    (:func:`labctl.library.views.resting_pose_for_view`, ``pose_choice`` "upright" when teaching,
    "random" for benchmark queries; ``random_yaw`` turns it about the vertical), the camera at
    ``T_o_c`` in the object frame, the textured table as background. If no stable pose puts the
    camera above the table, the object is turned so that the view looks straight down and set
    on the table by its lowest point (the only way to take that view).
    """
    from ..geometry import make_T, rotvec_to_matrix
    from ..library.model import stable_poses as compute_stable_poses
    from ..library.views import resting_pose_for_view
    from .render import MarkerDisc, Mesh, TableSurface, render

    rng = rng if rng is not None else np.random.default_rng(0)
    table = TableSurface(origin_w=table_origin)

    def factory(mesh_o, markers, stable_poses=None):
        V = np.asarray(mesh_o.vertices, float)
        F = np.asarray(mesh_o.faces)
        poses = stable_poses if stable_poses is not None else compute_stable_poses(mesh_o)

        def render_view(T_o_c, with_pose: bool = False):
            """The BGR image seen from ``T_o_c``; with ``with_pose``, (image, ``T_w_o`` the resting pose)."""
            yaw = float(rng.uniform(-np.pi, np.pi)) if random_yaw else 0.0
            T_w_o = resting_pose_for_view(poses, T_o_c, yaw_rad=yaw, choice=pose_choice, rng=rng)
            if T_w_o is None:
                axis = T_o_c[:3, 2]  # optical axis in O, turned to −z of W
                target = np.array([0.0, 0.0, -1.0])
                v = np.cross(axis, target)
                s, c = np.linalg.norm(v), float(axis @ target)
                R = rotvec_to_matrix(v / s * np.arctan2(s, c)) if s > 1e-12 else (
                    np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0]))
                Vr = V @ R.T
                T_w_o = make_T(R, [-Vr[:, 0].mean(), -Vr[:, 1].mean(), -Vr[:, 2].min()])
            Vw = V @ T_w_o[:3, :3].T + T_w_o[:3, 3]
            discs = [MarkerDisc(T_w_o[:3, :3] @ m.center + T_w_o[:3, 3], T_w_o[:3, :3] @ m.normal, m.radius)
                     for m in markers]
            image = render(camera, T_w_o @ T_o_c, [Mesh(Vw, F, markers=discs)], table=table,
                           noise_sigma=noise_sigma, rng=rng).image
            return (image, T_w_o) if with_pose else image

        return render_view

    return factory
