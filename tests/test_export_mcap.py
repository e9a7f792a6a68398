"""``labctl export RUN --mcap`` read back with the mcap package's own reader; ``labctl runs``; run ids."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from labctl.records import load_run
from labctl.records.mcap_export import SCHEMAS, TOPICS, quaternion_from_matrix

ROOT = Path(__file__).resolve().parents[1]


def _labctl(*args, lab: Path, check=True) -> subprocess.CompletedProcess:
    res = subprocess.run([sys.executable, "-m", "labctl", "--lab", str(lab), *args], capture_output=True, text=True,
                         timeout=600)
    if check and res.returncode != 0:
        raise AssertionError(f"labctl {' '.join(args)} exited {res.returncode}: {res.stderr}")
    return res


@pytest.fixture(scope="module")
def lab_with_run(tmp_path_factory) -> tuple[Path, Path]:
    """A copy of the sample lab holding one virtual run's record."""
    lab = tmp_path_factory.mktemp("lab")
    for name in ("lab.yaml", "drivers", "calibration", "object_library"):
        src = ROOT / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, lab / name)
    (lab / "runs").mkdir()
    _labctl("run", "--virtual", "--trajectory", "line", "--seed", "3", lab=lab)
    (run,) = [p for p in (lab / "runs").iterdir() if (p / "meta.json").is_file()]
    return lab, run


def test_mcap_round_trips_through_the_mcap_reader(lab_with_run, tmp_path):
    from mcap.reader import make_reader

    lab, run = lab_with_run
    out = tmp_path / "run.mcap"
    _labctl("export", run.name, "--mcap", str(out), lab=lab)  # by id
    data = load_run(run)
    with open(out, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == set(TOPICS)
        for topic, ch in channels.items():
            schema = summary.schemas[ch.schema_id]
            assert schema.name == TOPICS[topic] and schema.encoding == "jsonschema"
            assert json.loads(schema.data)["title"] == schema.name
            assert ch.message_encoding == "json"
        by_topic: dict[str, list[dict]] = {t: [] for t in TOPICS}
        log_times = []
        for _schema, ch, msg in reader.iter_messages(log_time_order=False):
            by_topic[ch.topic].append(json.loads(msg.data))
            log_times.append(msg.log_time)
    assert log_times == sorted(log_times)
    assert len(by_topic["/labctl/events"]) == len(data.events)
    assert [e["event"] for e in by_topic["/labctl/events"]] == [e["event"] for e in data.events]
    n_scene = len(data.of("track")) + len([e for e in data.of("predict") if e.get("path")]) + len(data.of("segment"))
    assert len(by_topic["/scene"]) == n_scene
    assert len(by_topic["/tf"]) == len(data.of("capture_request"))
    assert len(by_topic["/log"]) >= len(data.of("stage")) + len(data.of("identity"))
    views = sorted(p for s, p in data.images.items() if s.startswith("view_"))
    assert len(by_topic["/mobile_camera/image"]) == len(views) > 0
    assert sorted(base64.b64decode(m["data"]) for m in by_topic["/mobile_camera/image"]) == \
        sorted(p.read_bytes() for p in views)
    # the first camera pose: metres, and the rotation of the record's T_w_c2
    T = np.array(data.of("capture_request")[0]["T_w_c2"])
    tf = by_topic["/tf"][0]
    assert np.allclose([tf["translation"][k] for k in "xyz"], T[:3, 3] / 1000.0)
    q = [tf["rotation"][k] for k in "xyzw"]
    assert np.allclose(Rotation.from_quat(q).as_matrix(), T[:3, :3], atol=1e-6)
    track = data.of("track")[0]
    sphere = by_topic["/scene"][0]["entities"][0]["spheres"][0]["pose"]["position"]
    assert np.allclose([sphere["x"], sphere["y"]], [track["x"] / 1000, track["y"] / 1000])


def test_every_schema_written_is_declared():
    assert set(TOPICS.values()) <= set(SCHEMAS)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 1e-3))
def test_quaternion_matches_scipy(v):
    R = Rotation.from_quat(v).as_matrix()
    q = quaternion_from_matrix(R)
    assert q["w"] >= 0
    assert np.allclose(Rotation.from_quat([q[k] for k in "xyzw"]).as_matrix(), R, atol=1e-9)


def test_export_never_overwrites_without_force(lab_with_run, tmp_path):
    lab, run = lab_with_run
    out = tmp_path / "keep.mcap"
    out.write_bytes(b"the user's file")
    res = _labctl("export", "last", "--mcap", str(out), lab=lab, check=False)
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "--force" in res.stderr
    assert out.read_bytes() == b"the user's file"
    _labctl("export", "last", "--mcap", str(out), "--force", lab=lab)
    assert out.read_bytes()[:8] == b"\x89MCAP0\r\n"
    assert not list(tmp_path.glob(".*partial"))


@pytest.mark.parametrize("cmd", ["report", "replay", "export"])
def test_run_ids_and_bad_runs_are_one_line_exit_2(lab_with_run, cmd, tmp_path):
    lab, run = lab_with_run
    extra = ["--mcap", str(tmp_path / "x.mcap")] if cmd == "export" else []
    for bad in ("no-such-run", str(lab)):
        res = _labctl(cmd, bad, *extra, lab=lab, check=False)
        assert res.returncode == 2, res.stderr
        assert res.stderr.startswith("labctl: error:") and res.stderr.count("\n") == 1
        assert "labctl runs list" in res.stderr
    assert _labctl(cmd, run.name, *extra, lab=lab).returncode == 0


def test_runs_list_show_prune(lab_with_run):
    lab, run = lab_with_run
    listed = json.loads(_labctl("runs", "list", "--json", lab=lab).stdout)
    assert [r["id"] for r in listed["runs"]] == [run.name]
    assert listed["runs"][0]["correct"] in (True, False) and listed["bytes"] > 0
    shown = json.loads(_labctl("runs", "show", "last", "--json", lab=lab).stdout)
    assert shown["id"] == run.name and shown["finished"]
    copy = run.parent / "20000101T000000Z"  # an older record
    shutil.copytree(run, copy)
    dry = json.loads(_labctl("runs", "prune", "--keep", "1", "--dry-run", "--json", lab=lab).stdout)
    assert dry["removed"] == [copy.name] and copy.is_dir()
    done = json.loads(_labctl("runs", "prune", "--keep", "1", "--json", lab=lab).stdout)
    assert done["removed"] == [copy.name] and not copy.exists() and run.is_dir()
