"""A run record as an MCAP file with Foxglove's well-known schemas (``labctl export RUN --mcap FILE``).

MCAP (https://mcap.dev) is the container Foxglove, ROS 2 bags and many robotics tools read. Each
message is JSON-encoded under one of Foxglove's schema names, so Foxglove picks its panels by name:

==========================  ==========================  =============================================
topic                       schema                      from the record
==========================  ==========================  =============================================
``/mobile_camera/image``    ``foxglove.CompressedImage``  each ``view_<id>.png`` at its ``capture_request``
``/tf``                     ``foxglove.FrameTransform``   ``world → mobile_camera`` of each capture request
``/scene``                  ``foxglove.SceneUpdate``      the tracked marker (sphere), the predicted path
                                                          (line), the robot's commanded targets (cubes)
``/log``                    ``foxglove.Log``              stages, identity, failures, aborts
``/labctl/events``          ``labctl.Event``              every event of the record, verbatim
==========================  ==========================  =============================================

Units at this edge are Foxglove's: metres, quaternions (x, y, z, w), nanoseconds since the UNIX
epoch (the events' ``wall`` stamp). Inside labctl they stay millimetres and rotation matrices.
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from ..errors import UserInputError
from .events import spec
from .record import RunData

MM_PER_M = 1000.0
WORLD = "world"
MOBILE_CAMERA = "mobile_camera"

_TIME = {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0},
                                          "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}}
_VEC3 = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}
_POSE = {"type": "object", "properties": {"position": _VEC3, "orientation": _QUAT}}
_COLOR = {"type": "object", "properties": {k: {"type": "number"} for k in "rgba"}}

#: JSON Schemas of the Foxglove message types written here (the fields used; names as Foxglove's)
SCHEMAS: dict[str, dict] = {
    "foxglove.CompressedImage": {"type": "object", "properties": {
        "timestamp": _TIME, "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"}, "format": {"type": "string"}}},
    "foxglove.FrameTransform": {"type": "object", "properties": {
        "timestamp": _TIME, "parent_frame_id": {"type": "string"}, "child_frame_id": {"type": "string"},
        "translation": _VEC3, "rotation": _QUAT}},
    "foxglove.SceneUpdate": {"type": "object", "properties": {
        "deletions": {"type": "array", "items": {"type": "object"}},
        "entities": {"type": "array", "items": {"type": "object", "properties": {
            "timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"},
            "lifetime": _TIME, "frame_locked": {"type": "boolean"},
            "spheres": {"type": "array", "items": {"type": "object", "properties": {
                "pose": _POSE, "size": _VEC3, "color": _COLOR}}},
            "cubes": {"type": "array", "items": {"type": "object", "properties": {
                "pose": _POSE, "size": _VEC3, "color": _COLOR}}},
            "lines": {"type": "array", "items": {"type": "object", "properties": {
                "type": {"type": "integer"}, "pose": _POSE, "thickness": {"type": "number"},
                "scale_invariant": {"type": "boolean"}, "points": {"type": "array", "items": _VEC3},
                "color": _COLOR}}}}}}}},
    "foxglove.Log": {"type": "object", "properties": {
        "timestamp": _TIME, "level": {"type": "integer", "minimum": 0, "maximum": 5},
        "message": {"type": "string"}, "name": {"type": "string"}, "file": {"type": "string"},
        "line": {"type": "integer", "minimum": 0}}},
    "labctl.Event": {"type": "object", "properties": {"event": {"type": "string"}, "t": {"type": "number"},
                                                      "wall": {"type": "number"}}},
}

TOPICS: dict[str, str] = {
    "/mobile_camera/image": "foxglove.CompressedImage",
    "/tf": "foxglove.FrameTransform",
    "/scene": "foxglove.SceneUpdate",
    "/log": "foxglove.Log",
    "/labctl/events": "labctl.Event",
}

# foxglove.LogLevel and foxglove.LineType values
INFO, WARNING, ERROR = 2, 3, 4
LINE_STRIP = 0
_LOGGED = {"stage": INFO, "identity": INFO, "devices_stopped": INFO, "ambiguous": WARNING, "failure": WARNING,
           "recognizer_failure": WARNING, "marker_lost": WARNING, "no_marker": WARNING, "no_silhouette": WARNING,
           "standard_view_misaligned": WARNING, "standard_view_unreachable": WARNING, "replan_refused": WARNING,
           "message_dropped": WARNING, "run_aborted": ERROR, "robot_stop_failed": ERROR, "worker_error": ERROR,
           "link_refused": ERROR}


def _stamp(wall_s: float) -> dict:
    ns = int(round(wall_s * 1e9))
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _point(p_mm: Iterable[float]) -> dict:
    x, y, *z = (float(v) / MM_PER_M for v in p_mm)
    return {"x": x, "y": y, "z": z[0] if z else 0.0}


def quaternion_from_matrix(R: Any) -> dict:
    """Unit quaternion (x, y, z, w) of a 3×3 rotation matrix (Shepperd's method, w ≥ 0)."""
    m = [[float(R[i][j]) for j in range(3)] for i in range(3)]
    tr = m[0][0] + m[1][1] + m[2][2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = ((m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s, 0.25 * s)
    else:
        i = max(range(3), key=lambda k: m[k][k])
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i][i] - m[j][j] - m[k][k])
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (m[j][i] + m[i][j]) / s
        v[k] = (m[k][i] + m[i][k]) / s
        q = (v[0], v[1], v[2], (m[k][j] - m[j][k]) / s)
    sign = -1.0 if q[3] < 0 else 1.0
    return dict(zip("xyzw", (sign * c for c in q), strict=True))


_IDENTITY = {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def _entity(wall: float, ident: str, **shapes) -> dict:
    return {"timestamp": _stamp(wall), "frame_id": WORLD, "id": ident, "lifetime": {"sec": 0, "nsec": 0},
            "frame_locked": False, **shapes}


def _log_message(e: dict) -> str:
    fields = {k: v for k, v in e.items() if k not in ("event", "wall", "t")}
    body = ", ".join(f"{k}={v}" for k, v in fields.items() if not isinstance(v, (list, dict)))
    return f"t={e.get('t', 0.0):.3f} s {e['event']}" + (f": {body}" if body else "")


TRACK, PREDICT, SEGMENT, CAPTURE = (spec(n) for n in ("track", "predict", "segment", "capture_request"))


def messages(run: RunData) -> Iterable[tuple[str, float, dict]]:
    """The export's messages as (topic, wall time s, message), in the record's order."""
    captures = {}
    for e in run.events:
        wall = float(e.get("wall", 0.0))
        name = e["event"]
        yield "/labctl/events", wall, e
        if name in _LOGGED:
            yield "/log", wall, {"timestamp": _stamp(wall), "level": _LOGGED[name], "message": _log_message(e),
                                 "name": "labctl", "file": "", "line": 0}
        if name == "track" and TRACK.valid(e, "x") is not None and TRACK.valid(e, "y") is not None:
            yield "/scene", wall, {"deletions": [], "entities": [_entity(wall, "marker", spheres=[
                {"pose": {**_IDENTITY, "position": _point((TRACK.get(e, "x"), TRACK.get(e, "y")))},
                 "size": {"x": 0.016, "y": 0.016, "z": 0.016}, "color": {"r": 1.0, "g": 0.1, "b": 0.1, "a": 1.0}}])]}
        elif name == "predict" and PREDICT.valid(e, "path"):
            yield "/scene", wall, {"deletions": [], "entities": [_entity(wall, "prediction", lines=[
                {"type": LINE_STRIP, "pose": _IDENTITY, "thickness": 2.0, "scale_invariant": True,
                 "points": [_point(p) for p in PREDICT.get(e, "path")],
                 "color": {"r": 0.2, "g": 0.6, "b": 1.0, "a": 1.0}}])]}
        elif name == "segment" and SEGMENT.valid(e, "p") is not None:
            target = f"robot_target_{SEGMENT.get(e, 'kind', '')}"
            yield "/scene", wall, {"deletions": [], "entities": [_entity(wall, target, cubes=[
                {"pose": {**_IDENTITY, "position": _point(SEGMENT.get(e, "p"))},
                 "size": {"x": 0.03, "y": 0.03, "z": 0.03}, "color": {"r": 0.2, "g": 0.9, "b": 0.3, "a": 0.8}}])]}
        elif name == "capture_request" and CAPTURE.valid(e, "T_w_c2") is not None:
            T = CAPTURE.get(e, "T_w_c2")
            captures[CAPTURE.get(e, "view_id")] = wall
            yield "/tf", wall, {"timestamp": _stamp(wall), "parent_frame_id": WORLD, "child_frame_id": MOBILE_CAMERA,
                                "translation": _point(row[3] for row in T[:3]),
                                "rotation": quaternion_from_matrix([row[:3] for row in T[:3]])}
    for stem, path in sorted(run.images.items()):
        if stem.startswith("view_") and stem[5:].isdigit() and int(stem[5:]) in captures:
            wall = captures[int(stem[5:])]
            yield "/mobile_camera/image", wall, {"timestamp": _stamp(wall), "frame_id": MOBILE_CAMERA,
                                                 "data": base64.b64encode(path.read_bytes()).decode("ascii"),
                                                 "format": "png"}


def export_mcap(run: RunData, out: Path) -> dict[str, int]:
    """Write ``run`` to ``out`` (MCAP, JSON messages, zstd chunks); returns the message count per topic.

    The file is written beside ``out`` and renamed into place, so a crash leaves the old file or none."""
    from mcap.writer import Writer

    msgs = sorted(messages(run), key=lambda m: m[1])  # MCAP readers expect log time order within a chunk
    if not msgs:
        raise UserInputError(f"{run.path} has no events to export")
    tmp = out.with_name(f".{out.name}.partial")
    counts = dict.fromkeys(TOPICS, 0)
    with open(tmp, "wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="labctl")
        schema_ids = {name: w.register_schema(name=name, encoding="jsonschema",
                                              data=json.dumps({"title": name, **s}).encode())
                      for name, s in SCHEMAS.items()}
        channels = {topic: w.register_channel(topic=topic, message_encoding="json", schema_id=schema_ids[schema])
                    for topic, schema in TOPICS.items()}
        for seq, (topic, wall, msg) in enumerate(msgs):
            ns = int(round(wall * 1e9))
            w.add_message(channel_id=channels[topic], log_time=ns, publish_time=ns, sequence=seq,
                          data=json.dumps(msg, separators=(",", ":")).encode())
            counts[topic] += 1
        w.finish()
        fh.flush()
    tmp.replace(out)
    return counts
