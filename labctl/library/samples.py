"""The sample lab's seven objects and a generator of random machined parts (for benchmarks and tests).

Paper §5.3: seven objects from 40×40×35 mm (object 2) to 90×90×70 mm (object 5). Ours are
prismatic machined parts spanning that size range: a block, two L profiles that share their end
view (so the extra-view path is exercised), a T profile, a hexagonal prism, a stepped block
and a trapezoidal wedge. Meshes are built by hand (ear-clipped extrusions), no triangulation
engine needed.

``python -m labctl.library.samples [DIR]`` writes the seven STL files (default: the package's
``sample_models/`` folder).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

from ..geometry import rot_x
from .model import extrude_polygon

SAMPLE_MODELS_DIR = Path(__file__).with_name("sample_models")


def _profile(poly, height, *, lay_flat: bool = False) -> trimesh.Trimesh:
    """Extrude a profile along z; ``lay_flat`` turns it so the extrusion runs along y."""
    m = extrude_polygon(np.asarray(poly, float), height)
    if lay_flat:
        T = np.eye(4)
        T[:3, :3] = rot_x(np.pi / 2)
        m.apply_transform(T)
    m.apply_translation(-m.bounds.mean(axis=0))
    return m


def l_profile(w: float, h: float, t: float, length: float) -> list:
    """Outline (mm) of an L-section ``w`` wide and ``h`` high with legs ``t`` thick (``length`` unused)."""
    return [(0, 0), (w, 0), (w, t), (t, t), (t, h), (0, h)]


def t_profile(w: float, h: float, bar: float, stem: float) -> list:
    """Outline (mm) of a T-section ``w``×``h`` with a top bar ``bar`` high and a stem ``stem`` wide."""
    x0 = (w - stem) / 2
    return [(x0, 0), (x0 + stem, 0), (x0 + stem, h - bar), (w, h - bar), (w, h), (0, h), (0, h - bar), (x0, h - bar)]


def regular_polygon(n: int, across_flats: float) -> list:
    """Vertices (mm) of a regular ``n``-gon ``across_flats`` wide, centred on the origin."""
    r = across_flats / 2 / np.cos(np.pi / n)
    a = np.pi / n + np.arange(n) * 2 * np.pi / n
    return list(zip(r * np.cos(a), r * np.sin(a), strict=True))


def stepped(length: float, heights: list[float]) -> list:
    """Outline (mm) of a staircase ``length`` long with equal-width steps of the given ``heights``."""
    w = length / len(heights)
    pts = [(0.0, 0.0), (length, 0.0)]
    for i in range(len(heights) - 1, -1, -1):
        pts += [((i + 1) * w, heights[i]), (i * w, heights[i])]
    return pts


def trapezoid(bottom: float, top: float, h: float) -> list:
    """Outline (mm) of a trapezoid with parallel sides ``bottom`` and ``top``, ``h`` high."""
    d = (bottom - top) / 2
    return [(0, 0), (bottom, 0), (bottom - d, h), (d, h)]


def sample_objects() -> dict[str, trimesh.Trimesh]:
    """The seven sample objects (mm, centred on their bounding box), 40×40×35 to 90×90×70 mm.

    ``block`` is the paper's smallest size (object 2, 40×40×35), ``stepped_block`` its largest
    (object 5, 90×90×70); ``angle_short`` and ``angle_long`` share their L-shaped end view.
    """
    return {
        "block": trimesh.creation.box((40.0, 40.0, 35.0)),
        "angle_short": _profile(l_profile(60, 50, 25, 0), 45, lay_flat=True),
        "angle_long": _profile(l_profile(60, 50, 25, 0), 65, lay_flat=True),
        "tee": _profile(t_profile(75, 60, 25, 30), 45, lay_flat=True),
        "hex_nut": _profile(regular_polygon(6, 66), 40),
        "stepped_block": _profile(stepped(90, [70, 40]), 90, lay_flat=True),
        "wedge": _profile(trapezoid(85, 45, 45), 55, lay_flat=True),
    }


def random_object(rng: np.random.Generator) -> trimesh.Trimesh:
    """A random prismatic part within the lab's size range (L, T, U, cross, polygon, step, trapezoid, box)."""
    kind = rng.choice(["box", "L", "T", "U", "cross", "ngon", "step", "trap"])
    u = lambda lo, hi: float(rng.uniform(lo, hi))  # noqa: E731
    length = u(30, 70)
    if kind == "box":
        return trimesh.creation.box((u(30, 70), u(30, 70), u(25, 60)))
    if kind == "L":
        w, h = u(50, 70), u(50, 70)
        poly = l_profile(w, h, u(22, min(w, h) - 22), 0)
    elif kind == "T":
        w, h = u(60, 75), u(50, 70)
        poly = t_profile(w, h, u(22, 28), u(22, w - 30))
    elif kind == "U":
        w, h = u(70, 78), u(50, 65)
        t = u(22, 26)
        poly = [(0, 0), (w, 0), (w, h), (w - t, h), (w - t, t), (t, t), (t, h), (0, h)]
    elif kind == "cross":
        a, t = u(68, 78), u(22, 28)
        c0, c1 = (a - t) / 2, (a + t) / 2
        poly = [(c0, 0), (c1, 0), (c1, c0), (a, c0), (a, c1), (c1, c1), (c1, a), (c0, a), (c0, c1), (0, c1),
                (0, c0), (c0, c0)]
    elif kind == "ngon":
        poly = regular_polygon(int(rng.integers(3, 9)), u(45, 65))
    elif kind == "step":
        n = int(rng.integers(2, 4))
        poly = stepped(u(28 * n, 84), sorted([u(24, 60) for _ in range(n)], reverse=True))
    else:
        b = u(60, 78)
        poly = trapezoid(b, u(25, b - 20), u(30, 50))
    return _profile(poly, length, lay_flat=bool(rng.integers(0, 2)))


def write_sample_models(folder: Path | str = SAMPLE_MODELS_DIR) -> list[Path]:
    """Export each of :func:`sample_objects` as ``folder/NAME.stl`` (mm); returns the paths written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for name, mesh in sample_objects().items():
        p = folder / f"{name}.stl"
        mesh.export(p)
        out.append(p)
    return out


if __name__ == "__main__":  # pragma: no cover - a generator script
    for p in write_sample_models(sys.argv[1] if len(sys.argv) > 1 else SAMPLE_MODELS_DIR):
        print(p)


PART_KINDS = ("box", "plate", "concave", "stepped", "holed")


def random_part(rng: np.random.Generator, kind: str | None = None) -> trimesh.Trimesh:
    """A random machined part for the scale benchmark, 5–120 mm, centred on its bounding box.

    ``box`` 15–110 mm per side; ``plate`` 5–9 mm thick, 30–110 mm across; ``concave`` an extruded L, T,
    U or cross profile (:func:`random_object`'s shapes); ``stepped`` a block with 2–3 steps; ``holed``
    a rectangular or round-cornered block with a through hole (trimesh's extrusion of a polygon with a
    hole, via shapely + mapbox_earcut)."""
    kind = kind or str(rng.choice(PART_KINDS))
    u = lambda lo, hi: float(rng.uniform(lo, hi))  # noqa: E731
    if kind == "box":
        return trimesh.creation.box((u(15, 110), u(15, 110), u(15, 110)))
    if kind == "plate":
        return trimesh.creation.box((u(30, 110), u(30, 110), u(5, 9)))
    if kind == "concave":
        while True:
            m = random_object(rng)
            if not m.is_convex:
                return m
    if kind == "stepped":
        n = int(rng.integers(2, 4))
        return _profile(stepped(u(30 * n, 100), sorted([u(15, 70) for _ in range(n)], reverse=True)), u(25, 90),
                        lay_flat=bool(rng.integers(0, 2)))
    if kind == "holed":
        from shapely.geometry import Point, Polygon

        w, d = u(40, 100), u(40, 100)
        wall = u(12, 20)
        outer = Polygon([(0, 0), (w, 0), (w, d), (0, d)])
        if rng.random() < 0.5:
            hole = Point(w / 2, d / 2).buffer(min(w, d) / 2 - wall, resolution=8)
        else:
            hole = Polygon([(wall, wall), (w - wall, wall), (w - wall, d - wall), (wall, d - wall)])
        m = trimesh.creation.extrude_polygon(outer.difference(hole), u(10, 60))
        m.apply_translation(-m.bounds.mean(axis=0))
        return m
    raise ValueError(f"unknown part kind {kind!r} ({', '.join(PART_KINDS)})")
