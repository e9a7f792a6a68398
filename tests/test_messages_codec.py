"""Worker messages: exact round trips, compact sizes, garbage -> MessageError (never a crash)."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.decisions import messages as m
from labctl.decisions.messages import (
    Ambiguous,
    CaptureRequest,
    Discard,
    Failure,
    FrameTaken,
    Heartbeat,
    Hello,
    Identity,
    MarkerPose,
    MessageError,
    StandardViewRequest,
    Stop,
    decode,
    encode,
    size_of,
)
from labctl.geometry.transforms import look_at, make_T, rotvec_to_matrix

f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
f64 = st.floats(allow_nan=False, allow_infinity=False)
u16 = st.integers(0, 0xFFFF)
u8 = st.integers(0, 0xFF)
role = st.sampled_from(m.ROLES)
ids = st.lists(u16, max_size=m.MAX_CANDIDATES).map(tuple)
text = st.text(max_size=40)  # <= 160 bytes worst case; filtered by the byte limit below
short_text = text.filter(lambda s: len(s.encode()) <= m.MAX_TEXT_BYTES)


@st.composite
def unit_vectors(draw):
    v = np.array(draw(st.tuples(*[st.floats(-1, 1)] * 3)))
    n = np.linalg.norm(v)
    if n < 1e-3:
        v, n = np.array([0.0, 0.0, 1.0]), 1.0
    return tuple(v / n)


@st.composite
def rotvecs(draw):
    axis = np.array(draw(unit_vectors()))
    return tuple(axis * draw(st.floats(0, math.pi - 1e-6)))


messages = st.one_of(
    st.builds(Hello, role, st.integers(0, 2**32 - 1)),
    st.builds(Heartbeat, role, st.integers(0, 2**32 - 1), f64),
    st.builds(CaptureRequest, u16, st.sampled_from(m.CAPTURE_KINDS), f64, st.tuples(f32, f32, f32), rotvecs()),
    st.builds(FrameTaken, u16, f64),
    st.builds(MarkerPose, u16, st.tuples(f32, f32, f32), unit_vectors(), st.booleans(), f32),
    st.builds(StandardViewRequest, u16, u8),
    st.builds(Identity, u16, f32, u16, ids),
    st.builds(Ambiguous, ids, st.one_of(st.none(), st.integers(0, 254))),
    st.builds(Failure, u8, short_text),
    st.builds(Stop, short_text),
    st.builds(Discard, u16),
)


@settings(max_examples=300, deadline=None)
@given(messages)
def test_round_trip_is_exact(msg):
    data = encode(msg)
    assert isinstance(data, bytes)
    assert decode(data) == msg
    assert size_of(msg) == len(data)
    assert data[0] == type(msg).TAG


@settings(max_examples=200, deadline=None)
@given(messages, st.data())
def test_truncated_or_extended_frames_raise_message_error(msg, data):
    raw = encode(msg)
    cut = data.draw(st.integers(0, len(raw) - 1))
    with pytest.raises(MessageError):
        decode(raw[:cut])
    with pytest.raises(MessageError):
        decode(raw + b"\x00")


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=120))
def test_garbage_never_crashes(blob):
    try:
        msg = decode(blob)
    except MessageError:
        return
    # anything accepted must be a valid message that re-encodes to the same bytes
    assert encode(msg) == blob


@settings(max_examples=300, deadline=None)
@given(messages, st.data())
def test_bit_flips_give_valid_message_or_error(msg, data):
    raw = bytearray(encode(msg))
    i = data.draw(st.integers(0, len(raw) - 1))
    raw[i] ^= 1 << data.draw(st.integers(0, 7))
    try:
        out = decode(bytes(raw))
    except MessageError:
        return
    assert encode(out) == bytes(raw)


def test_decode_rejects_non_bytes_and_unknown_tags():
    for bad in (None, 12, "text"):
        with pytest.raises(MessageError):
            decode(bad)
    with pytest.raises(MessageError):
        decode(b"")
    with pytest.raises(MessageError, match="unknown message tag"):
        decode(bytes([200, 1, 2, 3]))
    with pytest.raises(MessageError):
        encode("not a message")


def test_nan_on_the_wire_is_rejected():
    good = encode(MarkerPose(1, (1, 2, 3), (0, 0, 1), False, 1.0))
    nan = struct.pack("<f", float("nan"))
    bad = good[:3] + nan + good[7:]  # center_w[0] := NaN
    with pytest.raises(MessageError, match="not finite"):
        decode(bad)


@pytest.mark.parametrize(
    "build",
    [
        lambda: Hello("boss", 1),
        lambda: Hello("predictor", -1),
        lambda: Heartbeat("predictor", 2**32, 0.0),
        lambda: Heartbeat("predictor", 1, float("inf")),
        lambda: CaptureRequest(1, "sideways", 0.0, (0, 0, 0), (0, 0, 0)),
        lambda: CaptureRequest(1, "standard", 0.0, (0, 0), (0, 0, 0)),
        lambda: CaptureRequest(1, "standard", 0.0, (0, 0, 1e39), (0, 0, 0)),
        lambda: CaptureRequest(1, "standard", 0.0, (0, 0, 0), (0, 0, 4.0)),
        lambda: CaptureRequest.from_pose(1, "standard", 0.0, np.eye(3)),
        lambda: MarkerPose(70000, (0, 0, 0), (0, 0, 1), False, 0.0),
        lambda: MarkerPose(1, (0, 0, 0), (0, 0, 2), False, 0.0),
        lambda: MarkerPose(1, (0, 0, float("nan")), (0, 0, 1), False, 0.0),
        lambda: MarkerPose(1, (0, 0, 0), (0, 0, 1), "yes", 0.0),
        lambda: StandardViewRequest(1, 256),
        lambda: Identity(1, 0.5, 3, tuple(range(m.MAX_CANDIDATES + 1))),
        lambda: Identity(True, 0.5, 3),
        lambda: Ambiguous((1, 2), 255),
        lambda: Failure(1, "x" * (m.MAX_TEXT_BYTES + 1)),
        lambda: Stop(42),
        lambda: Discard(70000),
        lambda: Discard(-1),
    ],
)
def test_bad_fields_raise_message_error(build):
    with pytest.raises(MessageError):
        build()


def test_sizes_fit_the_9600_bps_budget():
    pose = MarkerPose(3, (412.5, -120.25, 35.0), (0.0, 0.6, 0.8), False, 3.2)
    assert size_of(pose) == 32  # paper §5.2: a marker pose "well under 50 bytes"
    assert size_of(Heartbeat("predictor", 1, 0.0)) == 14
    assert size_of(CaptureRequest(1, "initial1", 0.0, (0, 0, 0), (0, 0, 0))) == 36
    assert size_of(StandardViewRequest(2, 1)) == 4
    assert size_of(Discard(2)) == 3
    assert size_of(Identity(5, 0.9, 7, (5, 3))) == 1 + 8 + 1 + 4
    assert size_of(Failure.short(m.FailureCode.MARKER_LOST, "é" * 200)) <= 3 + m.MAX_TEXT_BYTES


def test_failure_short_cuts_on_a_character_boundary():
    f = Failure.short(1, "ü" * 100)  # 200 bytes of UTF-8
    assert len(f.text.encode()) <= m.MAX_TEXT_BYTES
    assert set(f.text) == {"ü"}
    assert decode(encode(f)) == f
    assert Stop.short("halt " * 50).reason.startswith("halt halt")


@settings(max_examples=100, deadline=None)
@given(st.tuples(*[st.floats(-800, 800)] * 3), rotvecs())
def test_capture_request_pose_survives_float32(position, rv):
    T = make_T(rotvec_to_matrix(np.array(rv)), np.array(position))
    req = decode(encode(CaptureRequest.from_pose(7, "standard", 12.5, T)))
    T2 = req.pose()
    assert np.allclose(T2[:3, 3], T[:3, 3], atol=1e-3)  # mm: float32 keeps ~1e-4 mm at 800 mm
    assert np.allclose(T2[:3, :3], T[:3, :3], atol=1e-5)  # rad


def test_capture_request_from_look_at_pose():
    T = look_at([300.0, 100.0, 450.0], [250.0, 80.0, 0.0])
    req = CaptureRequest.from_pose(1, "initial2", 3.25, T)
    assert req.kind == "initial2" and req.t_capture == 3.25
    assert np.allclose(req.pose(), T, atol=1e-4)
