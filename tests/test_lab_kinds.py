"""Device kinds across a lab: mixing simulated and real devices, a lab without a table, the stream kind."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest
import yaml

from labctl.config import ConfigError, load_lab
from labctl.workspace import init_workspace, sample_lab_path


@pytest.fixture(scope="module")
def sample():
    return load_lab(sample_lab_path())


def _with(lab, **roles):
    return dataclasses.replace(lab, **{r: (None if v is None else dataclasses.replace(getattr(lab, r), **v))
                                       for r, v in roles.items()})


def test_all_sim_and_all_real_labs_have_no_mixing_problem(sample):
    assert sample.is_simulated and sample.mixed_kinds_problem() is None
    real = _with(sample, table={"kind": "grbl", "port": "/dev/ttyUSB0"}, robot={"kind": "serial", "port": "/dev/ttyS0"},
                 fixed_camera={"kind": "v4l2", "device": 0}, mobile_camera={"kind": "stream", "url": "http://x/"})
    assert not real.is_simulated and real.mixed_kinds_problem() is None


@pytest.mark.parametrize("roles, words", [
    ({"table": {"kind": "grbl", "port": "/dev/ttyUSB0"}}, ["fixed_camera is simulated", "static world"]),
    ({"robot": {"kind": "serial", "port": "/dev/ttyS0"}}, ["mobile_camera is simulated", "robot"]),
    ({"fixed_camera": {"kind": "v4l2", "device": 0}}, ["fixed_camera is real", "never see it move"]),
])
def test_a_sim_camera_watching_real_motion_or_the_reverse_is_refused(sample, roles, words):
    problem = _with(sample, **roles).mixed_kinds_problem()
    assert problem is not None and all(w in problem for w in words), problem


def test_devices_says_a_sim_camera_in_a_real_lab_shows_a_static_world(sample):
    from labctl.runtime.devices import check_device

    row = check_device("fixed_camera", _with(sample, table={"kind": "grbl", "port": "/dev/labctl-none"}))
    assert row["ok"] and "static world" in row["verdict"]
    assert "static" not in check_device("fixed_camera", sample)["verdict"]


def test_a_lab_without_a_table_loads_and_is_checked_without_it(tmp_path, sample):
    from labctl.runtime.devices import check_devices

    root = init_workspace(tmp_path / "lab")
    cfg = yaml.safe_load((root / "lab.yaml").read_text())
    cfg["drivers"]["table"] = None
    (root / "lab.yaml").write_text(yaml.safe_dump(cfg))
    lab = load_lab(root)
    assert lab.table is None and "table" not in lab.kinds and lab.is_simulated
    rows = check_devices(_with(lab, robot={"kind": "serial", "port": "/dev/labctl-none"},
                               fixed_camera={"kind": "stream", "url": "http://127.0.0.1:9/x.mjpg"},
                               mobile_camera={"kind": "stream", "url": "http://127.0.0.1:9/y.mjpg"}))
    assert [r["role"] for r in rows] == ["robot", "fixed_camera", "mobile_camera"]
    assert not any(r["ok"] for r in rows) and "127.0.0.1:9" in rows[1]["verdict"]
    cfg["drivers"]["robot"] = None  # only the table may be absent
    (root / "lab.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(ConfigError, match="drivers.robot"):
        load_lab(root)


def test_run_on_a_lab_without_a_table_accepts_only_external_in_one_line(tmp_path):
    root = init_workspace(tmp_path / "lab")
    cfg = yaml.safe_load((root / "lab.yaml").read_text())
    cfg["drivers"]["table"] = None
    (root / "lab.yaml").write_text(yaml.safe_dump(cfg))
    r = subprocess.run([sys.executable, "-m", "labctl", "--lab", str(root), "run", "--trajectory", "line"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "external" in r.stderr


def test_stream_camera_needs_a_url(tmp_path):
    root = init_workspace(tmp_path / "lab")
    f = root / "drivers" / "fixed_camera.yaml"
    f.write_text(yaml.safe_dump({**yaml.safe_load(f.read_text()), "kind": "stream"}))
    with pytest.raises(ConfigError, match="url"):
        load_lab(root)
