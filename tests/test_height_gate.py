"""The marker-height gate of standard-view matching (issue 15: plates that differ only in thickness)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import trimesh

from labctl.geometry import make_T
from labctl.library.matching import LibraryIndex, height_gate, marker_heights, match
from labctl.library.model import stable_poses
from labctl.library.placement import Marker
from labctl.library.storage import load_library
from labctl.vision.shape import ShapeFeatures
from labctl.workspace import sample_lab_path


def _plate(thickness: float, features: ShapeFeatures):
    """An 80×50 mm plate with one marker on its top face; its stable poses from trimesh."""
    mesh = trimesh.creation.box(extents=(80.0, 50.0, thickness))
    mesh.apply_transform(make_T(np.eye(3), [0, 0, thickness / 2]))
    marker = Marker(id=0, center=np.array([0.0, 0.0, thickness]), normal=np.array([0.0, 0.0, 1.0]), radius=8.0)
    return SimpleNamespace(markers=[marker], stable_poses=stable_poses(mesh),
                           views={0: SimpleNamespace(features=features)}, marker=lambda mid, _m=marker: _m)


def _features() -> ShapeFeatures:
    rng = np.random.default_rng(1)
    return ShapeFeatures(eccentricity=0.6, size_mm=60.0, perimeter_mm=260.0, chain_start=(0, 0),
                         chain_code=np.zeros(0, np.uint8), aos=rng.uniform(1.5, 4.5, (3, 64)), fd=rng.random(16),
                         hu=rng.random(7))


def test_plates_of_one_footprint_are_told_apart_by_the_marker_height():
    f = _features()
    lib = {"plate_5mm": _plate(5.0, f), "plate_12mm": _plate(12.0, f)}
    index = LibraryIndex.from_library(lib)
    assert match(f, index).ambiguous  # the standard views are the same rectangle
    for h, name in ((5.3, "plate_5mm"), (11.2, "plate_12mm")):
        r = match(f, index, height_mm=h)
        assert not r.ambiguous and r.best[0] == name
    assert match(f, index, height_mm=8.5, height_tol_mm=4.0).ambiguous  # within both tolerances
    # no plate rests with its marker 30 mm up: a height no shape candidate fits is ignored, never trusted
    assert match(f, index, height_mm=30.0).ambiguous
    assert match(f, index, height_mm=30.0, height_tol_mm=0.0).ambiguous  # 0 turns the gate off


def test_the_gate_never_excludes_a_sample_view_at_its_true_height():
    lib = load_library(sample_lab_path() / "object_library")
    index = LibraryIndex.from_library(lib)
    for name, obj in lib.items():
        for mid in obj.views:
            i = index.view_index(name, mid)
            for h in marker_heights(obj, mid):
                assert height_gate(index, h + 3.9)[i] and height_gate(index, h - 3.9)[i]
    assert height_gate(index, None).all()


def test_an_index_without_poses_has_no_height_gate():
    f = _features()
    lib = {"a": SimpleNamespace(views={0: SimpleNamespace(features=f)}, stable_poses=[])}
    index = LibraryIndex.from_library(lib)
    assert index.heights is None and height_gate(index, 1e3).all()


def test_evidence_over_several_views_resolves_a_lasting_lead_only():
    from labctl.library.matching import MARGIN, evidence_leader

    assert evidence_leader({"a": 0.05, "b": 0.13}, 1) is None  # one view: the paper's threshold rule stands
    assert evidence_leader({"a": 0.10, "b": 0.36}, 3) == "a"  # 0.26 > 0.08·√3
    assert evidence_leader({"a": 0.10, "b": 0.20}, 3) is None  # 0.10 < 0.08·√3: could be noise
    assert evidence_leader({"a": 0.1}, 2) == "a"
    for n in range(2, 6):  # the bar grows as √n
        gap = MARGIN * np.sqrt(n)
        assert evidence_leader({"a": 0.0, "b": gap * 1.01}, n) == "a"
        assert evidence_leader({"a": 0.0, "b": gap * 0.99}, n) is None


def test_a_look_alike_within_the_threshold_is_outvoted_by_repeated_views():
    """A part seen only from one side (a plate) against a look-alike that scores inside the
    threshold every time: identify() resolves it once the summed lead is beyond chance."""
    from labctl.library.matching import identify

    rng = np.random.default_rng(3)
    f = _features()
    other = ShapeFeatures(eccentricity=f.eccentricity, size_mm=f.size_mm, perimeter_mm=f.perimeter_mm,
                          chain_start=(0, 0), chain_code=f.chain_code, aos=f.aos + rng.normal(0, 0.1, f.aos.shape),
                          fd=f.fd, hu=f.hu)
    lib = {"plate": SimpleNamespace(views={0: SimpleNamespace(features=f)}, stable_poses=[]),
           "look_alike": SimpleNamespace(views={0: SimpleNamespace(features=other)}, stable_poses=[])}
    index = LibraryIndex.from_library(lib)
    first = match(f, index)
    assert first.ambiguous and first.scores["look_alike"] <= 0.15
    res = identify(f, index, lambda h, j: f, max_views=3)
    assert res.resolved and res.name == "plate" and res.views_used >= 2
    one = identify(f, index, lambda h, j: f, max_views=1)
    assert not one.resolved  # a single view stays ambiguous


def test_an_unusable_view_spends_a_view_and_refutes_no_hypothesis():
    """``acquire`` returning :class:`UnusableView` (a cropped standard view) costs a view but strikes no
    candidate out, unlike None (no marker where the hypothesis predicts one)."""
    from labctl.library.matching import UnusableView, identify, split_query

    f = _features()
    lib = {"a": SimpleNamespace(views={0: SimpleNamespace(features=f)}, stable_poses=[]),
           "b": SimpleNamespace(views={0: SimpleNamespace(features=f)}, stable_poses=[])}
    index = LibraryIndex.from_library(lib)
    res = identify(f, index, lambda h, j: UnusableView(), max_views=3)
    assert not res.resolved and sorted(res.candidates) == ["a", "b"] and res.views_used == 3
    refuted = identify(f, index, lambda h, j: None, max_views=3)
    assert len(refuted.candidates) == 1
    assert split_query(f) == (f, {})
    from labctl.library.matching import StandardViewQuery

    assert split_query(StandardViewQuery(f, 12.5)) == (f, {"height_mm": 12.5})
    assert split_query(StandardViewQuery(f, None)) == (f, {})
