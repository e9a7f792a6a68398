"""Random test parts for issue 15, built with trimesh's own primitives and extrusion (shapely +
mapbox_earcut triangulation) — independent of labctl's ear-clipping extruder.

* :func:`random_box` — 10–120 mm per side, or a 5 mm plate (one side 5 mm);
* :func:`random_extrusion` — a convex (hull of random points) or concave (star-shaped, L, T, U,
  notched) polygon, 25–120 mm across, extruded 5–80 mm.
"""

from __future__ import annotations

import numpy as np
import trimesh

shapely_geometry = __import__("pytest").importorskip("shapely.geometry")


def random_box(rng: np.random.Generator, plate: bool | None = None) -> trimesh.Trimesh:
    s = rng.uniform(10.0, 120.0, 3)
    if plate if plate is not None else rng.random() < 0.3:
        s[rng.integers(3)] = 5.0
    return trimesh.creation.box(s)


def _convex(rng):
    pts = rng.uniform(-1, 1, (int(rng.integers(5, 12)), 2))
    return shapely_geometry.MultiPoint(pts).convex_hull


def _star(rng):
    n = int(rng.integers(5, 10))
    a = np.sort(rng.uniform(0, 2 * np.pi, n))
    r = rng.uniform(0.45, 1.0, n)
    return shapely_geometry.Polygon(np.c_[r * np.cos(a), r * np.sin(a)])


def _letter(rng):
    t = rng.uniform(0.25, 0.45)
    kind = rng.choice(["L", "T", "U", "notch"])
    if kind == "L":
        p = [(0, 0), (1, 0), (1, t), (t, t), (t, 1), (0, 1)]
    elif kind == "T":
        c0, c1 = 0.5 - t / 2, 0.5 + t / 2
        p = [(c0, 0), (c1, 0), (c1, 1 - t), (1, 1 - t), (1, 1), (0, 1), (0, 1 - t), (c0, 1 - t)]
    elif kind == "U":
        p = [(0, 0), (1, 0), (1, 1), (1 - t, 1), (1 - t, t), (t, t), (t, 1), (0, 1)]
    else:
        w = rng.uniform(0.2, 0.5)
        p = [(0, 0), (1, 0), (1, 1), (0.5 + w / 2, 1), (0.5 + w / 2, 1 - t), (0.5 - w / 2, 1 - t), (0.5 - w / 2, 1),
             (0, 1)]
    return shapely_geometry.Polygon(p)


def random_extrusion(rng: np.random.Generator, concave: bool | None = None) -> trimesh.Trimesh:
    """A random extruded polygon within the lab's size range (largest extent ≤ 120 mm)."""
    concave = rng.random() < 0.5 if concave is None else concave
    poly = (_star(rng) if rng.random() < 0.5 else _letter(rng)) if concave else _convex(rng)
    poly = poly.buffer(0) if not poly.is_valid else poly
    minx, miny, maxx, maxy = poly.bounds
    span = max(maxx - minx, maxy - miny)
    size = rng.uniform(25.0, 120.0)
    from shapely import affinity

    poly = affinity.scale(poly, size / span, size * rng.uniform(0.5, 1.0) / span, origin=(0, 0))
    mesh = trimesh.creation.extrude_polygon(poly, float(rng.uniform(5.0, 80.0)))
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh
