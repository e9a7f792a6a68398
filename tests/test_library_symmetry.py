"""Resting poses merged by the part's symmetry, the probability floor, and the coverage refusal."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from labctl.geometry import CameraModel
from labctl.library import samples
from labctl.library.model import extrude_polygon, merge_symmetric_poses, stable_poses, validate_model
from labctl.library.placement import Marker, ViewingGeometry, check_coverage
from labctl.library.teach import POSE_SYMMETRY_TOL_MM, CoverageRefused, markers_map_onto_themselves, teach_object
from labctl.library.views import mm_per_px, silhouette_renderer

ROOT = Path(__file__).resolve().parents[1]
CAM = CameraModel(f=25.0, kappa1=-0.0008, sx=1.0, cx=319.5, cy=239.5, dx=0.0098, dy=0.0098, ncx=640, nfx=640)
VIEW = ViewingGeometry()


def _teach(name, mesh, **kw):
    return teach_object(name, mesh, radius_mm=8.0, view=VIEW, standoff_mm=600.0, scale_mm_per_px=mm_per_px(CAM, 600),
                        render_factory=lambda m, mk, *_: silhouette_renderer(CAM, m, mk), sweep=False, **kw)


def _cylinder(sections: int) -> trimesh.Trimesh:
    return validate_model(trimesh.creation.cylinder(radius=30, height=40, sections=sections), marker_radius_mm=8)


def _maps_mesh_onto_itself(mesh, S, tol):
    moved = trimesh.transform_points(mesh.vertices, S)
    d, _ = cKDTree(mesh.vertices).query(moved)
    return float(d.max()) <= tol


def test_a_cylinder_has_two_resting_poses_up_to_symmetry():
    mesh = _cylinder(96)
    poses = stable_poses(mesh)
    classes = merge_symmetric_poses(mesh, poses, tol_mm=POSE_SYMMETRY_TOL_MM)
    assert len(poses) == 98
    assert sorted(len(c) for c in classes) == [2, 96]
    assert sum(p for c in classes for _, p, _ in c) == pytest.approx(1.0)
    for c in classes:  # each S is a symmetry of the whole mesh (checked on every vertex, not just the hull)
        for T, _, S in c:
            assert _maps_mesh_onto_itself(mesh, S, 1e-3)
            assert np.allclose(T @ S, c[0][0] @ np.linalg.inv(c[0][0]) @ T @ S)  # well-formed 4x4


@pytest.mark.parametrize("seed", range(4))
def test_an_asymmetric_part_keeps_every_pose(seed):
    rng = np.random.default_rng(seed)
    mesh = validate_model(trimesh.convex.convex_hull(rng.uniform(-30, 30, (12, 3))), marker_radius_mm=2)
    poses = stable_poses(mesh)
    assert len(merge_symmetric_poses(mesh, poses, tol_mm=POSE_SYMMETRY_TOL_MM)) == len(poses)


def test_mirror_image_poses_are_not_merged():
    # a right-angled wedge with unequal legs, extruded: resting on either leg face differs, and its two
    # triangular ends are mirror images, which no rotation about the vertical relates
    mesh = validate_model(extrude_polygon(np.array([[0, 0], [60, 0], [0, 25]], float), 40), marker_radius_mm=4)
    poses = stable_poses(mesh)
    classes = merge_symmetric_poses(mesh, poses, tol_mm=POSE_SYMMETRY_TOL_MM)
    for c in classes:
        for _, _, S in c:
            assert _maps_mesh_onto_itself(mesh, S, 1e-3)
            assert np.linalg.det(S[:3, :3]) == pytest.approx(1.0)  # rotations only, never a reflection


def test_merged_coverage_equals_the_coverage_over_every_pose():
    mesh = _cylinder(24)
    poses = stable_poses(mesh)
    classes = merge_symmetric_poses(mesh, poses, tol_mm=POSE_SYMMETRY_TOL_MM)
    markers = [Marker(0, np.array([0.0, 0, 20]), np.array([0.0, 0, 1]), 8.0),
               Marker(1, np.array([0.0, 0, -20]), np.array([0.0, 0, -1]), 8.0)]
    every = (check_coverage(mesh, [T for T, _ in poses], markers, VIEW) > 0).mean(axis=1)
    full = float(np.dot([p for _, p in poses], every))
    reps = (check_coverage(mesh, [c[0][0] for c in classes], markers, VIEW) > 0).mean(axis=1)
    merged = float(np.dot([sum(p for _, p, _ in c) for c in classes], reps))
    assert merged == pytest.approx(full, abs=2 / 360)  # one yaw sample either way


def test_markers_less_symmetric_than_the_part_split_its_poses():
    mesh = validate_model(extrude_polygon(samples.regular_polygon(6, 55), 40), marker_radius_mm=8)
    classes = merge_symmetric_poses(mesh, stable_poses(mesh), tol_mm=POSE_SYMMETRY_TOL_MM)
    side = max(classes, key=len)
    assert len(side) == 6  # the six flats
    caps = [Marker(0, np.array([0.0, 0, 40]), np.array([0.0, 0, 1]), 8.0),
            Marker(1, np.array([0.0, 0, 0]), np.array([0.0, 0, -1]), 8.0)]
    assert all(markers_map_onto_themselves(caps, S) for _, _, S in side)
    one_flat = caps + [Marker(2, np.array([27.5 * np.cos(np.pi / 6), 27.5 * np.sin(np.pi / 6), 20]) * [1, 1, 1],
                              np.array([np.cos(np.pi / 6), np.sin(np.pi / 6), 0.0]), 8.0)]
    assert not all(markers_map_onto_themselves(one_flat, S) for _, _, S in side)


def test_teaching_a_cylinder_merges_poses_and_refuses_low_coverage():
    mesh = _cylinder(48)
    with pytest.raises(CoverageRefused, match="below library.min_coverage"):
        _teach("cyl", mesh, min_coverage=0.9)
    obj = _teach("cyl", mesh, min_coverage=0.9, accept_partial=True)
    assert len(obj.stable_poses) == 2 and obj.info["accepted_partial"]
    assert obj.info["resting_poses"]["computed"] == 50 and obj.info["resting_poses"]["merged"] == 48


def test_the_probability_floor_leaves_out_rare_poses_and_says_so():
    mesh = _cylinder(48)
    p_cap = sum(p for T, p in stable_poses(mesh) if abs(T[2, 2]) > 0.99)
    obj = _teach("cyl", mesh, pose_probability_floor=min(p_cap, 1 - p_cap) + 1e-3)
    assert len(obj.stable_poses) == 1
    assert obj.info["resting_poses"]["dropped_probability"] == pytest.approx(min(p_cap, 1 - p_cap), abs=1e-5)
    assert any("pose_probability_floor" in w for w in obj.info["warnings"])


def _labctl(*args, lab):
    return subprocess.run([sys.executable, "-m", "labctl", "--lab", str(lab), *args], capture_output=True,
                          text=True, timeout=900)


def test_teach_object_refuses_a_round_part_in_one_line_and_writes_nothing(tmp_path):
    lab = tmp_path / "lab"
    lab.mkdir()
    for name in ("lab.yaml", "drivers", "calibration", "object_library"):
        src = ROOT / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, lab / name)
    model = tmp_path / "cyl96.stl"
    trimesh.creation.cylinder(radius=30, height=40, sections=96).export(model)
    before = sorted(p.name for p in (lab / "object_library").iterdir())
    res = _labctl("teach-object", "cyl96", "--model", str(model), lab=lab)
    assert res.returncode == 1, res.stderr
    err = [line for line in res.stderr.splitlines() if line.startswith("labctl: error:")]
    assert len(err) == 1 and "--accept-partial" in err[0] and "44." in err[0]
    assert sorted(p.name for p in (lab / "object_library").iterdir()) == before
    res = _labctl("teach-object", "cyl96", "--model", str(model), "--accept-partial", lab=lab)
    assert res.returncode == 0, res.stderr
    assert "ambiguity_groups" not in res.stdout or all("cyl96" in line for line in res.stdout.splitlines()
                                                       if "ambiguity_groups" in line)
    assert _labctl("library", "check", lab=lab).returncode == 0


def test_library_check_reports_an_object_below_the_coverage_setting(tmp_path):
    from labctl.library.storage import check_library

    obj = teach_object("cyl", _cylinder(48), radius_mm=8.0, view=VIEW, standoff_mm=600.0,
                       scale_mm_per_px=mm_per_px(CAM, 600), sweep=False, library_dir=tmp_path,
                       render_factory=lambda m, mk, *_: silhouette_renderer(CAM, m, mk))
    assert obj.info["coverage"]["probability"] < 0.9
    ok, problems = check_library(tmp_path, min_coverage=0.9)
    assert ok == [] and len(problems) == 1 and "below library.min_coverage" in problems[0]
    assert check_library(tmp_path)[1] == []  # no setting, no such problem
