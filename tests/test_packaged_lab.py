"""The sample lab inside an installed package is read-only: records go to the per-user data folder,
and commands that would write a calibration or a library entry refuse in one line (issue 17)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from labctl.config import load_lab
from labctl.workspace import sample_lab_path


@pytest.fixture
def packaged(tmp_path):
    """A copy laid out as in a wheel: <site>/labctl/sample_lab with labctl/__init__.py beside it."""
    pkg = tmp_path / "site" / "labctl"
    shutil.copytree(sample_lab_path(), pkg / "sample_lab",
                    ignore=shutil.ignore_patterns("runs", ".git", "labctl", "tests", "docs", ".venv"))
    (pkg / "__init__.py").write_text("")
    return pkg / "sample_lab"


def test_records_of_the_packaged_lab_go_to_the_user_data_folder(packaged, tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    lab = load_lab(packaged)
    assert lab.is_packaged
    assert lab.runs_dir == tmp_path / "data" / "labctl" / "runs"


def test_teach_into_the_packaged_lab_is_refused(packaged, tmp_path):
    model = tmp_path / "box.stl"
    import trimesh

    trimesh.creation.box((40, 30, 20)).export(model)
    before = sorted(p.name for p in (packaged / "object_library").iterdir())
    p = subprocess.run([sys.executable, "-m", "labctl", "--lab", str(packaged), "teach-object", "box",
                        "--model", str(model)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "labctl init" in lines[0]
    assert sorted(p.name for p in (packaged / "object_library").iterdir()) == before


def test_outside_any_workspace_records_go_to_the_user_folder_not_the_source_tree(tmp_path):
    """An editable install's sample lab is its source tree: with no lab.yaml at or above the working
    folder, a run's record goes to the per-user data folder and nothing is written into the tree."""
    import os

    env = {**os.environ, "XDG_DATA_HOME": str(tmp_path / "xdg")}
    work = tmp_path / "elsewhere"
    work.mkdir()
    repo_runs = Path(__file__).resolve().parents[1] / "runs"
    before = set(repo_runs.iterdir()) if repo_runs.is_dir() else set()
    r = subprocess.run([sys.executable, "-m", "labctl", "--json", "run", "--virtual", "--trajectory", "line"],
                       capture_output=True, text=True, cwd=work, env=env, timeout=300)
    assert r.returncode in (0, 1), r.stderr
    record = Path(json.loads(r.stdout)["record"])
    assert record.parent == tmp_path / "xdg" / "labctl" / "runs"
    assert (set(repo_runs.iterdir()) if repo_runs.is_dir() else set()) == before
    t = subprocess.run([sys.executable, "-m", "labctl", "teach-object", "x", "--model", "nothing.stl"],
                       capture_output=True, text=True, cwd=work, env=env, timeout=120)
    assert t.returncode == 2 and "labctl init DIR" in t.stderr
