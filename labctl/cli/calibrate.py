"""``labctl calibrate``: Tsai calibration of both cameras, hand-eye, table registration;
``labctl calibrate points FILE``: Tsai on a correspondence file. Parse, call, print."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from ._common import emit, get_ctx, json_option


def _human_report(rep: dict):
    def show(c):
        for key in ("fixed_camera", "table", "mobile_camera"):
            if key not in rep:
                continue
            r = rep[key]
            line = f"[bold]{key}[/]:"
            if "rms_px" in r:
                line += f" RMS {r['rms_px']:.4f} px (max {r['max_px']:.4f}), {r['n_points']} points"
            if "rms_mm" in r:
                line += f" fit RMS {r['rms_mm']:.4f} mm, scale {r['scale'][0]:.5f}/{r['scale'][1]:.5f}"
            c.print(line)
            err = r.get("error_vs_truth")
            if err:
                c.print("   vs ground truth: " + ", ".join(f"{k}={_fmt(v)}" for k, v in err.items()))
        for f in rep.get("files", []):
            c.print(f"wrote {f}")
    return show


def _fmt(v):
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items()) + "}"
    return f"{v:.4g}" if isinstance(v, float) else str(v)


@click.group("calibrate", invoke_without_command=True)
@click.option("--camera", type=click.Choice(["fixed", "mobile", "all"]), default="all", show_default=True,
              help="fixed: C1 and table registration; mobile: C2 and hand-eye; all: both.")
@click.option("--ros", is_flag=True, help="Also write ROS camera_info YAML for each calibrated camera.")
@click.option("--full", is_flag=True, help="Optimise the image centre too (default: held at nominal).")
@click.option("--seed", type=int, default=0, show_default=True, help="Sensor-noise seed of the simulated lab.")
@json_option
@click.pass_context
def calibrate_group(ctx: click.Context, camera: str, ros: bool, full: bool, seed: int) -> None:
    """Calibrate the lab: Tsai for both cameras, hand-eye of the mobile one, table registration."""
    if ctx.invoked_subcommand is not None:
        return
    from rich.progress import Progress

    from ..calibration.run import Truth, lab_target, run_lab_calibration, steps_for
    from ..errors import LabctlError
    from ..geometry import make_T
    from ..sim import truth
    from ..sim.rigs import CalibrationRig

    c = get_ctx()
    lab = c.lab()
    if not lab.is_simulated:
        raise LabctlError("image capture for calibration on hardware is not built yet: capture the dot target, "
                          "then use `labctl calibrate points FILE`")
    target = lab_target(lab.calibration_dir)
    rig = CalibrationRig(lab, target, seed=seed)
    tr = Truth(rig.c1, rig.T_w_c1, rig.c2, rig.X, make_T(None, lab.table.origin_w_mm))
    with Progress(console=c.console, transient=c.json) as bar:
        task = bar.add_task("calibrating", total=steps_for(camera, target, 10))
        rep = run_lab_calibration(
            lab.calibration_dir, rig, target, nominal_fixed=truth.camera_model(lab.fixed_camera),
            nominal_mobile=truth.camera_model(lab.mobile_camera), X_nominal=truth.hand_eye(lab.mobile_camera),
            robot_workspace=(lab.robot.workspace_min_mm, lab.robot.workspace_max_mm), cameras=camera, ros=ros,
            full=full, truth=tr, progress=lambda msg: bar.update(task, advance=1, description=msg))
    emit(rep, _human_report(rep))


@calibrate_group.command("points")
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--sensor", nargs=4, type=float, required=True, metavar="NCX NFX DX DY",
              help="Sensor elements in x, frame-buffer pixels per line, element size x and y (mm).")
@click.option("--center", nargs=2, type=float, required=True, metavar="CX CY",
              help="Nominal image centre (px); held fixed unless --full.")
@click.option("--full", is_flag=True, help="Optimise every parameter, image centre included.")
@click.option("--coplanar", is_flag=True, help="The points lie on one plane (Tsai's coplanar method).")
@json_option
def calibrate_points(file: Path, sensor, center, full: bool, coplanar: bool) -> None:
    """Tsai calibration from FILE with lines 'xw yw zw Xf Yf' (mm, px); OpenCV's result beside it."""
    from ..calibration.run import calibrate_points_file

    ncx, nfx, dx, dy = sensor
    out = calibrate_points_file(file, ncx=ncx, nfx=nfx, dx=dx, dy=dy, cx=center[0], cy=center[1], full=full,
                                coplanar=coplanar)

    def human(c):
        c.print(f"[bold]{out['method']}[/] on {out['n_points']} points: RMS {out['rms_px']:.4f} px, "
                f"max {out['max_px']:.4f} px")
        c.print(f"f = {out['f_mm']:.4f} mm, kappa1 = {out['kappa1']:.5g} /mm², sx = {out['sx']:.6f}, "
                f"centre = ({out['cx']:.2f}, {out['cy']:.2f}) px")
        c.print(f"T = ({', '.join(f'{v:.3f}' for v in out['T'])}) mm")
        cv = out.get("opencv", {})
        if "rms_px" in cv:
            K = np.asarray(cv["K"])
            c.print(f"OpenCV calibrateCamera: RMS {cv['rms_px']:.4f} px, fx {K[0, 0]:.2f}, fy {K[1, 1]:.2f}, "
                    f"c = ({K[0, 2]:.2f}, {K[1, 2]:.2f}), k1 {cv['dist'][0]:.4g}")

    emit(out, human)
