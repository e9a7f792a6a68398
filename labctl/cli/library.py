"""``labctl teach-object`` and ``labctl library list|show``: parse, call, print.

Teaching renders standard views with :func:`labctl.sim.rigs.standard_view_renderer`, injected as the
library's ``render_view(T_o_c)`` (the library itself never imports the simulator).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import click
import numpy as np

from ..errors import UserInputError
from ._common import emit, get_ctx, json_option


def _expand_models(model: str) -> list[Path]:
    """A model file, a folder of models, or a glob of models → the STL/OBJ files, sorted."""
    import glob

    p = Path(model).expanduser()
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in (".stl", ".obj") and f.is_file())
        if not files:
            raise UserInputError(f"no STL or OBJ models in folder {p}")
        return files
    if glob.has_magic(model):
        files = sorted(Path(f) for f in glob.glob(str(p)) if Path(f).suffix.lower() in (".stl", ".obj"))
        if not files:
            raise UserInputError(f"no STL or OBJ models match {model!r}")
        return files
    return [p]


def _name_from_file(path: Path) -> str:
    import re

    name = re.sub(r"[^A-Za-z0-9_.-]", "_", path.stem).lstrip("._-") or "object"
    return name[:64]


@click.command("teach-object")
@click.argument("name", required=False)
@click.option("--model", "model", required=True,
              help="CAD model (STL or OBJ, millimetres), or a folder or a quoted glob of models (batch: each is "
                   "named after its file).")
@click.option("--markers", "markers", default="auto", show_default=True,
              help="'auto' to plan the markers, or a YAML file of markers (id, center, normal, radius; mm).")
@click.option("--force", is_flag=True, help="Replace an object of the same name (atomically).")
@click.option("--accept-partial", is_flag=True,
              help="Keep an object covered less than lab.yaml's library.min_coverage (otherwise refused, exit 1).")
@json_option
def teach_object_cmd(name: str | None, model: str, markers: str, force: bool, accept_partial: bool) -> int:
    """Plan markers for CAD models and build their standard views into the object library.

    Small faces get smaller markers; resting poses the part's symmetry makes alike are taught once.
    An object whose coverage (a tracked marker in view over random placements) is below lab.yaml's
    library.min_coverage is refused with what would fix it (exit 1), unless --accept-partial. The
    library's initial viewing angle is re-checked after.
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from ..library.placement import viewing_geometry
    from ..library.storage import check_name, library_angle, refresh_library
    from ..library.teach import CoverageRefused, read_markers_file, teach_object
    from ..library.views import mm_per_px
    from ..sim.rigs import standard_view_renderer
    from ..sim.truth import camera_model

    c = get_ctx()
    lab = c.writable_lab("a taught object")
    files = _expand_models(model)
    import glob

    batch = Path(model).expanduser().is_dir() or glob.has_magic(model)
    if batch and name is not None:
        raise UserInputError("NAME is taken from each file's name when --model is a folder or a glob; leave it out")
    if not batch and name is None:
        name = _name_from_file(files[0])
    if batch and markers != "auto":
        raise UserInputError("--markers FILE applies to one model; teach a folder or glob with --markers auto")
    # one model: NAME given or taken from its file above
    jobs = [(cast(str, name) if not batch else _name_from_file(f), f) for f in files]
    for n, _ in jobs:
        check_name(n)
    radius = lab.config.marker.radius_mm
    given = None if markers == "auto" else read_markers_file(markers, radius)
    camera = camera_model(lab.mobile_camera)
    standoff = lab.config.viewing.standoff_mm
    view = viewing_geometry(lab, angle_deg=library_angle(lab.library_dir, lab.config.viewing.initial_angle_deg))
    taught, failed, warnings = [], {}, []
    columns = [TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()]
    with Progress(*columns, console=c.console, transient=True, disable=c.json) as bar:
        total = bar.add_task("models", total=len(jobs))
        stage = bar.add_task("", total=None)
        for k, (n, f) in enumerate(jobs):
            bar.update(total, description=f"{n} ({k + 1}/{len(jobs)})", completed=k)

            def progress(what, done, tot, _n=n):
                bar.update(stage, description=f"  {what}", completed=done, total=max(tot, 1))

            try:
                obj = teach_object(n, f, radius_mm=radius, view=view, standoff_mm=standoff,
                                   scale_mm_per_px=mm_per_px(camera, standoff),
                                   render_factory=standard_view_renderer(camera, noise_sigma=0.0),
                                   markers=given, library_dir=lab.library_dir, progress=progress, force=force,
                                   sweep=not batch, pose_probability_floor=lab.config.library.pose_probability_floor,
                                   min_coverage=lab.config.library.min_coverage, accept_partial=accept_partial)
            except (UserInputError, CoverageRefused) as exc:
                if not batch:
                    raise
                failed[n] = str(exc)
                c.console.print(f"[red]✗[/] {exc}", highlight=False)
                continue
            taught.append(obj)
            for w in obj.info["warnings"]:
                warnings.append(w)
                click.echo(f"warning: {w}", err=True)
        bar.update(total, completed=len(jobs))
    lib_info = refresh_library(lab.library_dir, viewing_geometry(lab)) if taught else None
    if lib_info:  # what concerns the objects just taught, not the whole library's groups and coverage
        new = {o.name for o in taught}
        lib_info = {**lib_info,
                    "ambiguity_groups": [g for g in lib_info.get("ambiguity_groups", [])
                                         if any(t.split("#", 1)[0] in new for t in g)],
                    "coverage": {n: v for n, v in lib_info.get("coverage", {}).items() if n in new}}
    data = {"taught": [_summary(o) for o in taught], "failed": failed, "warnings": warnings, "library": lib_info}

    def human(console):
        for obj in taught:
            p, cov = obj.info["placement"], obj.info["coverage"]
            radii = ", ".join(f"{r:g}" for r in obj.info["marker_radii_mm"])
            console.print(f"[bold]{obj.name}[/]: {len(obj.markers)} markers ({p['method']}; radius {radii} mm), "
                          f"{len(obj.stable_poses)} stable poses, {len(obj.views)} standard views, coverage "
                          f"{100 * cov['probability']:.1f} % → {obj.path}")
            sw = obj.info.get("viewing_angle_sweep") or {}
            if sw.get("optimal_deg") is not None:
                console.print(f"  optimal initial viewing angle for this object alone {sw['optimal_deg']}° "
                              f"(range {sw['optimal_range_deg']}°); contact sheet: {obj.folder / 'contact_sheet.png'}")
        if lib_info:
            a, prev = lib_info["initial_angle_deg"], lib_info["previous_deg"]
            low = {n: v for n, v in lib_info["coverage"].items() if v < 1.0}
            console.print(f"library initial viewing angle {a:g}°" + (f" (was {prev:g}°)" if a != prev else "")
                          + (f"; below full coverage there: {low}" if low else "; every object fully covered there"))
        if failed:
            console.print(f"[red]{len(failed)} of {len(jobs)} models not taught[/]")

    emit(data, human)
    return 2 if failed else 0


def _summary(obj) -> dict:
    return {
        "name": obj.name, "path": obj.path, "extents_mm": obj.info.get("extents_mm"),
        "markers": [m.to_dict() for m in obj.markers],
        "stable_poses": [{"probability": p} for _, p in obj.stable_poses],
        "views": {int(k): {"eccentricity": v.features.eccentricity, "size_mm": v.features.size_mm}
                  for k, v in obj.views.items()},
        "placement": obj.info.get("placement"), "viewing_angle_sweep": obj.info.get("viewing_angle_sweep"),
        "coverage": obj.info.get("coverage"), "marker_radii_mm": obj.info.get("marker_radii_mm"),
        "source": obj.info.get("source"), "warnings": obj.info.get("warnings", []),
    }


@click.group("library")
def library_group() -> None:
    """Show the object library (object_library/)."""


@library_group.command("list")
@json_option
def list_cmd() -> None:
    """List the objects of the library (a broken object is skipped with a one-line warning)."""
    from ..library.storage import library_angle, load_library

    lab = get_ctx().lab()
    lib = load_library(lab.library_dir)
    rows: list[dict[str, Any]] = [
        {"name": n, "markers": len(o.markers), "stable_poses": len(o.stable_poses), "views": len(o.views),
         "extents_mm": o.info.get("extents_mm"), "marker_radii_mm": o.info.get("marker_radii_mm"),
         "coverage": (o.info.get("coverage") or {}).get("probability")} for n, o in lib.items()]
    angle = library_angle(lab.library_dir, lab.config.viewing.initial_angle_deg)

    def human(console):
        from rich.table import Table

        t = Table("object", "extents (mm)", "markers", "radii (mm)", "stable poses", "views", "coverage",
                  title=f"object library (initial viewing angle {angle:g}°)")
        for r in rows:
            cov = r["coverage"]
            t.add_row(r["name"], " × ".join(f"{v:g}" for v in r["extents_mm"] or []), str(r["markers"]),
                      ", ".join(f"{v:g}" for v in r["marker_radii_mm"] or []), str(r["stable_poses"]), str(r["views"]),
                      "-" if cov is None else f"{100 * cov:.1f} %")
        console.print(t)

    emit({"objects": rows, "initial_angle_deg": angle}, human)


@library_group.command("show")
@click.argument("name")
@json_option
def show_cmd(name: str) -> None:
    """Show one object: markers, stable poses, standard views, coverage."""
    from ..library.storage import check_name, load_object

    obj = load_object(get_ctx().lab().library_dir / check_name(name))
    data = _summary(obj)

    def human(console):
        from rich.table import Table

        console.print(f"[bold]{obj.name}[/] {obj.path}")
        t = Table("marker", "center (mm)", "normal", "radius", "ε", "size (mm)")
        for m in obj.markers:
            f = obj.views[m.id].features
            t.add_row(str(m.id), str(np.round(m.center, 1).tolist()), str(np.round(m.normal, 3).tolist()),
                      f"{m.radius:g}", f"{f.eccentricity:.3f}", f"{f.size_mm:.1f}")
        console.print(t)
        console.print("stable poses: " + ", ".join(f"{p:.3f}" for _, p in obj.stable_poses))
        cov = obj.info.get("coverage")
        if cov:
            console.print(f"coverage {100 * cov['probability']:.1f} % (initial view {100 * cov['initial_view']:.1f} %, "
                          f"tracked {100 * cov['tracked']:.1f} %)")
        for w in obj.info.get("warnings", []):
            console.print(f"[yellow]warning:[/] {w}", highlight=False)

    emit(data, human)


@library_group.command("remove")
@click.argument("name")
@json_option
def remove_cmd(name: str) -> None:
    """Delete one object from the library; the library's viewing angle is re-checked."""
    from ..library.placement import viewing_geometry
    from ..library.storage import refresh_library, remove_object

    lab = get_ctx().writable_lab("a library change")
    path = remove_object(lab.library_dir, name)
    info = refresh_library(lab.library_dir, viewing_geometry(lab))
    emit({"removed": name, "path": path, "library": info},
         lambda console: console.print(f"removed {name} ({path}); library initial viewing angle "
                                       f"{info['initial_angle_deg']:g}°"))


@library_group.command("check")
@json_option
def check_cmd() -> int:
    """Validate every object: one line per problem naming the object, the file and the problem (exit 2 if any)."""
    from ..library.storage import check_library

    lab = get_ctx().lab()
    ok, problems = check_library(lab.library_dir, min_coverage=lab.config.library.min_coverage)

    if not get_ctx().json:  # the problems go to stderr however stdout is read (terminal or pipe)
        for line in problems:
            click.echo(line, err=True)
    emit({"ok": ok, "problems": problems},
         lambda console: console.print(f"{len(ok)} objects ok, {len(problems)} problems"))
    return 2 if problems else 0
