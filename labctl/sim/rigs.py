"""The simulated lab as the offline procedures see it: a calibration rig and a standard-view camera.

* :class:`CalibrationRig` — :mod:`labctl.calibration.procedure`'s ``Rig``: renders the target with
  the true cameras; the robot reports exactly the commanded flange pose.
* :func:`standard_view_renderer` — what ``teach-object`` and the recognition benchmark render: the
  object resting on the table, seen by the robot's mobile camera along a marker normal.

Both are adapters between procedures that may not import the simulator and :mod:`.render`.
"""

from __future__ import annotations

import numpy as np


class CalibrationRig:
    """The simulated lab as a calibration rig: renders the target/plate with the true cameras.

    Adapter between :mod:`labctl.calibration.procedure` (which may not import the simulator) and
    :mod:`labctl.sim.render`; the robot reports exactly the commanded flange pose.
    """

    def __init__(self, lab, target, seed: int = 0):
        from ..geometry import make_T
        from . import truth

        self.lab, self.target = lab, target
        self.rng = np.random.default_rng(seed)
        self.c1, self.T_w_c1 = truth.camera_model(lab.fixed_camera), truth.fixed_camera_pose(lab.fixed_camera)
        self.c2, self.X = truth.camera_model(lab.mobile_camera), truth.hand_eye(lab.mobile_camera)
        self.T_w_table = make_T(None, lab.table.origin_w_mm)

    def _mesh(self, solid, T, colours):
        from .render import MarkerDisc, Mesh

        s = solid.transformed(T)
        marks = [MarkerDisc(c, n, r, col) for c, n, r, col in zip(s.dots, s.normals, s.radii, colours)]
        return Mesh(s.vertices, s.faces, tuple(self.target.plate_colour_bgr), marks)

    def fixed_image(self, T_w_t):
        from .render import render

        mesh = self._mesh(self.target.solid(), T_w_t, self.target.dot_colours())
        return render(self.c1, self.T_w_c1, [mesh], noise_sigma=self.lab.fixed_camera.noise_sigma, rng=self.rng).image

    def mobile_image(self, T_b_f):
        from .render import render

        mesh = self._mesh(self.target.solid(), self.target.T_w_t, self.target.dot_colours())
        img = render(self.c2, T_b_f @ self.X, [mesh], noise_sigma=self.lab.mobile_camera.noise_sigma, rng=self.rng)
        return img.image, T_b_f

    def table_image(self, xy):
        from ..geometry import make_T
        from .render import TableSurface, render

        T = self.T_w_table @ make_T(None, [xy[0], xy[1], 0.0])
        mesh = self._mesh(self.target.plate_solid(), T, [tuple(self.target.dot_colour_bgr)])
        return render(self.c1, self.T_w_c1, [mesh], table=TableSurface(origin_w=(float(T[0, 3]), float(T[1, 3]))),
                      noise_sigma=self.lab.fixed_camera.noise_sigma, rng=self.rng).image


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

        def render_view(T_o_c):
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
            return render(camera, T_w_o @ T_o_c, [Mesh(Vw, F, markers=discs)], table=table,
                          noise_sigma=noise_sigma, rng=rng).image

        return render_view

    return factory
