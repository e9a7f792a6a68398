"""``labctl teach-object`` and ``labctl library list|show``: parse, call, print.

Teaching renders standard views with :func:`labctl.sim.rigs.standard_view_renderer`, injected as the
library's ``render_view(T_o_c)`` (the library itself never imports the simulator).
"""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from ._common import emit, get_ctx, json_option


@click.command("teach-object")
@click.argument("name")
@click.option("--model", "model", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="CAD model (STL or OBJ, millimetres).")
@click.option("--markers", "markers", default="auto", show_default=True,
              help="'auto' to plan the markers, or a YAML file of markers (id, center, normal, radius; mm).")
@json_option
def teach_object_cmd(name: str, model: Path, markers: str) -> None:
    """Plan markers for a CAD model and build its standard views into the object library."""
    from rich.progress import Progress

    from ..library.placement import viewing_geometry
    from ..library.teach import read_markers_file, teach_object
    from ..library.views import mm_per_px
    from ..sim.rigs import standard_view_renderer
    from ..sim.truth import camera_model

    c = get_ctx()
    lab = c.lab()
    radius = lab.config.marker.radius_mm
    given = None if markers == "auto" else read_markers_file(markers, radius)
    camera = camera_model(lab.mobile_camera)
    standoff = lab.config.viewing.standoff_mm
    with Progress(console=c.console, transient=True, disable=c.json) as bar:
        task = bar.add_task("teaching", total=None)

        def progress(stage, done, total):
            bar.update(task, description=stage, completed=done, total=max(total, 1))

        obj = teach_object(name, model, radius_mm=radius, view=viewing_geometry(lab), standoff_mm=standoff,
                           scale_mm_per_px=mm_per_px(camera, standoff),
                           render_factory=standard_view_renderer(camera, noise_sigma=0.0),
                           markers=given, library_dir=lab.library_dir, progress=progress)
    data = _summary(obj)

    def human(console):
        p = obj.info["placement"]
        console.print(f"[bold]{obj.name}[/]: {len(obj.markers)} markers ({p['method']}), "
                      f"{len(obj.stable_poses)} stable poses, {len(obj.views)} standard views → {obj.path}")
        sw = obj.info["viewing_angle_sweep"]
        console.print(f"optimal initial viewing angle {sw['optimal_deg']}° (minimum-count range "
                      f"{sw['optimal_range_deg']}°); contact sheet: {obj.path / 'contact_sheet.png'}")

    emit(data, human)


def _summary(obj) -> dict:
    return {
        "name": obj.name, "path": obj.path, "extents_mm": obj.info.get("extents_mm"),
        "markers": [m.to_dict() for m in obj.markers],
        "stable_poses": [{"probability": p} for _, p in obj.stable_poses],
        "views": {int(k): {"eccentricity": v.features.eccentricity, "size_mm": v.features.size_mm}
                  for k, v in obj.views.items()},
        "placement": obj.info.get("placement"), "viewing_angle_sweep": obj.info.get("viewing_angle_sweep"),
    }


@click.group("library")
def library_group() -> None:
    """Show the object library (object_library/)."""


@library_group.command("list")
@json_option
def list_cmd() -> None:
    """List the objects of the library."""
    from ..library.storage import load_library

    lib = load_library(get_ctx().lab().library_dir)
    rows = [{"name": n, "markers": len(o.markers), "stable_poses": len(o.stable_poses), "views": len(o.views),
             "extents_mm": o.info.get("extents_mm")} for n, o in lib.items()]

    def human(console):
        from rich.table import Table

        t = Table("object", "extents (mm)", "markers", "stable poses", "views", title="object library")
        for r in rows:
            t.add_row(r["name"], " × ".join(f"{v:g}" for v in r["extents_mm"] or []), str(r["markers"]),
                      str(r["stable_poses"]), str(r["views"]))
        console.print(t)

    emit({"objects": rows}, human)


@library_group.command("show")
@click.argument("name")
@json_option
def show_cmd(name: str) -> None:
    """Show one object: markers, stable poses, standard views."""
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

    emit(data, human)
