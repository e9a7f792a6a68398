"""The layer rules of docs/architecture.md, as import-linter contracts (``[tool.importlinter]`` in
pyproject.toml): no upward imports, and no clocks, ports or processes in the functional core."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_import_contracts_hold():
    # in a subprocess: import-linter reconfigures logging, which would silence labctl's loggers for
    # every test after this one; it reads pyproject.toml from its working directory
    code = "from importlinter.cli import lint_imports; raise SystemExit(lint_imports())"
    p = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "0 broken" in p.stdout
