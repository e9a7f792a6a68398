"""Lab workspace, configuration validation and the CLI frame, through the real entry point."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from labctl.config import ConfigError, load_lab
from labctl.workspace import init_workspace, sample_lab_path


def labctl(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "labctl", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=60)


@pytest.fixture
def lab(tmp_path) -> Path:
    return init_workspace(tmp_path / "lab")


def test_sample_lab_loads_and_is_simulated():
    lab = load_lab(sample_lab_path())
    assert lab.is_simulated
    assert lab.fixed_camera.eye_w_mm[2] == 1800.0  # paper §5.2: 1.8 m above the table
    assert lab.config.viewing.initial_angle_deg == 63.0


def test_init_then_lab_show_json(tmp_path):
    dest = tmp_path / "x"
    r = labctl("init", str(dest))
    assert r.returncode == 0, r.stderr
    r = labctl("--lab", str(dest), "lab", "show", "--json")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert info["lab"] == str(dest.resolve())
    assert set(info["drivers"]) == {"table", "robot", "fixed_camera", "mobile_camera", "host_link", "arm"}
    assert info["drivers"]["table"]["file"] == str(dest.resolve() / "drivers" / "table.yaml")
    assert isinstance(info["calibration"], list) and isinstance(info["object_library"], list)
    # the global --json flag works as well as the per-command one
    assert json.loads(labctl("--json", "--lab", str(dest), "lab", "show").stdout)["name"] == info["name"]


def test_init_refuses_to_overwrite(lab):
    r = labctl("init", str(lab))
    assert r.returncode == 2
    assert "already holds a lab workspace" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_lab_found_upward_from_cwd(lab):
    sub = lab / "runs" / "deep"
    sub.mkdir(parents=True)
    r = labctl("--json", "lab", "show", cwd=sub)
    assert json.loads(r.stdout)["lab"] == str(lab)


BROKEN = {
    "wrong type": ("lab.yaml", "marker:\n  radius_mm: big\n", "marker.radius_mm", "expected a number"),
    "unknown key": ("lab.yaml", "colour: red\n", "colour", "unknown key"),
    "missing driver": ("lab.yaml", "drivers:\n  robot: drivers/nope.yaml\n", "drivers.robot", "not found"),
    "yaml syntax": ("lab.yaml", "marker: [1, 2\n", None, "YAML does not parse"),
    "driver wrong type": ("drivers/table.yaml", "baud: fast\n", "baud", "expected an integer"),
    "driver unknown key": ("drivers/robot.yaml", "speed: 3\n", "speed", "unknown key"),
    "literal": ("drivers/table.yaml", "kind: marlin\n", "kind", "one of 'sim', 'grbl'"),
}


@pytest.mark.parametrize("case", sorted(BROKEN))
def test_broken_config_one_line_exit_2(lab, case):
    rel, text, key, words = BROKEN[case]
    (lab / rel).write_text(text)
    r = labctl("--lab", str(lab), "lab", "show")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "Traceback" not in r.stderr
    assert rel.split("/")[-1] in lines[0] and words in lines[0]
    if key:
        assert key in lines[0]
    with pytest.raises(ConfigError):
        load_lab(lab)


def test_verbose_shows_traceback(lab):
    (lab / "lab.yaml").write_text("colour: red\n")
    r = labctl("-v", "--lab", str(lab), "lab", "show")
    assert r.returncode == 2 and "Traceback" in r.stderr


def test_version():
    r = labctl("--version")
    assert r.returncode == 0 and "labctl" in r.stdout
