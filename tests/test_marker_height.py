"""The marker height measured in a standard view (issue 15), against the renderer's scene geometry,
and the height gate's guarantee: a height narrows the silhouette's candidates, never widens them."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.config.lab import RunConfig, SimCameraConfig
from labctl.geometry import make_T
from labctl.library.marker_height import measure_marker_height
from labctl.library.matching import LibraryIndex, match
from labctl.library.model import stable_poses
from labctl.library.placement import Marker
from labctl.library.views import perturbed_view_pose, resting_pose_for_view, standard_view_pose
from labctl.sim.effects import CameraEffects
from labctl.sim.render import MarkerDisc, Mesh, TableSurface, render
from labctl.vision import MarkerThresholds
from labctl.vision.shape import ShapeFeatures

STANDOFF = 800.0


def _camera():
    from labctl.config import load_lab
    from labctl.sim.truth import camera_model
    from labctl.workspace import sample_lab_path

    return camera_model(load_lab(sample_lab_path()).mobile_camera)


def _box_with_markers(extents, radius):
    """A box resting on z = 0 (O at its footprint's centre), a marker on its top face and one on +x."""
    ex, ey, ez = extents
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_transform(make_T(np.eye(3), [0, 0, ez / 2]))
    markers = [Marker(0, np.array([5.0, -3.0, ez]), np.array([0.0, 0.0, 1.0]), radius),
               Marker(1, np.array([ex / 2, 2.0, ez / 2 + 3.0]), np.array([1.0, 0.0, 0.0]), radius)]
    return mesh, markers


def _render_standard_view(cam, mesh, markers, m, rng, effects=None, choice="random"):
    """A perturbed standard view of marker ``m`` (±3 % stand-off, ≤ 2° tilt, random roll) with the
    object resting in a stable pose; returns (image, T_w_c, the marker centre's true height)."""
    T_o_c = perturbed_view_pose(standard_view_pose(m, STANDOFF), m.center, rng)
    T_w_o = resting_pose_for_view(stable_poses(mesh), T_o_c, yaw_rad=0.0, choice=choice, rng=rng)
    V = np.asarray(mesh.vertices) @ T_w_o[:3, :3].T + T_w_o[:3, 3]
    discs = [MarkerDisc(T_w_o[:3, :3] @ q.center + T_w_o[:3, 3], T_w_o[:3, :3] @ q.normal, q.radius) for q in markers]
    T_w_c = T_w_o @ T_o_c
    image = render(cam, T_w_c, [Mesh(V, np.asarray(mesh.faces), markers=discs)], table=TableSurface(),
                   noise_sigma=2.0, rng=rng, effects=effects).image
    return image, T_w_c, float(T_w_o[2, :3] @ m.center + T_w_o[2, 3])


def test_marker_height_matches_the_rendered_scene_and_picks_the_marker_size():
    cam = _camera()
    rng = np.random.default_rng(4)
    d = RunConfig()
    for radius in (8.0, 5.12):
        mesh, markers = _box_with_markers((70.0, 50.0, 35.0), radius)
        for m in markers:
            for _ in range(2):
                image, T_w_c, truth = _render_standard_view(cam, mesh, markers, m, rng)
                h = measure_marker_height(image, cam, T_w_c, (8.0, 6.4, 5.12, 4.096), standoff_mm=STANDOFF)
                assert h is not None and h.radius_mm == radius
                assert abs(h.height_mm - truth) < 0.5, (radius, m.id, h, truth)
                tol = h.tolerance_mm(d.height_gate_mm, d.height_gate_sigmas, d.height_gate_depth_frac)
                assert abs(h.height_mm - truth) <= tol
                assert tol >= d.height_gate_mm
    # seen from above, the wrong size alone puts the marker 25 % nearer or farther than the stand-off
    image, T_w_c, truth = _render_standard_view(cam, mesh, markers, markers[0], rng, choice="upright")
    wrong = measure_marker_height(image, cam, T_w_c, (8.0,), standoff_mm=STANDOFF)
    assert abs(wrong.depth_vertical_mm) > 700.0 and abs(wrong.height_mm - truth) > 100.0
    assert measure_marker_height(np.zeros_like(image), cam, T_w_c, (8.0,), standoff_mm=STANDOFF) is None


def test_the_default_tolerance_holds_under_the_realistic_camera():
    """JPEG, Bayer, sRGB, highlights and shadows bias the apparent marker size (the distance, so the
    height of a marker seen from above): the depth term of the tolerance covers it."""
    cam = _camera()
    rng = np.random.default_rng(7)
    fx = CameraEffects(response="srgb", **SimCameraConfig(preset="realistic").settings())
    d = RunConfig()
    mesh, markers = _box_with_markers((60.0, 45.0, 25.0), 8.0)
    measured = 0
    for m in markers:
        for _ in range(3):
            image, T_w_c, truth = _render_standard_view(cam, mesh, markers, m, rng, effects=fx)
            h = measure_marker_height(image, cam, T_w_c, (8.0, 6.4), standoff_mm=STANDOFF, response="srgb",
                                      thresholds=MarkerThresholds(min_saturation=0.25))
            if h is None:  # no trusted marker (flagged blurred): no height, no gate for this view
                continue
            measured += 1
            tol = h.tolerance_mm(d.height_gate_mm, d.height_gate_sigmas, d.height_gate_depth_frac)
            assert abs(h.height_mm - truth) <= tol, (m.id, h, truth, tol)
    assert measured >= 4


def _features(rng, ecc=0.6, size=60.0):
    return ShapeFeatures(eccentricity=ecc, size_mm=size, perimeter_mm=260.0, chain_start=(0, 0),
                         chain_code=np.zeros(0, np.uint8), aos=rng.uniform(1.5, 4.5, (3, 64)), fd=rng.random(16),
                         hu=rng.random(7))


def _plate(thickness, features):
    mesh = trimesh.creation.box(extents=(80.0, 50.0, thickness))
    mesh.apply_transform(make_T(np.eye(3), [0, 0, thickness / 2]))
    marker = Marker(id=0, center=np.array([0.0, 0.0, thickness]), normal=np.array([0.0, 0.0, 1.0]), radius=8.0)
    return SimpleNamespace(markers=[marker], stable_poses=stable_poses(mesh),
                           views={0: SimpleNamespace(features=features)}, marker=lambda mid, _m=marker: _m)


_LIB_RNG = np.random.default_rng(12)
_SHAPES = [_features(_LIB_RNG, ecc=e, size=s) for e, s in ((0.6, 60.0), (0.62, 61.0), (0.3, 45.0), (0.6, 64.0))]
_LIB = {f"p{k}_{t:g}": _plate(t, _SHAPES[k]) for k, t in ((0, 5.0), (1, 12.0), (2, 20.0), (3, 30.0), (0, 9.0))}
_INDEX = LibraryIndex.from_library(_LIB)


@settings(max_examples=60, deadline=None)
@given(k=st.integers(0, len(_SHAPES) - 1), noise=st.floats(0.0, 0.3), height=st.floats(-20.0, 150.0),
       tol=st.floats(0.0, 15.0), seed=st.integers(0, 2**16))
def test_a_height_only_narrows_the_silhouettes_candidates(k, noise, height, tol, seed):
    """Whatever the measured height (right, wrong, impossible), the answer is one of the objects the
    silhouette alone leaves as candidates, with the same best-match rule: a height error can leave a
    view ambiguous but never promote a far match."""
    rng = np.random.default_rng(seed)
    base = _SHAPES[k]
    q = ShapeFeatures(eccentricity=base.eccentricity, size_mm=base.size_mm, perimeter_mm=base.perimeter_mm,
                      chain_start=(0, 0), chain_code=base.chain_code,
                      aos=base.aos + rng.normal(0, noise, base.aos.shape), fd=base.fd, hu=base.hu)
    plain = match(q, _INDEX)
    gated = match(q, _INDEX, height_mm=height, height_tol_mm=tol)
    assert set(gated.candidates) <= set(plain.candidates)
    assert (gated.best is None) == (plain.best is None)
    if gated.best is not None:
        assert gated.best[0] in plain.candidates
        assert gated.scores[gated.best[0]] <= plain.scores[plain.best[0]] + 0.08 + 1e-9 \
            or gated.scores[gated.best[0]] <= 0.15


def _boxed(extents, faces):
    """A box resting on z = 0 with a marker at the centre of each face in ``faces`` (±x, ±y, ±z)."""
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_transform(make_T(np.eye(3), [0, 0, extents[2] / 2]))
    axes = {"+x": (0, 1), "-x": (0, -1), "+y": (1, 1), "-y": (1, -1), "+z": (2, 1), "-z": (2, -1)}
    markers = []
    for k, f in enumerate(faces):
        a, sgn = axes[f]
        n = np.zeros(3)
        n[a] = sgn
        c = n * np.asarray(extents) / 2 + np.array([0, 0, extents[2] / 2])
        markers.append(Marker(k, c, n, 8.0))
    return mesh, markers


def test_a_look_alike_that_needs_a_marker_facing_up_is_told_from_a_plate_on_its_edge():
    """part041_plate stood on its edge against part089_holed (issue 15 trials): the same 80×42 mm
    rectangle, its marker 21 mm up; only the block, resting so, shows a marker facing up."""
    from labctl.library.matching import needs_top_marker, view_scores

    rng = np.random.default_rng(2)
    face = _features(rng, ecc=0.84, size=58.0)
    p_mesh, p_markers = _boxed((80.0, 42.0, 7.5), ("+z", "-z"))
    b_mesh, b_markers = _boxed((80.0, 51.0, 42.0), ("+z", "-z", "+y", "-y"))
    feats = {0: face, 1: face, 2: face, 3: face}

    def obj(mesh, markers):
        by_id = {m.id: m for m in markers}
        return SimpleNamespace(markers=markers, stable_poses=stable_poses(mesh), marker=lambda mid: by_id[mid],
                               views={m.id: SimpleNamespace(features=feats[m.id]) for m in markers})

    index = LibraryIndex.from_library({"plate": obj(p_mesh, p_markers), "block": obj(b_mesh, b_markers)})
    s = view_scores(face, index)
    side = dict(height_mm=21.0, tol_mm=1.5, normal_z=0.0)
    assert needs_top_marker(index, "block", s, 0.15, **side)  # its side face is vertical only lying flat
    assert not needs_top_marker(index, "plate", s, 0.15, **side)  # on its edge no marker faces up
    # a height no resting pose gives, or views the silhouette rules out, refute nothing
    assert not needs_top_marker(index, "block", s, 0.15, height_mm=60.0, tol_mm=1.5, normal_z=0.0)
    assert not needs_top_marker(index, "block", np.full(len(index), np.inf), 0.15, **side)
    assert not needs_top_marker(index, "block", s, 0.15, height_mm=21.0, tol_mm=0.0, normal_z=0.0)


def test_the_recogniser_sees_a_marker_facing_up_from_the_initial_viewpoint():
    """An initial image (1 m, 63° elevation) of a box with a marker on top shows a marker facing up;
    a plate on its edge, markers on its two faces only, shows none (whatever the azimuth)."""
    from labctl.config import load_lab
    from labctl.decisions.recognizer import Recognizer
    from labctl.geometry import look_at
    from labctl.sim.truth import camera_model
    from labctl.vision import detect_markers
    from labctl.workspace import sample_lab_path

    lab = load_lab(sample_lab_path())
    cam = camera_model(lab.mobile_camera)
    rec = Recognizer(SimpleNamespace(lab=lab, mobile_camera=cam, marker_radii_mm=()), grab=None,
                     log=lambda *a, **k: None)
    rng = np.random.default_rng(5)
    box_mesh, box_markers = _boxed((60.0, 50.0, 30.0), ("+z", "+x", "-y"))
    plate_mesh, plate_markers = _boxed((70.0, 40.0, 8.0), ("+z", "-z"))
    R_edge = make_T(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])[:3, :3], [0, 4.0, 20.0])
    plate_markers_seen = 0
    for az in (0.0, 1.2, 2.5):
        eye = np.array([np.cos(az) * np.cos(np.radians(63)), np.sin(az) * np.cos(np.radians(63)),
                        np.sin(np.radians(63))]) * 1000.0
        T_w_c = look_at(eye, np.array([0.0, 0.0, 20.0]))
        for (mesh, markers, T_w_o), up in (((box_mesh, box_markers, np.eye(4)), True),
                                            ((plate_mesh, plate_markers, R_edge), False)):
            V = np.asarray(mesh.vertices) @ T_w_o[:3, :3].T + T_w_o[:3, 3]
            discs = [MarkerDisc(T_w_o[:3, :3] @ q.center + T_w_o[:3, 3], T_w_o[:3, :3] @ q.normal, q.radius)
                     for q in markers]
            image = render(cam, T_w_c, [Mesh(V, np.asarray(mesh.faces), markers=discs)], table=TableSurface(),
                           noise_sigma=2.0, rng=rng).image
            assert rec._sees_top_marker(SimpleNamespace(image=image), T_w_c) is up, (az, up)
            if not up:
                plate_markers_seen += bool(detect_markers(image, include_suspect=True))
    assert plate_markers_seen >= 1  # the plate's face markers were in view: the answer is not for want of blobs
