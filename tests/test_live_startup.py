"""Live start-up: the command's and the workers' library check read the models without trimesh, and say the
same as trimesh does about them; the simulated lab still gets trimesh's own mesh; the table, connected beside
the robot and the camera, fails the run in one line."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from labctl.library.storage import LibraryError, _binary_stl_watertight, load_library
from labctl.records import load_run
from labctl.workspace import init_workspace


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    return init_workspace(tmp_path_factory.mktemp("startup") / "lab")


def test_the_run_commands_library_and_calibration_check_imports_no_trimesh(lab):
    # what ``labctl run`` imports and loads before its simulated lab can start (labctl/cli/run.py), in a fresh
    # interpreter; trimesh (scipy.spatial, networkx, shapely) was 1.0 s of CPU of it
    code = (f"import sys; import labctl.cli.run, labctl.records, labctl.cli.report, labctl.runtime.live; "
            f"from labctl.config import load_lab; from labctl.decisions.context import RunContext; "
            f"from labctl.decisions.recognizer import Recognizer; "
            f"ctx = RunContext.load(load_lab({str(lab)!r})); assert len(ctx.library) >= 3; "
            f"print(sorted(m for m in ('trimesh', 'scipy.spatial', 'networkx') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]", out.stdout


def test_the_numpy_check_agrees_with_trimesh_on_closed_and_opened_meshes(tmp_path):
    rng = np.random.default_rng(7)
    meshes = [trimesh.creation.box((41.0, 30.0, 20.0)), trimesh.creation.icosphere(2, radius=25.0),
              trimesh.creation.cylinder(12.0, 40.0, sections=24), trimesh.creation.annulus(8.0, 20.0, 10.0)]
    cases = []
    for i, mesh in enumerate(meshes):
        cases.append((f"closed{i}", mesh))
        drop = rng.integers(len(mesh.faces))  # one triangle missing: open along its three edges
        cases.append((f"open{i}", trimesh.Trimesh(mesh.vertices, np.delete(mesh.faces, drop, axis=0), process=False)))
        doubled = np.vstack([mesh.faces, mesh.faces[:1]])  # an edge shared by three or four triangles
        cases.append((f"doubled{i}", trimesh.Trimesh(mesh.vertices, doubled, process=False)))
    for name, mesh in cases:
        path = tmp_path / f"{name}.stl"
        mesh.export(path)
        expected = trimesh.load(path, force="mesh").is_watertight  # the oracle: what the loader said before
        if expected:
            assert _binary_stl_watertight(path, name) is True, name
        else:
            with pytest.raises(LibraryError, match=f"{name}: model.stl is empty or not watertight"):
                _binary_stl_watertight(path, name)


def test_not_binary_stl_is_left_to_trimesh_and_garbage_is_a_library_error(tmp_path):
    ascii_stl = tmp_path / "a.stl"
    ascii_stl.write_text(trimesh.exchange.stl.export_stl_ascii(trimesh.creation.box((10.0, 10.0, 10.0))))
    assert _binary_stl_watertight(ascii_stl, "a") is False
    garbage = tmp_path / "g.stl"
    garbage.write_bytes(b"\x00" * 80 + np.uint32(3).tobytes() + b"\x01" * 20)  # claims 3 triangles, has none
    assert _binary_stl_watertight(garbage, "g") is False


def test_the_lazy_mesh_is_trimeshs_own_and_a_model_broken_later_is_a_clear_error(tmp_path):
    lab = init_workspace(tmp_path / "lab")  # its own: a model is broken below
    lib = load_library(lab / "object_library")
    name = sorted(lib)[0]
    obj = lib[name]
    assert obj.loaded_mesh is None  # nothing read until a mesh is asked for
    direct = trimesh.load(obj.folder / "model.stl", force="mesh")
    assert np.array_equal(obj.mesh.vertices, direct.vertices) and np.array_equal(obj.mesh.faces, direct.faces)
    assert obj.mesh is obj.mesh  # read once

    other = load_library(lab / "object_library")[name]
    (obj.folder / "model.stl").write_bytes(b"solid broken\n")
    with pytest.raises(LibraryError, match=f"{name}: "):
        _ = other.mesh


@pytest.mark.timeout(180)
@pytest.mark.skipif(sys.platform != "linux", reason="the simulated lab's ptys need Linux")
def test_a_table_that_fails_while_connecting_beside_the_robot_ends_the_run_in_one_line(lab, tmp_path):
    # the predictor opens the table in a thread while its main thread opens the robot and the camera; a status
    # report (~60 bytes at 9600 bps) cannot come within 1 ms, so the table's connection fails there
    bad = tmp_path / "lab"
    shutil.copytree(lab, bad, ignore=shutil.ignore_patterns("runs"))
    table = bad / "drivers" / "table.yaml"
    text = table.read_text()
    assert "\ntimeout_s: 5.0\n" in text
    table.write_text(text.replace("\ntimeout_s: 5.0\n", "\ntimeout_s: 0.001\n"))
    run = subprocess.run([sys.executable, "-m", "labctl", "--lab", str(bad), "run", "--trajectory", "line",
                          "--seed", "1"], capture_output=True, text=True, timeout=150)
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 3, run.stderr[-2000:]
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr[-2000:]
    cause = lines[0].split(": robot stopped", 1)[0]  # the first failure: a write or a status query timing out
    assert cause.startswith("labctl: error: predictor: ") and "grbl@" in cause and "timeout" in cause.lower(), cause
    assert "robot stopped (confirmed)" in lines[0], lines[0]
    record = load_run(lines[0].rsplit("record kept in ", 1)[1])
    assert record.of("table_program") == [] and record.of("track") == []  # nothing started, nothing tracked


@pytest.mark.timeout(400)
@pytest.mark.skipif(sys.platform != "linux", reason="the simulated lab's ptys need Linux")
def test_the_startup_bench_reads_each_runs_phases_from_its_record():
    from labctl.bench.startup import import_breakdown, measure

    res = measure(1, cold=False)
    (run,) = res["warm"]
    assert run["exit_code"] == 0 and run["identity"], run
    phases = run["startup_s"]
    # stamps by three processes (command, simulated lab, predictor) against the command's /proc start time
    assert list(phases)[-1] == "first_tracked_frame" and 0 < phases["sim_lab_starting"] < phases["first_tracked_frame"]
    assert phases["first_tracked_frame"] < run["command_s"]  # the whole command, timed by the bench's own clock
    assert res["warm_first_tracked_frame_s"] == [phases["first_tracked_frame"]]
    assert "error" in res["cold"]  # not asked for: said so, not guessed
    imports = import_breakdown()
    assert imports["total_s"] > 0 and "labctl.cli" in imports["labctl_roots_s"]
    assert "trimesh" not in imports["largest_packages_s"]
