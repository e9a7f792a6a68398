"""Marker suggestions a part's geometry can carry: a round part is not told to turn "a flat face ≥ 9 mm"
to the camera when it has none; a part with an unused flat face that the camera would see is told that
face, checked against the geometry here (its normal in the pose, seen from the initial view)."""

from __future__ import annotations

import numpy as np
import trimesh
from test_library_symmetry import VIEW, _cylinder, _teach

from labctl.library.model import stable_poses, validate_model
from labctl.library.placement import Marker
from labctl.library.teach import pose_marker_fix


def test_a_round_part_is_told_it_carries_no_marker_there_not_to_turn_a_face():
    obj = _teach("cyl", _cylinder(96), min_coverage=0.9, accept_partial=True)
    initial = [w for w in obj.info["warnings"] if "in the initial view" in w]
    assert len(initial) == 1, obj.info["warnings"]
    assert "turned to the camera" not in initial[0]
    assert "none this part can carry" in initial[0] and "curved side" in initial[0]
    tracked = [w for w in obj.info["warnings"] if "overhead camera tracks" in w]
    assert all("none this part can carry" in w for w in tracked)
    # the oracle: every flat face of the cylinder big enough for a marker is an end cap, and in the
    # worst pose (lying on its side) an end cap is vertical: its normal has no upward part
    worst = min(range(len(obj.stable_poses)), key=lambda k: obj.info["coverage"]["per_pose"][k]["visible_yaw_share"])
    T = np.asarray(obj.stable_poses[worst][0])
    assert abs(T[2, :3] @ np.array([0, 0, 1.0])) < 1e-6  # the cap normal (O's z) lies in the table plane


def test_an_unused_flat_face_the_camera_would_see_is_named():
    box = validate_model(trimesh.creation.box(extents=(60.0, 50.0, 40.0)), marker_radius_mm=8)
    poses = stable_poses(box)
    T = next(np.asarray(T) for T, _ in poses if np.allclose(np.asarray(T)[2, :3], [0, 0, -1], atol=1e-6))
    top_in_o = np.array([0.0, 0.0, 20.0])  # the marker is on +z of O, which this pose turns face down
    fix = pose_marker_fix(box, T, [Marker(0, top_in_o, np.array([0.0, 0.0, 1.0]), 8.0)], VIEW)
    assert fix.startswith("a marker on the flat face at"), fix
    normal = np.array([float(v) for v in fix.split("facing (")[1].split(")")[0].split(",")])
    up = (T[:3, :3] @ normal)[2]
    assert up > 0.5  # the named face looks up in that pose: the 63° initial view sees it
