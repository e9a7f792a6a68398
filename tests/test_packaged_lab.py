"""The sample lab inside an installed package is read-only: records go to the per-user data folder,
and commands that would write a calibration or a library entry refuse in one line (issue 17)."""

from __future__ import annotations

import shutil
import subprocess
import sys

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
