"""Finding, creating and describing lab workspaces (README "The lab workspace")."""

from __future__ import annotations

import shutil
from pathlib import Path

from .config.lab import LAB_FILE

WORKSPACE_ITEMS = ("lab.yaml", "drivers", "calibration", "object_library")


def sample_lab_path() -> Path:
    """The packaged sample simulated lab.

    In a wheel it is ``labctl/sample_lab``; in a source checkout it is the repository's top
    level, which is itself the sample workspace.
    """
    here = Path(__file__).resolve().parent
    packaged = here / "sample_lab"
    if (packaged / LAB_FILE).is_file():
        return packaged
    checkout = here.parent
    if (checkout / LAB_FILE).is_file():
        return checkout
    raise FileNotFoundError("the sample lab is missing from this installation")


def find_lab(start: Path | str | None = None) -> Path:
    """The nearest folder at or above ``start`` (default: cwd) holding lab.yaml, else the sample lab."""
    cur = Path(start or Path.cwd()).resolve()
    for d in (cur, *cur.parents):
        if (d / LAB_FILE).is_file():
            return d
    return sample_lab_path()


def init_workspace(dest: Path | str, *, force: bool = False) -> Path:
    """Copy the sample simulated lab into ``dest``. Refuses to overwrite an existing lab."""
    dest = Path(dest).resolve()
    if (dest / LAB_FILE).exists() and not force:
        raise FileExistsError(f"{dest} already holds a lab workspace (lab.yaml); not overwriting it")
    src = sample_lab_path()
    dest.mkdir(parents=True, exist_ok=True)
    for item in WORKSPACE_ITEMS:
        s = src / item
        if s.is_dir():
            shutil.copytree(s, dest / item, dirs_exist_ok=True,
                            ignore=shutil.ignore_patterns(".*", "__pycache__"))
        elif s.is_file():
            shutil.copy2(s, dest / item)
    (dest / "runs").mkdir(exist_ok=True)
    return dest


def calibration_entries(root: Path) -> list[str]:
    d = Path(root) / "calibration"
    return sorted(p.name for p in d.glob("*.yaml")) if d.is_dir() else []


def library_entries(root: Path) -> list[str]:
    d = Path(root) / "object_library"
    return sorted(p.name for p in d.iterdir() if p.is_dir() and not p.name.startswith(".")) if d.is_dir() else []
