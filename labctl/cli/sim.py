"""``labctl sim serve`` and ``labctl sim snapshot``: expose and look at the simulated lab."""

from __future__ import annotations

from pathlib import Path

import click

from ..config.lab import TRAJECTORIES
from ._common import emit, get_ctx, json_option


@click.group("sim")
def sim_group() -> None:
    """The simulated lab's devices and cameras."""


@sim_group.command("serve")
@click.option("--baud", type=click.IntRange(min=1), default=None,
              help="Pace the emulators at this baud rate (default: driver files).")
@click.option("--tcp", is_flag=True, help="Serve the table and robot on TCP ports as ser2net would (socket://).")
@click.option("--lab-out", "lab_out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Write a lab whose drivers are real kinds on the served endpoints, with the served truth.")
@click.option("--force", is_flag=True, help="With --lab-out: replace an earlier served lab there.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the world (object placement, noise).")
@click.option("--object", "object_name", default=None, help="Object on the table (default: random from the library).")
@click.option("--trajectory", default="line", show_default=True,
              help="Start the table where this trajectory starts (line, arc, circle, zigzag).")
@click.option("--conveyor", type=click.Choice(TRAJECTORIES), default=None,
              help="Move the parts by the simulator itself (a conveyor labctl does not drive); with --lab-out "
                   "the lab has no table and runs --trajectory external.")
@click.option("--conveyor-delay", type=click.FloatRange(min=0), default=1.0, show_default=True,
              help="The conveyor starts once the fixed camera has been watched this long without a pause (s).")
@click.option("--speed", type=click.FloatRange(min=0.1, max=200), default=None,
              help="Conveyor speed, mm/s (default: lab.yaml run.speed_mm_s).")
@click.option("--http-port", type=click.IntRange(0, 65535), default=0, show_default=True,
              help="Port of the MJPEG streams (0: any free port).")
@click.option("--jpeg-quality", type=click.IntRange(1, 100), default=90, show_default=True)
@click.option("--fps", type=click.FloatRange(min=1, max=120), default=None,
              help="Frame rate of both served cameras (default: driver files).")
@click.option("--scene", type=click.Choice(["object", "calibration"]), default="object", show_default=True,
              help="What the table carries at first: the run's object, or the lab's calibration target "
                   "(switch later with `labctl sim place-target` / `labctl sim scene`).")
@click.option("--truth-log", "truth_log", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Append the served table's and robot's motion (moving/still, GRBL state, the robot's stop ramp; "
                   "CLOCK_MONOTONIC) to this file as JSON lines, sampled from the emulators every 10 ms.")
@json_option
def sim_serve(baud, tcp, lab_out, force, seed, object_name, trajectory, conveyor, conveyor_delay, speed, http_port,
              jpeg_quality, fps, scene, truth_log) -> None:
    """Serve the simulated lab out of process in real time, from one world, until Ctrl-C.

    The GRBL table and robot controller emulators on pseudo-terminals (or TCP ports), and both
    cameras as MJPEG-over-HTTP streams showing what the served table and robot do. The HTTP
    server's /control/scene endpoint swaps the object for the calibration target and puts it on
    a spacer (`labctl calibrate --prompt-command "labctl --lab DIR sim place-target"`).
    """
    import signal
    import time

    from ..errors import UserInputError
    from ..runtime.simlab import ServedLab, write_served_lab

    lab = get_ctx().lab()
    if not lab.is_simulated:
        raise UserInputError("sim serve serves the simulated lab: every driver file of this lab must say kind: sim")
    if trajectory not in TRAJECTORIES:
        raise UserInputError(f"--trajectory must be one of {', '.join(TRAJECTORIES)}, got {trajectory!r}")
    if object_name is not None:
        from ..library.storage import load_library

        names = sorted(load_library(lab.library_dir))
        if object_name not in names:
            raise UserInputError(f"no object {object_name!r} in the library (have: {', '.join(names)})")
    if truth_log is not None and not truth_log.parent.is_dir():
        raise UserInputError(f"--truth-log: no folder {truth_log.parent}")
    if lab_out is not None and lab_out.exists() and any(lab_out.iterdir()) and not (
            force and (lab_out / "served_truth.json").is_file()):
        raise UserInputError(f"--lab-out {lab_out} is not empty; not overwriting it")
    spec = {"seed": seed, "object_name": object_name, "trajectory": conveyor or trajectory,
            "speed_mm_s": speed or lab.config.run.speed_mm_s, "tcp": tcp, "baud": baud, "http_port": http_port,
            "jpeg_quality": jpeg_quality, "conveyor": conveyor, "conveyor_delay_s": conveyor_delay, "fps": fps,
            "scene": scene}

    def stop(signum, _frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)  # a supervisor's terminate: the same clean stop as Ctrl-C
    try:
        with ServedLab(lab, spec) as served:
            info = served.endpoints()
            if truth_log is not None:
                try:
                    served.log_truth(truth_log)
                except OSError as exc:
                    raise UserInputError(f"--truth-log {truth_log}: {exc.strerror or exc}") from None
                info["truth_log"] = str(truth_log)
            if lab_out is not None:
                info["lab_out"] = str(write_served_lab(lab, lab_out, served, force=force))
                # the served GRBL powers up in Alarm (homing on), as a real board does: home it first
                info["next"] = f"labctl --lab {info['lab_out']} table home"
            info["object"] = served.object_name

            def human(c):
                for role, where in info.items():
                    c.print(f"[bold]{role}[/]: {where}")
                c.print("Ctrl-C to stop.")

            emit(info, human)
            while True:
                time.sleep(0.2)
                served.check_alive()
    except KeyboardInterrupt:
        pass
    except RuntimeError as exc:
        from ..errors import LabctlError

        raise LabctlError(str(exc)) from None


def _scene_control_url(url: str | None, control: str = "scene") -> str:
    """``--url``, else the served lab's control endpoint from ``served_truth.json`` in the lab folder."""
    import json

    from ..errors import UserInputError

    if url:
        return url
    path = get_ctx().lab_root / "served_truth.json"
    try:
        return json.loads(path.read_text(encoding="utf-8"))["endpoints"][f"{control}_control"]
    except (OSError, ValueError, KeyError, TypeError):
        raise UserInputError(f"no served {control} control in {path} (a lab written by `labctl sim serve "
                             f"--lab-out`{' --tcp' if control == 'link' else ''}); give --url") from None


def _post_scene(url: str, **params) -> dict:
    """POST the scene change to the served lab; one-line errors (2: refused as bad input, 3: unreachable)."""
    import json
    import urllib.error
    import urllib.parse
    import urllib.request

    from ..errors import DeviceError, UserInputError

    full = f"{url}?{urllib.parse.urlencode(params)}"
    try:
        with urllib.request.urlopen(urllib.request.Request(full, method="POST"), timeout=10) as r:
            return json.loads(r.read())
    except urllib.error.HTTPError as exc:
        try:
            why = json.loads(exc.read()).get("error") or exc.reason
        except ValueError:
            why = exc.reason
        raise (UserInputError if exc.code == 400 else DeviceError)(f"the served lab refused: {why}") from None
    except (urllib.error.URLError, OSError, ValueError) as exc:
        raise DeviceError(f"cannot reach the served lab at {url}: {getattr(exc, 'reason', exc)}") from None


@sim_group.command("place-target")
@click.argument("spacer_mm", type=click.FloatRange(0, 1000))
@click.argument("index", type=int, required=False)
@click.argument("count", type=int, required=False)
@click.option("--url", default=None, help="The served lab's /control/scene URL (default: from the lab's "
              "served_truth.json).")
@json_option
def sim_place_target(spacer_mm: float, index, count, url) -> None:
    """Put the calibration target on its pins on a SPACER_MM spacer in a served lab (`sim serve`).

    The simulator's answer to `labctl calibrate`'s prompt: use it as
    `--prompt-command "labctl --lab DIR sim place-target"` (called with SPACER_MM INDEX COUNT).
    """
    info = _post_scene(_scene_control_url(url), scene="calibration", spacer_mm=f"{spacer_mm:g}")
    emit(info, lambda c: c.print(f"target on {info['spacer_mm']:g} mm" + (f" ({index}/{count})" if index else "")))


@sim_group.command("scene")
@click.argument("scene", type=click.Choice(["object", "calibration"]))
@click.option("--spacer", "spacer_mm", type=click.FloatRange(0, 1000), default=0.0, show_default=True,
              help="With calibration: the spacer under the target (mm).")
@click.option("--url", default=None, help="The served lab's /control/scene URL (default: from served_truth.json).")
@json_option
def sim_scene(scene: str, spacer_mm: float, url) -> None:
    """Switch a served lab (`sim serve`) between the run's object and the calibration target."""
    info = _post_scene(_scene_control_url(url), scene=scene, spacer_mm=f"{spacer_mm:g}")
    emit(info, lambda c: c.print(f"scene: {info['scene']}"))


@sim_group.command("link")
@click.argument("device", type=click.Choice(["table", "robot"]))
@click.argument("state", type=click.Choice(["down", "up"]))
@click.option("--reset", is_flag=True, help="Also power-cycle the controller (as a ser2net restart pulsing DTR).")
@click.option("--url", default=None, help="The served lab's /control/link URL (default: from served_truth.json).")
@json_option
def sim_link(device: str, state: str, reset: bool, url) -> None:
    """Stop or restart a device's ser2net-style bridge in a served lab (`sim serve --tcp`): a dropped link."""
    info = _post_scene(_scene_control_url(url, "link"), device=device, up="1" if state == "up" else "0",
                       **({"reset": "1"} if reset else {}))
    emit(info, lambda c: c.print(f"{device} link {'up' if info['up'] else 'down'}"
                                 + (f" (controller reset {info['resets']}×)" if info["resets"] else "")))


@sim_group.command("snapshot")
@click.option("--camera", type=click.Choice(["fixed", "mobile"]), required=True)
@click.option("--t", "t", type=float, default=0.0, show_default=True, help="Simulated time (s).")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="PNG to write.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--object", "object_name", default=None, help="Object from the library (default: random).")
@json_option
def sim_snapshot(camera: str, t: float, out: Path, seed: int, object_name: str | None) -> None:
    """Write what a simulated camera sees at time T to a PNG."""
    from ..sim.snapshot import snapshot

    info = snapshot(get_ctx().lab(), camera=camera, t=t, out=out, seed=seed, object_name=object_name)
    emit(info, lambda c: c.print(f"wrote {out}"))
