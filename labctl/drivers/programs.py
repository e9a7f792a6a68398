"""Motion programs for the NC table: the ``--trajectory`` shapes as G-code, and G-code files.

The paper moves the object at 4-12 mm/s along simple paths (§5: straight line and curved
paths). ``program(name, speed_mm_s, start)`` writes them as GRBL G-code in machine-table
millimetres (G21 G90 G94): ``line`` (one G1), ``arc`` (one G2/G3), ``circle`` (a full G2),
``zigzag`` (a polyline). Pure functions: text in, text out.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from ..config.lab import TRAJECTORIES
from ..errors import UserInputError


def _fmt(v: float) -> str:
    s = f"{v:.3f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _check_inside(points, travel_mm, name) -> None:
    for x, y in points:
        if not (-1e-9 <= x <= travel_mm[0] + 1e-9 and -1e-9 <= y <= travel_mm[1] + 1e-9):
            raise UserInputError(f"trajectory {name!r} leaves the table's travel 0..{travel_mm[0]:g} × "
                                 f"0..{travel_mm[1]:g} mm (reaches {x:.1f}, {y:.1f}); move its start or shorten it")


def program(name: str, speed_mm_s: float, start=(150.0, 200.0), *, length_mm: float = 300.0,
            direction_deg: float = 0.0, radius_mm: float = 80.0, sweep_deg: float = 180.0,
            amplitude_mm: float = 40.0, period_mm: float = 100.0, clockwise: bool = False,
            travel_mm=(600.0, 400.0), rapid_to_start: bool = True) -> list[str]:
    """G-code lines moving the table along trajectory ``name`` at ``speed_mm_s`` from ``start`` (mm).

    * line: ``length_mm`` along ``direction_deg`` (0 = +X, counter-clockwise);
    * arc: ``sweep_deg`` of a circle of ``radius_mm``, starting tangent to ``direction_deg``;
    * circle: a full circle of ``radius_mm`` tangent to ``direction_deg`` at ``start``;
    * zigzag: ``length_mm`` along ``direction_deg`` with ±``amplitude_mm`` legs every ``period_mm/2``.

    Raises UserInputError for an unknown name, a non-positive speed or a path off the table.
    """
    if name not in TRAJECTORIES:
        raise UserInputError(f"unknown trajectory {name!r} (have: {', '.join(TRAJECTORIES)})")
    if not (speed_mm_s > 0 and math.isfinite(speed_mm_s)):
        raise UserInputError(f"speed must be a positive number of mm/s, got {speed_mm_s}")
    x0, y0 = float(start[0]), float(start[1])
    feed = _fmt(speed_mm_s * 60.0)
    th = math.radians(direction_deg)
    ux, uy = math.cos(th), math.sin(th)
    nx, ny = (-uy, ux) if not clockwise else (uy, -ux)  # towards the centre of turning
    lines = ["G21", "G90", "G94"]
    if rapid_to_start:
        lines.append(f"G0 X{_fmt(x0)} Y{_fmt(y0)}")
    points = [(x0, y0)]
    if name == "line":
        x1, y1 = x0 + length_mm * ux, y0 + length_mm * uy
        points.append((x1, y1))
        lines.append(f"G1 X{_fmt(x1)} Y{_fmt(y1)} F{feed}")
    elif name in ("arc", "circle"):
        cx, cy = x0 + radius_mm * nx, y0 + radius_mm * ny
        sweep = 360.0 if name == "circle" else sweep_deg
        a0 = math.atan2(y0 - cy, x0 - cx)
        sign = -1.0 if clockwise else 1.0
        n = 72
        for k in range(1, n + 1):
            a = a0 + sign * math.radians(sweep) * k / n
            points.append((cx + radius_mm * math.cos(a), cy + radius_mm * math.sin(a)))
        x1, y1 = (x0, y0) if name == "circle" else points[-1]
        code = "G2" if clockwise else "G3"
        if name == "arc" and sweep > 180.0:  # split: one G2/G3 per half keeps the arc unambiguous
            mid = points[n // 2]
            lines.append(f"{code} X{_fmt(mid[0])} Y{_fmt(mid[1])} I{_fmt(cx - x0)} J{_fmt(cy - y0)} F{feed}")
            lines.append(f"{code} X{_fmt(x1)} Y{_fmt(y1)} I{_fmt(cx - mid[0])} J{_fmt(cy - mid[1])}")
        else:
            lines.append(f"{code} X{_fmt(x1)} Y{_fmt(y1)} I{_fmt(cx - x0)} J{_fmt(cy - y0)} F{feed}")
    else:  # zigzag
        half = period_mm / 2.0
        legs = max(1, int(round(length_mm / half)))
        for k in range(1, legs + 1):
            along = k * half
            side = amplitude_mm if k % 2 else -amplitude_mm
            if k == legs:
                side = 0.0
            x, y = x0 + along * ux + side * (-uy), y0 + along * uy + side * ux
            points.append((x, y))
            lines.append(f"G1 X{_fmt(x)} Y{_fmt(y)}" + (f" F{feed}" if k == 1 else ""))
    _check_inside(points, travel_mm, name)
    return lines


def load_gcode_numbered(path: str | Path) -> list[tuple[int, str]]:
    """``(file line number, line)`` for every line of a G-code file to stream (1-based numbers;
    blank lines, ``%`` and comment-only lines dropped), so errors can name the file's line."""
    p = Path(path)
    try:
        text = p.read_text(encoding="ascii")
    except FileNotFoundError:
        raise UserInputError(f"G-code file not found: {p}") from None
    except IsADirectoryError:
        raise UserInputError(f"{p} is a directory, not a G-code file") from None
    except UnicodeDecodeError as exc:
        raise UserInputError(f"{p}: not an ASCII G-code file (byte {exc.start})") from None
    out = []
    for i, raw in enumerate(text.splitlines(), 1):
        line = raw.split(";", 1)[0].strip()
        stripped = re.sub(r"\([^)]*\)", "", "".join(c for c in line if c not in " \t"))
        if not stripped or stripped == "%":
            continue
        if len(stripped) > 79:
            raise UserInputError(f"{p}:{i}: line longer than GRBL's 79 characters")
        out.append((i, line))
    return out


def load_gcode(path: str | Path) -> list[str]:
    """The lines of a G-code file to stream (blank lines, ``%`` and comment-only lines dropped)."""
    return [line for _, line in load_gcode_numbered(path)]
