"""``labctl calibrate``: Tsai calibration of both cameras, hand-eye, table registration, through
the device interfaces (simulator or hardware), stopping the devices on every exit path;
``labctl calibrate target``: a printable target; ``labctl calibrate points FILE``: Tsai on a
correspondence file. Parse, call, print."""

from __future__ import annotations

import contextlib
from pathlib import Path

import click
import numpy as np

from ._common import emit, get_ctx, json_option
from .signals import catch_stop_signals, ignore_stop_signals, restore_signals


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
        fx = rep.get("fixed_camera", {}).get("error_vs_truth")
        he = rep.get("mobile_camera", {}).get("error_vs_truth")
        if fx or he:
            parts = []
            if fx:
                parts.append(f"fixed camera {fx['table_plane']['max_percent_of_fov']:.4f} % of the field of view "
                             f"({fx['table_plane']['max_mm']:.3f} mm)")
            if he:
                h = he["hand_eye"]
                parts.append(f"hand-eye {h['rotation_deg']:.4f}°, {h['translation_mm']:.3f} mm")
            c.print("[bold]error vs ground truth:[/] " + "; ".join(parts))
        c.print(f"{rep.get('images', 0)} images kept in {rep.get('captures')}")
        for f in rep.get("files", []):
            c.print(f"wrote {f}")
        if rep.get("scene_restored"):
            c.print("the served lab's object is back on the table", highlight=False)
        c.print(f"next: {rep.get('next') or 'labctl run --trajectory line'}", highlight=False)
    return show


def _fmt(v):
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items()) + "}"
    return f"{v:.4g}" if isinstance(v, float) else str(v)


class PromptRefused(Exception):
    """Nobody placed the target: the prompt was refused or not answered. Nothing moves at a prompt (the
    robot is back at its start), so the devices are read, not stopped: a STOP would latch a fault on the
    robot's controller that only ``labctl robot clear`` releases."""

    def __init__(self, error: Exception):
        super().__init__(str(error))
        self.error = error


class TerminalPrompt:
    """The procedure's prompt on hardware: asks on the console (above the progress bar), waits
    for Enter on stdin."""

    def __init__(self, console=None):
        self.console = console

    def place_target(self, spacer_mm: float, index: int, count: int) -> None:
        """Ask for the target on spacer ``spacer_mm`` (mm), wait for Enter; UserInputError if stdin is closed."""
        import sys

        from ..errors import UserInputError

        where = "directly on the carriage (no spacer)" if spacer_mm == 0 else f"on the {spacer_mm:g} mm spacer"
        text = (f"[{index + 1}/{count}] put the calibration target on its locating pins {where}, "
                "then press Enter (Ctrl-C stops)")
        if self.console is not None:
            self.console.print(text, markup=False, highlight=False)
        else:
            click.echo(text, err=True)
        if not sys.stdin.readline():
            raise PromptRefused(UserInputError("no answer to the prompt (stdin closed): the target's placement "
                                               "was not confirmed"))


class CommandPrompt:
    """The procedure's prompt answered by a program: ``CMD SPACER_MM INDEX COUNT`` places the
    target (an out-of-process simulator's hook, a fixture robot); a non-zero exit refuses."""

    def __init__(self, command: str):
        import shlex

        self.argv = shlex.split(command)

    def place_target(self, spacer_mm: float, index: int, count: int) -> None:
        """Run ``CMD SPACER_MM INDEX COUNT`` (index from 1); UserInputError if it fails or exits non-zero."""
        import subprocess

        from ..errors import UserInputError

        try:
            done = subprocess.run([*self.argv, f"{spacer_mm:g}", str(index + 1), str(count)], stdin=subprocess.DEVNULL,
                                  capture_output=True, text=True, timeout=600)
        except (OSError, subprocess.TimeoutExpired) as exc:
            raise PromptRefused(UserInputError(f"--prompt-command failed: {exc}")) from None
        if done.returncode != 0:
            why = (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
            raise PromptRefused(UserInputError(f"--prompt-command did not place the target on {spacer_mm:g} mm: "
                                               f"{why}"))


class ServedPrompt:
    """The prompt answered by a served lab (``labctl sim serve``) itself: its ``/control/scene`` puts the
    target on the spacer, and :meth:`restore` puts the run's object back afterwards."""

    def __init__(self, url: str):
        self.url = url
        self.placed = False

    def place_target(self, spacer_mm: float, index: int, count: int) -> None:
        """Put the calibration target on its pins on a ``spacer_mm`` spacer (mm) in the served world."""
        from .sim import _post_scene

        try:
            _post_scene(self.url, scene="calibration", spacer_mm=f"{spacer_mm:g}")
        except Exception as exc:  # noqa: BLE001 — a served lab that does not answer is a refused prompt
            raise PromptRefused(exc) from None
        self.placed = True

    def restore(self) -> bool:
        """Put the run's object back on the table (once the target was placed); whether it was."""
        from .sim import _post_scene

        if not self.placed:
            return False
        _post_scene(self.url, scene="object", spacer_mm="0")
        self.placed = False
        return True


def served_scene_url(lab) -> str | None:
    """The served lab's scene control (``served_truth.json`` beside ``lab.yaml``, written by ``labctl sim serve
    --lab-out``), or None for any other lab."""
    import json

    try:
        return str(json.loads((Path(lab.root) / "served_truth.json").read_text())["endpoints"]["scene_control"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _read_still(devs) -> str:
    """After a refused prompt: read both devices back without stopping them (nothing moves at a prompt); a
    device found moving is stopped (:func:`_confirm_stopped`)."""
    parts = []
    table, robot = devs.table, devs.robot
    moving = False
    if table is not None:
        try:
            st = table.status()
            moving |= not st.state.startswith(("Idle", "Alarm", "Check"))
            parts.append(f"table still ({st.state})")
        except Exception as exc:  # noqa: BLE001
            parts.append(f"table status NOT read ({type(exc).__name__}: {exc})")
            moving = True
    if robot is not None:
        try:
            moving |= robot.status().moving
            parts.append("robot still, no STOP sent")
        except Exception as exc:  # noqa: BLE001
            parts.append(f"robot status NOT read ({type(exc).__name__}: {exc})")
            moving = True
    return _confirm_stopped(devs) if moving else ", ".join(parts) or "no device was opened"


def _confirm_stopped(devs, settle_s: float = 2.0) -> str:
    """Stop the table (GRBL feed hold, then soft reset: ``Table.stop``) and the robot (``STOP``),
    then read both back until they report rest (bounded by ``settle_s`` on the devices' clock).
    Returns what was confirmed, for the one line printed."""
    parts = []
    table, robot = devs.table, devs.robot
    if table is not None:
        try:
            table.stop()
            st = table.status()
            parts.append(f"table stopped ({st.state} at {st.position[0]:.3f}, {st.position[1]:.3f})")
        except Exception as exc:  # noqa: BLE001 - reported in the one line, the exit status stays
            parts.append(f"table stop NOT confirmed ({type(exc).__name__}: {exc})")
    if robot is not None:
        try:
            robot.stop()
            deadline = devs.clock.now() + settle_s
            while (st := robot.status()).moving and devs.clock.now() < deadline:
                devs.clock.sleep(0.05)  # STOP brings the arm to rest with a short quintic
            parts.append("robot stopped" if not st.moving else f"robot STILL MOVING after {settle_s:g} s")
        except Exception as exc:  # noqa: BLE001
            parts.append(f"robot stop NOT confirmed ({type(exc).__name__}: {exc})")
    return ", ".join(parts) or "nothing was moving"


def _latch_left(devs, lab) -> str | None:
    """After :func:`_confirm_stopped`: the phrase naming a fault the robot's controller reported latched at its
    last status (its STOP), if that controller outlives the command (not the built-in simulated lab's)."""
    from ..runtime.stopping import latch_note

    robot = devs.robot if devs is not None else None
    fault = getattr(robot, "latched", None) if robot is not None and lab.robot.kind != "sim" else None
    return latch_note(fault) if fault else None


def _open_devices(lab, cameras: str, seed: int, target, prompt_command: str | None = None, console=None, *,
                  home: bool = False, ask: bool = False):
    """(Devices, prompt, truth or None, closer) for ``lab``: the coupled in-process simulator when
    every device is simulated, else the real drivers (mixing the two cannot work: a simulated
    camera would not see a real table). ``home``: home a table found in Alarm (else that is an error
    naming the command that homes it). The prompt: ``prompt_command``, else a served lab's own scene
    control unless ``ask``, else the terminal."""

    from ..calibration.procedure import Devices
    from ..calibration.run import Truth
    from ..drivers.clock import MONOTONIC
    from ..errors import UserInputError
    from ..runtime.devices import check_robot_limits, check_table_settings, open_device

    roles = ["table", "fixed_camera"] if cameras == "fixed" else ["table", "robot", "fixed_camera", "mobile_camera"]
    if cameras == "mobile":
        roles.remove("fixed_camera")
    kinds = {r: getattr(lab, r).kind for r in roles}
    if all(k == "sim" for k in kinds.values()):
        from ..sim.rigs import SimCalibrationLab

        sim = SimCalibrationLab(lab, target, seed=seed)
        sim.open()
        devs = Devices(table=sim.table, robot=sim.robot if "robot" in roles else None, fixed=sim.cameras["fixed"],
                       mobile=sim.cameras["mobile"], clock=sim.clock)
        return devs, sim, Truth(**sim.truth()), sim.close
    if any(k == "sim" for k in kinds.values()):
        raise UserInputError("calibration needs the devices all simulated or all real, not "
                             + ", ".join(f"{r}: {k}" for r, k in kinds.items()))
    opened = {}
    homing = False
    try:
        for r in roles:
            dev = open_device(r, lab)
            dev.open()
            opened[r] = dev
        table = opened["table"]
        if table.status().state.startswith("Alarm"):  # GRBL powers up homing-locked, as the served one does
            from ..drivers.grbl import GrblTable
            from ..errors import DeviceError

            if not home or not isinstance(table, GrblTable):
                raise DeviceError(f"table: in Alarm (position unknown; GRBL powers up locked until homed): "
                                  f"next: labctl --lab {lab.root} calibrate --home (homes it, then calibrates)")
            homing = True
            table.home()
            homing = False
        # before anything moves: a fault latched on the robot's controller (a STOP of an earlier command) would
        # refuse the first station only after the table has moved the target through the fixed camera's positions
        if "robot" in opened:
            opened["robot"].ensure_ready()
        # ... and the target's positions and the robot's stations must be moves the devices accept
        check_table_settings(opened["table"], lab)
        if "robot" in opened:
            check_robot_limits(opened["robot"], lab)
    except BaseException:
        if homing:  # Ctrl-C or a fault during the homing cycle: the table must not go on moving
            with contextlib.suppress(Exception):
                opened["table"].stop()
        for dev in opened.values():
            with contextlib.suppress(Exception):
                dev.close()
        raise

    def close():
        for dev in opened.values():
            with contextlib.suppress(Exception):
                dev.close()

    devs = Devices(table=opened["table"], robot=opened.get("robot"), fixed=opened.get("fixed_camera"),
                   mobile=opened.get("mobile_camera"), clock=MONOTONIC)
    url = served_scene_url(lab) if not (prompt_command or ask) else None
    prompt = CommandPrompt(prompt_command) if prompt_command else ServedPrompt(url) if url else TerminalPrompt(console)
    return devs, prompt, None, close


@click.group("calibrate", invoke_without_command=True)
@click.option("--camera", type=click.Choice(["fixed", "mobile", "all"]), default="all", show_default=True,
              help="fixed: C1 (needs a table registration); mobile: C2, hand-eye and table registration; all: both.")
@click.option("--dry-run", is_flag=True, help="List the planned table positions and robot poses and check them "
              "against the table's travel, the robot's workspace and the cameras' views; nothing moves.")
@click.option("--ros", is_flag=True, help="Also write ROS camera_info YAML for each calibrated camera.")
@click.option("--full", is_flag=True, help="Optimise the image centre too (default: held at nominal).")
@click.option("--seed", type=int, default=0, show_default=True, help="Sensor-noise seed of the simulated lab.")
@click.option("--prompt-command", default=None, metavar="CMD",
              help="Instead of asking on the terminal, run 'CMD SPACER_MM N COUNT' to place the target (real kinds).")
@click.option("--home", is_flag=True, help="Home the table first (GRBL's $H) if it is in Alarm, as a served or "
              "freshly powered GRBL is.")
@click.option("--ask", is_flag=True, help="On a served lab (`sim serve --lab-out`), ask on the terminal instead of "
              "placing the target through the served lab.")
@click.option("--truth", "truth_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Compare with this ground truth (served_truth.json of `labctl sim serve --lab-out`).")
@json_option
@click.pass_context
def calibrate_group(ctx: click.Context, camera: str, dry_run: bool, ros: bool, full: bool, seed: int,
                    prompt_command: str | None, home: bool, ask: bool, truth_file: Path | None) -> None:
    """Calibrate the lab through its devices: the fixed camera (Tsai, target moved by the table at
    one or more spacer heights), the mobile camera and its hand-eye (robot stations), the table's
    registration. The same procedure runs on the simulated lab and on hardware. On a served lab
    (`labctl sim serve --lab-out`) the served lab places the target itself, is checked against its
    truth, and gets its object back afterwards."""
    if ctx.invoked_subcommand is not None:
        return
    from rich.progress import Progress

    from ..calibration.run import (
        lab_target,
        load_truth,
        make_plan,
        nominal_for,
        plan_report,
        run_lab_calibration,
        steps_for,
    )
    from ..calibration.target import TargetError
    from ..errors import LabctlError, UserInputError

    c = get_ctx()
    lab = c.lab()
    try:
        target = lab_target(lab.calibration_dir)
    except TargetError as exc:
        raise UserInputError(str(exc)) from None
    nominal = nominal_for(lab)
    if lab.arm is not None:  # the robot is an arm: every station (and the registration after them) within its reach
        from dataclasses import replace

        from ..planning.arm import ArmModel
        from ..planning.arm_plan import ArmCheckSettings, ArmPlanner, StationReach

        planner = ArmPlanner(ArmModel.from_config(lab.arm), ArmCheckSettings.from_run(lab.config.run))
        nominal = replace(nominal, reach=StationReach(planner))
    if dry_run:
        rep = plan_report(target, nominal, camera)
        emit(rep, _plan_human(rep))
        if not rep["ok"]:
            raise UserInputError(f"the calibration plan does not fit the lab: {rep['problems'][0]}")
        return
    plan = make_plan(target, nominal, camera)
    served = served_scene_url(lab) is not None and not (prompt_command or ask)
    if truth_file is None and served:
        truth_file = Path(lab.root) / "served_truth.json"
    given_truth = load_truth(truth_file) if truth_file is not None else None
    if plan.problems:
        raise UserInputError(f"the calibration plan does not fit the lab: {plan.problems[0]}")
    # Ctrl-C, SIGTERM and SIGHUP all end in the stop below, even if the parent started us ignoring SIGINT
    old_signals = catch_stop_signals()
    devs = None
    close = None
    prompt = None
    try:
        devs, prompt, truth, close = _open_devices(lab, camera, seed, target, prompt_command, c.console, home=home,
                                                   ask=ask)
        truth = given_truth or truth
        with Progress(console=c.console, transient=c.json) as bar:
            task = bar.add_task("calibrating", total=steps_for(plan))
            rep = run_lab_calibration(lab.calibration_dir, devs, prompt, target, nominal, cameras=camera, ros=ros,
                                      full=full, truth=truth,
                                      progress=lambda msg: bar.update(task, advance=1, description=msg))
    except BaseException as exc:
        # stop on every exit path; a second Ctrl-C/TERM must not cut the stop short
        ignore_stop_signals()
        refused = isinstance(exc, PromptRefused)
        if devs is None:
            said = "no device was opened"
        else:  # nothing moves at a prompt: a refusal reads the devices, it sends no STOP to latch
            said = _read_still(devs) if refused else _confirm_stopped(devs)
        latched = _latch_left(devs, lab)
        if isinstance(prompt, ServedPrompt):
            with contextlib.suppress(Exception):
                prompt.restore()
        if close is not None:
            with contextlib.suppress(Exception):
                close()
        if isinstance(exc, KeyboardInterrupt):
            click.echo(f"labctl: interrupted: {said}" + (f"; {latched}" if latched else ""), err=True)
            raise SystemExit(130) from None
        if isinstance(exc, PromptRefused):
            err = exc.error if isinstance(exc.error, LabctlError) else UserInputError(str(exc.error))
            raise type(err)(f"{err}; {said}" + (f"; {latched}" if latched else "")) from None
        if latched and isinstance(exc, LabctlError):  # a device fault: still one line
            exc.args = (f"{exc}; {latched}",)
        raise
    finally:
        restore_signals(old_signals)
    if isinstance(prompt, ServedPrompt):
        rep["scene_restored"] = prompt.restore()  # the next run finds its object, not the target
    if close is not None:
        close()
    rep["next"] = f"labctl --lab {lab.root} run --trajectory line"
    emit(rep, _human_report(rep))


def _plan_human(rep: dict):
    def show(c):
        def xy(p):
            return f"{p[0]:g}, {p[1]:g}"

        for f in rep["fixed"]:
            c.print(f"fixed camera  table {xy(f['table_xy_mm'])}  spacer {f['spacer_mm']:g} mm")
        rb = rep["robot"]
        if rb["stations"]:
            c.print(f"robot stations (table {xy(rb['table_xy_mm'])}, spacer {rb['spacer_mm']:g} mm):")
        for i, s in enumerate(rb["stations"]):
            c.print(f"  {i + 1:2d}  flange {xy(s['xyz_mm'])}, {s['xyz_mm'][2]:g}  tilt {s['tilt_deg']:g}°")
        for r in rep["registration"]:
            c.print(f"registration  table {xy(r['table_xy_mm'])}  flange {xy(r['flange']['xyz_mm'])}, "
                    f"{r['flange']['xyz_mm'][2]:g}")
        for p in rep["problems"]:
            c.print(f"[red]problem:[/] {p}")
        if rep["ok"]:
            c.print("plan OK: every pose is inside the table's travel and the robot's workspace")
    return show


@calibrate_group.command("target")
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="FILE.svg or FILE.pdf; the geometry file FILE.yaml is written beside it.")
@click.option("--cols", type=click.IntRange(3, 60), default=None, help="Dots across (default: the lab's target).")
@click.option("--rows", type=click.IntRange(3, 60), default=None, help="Dots down.")
@click.option("--pitch", "pitch_mm", type=click.FloatRange(1.0, 500.0), default=None, help="Dot pitch, mm.")
@click.option("--radius", "dot_radius_mm", type=click.FloatRange(0.2, 200.0), default=None, help="Dot radius, mm.")
@json_option
def calibrate_target(out: Path, cols, rows, pitch_mm, dot_radius_mm) -> None:
    """Write a printable, true-scale plane dot target (SVG in mm units, or PDF) and its geometry
    file (dot centres in the target frame, mm) for calibration/target.yaml."""
    from dataclasses import replace

    from ..calibration.run import lab_target
    from ..calibration.target import PlaneTarget, TargetError, target_pdf, target_svg, target_yaml
    from ..errors import UserInputError
    from ..fsutil import atomic_write_bytes, atomic_write_text

    suffix = out.suffix.lower()
    if suffix not in (".svg", ".pdf"):
        raise UserInputError(f"--out must end in .svg or .pdf, not {out.name!r}")
    try:
        base = lab_target(get_ctx().lab().calibration_dir)
    except Exception:  # noqa: BLE001 - no lab or no plane target: start from the default
        base = PlaneTarget()
    if not isinstance(base, PlaneTarget):
        base = PlaneTarget()
    kw = {k: v for k, v in {"cols": cols, "rows": rows, "pitch_mm": pitch_mm, "dot_radius_mm": dot_radius_mm}.items()
          if v is not None}
    target = replace(base, **kw)
    if kw and {"cols", "rows"} & set(kw):  # the default fiducials may not fit a smaller grid
        c_, r_ = target.cols - 1, target.rows - 1
        fid = ((0, 0), (min(3, c_), 0), (0, min(2, r_)), (c_, r_), (max(c_ - 2, 1), r_ - 1))
        target = replace(target, fiducials=fid)
    try:
        target.check()
    except TargetError as exc:
        raise UserInputError(f"target: {exc}") from None
    geometry = out.with_suffix(".yaml")
    try:
        if suffix == ".svg":
            atomic_write_text(out, target_svg(target))
        else:
            atomic_write_bytes(out, target_pdf(target))
        atomic_write_text(geometry, target_yaml(target, with_dots=True))
    except OSError as exc:
        raise UserInputError(f"cannot write {out}: {exc}") from None
    rep = {"drawing": str(out), "geometry": str(geometry), "size_mm": [target.width_mm, target.length_mm],
           "dots": len(target.dot_table())}
    emit(rep, lambda c: c.print(f"wrote {out} ({target.width_mm:g} × {target.length_mm:g} mm, print at 100 %) and "
                                f"{geometry}; copy the geometry file to the lab's calibration/target.yaml"))


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
