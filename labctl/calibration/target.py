"""The lab's calibration target: circular dots on a two-plane "roof" (non-coplanar, Tsai §IV.B).

Defined by ``calibration/target.yaml`` (see :func:`load_target`). Two light planes meet at a
ridge along the target's y axis; each carries a grid of dark circular dots; a few dots are
coloured (fiducials) so the grid can be identified in any view. Target frame t: origin at the
centre of the footprint on the table, z up, x across the ridge, y along it. mm throughout.

Also defines the table-registration plate: a light square plate with one dark dot, fixed to
the NC table's carriage at a known table position (used by :mod:`.table`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from ..geometry import make_T, rot_z

TARGET_FILE = "target.yaml"


class TargetError(ValueError):
    """The target file is missing or malformed (one line)."""


@dataclass(frozen=True)
class Solid:
    """A closed convex triangle mesh (outward winding) with dots on it, in some frame."""

    vertices: np.ndarray  # (V, 3) mm
    faces: np.ndarray  # (F, 3) int
    dots: np.ndarray  # (N, 3) dot centres, mm
    normals: np.ndarray  # (N, 3) outward unit normals
    radii: np.ndarray  # (N,) mm

    def transformed(self, T: np.ndarray) -> Solid:
        R, t = T[:3, :3], T[:3, 3]
        return Solid(self.vertices @ R.T + t, self.faces, self.dots @ R.T + t, self.normals @ R.T, self.radii)


def _outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip triangles of a convex solid so their winding is counter-clockwise seen from outside."""
    c = vertices.mean(axis=0)
    out = faces.copy()
    for i, (a, b, d) in enumerate(faces):
        n = np.cross(vertices[b] - vertices[a], vertices[d] - vertices[a])
        if n @ (vertices[[a, b, d]].mean(axis=0) - c) < 0:
            out[i] = (a, d, b)
    return out


def _box(half: np.ndarray, z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
    hx, hy = half
    V = np.array([[x, y, z] for z in (z0, z1) for y in (-hy, hy) for x in (-hx, hx)], dtype=float)
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 5, 7], [4, 7, 6], [0, 1, 5], [0, 5, 4],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 3, 7], [1, 7, 5]])
    return V, _outward(V, F)


@dataclass(frozen=True)
class RoofTarget:
    """Dot target on two planes meeting at a ridge (see module doc). All lengths in mm."""

    width_mm: float = 180.0  # across the ridge (x)
    length_mm: float = 120.0  # along the ridge (y)
    ridge_height_mm: float = 90.0
    eave_height_mm: float = 20.0
    pitch_mm: float = 16.0
    first_dot_mm: float = 10.0  # from the ridge, along each face
    dots_per_face: int = 6  # along the slope
    rows: int = 7  # along the ridge
    dot_radius_mm: float = 3.5
    fiducial_radius_mm: float = 3.5
    # (face, k, row) of the coloured fiducial dots that identify the grid in any view
    fiducials: tuple[tuple[int, int, int], ...] = ((0, 0, 0), (0, 3, 0), (0, 0, 3), (1, 4, 6), (1, 1, 5))
    plate_colour_bgr: tuple[int, int, int] = (215, 215, 215)
    dot_colour_bgr: tuple[int, int, int] = (25, 25, 25)
    fiducial_colour_bgr: tuple[int, int, int] = (170, 70, 20)  # dark blue: chroma tells them apart
    # where it sits in W, on locating pins: (x mm, y mm, yaw deg) on the table plane z = 0. The
    # fixed camera sees it at every placement (one Tsai calibration over all points, as moving
    # Tsai's plate to known positions); the mobile camera's stations look at the first.
    placements_w: tuple[tuple[float, float, float], ...] = (
        (300.0, 200.0, 0.0), (130.0, 80.0, 0.0), (470.0, 80.0, 90.0), (130.0, 320.0, 90.0), (470.0, 320.0, 0.0))
    # table-registration plate on the table carriage
    plate_size_mm: float = 50.0
    plate_thickness_mm: float = 3.0
    plate_dot_radius_mm: float = 8.0
    plate_at_table_mm: tuple[float, float] = (0.0, 0.0)
    table_positions_mm: tuple[tuple[float, float], ...] = (
        (60.0, 60.0), (300.0, 60.0), (540.0, 60.0), (60.0, 200.0), (300.0, 200.0), (540.0, 200.0),
        (60.0, 340.0), (300.0, 340.0), (540.0, 340.0))

    # --- geometry in the target frame -------------------------------------------------------
    def _face(self, side: int):
        a = self.width_mm / 2.0
        rise = self.ridge_height_mm - self.eave_height_mm
        slope_len = float(np.hypot(a, rise))
        d = np.array([side * a, 0.0, -rise]) / slope_len  # down the slope from the ridge
        n = np.array([side * rise, 0.0, a]) / slope_len  # outward normal
        return d, n, slope_len

    def dot_table(self) -> list[tuple[int, int, int]]:
        """(face, k, row) of every dot, in the order of :meth:`solid`'s dots."""
        return [(face, k, j) for face in (0, 1) for k in range(self.dots_per_face) for j in range(self.rows)]

    def dot_colours(self) -> list[tuple[int, int, int]]:
        """BGR colour of every dot (fiducials coloured), in :meth:`solid`'s order."""
        fid = set(self.fiducials)
        return [tuple(self.fiducial_colour_bgr) if d in fid else tuple(self.dot_colour_bgr) for d in self.dot_table()]

    def solid(self) -> Solid:
        """The target in its own frame t: mesh and dots."""
        a, hl = self.width_mm / 2.0, self.length_mm / 2.0
        V = np.array([[x, y, 0.0] for y in (-hl, hl) for x in (-a, a)]
                     + [[x, y, self.eave_height_mm] for y in (-hl, hl) for x in (-a, a)]
                     + [[0.0, -hl, self.ridge_height_mm], [0.0, hl, self.ridge_height_mm]])
        # 0..3 bottom, 4..7 eaves (x=-a,y=-hl | x=a,y=-hl | x=-a,y=hl | x=a,y=hl), 8, 9 ridge
        F = np.array([[0, 1, 3], [0, 3, 2],  # bottom
                      [0, 1, 5], [0, 5, 4], [2, 3, 7], [2, 7, 6],  # long walls
                      [1, 3, 7], [1, 7, 5], [0, 2, 6], [0, 6, 4],  # eave walls
                      [5, 7, 9], [5, 9, 8], [4, 6, 9], [4, 9, 8],  # roof faces
                      [4, 5, 8], [6, 7, 9]])  # gable ends
        F = _outward(V, F)
        ridge = np.array([0.0, 0.0, self.ridge_height_mm])
        fid = set(self.fiducials)
        dots, normals, radii = [], [], []
        for face, k, j in self.dot_table():
            d, n, _ = self._face(+1 if face == 0 else -1)
            s = self.first_dot_mm + k * self.pitch_mm
            y = (j - (self.rows - 1) / 2.0) * self.pitch_mm
            dots.append(ridge + s * d + np.array([0.0, y, 0.0]))
            normals.append(n)
            radii.append(self.fiducial_radius_mm if (face, k, j) in fid else self.dot_radius_mm)
        return Solid(V, F, np.array(dots), np.array(normals), np.array(radii))

    @property
    def fiducial_indices(self) -> np.ndarray:
        table = self.dot_table()
        return np.array([table.index(tuple(f)) for f in self.fiducials])

    @property
    def placements(self) -> list[np.ndarray]:
        """``T_w_t`` of every placement (on its locating pins)."""
        return [make_T(rot_z(np.radians(yaw)), [x, y, 0.0]) for x, y, yaw in self.placements_w]

    @property
    def T_w_t(self) -> np.ndarray:
        """The first placement: where the target sits for the mobile camera."""
        return self.placements[0]

    def plate_solid(self) -> Solid:
        """The table-registration plate in the table-carriage frame (dot centre at
        ``plate_at_table_mm``, on the plate's top face)."""
        V, F = _box(np.array([self.plate_size_mm / 2.0] * 2), 0.0, self.plate_thickness_mm)
        t = np.array([*self.plate_at_table_mm, 0.0])
        dot = np.array([[*self.plate_at_table_mm, self.plate_thickness_mm]])
        return Solid(V + t, F, dot, np.array([[0.0, 0.0, 1.0]]), np.array([self.plate_dot_radius_mm]))

    def check(self) -> None:
        s = self._face(1)[2]
        last = self.first_dot_mm + (self.dots_per_face - 1) * self.pitch_mm
        if min(self.width_mm, self.length_mm, self.pitch_mm, self.dot_radius_mm) <= 0:
            raise TargetError("target sizes must be positive")
        if self.ridge_height_mm <= self.eave_height_mm:
            raise TargetError("ridge_height_mm must exceed eave_height_mm (the target must not be flat)")
        if last + self.fiducial_radius_mm > s or self.first_dot_mm < self.fiducial_radius_mm:
            raise TargetError("the dots do not fit on the roof faces")
        if (self.rows - 1) * self.pitch_mm + 2 * self.fiducial_radius_mm > self.length_mm:
            raise TargetError("the dot rows do not fit along the ridge")
        if self.pitch_mm < 2.5 * max(self.fiducial_radius_mm, self.dot_radius_mm):
            raise TargetError("dots overlap: pitch too small for the fiducial radius")
        if len(set(self.fiducials)) < 4 or not set(self.fiducials) <= set(self.dot_table()):
            raise TargetError("need at least 4 distinct fiducials, each naming an existing (face, k, row) dot")
        if not self.placements_w or any(len(p) != 3 for p in self.placements_w):
            raise TargetError("placements_w: give at least one (x, y, yaw_deg) placement")
        if len(self.table_positions_mm) < 3:
            raise TargetError("table registration needs at least 3 table positions")


def load_target(path: Path | str) -> RoofTarget:
    """Read ``calibration/target.yaml``; raise :class:`TargetError` with a one-line reason."""
    path = Path(path)
    if not path.is_file():
        raise TargetError(f"calibration target file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as exc:
        raise TargetError(f"{path}: not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict) or data.get("kind", "roof") != "roof":
        raise TargetError(f"{path}: expected a mapping with kind: roof")
    fields = RoofTarget.__dataclass_fields__
    unknown = sorted(set(data) - set(fields) - {"kind"})
    if unknown:
        raise TargetError(f"{path}: unknown key(s): {', '.join(unknown)}")
    kw = {}
    for k, v in data.items():
        if k == "kind":
            continue
        if k in ("fiducials", "table_positions_mm", "placements_w"):
            v = tuple(tuple(x) for x in v)
        elif isinstance(v, list):
            v = tuple(v)
        kw[k] = v
    try:
        target = RoofTarget(**kw)
        target.check()
        target.solid()
    except (TypeError, ValueError) as exc:
        raise TargetError(f"{path}: {exc}") from None
    return target


def target_yaml(target: RoofTarget) -> str:
    """The YAML text of a target definition (the sample lab's ``calibration/target.yaml``)."""
    from dataclasses import asdict

    d = {"kind": "roof"}
    for k, v in asdict(target).items():
        if k in ("fiducials", "table_positions_mm", "placements_w"):
            v = [list(x) for x in v]
        d[k] = list(v) if isinstance(v, tuple) else v
    head = ("# Calibration target (labctl calibrate): dark dots on two light planes meeting at a ridge,\n"
            "# non-coplanar for Tsai's method. Target frame: origin at the footprint centre on the table,\n"
            "# z up, x across the ridge. fiducials: (face, k, row) of the coloured dots. placements_w: where\n"
            "# it sits in the world frame during calibration (x, y, yaw_deg). plate_*: the table-registration\n"
            "# plate on the carriage; table_positions_mm: where the table is commanded while C1 looks.\n")
    return head + yaml.safe_dump(d, sort_keys=False, default_flow_style=None)
