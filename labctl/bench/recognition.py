"""Recognition benchmark (paper §3.4): standard-view identification rates and matching speed.

Standard views are rendered by the simulated lab's renderer with a random in-plane rotation,
±3 % stand-off error, ±2° optical-axis misalignment and sensor noise (σ = 2 grey levels).

* ``sample``: the sample lab's seven objects (its ``object_library/``); every view × trials.
* ``generated``: a library of ≥ 30 random machined parts taught on the fly (same pipeline).
* ``scale``: 100 random parts (boxes, plates, concave extrusions, stepped blocks, parts with holes)
  taught on the fly, one trial per view.

For each, the angle-of-sight matcher with the ambiguity threshold and extra standard views
(:func:`labctl.library.matching.identify`), and three single-view minimum-distance rates in the
same run: angle-of-sight, Hu moments (``cv2.matchShapes`` I1) and centroid-distance Fourier
descriptors (same eccentricity and size gates). Timing: one ``match`` against a 1,000-view library
versus the same query matched with ``cv2.matchShapes`` contour by contour (the baseline).
"""

from __future__ import annotations

import numpy as np

from ..geometry import invert, make_T, rot_z
from ..library.matching import (
    DEFAULT_THRESHOLD,
    LibraryIndex,
    StandardViewQuery,
    UnusableView,
    identify,
    match,
    split_query,
)
from ..library.views import marker_frame, mm_per_px, perturbed_view_pose, standard_view_pose
from ..vision.shape import ShapeError, features_from_image, silhouette_mask
from ._timing import median_time, row


def _setup():
    from ..config import load_lab
    from ..sim.truth import camera_model
    from ..workspace import sample_lab_path

    lab = load_lab(sample_lab_path())
    return lab, camera_model(lab.mobile_camera)


def render_pool(library: dict, camera, standoff: float, per_view: int, rng: np.random.Generator, *,
                gate: tuple[float, float, float] | None = None) -> dict:
    """Perturbed standard views, rendered once: ``{(name, marker_id): [StandardViewQuery | None, ...]}``.

    Each view is rendered ``per_view`` times by the simulated lab's renderer (object resting on
    the table, :func:`labctl.sim.rigs.standard_view_renderer`) with a random in-plane rotation,
    ±3 % stand-off, ≤ 2° axis tilt and σ = 2 sensor noise; None where no silhouette was found.
    Each query carries its marker's height above the table as a run measures it
    (:func:`labctl.library.marker_height.measure_marker_height` on the rendered image, the camera
    pose known) and the gate's tolerance from ``gate`` = (``run.height_gate_mm``,
    ``height_gate_sigmas``, ``height_gate_depth_frac``; default: RunConfig's). All matchers (and
    the extra views of :func:`evaluate`) draw on the same pool.
    """
    from ..config.lab import RunConfig
    from ..library.marker_height import measure_marker_height
    from ..sim.rigs import standard_view_renderer

    if gate is None:
        d = RunConfig()
        gate = (d.height_gate_mm, d.height_gate_sigmas, d.height_gate_depth_frac)
    radii = sorted({float(m.radius) for o in library.values() for m in o.markers}, reverse=True)
    scale = mm_per_px(camera, standoff)
    factory = standard_view_renderer(camera, noise_sigma=2.0, rng=rng)
    pool: dict = {}
    for name, obj in sorted(library.items()):
        render_view = factory(obj.mesh, obj.markers, obj.stable_poses)
        for m in obj.markers:
            feats: list[StandardViewQuery | None] = []
            for _ in range(per_view):
                T_o_c = perturbed_view_pose(standard_view_pose(m, standoff), m.center, rng)
                image, T_w_o = render_view(T_o_c, with_pose=True)
                try:
                    f = features_from_image(image, scale)
                except ShapeError:
                    feats.append(None)
                    continue
                h = measure_marker_height(image, camera, T_w_o @ T_o_c, radii, standoff_mm=standoff) \
                    if gate[0] > 0 else None
                feats.append(StandardViewQuery(f) if h is None else
                             StandardViewQuery(f, h.height_mm, h.tolerance_mm(*gate)))
            pool[(name, m.id)] = feats
    return pool


NEW_SIDE_DEG = 20.0  # the predictor's novelty rule: a face within 20° of one viewed tells nothing new


def _other_marker_view(obj, pool: dict, name: str, tried: list[int], rng: np.random.Generator):
    """The run's answer to a standard view with no usable silhouette (a large part cropped by the
    image edge): the predictor takes a spare pose or looks from another side (``_next_marker``) for a
    marker on a face at least ``NEW_SIDE_DEG`` from those tried. Returns (marker, pool index,
    features or None) drawn from the pool, or None when the object has no such marker."""
    normals = [obj.marker(i).normal for i in tried]
    cos_new = np.cos(np.radians(NEW_SIDE_DEG))
    fresh = [mk for mk in obj.markers if mk.id not in tried and all(float(mk.normal @ n) < cos_new for n in normals)]
    if not fresh:
        return None
    mk = fresh[int(rng.integers(len(fresh)))]
    k = int(rng.integers(len(pool[(name, mk.id)])))
    return mk, k, pool[(name, mk.id)][k]


def evaluate(library: dict, pool: dict, rng: np.random.Generator, *, threshold: float = DEFAULT_THRESHOLD,
             max_views: int = 3, first_per_view: int | None = None, height_gate: bool = True, **match_kw) -> dict:
    """Identification rates over the pool: every pooled view is a first view (or the first
    ``first_per_view`` of each); extra views are other pooled renders of the marker reached.

    A first view with no usable silhouette is followed, as in a run, by the view of another marker
    (:func:`_other_marker_view`); every view taken counts towards ``max_views``. The single-view
    rates count such a first view as wrong.
    Queries that carry a measured marker height (:func:`render_pool`) narrow their candidates by it as a
    run does (``run.height_gate_*``); ``height_gate`` False ignores the heights (same pool, for comparison)."""
    index = LibraryIndex.from_library(library)
    if not height_gate:
        pool = {k: [q if q is None else StandardViewQuery(split_query(q)[0]) for q in v] for k, v in pool.items()}
    n = 0
    ok = {"aos_with_extra_views": 0, "aos_single_view": 0, "hu_single_view": 0, "fd_single_view": 0}
    ambiguous = extra_views = failures = unresolved = recovered = wrong_ids = 0
    wrong: list[str] = []
    for (name, mid), feats in sorted(pool.items()):
        obj = library[name]
        for q0, f0 in enumerate(feats[:first_per_view]):
            n += 1
            if f0 is not None:
                for method in ("aos", "hu", "fd"):  # the single-view rates: the silhouette alone
                    r = match(split_query(f0)[0], index, threshold, method=method, **match_kw)
                    ok[f"{method}_single_view"] += int(r.best is not None and r.best[0] == name)
            m, q, f, tried = obj.marker(mid), q0, f0, [mid]
            while f is None and len(tried) < max_views:
                other = _other_marker_view(obj, pool, name, tried, rng)
                if other is None:
                    break
                m, q, f = other
                tried.append(m.id)
            if f is None:
                failures += 1
                continue
            recovered += int(len(tried) > 1)
            first_f, first_h = split_query(f)
            first = match(first_f, index, threshold, **first_h, **match_kw)

            def acquire(h: str, j: int, _m=m, _first=first, _obj=obj, _name=name, _q=q):
                # the robot heads for where marker j would be if the object were h, then takes
                # the standard view of the marker of the true object it finds there
                hyp = library[h]
                mh = hyp.marker(_first.views[h])
                T_x_h = marker_frame(_m) @ make_T(rot_z(rng.uniform(-np.pi, np.pi))) @ invert(marker_frame(mh))
                want = T_x_h[:3, :3] @ hyp.marker(j).normal if h != _name else _obj.marker(j).normal
                mk = max(_obj.markers, key=lambda qm: float(qm.normal @ want))
                if float(mk.normal @ want) < np.cos(np.radians(60)):
                    return None
                # another render of that marker, drawn as the run would meet it: it may be unusable
                others = [g for k, g in enumerate(pool[(_name, mk.id)]) if not (mk.id == _m.id and k == _q)]
                g = others[int(rng.integers(len(others)))] if others else None
                return UnusableView() if g is None else g

            res = identify(f, index, acquire, threshold=threshold, max_views=max_views - len(tried) + 1,
                           **match_kw)
            ambiguous += int(first.ambiguous)
            extra_views += res.views_used - 1 + len(tried) - 1
            unresolved += int(not res.resolved)
            if res.resolved and res.name == name:  # a run answers only when resolved
                ok["aos_with_extra_views"] += 1
                continue
            wrong_ids += int(res.resolved)
            if len(wrong) < 10:  # "unresolved" or the wrong identity a run would answer
                wrong.append(f"{name}#{mid}->{res.name if res.resolved else 'unresolved'}")
    rates = {k: v / max(n, 1) for k, v in ok.items()}
    return {"objects": len(library), "views": len(index), "trials": n, "rates": rates,
            "ambiguous_first_views": ambiguous, "extra_views": extra_views,
            "unresolved_after_max_views": unresolved, "silhouette_failures": failures,
            "recovered_by_another_marker": recovered, "wrong_identities": wrong_ids, "errors": wrong}


def _evaluate(library: dict, camera, standoff: float, trials: int, rng: np.random.Generator, *,
              threshold: float = DEFAULT_THRESHOLD, max_views: int = 3,
              gate: tuple[float, float, float] | None = None) -> dict:
    """Render a pool with ``trials + 1`` renders per view; ``trials`` of them are first views; ``gate``
    the marker-height gate's settings (:func:`render_pool`)."""
    pool = render_pool(library, camera, standoff, trials + 1, rng, gate=gate)
    return evaluate(library, pool, rng, threshold=threshold, max_views=max_views, first_per_view=trials)


def generated_library(n_objects: int, camera, lab, rng: np.random.Generator) -> dict:
    """Teach ``n_objects`` random machined parts (skipping ones the lab cannot take)."""
    from ..library.model import ModelError
    from ..library.placement import viewing_geometry
    from ..library.samples import random_object
    from ..library.teach import teach_object
    from ..sim.rigs import standard_view_renderer

    standoff = lab.config.viewing.standoff_mm
    out: dict = {}
    attempts = 0
    while len(out) < n_objects and attempts < 4 * n_objects:
        attempts += 1
        name = f"gen{len(out):02d}"
        try:
            obj = teach_object(name, random_object(rng), radius_mm=lab.config.marker.radius_mm,
                               view=viewing_geometry(lab), standoff_mm=standoff,
                               scale_mm_per_px=mm_per_px(camera, standoff),
                               render_factory=standard_view_renderer(camera, noise_sigma=0.0), sweep=False)
        except ModelError:
            continue
        if out and _indistinguishable(obj, out):
            continue
        out[name] = obj
    return out


def _indistinguishable(obj, library: dict, threshold: float = DEFAULT_THRESHOLD) -> bool:
    """True if every standard view of ``obj`` matches a view of one same existing object: no view
    could tell them apart (a random near-duplicate, not a fair test of any matcher)."""
    from ..library.matching import view_scores

    index = LibraryIndex.from_library(library)
    names = np.array(index.names)
    worst: dict[str, float] = {}
    for v in obj.views.values():
        s = view_scores(v.features, index)
        for n in library:
            worst[n] = max(worst.get(n, 0.0), float(s[names == n].min()))
    return min(worst.values()) <= threshold


def _timing(library: dict, n_views: int = 1000, repeat: int = 200) -> list[dict]:
    """One ``match`` against ``n_views`` library views (the library's views repeated in turn when it has
    fewer: the cost depends on the count, not on which views) versus ``cv2.matchShapes`` over the same
    number of contours (baseline)."""
    import cv2

    from ..library.matching import LibraryIndex

    items = [(n, mid, v) for n, o in sorted(library.items()) for mid, v in sorted(o.views.items())]
    contours = []
    for _, _, v in items:
        cs, _ = cv2.findContours(silhouette_mask(v.image).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        contours.append(max(cs, key=cv2.contourArea))
    reps = [k % len(items) for k in range(n_views)]
    index = LibraryIndex.from_views([(f"{items[k][0]}~{i // len(items)}", items[k][1], items[k][2].features)
                                     for i, k in enumerate(reps)])
    contours = [contours[k] for k in reps]
    q = items[len(items) // 2][2].features
    qc = contours[len(items) // 2]
    t_aos = median_time(lambda: match(q, index), repeat)
    t_hu = median_time(lambda: [cv2.matchShapes(qc, c, cv2.CONTOURS_MATCH_I1, 0) for c in contours],
                       max(5, repeat // 10))
    t_fd = median_time(lambda: match(q, index, method="fd"), repeat)
    return [
        row(f"AOS match vs {len(index)} views", t_aos, baseline="cv2.matchShapes loop", baseline_s=t_hu,
            target_s=2e-3, met=t_aos <= 2e-3),
        row(f"FD match vs {len(index)} views", t_fd, baseline="cv2.matchShapes loop", baseline_s=t_hu),
    ]


def scale_library(n_objects: int, camera, lab, rng: np.random.Generator, library_dir=None) -> tuple[dict, dict]:
    """Teach ``n_objects`` random parts cycling through boxes, plates, concave extrusions, stepped blocks
    and parts with holes (:func:`labctl.library.samples.random_part`) with teach-object's pipeline and
    the simulated lab's renderer; near-duplicates (every view matches one existing object) are drawn
    again. Returns (library, stats: per-kind counts, marker radii used, coverage per part)."""
    from ..library.placement import viewing_geometry
    from ..library.samples import PART_KINDS, random_part
    from ..library.teach import teach_object
    from ..sim.rigs import standard_view_renderer

    standoff = lab.config.viewing.standoff_mm
    view = viewing_geometry(lab)
    out: dict = {}
    kinds: dict[str, int] = {}
    duplicates = 0
    while len(out) < n_objects:
        kind = PART_KINDS[len(out) % len(PART_KINDS)]
        name = f"part{len(out):03d}_{kind}"
        obj = teach_object(name, random_part(rng, kind), radius_mm=lab.config.marker.radius_mm, view=view,
                           standoff_mm=standoff, scale_mm_per_px=mm_per_px(camera, standoff),
                           render_factory=standard_view_renderer(camera, noise_sigma=0.0), sweep=False,
                           angle_curve=False)
        if out and _indistinguishable(obj, out):
            duplicates += 1
            continue
        if library_dir is not None:
            from ..library.storage import save_object

            obj.path = save_object(library_dir, obj)
        out[name] = obj
        kinds[kind] = kinds.get(kind, 0) + 1
    radii: dict[str, int] = {}
    for o in out.values():
        for m in o.markers:
            radii[f"{m.radius:g}"] = radii.get(f"{m.radius:g}", 0) + 1
    cov = {n: o.info["coverage"]["probability"] for n, o in out.items()}
    return out, {"kinds": kinds, "redrawn_near_duplicates": duplicates, "markers_by_radius_mm": radii,
                 "views": sum(len(o.views) for o in out.values()),
                 "coverage_min": min(cov.values()), "coverage_mean": round(float(np.mean(list(cov.values()))), 4),
                 "below_full_coverage": {n: v for n, v in cov.items() if v < 1.0}}


def run(quick: bool = False) -> dict:
    """Identification rates and matching speed on the sample, generated and scale libraries (paper §3.4)."""
    from ..library.storage import load_library

    lab, camera = _setup()
    rng = np.random.default_rng(5)
    standoff = lab.config.viewing.standoff_mm
    sample = load_library(lab.library_dir)
    run_cfg = {"threshold": lab.config.run.ambiguity_threshold or DEFAULT_THRESHOLD,
               "max_views": lab.config.run.max_views,
               "gate": (lab.config.run.height_gate_mm, lab.config.run.height_gate_sigmas,
                        lab.config.run.height_gate_depth_frac)}
    res_sample = _evaluate(sample, camera, standoff, trials=2 if quick else 4, rng=rng, **run_cfg)
    gen = generated_library(30, camera, lab, rng)
    res_gen = _evaluate(gen, camera, standoff, trials=1 if quick else 2, rng=rng, **run_cfg)
    big, big_stats = scale_library(20 if quick else 100, camera, lab, np.random.default_rng(15))
    res_big = _evaluate(big, camera, standoff, trials=1, rng=rng, **run_cfg)
    timing_lib = {**gen, **big, **{k: v for k, v in sample.items()}}
    for o in sample.values():
        for mid in o.views:
            o.view_image(mid)
    rows = _timing(timing_lib, n_views=1000, repeat=50 if quick else 200)
    return {"rows": rows, "sample": res_sample, "generated": res_gen, "scale": {**res_big, **big_stats},
            "acceptance": {"sample_100pct": res_sample["rates"]["aos_with_extra_views"] == 1.0,
                           "generated_ge_99pct": res_gen["rates"]["aos_with_extra_views"] >= 0.99,
                           "scale_ge_99pct": res_big["rates"]["aos_with_extra_views"] >= 0.99,
                           "match_le_2ms_at_1000_views": rows[0]["median_s"] <= 2e-3}}


if __name__ == "__main__":  # pragma: no cover - writes a generated library for `labctl trials`
    import sys

    _lab, _cam = _setup()
    _n = int(sys.argv[2]) if len(sys.argv) > 2 else 100
    _, _stats = scale_library(_n, _cam, _lab, np.random.default_rng(15), library_dir=sys.argv[1])
    print(_stats)
