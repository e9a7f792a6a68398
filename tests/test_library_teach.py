"""Teaching objects: models, stable poses, marker placement, storage, bad input (issue 5)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh
import yaml

from labctl.geometry import CameraModel
from labctl.library import samples
from labctl.library.model import ModelError, extrude_polygon, load_model, stable_poses, validate_model
from labctl.library.placement import (
    ViewingGeometry,
    candidate_sites,
    check_coverage,
    check_overhead_coverage,
    overhead_directions_o,
    plan_markers,
    segments_blocked,
    set_cover,
)
from labctl.library.storage import LibraryError, load_library, load_object
from labctl.library.teach import teach_object
from labctl.library.views import mm_per_px, silhouette_renderer

CAM = CameraModel(f=25.0, kappa1=-0.0008, sx=1.0, cx=319.5, cy=239.5, dx=0.0098, dy=0.0098, ncx=640, nfx=640)
VIEW = ViewingGeometry()
PROFILES = {
    "L": samples.l_profile(60, 50, 25, 0),
    "T": samples.t_profile(70, 60, 25, 30),
    "hex": samples.regular_polygon(6, 55),
    "triangle": samples.regular_polygon(3, 45),
    "trapezoid": samples.trapezoid(70, 35, 40),
}


def _teach(name, mesh, library_dir=None, **kw):
    return teach_object(name, mesh, radius_mm=8.0, view=VIEW, standoff_mm=600.0, scale_mm_per_px=mm_per_px(CAM, 600),
                        render_factory=lambda m, mk, *_: silhouette_renderer(CAM, m, mk), library_dir=library_dir,
                        sweep=False, **kw)


def test_set_cover_exact_is_minimal_by_brute_force():
    rng = np.random.default_rng(3)
    for _ in range(5):
        A = rng.random((40, 9)) < 0.3
        A[np.arange(40), rng.integers(0, 9, 40)] = True
        chosen, method, _ = set_cover(A)
        assert method == "exact" and A[:, chosen].any(axis=1).all()
        best = next(k for k in range(1, 10) for c in itertools.combinations(range(9), k) if A[:, c].any(axis=1).all())
        assert len(chosen) == best


def test_greedy_cover_beyond_exact_limit_covers_and_reports_bound():
    A = np.eye(6, dtype=bool)[:, [0, 1, 2, 3, 4, 5, 0, 1]]
    chosen, method, bound = set_cover(A, exact_max_sites=2)
    assert method == "greedy" and A[:, chosen].any(axis=1).all() and bound >= 1.0


def test_segment_blocking_against_a_cube():
    tris = trimesh.creation.box((10, 10, 10)).triangles
    o = np.array([[-20.0, 0, 0], [-20.0, 20, 0]])
    t = np.array([[20.0, 0, 0], [20.0, 20, 0]])
    assert segments_blocked(o, t, tris).tolist() == [True, False]


def test_box_stable_poses_and_marker_sites():
    box = validate_model(trimesh.creation.box((40, 40, 35)), marker_radius_mm=8)
    poses = stable_poses(box)
    assert len(poses) == 6 and sum(p for _, p in poses) == pytest.approx(1.0)
    for T, _ in poses:
        assert trimesh.transform_points(box.vertices, T)[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    sites = candidate_sites(box, 8.0)
    assert len(sites) == 6
    for s in sites:  # face centres of the box
        assert np.allclose(np.abs(s.center), np.abs(s.normal) * [20, 20, 17.5], atol=0.5)


@pytest.mark.parametrize("profile", sorted(PROFILES))
def test_teaching_extruded_profiles_covers_every_pose_and_yaw(profile):
    mesh = extrude_polygon(np.array(PROFILES[profile], float), 45.0)
    obj = _teach(profile, mesh)
    Ts = [T for T, _ in obj.stable_poses]
    counts = check_coverage(obj.mesh, Ts, obj.markers, VIEW, n_yaw=360)
    assert counts.min() >= 1  # brute force over stable poses × 360 yaw steps
    assert check_overhead_coverage(obj.mesh, Ts, obj.markers, VIEW).min() >= 1  # and the overhead camera's cone
    assert obj.info["placement"]["overhead"]["min_tracked_markers"] >= 1
    assert obj.info["placement"]["method"] == "exact"
    assert len(obj.views) == len(obj.markers)


def _brute_force_minimum(mesh, poses, view, candidates):
    """Smallest subset of the candidate sites meeting both requirements, by enumeration (72 yaws
    with the planner's obliquity margin for the initial view; 1 + 4×72 directions of the overhead cone)."""
    from labctl.library.placement import overhead_visibility, view_directions_o, visibility_matrix

    Ts = [T for T, _ in poses]
    init = visibility_matrix(mesh, candidates, view_directions_o(Ts, view.angle_deg, 72),  # the planner's margin
                             distance_mm=view.distance_mm, max_obliquity_deg=view.max_obliquity_deg - 2.0)
    over = overhead_visibility(mesh, candidates, Ts, view, n_azimuth=72, n_rings=4)
    rows = np.vstack([init, over])
    for k in range(1, len(candidates) + 1):
        for c in itertools.combinations(range(len(candidates)), k):
            if rows[:, c].any(axis=1).all():
                return k
    return None


@pytest.mark.parametrize("name", ["wedge", "tee"])
def test_exact_marker_count_is_minimal_over_candidates(name):
    """Both requirement families: (a) initial view at every pose × yaw, (b) overhead tracking in every pose."""
    mesh = validate_model(samples.sample_objects()[name], marker_radius_mm=8)
    poses = stable_poses(mesh)
    view = ViewingGeometry(n_yaw=72)
    r = plan_markers(mesh, poses, 8.0, view)
    assert r.method == "exact" and r.min_overhead_visible >= 1
    assert len(r.markers) == _brute_force_minimum(mesh, poses, view, r.candidates)
    # and the chosen markers pass the fine brute-force checks of both requirements
    Ts = [T for T, _ in poses]
    assert check_coverage(mesh, Ts, r.markers, view).min() >= 1
    assert check_overhead_coverage(mesh, Ts, r.markers, view).min() >= 1


def test_overhead_cone_directions_are_within_the_cone_of_the_vertical():
    rng = np.random.default_rng(1)
    from labctl.geometry import rotvec_to_matrix

    Ts = [np.eye(4)] + [np.block([[rotvec_to_matrix(rng.normal(size=3)), np.zeros((3, 1))], [np.zeros((1, 3)), 1]])
                        for _ in range(5)]
    d = overhead_directions_o(Ts, 10.0, n_azimuth=36, n_rings=3)
    assert d.shape == (6, 1 + 3 * 36, 3) and np.allclose(np.linalg.norm(d, axis=2), 1.0)
    for T, dd in zip(Ts, d, strict=True):
        up = dd @ T[:3, :3].T  # back to W
        tilt = np.degrees(np.arccos(np.clip(up[:, 2], -1, 1)))
        assert tilt.max() == pytest.approx(10.0) and tilt.min() == pytest.approx(0.0, abs=1e-4)


def test_overhead_camera_on_a_box_needs_the_top_face_of_every_resting_pose():
    """Ground truth: looking down within 10°, the overhead camera can track only the marker on the
    upward face (the side faces are 80–100° off its view), so a box needs one marker per face,
    whereas the initial-view requirement alone needs fewer and leaves some resting pose untracked."""
    box = validate_model(trimesh.creation.box((40, 40, 35)), marker_radius_mm=8)
    poses = stable_poses(box)
    Ts = [T for T, _ in poses]
    without = plan_markers(box, poses, 8.0, ViewingGeometry(n_yaw=72, overhead_distance_mm=None))
    assert len(without.markers) < 6 and check_overhead_coverage(box, Ts, without.markers, VIEW).min() == 0
    r = plan_markers(box, poses, 8.0, ViewingGeometry(n_yaw=72))
    assert len(r.markers) == 6
    for T in Ts:  # in each pose, the tracked marker is the one facing up
        tracked = check_overhead_coverage(box, [T], r.markers, VIEW)
        up = [m for m in r.markers if (T[:3, :3] @ m.normal)[2] > 0.99]
        assert tracked.tolist() == [1] and len(up) == 1


def test_a_pose_no_face_can_serve_overhead_is_reported_untracked():
    """The wedge resting on a slanted side shows its steepest upward face 48.7° off vertical: with a 40°
    tracking limit that pose cannot be served overhead. Placement still covers the initial view and
    every other pose overhead, and names the untracked pose (the tracker then follows red pixels)."""
    mesh = validate_model(samples.sample_objects()["wedge"], marker_radius_mm=8)
    poses = stable_poses(mesh)
    Ts = [T for T, _ in poses]
    strict = ViewingGeometry(n_yaw=72, overhead_max_tilt_deg=40.0)
    r = plan_markers(mesh, poses, 8.0, strict)
    assert r.untracked_poses, "the slanted pose cannot be tracked at 40°"
    over = check_overhead_coverage(mesh, Ts, r.markers, strict)
    assert set(np.flatnonzero(over == 0)) == set(r.untracked_poses)
    assert check_coverage(mesh, Ts, r.markers, strict, n_yaw=72).min() >= 1
    loose = plan_markers(mesh, poses, 8.0, ViewingGeometry(n_yaw=72, overhead_max_tilt_deg=50.0))
    assert loose.untracked_poses == [] and loose.min_overhead_visible >= 1


def test_saved_object_round_trips(tmp_path):
    obj = _teach("hexagon", extrude_polygon(np.array(PROFILES["hex"], float), 40.0), library_dir=tmp_path)
    lib = load_library(tmp_path)
    got = lib["hexagon"]
    assert [m.id for m in got.markers] == [m.id for m in obj.markers]
    assert np.allclose(got.markers[0].center, obj.markers[0].center, atol=1e-3)
    assert len(got.stable_poses) == len(obj.stable_poses)
    assert np.allclose(got.views[0].features.aos, obj.views[0].features.aos, atol=1e-5)
    assert got.view_image(0).shape[2] == 3 and (tmp_path / "hexagon" / "contact_sheet.png").is_file()
    assert got.mesh.is_watertight


def _snapshot(path):
    return sorted((p.relative_to(path).as_posix(), p.stat().st_size) for p in path.rglob("*"))


def test_bad_models_give_clear_errors_and_leave_library_untouched(tmp_path):
    lib = tmp_path / "lib"
    _teach("good", trimesh.creation.box((40, 40, 35)), library_dir=lib)
    before = _snapshot(lib)
    open_box = trimesh.creation.box((40, 40, 35))
    open_box.update_faces(np.arange(len(open_box.faces)) > 0)
    cases = {
        "watertight": open_box,
        "empty": trimesh.Trimesh(),
        "metres": trimesh.creation.box((40000, 40000, 35000)),
        "too small for one marker": trimesh.creation.box((12, 12, 12)),
    }
    for expect, mesh in cases.items():
        with pytest.raises(ModelError) as err:
            _teach("bad", mesh, library_dir=lib)
        msg = str(err.value)
        assert expect.split()[0] in msg or (expect == "metres" and "mm" in msg), msg
    # a viewing geometry from which no marker can ever be seen is taught anyway, with a warning saying
    # what would fix it (issue 15: never refuse a valid model; coverage is reported, not an error)
    hidden = teach_object("hidden", trimesh.creation.box((40, 40, 35)), radius_mm=8.0,
                          view=ViewingGeometry(angle_deg=63.0, max_obliquity_deg=15.0), standoff_mm=600.0,
                          scale_mm_per_px=mm_per_px(CAM, 600),
                          render_factory=lambda m, mk, *_: silhouette_renderer(CAM, m, mk), sweep=False,
                          angle_curve=True)
    assert hidden.info["coverage"]["initial_view"] == 0.0
    assert "initial viewing angle of" in hidden.info["warnings"][0]
    assert _snapshot(lib) == before
    assert not (lib / "bad").exists()


def test_units_hint_and_file_errors(tmp_path):
    big = tmp_path / "big.stl"
    trimesh.creation.box((40000, 40000, 35000)).export(big)
    with pytest.raises(ModelError, match="mm"):
        validate_model(load_model(big), marker_radius_mm=8)
    with pytest.raises(ModelError, match="not found"):
        load_model(tmp_path / "missing.stl")
    (tmp_path / "junk.stl").write_bytes(b"solid x\nthis is not stl\n")
    with pytest.raises(ModelError):
        validate_model(load_model(tmp_path / "junk.stl"), marker_radius_mm=8)


def test_corrupt_library_folder_is_a_clear_error(tmp_path):
    _teach("cube", trimesh.creation.box((40, 40, 40)), library_dir=tmp_path)
    mk = tmp_path / "cube" / "markers.yaml"
    good = mk.read_text()
    mk.write_text("markers: [{id: 0, center: [0, 0], normal: [0, 0, 1], radius: 8}]")
    with pytest.raises(LibraryError, match="cube: markers.yaml"):
        load_object(tmp_path / "cube")
    mk.write_text(good)
    (tmp_path / "cube" / "views" / "0.json").write_text("{not json")
    with pytest.raises(LibraryError, match="views/0.json"):
        load_object(tmp_path / "cube")
    (tmp_path / "cube" / "views" / "0.json").unlink()
    with pytest.raises(LibraryError, match="missing views/0.json"):
        load_object(tmp_path / "cube")
    (tmp_path / "cube" / "object.yaml").write_text(yaml.safe_dump({"name": "other", "format": 1}))
    with pytest.raises(LibraryError, match="names it"):
        load_object(tmp_path / "cube")


def test_standard_views_are_taught_with_the_object_resting_in_the_pose_that_faces_the_marker_up():
    """Each marker of a box has a stable pose with it on top: the taught view looks straight down on it,
    the object resting on the table (lowest point z = 0) and the camera at the stand-off above it."""
    import trimesh

    from labctl.library.model import stable_poses
    from labctl.library.placement import Marker
    from labctl.library.views import resting_pose_for_view, standard_view_pose

    box = trimesh.creation.box((50.0, 40.0, 30.0))
    poses = stable_poses(box)
    for n in np.vstack([np.eye(3), -np.eye(3)]):
        m = Marker(0, n * box.extents / 2, n, 8.0)
        T_o_c = standard_view_pose(m, 800.0)
        T_w_o = resting_pose_for_view(poses, T_o_c)
        assert np.allclose(T_w_o[:3, :3] @ n, [0, 0, 1], atol=1e-6)
        assert abs(trimesh.transform_points(box.vertices, T_w_o)[:, 2].min()) < 1e-6
        assert np.isclose((T_w_o @ T_o_c)[2, 3], 800.0 + (T_w_o[:3, :3] @ m.center + T_w_o[:3, 3])[2])


def test_shipped_sample_library_meets_both_marker_requirements_by_brute_force():
    """The sample lab's object_library/: every stable pose × 360 yaws shows a marker to the initial
    viewing camera, and every stable pose has a marker the overhead camera tracks over its cone."""
    from labctl.config import load_lab
    from labctl.library.placement import viewing_geometry
    from labctl.workspace import sample_lab_path

    lab = load_lab(sample_lab_path())
    view = viewing_geometry(lab)
    lib = load_library(lab.library_dir)
    assert len(lib) == 7
    for name, obj in lib.items():
        Ts = [T for T, _ in obj.stable_poses]
        assert check_coverage(obj.mesh, Ts, obj.markers, view).min() >= 1, name
        assert check_overhead_coverage(obj.mesh, Ts, obj.markers, view).min() >= 1, name
        assert obj.info["placement"]["overhead"]["min_tracked_markers"] >= 1


def test_a_binary_obj_is_refused_in_words_not_by_a_missing_module(tmp_path):
    bad = tmp_path / "garbage.obj"
    bad.write_bytes(bytes(range(256)) * 8)
    with pytest.raises(ModelError) as exc:
        load_model(bad)
    assert "not a text OBJ" in str(exc.value) and "module" not in str(exc.value)
