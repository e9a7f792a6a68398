"""The ``labctl`` command line: parse, call, print. No logic of its own lives here.

Commands are loaded lazily from their modules so that ``labctl --help`` stays fast and a
missing optional piece never breaks the others.
"""

from __future__ import annotations

import importlib
import sys
import traceback
from pathlib import Path

import click

from .. import __version__
from ._common import Ctx

COMMANDS: dict[str, tuple[str, str]] = {
    "init": ("labctl.cli.lab", "init_cmd"),
    "lab": ("labctl.cli.lab", "lab_group"),
    "devices": ("labctl.cli.devices", "devices_cmd"),
    "table": ("labctl.cli.devices", "table_group"),
    "robot": ("labctl.cli.robot", "robot_group"),
    "sim": ("labctl.cli.sim", "sim_group"),
    "vision": ("labctl.cli.vision", "vision_group"),
    "calibrate": ("labctl.cli.calibrate", "calibrate_group"),
    "teach-object": ("labctl.cli.library", "teach_object_cmd"),
    "library": ("labctl.cli.library", "library_group"),
    "run": ("labctl.cli.run", "run_cmd"),
    "trials": ("labctl.cli.trials", "trials_cmd"),
    "replay": ("labctl.cli.run", "replay_cmd"),
    "report": ("labctl.cli.report", "report_cmd"),
    "runs": ("labctl.cli.runs", "runs_group"),
    "export": ("labctl.cli.runs", "export_cmd"),
    "worker": ("labctl.cli.run", "worker_cmd"),
    "bench": ("labctl.cli.bench", "bench_group"),
}


def _load(name: str) -> click.Command | None:
    module, attr = COMMANDS[name]
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name == module:  # that piece is not built into this installation
            return None
        raise
    return getattr(mod, attr, None)


class LazyGroup(click.Group):
    """Click group that imports each subcommand's module only when it is listed or called."""

    def list_commands(self, ctx):
        """Names of the subcommands built into this installation."""
        return [n for n in COMMANDS if _load(n) is not None]

    def get_command(self, ctx, name):
        """The subcommand ``name`` (imported now), or None if unknown or not built in."""
        return _load(name) if name in COMMANDS else None


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--lab", "lab", type=click.Path(file_okay=False, path_type=Path),
              help="Lab workspace (default: nearest folder upward with lab.yaml, else the sample lab).")
@click.option("--json", "json_", is_flag=True, help="Machine-readable JSON on stdout.")
@click.option("-v", "--verbose", count=True, help="More detail; tracebacks on errors.")
@click.version_option(__version__, prog_name="labctl")
@click.pass_context
def cli(ctx: click.Context, lab: Path | None, json_: bool, verbose: int) -> None:
    """labctl: moving-object recognition with premarking and active vision (He et al., ICRA 1996)."""
    obj = ctx.ensure_object(Ctx)
    obj.lab_path, obj.json, obj.verbose = lab, json_, verbose
    if verbose:
        import logging

        logging.basicConfig(level=logging.DEBUG if verbose > 1 else logging.INFO,
                            format="%(asctime)s %(name)s %(levelname)s %(message)s")


def main(argv: list[str] | None = None) -> None:
    """Console entry point: expected failures become one line on stderr and an exit code."""
    from ..config import ConfigError
    from ..errors import LabctlError

    verbose = any(a in ("-v", "--verbose") or (a.startswith("-v") and set(a[1:]) == {"v"})
                  for a in (argv if argv is not None else sys.argv[1:]))
    try:
        rv = cli.main(args=argv, prog_name="labctl", standalone_mode=False)
        if isinstance(rv, int) and not isinstance(rv, bool) and rv:
            sys.exit(rv)  # a command may return its exit status
    except click.exceptions.Abort:
        click.echo("labctl: aborted", err=True)
        sys.exit(130)
    except click.exceptions.Exit as exc:
        sys.exit(exc.exit_code)
    except click.UsageError as exc:  # one line, as every expected failure, with where to look
        cmd = exc.ctx.command_path if exc.ctx is not None else "labctl"
        click.echo(f"labctl: error: {exc.format_message()} (see '{cmd} --help')", err=True)
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        click.echo(f"labctl: error: {exc.format_message()}", err=True)
        sys.exit(exc.exit_code)
    except (ConfigError, LabctlError, FileExistsError, FileNotFoundError) as exc:
        if verbose:
            traceback.print_exc()
        code = getattr(exc, "exit_code", 2)
        click.echo(f"labctl: error: {exc}", err=True)
        sys.exit(code)
    except KeyboardInterrupt:
        click.echo("labctl: interrupted", err=True)
        sys.exit(130)
