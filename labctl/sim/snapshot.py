"""``labctl sim snapshot``: what a simulated camera sees at time t, written to a PNG.

The scene: an object from the lab's library (by name, or drawn with the seed), resting in a
stable pose drawn with its probability at a random yaw and offset; the table running the lab's
default run at ``run.speed_mm_s`` along +x from the centre of its travel (where both cameras look);
the robot at home with the mobile camera looking at the table's centre. If the library is empty,
a built-in 40×40×35 mm test block with a marker on every face stands in (and the result says so).
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

import cv2
import numpy as np

from ..errors import UserInputError
from ..fsutil import atomic_write_bytes
from .world import SimObject, SimWorld, builtin_test_object, random_placement

SNAPSHOT_LEAD_MM = 0.0


def _library_objects(lab) -> tuple[dict, str | None]:
    """Objects of the lab's library by name; and why it fell back, if it did."""
    folder = Path(lab.library_dir)
    if not folder.is_dir() or not any(p.is_dir() and not p.name.startswith(".") for p in folder.iterdir()):
        return {}, f"the object library {folder} is empty"
    from ..library.storage import load_library

    return load_library(folder), None


def table_line_position(lab, speed_mm_s: float, lead_mm: float = SNAPSHOT_LEAD_MM):
    """Carriage position over time for a straight run along +x through the centre of the travel (clipped)."""
    tx, ty = lab.table.travel_mm
    x0, y0 = tx / 2.0 - lead_mm, ty / 2.0

    def position(t: float):
        return (float(np.clip(x0 + speed_mm_s * t, 0.0, tx)), y0, 0.0)

    return position


def snapshot(lab, camera: str, t: float, out: Path, seed: int = 0, object_name: str | None = None) -> dict:
    """Render camera ``fixed``/``mobile`` of the simulated lab at time ``t`` (s) into the PNG ``out``.

    Returns what was drawn: object and placement, camera pose, table position, marker pixels.
    """
    if camera not in ("fixed", "mobile"):
        raise UserInputError(f"unknown camera {camera!r}: use fixed or mobile")
    if not np.isfinite(t) or t < 0:
        raise UserInputError(f"--t must be a time in seconds ≥ 0, got {t}")
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise UserInputError(f"--out must name a .png file, got {out.name!r}")
    library, fallback = _library_objects(lab)
    rng = np.random.default_rng(seed)
    builtin = builtin_test_object(lab.config.marker.radius_mm)
    if object_name is not None:
        if object_name in library:
            obj, source = SimObject.from_library(library[object_name]), "library"
        elif object_name == builtin.name:
            obj, source = builtin, "built-in"
        else:
            have = ", ".join(sorted(library) + [builtin.name])
            raise UserInputError(f"no object {object_name!r} in the library (have: {have})")
    elif library:
        name = sorted(library)[int(rng.integers(len(library)))]
        obj, source = SimObject.from_library(library[name]), "library"
    else:
        obj, source = builtin, "built-in"
    placement = random_placement(obj, rng)
    speed = float(lab.config.run.speed_mm_s)
    world = SimWorld.from_lab(lab, obj=obj, placement=placement, table_position=table_line_position(lab, speed))
    res = world.render(camera, t, np.random.default_rng([seed, 1 if camera == "fixed" else 2, 0]), truth=True)
    ok, png = cv2.imencode(".png", res.image)
    if not ok:
        raise UserInputError(f"cannot encode a PNG for {out}")
    try:
        atomic_write_bytes(out, png.tobytes())
    except OSError as exc:
        raise UserInputError(f"cannot write {out}: {exc.strerror or exc}") from None
    truth = world.truth(t)
    mask, marker_pixels = cast(np.ndarray, res.mask), cast("list[int]", res.marker_pixels)  # truth=True: both set
    info = {
        "out": str(out),
        "camera": camera,
        "t": float(t),
        "seed": int(seed),
        "object": obj.name,
        "object_source": source,
        "stable_pose": placement.pose_index,
        "yaw_deg": round(float(np.degrees(placement.yaw)), 3),
        "offset_mm": [round(v, 3) for v in placement.offset_xy],
        "table_position_mm": [round(float(v), 3) for v in world.table_position(t)],
        "table_motion": f"line along +x at {speed:g} mm/s",
        "T_w_c": np.round(world.T_w_c(camera, t), 6).tolist(),
        "T_w_o": np.round(cast(np.ndarray, truth.T_w_o), 6).tolist(),  # an object is placed
        "object_pixels": int(mask.sum()),
        "marker_pixels": {str(m.id): int(n) for m, n in zip(obj.markers, marker_pixels)},
    }
    if source == "built-in":
        info["note"] = (f"{fallback}; " if fallback else "") + "drew the built-in test block (40×40×35 mm)"
    return info
