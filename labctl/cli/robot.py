"""``labctl robot …``: the robot controller's dialect, from the host side.

``labctl robot conformance --port PORT`` runs the conformance suite of docs/protocols/robot.md
against any controller (a lab's bridge, the reference served by ``labctl sim serve``) and prints
PASS/FAIL per named rule. Exit 0 all pass, 1 some fail, 3 cannot talk to the controller.

``labctl robot clear`` clears a fault latched on the lab's controller (a ``STOP`` from a stopped
run, a watchdog trip): a run refuses to start while one is latched. It moves nothing.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import click

from ._common import emit, get_ctx, json_option, to_json


@click.group("robot")
def robot_group() -> None:
    """The robot controller: conformance of its dialect; clearing a latched fault."""


@robot_group.command("conformance")
@click.option("--port", required=True, help="Serial port or pyserial URL of the controller.")
@click.option("--baud", type=click.IntRange(min=1), default=9600, show_default=True)
@click.option("--no-motion", is_flag=True, help="Only framing and error replies; never command motion.")
@click.option("--only", "only", multiple=True, metavar="GLOB",
              help="Run only rules matching GLOB (repeatable), e.g. 'watchdog.*'.")
@click.option("--timeout", "timeout_s", type=click.FloatRange(min=0.05), default=2.0, show_default=True,
              help="Seconds to wait for each reply.")
@click.option("--arm", "arm_file", type=click.Path(dir_okay=False, exists=True, path_type=Path), default=None,
              help="The arm's kinematics file (drivers/arms/*.yaml) for the 1.3 arm rules (default: the lab's "
                   "robot.yaml arm, at its mount).")
@json_option
def conformance_cmd(port: str, baud: int, no_motion: bool, only: tuple[str, ...], timeout_s: float,
                    arm_file: Path | None) -> int:
    """Check a robot controller against docs/protocols/robot.md; PASS/FAIL per rule."""
    import dataclasses

    from ..config.arm import load_arm
    from ..conformance.robot import ArmKinematics, CannotTalk, run_suite

    ctx = get_ctx()
    arm_cfg = load_arm(arm_file) if arm_file is not None else ctx.lab().arm
    arm = ArmKinematics.from_mapping(dataclasses.asdict(arm_cfg)) if arm_cfg is not None else None

    def show(res) -> None:
        if not ctx.json:
            click.echo(f"{res.status:4}  {res.rule:26} {res.detail}")
            sys.stdout.flush()

    try:
        results = run_suite(port, baud, no_motion=no_motion, only=list(only), log=show, timeout_s=timeout_s,
                            arm=arm)
    except CannotTalk as exc:
        click.echo(f"labctl: error: robot controller on {port}: {exc}", err=True)
        return 3
    failed = [r for r in results if r.status == "FAIL"]
    if ctx.json:
        sys.stdout.write(to_json({"port": port, "passed": not failed,
                                  "results": [r.__dict__ for r in results]}) + "\n")
    else:
        n_pass = sum(r.status == "PASS" for r in results)
        n_skip = sum(r.status == "SKIP" for r in results)
        click.echo(f"{n_pass} passed, {len(failed)} failed, {n_skip} skipped"
                   + (f": {', '.join(r.rule for r in failed)}" if failed else ""))
    return 1 if failed else 0


@robot_group.command("clear")
@click.option("--port", default=None, help="Serial port or pyserial URL (default: the lab's robot port).")
@click.option("--baud", type=click.IntRange(min=1), default=None, help="Baud rate (default: the lab's).")
@json_option
def clear_cmd(port: str | None, baud: int | None) -> None:
    """Clear a fault latched on the robot controller (a STOP, a watchdog trip), after checking the arm.

    Reads STATUS, sends CLEAR if a fault is latched, and reads STATUS again to confirm. Moves nothing."""
    from ..drivers.robot import RobotFault
    from ..runtime.devices import open_device

    robot = open_device("robot", get_ctx().lab(), port=port, baud=baud)
    with robot:
        robot.status()
        was = robot.latched
        if was is not None:
            robot.clear()
            robot.status()
            if robot.latched is not None:
                raise RobotFault(f"{robot.link.name}: CLEAR sent, but the controller still reports '{robot.latched}'")
    d = {"robot": robot.link.name, "cleared": was, "latched": None}
    emit(d, lambda con: con.print(f"robot: cleared the latched '{was}' fault" if was else "robot: no fault latched"))


def _triple(text: str | None, what: str):
    """``"x,y,z"`` → three floats; a bad value is a one-line error (exit 2)."""
    from ..errors import UserInputError

    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise UserInputError(f"{what}: expected three numbers 'x,y,z', got {text!r}")
    return vals


def _arm(arm_file: str | Path, base: str | None, base_rpy: str | None):
    from ..config.arm import load_arm
    from ..planning.arm import ArmModel

    cfg = load_arm(arm_file, base_xyz_mm=_triple(base, "--base"), base_rpy_deg=_triple(base_rpy, "--base-rpy"))
    return ArmModel.from_config(cfg)


@robot_group.command("feasibility")
@click.argument("runs_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--arm", "arm_file", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Arm data file (e.g. drivers/arms/ur10e.yaml).")
@click.option("--base", default=None, metavar="X,Y,Z",
              help="The arm's base in the world, mm (default: the lab's mount in robot.yaml, else the file's).")
@click.option("--base-rpy", default=None, metavar="R,P,Y",
              help="The base's roll, pitch, yaw, degrees (default: the lab's mount, else the file's).")
@json_option
def feasibility_cmd(runs_dir: Path, arm_file: Path, base: str | None, base_rpy: str | None) -> None:
    """Could this arm have flown these runs? Every record's commanded motion, followed in joint space.

    Recovers the controller's exact trajectory of each record under RUNS_DIR (a trials sweep, a runs
    folder), then reports: commanded targets the arm reaches, trials whose whole path it follows from
    one home configuration (no configuration change, within joint limits), and of those, the ones
    within its joint speeds."""
    from ..experiments.arm_feasibility import feasibility

    lab = get_ctx().lab()
    mount = lab.robot  # the runs were flown with the arm where the lab mounts it, not where the file's default puts it
    base = base if base is not None or mount.arm_base_xyz_mm is None else ",".join(map(str, mount.arm_base_xyz_mm))
    if base_rpy is None and mount.arm_base_rpy_deg is not None:
        base_rpy = ",".join(map(str, mount.arm_base_rpy_deg))
    arm = _arm(arm_file, base, base_rpy)
    res = feasibility(runs_dir, arm, lab)
    if get_ctx().json:
        emit(res)
        return
    summary = {k: v for k, v in res.items() if k != "per_trial"}

    def human(con) -> None:
        con.print(f"{res['arm']} at base {res['base_xyz_mm']} mm, {res['trials']} trials, {res['samples']} samples")
        con.print(f"targets reachable      {res['targets_reachable_pct']:.1f} % of {res['targets']}")
        con.print(f"paths followed         {res['followed_pct']:.1f} %  (start {res['start_deg']} deg)")
        con.print(f"... within joint speeds {res['within_speeds_pct']:.1f} %")
        for cause, n in res["failures"].items():
            con.print(f"  {n:4d}  {cause}")
        for joint, n in res["over_speed"].items():
            con.print(f"  {n:4d}  over speed: {joint}")

    emit(summary, human)


@robot_group.command("mount")
@click.option("--arm", "arm_file", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Arm data file (e.g. drivers/arms/ur10e.yaml).")
@click.option("--runs", "runs_dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Run records whose commanded views must be reached too (a trials sweep, a runs folder).")
@click.option("--base", "bases", multiple=True, metavar="X,Y,Z",
              help="Check this base (mm, upright; repeatable) instead of the grid round the table.")
@click.option("--top", type=click.IntRange(min=1), default=10, show_default=True, help="Bases to list.")
@json_option
def mount_cmd(arm_file: Path, runs_dir: Path | None, bases: tuple[str, ...], top: int) -> None:
    """Where to bolt the arm: which base positions reach every view the lab plans.

    The views: the home pose, the calibration plan's robot stations and registration poses, and with
    --runs every target those runs commanded. The bases: upright, on a grid round the table's travel
    (or --base). Reaching every view is necessary, not sufficient: check the paths with
    ``labctl robot feasibility``."""
    from ..config.arm import load_arm
    from ..experiments.arm_mount import default_grid, mount_search, planned_views

    cfg = load_arm(arm_file)
    lab = get_ctx().lab()
    grid = [_triple(b, "--base") for b in bases] or default_grid(lab)
    res = mount_search(cfg, planned_views(lab, runs_dir), grid)
    if get_ctx().json:
        emit(res)
        return
    summary = {k: v for k, v in res.items() if k != "ranked"}
    summary["ranked"] = res["ranked"][:top]

    def human(con) -> None:
        views = ", ".join(f"{n} {k}" for k, n in res["views"].items())
        con.print(f"{res['arm']}: {res['bases']} bases against {views} views; "
                  f"{len(res['reach_all'])} reach every view")
        for r in res["ranked"][:top]:
            got = ", ".join(f"{k} {n}/{res['views'][k]}" for k, n in r["reached"].items())
            con.print(f"  base {r['base_xyz_mm']} mm: {got}")

    emit(summary, human)
