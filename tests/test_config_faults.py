"""The fault table of issue 17: a bad value in any file the lab reads (NaN, inf, zero, negative, a
cross-field conflict, a calibration that is physically wrong) is refused at load time in one line on
stderr naming the file and the key, with exit status 2, no traceback, and no record written."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest
import yaml

from labctl.cli import main
from labctl.workspace import sample_lab_path


def _set(path: Path, dotted: str, value) -> None:
    data = yaml.safe_load(path.read_text())
    node = data
    *parents, leaf = dotted.split(".")
    for k in parents:
        node = node[k]
    node[leaf] = value
    path.write_text(yaml.safe_dump(data))


def _replace(path: Path, pattern: str, new: str) -> None:
    text, n = re.subn(pattern, new, path.read_text(), count=1)
    assert n == 1, (path, pattern)
    path.write_text(text)


NAN, INF = float("nan"), float("inf")
# (file, key, value, what the one line must name)
FAULTS = [
    ("lab.yaml", "run.speed_mm_s", NAN, "speed_mm_s"),
    ("lab.yaml", "run.fps", 0, "fps"),
    ("lab.yaml", "run.timeout_s", -5, "timeout_s"),
    ("lab.yaml", "marker.radius_mm", INF, "radius_mm"),
    ("lab.yaml", "tracking.measurement_noise_mm", -0.1, "measurement_noise_mm"),
    ("lab.yaml", "viewing.standoff_mm", 0, "standoff_mm"),
    ("drivers/table.yaml", "baud", 0, "baud"),
    ("drivers/table.yaml", "status_hz", NAN, "status_hz"),
    ("drivers/table.yaml", "accel_mm_s2", -200, "accel_mm_s2"),
    ("drivers/robot.yaml", "v_max_mm_s", 0, "v_max_mm_s"),
    ("drivers/robot.yaml", "heartbeat_s", 0.9, "heartbeat_s"),  # cross-field: not below the 0.5 s watchdog
    ("drivers/robot.yaml", "a_max_mm_s2", INF, "a_max_mm_s2"),
    ("drivers/robot.yaml", "reconnect_s", -1.0, "reconnect_s"),
    ("drivers/table.yaml", "reconnect_s", NAN, "reconnect_s"),
    ("drivers/fixed_camera.yaml", "fps", -30, "fps"),
    ("drivers/fixed_camera.yaml", "marker_min_saturation", 1.5, "marker_min_saturation"),
    ("drivers/mobile_camera.yaml", "width", 0, "width"),
    ("drivers/host_link.yaml", "heartbeat_s", 5.0, "heartbeat_s"),  # cross-field: not below dead_after_s
    ("drivers/host_link.yaml", "dead_after_s", NAN, "dead_after_s"),
]
CALIBRATION_FAULTS = [  # (file, regex, replacement, what the line must name)
    ("calibration/fixed_camera.yaml", r"\{f: [0-9.e+-]+", "{f: .nan", "camera.f"),
    ("calibration/mobile_camera.yaml", r"dx: [0-9.e+-]+", "dx: -0.013", "camera.dx"),
    # the camera 1.8 m below the table instead of above it
    ("calibration/fixed_camera.yaml", r"(T_w_c:\n(?:- .*\n){2}- \[[^,]+, [^,]+, [^,]+, )([0-9.]+)\]", r"\1-\2]",
     "behind the fixed camera"),
]


@pytest.fixture
def lab(tmp_path):
    root = tmp_path / "lab"
    shutil.copytree(sample_lab_path(), root, ignore=shutil.ignore_patterns("runs", ".git", "labctl", "tests", "docs",
                                                                           ".venv", ".ci"))
    return root


def _run(lab: Path, capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as info:
        main(["--lab", str(lab), "run", "--virtual", "--seed", "1"])
    return info.value.code, capsys.readouterr().err


def _check(lab: Path, capsys, file: str, name: str) -> None:
    code, err = _run(lab, capsys)
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1 and "Traceback" not in err, err
    assert name in lines[0] and Path(file).name in lines[0], lines[0]
    runs = lab / "runs"
    assert not runs.exists() or not any(runs.iterdir()), "a record was written for a refused configuration"


@pytest.mark.parametrize("file,key,value,name", FAULTS, ids=[f"{f}:{k}={v}" for f, k, v, _ in FAULTS])
def test_bad_config_value_is_one_line_exit_2_nothing_written(lab, capsys, file, key, value, name):
    _set(lab / file, key, value)
    _check(lab, capsys, file, name)


@pytest.mark.parametrize("file,old,new,name", CALIBRATION_FAULTS, ids=[n for *_, n in CALIBRATION_FAULTS])
def test_bad_calibration_is_one_line_exit_2_nothing_written(lab, capsys, file, old, new, name):
    _replace(lab / file, old, new)
    _check(lab, capsys, file, name)


def test_yaml_1_2_numbers_are_numbers(lab):
    from labctl.config import load_lab

    text = (lab / "lab.yaml").read_text()
    (lab / "lab.yaml").write_text(re.sub(r"timeout_s: [0-9.]+", "timeout_s: 9.0e1", text, count=1))
    assert load_lab(lab).config.run.timeout_s == 90.0


@pytest.mark.parametrize("args", [["run", "--virtual", "--seed", "1", "--speed", "150"],
                                  ["trials", "--n", "1", "--speed", "50,150", "--no-record", "-j", "1"]])
def test_a_speed_above_the_tables_maximum_feed_is_one_line_exit_2(lab, capsys, args):
    """GRBL clamps a feed above its maximum rate ($110/$111) without a word: the run would record a speed the table
    never ran. The sample table's max_feed_mm_min is 6000 (100 mm/s)."""
    with pytest.raises(SystemExit) as info:
        main(["--lab", str(lab), *args])
    err = capsys.readouterr().err.strip()
    assert info.value.code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert "150 mm/s" in err and "100 mm/s" in err and "table.yaml: max_feed_mm_min 6000" in err, err
    runs = lab / "runs"
    assert not runs.exists() or not any(runs.iterdir())


def test_the_tables_maximum_feed_does_not_bound_motion_labctl_does_not_drive(lab):
    from labctl.cli.run import _speed
    from labctl.config import load_lab

    loaded = load_lab(lab)
    assert _speed(150.0, loaded, "external") == 150.0 and _speed(100.0, loaded, "line") == 100.0
