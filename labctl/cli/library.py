"""``labctl teach-object`` and ``labctl library list|show``: parse, call, print.

The only glue here is :func:`sim_render_factory`, which wires the simulated lab's renderer into
the library's injected ``render_view(T_o_c)`` (the library itself never imports the simulator).
"""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from ._common import emit, get_ctx, json_option


def sim_render_factory(camera, *, noise_sigma: float = 2.0, rng=None, table_origin=(0.0, 0.0),
                       pose_choice: str = "upright", random_yaw: bool = False):
    """``(mesh_o, markers, stable_poses=None) -> render_view(T_o_c) -> BGR`` with ``labctl.sim.render``.

    Renders what the robot's mobile camera sees in the simulated lab: the object rests on the
    table in a stable pose that puts the camera above the table
    (:func:`labctl.library.views.resting_pose_for_view`, ``pose_choice`` "upright" when teaching,
    "random" for benchmark queries; ``random_yaw`` turns it about the vertical), the camera at
    ``T_o_c`` in the object frame, the textured table as background. If no stable pose puts the
    camera above the table, the object is turned so that the view looks straight down and set
    on the table by its lowest point (the only way to take that view).
    """
    from ..geometry import make_T, rotvec_to_matrix
    from ..library.model import stable_poses as compute_stable_poses
    from ..library.views import resting_pose_for_view
    from ..sim.render import MarkerDisc, Mesh, TableSurface, render

    rng = rng if rng is not None else np.random.default_rng(0)
    table = TableSurface(origin_w=table_origin)

    def factory(mesh_o, markers, stable_poses=None):
        V = np.asarray(mesh_o.vertices, float)
        F = np.asarray(mesh_o.faces)
        poses = stable_poses if stable_poses is not None else compute_stable_poses(mesh_o)

        def render_view(T_o_c):
            yaw = float(rng.uniform(-np.pi, np.pi)) if random_yaw else 0.0
            T_w_o = resting_pose_for_view(poses, T_o_c, yaw_rad=yaw, choice=pose_choice, rng=rng)
            if T_w_o is None:
                axis = T_o_c[:3, 2]  # optical axis in O, turned to −z of W
                target = np.array([0.0, 0.0, -1.0])
                v = np.cross(axis, target)
                s, c = np.linalg.norm(v), float(axis @ target)
                R = rotvec_to_matrix(v / s * np.arctan2(s, c)) if s > 1e-12 else (
                    np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0]))
                Vr = V @ R.T
                T_w_o = make_T(R, [-Vr[:, 0].mean(), -Vr[:, 1].mean(), -Vr[:, 2].min()])
            Vw = V @ T_w_o[:3, :3].T + T_w_o[:3, 3]
            discs = [MarkerDisc(T_w_o[:3, :3] @ m.center + T_w_o[:3, 3], T_w_o[:3, :3] @ m.normal, m.radius)
                     for m in markers]
            return render(camera, T_w_o @ T_o_c, [Mesh(Vw, F, markers=discs)], table=table,
                          noise_sigma=noise_sigma, rng=rng).image

        return render_view

    return factory


def _viewing(lab):
    from ..library.placement import ViewingGeometry

    v = lab.config.viewing
    cam = lab.fixed_camera
    height = 1800.0  # paper §5.2: the fixed camera 1.8 m above the table
    if getattr(cam, "eye_w_mm", None) is not None:
        height = float(cam.eye_w_mm[2]) - float(lab.table.origin_w_mm[2])
    return ViewingGeometry(angle_deg=v.initial_angle_deg, distance_mm=v.initial_distance_mm,
                           max_obliquity_deg=v.max_obliquity_deg, overhead_distance_mm=height)


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

    from ..library.teach import read_markers_file, teach_object
    from ..library.views import mm_per_px
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

        obj = teach_object(name, model, radius_mm=radius, view=_viewing(lab), standoff_mm=standoff,
                           scale_mm_per_px=mm_per_px(camera, standoff),
                           render_factory=sim_render_factory(camera, noise_sigma=0.0),
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
