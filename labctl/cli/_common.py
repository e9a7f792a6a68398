"""What every command shares: the context object, --json, and output for people or machines."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import click
import numpy as np


@dataclass
class Ctx:
    """The click context object: ``--lab`` path, ``--json``, ``-v`` count and the lab, loaded once."""

    lab_path: Path | None = None  # None: resolve with find_lab()
    json: bool = False
    verbose: int = 0
    _lab: Any = field(default=None, repr=False)

    @property
    def lab_root(self) -> Path:
        """The lab folder: ``--lab`` if given, else :func:`labctl.workspace.find_lab`."""
        from ..workspace import find_lab

        return Path(self.lab_path) if self.lab_path else find_lab()

    def lab(self):
        """The resolved, validated :class:`labctl.config.Lab` (raises ConfigError)."""
        if self._lab is None:
            import dataclasses

            from ..config import load_lab
            from ..workspace import find_workspace

            lab = load_lab(self.lab_root)
            if not self.lab_path and find_workspace() is None:
                # no workspace here: the sample lab is read, never written, wherever labctl is installed
                # from (an editable install's sample lab is its source tree)
                lab = dataclasses.replace(lab, read_only=True)
            self._lab = lab
        return self._lab

    def writable_lab(self, what: str):
        """The lab, refusing the sample lab inside the installed package (never written to)."""
        lab = self.lab()
        if lab.is_packaged:
            from ..errors import UserInputError

            raise UserInputError(f"no lab workspace here, and {what} is never written into the installed sample lab: "
                                 "run `labctl init DIR`, then work inside DIR (or pass --lab DIR)")
        return lab

    @property
    def console(self):
        """A rich console for people: on stderr under ``--json`` (stdout carries the JSON)."""
        from rich.console import Console

        return Console(stderr=self.json)


def get_ctx() -> Ctx:
    """The current command's :class:`Ctx` (created if the group did not make one)."""
    ctx = click.get_current_context()
    obj = ctx.find_object(Ctx)
    if obj is None:
        obj = ctx.ensure_object(Ctx)
    return obj


def _set_json(ctx: click.Context, _param, value):
    if value:
        get_ctx().json = True
    return value


json_option = click.option(
    "--json", "json_", is_flag=True, expose_value=False, callback=_set_json, is_eager=True,
    help="Machine-readable JSON on stdout.",
)


def _default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def to_json(data: Any) -> str:
    """``data`` as indented JSON; numpy arrays and scalars and paths converted, NaN refused (ValueError)."""
    return json.dumps(data, default=_default, indent=2, allow_nan=False)


def stdout_is_terminal() -> bool:
    """True when stdout is a terminal (people read it); False when piped or redirected (programs do)."""
    try:
        return sys.stdout.isatty()
    except (AttributeError, ValueError):  # replaced or closed stream
        return False


def live_console():
    """Where a live display (progress bar, live view) goes: the terminal on stdout; stderr's terminal
    when stdout is piped or carries --json; None when neither is a terminal (nothing to redraw on)."""
    from rich.console import Console

    if not get_ctx().json and stdout_is_terminal():
        return Console()
    try:
        return Console(stderr=True) if sys.stderr.isatty() else None
    except (AttributeError, ValueError):
        return None


def _scalar(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    text = str(v)
    return text.replace("\\", "\\\\").replace("\n", "\\n").replace("\r", "\\r")  # one key, one line


def key_lines(data: Any, prefix: str = "") -> list[str]:
    """``data`` flattened to ``key: value`` lines: nested keys joined by ``.``, list items as ``key[i]``,
    a list of plain values on one line (comma-separated), newlines in values escaped."""
    if isinstance(data, dict):
        if not data:
            return [f"{prefix}: {{}}"] if prefix else []
        out: list[str] = []
        for k, v in data.items():
            out += key_lines(v, f"{prefix}.{k}" if prefix else str(k))
        return out
    if isinstance(data, list | tuple):
        if all(not isinstance(v, dict | list | tuple) for v in data):
            return [f"{prefix or 'value'}: {', '.join(_scalar(v) for v in data)}"]
        out = []
        for i, v in enumerate(data):
            out += key_lines(v, f"{prefix}[{i}]")
        return out
    return [f"{prefix or 'value'}: {_scalar(data)}"]


def emit(data: Any, human=None) -> None:
    """Print a command's result: JSON with --json; one ``key: value`` line per key when stdout is not
    a terminal (piped: for grep, awk, a shell loop); else ``human(console)`` (or a pretty-print)."""
    c = get_ctx()
    if c.json:
        sys.stdout.write(to_json(data) + "\n")
        sys.stdout.flush()
    elif not stdout_is_terminal():
        plain = json.loads(json.dumps(data, default=_default))  # numpy, paths → plain values
        sys.stdout.write("".join(line + "\n" for line in key_lines(plain)))
        sys.stdout.flush()
    elif human is not None:
        human(c.console)
    else:
        from rich.pretty import pprint

        pprint(data, console=c.console)
