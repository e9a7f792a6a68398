"""Serial framing (pure): COBS, CRC-16, and a deframer that resyncs after noise."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.decisions.messages import Heartbeat, MarkerPose, encode
from labctl.runtime.transport import (
    MAX_SERIAL_PAYLOAD,
    SERIAL_OVERHEAD,
    HostLinkError,
    SerialDeframer,
    cobs_decode,
    cobs_encode,
    crc16,
    serial_frame,
    wire_time_s,
)

payloads = st.binary(min_size=1, max_size=MAX_SERIAL_PAYLOAD)


def test_crc16_check_value():
    assert crc16(b"123456789") == 0xD64E  # CRC-16/GENIBUS catalogue check value
    assert crc16(b"") == 0x0000


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=700))
def test_cobs_round_trip_has_no_zero_bytes(data):
    enc = cobs_encode(data)
    assert 0 not in enc
    assert cobs_decode(enc) == data
    assert len(enc) <= len(data) + 1 + len(data) // 254


def test_cobs_known_vectors():
    # from the COBS paper / Wikipedia examples
    assert cobs_encode(b"\x00") == b"\x01\x01"
    assert cobs_encode(b"\x00\x00") == b"\x01\x01\x01"
    assert cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    assert cobs_encode(b"\x11\x00\x00\x00") == b"\x02\x11\x01\x01\x01"
    assert cobs_encode(bytes(range(1, 255))) == b"\xff" + bytes(range(1, 255)) + b"\x01"


@pytest.mark.parametrize("bad", [b"", b"\x00", b"\x05\x01\x02", b"\x03\x01\x00"])
def test_cobs_decode_rejects_invalid(bad):
    with pytest.raises(ValueError):
        cobs_decode(bad)


@settings(max_examples=200, deadline=None)
@given(st.lists(payloads, min_size=1, max_size=6), st.data())
def test_deframer_reassembles_any_chunking(items, data):
    stream = b"".join(serial_frame(p) for p in items)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
    d = SerialDeframer()
    out = []
    prev = 0
    for c in cuts + [len(stream)]:
        out += d.feed(stream[prev:c])
        prev = c
    assert out == items
    assert d.dropped == 0
    assert all(len(serial_frame(p)) == len(p) + SERIAL_OVERHEAD for p in items)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600), payloads)
def test_frame_after_any_noise_is_delivered(noise, payload):
    d = SerialDeframer()
    out = d.feed(noise) + d.feed(serial_frame(payload))
    assert out and out[-1] == payload


# derandomized: CRC-16 lets about 1 in 65536 corrupt fragments through, so a random run could
# (rarely, rightly) meet one; the property is about everything else.
@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.lists(payloads, min_size=3, max_size=6), st.data())
def test_flipped_bit_loses_at_most_two_frames_and_never_delivers_garbage(items, data):
    stream = bytearray(b"".join(serial_frame(p) for p in items))
    i = data.draw(st.integers(0, len(stream) - 1))
    stream[i] ^= 1 << data.draw(st.integers(0, 7))
    d = SerialDeframer()
    out = d.feed(bytes(stream)) + d.feed(b"\x00")  # the next frame's leading 00 ends a pending one
    # a flip inside a frame kills that frame; a flip of a delimiter may merge two neighbours
    assert len(out) >= len(items) - 2
    it = iter(items)
    assert all(any(p == q for q in it) for p in out)  # delivered frames are sent ones, in order
    if len(out) < len(items):
        assert d.dropped >= 1


def test_oversized_junk_is_dropped_and_counted_then_resyncs():
    d = SerialDeframer()
    assert d.feed(bytes([7]) * 2000) == []
    payload = encode(Heartbeat("predictor", 3, 1.5))
    assert d.feed(serial_frame(payload)) == [payload]
    assert d.dropped == 1


def test_serial_frame_rejects_too_long_payloads():
    with pytest.raises(HostLinkError):
        serial_frame(bytes(MAX_SERIAL_PAYLOAD + 1))


def test_random_line_noise_is_survivable():
    rng = random.Random(7)
    d = SerialDeframer()
    noise = bytes(rng.randrange(256) for _ in range(20000))
    assert d.feed(noise) == []  # 20 kB of noise: no false frame passes COBS + CRC-16 here
    assert d.dropped > 10
    payload = encode(MarkerPose(2, (1.0, 2.0, 3.0), (0.0, 0.0, 1.0), True, 0.25))
    assert d.feed(serial_frame(payload)) == [payload]


def test_wire_time_is_ten_bits_per_byte():
    assert wire_time_s(960, 9600) == pytest.approx(1.0)
    assert wire_time_s(len(serial_frame(encode(MarkerPose(1, (0, 0, 0), (0, 0, 1), False, 0)))), 9600) < 0.05
