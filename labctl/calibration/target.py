"""The lab's calibration targets and where the procedure puts them (``calibration/target.yaml``).

Two kinds, both dark circular dots on light surfaces with a few coloured fiducial dots (told
apart by chroma) that identify the grid in any view. Target frame t: origin at the centre of
the footprint on the table, z up. mm throughout.

* ``kind: plane`` — :class:`PlaneTarget`, a printable flat grid (``labctl calibrate target``
  writes it true to scale). Flat, so the fixed camera must see it at two or more heights
  (spacers) for Tsai's non-coplanar method (Tsai 1987 §IV.B).
* ``kind: roof`` — :class:`RoofTarget`, two planes meeting at a ridge: a 3D target that is
  non-coplanar in one image.

Both carry the procedure's layout (:class:`Layout`): the target sits on locating pins on the NC
table's carriage at ``mount_on_table`` (x, y, yaw° in the table's machine frame at machine
zero), raised by each of ``spacers_mm`` in turn; GRBL moves it to ``fixed_positions_mm`` for
the fixed camera, to ``robot_position_mm`` for the robot's stations and to
``registration_positions_mm`` for table registration. The file may list the dot centres
(``dots_mm``, target frame, as measured on a print); they then replace the nominal grid.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

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
        """This solid moved by the 4×4 pose ``T`` (new frame ← solid frame)."""
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
class Layout:
    """Where the procedure puts the target (table machine frame, mm; see the module doc)."""

    mount_on_table: tuple[float, float, float] = (0.0, 0.0, 0.0)  # x mm, y mm, yaw deg on the carriage
    spacers_mm: tuple[float, ...] = (0.0, 60.0)
    fixed_positions_mm: tuple[tuple[float, float], ...] = (
        (300.0, 200.0), (160.0, 110.0), (440.0, 110.0), (160.0, 290.0), (440.0, 290.0))
    robot_position_mm: tuple[float, float] = (300.0, 200.0)
    registration_positions_mm: tuple[tuple[float, float], ...] = (
        (300.0, 200.0), (120.0, 80.0), (480.0, 80.0), (120.0, 320.0), (480.0, 320.0))
    robot_distance_mm: float = 1000.0  # camera to target at the robot's stations
    robot_stations: int = 10
    plate_colour_bgr: tuple[int, int, int] = (215, 215, 215)
    dot_colour_bgr: tuple[int, int, int] = (25, 25, 25)
    fiducial_colour_bgr: tuple[int, int, int] = (170, 70, 20)  # dark blue: chroma tells them apart
    dots_mm: tuple[tuple[float, float, float], ...] | None = None  # measured centres (replace the grid)

    if TYPE_CHECKING:  # each target kind provides these
        kind: ClassVar[str]

        @property
        def fiducials(self) -> Sequence[tuple[int, ...]]:
            """The coloured fiducial dots, as :meth:`dot_table` names them."""

        @property
        def width_mm(self) -> float:
            """The base's width (x, mm)."""

        @property
        def length_mm(self) -> float:
            """The base's length (y, mm)."""

        def dot_table(self) -> Sequence[tuple[int, ...]]:
            """The name of every dot, in :meth:`solid`'s order."""

    # --- the layout as poses ------------------------------------------------------------------
    @property
    def T_table_mount(self) -> np.ndarray:
        """The target's pose on the carriage with the table at machine zero and no spacer."""
        x, y, yaw = self.mount_on_table
        return make_T(rot_z(np.radians(yaw)), [x, y, 0.0])

    def T_table_t(self, table_xy, spacer_mm: float = 0.0) -> np.ndarray:
        """``T_table_t``: the target with the table at ``table_xy`` (machine mm) on a spacer."""
        return make_T(None, [float(table_xy[0]), float(table_xy[1]), float(spacer_mm)]) @ self.T_table_mount

    @property
    def needs_heights(self) -> int:
        """How many distinct spacer heights the fixed camera needs (2 for a flat target)."""
        return 1

    def _check_layout(self) -> None:
        if len(self.mount_on_table) != 3:
            raise TargetError("mount_on_table: give (x_mm, y_mm, yaw_deg)")
        if not self.spacers_mm or any(h < 0 for h in self.spacers_mm):
            raise TargetError("spacers_mm: give one or more non-negative heights")
        if len(set(self.spacers_mm)) < self.needs_heights:
            raise TargetError(f"a {self.kind} target is flat: spacers_mm needs {self.needs_heights} different "
                              "heights for Tsai's non-coplanar method")
        if not self.fixed_positions_mm or any(len(p) != 2 for p in self.fixed_positions_mm):
            raise TargetError("fixed_positions_mm: give at least one (x, y) table position")
        if len(self.robot_position_mm) != 2:
            raise TargetError("robot_position_mm: give one (x, y) table position")
        reg = np.asarray(self.registration_positions_mm, float)
        if reg.ndim != 2 or reg.shape[1] != 2 or len(reg) < 3:
            raise TargetError("registration_positions_mm: table registration needs at least 3 (x, y) positions")
        if np.linalg.matrix_rank(reg - reg.mean(axis=0), tol=1e-6) < 2:
            raise TargetError("registration_positions_mm are collinear: X and Y would not both be observed")
        if self.robot_distance_mm <= 0 or self.robot_stations < 3:
            raise TargetError("robot_distance_mm must be positive and robot_stations at least 3")

    def _measured(self, solid: Solid) -> Solid:
        if self.dots_mm is None:
            return solid
        d = np.asarray(self.dots_mm, float)
        if d.shape != solid.dots.shape or not np.all(np.isfinite(d)):
            raise TargetError(f"dots_mm: expected {len(solid.dots)} finite (x, y, z) centres, got {d.shape}")
        return Solid(solid.vertices, solid.faces, d, solid.normals, solid.radii)

    @property
    def fiducial_indices(self) -> np.ndarray:
        """Indices of the fiducial dots in :meth:`dot_table` order."""
        table = self.dot_table()
        return np.array([table.index(tuple(f)) for f in self.fiducials])

    def dot_colours(self) -> list[tuple[int, ...]]:
        """BGR colour of every dot (fiducials coloured), in :meth:`solid`'s order."""
        fid = set(tuple(f) for f in self.fiducials)
        return [tuple(self.fiducial_colour_bgr) if d in fid else tuple(self.dot_colour_bgr) for d in self.dot_table()]

    @property
    def footprint_mm(self) -> tuple[float, float]:
        """(width, length) of the target's base (mm)."""
        return (self.width_mm, self.length_mm)


@dataclass(frozen=True)
class RoofTarget(Layout):
    """Dot target on two planes meeting at a ridge (a 3D target; see the module doc). mm."""

    kind = "roof"
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
    spacers_mm: tuple[float, ...] = (0.0,)

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

    @property
    def height_mm(self) -> float:
        """Height of the target above its base (mm): the ridge height."""
        return self.ridge_height_mm

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
        return self._measured(Solid(V, F, np.array(dots), np.array(normals), np.array(radii)))

    def check(self) -> None:
        """Raise TargetError (one line) if the roof layout is inconsistent or the dots do not fit."""
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
        self._check_layout()


@dataclass(frozen=True)
class PlaneTarget(Layout):
    """A flat, printable grid of dots on a plate of ``thickness_mm`` (see the module doc). mm.

    Dots at ``(col - (cols-1)/2)·pitch, (row - (rows-1)/2)·pitch`` on the plate's top face; the
    plate is ``cols·pitch + 2·margin`` by ``rows·pitch + 2·margin`` (the grid's outer dots
    ``pitch/2 + margin`` from the edge). Fiducials are (col, row) pairs, chosen so that no
    symmetry of the grid maps them onto themselves."""

    kind = "plane"
    cols: int = 9
    rows: int = 6
    pitch_mm: float = 22.0
    margin_mm: float = 8.0
    thickness_mm: float = 3.0
    dot_radius_mm: float = 5.0
    fiducials: tuple[tuple[int, int], ...] = ((0, 0), (3, 0), (0, 2), (8, 5), (6, 4))

    @property
    def width_mm(self) -> float:
        """Plate width (mm): the dot columns plus the margin on both sides."""
        return self.cols * self.pitch_mm + 2 * self.margin_mm

    @property
    def length_mm(self) -> float:
        """Plate length (mm): the dot rows plus the margin on both sides."""
        return self.rows * self.pitch_mm + 2 * self.margin_mm

    @property
    def height_mm(self) -> float:
        """Height of the dotted face above the base (mm): the plate thickness."""
        return self.thickness_mm

    @property
    def needs_heights(self) -> int:
        """Two distinct spacer heights: a flat plate needs them for Tsai's non-coplanar method."""
        return 2

    def dot_table(self) -> list[tuple[int, int]]:
        """(col, row) of every dot, in the order of :meth:`solid`'s dots."""
        return [(i, j) for j in range(self.rows) for i in range(self.cols)]

    def dot_centres_2d(self) -> np.ndarray:
        """(N, 2) dot centres on the plate's face (x, y in the target frame), nominal grid."""
        return np.array([[(i - (self.cols - 1) / 2.0) * self.pitch_mm, (j - (self.rows - 1) / 2.0) * self.pitch_mm]
                         for i, j in self.dot_table()])

    def solid(self) -> Solid:
        """The plate in its own frame t: box mesh and its dots on the top face (z = thickness, mm)."""
        V, F = _box(np.array([self.width_mm / 2.0, self.length_mm / 2.0]), 0.0, self.thickness_mm)
        xy = self.dot_centres_2d()
        dots = np.column_stack([xy, np.full(len(xy), self.thickness_mm)])
        n = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
        return self._measured(Solid(V, F, dots, n, np.full(len(xy), self.dot_radius_mm)))

    def check(self) -> None:
        """Raise TargetError (one line) if the plate layout is inconsistent or the dots overlap."""
        if min(self.cols, self.rows) < 3 or min(self.pitch_mm, self.dot_radius_mm, self.thickness_mm) <= 0:
            raise TargetError("a plane target needs at least 3×3 dots and positive sizes")
        if self.margin_mm < 0:
            raise TargetError("margin_mm must not be negative")
        if self.pitch_mm < 2.5 * self.dot_radius_mm:
            raise TargetError("dots overlap: pitch too small for the dot radius")
        fid = [tuple(f) for f in self.fiducials]
        if len(set(fid)) < 4 or not set(fid) <= set(self.dot_table()):
            raise TargetError("need at least 4 distinct fiducials, each naming an existing (col, row) dot")
        self._check_layout()


Target = RoofTarget | PlaneTarget
KINDS: dict[str, type[RoofTarget] | type[PlaneTarget]] = {"roof": RoofTarget, "plane": PlaneTarget}
_TUPLE_OF_TUPLES = ("fiducials", "fixed_positions_mm", "registration_positions_mm", "dots_mm")


def load_target(path: Path | str) -> Target:
    """Read ``calibration/target.yaml``; raise :class:`TargetError` with a one-line reason."""
    path = Path(path)
    if not path.is_file():
        raise TargetError(f"calibration target file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as exc:
        raise TargetError(f"{path}: not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict) or data.get("kind", "roof") not in KINDS:
        raise TargetError(f"{path}: expected a mapping with kind: plane or kind: roof")
    cls = KINDS[data.get("kind", "roof")]
    fields = cls.__dataclass_fields__
    unknown = sorted(set(data) - set(fields) - {"kind"})
    if unknown:
        raise TargetError(f"{path}: unknown key(s): {', '.join(unknown)}")
    kw = {}
    for k, v in data.items():
        if k == "kind":
            continue
        if k in _TUPLE_OF_TUPLES and v is not None:
            if not isinstance(v, list) or not all(isinstance(x, list) for x in v):
                raise TargetError(f"{path}: {k}: expected a list of lists")
            v = tuple(tuple(x) for x in v)
        elif isinstance(v, list):
            v = tuple(v)
        kw[k] = v
    try:
        target = cls(**kw)
        target.check()
        target.solid()
    except TargetError as exc:
        raise TargetError(f"{path}: {exc}") from None
    except (TypeError, ValueError) as exc:
        raise TargetError(f"{path}: {exc}") from None
    return target


def target_yaml(target: Target, *, with_dots: bool = False) -> str:
    """The YAML text of a target definition (the sample lab's ``calibration/target.yaml``)."""
    from dataclasses import asdict

    d: dict[str, Any] = {"kind": target.kind}
    for k, v in asdict(target).items():
        if k == "dots_mm" and v is None:
            if not with_dots:
                continue
            v = [[round(float(c), 6) for c in p] for p in target.solid().dots]
        elif k in _TUPLE_OF_TUPLES and v is not None:
            v = [list(x) for x in v]
        d[k] = list(v) if isinstance(v, tuple) else v
    what = "flat: seen at two or more spacer heights" if target.kind == "plane" else "3D"
    head = ("# Calibration target (labctl calibrate): dark dots on light faces, coloured fiducials.\n"
            f"# kind: {target.kind} ({what}).\n"
            "# Target frame: origin at the footprint centre on the table, z up. mount_on_table: its pose\n"
            "# on the carriage's locating pins at machine zero (x, y mm, yaw deg); spacers_mm: heights it\n"
            "# is raised to in turn (you are asked to insert each spacer); *_positions_mm: where GRBL moves\n"
            "# the table (machine mm) for the fixed camera, the robot's stations and table registration.\n"
            "# dots_mm (optional): dot centres in the target frame (mm); they replace the nominal grid.\n")
    return head + yaml.safe_dump(d, sort_keys=False, default_flow_style=None)


# --- printable targets ------------------------------------------------------------------------
def _printable(target: Target) -> PlaneTarget:
    if not isinstance(target, PlaneTarget):
        raise TargetError("only a plane target can be printed (a roof target is built, not printed)")
    return target


def _rgb_hex(bgr) -> str:
    b, g, r = (int(c) for c in bgr)
    return f"#{r:02x}{g:02x}{b:02x}"


def _page_dots(target: PlaneTarget):
    """(x, y) on the page (mm, origin top-left, y down), radius and colour of every dot."""
    w, h = target.width_mm, target.length_mm
    dots = target.solid().dots
    cols = target.dot_colours()
    return [(w / 2.0 + p[0], h / 2.0 - p[1], target.dot_radius_mm, c) for p, c in zip(dots, cols)]


def target_svg(target: Target) -> str:
    """SVG of the plane target at true scale (the page is the plate, in mm units): the printed
    target's dot centres are the geometry file's, the target frame's y axis points up the page."""
    t = _printable(target)
    w, h = t.width_mm, t.length_mm
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w:.3f}mm" height="{h:.3f}mm" '
           f'viewBox="0 0 {w:.3f} {h:.3f}">',
           f"<title>labctl calibration target {t.cols}x{t.rows}, pitch {t.pitch_mm:g} mm: print at 100 %</title>",
           f'<rect x="0" y="0" width="{w:.3f}" height="{h:.3f}" fill="{_rgb_hex(t.plate_colour_bgr)}"/>']
    for x, y, r, c in _page_dots(t):
        out.append(f'<circle cx="{x:.4f}" cy="{y:.4f}" r="{r:.4f}" fill="{_rgb_hex(c)}"/>')
    out.append("</svg>")
    return "\n".join(out) + "\n"


def target_pdf(target: Target) -> bytes:
    """PDF of the plane target at true scale (matplotlib, one page the size of the plate)."""
    import io

    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Rectangle

    t = _printable(target)
    w, h = t.width_mm, t.length_mm
    fig = Figure(figsize=(w / 25.4, h / 25.4))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0.0, w)
    ax.set_ylim(h, 0.0)  # page coordinates, y down, as the SVG
    ax.set_axis_off()
    ax.add_patch(Rectangle((0.0, 0.0), w, h, facecolor=_rgb_hex(t.plate_colour_bgr), edgecolor="none"))
    for x, y, r, c in _page_dots(t):
        ax.add_patch(Circle((x, y), r, facecolor=_rgb_hex(c), edgecolor="none"))
    buf = io.BytesIO()
    fig.savefig(buf, format="pdf")
    return buf.getvalue()
