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


def _read_gcode(p: Path) -> bytes:
    """A G-code file's bytes; UserInputError, one line, when it cannot be read."""
    try:
        return p.read_bytes()
    except FileNotFoundError:
        raise UserInputError(f"G-code file not found: {p}") from None
    except IsADirectoryError:
        raise UserInputError(f"{p} is a directory, not a G-code file") from None
    except OSError as exc:
        raise UserInputError(f"cannot read G-code file {p}: {exc.strerror or exc}") from None


def load_gcode_numbered(path: str | Path, data: bytes | None = None) -> list[tuple[int, str]]:
    """``(file line number, line)`` for every line of a G-code file to stream (1-based numbers;
    blank lines, ``%`` and comment-only lines dropped), so errors can name the file's line.
    ``data``: the file's bytes, when the caller has read them already."""
    p = Path(path)
    try:
        text = (_read_gcode(p) if data is None else data).decode("ascii")
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


# ---- reading a G-code trajectory before it moves anything ----------------------------------------

#: G words the check can follow: units, distance modes, plane XY, feed per minute, machine
#: coordinates, dwell, motion. Others (offsets G10/G92, stored positions G28/G30, probing G38,
#: inverse-time feed G93, other planes, cutter and length compensation) move the table where a
#: reading of the file cannot tell, and are refused.
_G_FOLLOWED = {"0", "1", "2", "3", "4", "17", "20", "21", "53", "54", "80", "90", "91", "91.1", "94"}
_M_ALLOWED = {"0", "1", "2", "3", "4", "5", "7", "8", "9", "30"}
_WORD = re.compile(r"([A-Z])([-+]?(?:\d+\.?\d*|\.\d+))")
_ARGS = {"X", "Y", "Z", "I", "J", "K", "R", "F", "P", "S", "T", "N", "L"}


def _words(text: str) -> list[tuple[str, str]] | None:
    """The line's words ``(letter, number)``, or None if it is not made of G-code words only."""
    pos, out = 0, []
    for m in _WORD.finditer(text):
        if m.start() != pos:
            return None
        out.append((m.group(1), m.group(2)))
        pos = m.end()
    return out if pos == len(text) else None


def _arc_extremes(x0, y0, x1, y1, cx, cy, clockwise: bool, full: bool) -> list[tuple[float, float]]:
    """The points of an XY arc from (x0, y0) to (x1, y1) about (cx, cy) where it reaches furthest along
    ±X and ±Y (its end points and every quadrant point its sweep passes)."""
    r = math.hypot(x0 - cx, y0 - cy)
    a0, a1 = math.atan2(y0 - cy, x0 - cx), math.atan2(y1 - cy, x1 - cx)
    sweep = a1 - a0
    if clockwise:
        sweep = -2 * math.pi if full else (sweep - 2 * math.pi if sweep >= 0 else sweep)
    else:
        sweep = 2 * math.pi if full else (sweep + 2 * math.pi if sweep <= 0 else sweep)
    lo, hi = sorted((a0, a0 + sweep))
    pts = [(x0, y0), (x1, y1)]
    for n in range(math.ceil(lo / (math.pi / 2)), math.floor(hi / (math.pi / 2)) + 1):
        a = n * math.pi / 2
        pts.append((cx + r * math.cos(a), cy + r * math.sin(a)))
    return pts


def check_program(numbered: list[tuple[int, str]], where: str, *, travel_mm, max_feed_mm_min: float) -> None:
    """Read a G-code program as GRBL would run it and refuse it (UserInputError, one line naming the
    file's line) unless every line is G-code the check can follow, every position it reaches in X
    and Y lies inside the table's travel ``0..travel_mm`` (machine mm; arcs by their extreme points),
    and every feed is positive and at most ``max_feed_mm_min``. Positions are machine coordinates
    (as the run's own programs, a zero work offset); a relative move before the program has set an
    absolute position is refused, since where the table stands before it runs is not known here.
    A program with no motion is refused. ``numbered`` is :func:`load_gcode_numbered`'s output."""
    inch = relative = False
    motion: str | None = "0"
    feed: float | None = None
    pos: list[float | None] = [None, None]
    moved = False
    for n, raw in numbered:
        text = re.sub(r"\([^)]*\)", "", raw.split(";", 1)[0]).upper()
        text = "".join(text.split())
        if text.startswith("$"):
            raise UserInputError(f"{where}:{n}: {raw.strip()!r} is a GRBL system command, not part of a motion "
                                 f"program")
        words = _words(text)
        if words is None or not words:
            raise UserInputError(f"{where}:{n}: not G-code: {raw.strip()[:40]!r}")
        args: dict[str, float] = {}
        machine = False
        for letter, num in words:
            if letter == "G":
                code = num.lstrip("0") or "0" if "." not in num else num
                if code not in _G_FOLLOWED:
                    raise UserInputError(f"{where}:{n}: G{num} is not allowed in a trajectory (only moves in "
                                         f"G90/G91, G20/G21, G17, G94 and G53 can be checked against the travel)")
                if code in ("0", "1", "2", "3"):
                    motion = code
                elif code == "80":
                    motion = None
                elif code in ("20", "21"):
                    inch = code == "20"
                elif code in ("90", "91"):
                    relative = code == "91"
                elif code == "53":
                    machine = True
            elif letter == "M":
                if (num.lstrip("0") or "0") not in _M_ALLOWED:
                    raise UserInputError(f"{where}:{n}: M{num} is not allowed in a trajectory")
            elif letter in _ARGS:
                if letter in args:
                    raise UserInputError(f"{where}:{n}: {letter} given twice")
                args[letter] = float(num)
            else:
                raise UserInputError(f"{where}:{n}: {letter}{num} is not a G-code word GRBL accepts")
        scale = 25.4 if inch else 1.0
        if "F" in args:
            f = args["F"] * scale
            if not f > 0:
                raise UserInputError(f"{where}:{n}: feed F{args['F']:g} must be positive")
            if f > max_feed_mm_min + 1e-9:
                raise UserInputError(f"{where}:{n}: feed F{args['F']:g} ({f:g} mm/min) is above the table's "
                                     f"maximum, {max_feed_mm_min:g} mm/min (max_feed_mm_min)")
            feed = f
        axes = [a for a in ("X", "Y") if a in args]
        if not axes and "Z" not in args:
            continue
        if motion is None:
            raise UserInputError(f"{where}:{n}: axis words without a motion mode (G80 cancelled it)")
        if motion != "0" and feed is None:
            raise UserInputError(f"{where}:{n}: G{motion} without a feed rate (no F yet)")
        start = list(pos)
        target = list(pos)
        for i, a in enumerate(("X", "Y")):
            if a not in args:
                continue
            v = args[a] * scale
            if relative and not machine:
                here = pos[i]
                if here is None:
                    raise UserInputError(f"{where}:{n}: a relative move (G91) before the program set an absolute "
                                         f"{a}: where the table starts is not known before the run")
                v += here
            target[i] = v
        points: list[tuple[float | None, float | None]] = [(target[0], target[1])]
        if motion in ("2", "3") and axes:
            x0, y0 = start
            if x0 is None or y0 is None:
                raise UserInputError(f"{where}:{n}: an arc before the program set absolute X and Y")
            x1 = target[0] if target[0] is not None else x0
            y1 = target[1] if target[1] is not None else y0
            if "R" in args:
                r = args["R"] * scale
                dx, dy = x1 - x0, y1 - y0
                h2 = 4.0 * r * r - dx * dx - dy * dy
                if h2 < 0 or (dx == 0 and dy == 0):
                    raise UserInputError(f"{where}:{n}: arc radius R{args['R']:g} cannot join its end points")
                h = -math.sqrt(h2) / math.hypot(dx, dy)  # GRBL's own construction of the centre (gcode.c)
                if motion == "3":
                    h = -h
                if r < 0:
                    h = -h
                cx, cy = x0 + 0.5 * (dx - dy * h), y0 + 0.5 * (dy + dx * h)
                full = False
            else:
                cx, cy = x0 + args.get("I", 0.0) * scale, y0 + args.get("J", 0.0) * scale
                full = abs(x1 - x0) < 1e-6 and abs(y1 - y0) < 1e-6
            points = list(_arc_extremes(x0, y0, x1, y1, cx, cy, motion == "2", full))
        for x, y in points:
            for i, c in enumerate((x, y)):
                if c is not None and not (-1e-6 <= c <= travel_mm[i] + 1e-6):
                    raise UserInputError(f"{where}:{n}: the program reaches {'XY'[i]}{c:.3f} mm, outside the "
                                         f"table's travel 0..{travel_mm[i]:g} mm")
        pos = target
        moved = moved or bool(axes)
    if not moved:
        raise UserInputError(f"{where}: no motion in X or Y: not a trajectory program")


def load_trajectory(path: str | Path, *, travel_mm, max_feed_mm_min: float) -> list[str]:
    """The lines of a G-code trajectory file, read and checked before anything moves: text (a
    binary file, such as an STL model, is refused), GRBL's line length, the table's travel and feed
    limits (:func:`check_program`). UserInputError, one line, otherwise."""
    p = Path(path)
    data = _read_gcode(p)
    bad = next((i for i, b in enumerate(data) if b == 0 or b > 127 or (b < 32 and b not in b"\t\r\n")), None)
    if bad is not None:
        raise UserInputError(f"{p} is not a G-code text file (binary data at byte {bad})")
    numbered = load_gcode_numbered(p, data)
    check_program(numbered, str(p), travel_mm=travel_mm, max_feed_mm_min=max_feed_mm_min)
    return [line for _, line in numbered]
