"""The robot arm as the simulated cameras see it: its links as capsules along the DH chain, posed by
following the flange with inverse kinematics.

In the paper the mobile camera rides the wrist of a six-joint arm (He et al. 1996 §5.1); on a real lab
the arm reaches over the table and crosses the fixed camera's view of it, so the simulated lab draws it.

* **Pose.** In a simulated lab the drawn arm is the controller's arm: its joints are the ones the robot
  controller's emulator keeps for the segment it flies (``joints_at``, :meth:`labctl.sim.emulators.robot.
  RobotEmulator.configuration_at`), so the picture and the controller agree and no frame solves IK. A world
  without a controller (its flange a pose, or a function of time) follows the flange with
  :meth:`labctl.planning.arm.ArmModel.ik` seeded with the configuration of the previous frame, starting in
  the branch of the arm's home (:meth:`ArmBody.q_at`). A pose the arm cannot reach leaves it where it last
  was (``ik_failures``).
* **Links.** Each DH step ``Rz(θ)·Tz(d)·Tx(a)·Rx(α)`` moves along z by ``d`` and then along x by ``a``;
  every non-zero move is one capsule (a cylinder with hemispherical ends, radius the arm file's
  ``link_radius_mm`` of that joint's link), from DH frame 0 (the base, on its mount) to frame 6 (the
  flange). Capsules, not boxes: round ends close the joints between links as the real housings do,
  and the silhouette does not depend on the links' roll, which the DH frames do not give.
* **The mobile camera's own wrist.** The camera is fixed to the flange in front of the last two links
  (wrist 2 and wrist 3 carry it): :data:`MOBILE_SKIP_LINKS` of them are left out of its own image, which
  a camera cannot see through its mount. The links left (base, arms, wrist 1) lie behind its optical
  centre in every pose the planner flies (checked by tests/test_arm_render.py).

Millimetres and radians; poses ``T_<to>_<from>``.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..geometry import make_T

#: the arm's colour (BGR): a dark neutral grey, darker than the parts and never red (the markers are)
ARM_COLOUR_BGR = (92, 92, 96)
#: links left out of the mobile camera's image: the two wrist links its mount sits on (see the module doc)
MOBILE_SKIP_LINKS = 2
#: the mobile camera on its bracket as the fixed camera sees it: a box in the camera's frame, x and y across
#: (mm), z from the bracket's back to the lens's front (a 29-mm machine-vision body, a 25-mm lens ~Ø30 × 35 mm,
#: the bracket round them); the lens's front a few mm behind the optical centre
CAMERA_BODY_XY_MM = (50.0, 50.0)
CAMERA_BODY_Z_MM = (-90.0, -5.0)
#: facets round a capsule and rings in each hemispherical end: a 12-gon is within 3.4 % of the circle's
#: radius (1.5 mm at 45 mm), below a pixel of the fixed camera at the arm's height (~0.6 mm/px)
_SIDES = 12
_CAP_RINGS = 2


def _capsule(radius: float, length: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed capsule along +z from 0 to ``length`` (mm), outward counter-clockwise faces: vertices, faces."""
    ang = 2 * np.pi * np.arange(_SIDES) / _SIDES
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    rings = []  # (z, r) of each ring, from the bottom pole's neighbour to the top pole's
    for k in range(_CAP_RINGS, 0, -1):  # bottom cap
        phi = math.pi / 2 * k / (_CAP_RINGS + 1)
        rings.append((-radius * math.sin(phi), radius * math.cos(phi)))
    rings += [(0.0, radius), (length, radius)]
    for k in range(1, _CAP_RINGS + 1):  # top cap
        phi = math.pi / 2 * k / (_CAP_RINGS + 1)
        rings.append((length + radius * math.sin(phi), radius * math.cos(phi)))
    verts = [np.array([[0.0, 0.0, -radius]])]
    verts += [np.column_stack([r * ring, np.full(_SIDES, z)]) for z, r in rings]
    verts.append(np.array([[0.0, 0.0, length + radius]]))
    V = np.concatenate(verts)
    n_r, top = len(rings), len(V) - 1
    faces = []
    for j in range(_SIDES):  # bottom fan, seen from below: counter-clockwise outward
        faces.append((0, 1 + (j + 1) % _SIDES, 1 + j))
    for i in range(n_r - 1):
        a, b = 1 + i * _SIDES, 1 + (i + 1) * _SIDES
        for j in range(_SIDES):
            j1 = (j + 1) % _SIDES
            faces += [(a + j, a + j1, b + j1), (a + j, b + j1, b + j)]
    last = 1 + (n_r - 1) * _SIDES
    for j in range(_SIDES):
        faces.append((top, last + j, last + (j + 1) % _SIDES))
    return V, np.array(faces, np.int64)


def camera_body(T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mobile camera's body (:data:`CAMERA_BODY_XY_MM`, :data:`CAMERA_BODY_Z_MM`) at its pose ``T_w_c`` as a
    closed box mesh in W: vertices (mm), outward counter-clockwise faces."""
    (hx, hy), (z0, z1) = (v / 2 for v in CAMERA_BODY_XY_MM), CAMERA_BODY_Z_MM
    corners = np.array([[x, y, z] for z in (z0, z1) for y in (-hy, hy) for x in (-hx, hx)])
    faces = np.array([(0, 2, 1), (1, 2, 3), (4, 5, 6), (5, 7, 6), (0, 1, 4), (1, 5, 4),
                      (2, 6, 3), (3, 6, 7), (0, 4, 2), (2, 4, 6), (1, 3, 5), (3, 7, 5)], np.int64)
    T = np.asarray(T_w_c, float)
    return corners @ T[:3, :3].T + T[:3, 3], faces


def body_hides(T_w_c: np.ndarray, eye_w, points_w) -> np.ndarray:
    """Which of ``points_w`` (N×3, mm W) the mobile camera's body (:func:`camera_body`, at ``T_w_c``) hides from
    a camera at ``eye_w``: the sight line crosses the box (slab test in the body's frame)."""
    from ..geometry import invert

    T_c_w = invert(np.asarray(T_w_c, float))
    e = T_c_w[:3, :3] @ np.asarray(eye_w, float) + T_c_w[:3, 3]
    P = np.asarray(points_w, float).reshape(-1, 3) @ T_c_w[:3, :3].T + T_c_w[:3, 3]
    (hx, hy), (z0, z1) = (v / 2 for v in CAMERA_BODY_XY_MM), CAMERA_BODY_Z_MM
    lo, hi = np.array([-hx, -hy, z0]), np.array([hx, hy, z1])
    d = P - e
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - e) / d, (hi - e) / d
    near = np.where(d != 0, np.minimum(t0, t1), np.where((e >= lo) & (e <= hi), -np.inf, np.inf))
    far = np.where(d != 0, np.maximum(t0, t1), np.where((e >= lo) & (e <= hi), np.inf, -np.inf))
    enter, leave = np.max(near, axis=1), np.min(far, axis=1)
    return (enter <= leave) & (leave >= 0.0) & (enter <= 1.0)


def _frame_along(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """A 4×4 pose whose origin is ``p0`` and whose z axis points at ``p1`` (the capsule's frame)."""
    z = (p1 - p0) / np.linalg.norm(p1 - p0)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return make_T(np.column_stack([x, np.cross(z, x), z]), p0)


@dataclass(frozen=True)
class Capsule:
    """One link piece: joint ``link`` (1–6, the DH row whose step it is), ``radius`` (mm) and where its step
    starts in that row's frames (``along``: ``"d"``, along z of the frame before, or ``"a"``, along x after)."""

    link: int
    along: str
    radius: float
    length: float


class ArmBody:
    """A six-joint arm's links in the world, following the flange (see the module doc).

    ``model``: the arm's :class:`~labctl.planning.arm.ArmModel` (its mount ``T_w_base`` in the world);
    ``link_radius_mm``: each DH row's link radius (mm); ``joints_at(t)``: the arm's configuration (rad) at time
    ``t`` (s) as its controller keeps it, when there is one (else the body follows the flange by IK)."""

    def __init__(self, model, link_radius_mm, joints_at: Callable[[float], np.ndarray] | None = None):
        self.model = model
        self.joints_at = joints_at
        self.radius = np.asarray(link_radius_mm, float).reshape(6)
        self.capsules: list[Capsule] = []
        self._local: list[tuple[np.ndarray, np.ndarray]] = []
        for i in range(6):
            for along, length in (("d", abs(float(model.d[i]))), ("a", abs(float(model.a[i])))):
                if length > 1e-9:
                    self.capsules.append(Capsule(i + 1, along, float(self.radius[i]), length))
                    self._local.append(_capsule(float(self.radius[i]), length))
        self._q: np.ndarray | None = None
        self._T: np.ndarray | None = None
        self._cache: dict[float, np.ndarray] = {}
        self._segments: dict[bytes, list[tuple[np.ndarray, np.ndarray, float]]] = {}
        self._placed_at: dict[bytes, list[np.ndarray]] = {}
        self._lock = threading.Lock()  # a served lab renders its two cameras from two threads
        self.ik_failures = 0

    @classmethod
    def from_config(cls, cfg, joints_at: Callable[[float], np.ndarray] | None = None) -> ArmBody | None:
        """The body of an :class:`~labctl.config.arm.ArmConfig` (None when its file gives no link radii), posed by
        its controller's ``joints_at`` when given."""
        if cfg is None or cfg.link_radius_mm is None:
            return None
        from ..planning.arm import ArmModel

        return cls(ArmModel.from_config(cfg), cfg.link_radius_mm, joints_at)

    # --- pose -------------------------------------------------------------------------------
    def _first(self, T_w_F: np.ndarray) -> np.ndarray:
        """The configuration at the first pose: in the home's branch, nearest the home."""
        m = self.model
        branch = m.configuration(m.home)
        same = [q for q in m.closed_form(T_w_F) if m.configuration(q) == branch]
        seeds = sorted(same, key=lambda q: float(np.max(np.abs(q - m.home)))) + [m.home]
        for seed in seeds:
            res = m.ik(T_w_F, seed)
            if res.ok:
                return res.q
        self.ik_failures += 1
        return m.home.copy()

    def q_for(self, T_w_F: np.ndarray) -> np.ndarray:
        """The arm's configuration with its flange at ``T_w_F`` (4×4, W): IK from the last configuration."""
        if self._q is None:
            self._q, self._T = self._first(T_w_F), T_w_F.copy()
            return self._q
        if self._T is not None and np.array_equal(T_w_F, self._T):  # standing still (most frames)
            return self._q
        self._T = T_w_F.copy()
        res = self.model.ik(T_w_F, self._q)
        if res.ok:
            self._q = res.q
        else:  # out of the arm's reach: it stays where it was
            self.ik_failures += 1
        return self._q

    def q_at(self, t: float, T_w_F) -> np.ndarray:
        """The configuration at time ``t`` (s): the controller's (``joints_at``) when the body has one, else
        :meth:`q_for` at the flange pose ``T_w_F`` (4×4, or a function of t); remembered per time: a frame's
        cameras and passes share one answer."""
        with self._lock:
            q = self._cache.get(t)
            if q is None:
                if len(self._cache) > 64:
                    self._cache.clear()
                if self.joints_at is not None:
                    q = np.asarray(self.joints_at(t), float)
                else:
                    q = self.q_for(np.asarray(T_w_F(t) if callable(T_w_F) else T_w_F, float))
                self._cache[t] = q
            return q

    # --- geometry ---------------------------------------------------------------------------
    def segments(self, q) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """Each capsule's axis in W: ``(start, end, radius)`` (mm), base first, flange last; remembered per
        configuration (a frame's render and its occlusion truth walk the same chain)."""
        key = np.asarray(q, float).tobytes()
        with self._lock:
            out = self._segments.get(key)
        if out is None:
            out = self._chain(q)
            with self._lock:
                if len(self._segments) > 64:
                    self._segments.clear()
                self._segments[key] = out
        return out

    def _chain(self, q) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """The capsules' axes of :meth:`segments`, walked down the DH chain."""
        m = self.model
        T = m.T_w_base.copy()
        out = []
        for i in range(6):
            th = float(q[i]) + float(m.offset[i])
            ct, st = math.cos(th), math.sin(th)
            Rz = make_T(np.array([[ct, -st, 0.0], [st, ct, 0.0], [0.0, 0.0, 1.0]]), np.zeros(3))
            T = T @ Rz
            p0 = T[:3, 3].copy()
            T = T @ make_T(None, (0.0, 0.0, float(m.d[i])))
            p1 = T[:3, 3].copy()
            if abs(float(m.d[i])) > 1e-9:
                out.append((p0, p1, float(self.radius[i])))
            T = T @ make_T(None, (float(m.a[i]), 0.0, 0.0))
            p2 = T[:3, 3].copy()
            if abs(float(m.a[i])) > 1e-9:
                out.append((p1, p2, float(self.radius[i])))
            ca, sa = math.cos(float(m.alpha[i])), math.sin(float(m.alpha[i]))
            T = T @ make_T(np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]]), np.zeros(3))
        return out

    def mesh(self, q, *, skip_last: int = 0, view=None) -> tuple[np.ndarray, np.ndarray]:
        """The links at ``q`` as one closed triangle mesh in W (vertices mm, faces), leaving out the links
        of the last ``skip_last`` joints (the mobile camera's own wrist). ``view`` ``(camera, T_w_c, window)``
        leaves out the capsules wholly outside that camera's view (or its pixel window (x0, y0, x1, y1)):
        they would cost the rasteriser their triangles' set-up for no pixel."""
        keep_links = 6 - skip_last
        cull = None if view is None else _ViewCull(*view)
        verts, faces, n = [], [], 0
        placed = self._placed(q)
        for cap, (_, F), (p0, p1, r), Vw in zip(self.capsules, self._local, self.segments(q), placed):
            if cap.link > keep_links or (cull is not None and not cull.may_see(p0, p1, r)):
                continue
            verts.append(Vw)
            faces.append(F + n)
            n += len(Vw)
        if not verts:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        return np.concatenate(verts), np.concatenate(faces)

    def _placed(self, q) -> list[np.ndarray]:
        """Each capsule's vertices in W at ``q`` (mm), remembered per configuration: an arm at rest (most
        frames) is placed once, whatever each camera and window then culls."""
        key = np.asarray(q, float).tobytes()
        with self._lock:
            out = self._placed_at.get(key)
        if out is None:
            out = []
            for (V, _), (p0, p1, _) in zip(self._local, self.segments(q)):
                T = _frame_along(p0, p1)
                out.append(V @ T[:3, :3].T + T[:3, 3])
            with self._lock:
                if len(self._placed_at) > 16:
                    self._placed_at.clear()
                self._placed_at[key] = out
        return out

    def hides(self, q, eye_w, points_w, *, skip_last: int = 0) -> np.ndarray:
        """Which of ``points_w`` (N×3, mm) the links at ``q`` hide from a camera at ``eye_w``: the sight line
        passes inside a capsule (segment–segment distance below its radius). Exact for the capsules drawn
        up to their 12-gon facets."""
        eye = np.asarray(eye_w, float)
        P = np.asarray(points_w, float).reshape(-1, 3)
        kept = [seg for cap, seg in zip(self.capsules, self.segments(q)) if cap.link <= 6 - skip_last]
        if not kept or not len(P):
            return np.zeros(len(P), bool)
        a0 = np.array([k[0] for k in kept])
        a1 = np.array([k[1] for k in kept])
        r = np.array([k[2] for k in kept])
        return np.any(_segment_distance(eye, P, a0, a1) < r[:, None], axis=0)


class _ViewCull:
    """Whether a capsule may show in a camera's view: its bounding sphere against the four side planes of
    the view (or of a pixel window's) frustum, and the near plane (normalised image coordinates, 5 % margin
    for the lens distortion between the sampled boundary points)."""

    def __init__(self, camera, T_w_c, window=None):
        from ..geometry import invert

        x0, y0, x1, y1 = (0, 0, camera.width, camera.height) if window is None else window
        xs, ys = np.array([x0 - 0.5, (x0 + x1) / 2, x1 - 0.5]), np.array([y0 - 0.5, (y0 + y1) / 2, y1 - 0.5])
        px = np.array([[x, y] for x in xs for y in ys if (x, y) != (xs[1], ys[1])], float)
        nrm = camera.normalized(px)
        lo, hi = nrm.min(axis=0), nrm.max(axis=0)
        pad = 0.05 * (hi - lo) + 1e-9
        lo, hi = lo - pad, hi + pad
        # outward normals of the planes x = hi_x z, x = lo_x z, y = hi_y z, y = lo_y z
        planes = np.array([[1.0, 0.0, -hi[0]], [-1.0, 0.0, lo[0]], [0.0, 1.0, -hi[1]], [0.0, -1.0, lo[1]]])
        self.planes = planes / np.linalg.norm(planes, axis=1, keepdims=True)
        self.T_c_w = invert(np.asarray(T_w_c, float))

    def may_see(self, p0, p1, r: float) -> bool:
        """The capsule from ``p0`` to ``p1`` (W, mm) of radius ``r`` may cover a pixel of the view."""
        c_w = 0.5 * (np.asarray(p0) + np.asarray(p1))
        R = 0.5 * float(np.linalg.norm(np.asarray(p1) - np.asarray(p0))) + r
        c = self.T_c_w[:3, :3] @ c_w + self.T_c_w[:3, 3]
        return bool(c[2] + R > 1.0 and np.all(self.planes @ c <= R))


def _segment_distance(e: np.ndarray, P: np.ndarray, a0: np.ndarray, a1: np.ndarray) -> np.ndarray:
    """Distances (mm) between the segments ``e``–``P[k]`` and ``a0``–``a1`` (Ericson, Real-Time Collision
    Detection §5.1.9, clamped closest points): N distances for one segment ``a0``–``a1`` (3,), or M×N for
    M of them (M×3 each), all at once."""
    one = np.ndim(a0) == 1
    a0, a1 = np.atleast_2d(a0)[:, None, :], np.atleast_2d(a1)[:, None, :]  # (M, 1, 3)
    d1 = (P - e)[None]  # (1, N, 3)
    d2 = a1 - a0
    r = e - a0
    a = np.sum(d1 * d1, axis=-1)
    ee = np.sum(d2 * d2, axis=-1)
    f = np.sum(d2 * r, axis=-1)
    c = np.sum(d1 * r, axis=-1)
    b = np.sum(d1 * d2, axis=-1)
    denom = a * ee - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-12, np.clip((b * f - c * ee) / denom, 0.0, 1.0), 0.0)
    t = (b * s + f) / ee
    t_c = np.clip(t, 0.0, 1.0)
    s = np.where(t < 0.0, np.clip(-c / a, 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / a, 0.0, 1.0), s))
    c1 = e + s[..., None] * d1
    c2 = a0 + t_c[..., None] * d2
    dist = np.linalg.norm(c1 - c2, axis=-1)
    return dist[0] if one else dist
