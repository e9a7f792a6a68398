"""Teaching an object (``labctl teach-object``): model → stable poses → markers → standard views.

Runs paper §4.1 (marker placement: visible to the initial viewing camera at every pose and yaw,
and trackable by the overhead fixed camera of §5.2 in every pose; the optimal initial viewing
angle) and §3.4 (standard views and their features) on a CAD model. The images come from an
injected ``render_view_factory(mesh, markers) -> render_view(T_o_c) -> BGR image`` (the
simulated lab's renderer, or the robot camera on hardware), so nothing here touches a device
or the simulator."""

from __future__ import annotations

import hashlib
import io
from collections.abc import Callable
from pathlib import Path
from typing import cast

import numpy as np
import trimesh
import yaml

from ..errors import LabctlError
from .model import ModelError, load_model, merge_symmetric_poses, stable_poses, validate_model
from .placement import (
    Marker,
    ViewingGeometry,
    candidate_sites,
    check_coverage,
    check_overhead_coverage,
    coverage_probability,
    coverage_vs_angle,
    optimal_viewing_angle,
    plan_markers,
    view_directions_o,
    visibility_matrix,
)
from .storage import LibraryError, LibraryObject, check_name, save_object
from .views import RenderView, build_standard_views

RenderFactory = Callable[..., RenderView]  # (mesh, markers, stable_poses) -> render_view

#: resting poses closer than this (mm, every hull vertex) count as one pose turned about the vertical:
#: STL's float32 coordinates round a 100-mm part at ~1e-5 mm, and a standard-view pixel is ~0.3 mm
POSE_SYMMETRY_TOL_MM = 0.05
#: a marker mapped by a symmetry of the part lands on another marker within these
MARKER_SYMMETRY_TOL_MM = 0.5
MARKER_SYMMETRY_TOL_DEG = 1.0


class CoverageRefused(LabctlError):
    """A taught object covered less than ``library.min_coverage`` (exit 1: the model is valid, the part is not)."""


def markers_map_onto_themselves(markers: list[Marker], S: np.ndarray) -> bool:
    """True when the symmetry ``S`` (4×4, object frame) maps the marker set onto itself (``S⁻¹·M = M``)."""
    S_inv = np.linalg.inv(S)
    cos_tol = np.cos(np.radians(MARKER_SYMMETRY_TOL_DEG))
    for m in markers:
        c = S_inv[:3, :3] @ m.center + S_inv[:3, 3]
        n = S_inv[:3, :3] @ m.normal
        if not any(np.linalg.norm(c - o.center) <= MARKER_SYMMETRY_TOL_MM and float(n @ o.normal) >= cos_tol
                   and abs(m.radius - o.radius) < 1e-6 for o in markers):
            return False
    return True


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


def _pose_words(mesh: trimesh.Trimesh, T: np.ndarray) -> str:
    """A stable pose as the user sees it: the footprint and height (mm) of the object resting so."""
    e = np.ptp(trimesh.transform_points(mesh.vertices, T), axis=0)
    return f"resting {e[2]:.0f} mm tall on a {min(e[0], e[1]):.0f}×{max(e[0], e[1]):.0f} mm footprint"


def coverage_report(mesh: trimesh.Trimesh, poses: list[tuple[np.ndarray, float]], counts: np.ndarray,
                    overhead: np.ndarray | None) -> dict:
    """Coverage probability of a placement (paper §4.1): the share of random placements — stable pose
    by its probability, yaw uniform — in which the initial viewing camera sees a marker
    (``initial_view``), the overhead camera tracks one (``tracked``), and both (``probability``).
    ``counts`` (P, n_yaw): visible markers (:func:`check_coverage`); ``overhead`` (P,): tracked markers."""
    probs = np.array([p for _, p in poses])
    share = (counts > 0).mean(axis=1)
    tracked = np.ones(len(poses)) if overhead is None else (np.asarray(overhead) > 0).astype(float)
    return {
        "probability": round(coverage_probability(probs, share, tracked), 4),
        "initial_view": round(coverage_probability(probs, share), 4),
        "tracked": round(float(probs @ tracked), 4),
        "per_pose": [{"probability": round(float(p), 4), "visible_yaw_share": round(float(v), 4),
                      "tracked": bool(t), "pose": _pose_words(mesh, T)}
                     for (T, p), v, t in zip(poses, share, tracked, strict=True)],
    }


MARKER_MARGIN = 1.3  # a marker's disc of radius r needs a flat of 2·1.3·r across (candidate_sites' margin)


def pose_marker_fix(mesh: trimesh.Trimesh, T: np.ndarray, markers: list[Marker], view: ViewingGeometry,
                    n_yaw: int = 36) -> str:
    """What this part's own geometry can carry for the yaws of resting pose ``T`` (4×4, O on the table) that no
    marker covers (paper §4.1): a flat face that can hold a marker and would be seen there, named by its centre
    and normal (mm, rad-free unit vector, frame O); or, when no flat face of the part could (a round part's
    curved side is many narrow facets), that nothing flat faces the camera there, in words."""
    smallest = min(view.radii_mm) if view.radii_mm else None
    radius = smallest if smallest is not None else 5.0
    sites = candidate_sites(mesh, radius, margin=MARKER_MARGIN, radii_mm=view.radii_mm)
    dirs = view_directions_o([T], view.angle_deg, n_yaw, 0.5)
    kw = {"distance_mm": view.distance_mm, "max_obliquity_deg": view.max_obliquity_deg}
    seen = visibility_matrix(mesh, markers, dirs, **kw).any(axis=1) if markers else np.zeros(len(dirs), bool)
    miss = dirs[~seen]
    used = {tuple(np.round(m.center, 3)) for m in markers}
    free = [s for s in sites if tuple(np.round(s.center, 3)) not in used]
    if len(miss) and free:
        vis = visibility_matrix(mesh, free, miss, **kw)
        k = int(np.argmax(vis.sum(axis=0)))
        if vis[:, k].any():
            s = free[k]
            return (f"a marker on the flat face at ({', '.join(f'{v:.0f}' for v in s.center)}) mm facing "
                    f"({', '.join(f'{v:.2f}' for v in s.normal)}), seen at {int(vis[:, k].sum())} of the "
                    f"{len(miss)} uncovered yaws sampled")
    need = 2 * MARKER_MARGIN * radius
    narrow = len(mesh.facets) + int(len(mesh.faces) - sum(len(f) for f in mesh.facets)) - len(sites)
    return (f"none this part can carry: no flat face ≥ {need:.0f} mm across faces the camera in that pose "
            f"({narrow} of its faces are narrower, a curved side); hand-placed markers (--markers FILE) only if "
            "the real part has a flat there, else --accept-partial")


def overhead_marker_fix(mesh: trimesh.Trimesh, T: np.ndarray, markers: list[Marker], view: ViewingGeometry) -> str:
    """What this part can carry for the overhead camera in resting pose ``T``: an unused flat face that can hold
    a marker and looks within ``overhead_max_tilt_deg`` of upward there, or that it has none."""
    radius = min(view.radii_mm) if view.radii_mm else 5.0
    used = {tuple(np.round(m.center, 3)) for m in markers}
    cos_max = np.cos(np.radians(view.overhead_max_tilt_deg))
    up = [s for s in candidate_sites(mesh, radius, margin=MARKER_MARGIN, radii_mm=view.radii_mm)
          if tuple(np.round(s.center, 3)) not in used and float((T[:3, :3] @ s.normal)[2]) >= cos_max]
    if up:
        s = up[0]
        return (f"a marker on the flat face at ({', '.join(f'{v:.0f}' for v in s.center)}) mm facing "
                f"({', '.join(f'{v:.2f}' for v in s.normal)}), within {view.overhead_max_tilt_deg:g}° of upward there")
    return (f"none this part can carry: no flat face ≥ {2 * MARKER_MARGIN * radius:.0f} mm across looks within "
            f"{view.overhead_max_tilt_deg:g}° of upward in that pose")


def coverage_warnings(name: str, cov: dict, view: ViewingGeometry, curve: dict | None = None,
                      pose_fix: str | None = None, tracked_fix: str | None = None) -> list[str]:
    """One line per shortfall of a coverage report, saying what would fix it (``pose_fix``, ``tracked_fix``: what
    the part's geometry can carry in its worst pose, :func:`pose_marker_fix`, :func:`overhead_marker_fix`)."""
    out = []
    if cov["initial_view"] < 1.0:
        worst = min(cov["per_pose"], key=lambda d: d["visible_yaw_share"])
        fixes = []
        if curve:
            k = int(np.argmax(curve["coverage"]))
            if curve["coverage"][k] > cov["initial_view"] + 1e-3:
                fixes.append(f"an initial viewing angle of {curve['angles_deg'][k]:g}° "
                             f"({100 * curve['coverage'][k]:.1f} %)")
        if pose_fix is not None:
            fixes.append(pose_fix)
        else:
            fixes.append("hand-placed markers (--markers FILE)")
        out.append(f"{name}: a marker is in the initial view in {100 * cov['initial_view']:.1f} % of random "
                   f"placements (worst: {worst['pose']}, probability {worst['probability']:.3f}, no marker at "
                   f"{100 * (1 - worst['visible_yaw_share']):.0f} % of yaws); would fix it: " + "; ".join(fixes))
    if cov["tracked"] < 1.0:
        miss = [d for d in cov["per_pose"] if not d["tracked"]]
        out.append(f"{name}: the overhead camera tracks a marker in {100 * cov['tracked']:.1f} % of random "
                   f"placements (not when {miss[0]['pose']}); the run then follows red pixels seen edge-on; "
                   "would fix it: " + (tracked_fix or f"a flat face within {view.overhead_max_tilt_deg:g}° of "
                                                        "upward in that pose"))
    return out


def file_sha256(path: Path | str) -> str:
    """Hex SHA-256 digest of the file at ``path`` (read in 1 MiB chunks)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _standard_views(name, mesh, markers, poses, render_factory, standoff_mm, scale_mm_per_px, step):
    """Standard views of ``markers``: (views, {marker id: why it has none}, [(marker id, crop warning)])."""
    step("standard views", 0, len(markers))
    render_view = render_factory(mesh, markers, poses)
    done, crops = [0], []
    failed: dict[int, str] = {}

    def tick(k):
        done[0] += k
        step("standard views", done[0], len(markers))

    def crop(mid, why):
        crops.append((mid, f"{name}: standard view of marker {mid}: {why}; would fix it: a longer "
                           "viewing.standoff_mm"))

    views = build_standard_views(markers, render_view, standoff_mm=standoff_mm, scale_mm_per_px=scale_mm_per_px,
                                 progress=tick, on_crop=crop, on_fail=failed.__setitem__)
    return views, failed, crops


def teach_object(name: str, model: Path | str | trimesh.Trimesh, *, radius_mm: float, view: ViewingGeometry,
                 standoff_mm: float, scale_mm_per_px: float, render_factory: RenderFactory,
                 markers: list[Marker] | None = None, library_dir: Path | str | None = None,
                 progress: Callable[[str, int, int], None] | None = None, sweep: bool = True,
                 force: bool = False, angle_curve: bool | None = None,
                 pose_probability_floor: float = 0.0, min_coverage: float | None = None,
                 accept_partial: bool = False) -> LibraryObject:
    """Teach one object; write it to ``library_dir/NAME`` (atomically) when a folder is given.

    Never refuses a valid watertight model that fits the lab: faces too small for the lab's
    marker get smaller ones (``view.radii_mm``), and where full coverage is physically impossible
    the object is taught anyway with its coverage probability in ``info["coverage"]`` and one
    line per shortfall in ``info["warnings"]`` (what would fix it). Raises :class:`ModelError`
    for a model that cannot be taught and :class:`LibraryError` if ``NAME`` exists and ``force``
    is False (the library is untouched either way). ``progress(stage, done, total)`` is called as
    the stages advance. ``sweep`` also computes the marker count versus viewing angle (paper
    §4.1); ``angle_curve`` the coverage of the chosen markers versus viewing angle (what the
    library-wide angle is chosen from, :func:`labctl.library.storage.update_library_angle`;
    default: when the object is written to a library).

    Resting poses that are the same up to the part's symmetry (a cylinder's sides, a nut's flats) are
    one pose with their summed probability (:func:`labctl.library.model.merge_symmetric_poses`), as
    long as the markers are as symmetric as the part; classes below ``pose_probability_floor``
    (lab.yaml ``library.pose_probability_floor``) are left out, and their share is reported.

    With ``min_coverage`` (lab.yaml ``library.min_coverage``), an object whose coverage probability
    (a tracked marker in the initial view, over the poses kept, times their share) is below it raises
    :class:`CoverageRefused` and is not written, unless ``accept_partial``.
    """
    check_name(name)
    if library_dir is not None and (Path(library_dir) / name).exists() and not force:
        raise LibraryError(f"object {name!r} already exists in {library_dir}; use --force to replace it")

    def step(stage, done, total):
        if progress is not None:
            progress(stage, done, total)

    source: dict = {"path": None, "sha256": None}
    if not isinstance(model, trimesh.Trimesh):
        source = {"path": str(Path(model).expanduser().resolve()), "sha256": None}
        mesh = load_model(model)
        source["sha256"] = file_sha256(model)
    else:
        mesh = model
    smallest = min(view.radii_mm) if view.radii_mm else radius_mm
    mesh = validate_model(mesh, marker_radius_mm=smallest, name=name)
    step("stable poses", 0, 1)
    classes = merge_symmetric_poses(mesh, stable_poses(mesh), tol_mm=POSE_SYMMETRY_TOL_MM)
    n_resting = sum(len(c) for c in classes)
    kept = [c for c in classes if sum(p for _, p, _ in c) >= pose_probability_floor]
    dropped_probability = 1.0 - sum(p for c in kept for _, p, _ in c)
    given_markers = markers

    def place(poses):
        markers = given_markers
        candidates = None
        rejected: list[str] = []
        for _attempt in range(8):
            step("marker placement", 0, 1)
            if markers is None or candidates is not None:
                placement = plan_markers(mesh, poses, radius_mm, view, candidates=candidates)
                chosen = placement.markers
                method, bound = placement.method, placement.bound
                n_candidates = len(placement.candidates)
            else:
                chosen, method, bound, n_candidates = markers, "given", None, len(markers)
            views, failed, crops = _standard_views(name, mesh, chosen, poses, render_factory, standoff_mm,
                                                   scale_mm_per_px, step)
            if not failed:
                break
            if method == "given":
                mid, why = next(iter(failed.items()))
                raise ModelError(f"{name}: the standard view of marker {mid} shows no usable silhouette ({why})")
            # a site whose standard view leaves the image (an off-centre marker on a large part): drop that
            # site and plan again from the others (the view is centred on the marker, paper §3.4)
            bad = {tuple(np.round(chosen[mid].center, 6)) for mid in failed}
            rejected += [f"marker site at {np.round(chosen[mid].center, 1).tolist()} mm: {why}"
                         for mid, why in failed.items()]
            candidates = [c for c in placement.candidates if tuple(np.round(c.center, 6)) not in bad]
            if not candidates:
                raise ModelError(f"{name}: no marker site has a standard view that fits the image "
                                 f"({next(iter(failed.values()))}); a longer viewing.standoff_mm would fix it")
        else:
            raise ModelError(f"{name}: standard views keep leaving the image ({next(iter(failed.values()))})")
        if crops and method != "given":
            # views that fit as taught but leave the image at some in-plane rotation fail in runs: plan once more
            # without those sites and keep that plan if it covers as much and all its views fit any rotation
            bad = {tuple(np.round(chosen[mid].center, 6)) for mid, _ in crops}
            alt = [c for c in placement.candidates if tuple(np.round(c.center, 6)) not in bad]
            if alt:
                p2 = plan_markers(mesh, poses, radius_mm, view, candidates=alt)
                if (len(p2.uncovered_rows), len(p2.untracked_poses)) <= (len(placement.uncovered_rows),
                                                                       len(placement.untracked_poses)):
                    v2, f2, c2 = _standard_views(name, mesh, p2.markers, poses, render_factory, standoff_mm,
                                                 scale_mm_per_px, step)
                    if not f2 and not c2:
                        placement, chosen, views, crops = p2, p2.markers, v2, []
                        method, bound, n_candidates = p2.method, p2.bound, len(p2.candidates)
        return chosen, views, crops, rejected, method, bound, n_candidates

    for _attempt in range(n_resting + 1):  # each round splits a class, so this ends
        total = sum(p for c in kept for _, p, _ in c)
        poses = [(c[0][0], sum(p for _, p, _ in c) / total) for c in kept]
        Ts = [T for T, _ in poses]
        chosen, views, crops, rejected, method, bound, n_candidates = place(poses)
        # a class stands for its members only if the markers are as symmetric as the part: a member
        # pose shows the markers S⁻¹·M of the first pose, so M must map onto itself
        broken = [k for k, c in enumerate(kept) if not all(markers_map_onto_themselves(chosen, S) for _, _, S in c[1:])]
        if not broken:
            break
        kept = [m for k, c in enumerate(kept) for m in ([[x] for x in c] if k in broken else [c])]
    else:
        raise ModelError(f"{name}: its markers are not as symmetric as its resting poses; teach it with --markers")
    markers = chosen
    counts = check_coverage(mesh, Ts, markers, view)
    overhead = check_overhead_coverage(mesh, Ts, markers, view) if view.overhead_distance_mm is not None else None
    untracked = [] if overhead is None else [int(p) for p in np.flatnonzero(overhead == 0)]
    cov = coverage_report(mesh, poses, counts, overhead)
    if angle_curve is None:
        angle_curve = library_dir is not None
    curve = coverage_vs_angle(mesh, poses, markers, view, n_yaw=36) if angle_curve else None
    fix = None
    if cov["initial_view"] < 1.0:
        worst = int(np.argmin([d["visible_yaw_share"] for d in cov["per_pose"]]))
        fix = pose_marker_fix(mesh, Ts[worst], list(markers), view)
    tracked_fix = overhead_marker_fix(mesh, Ts[untracked[0]], list(markers), view) if untracked else None
    warnings = coverage_warnings(name, cov, view, curve, fix, tracked_fix) + [w for _, w in crops]
    if dropped_probability > 0:
        warnings.append(f"{name}: resting poses with {100 * dropped_probability:.1f} % of the probability are below "
                        f"library.pose_probability_floor ({pose_probability_floor:g}) and were left out")
    if rejected:
        warnings.append(f"{name}: {len(rejected)} marker site(s) left out, their standard view leaves the image "
                        f"(e.g. {rejected[0]}); would fix it: a longer viewing.standoff_mm")
    sweep_info = optimal_viewing_angle(mesh, poses, radius_mm, view) if sweep else None
    with io.BytesIO() as buf:
        mesh.export(buf, file_type="stl")
        stored_sha = hashlib.sha256(buf.getvalue()).hexdigest()
    info = {
        "units": "mm",
        "source": {**source, "stored_model_sha256": stored_sha},
        "extents_mm": [round(float(v), 3) for v in mesh.extents],
        "marker_radii_mm": sorted({float(m.radius) for m in markers}, reverse=True),
        "coverage": {k: v for k, v in cov.items()},
        "warnings": warnings,
        "placement": {"method": method, "greedy_bound": bound, "candidate_sites": n_candidates,
                      "markers": len(markers), "viewing_angle_deg": view.angle_deg,
                      "distance_mm": view.distance_mm, "max_obliquity_deg": view.max_obliquity_deg,
                      "min_visible_markers": int(counts.min()), "checked_yaw_steps": int(counts.shape[1]),
                      "overhead": None if overhead is None else {
                          # overhead is checked only with a distance
                          "distance_mm": float(cast(float, view.overhead_distance_mm)),
                          "cone_deg": float(view.overhead_cone_deg),
                          "max_tilt_deg": float(view.overhead_max_tilt_deg),
                          "min_tracked_markers": int(overhead.min()),
                          "untracked_poses": untracked,
                          "untracked_probability": round(sum(poses[p][1] for p in untracked), 4),
                          "tracked_markers_per_pose": [int(v) for v in overhead]}},
        "coverage_vs_angle": curve if curve is not None else {},
        "viewing_angle_sweep": sweep_info if sweep_info is not None else {},
        "standoff_mm": float(standoff_mm), "mm_per_px": float(scale_mm_per_px),
        "resting_poses": {"computed": n_resting, "kept": len(poses), "merged": n_resting - len(poses),
                          "dropped_probability": round(dropped_probability, 6),
                          "probability_floor": float(pose_probability_floor)},
    }
    covered = float(cov["probability"]) * (1.0 - dropped_probability)
    if min_coverage is not None and covered < min_coverage:
        if not accept_partial:
            fixes = "; ".join(w.split("would fix it: ", 1)[1] for w in warnings if "would fix it: " in w)
            raise CoverageRefused(f"{name}: a tracked marker is in view in {100 * covered:.1f} % of random placements, "
                                  f"below library.min_coverage ({100 * min_coverage:.0f} %); "
                                  + (f"would fix it: {fixes}; " if fixes else "")
                                  + "or teach it anyway with --accept-partial")
        info["accepted_partial"] = True
    obj = LibraryObject(name, mesh, list(markers), poses, {v.marker_id: v for v in views}, info=info)
    if library_dir is not None:
        try:
            obj.path = save_object(library_dir, obj)
        except OSError as exc:
            raise LibraryError(f"cannot write {Path(library_dir) / name}: {exc}") from None
    return obj
