"""Issue 15: a safe library — no silent overwrite, atomic replace, remove, check, broken objects
skipped with one line, provenance, batch teaching. Driven out of process through the CLI."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from labctl.library.storage import load_library, load_object
from labctl.workspace import init_workspace


def labctl(*args, lab: Path):
    return subprocess.run([sys.executable, "-m", "labctl", "--lab", str(lab), *args], capture_output=True, text=True,
                          timeout=300)


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> Path:
    """The sample lab with one sample object (block) and two taught boxes (kept small: tests stay quick)."""
    root = init_workspace(tmp_path_factory.mktemp("safety") / "lab")
    for d in (root / "object_library").iterdir():
        if d.name != "block":
            shutil.rmtree(d)
    models = root.parent / "models"
    models.mkdir()
    trimesh.creation.box((40.0, 30.0, 20.0)).export(models / "box_a.stl")
    trimesh.creation.box((50.0, 35.0, 12.0)).export(models / "box b.stl")
    r = labctl("--json", "teach-object", "--model", str(models), lab=root)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert sorted(o["name"] for o in out["taught"]) == ["box_a", "box_b"]
    return root


def _snapshot(folder: Path):
    return sorted((p.relative_to(folder).as_posix(), hashlib.sha256(p.read_bytes()).hexdigest())
                  for p in folder.rglob("*") if p.is_file())


def test_batch_teach_keeps_the_model_with_its_absolute_path_and_hash(lab):
    obj = load_object(lab / "object_library" / "box_b")
    src = obj.info["source"]
    model = lab.parent / "models" / "box b.stl"
    assert src["path"] == str(model.resolve()) and Path(src["path"]).is_absolute()
    assert src["sha256"] == hashlib.sha256(model.read_bytes()).hexdigest()
    assert (lab / "object_library" / "box_b" / "model.stl").is_file()
    assert (lab / "object_library" / "library.yaml").is_file()
    # the refused 40×30×20 box: taught, fully covered, its 20 mm faces with smaller markers
    a = load_object(lab / "object_library" / "box_a")
    assert a.info["coverage"]["probability"] == 1.0 and min(m.radius for m in a.markers) < 8.0


def test_no_silent_overwrite_and_force_replaces(lab, tmp_path):
    folder = lab / "object_library" / "box_a"
    before = _snapshot(folder)
    other = tmp_path / "other.stl"
    trimesh.creation.box((45.0, 30.0, 25.0)).export(other)
    r = labctl("teach-object", "box_a", "--model", str(other), lab=lab)
    assert r.returncode == 2 and "already exists" in r.stderr and "--force" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
    assert _snapshot(folder) == before
    r = labctl("--json", "teach-object", "box_a", "--model", str(other), "--force", lab=lab)
    assert r.returncode == 0, r.stderr
    assert load_object(folder).info["source"]["sha256"] == hashlib.sha256(other.read_bytes()).hexdigest()
    assert not [p for p in folder.parent.iterdir() if p.name.startswith(".")]  # no temporary folders left


def test_a_crash_mid_teach_leaves_the_old_object_intact(lab, monkeypatch):
    """A failure while the new folder is being written (here: the contact sheet) or an interrupt while
    rendering leaves the old object byte for byte, and no temporary folder."""
    from labctl.library import storage
    from labctl.library.placement import ViewingGeometry
    from labctl.library.teach import teach_object
    from labctl.library.views import silhouette_renderer
    from labctl.sim.truth import camera_model

    lib = lab / "object_library"
    before = _snapshot(lib / "box_a")
    from labctl.config import load_lab

    cam = camera_model(load_lab(lab).mobile_camera)
    kw = dict(radius_mm=8.0, view=ViewingGeometry(n_yaw=72), standoff_mm=800.0, scale_mm_per_px=0.3136,
              library_dir=lib, sweep=False, angle_curve=False, force=True)

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(storage, "_sheet", boom)
    with pytest.raises(Exception, match="disk full"):
        teach_object("box_a", trimesh.creation.box((44.0, 33.0, 22.0)),
                     render_factory=lambda m, mk, *_: silhouette_renderer(cam, m, mk), **kw)
    monkeypatch.undo()

    def interrupted(m, mk, *_):
        def render(T):
            raise KeyboardInterrupt
        return render

    with pytest.raises(KeyboardInterrupt):
        teach_object("box_a", trimesh.creation.box((44.0, 33.0, 22.0)), render_factory=interrupted, **kw)
    assert _snapshot(lib / "box_a") == before
    assert not [p for p in lib.iterdir() if p.name.startswith(".") and p.is_dir()]


def test_broken_objects_are_skipped_with_one_line_and_named_ones_exit_2(lab, tmp_path):
    work = tmp_path / "lab"
    shutil.copytree(lab, work)
    lib = work / "object_library"
    (lib / "block" / "views" / "0.json").write_text('{"eccentricity": 0.3, "aos": [[')  # truncated
    (lib / "stray").mkdir()  # a stray empty folder
    text = (lib / "box_b" / "object.yaml").read_text()
    (lib / "box_b" / "object.yaml").write_text(text[: len(text) // 3] + "\n  - [unclosed")  # truncated YAML
    r = labctl("--json", "library", "list", lab=work)
    assert r.returncode == 0, r.stderr
    assert [o["name"] for o in json.loads(r.stdout)["objects"]] == ["box_a"]
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 3 and "Traceback" not in r.stderr
    assert any("block" in ln and "views/0.json" in ln for ln in lines)
    assert any("stray" in ln and "object.yaml" in ln for ln in lines)
    assert any("box_b" in ln and "object.yaml" in ln for ln in lines)
    for name, file in (("block", "views/0.json"), ("box_b", "object.yaml")):
        r = labctl("library", "show", name, lab=work)
        assert r.returncode == 2 and file in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = labctl("library", "check", lab=work)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "block: views/0.json" in r.stderr and "box_b: object.yaml" in r.stderr
    # every loader skips them: the run's context sees only the good object
    from labctl.config import load_lab
    from labctl.decisions.context import RunContext

    try:
        ctx = RunContext.load(load_lab(work))
    except Exception as exc:  # calibration problems are not this test's business
        pytest.skip(f"run context unavailable: {exc}")
    assert ctx.names == ["box_a"]


def test_check_names_a_changed_model_and_a_missing_image(lab, tmp_path):
    work = tmp_path / "lab"
    shutil.copytree(lab, work)
    lib = work / "object_library"
    trimesh.creation.box((41.0, 30.0, 20.0)).export(lib / "box_a" / "model.stl")
    (lib / "box_b" / "views" / "1.png").unlink()
    r = labctl("library", "check", lab=work)
    assert r.returncode == 2
    assert "box_a: model.stl differs" in r.stderr and "box_b: missing views/1.png" in r.stderr


def test_remove(lab, tmp_path):
    work = tmp_path / "lab"
    shutil.copytree(lab, work)
    r = labctl("library", "remove", "box_b", lab=work)
    assert r.returncode == 0, r.stderr
    assert sorted(load_library(work / "object_library")) == ["block", "box_a"]
    r = labctl("library", "remove", "box_b", lab=work)
    assert r.returncode == 2 and "no object 'box_b'" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_contact_sheet_labels_and_ambiguity_groups(lab):
    """Opposite faces of a box look alike: they form ambiguity groups recorded in library.yaml and on the
    object (the contact sheet marks them)."""
    import yaml

    data = yaml.safe_load((lab / "object_library" / "library.yaml").read_text())
    groups = data["ambiguity_groups"]
    assert any({"box_a#0", "box_a#1"} <= set(g) for g in groups)  # the two largest faces, opposite
    obj = load_object(lab / "object_library" / "box_a")
    assert obj.info["ambiguity_groups"]
    sheet = (lab / "object_library" / "box_a" / "contact_sheet.png")
    import cv2

    img = cv2.imread(str(sheet))
    assert img is not None and (np.abs(img.astype(int) - (0, 140, 255)).sum(axis=2) == 0).any()  # group frame
