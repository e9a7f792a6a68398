"""Object models: loading and validating CAD meshes (STL/OBJ, mm), stable resting poses, extrusion.

Paper §4.1 (offline marker planning): markers are planned from the object's CAD model. Models are
``trimesh.Trimesh`` in millimetres in the object frame O. Stable poses come from trimesh's
quasi-static computation (``trimesh.poses.compute_stable_poses``: the convex-hull facets the
centre of mass projects into, with the probability of landing on each estimated from the solid
angle of the hull facet region seen from the centre of mass).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import trimesh

from ..errors import UserInputError

# what the lab can hold: the paper's objects are 40×40×35 … 90×90×70 mm
MIN_EXTENT_MM = 5.0
MAX_EXTENT_MM = 130.0


class ModelError(UserInputError):
    """A CAD model that cannot be taught (not watertight, empty, wrong units, too small…)."""


def load_model(path: Path | str) -> trimesh.Trimesh:
    """Read an STL/OBJ file (mm) as one mesh; raise :class:`ModelError` if unreadable or empty."""
    import trimesh  # a heavy import (scipy, networkx): paid by teaching, not by a run
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"model file not found: {path}")
    if path.suffix.lower() not in (".stl", ".obj"):
        raise ModelError(f"unsupported model format {path.suffix!r}: use an STL or OBJ file in mm")
    if path.suffix.lower() == ".obj":  # OBJ is text; trimesh guesses other encodings with an optional package
        try:
            path.read_bytes().decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ModelError(f"cannot read model {path.name}: not a text OBJ file (byte {exc.start} is not "
                             f"UTF-8); export it again as OBJ or STL") from None
    try:
        loaded = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many kinds on broken files
        raise ModelError(f"cannot read model {path.name}: {exc}") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ModelError(f"model {path.name} is empty (no triangles)")
    return loaded


def validate_model(mesh: trimesh.Trimesh, *, marker_radius_mm: float, name: str = "model") -> trimesh.Trimesh:
    """Check a mesh can be taught; return it (O = the CAD file's frame, faces wound outward).

    Raises :class:`ModelError` when the mesh is empty, not watertight (no inside/outside, so no
    volume, centre of mass or silhouette), implausibly sized for the lab (a factor-1000 hint
    when it looks like metres or micrometres), or without a flat face that can hold one marker.
    """
    if mesh is None or len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise ModelError(f"{name}: the mesh is empty")
    if not np.all(np.isfinite(mesh.vertices)):
        raise ModelError(f"{name}: the mesh has non-finite vertices")
    if not mesh.is_watertight:
        raise ModelError(f"{name}: the mesh is not watertight (open edges); close it in the CAD tool")
    if mesh.volume <= 0:
        mesh = mesh.copy()
        mesh.invert()
    if not mesh.is_volume:
        raise ModelError(f"{name}: the mesh does not enclose a consistent volume (check face winding)")
    ext = float(np.max(mesh.extents))
    if ext > MAX_EXTENT_MM:
        hint = " — is it in metres×1000 or µm? models must be in mm" if ext > 20 * MAX_EXTENT_MM else ""
        raise ModelError(f"{name}: largest extent {ext:.4g} mm exceeds what the lab holds "
                         f"({MAX_EXTENT_MM:.0f} mm){hint}")
    if ext < MIN_EXTENT_MM:
        hint = " — is it in metres? models must be in mm" if ext < 1.0 else ""
        raise ModelError(f"{name}: largest extent {ext:.4g} mm is below {MIN_EXTENT_MM:.0f} mm{hint}")
    if sorted(mesh.extents)[1] < 2.0 * marker_radius_mm:
        raise ModelError(f"{name}: too small for a marker of radius {marker_radius_mm:g} mm "
                         f"(extents {np.round(mesh.extents, 1).tolist()} mm)")
    return mesh


def stable_poses(mesh: trimesh.Trimesh, *, min_probability: float = 0.0) -> list[tuple[np.ndarray, float]]:
    """Stable resting poses ``(T_w_o, probability)`` placing the object on the table plane z = 0.

    Quasi-static analysis (trimesh): each pose rests on a convex-hull facet whose region
    contains the projection of the centre of mass. Probabilities sum to 1 over the returned
    poses (renormalised after dropping those under ``min_probability``). Poses are sorted by
    probability, most likely first; translations put the lowest point at z = 0 and the centre
    of mass over the origin of x, y.
    """
    import trimesh  # a heavy import (scipy, networkx): paid by teaching, not by a run
    Ts, probs = trimesh.poses.compute_stable_poses(mesh, n_samples=1)
    out = []
    for T, p in zip(Ts, probs, strict=True):
        if p < min_probability:
            continue
        T = np.array(T, dtype=float)
        v = trimesh.transform_points(mesh.vertices, T)
        com = trimesh.transform_points(mesh.center_mass[None], T)[0]
        T[:3, 3] += [-com[0], -com[1], -v[:, 2].min()]
        out.append((T, float(p)))
    total = sum(p for _, p in out)
    if not out or total <= 0:
        raise ModelError("no stable resting pose found")
    out = [(T, p / total) for T, p in out]
    out.sort(key=lambda tp: -tp[1])
    return out


def _rested_points(mesh: trimesh.Trimesh, T: np.ndarray) -> np.ndarray:
    """The hull's vertices in resting pose ``T`` (the centre of mass over the origin, as stable_poses puts it)."""
    import trimesh  # a heavy import (scipy, networkx): paid by teaching, not by a run
    return trimesh.transform_points(mesh.convex_hull.vertices, T)


def _z_rotation(phi: float) -> np.ndarray:
    c, s = np.cos(phi), np.sin(phi)
    R = np.eye(4)
    R[:2, :2] = [[c, -s], [s, c]]
    return R


def same_pose_up_to_yaw(mesh: trimesh.Trimesh, T_a: np.ndarray, T_b: np.ndarray, tol_mm: float) -> np.ndarray | None:
    """The symmetry ``S`` of the mesh that makes resting pose ``T_b`` pose ``T_a`` turned about the vertical.

    Two resting poses look the same on the table (any yaw) exactly when the rested bodies differ by a
    rotation ``Rz(φ)`` about the vertical through the centre of mass: ``T_b·X = Rz(φ)·T_a·X`` as point
    sets, so ``S = T_b⁻¹·Rz(φ)·T_a`` maps the mesh onto itself. Tested on the convex hull's vertices
    (every vertex within ``tol_mm`` of one of the other pose's); candidate angles φ come from pairing
    the hull vertex farthest from the axis with the other pose's vertices at the same height and
    radius. Returns S (4×4, object frame), or None when the poses differ."""
    import trimesh  # a heavy import (scipy, networkx): paid by teaching, not by a run
    from scipy.spatial import cKDTree

    pa, pb = _rested_points(mesh, T_a), _rested_points(mesh, T_b)
    if len(pa) != len(pb):
        return None
    key = lambda p: np.column_stack([p[:, 2], np.hypot(p[:, 0], p[:, 1])])  # noqa: E731 - (height, radius)
    ka, kb = key(pa), key(pb)
    if not np.allclose(np.sort(ka[:, 0]), np.sort(kb[:, 0]), atol=tol_mm) or \
            not np.allclose(np.sort(ka[:, 1]), np.sort(kb[:, 1]), atol=tol_mm):
        return None
    tree = cKDTree(pb)
    i = int(np.argmax(ka[:, 1] - 1e-6 * ka[:, 0]))
    if ka[i, 1] < tol_mm:  # every vertex on the axis: a degenerate body
        return None
    partners = np.flatnonzero(np.all(np.abs(kb - ka[i]) <= tol_mm, axis=1))
    for j in partners:
        phi = np.arctan2(pb[j, 1], pb[j, 0]) - np.arctan2(pa[i, 1], pa[i, 0])
        Rz = _z_rotation(float(phi))
        d, _ = tree.query(trimesh.transform_points(pa, Rz))
        if np.max(d) <= tol_mm:
            return np.linalg.inv(T_b) @ Rz @ T_a
    return None


def merge_symmetric_poses(mesh: trimesh.Trimesh, poses: list[tuple[np.ndarray, float]], *,
                          tol_mm: float) -> list[list[tuple[np.ndarray, float, np.ndarray]]]:
    """Group resting poses that are the same up to the part's symmetry (:func:`same_pose_up_to_yaw`).

    Returns the classes in the order of their first (most likely) member; each class is a list of
    ``(T_w_o, probability, S)`` with S the symmetry that takes the class's first pose to that member
    (identity for the first). A 96-facet cylinder's 96 side poses are one class, its two end caps another."""
    classes: list[list[tuple[np.ndarray, float, np.ndarray]]] = []
    for T, p in poses:
        for cls in classes:
            S = same_pose_up_to_yaw(mesh, cls[0][0], T, tol_mm)
            if S is not None:
                cls.append((T, p, S))
                break
        else:
            classes.append([(T, p, np.eye(4))])
    return classes


# --- building models (sample objects, tests) ------------------------------------------
def triangulate_polygon(poly: np.ndarray) -> np.ndarray:
    """Ear-clipping triangulation of a simple polygon (n, 2); returns (n−2, 3) vertex indices, CCW."""
    p = np.asarray(poly, dtype=float)
    n = len(p)
    area = 0.5 * (np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(np.roll(p[:, 0], -1), p[:, 1]))
    idx = list(range(n)) if area > 0 else list(range(n))[::-1]

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    tris: list[tuple[int, ...]] = []
    guard = 0
    while len(idx) > 3 and guard < 10 * n * n:
        guard += 1
        m = len(idx)
        for j in range(m):
            i0, i1, i2 = idx[j - 1], idx[j], idx[(j + 1) % m]
            a, b, c = p[i0], p[i1], p[i2]
            if cross(a, b, c) <= 1e-12:
                continue  # reflex or degenerate vertex
            inside = False
            for k in idx:
                if k in (i0, i1, i2):
                    continue
                q = p[k]
                if cross(a, b, q) >= 0 and cross(b, c, q) >= 0 and cross(c, a, q) >= 0:
                    inside = True
                    break
            if not inside:
                tris.append((i0, i1, i2))
                idx.pop(j)
                break
        else:
            raise ValueError("polygon is not simple: ear clipping failed")
    tris.append(tuple(idx))
    return np.array(tris, dtype=np.int64)


def extrude_polygon(poly_xy: np.ndarray, height: float) -> trimesh.Trimesh:
    """Watertight prism: a simple polygon (n, 2) in mm extruded along +z by ``height`` mm.

    Hand-built (no triangulation engine needed): ear-clipped caps plus two triangles per side.
    """
    import trimesh  # a heavy import (scipy, networkx): paid by teaching, not by a run
    p = np.asarray(poly_xy, dtype=float)
    area = 0.5 * (np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(np.roll(p[:, 0], -1), p[:, 1]))
    if area < 0:
        p = p[::-1]
    n = len(p)
    cap = triangulate_polygon(p)
    verts = np.vstack([np.column_stack([p, np.zeros(n)]), np.column_stack([p, np.full(n, float(height))])])
    faces = [cap[:, ::-1], cap + n]  # bottom faces down, top faces up
    i = np.arange(n)
    j = (i + 1) % n
    faces.append(np.column_stack([i, j, j + n]))
    faces.append(np.column_stack([i, j + n, i + n]))
    mesh = trimesh.Trimesh(verts, np.vstack(faces), process=True)
    if not mesh.is_watertight or mesh.volume <= 0:
        raise ValueError("extrusion failed to produce a closed solid")
    return mesh

