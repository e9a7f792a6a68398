"""Marker placement: the minimum set of markers so that one is always visible (paper §4.1).

He, Benhabib & Smith, "CAD-based off-line planning for active vision", J. Robotic Systems 12,
1995 (paper ref. [12]): find the minimum number and locations of markers such that, for a
randomly posed object, at least one marker is visible to a single camera; and the optimal
initial viewing angle (63° in the paper).

Formulation used here:

* **Candidate sites** — one per planar face region (``trimesh`` facets and lone triangles) that
  can hold a marker disc of radius ``r`` with a margin: of the face points at least ``margin·r``
  inside the face (distance transform of the face rasterised at ``grid_mm``), the one nearest
  the projection of the object's centre, so the standard view is centred on the object.
* **Poses** — every stable resting pose (quasi-static, :func:`labctl.library.model.stable_poses`)
  × yaw ψ about the vertical sampled every ``360/n_yaw`` degrees.
* **Visibility** of a site in pose (T, ψ): the camera sits at distance ``D`` from the object's
  centre at elevation ``α`` (the viewing angle, from the table plane); the site is visible if
  the angle between its normal and the direction to the camera (obliquity) is at most
  ``max_obliquity`` and the segments from the marker's centre and four rim points to the
  camera cross no triangle of the mesh (Möller–Trumbore ray casting, numpy, own
  implementation — no ray engine needed).
* **Set cover** — rows = (pose, yaw) samples, columns = sites; choose the fewest columns
  covering every row. Exact 0/1 ILP with ``scipy.optimize.milp`` up to ``exact_max_sites``
  sites (ties broken towards more redundant coverage); greedy beyond, whose count is within
  ``H(m) ≤ ln m + 1`` of the optimum (m = the largest number of rows one site covers).
* **Overhead tracking** (paper §5.2) — the fixed camera C1 looks straight down from
  ``overhead_distance_mm`` (1.8 m) and tracks one marker's centroid through a red filter while
  the object crosses its field, so it sees the object up to ``overhead_cone_deg`` off vertical
  in any direction (the field's half-diagonal over the height, ≈ 11° in the sample lab).
  Requirement (b): for every stable pose, some single marker has its normal within
  ``overhead_max_tilt_deg`` = 60° of the vertical (so its image through the red filter is a
  usable blob: foreshortened at most to cos 70° ≈ 0.34 at the cone's rim) and is unoccluded and
  front-facing from every sampled direction of that cone (same ray casting) — one row per
  stable pose; site s covers it iff so. Yaw needs no sampling: the cone is symmetric about the
  vertical and the tilt does not depend on yaw.
* **Set cover** rows are the initial-view rows (a) followed by the overhead rows (b); one
  cover satisfies both.
* **Viewing angle** — the cover size as a function of α over a range; the optimal angles are
  those with the smallest count; the reported one has the largest worst-case number of
  visible chosen markers and, among those, is the steepest (top faces seen most frontally).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Protocol, cast

import cv2
import numpy as np

if TYPE_CHECKING:  # only annotations here: a run that loads a taught library never imports trimesh for it
    import trimesh

from ..geometry import rot_z
from .model import ModelError


@dataclass(frozen=True)
class Marker:
    """A circular marker in the object frame O: centre (mm), outward unit normal, radius (mm)."""

    id: int
    center: np.ndarray
    normal: np.ndarray
    radius: float

    def to_dict(self) -> dict:
        """JSON-ready dict: id, centre (mm, frame O), unit normal, radius (mm)."""
        return {"id": int(self.id), "center": [round(float(v), 4) for v in self.center],
                "normal": [round(float(v), 6) for v in self.normal], "radius": float(self.radius)}

    @classmethod
    def from_dict(cls, d: dict) -> Marker:
        """Marker from :meth:`to_dict` output; ValueError on a bad centre, normal or radius."""
        c = np.asarray(d["center"], dtype=float).reshape(3)
        n = np.asarray(d["normal"], dtype=float).reshape(3)
        if not np.all(np.isfinite(c)) or not np.isfinite(n).all() or abs(np.linalg.norm(n) - 1) > 1e-3:
            raise ValueError(f"marker {d.get('id')}: bad centre or normal")
        if not float(d["radius"]) > 0:
            raise ValueError(f"marker {d.get('id')}: radius must be positive")
        return cls(int(d["id"]), c, n / np.linalg.norm(n), float(d["radius"]))


@dataclass(frozen=True)
class ViewingGeometry:
    """Initial-view geometry (paper §5.3: ~1 m, 63°), the overhead fixed camera (§5.2: 1.8 m,
    straight down, up to ``overhead_cone_deg`` off vertical over its field) and the visibility
    limits. ``overhead_distance_mm=None`` drops the overhead requirement."""

    angle_deg: float = 63.0
    distance_mm: float = 1000.0
    max_obliquity_deg: float = 75.0
    n_yaw: int = 360
    overhead_distance_mm: float | None = 1800.0
    overhead_cone_deg: float = 10.0
    overhead_max_tilt_deg: float = 60.0
    # marker sizes a face may get, largest first (None: only the radius passed to the planner)
    radii_mm: tuple[float, ...] | None = None
    # the fixed camera's scale (px per mm at the table) and the red-blob area it needs to track a marker
    # at the rim of its cone; None: no size limit (only the tilt limit)
    overhead_px_per_mm: float | None = None
    overhead_min_area_px: float = 24.0


@dataclass
class PlacementResult:
    """Chosen marker set of the placement problem (paper §4.1) and how well it covers the sampled poses.

    ``markers``: chosen sites; ``candidates``: all sites; ``method``/``bound``: solver and its approximation
    bound; ``n_rows``: sampled (stable pose, yaw) rows; ``min_visible``: worst-case count of visible
    chosen markers; ``coverage``/``overhead_coverage``: visibility tables (see the field comments).
    """

    markers: list[Marker]
    candidates: list[Marker]
    method: str  # "exact" (milp) or "greedy"
    bound: float  # greedy approximation factor bound (1.0 when exact)
    n_rows: int
    min_visible: int  # worst case over the sampled (pose, yaw) of visible chosen markers
    coverage: np.ndarray = field(repr=False)  # (rows, chosen) bool, initial-view rows
    # (poses, chosen) bool: chosen marker visible to the overhead camera over the whole cone; None if not required
    overhead_coverage: np.ndarray | None = field(default=None, repr=False)
    # stable poses in which no face at all can carry a marker the overhead camera tracks (best effort:
    # there the fixed camera follows the red pixels of markers seen edge-on)
    untracked_poses: list[int] = field(default_factory=list)
    # initial-view rows (pose·n_yaw + yaw) that no candidate site can serve (coverage below 1)
    uncovered_rows: np.ndarray = field(default_factory=lambda: np.zeros(0, int), repr=False)

    @property
    def min_overhead_visible(self) -> int | None:
        """Worst case over the trackable stable poses of chosen markers the overhead camera sees over its cone."""
        if self.overhead_coverage is None:
            return None
        keep = np.setdiff1d(np.arange(len(self.overhead_coverage)), self.untracked_poses)
        return int(self.overhead_coverage[keep].sum(axis=1).min()) if keep.size else 0


# --- ray casting ------------------------------------------------------------------------
def segments_blocked(origins: np.ndarray, targets: np.ndarray, triangles: np.ndarray,
                     eps: float = 1e-9, chunk: int = 4096) -> np.ndarray:
    """For each segment origin→target (mm), does it cross any triangle (F, 3, 3)? Möller–Trumbore."""
    o = np.asarray(origins, dtype=float)
    d = np.asarray(targets, dtype=float) - o
    v0, v1, v2 = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    e1, e2 = v1 - v0, v2 - v0
    out = np.zeros(len(o), dtype=bool)
    for s in range(0, len(o), chunk):
        oo, dd = o[s:s + chunk, None, :], d[s:s + chunk, None, :]
        p = np.cross(dd, e2[None])
        det = np.sum(e1[None] * p, axis=-1)
        ok = np.abs(det) > eps
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = oo - v0[None]
        u = np.sum(tv * p, axis=-1) * inv
        q = np.cross(tv, e1[None])
        v = np.sum(dd * q, axis=-1) * inv
        t = np.sum(e2[None] * q, axis=-1) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6) & (t < 1.0)
        out[s:s + chunk] = hit.any(axis=1)
    return out


# --- candidate sites --------------------------------------------------------------------
def _plane_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def marker_radii(radius_mm: float, min_radius_mm: float, ratio: float = 0.8) -> tuple[float, ...]:
    """The marker sizes (mm) a face may get, largest first: the lab's ``radius_mm`` times ``ratio^k``
    down to ``min_radius_mm`` (the smallest the mobile camera resolves at the initial viewing distance).

    Discrete sizes a factor ``1/ratio`` apart, so the run can tell which size it sees from the
    marker's height above the table (an ellipse fixes a circle's distance only up to its radius)."""
    if not 0 < ratio < 1:
        raise ValueError("ratio must be in (0, 1)")
    out = [float(radius_mm)]
    while out[-1] * ratio >= min_radius_mm - 1e-9:
        out.append(round(out[-1] * ratio, 3))
    return tuple(out)


def min_marker_radius(fx_px: float, distance_mm: float, min_diameter_px: float) -> float:
    """Smallest marker radius (mm) whose face-on image at ``distance_mm`` is ``min_diameter_px`` across
    (pinhole: diameter_px = 2·r·fx/Z)."""
    return float(min_diameter_px * distance_mm / (2.0 * fx_px))


def candidate_sites(mesh: trimesh.Trimesh, radius_mm: float, *, margin: float = 1.3,
                    grid_mm: float = 0.25, radii_mm: tuple[float, ...] | None = None) -> list[Marker]:
    """Marker sites: one per planar face region (paper §4.1).

    Each face gets the largest radius of ``radii_mm`` (default: only ``radius_mm``) whose disc of
    ``margin·r`` fits inside it (distance transform of the face rasterised at ``grid_mm``); the
    site is the point that deep inside the face nearest the object's bounding-box centre
    (projected on the face), so standard views are centred but a marker may sit off-centre where
    the face's middle is cut away. Faces too small for the smallest radius get no site. Ids in
    order of decreasing face area."""
    radii = sorted(radii_mm if radii_mm else (radius_mm,), reverse=True)
    groups = [np.asarray(f) for f in mesh.facets]
    in_facet = np.zeros(len(mesh.faces), bool)
    for g in groups:
        in_facet[g] = True
    groups += [np.array([i]) for i in np.flatnonzero(~in_facet)]
    sites = []
    centre = mesh.bounds.mean(axis=0)
    for g in groups:
        n = mesh.face_normals[g].mean(axis=0)
        n /= np.linalg.norm(n)
        tri = mesh.triangles[g]  # (k, 3, 3)
        u, v = _plane_basis(n)
        uv = np.stack([tri @ u, tri @ v], axis=-1)  # (k, 3, 2)
        lo = uv.reshape(-1, 2).min(axis=0) - 2 * grid_mm
        hi = uv.reshape(-1, 2).max(axis=0) + 2 * grid_mm
        if np.min(hi - lo) < 2 * margin * radii[-1]:
            continue
        shape = np.ceil((hi - lo) / grid_mm).astype(int) + 1
        img = np.zeros((shape[1], shape[0]), np.uint8)
        pix = np.round((uv - lo) / grid_mm * 16).astype(np.int32)  # 4 fractional bits
        cv2.fillPoly(img, list(pix), 1, lineType=cv2.LINE_8, shift=4)
        dist = cv2.distanceTransform(img, cv2.DIST_L2, 5) * grid_mm
        fits = [r for r in radii if dist.max() >= margin * r]
        if not fits:
            continue
        r = fits[0]
        deep_r, deep_c = np.nonzero(dist >= margin * r)
        # of the points deep enough, the one nearest the object's centre: centred standard views
        aim = (np.array([centre @ u, centre @ v]) - lo) / grid_mm
        k = int(np.argmin((deep_c - aim[0]) ** 2 + (deep_r - aim[1]) ** 2))
        p2 = lo + np.array([deep_c[k], deep_r[k]]) * grid_mm
        plane_d = float(np.mean(tri.reshape(-1, 3) @ n))
        center = p2[0] * u + p2[1] * v + plane_d * n
        sites.append((float(mesh.area_faces[g].sum()), center, n, r))
    sites.sort(key=lambda s: -s[0])
    return [Marker(i, c, nn, float(r)) for i, (_, c, nn, r) in enumerate(sites)]


# --- visibility -------------------------------------------------------------------------
def _rim_points(m: Marker, k: int = 4) -> np.ndarray:
    u, v = _plane_basis(m.normal)
    a = np.arange(k) * 2 * np.pi / k
    return m.center + 0.9 * m.radius * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * v)


def view_directions_o(poses: list[np.ndarray], angle_deg: float, n_yaw: int, yaw_offset: float = 0.0) -> np.ndarray:
    """Unit directions (P·n_yaw, 3) from the object towards the camera, in the object frame O.

    World camera direction ``(cos α, 0, sin α)`` (α = viewing angle from the table plane); the
    object rests in pose ``T`` rotated by yaw ψ about the vertical, so ``d_O = (Rz(ψ)·R_T)ᵀ d``.
    Row ``p·n_yaw + j`` is pose p at yaw ``(j + yaw_offset)·360°/n_yaw``.
    """
    a = np.radians(angle_deg)
    d = np.array([np.cos(a), 0.0, np.sin(a)])
    out = []
    for T in poses:
        for j in range(n_yaw):
            R = rot_z(2 * np.pi * (j + yaw_offset) / n_yaw) @ T[:3, :3]
            out.append(R.T @ d)
    return np.array(out)


def overhead_directions_o(poses: list[np.ndarray], cone_deg: float, n_azimuth: int = 24,
                          n_rings: int = 2, azimuth_offset: float = 0.0) -> np.ndarray:
    """Unit directions (P, K, 3) from the object towards the overhead camera, in the object frame O.

    World directions ``(sin β cos φ, sin β sin φ, cos β)``: the vertical (β = 0) and ``n_rings``
    rings β = cone·i/n_rings (i = 1…n_rings) of ``n_azimuth`` azimuths φ = (j + azimuth_offset)·360°/n_azimuth
    — the off-vertical views of a camera looking straight down at an object anywhere in its
    field (paper §5.2). ``d_O = R_Tᵀ d`` for the stable pose T (yaw is absorbed by φ).
    """
    dirs = [np.array([0.0, 0.0, 1.0])]
    phi = 2 * np.pi * (np.arange(n_azimuth) + azimuth_offset) / n_azimuth
    for i in range(1, n_rings + 1):
        b = np.radians(cone_deg) * i / n_rings
        dirs += list(np.stack([np.sin(b) * np.cos(phi), np.sin(b) * np.sin(phi), np.full_like(phi, np.cos(b))], 1))
    d = np.array(dirs)
    return np.stack([d @ T[:3, :3] for T in poses])  # row-vector form of R_Tᵀ d


def visibility_matrix(mesh: trimesh.Trimesh, sites: list[Marker], dirs_o: np.ndarray, *,
                      distance_mm: float, max_obliquity_deg: float) -> np.ndarray:
    """Bool (rows, sites): is site s visible from camera direction row r (see module docstring)."""
    cam = mesh.bounds.mean(axis=0) + dirs_o * distance_mm  # camera aimed at the bounding-box centre
    tris = np.asarray(mesh.triangles)
    cos_max = np.cos(np.radians(max_obliquity_deg))
    vis = np.zeros((len(dirs_o), len(sites)), bool)
    for s, m in enumerate(sites):
        to_cam = cam - m.center
        to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
        ok = to_cam @ m.normal >= cos_max
        rows = np.flatnonzero(ok)
        if rows.size == 0:
            continue
        pts = np.vstack([m.center[None], _rim_points(m)]) + 1e-3 * m.normal  # lift off the face
        origins = np.repeat(pts[None], rows.size, axis=0).reshape(-1, 3)
        targets = np.repeat(cam[rows], len(pts), axis=0)
        blocked = segments_blocked(origins, targets, tris).reshape(rows.size, len(pts)).any(axis=1)
        vis[rows[~blocked], s] = True
    return vis


# --- set cover --------------------------------------------------------------------------
def set_cover(cover: np.ndarray, *, exact_max_sites: int = 60) -> tuple[np.ndarray, str, float]:
    """Fewest columns of ``cover`` (rows × cols bool) such that every row has one True.

    Exact (``scipy.optimize.milp``) when cols ≤ ``exact_max_sites``: minimise Σx − ε·Σ(rows
    covered)·x, so among minimum covers the most redundant one is chosen. Otherwise greedy
    (Chvátal), whose size is at most H(max column count) times the optimum. Returns
    (chosen column indices, "exact"|"greedy", bound factor).
    """
    A = np.unique(np.asarray(cover, bool), axis=0)
    if A.shape[0] == 0:
        return np.array([], int), "exact", 1.0
    if not A.any(axis=1).all():
        raise ValueError("some row cannot be covered")
    ncol = A.shape[1]
    if ncol <= exact_max_sites:
        from scipy.optimize import Bounds, LinearConstraint, milp

        counts = np.asarray(cover, bool).sum(axis=0).astype(float)
        eps = 0.5 / (ncol * (counts.max() + 1.0))
        c = 1.0 - eps * counts
        res = milp(c, constraints=LinearConstraint(A.astype(float), lb=1.0, ub=np.inf),
                   integrality=np.ones(ncol), bounds=Bounds(0, 1))
        if res.status == 0 and res.x is not None:
            return np.flatnonzero(res.x > 0.5), "exact", 1.0
    left = np.ones(A.shape[0], bool)
    chosen = []
    while left.any():
        gain = A[left].sum(axis=0)
        j = int(np.argmax(gain))
        chosen.append(j)
        left &= ~A[:, j]
    m = int(A.sum(axis=0).max())
    return np.array(sorted(chosen)), "greedy", float(np.sum(1.0 / np.arange(1, m + 1)))


def overhead_visibility(mesh: trimesh.Trimesh, sites: list[Marker], poses: list[np.ndarray], view: ViewingGeometry,
                        *, n_azimuth: int = 24, n_rings: int = 2, azimuth_offset: float = 0.0) -> np.ndarray:
    """Bool (P, sites): in stable pose p, site s can be tracked by the overhead camera (paper §5.2):
    its normal is within ``overhead_max_tilt_deg`` of the vertical and it is front-facing and
    unoccluded from EVERY sampled direction of the ``overhead_cone_deg`` cone (camera at
    ``overhead_distance_mm`` from the object's centre) — one marker the fixed camera can follow
    while the object crosses its field."""
    dirs = overhead_directions_o(poses, view.overhead_cone_deg, n_azimuth, n_rings, azimuth_offset)
    P, K = dirs.shape[:2]
    if view.overhead_distance_mm is None:
        raise TypeError("overhead visibility needs view.overhead_distance_mm")
    # the obliquity to any cone direction is at most tilt + cone: the tilt test below is the binding one
    seen = visibility_matrix(mesh, sites, dirs.reshape(-1, 3), distance_mm=float(view.overhead_distance_mm),
                             max_obliquity_deg=min(89.0, view.overhead_max_tilt_deg + view.overhead_cone_deg + 1.0))
    normals = np.array([m.normal for m in sites]).reshape(-1, 3)
    up_z = np.stack([T[2, :3] for T in poses]) @ normals.T  # (P, sites): z of the normal in W
    # 0.01° slack: a triangular prism lying on a side shows its upper faces at exactly 60°
    tilt_ok = up_z >= np.cos(np.radians(overhead_tilt_limits_deg(sites, view) + 0.01))[None, :]
    return seen.reshape(P, K, len(sites)).all(axis=1) & tilt_ok


def overhead_tilt_limits_deg(sites: list[Marker], view: ViewingGeometry) -> np.ndarray:
    """Per site, the largest tilt (deg) of its normal from the vertical at which the overhead camera
    still tracks it: ``overhead_max_tilt_deg``, lowered for small markers so that the red blob's area
    at the cone's rim, ``π (r·s)² cos(tilt + cone)`` (s = px/mm), stays ≥ ``overhead_min_area_px``;
    −inf (never trackable) when even a face-on marker is smaller than that."""
    lim = np.full(len(sites), float(view.overhead_max_tilt_deg))
    if view.overhead_px_per_mm is None:
        return lim
    for i, m in enumerate(sites):
        need = view.overhead_min_area_px / (np.pi * (m.radius * view.overhead_px_per_mm) ** 2)
        lim[i] = min(lim[i], np.degrees(np.arccos(need)) - view.overhead_cone_deg) if need <= 1 else -np.inf
    return lim


def plan_markers(mesh: trimesh.Trimesh, poses: list[tuple[np.ndarray, float]], radius_mm: float,
                 view: ViewingGeometry, *, planning_margin_deg: float = 2.0,
                 candidates: list[Marker] | None = None) -> PlacementResult:
    """Minimum marker set for ``mesh`` (paper §4.1) meeting (a) the initial-view requirement and,
    unless ``view.overhead_distance_mm`` is None, (b) the overhead-tracking requirement (module
    docstring), wherever some candidate site can meet them. Rows no site can serve (a pose and yaw
    from which every face that holds a marker is hidden or too oblique; a pose no face can serve
    overhead) are left out and reported (``uncovered_rows``, ``untracked_poses``): the model is
    taught anyway and :func:`coverage_report` gives the share of placements covered. Raises
    :class:`ModelError` only when no face can hold even the smallest marker or none is ever visible.

    Planning (a) uses an obliquity limit ``planning_margin_deg`` tighter than the check's, so the
    result holds between the sampled yaws too; (b)'s tilt test is exact (no sampling) and its
    occlusion test is re-checked on a finer cone grid by :func:`check_overhead_coverage`.
    """
    sites = candidates if candidates is not None else candidate_sites(mesh, radius_mm, radii_mm=view.radii_mm)
    if not sites:
        smallest = min(view.radii_mm) if view.radii_mm else radius_mm
        raise ModelError(f"no flat face can hold even the smallest marker (radius {smallest:g} mm: faces at "
                         f"least {2 * 1.3 * smallest:.1f} mm across)")
    Ts = [T for T, _ in poses]
    dirs = view_directions_o(Ts, view.angle_deg, view.n_yaw)
    vis = visibility_matrix(mesh, sites, dirs, distance_mm=view.distance_mm,
                            max_obliquity_deg=view.max_obliquity_deg - planning_margin_deg)
    coverable = vis.any(axis=1)  # (pose, yaw) rows no site can serve: left uncovered and reported
    rows = vis[coverable]
    over = None
    untracked: list[int] = []
    if view.overhead_distance_mm is not None:
        over = overhead_visibility(mesh, sites, Ts, view)
        trackable = over.any(axis=1)  # a pose no face can serve stays uncovered (reported, not fatal)
        untracked = np.flatnonzero(~trackable).tolist()
        rows = np.vstack([rows, over[trackable]])
    if rows.shape[0] == 0:
        raise ModelError("no marker site is visible from the initial viewing camera in any pose")
    chosen, method, bound = set_cover(rows)
    markers = [Marker(i, sites[k].center, sites[k].normal, sites[k].radius) for i, k in enumerate(chosen)]
    cov = vis[:, chosen]
    return PlacementResult(markers=markers, candidates=sites, method=method, bound=bound,
                           n_rows=len(rows), min_visible=int(cov.sum(axis=1).min()), coverage=cov,
                           overhead_coverage=None if over is None else over[:, chosen], untracked_poses=untracked,
                           uncovered_rows=np.flatnonzero(~coverable))


def check_coverage(mesh: trimesh.Trimesh, poses: list[np.ndarray], markers: list[Marker],
                   view: ViewingGeometry, n_yaw: int = 360, yaw_offset: float = 0.5) -> np.ndarray:
    """Brute force: number of visible markers for every stable pose × ``n_yaw`` yaws (P, n_yaw).

    Yaws are offset by ``yaw_offset`` steps from the planning grid so they are fresh samples.
    """
    dirs = view_directions_o(poses, view.angle_deg, n_yaw, yaw_offset)
    vis = visibility_matrix(mesh, markers, dirs, distance_mm=view.distance_mm,
                            max_obliquity_deg=view.max_obliquity_deg)
    return vis.sum(axis=1).reshape(len(poses), n_yaw)


def check_overhead_coverage(mesh: trimesh.Trimesh, poses: list[np.ndarray], markers: list[Marker],
                            view: ViewingGeometry, n_azimuth: int = 72, n_rings: int = 4,
                            azimuth_offset: float = 0.5) -> np.ndarray:
    """Brute force for the overhead requirement (b): per stable pose (P,), the number of markers the
    overhead camera sees from every one of ``1 + n_rings·n_azimuth`` directions of its cone
    (rings at cone·i/n_rings, azimuths offset from the planning grid), with the check's limits."""
    if view.overhead_distance_mm is None:
        raise ValueError("this viewing geometry has no overhead camera")
    return overhead_visibility(mesh, markers, poses, view, n_azimuth=n_azimuth, n_rings=n_rings,
                               azimuth_offset=azimuth_offset).sum(axis=1)


def optimal_viewing_angle(mesh: trimesh.Trimesh, poses: list[tuple[np.ndarray, float]], radius_mm: float,
                          view: ViewingGeometry, angles_deg=None, n_yaw: int = 72) -> dict:
    """Minimum marker count versus viewing angle; the optimal initial viewing angle (paper §4.1).

    Returns ``{"angles_deg", "counts", "coverage", "min_visible", "optimal_deg", "optimal_range_deg"}``:
    per angle the planned marker count and the initial-view coverage probability it reaches (1.0
    unless some pose and yaw can see no face that holds a marker). The optimum has the highest
    coverage, then the fewest markers (the paper's quantity), then the largest worst-case number
    of visible markers, then the steepest angle. The overhead rows do not depend on α.
    """
    angles = np.arange(30.0, 90.01, 3.0) if angles_deg is None else np.asarray(angles_deg, float)
    sites = candidate_sites(mesh, radius_mm, radii_mm=view.radii_mm)
    probs = np.array([p for _, p in poses])
    counts: list[int | None] = []
    worst: list[int] = []
    cover: list[float] = []
    for a in angles:
        v = replace(view, angle_deg=float(a), n_yaw=n_yaw, overhead_distance_mm=None)
        try:
            r = plan_markers(mesh, poses, radius_mm, v, candidates=sites)
        except ModelError:
            counts.append(None)
            worst.append(0)
            cover.append(0.0)
            continue
        counts.append(len(r.markers))
        worst.append(r.min_visible)
        missed = np.bincount(r.uncovered_rows // n_yaw, minlength=len(poses)) / n_yaw
        cover.append(round(float(probs @ (1.0 - missed)), 4))
    valid = [i for i, c in enumerate(counts) if c is not None]
    if not valid:
        return {"angles_deg": angles.tolist(), "counts": counts, "coverage": cover, "min_visible": worst,
                "optimal_deg": None, "optimal_range_deg": None}
    key = {i: (cover[i], -cast(int, counts[i]), worst[i], angles[i]) for i in valid}  # valid: counted
    pick = max(valid, key=lambda i: key[i])
    tied = [i for i in valid if key[i][:2] == key[pick][:2]]
    return {"angles_deg": angles.tolist(), "counts": counts, "coverage": cover, "min_visible": worst,
            "optimal_deg": float(angles[pick]),
            "optimal_range_deg": [float(angles[tied].min()), float(angles[tied].max())]}


# --- coverage probability (paper §4.1: the share of random placements with a usable marker) -------
def coverage_probability(probabilities, visible_share, tracked=None) -> float:
    """Σ_p π_p · v_p · t_p: stable pose p drawn with probability π_p, yaw uniform; v_p the share of yaws
    with a visible marker, t_p 1 if the overhead camera tracks one in pose p (omitted: 1)."""
    v = np.asarray(visible_share, float)
    t = np.ones_like(v) if tracked is None else np.asarray(tracked, float)
    return float(np.asarray(probabilities, float) @ (v * t))


def coverage_vs_angle(mesh: trimesh.Trimesh, poses: list[tuple[np.ndarray, float]], markers: list[Marker],
                      view: ViewingGeometry, angles_deg=None, n_yaw: int = 72) -> dict:
    """Initial-view coverage probability of fixed ``markers`` versus viewing angle α (deg):
    ``{"angles_deg": [...], "coverage": [...]}`` — what the library-wide angle is chosen from."""
    angles = np.arange(30.0, 90.01, 3.0) if angles_deg is None else np.asarray(angles_deg, float)
    probs = np.array([p for _, p in poses])
    Ts = [T for T, _ in poses]
    out = []
    for a in angles:
        counts = check_coverage(mesh, Ts, markers, replace(view, angle_deg=float(a)), n_yaw=n_yaw)
        out.append(round(coverage_probability(probs, (counts > 0).mean(axis=1)), 4))
    return {"angles_deg": [float(a) for a in angles], "coverage": out}


def library_viewing_angle(curves: dict[str, dict], current_deg: float) -> tuple[float, dict[str, float]]:
    """One initial viewing angle for the whole library (paper §4.1, "a given set of objects").

    ``curves``: per object ``{"angles_deg", "coverage"}`` (:func:`coverage_vs_angle`). The angle
    maximises the worst object's coverage, then the mean, then stays nearest ``current_deg``
    (markers were planned there). Returns (angle, each object's coverage at it). With no curves,
    ``current_deg``."""
    if not curves:
        return float(current_deg), {}
    grid = sorted({float(a) for c in curves.values() for a in c["angles_deg"]} | {float(current_deg)})

    def at(c, a):
        return float(np.interp(a, c["angles_deg"], c["coverage"]))

    def key(a):
        cov = [at(c, a) for c in curves.values()]
        return (round(min(cov), 4), round(float(np.mean(cov)), 4), -abs(a - current_deg))

    best = max(grid, key=key)
    return best, {n: round(at(c, best), 4) for n, c in curves.items()}


class MarkerLadder(Protocol):
    """The marker size ladder as lab.yaml ``marker`` gives it (``labctl.config.lab.MarkerConfig``)."""

    @property
    def radius_mm(self) -> float:
        """The largest marker's radius (mm)."""

    @property
    def min_image_diameter_px(self) -> float:
        """The smallest marker's face-on image diameter at the initial viewing distance (px)."""

    @property
    def size_ratio(self) -> float:
        """The ratio of one marker size to the next larger."""


class OverheadCamera(Protocol):
    """What the placement reads of the fixed camera's config (``labctl.config.devices.CameraConfig``)."""

    @property
    def eye_w_mm(self) -> Sequence[float] | None:
        """The camera's eye in the world frame (mm), or None (the paper's 1.8 m above the table)."""


def viewing_geometry(lab, angle_deg: float | None = None):
    """The marker-placement viewing geometry of a lab: lab.yaml ``viewing`` and ``marker`` (the size
    ladder down to the smallest marker the mobile camera resolves at the initial viewing distance),
    the fixed camera's height and scale. ``angle_deg`` overrides the initial viewing angle (the
    library's own, :func:`labctl.library.storage.library_angle`)."""
    v = lab.config.viewing
    mk: MarkerLadder = lab.config.marker
    cam = lab.fixed_camera
    overhead: OverheadCamera = cam
    height = 1800.0  # paper §5.2: the fixed camera 1.8 m above the table
    if overhead.eye_w_mm is not None:
        height = float(overhead.eye_w_mm[2]) - float(lab.table.origin_w_mm[2])
    mob = lab.mobile_camera.lens
    fx_mobile = mob.f_mm / mob.dx_mm
    r_min = min_marker_radius(fx_mobile, v.initial_distance_mm, mk.min_image_diameter_px)
    radii = marker_radii(mk.radius_mm, min(r_min, mk.radius_mm), mk.size_ratio)
    fixed_scale = cam.lens.f_mm / cam.lens.dx_mm / height
    return ViewingGeometry(angle_deg=v.initial_angle_deg if angle_deg is None else float(angle_deg),
                           distance_mm=v.initial_distance_mm, max_obliquity_deg=v.max_obliquity_deg,
                           overhead_distance_mm=height, radii_mm=radii, overhead_px_per_mm=fixed_scale)
