"""Running the labctl command in process for a test: its exit code and what it printed."""

from __future__ import annotations

from labctl.cli import main


def run_cli(capsys, *args: str) -> tuple[int, str, str]:
    """``labctl ARGS…`` in this process: (exit code, stdout, stderr), as pytest's ``capsys`` captured them."""
    code = 0
    try:
        main(list(args))
    except SystemExit as exc:
        code = exc.code or 0
    out = capsys.readouterr()
    return code, out.out, out.err
