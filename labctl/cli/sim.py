"""``labctl sim serve`` and ``labctl sim snapshot``: expose and look at the simulated lab."""

from __future__ import annotations

from pathlib import Path

import click

from ._common import emit, get_ctx, json_option


@click.group("sim")
def sim_group() -> None:
    """The simulated lab's devices and cameras."""


@sim_group.command("serve")
@click.option("--baud", type=int, default=None, help="Pace the emulators at this baud rate (default: driver files).")
@json_option
def sim_serve(baud: int | None) -> None:
    """Start the GRBL table and robot emulators on pseudo-terminals and print their ports."""
    from ..sim.emulators.serve import serve_forever

    def ready(ports: dict) -> None:
        emit(ports, lambda c: [c.print(f"[bold]{role}[/]: {port}") for role, port in ports.items()]
             + [c.print("Ctrl-C to stop.")])

    serve_forever(get_ctx().lab(), baud=baud, on_ready=ready)


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
