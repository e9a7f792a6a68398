"""The layer rules of docs/architecture.md, as import-linter contracts (``[tool.importlinter]`` in
pyproject.toml): no upward imports, and no clocks, ports or processes in the functional core."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_import_contracts_hold(capsys):
    from importlinter.cli import lint_imports

    cwd = os.getcwd()
    os.chdir(REPO)  # import-linter reads pyproject.toml from the working directory
    try:
        code = lint_imports()
    finally:
        os.chdir(cwd)
    out = capsys.readouterr().out
    assert code == 0, out
    assert "0 broken" in out
