"""``labctl init`` and ``labctl lab show``."""

from __future__ import annotations

from pathlib import Path

import click

from ._common import emit, get_ctx, json_option


@click.command("init")
@click.argument("directory", type=click.Path(file_okay=False, path_type=Path))
@click.option("--force", is_flag=True, help="Overwrite a workspace that already exists there.")
@click.option("--preset", type=click.Choice(["realistic-camera"]), default=None,
              help="realistic-camera: the simulated cameras render sRGB frames with shadows, highlights, "
                   "table grain, Bayer demosaicing and JPEG (lab.yaml sim.camera and both camera driver files).")
@json_option
def init_cmd(directory: Path, force: bool, preset: str | None) -> None:
    """Write a fresh lab workspace (the sample simulated lab) into DIRECTORY."""
    from ..workspace import init_workspace

    dest = init_workspace(directory, force=force, preset=preset)
    nxt = f"labctl --lab {dest} devices"
    emit({"lab": str(dest), "next": nxt},
         lambda c: c.print(f"[green]lab workspace written:[/] {dest}\nnext: {nxt}", highlight=False))


@click.group("lab")
def lab_group() -> None:
    """Inspect the lab workspace."""


def _kind_and_port(dev: object) -> tuple[str | None, str | None]:
    """A driver file's kind (a host link's transport) and port, per config type (a camera has no port)."""
    from ..config.devices import CameraConfig, HostLinkConfig, RobotConfig, TableConfig

    if isinstance(dev, HostLinkConfig):
        return dev.transport, dev.port
    if isinstance(dev, (TableConfig, RobotConfig)):
        return dev.kind, dev.port
    if isinstance(dev, CameraConfig):
        return dev.kind, None
    return None, None


def describe_lab(lab) -> dict:
    """The resolved lab as plain data: driver file per role, calibration and library entries."""
    from ..config import to_plain
    from ..workspace import calibration_entries, library_entries

    roles = {}
    for role, path in lab.driver_paths.items():
        dev = getattr(lab, role)
        kind, port = _kind_and_port(dev)
        roles[role] = {
            "file": str(path),
            "kind": kind,
            "port": port,
            "config": to_plain(dev),
        }
    return {
        "lab": str(lab.root),
        "name": lab.config.name,
        "simulated": lab.is_simulated,
        "drivers": roles,
        "calibration": calibration_entries(lab.root),
        "object_library": library_entries(lab.root),
        "config": to_plain(lab.config),
        # keys (as in this output) whose value is the code's default: the lab's files do not set them
        "defaults": [f"config.{k}" for k in lab.defaulted.get("lab", ())]
        + [f"drivers.{role}.config.{k}" for role in roles for k in lab.defaulted.get(role, ())],
    }


def _leaves(values: dict, prefix: str = ""):
    """(dotted key, value) of every leaf of a nested settings mapping, in file order."""
    for k, v in values.items():
        if isinstance(v, dict) and v:
            yield from _leaves(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


def _show(value) -> str:
    from rich.markup import escape

    return escape("null" if value is None else str(value))


@lab_group.command("show")
@json_option
def lab_show() -> None:
    """Print the resolved lab: driver per role, calibration and library entries found, and every setting,
    marking those that come from the defaults (not set in the lab's files)."""
    info = describe_lab(get_ctx().lab())

    def human(console):
        from rich.table import Table

        console.print(f"[bold]{info['name']}[/]  {info['lab']}  "
                      f"({'simulated' if info['simulated'] else 'hardware'})")
        t = Table("role", "kind", "port", "driver file")
        for role, d in info["drivers"].items():
            t.add_row(role, str(d["kind"]), str(d["port"] or "-"), d["file"])
        console.print(t)
        console.print("calibration: " + (", ".join(info["calibration"]) or "[yellow]none[/]"))
        console.print("object library: " + (", ".join(info["object_library"]) or "[yellow]empty[/]"))
        defaults = set(info["defaults"])
        sections = [("lab.yaml", "config", info["config"])] + [
            (Path(d["file"]).name, f"drivers.{role}.config", d["config"]) for role, d in info["drivers"].items()]
        for title, prefix, values in sections:
            t = Table("setting", "value", "", title=title, title_justify="left", box=None, pad_edge=False)
            for key, value in _leaves(values):
                t.add_row(key, _show(value), "[dim](default)[/]" if f"{prefix}.{key}" in defaults else "")
            console.print(t)

    emit(info, human)
