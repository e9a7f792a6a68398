"""Finding, creating and describing lab workspaces (README "The lab workspace")."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import TypedDict

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


def find_workspace(start: Path | str | None = None) -> Path | None:
    """The nearest folder at or above ``start`` (default: cwd) holding lab.yaml, or None."""
    cur = Path(start or Path.cwd()).resolve()
    for d in (cur, *cur.parents):
        if (d / LAB_FILE).is_file():
            return d
    return None


def find_lab(start: Path | str | None = None) -> Path:
    """The nearest folder at or above ``start`` (default: cwd) holding lab.yaml, else the sample lab."""
    return find_workspace(start) or sample_lab_path()


class InitPreset(TypedDict):
    """A ``labctl init --preset``: text appended to lab.yaml, and the camera driver files' top-level keys."""

    lab: str
    cameras: dict[str, str]


# `labctl init --preset NAME`: lab.yaml's sim section, and the camera driver files' keys that must agree with it
INIT_PRESETS: dict[str, InitPreset] = {
    "realistic-camera": {
        "lab": "sim:\n  camera:\n    preset: realistic   # shadows, highlights, table grain, Bayer, JPEG 80 "
               "(docs/notes/vision.md)\n",
        # the sRGB response the simulated cameras render with and vision linearises by; the
        # saturation floor `labctl vision learn-color` measures on these frames (0.21–0.25)
        "cameras": {"response": "srgb", "marker_min_saturation": "0.25"},
    },
}


def _set_top_level_keys(text: str, values: dict) -> str:
    """A driver file's text with top-level ``key: value`` lines replaced (or appended); the rest kept."""
    lines = text.splitlines()
    for key, val in values.items():
        for i, line in enumerate(lines):
            if line.split(":", 1)[0].strip() == key and not line.startswith((" ", "#")):
                lines[i] = f"{key}: {val}"
                break
        else:
            lines.append(f"{key}: {val}")
    return "\n".join(lines) + "\n"


def init_workspace(dest: Path | str, *, force: bool = False, preset: str | None = None) -> Path:
    """Copy the sample simulated lab into ``dest``. Refuses to overwrite an existing lab.

    ``preset`` (:data:`INIT_PRESETS`): ``realistic-camera`` turns on the simulated cameras'
    realistic effects (lab.yaml ``sim.camera.preset: realistic``) and gives both camera driver
    files the matching ``response: srgb`` and marker saturation floor."""
    dest = Path(dest).resolve()
    if preset is not None and preset not in INIT_PRESETS:
        raise ValueError(f"unknown preset {preset!r} (known: {', '.join(INIT_PRESETS)})")
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
    if preset is not None:
        spec = INIT_PRESETS[preset]
        lab_file = dest / LAB_FILE
        text = lab_file.read_text(encoding="utf-8")
        lab_file.write_text(text.rstrip("\n") + "\n" + spec["lab"], encoding="utf-8")
        for name in ("fixed_camera.yaml", "mobile_camera.yaml"):
            path = dest / "drivers" / name
            path.write_text(_set_top_level_keys(path.read_text(encoding="utf-8"), spec["cameras"]), encoding="utf-8")
    return dest


def calibration_entries(root: Path) -> list[str]:
    """Names of the ``*.yaml`` files in ``root/calibration`` (sorted; empty if there is no folder)."""
    d = Path(root) / "calibration"
    return sorted(p.name for p in d.glob("*.yaml")) if d.is_dir() else []


def library_entries(root: Path) -> list[str]:
    """Names of the objects (non-hidden folders) in ``root/object_library`` (sorted; empty if none)."""
    d = Path(root) / "object_library"
    return sorted(p.name for p in d.iterdir() if p.is_dir() and not p.name.startswith(".")) if d.is_dir() else []
