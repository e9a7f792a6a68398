"""Teaching an object (``labctl teach-object``): model → stable poses → markers → standard views.

Runs paper §4.1 (marker placement: visible to the initial viewing camera at every pose and yaw,
and trackable by the overhead fixed camera of §5.2 in every pose; the optimal initial viewing
angle) and §3.4 (standard views and their features) on a CAD model. The images come from an
injected ``render_view_factory(mesh, markers) -> render_view(T_o_c) -> BGR image`` (the
simulated lab's renderer, or the robot camera on hardware), so nothing here touches a device
or the simulator."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh
import yaml

from ..vision.shape import ShapeError
from .model import ModelError, load_model, stable_poses, validate_model
from .placement import (
    Marker,
    ViewingGeometry,
    check_coverage,
    check_overhead_coverage,
    optimal_viewing_angle,
    plan_markers,
)
from .storage import LibraryError, LibraryObject, check_name, save_object
from .views import RenderView, build_standard_views

RenderFactory = Callable[..., RenderView]  # (mesh, markers, stable_poses) -> render_view


def read_markers_file(path: Path | str, default_radius_mm: float) -> list[Marker]:
    """Markers given by hand: YAML ``markers: [{id, center, normal, radius?}]`` in the model's frame (mm)."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
        items = data["markers"] if isinstance(data, dict) else data
        out = []
        for i, d in enumerate(items):
            d = dict(d)
            d.setdefault("id", i)
            d.setdefault("radius", default_radius_mm)
            n = np.asarray(d["normal"], float)
            d["normal"] = (n / np.linalg.norm(n)).tolist()
            out.append(Marker.from_dict(d))
    except FileNotFoundError:
        raise ModelError(f"markers file not found: {path}") from None
    except (yaml.YAMLError, KeyError, TypeError, ValueError, ZeroDivisionError) as exc:
        raise ModelError(f"markers file {path.name} is malformed: {exc}") from None
    if not out:
        raise ModelError(f"markers file {path.name} lists no markers")
    return out


def teach_object(name: str, model: Path | str | trimesh.Trimesh, *, radius_mm: float, view: ViewingGeometry,
                 standoff_mm: float, scale_mm_per_px: float, render_factory: RenderFactory,
                 markers: list[Marker] | None = None, library_dir: Path | str | None = None,
                 progress: Callable[[str, int, int], None] | None = None, sweep: bool = True) -> LibraryObject:
    """Teach one object; write it to ``library_dir/NAME`` (atomically) when a folder is given.

    Raises :class:`ModelError` for a model that cannot be taught (the library is untouched).
    ``progress(stage, done, total)`` is called as the stages advance. ``sweep`` also computes the
    marker count versus viewing angle (the optimal initial viewing angle, paper §4.1).
    """
    check_name(name)

    def step(stage, done, total):
        if progress is not None:
            progress(stage, done, total)

    mesh = load_model(model) if not isinstance(model, trimesh.Trimesh) else model
    mesh = validate_model(mesh, marker_radius_mm=radius_mm, name=name)
    step("stable poses", 0, 1)
    poses = stable_poses(mesh)
    step("marker placement", 0, 1)
    if markers is None:
        placement = plan_markers(mesh, poses, radius_mm, view)
        markers = placement.markers
        method, bound = placement.method, placement.bound
        n_candidates = len(placement.candidates)
    else:
        method, bound, n_candidates = "given", None, len(markers)
    counts = check_coverage(mesh, [T for T, _ in poses], markers, view)
    if counts.min() == 0:
        p = int(np.argmin(counts.min(axis=1)))
        raise ModelError(f"{name}: in stable pose {p} (probability {poses[p][1]:.3f}) no marker is visible at "
                         f"{int((counts[p] == 0).sum())} of {counts.shape[1]} yaw angles")
    overhead, untracked = None, []
    if view.overhead_distance_mm is not None:
        overhead = check_overhead_coverage(mesh, [T for T, _ in poses], markers, view)
        untracked = [int(p) for p in np.flatnonzero(overhead == 0)]
        possible = set(untracked) if method == "given" else set(placement.untracked_poses)
        missed = [p for p in untracked if p not in possible]
        if missed:
            p = missed[0]
            raise ModelError(f"{name}: in stable pose {p} (probability {poses[p][1]:.3f}) the overhead camera can "
                             f"track no marker (none within {view.overhead_max_tilt_deg:g}° of the vertical and in "
                             f"view over its {view.overhead_cone_deg:g}° field cone)")
    sweep = optimal_viewing_angle(mesh, poses, radius_mm, view) if sweep else None
    step("standard views", 0, len(markers))
    render_view = render_factory(mesh, markers, poses)
    done = [0]

    def tick(k):
        done[0] += k
        step("standard views", done[0], len(markers))

    try:
        views = build_standard_views(markers, render_view, standoff_mm=standoff_mm, scale_mm_per_px=scale_mm_per_px,
                                     progress=tick)
    except ShapeError as exc:
        raise ModelError(f"{name}: a standard view shows no usable silhouette ({exc})") from None
    info = {
        "units": "mm",
        "source": str(model) if not isinstance(model, trimesh.Trimesh) else "mesh",
        "extents_mm": [round(float(v), 3) for v in mesh.extents],
        "placement": {"method": method, "greedy_bound": bound, "candidate_sites": n_candidates,
                      "markers": len(markers), "viewing_angle_deg": view.angle_deg,
                      "distance_mm": view.distance_mm, "max_obliquity_deg": view.max_obliquity_deg,
                      "min_visible_markers": int(counts.min()), "checked_yaw_steps": int(counts.shape[1]),
                      "overhead": None if overhead is None else {
                          "distance_mm": float(view.overhead_distance_mm), "cone_deg": float(view.overhead_cone_deg),
                          "max_tilt_deg": float(view.overhead_max_tilt_deg),
                          "min_tracked_markers": int(overhead.min()),
                          "untracked_poses": untracked,
                          "untracked_probability": round(sum(poses[p][1] for p in untracked), 4),
                          "tracked_markers_per_pose": [int(v) for v in overhead]}},
        "viewing_angle_sweep": sweep if sweep is not None else {},
        "standoff_mm": float(standoff_mm), "mm_per_px": float(scale_mm_per_px),
    }
    obj = LibraryObject(name, mesh, list(markers), poses, {v.marker_id: v for v in views}, info=info)
    if library_dir is not None:
        try:
            obj.path = save_object(library_dir, obj)
        except OSError as exc:
            raise LibraryError(f"cannot write {Path(library_dir) / name}: {exc}") from None
    return obj
