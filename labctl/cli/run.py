"""``labctl run`` (the live run). Not built yet: see issue 9."""

from __future__ import annotations

import click

from ..errors import LabctlError


@click.command("run")
@click.option("--trajectory", default="line", show_default=True)
@click.option("--speed", type=float, default=None)
@click.option("--object", "object_name", default=None)
@click.option("--seed", type=int, default=None)
@click.option("--json", "json_", is_flag=True)
def run_cmd(trajectory, speed, object_name, seed, json_) -> None:
    """A live run: move the table, track, intercept, pose, standard view, identify."""
    raise LabctlError("labctl run is not built yet (the live run is issue 9)")
