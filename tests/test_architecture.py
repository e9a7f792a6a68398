"""The layer rules of docs/architecture.md, checked on the source: no upward imports."""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "labctl"

# package -> labctl packages it may import (besides itself)
ALLOWED = {
    "geometry": set(),
    "config": set(),
    "vision": {"geometry"},
    "tracking": set(),
    "planning": {"geometry", "tracking", "errors"},
    "calibration": {"geometry", "vision", "config", "fsutil", "errors"},
    "library": {"geometry", "vision", "fsutil", "errors"},
    "drivers": {"geometry", "config", "errors", "fsutil"},
    "sim": {"geometry", "config", "drivers", "library", "errors", "fsutil", "planning"},
    "conformance": set(),
    "records": {"fsutil", "errors"},
}


def _labctl_imports(path: Path, package: str) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the module's package path
                parts = path.relative_to(PKG).parts[:-1]
                base = list(parts[: len(parts) - (node.level - 1)]) if node.level > 1 else list(parts)
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
                if not mod.startswith("labctl"):
                    continue
                mod = mod.removeprefix("labctl").lstrip(".")
            top = mod.split(".")[0] if mod else ""
            if top and top != package:
                found.add(top)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("labctl."):
                    top = alias.name.split(".")[1]
                    if top != package:
                        found.add(top)
    return found


def test_layers_import_only_downwards():
    problems = []
    for package, allowed in ALLOWED.items():
        for path in (PKG / package).rglob("*.py"):
            bad = _labctl_imports(path, package) - allowed
            if bad:
                problems.append(f"{path.relative_to(PKG)} imports {sorted(bad)}")
    assert not problems, "\n".join(problems)


def test_functional_core_has_no_clocks_ports_or_processes():
    banned = ("import serial", "import time", "multiprocessing", "import socket", "subprocess")
    problems = []
    for package in ("geometry", "vision", "tracking", "planning"):
        for path in (PKG / package).rglob("*.py"):
            text = path.read_text(encoding="utf-8")
            problems += [f"{path.relative_to(PKG)}: {b}" for b in banned if b in text]
    assert not problems, "\n".join(problems)
