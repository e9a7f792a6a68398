"""A G-code trajectory is read and checked before anything moves or any record is written.

``labctl run --trajectory FILE`` refuses, with exit 2 and one ``labctl: error:`` line, a binary file
(an STL model given by mistake), text that is not G-code, a line longer than GRBL's 80-byte line
buffer takes (79 characters and its end), a feed above the table's ``max_feed_mm_min`` and any
position outside the table's ``travel_mm`` (arcs included, by their extreme points).
"""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import pytest

from labctl.drivers.programs import load_trajectory
from labctl.errors import UserInputError
from labctl.workspace import init_workspace

TRAVEL, FEED = (600.0, 400.0), 6000.0  # the sample lab's table (drivers/table.yaml)


def _stl(path: Path) -> Path:
    """A one-facet binary STL, as trimesh writes it (80-byte header, count, 12 floats, attribute)."""
    path.write_bytes(b"solid part".ljust(80, b" ") + struct.pack("<I", 1)
                     + struct.pack("<12f", 0, 0, 1, 0, 0, 0, 10, 0, 0, 0, 10, 0) + b"\0\0")
    return path


BAD = {  # name: (file text or a maker, words the one line must hold)
    "binary_stl": (_stl, "not a G-code text file"),
    "beyond_travel": ("G21 G90\nG0 X100 Y100\nG1 X900 Y100 F600\n", "X900.000 mm, outside the table's travel 0..600"),
    "garbage": ("hello world\nthis is not a program\n", "not G-code"),
    "long_line": ("G21 G90\nG0 X10 Y10\nG1 X20" + "0" * 70 + " Y20 F600\n", "longer than GRBL's 79 characters"),
    "too_fast": ("G21 G90\nG0 X10 Y10\nG1 X200 Y10 F12000\n", "above the table's maximum, 6000 mm/min"),
}


def _write(tmp_path: Path, name: str) -> Path:
    body = BAD[name][0]
    f = tmp_path / (name + (".stl" if name == "binary_stl" else ".gcode"))
    return body(f) if callable(body) else (f.write_text(body), f)[1]


@pytest.mark.parametrize("name", sorted(BAD))
def test_a_bad_program_is_refused_when_read(tmp_path, name):
    with pytest.raises(UserInputError, match=BAD[name][1].replace("?", r"\?").replace(".", r"\.")):
        load_trajectory(_write(tmp_path, name), travel_mm=TRAVEL, max_feed_mm_min=FEED)


@pytest.mark.parametrize(("text", "words"), [
    ("G21 G90\nG0 X100 Y300\nG2 X100 Y300 I150 J0 F600\n", "Y450.000"),  # a full circle reaching past Y400
    ("G21 G90\nG0 X100 Y150\nG3 X500 Y150 R200 F600\n", "Y-50.000"),  # a half circle (R) below Y0, ends inside
    ("G91\nG1 X10 F600\n", "relative move (G91) before"),
    ("G21 G90\nG0 X10 Y10\nG92 X0 Y0\n", "G92 is not allowed"),
    ("G21 G90\nG0 X10 Y10\nG1 X20\n", "without a feed rate"),
    ("G20 G90\nG0 X1 Y1\nG1 X30 F100\n", "X762.000"),  # inches: 30 in = 762 mm
    ("$H\nG0 X10 Y10\n", "system command"),
    ("G21\nG4 P1\n", "no motion"),
])
def test_what_the_check_follows(tmp_path, text, words):
    f = tmp_path / "p.gcode"
    f.write_text(text)
    with pytest.raises(UserInputError, match=words.replace("(", r"\(").replace(")", r"\)").replace("$", r"\$")):
        load_trajectory(f, travel_mm=TRAVEL, max_feed_mm_min=FEED)


def test_a_good_program_passes_whole(tmp_path):
    f = tmp_path / "ok.nc"
    f.write_text("%\n(a square and arcs)\nG21 G90 G94\nG0 X100 Y100\nG1 X300 Y100 F600 ; along X\n"
                 "G2 X300 Y300 I0 J100\nG3 X100 Y300 R100\nG91 G1 Y-100\nG90 G53 G0 X300 Y200\nM2\n")
    assert load_trajectory(f, travel_mm=TRAVEL, max_feed_mm_min=FEED) == [
        "G21 G90 G94", "G0 X100 Y100", "G1 X300 Y100 F600", "G2 X300 Y300 I0 J100", "G3 X100 Y300 R100",
        "G91 G1 Y-100", "G90 G53 G0 X300 Y200", "M2"]


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> Path:
    return init_workspace(tmp_path_factory.mktemp("traj") / "lab")


@pytest.mark.timeout(120)
@pytest.mark.parametrize("name", sorted(BAD))
def test_run_refuses_a_bad_program_before_any_motion_or_record(lab, tmp_path, name):
    runs = lab / "runs"
    before = set(runs.glob("*")) if runs.is_dir() else set()
    done = subprocess.run([sys.executable, "-m", "labctl", "--lab", str(lab), "run", "--trajectory",
                           str(_write(tmp_path, name)), "--seed", "1"], capture_output=True, text=True, timeout=110)
    lines = [x for x in done.stderr.splitlines() if x.strip()]
    assert done.returncode == 2, done.stderr
    assert len(lines) == 1 and lines[0].startswith("labctl: error:") and BAD[name][1] in lines[0], done.stderr
    assert (set(runs.glob("*")) if runs.is_dir() else set()) == before  # no record was written
