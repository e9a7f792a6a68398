"""The TCP host link authenticates its peer (mutual HMAC challenge); garbage never crashes the codec,
the framing or the predictor, and never moves anything."""

from __future__ import annotations

import socket
import threading
import time

import pytest
from fakes import StillRobot
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labctl.config.devices import HostLinkConfig
from labctl.decisions import messages as m
from labctl.runtime.transport import (
    AUTH_MAGIC,
    TCP_HEADER,
    AuthError,
    HostLinkError,
    LinkClosed,
    SerialDeframer,
    TcpLink,
    link_key,
    open_link,
    serial_frame,
    tcp_connect,
    tcp_listen,
)

KEY = b"0123456789abcdef-test-key"


def _frame(msg) -> bytes:
    payload = m.encode(msg)
    return TCP_HEADER.pack(len(payload)) + payload


def test_tcp_link_without_a_key_is_refused_in_one_line():
    cfg = HostLinkConfig(transport="tcp", host="127.0.0.1", tcp_port=1)
    with pytest.raises(HostLinkError, match="LABCTL_LINK_KEY"):
        open_link(cfg, "predictor")


def test_default_listener_binds_localhost_only():
    assert HostLinkConfig().host == "127.0.0.1"


def test_unauthenticated_peer_is_refused_logged_and_never_heard(caplog):
    """An intruder connects first and fires valid frames (a capture request, a stop, a pose): the
    listener refuses it, logs one line, and the real peer then gets the link; the first message the
    predictor receives is the real peer's."""
    refused: list[str] = []
    got = {}
    with tcp_listen("127.0.0.1", 0) as listener:
        port = listener.port

        def serve():
            got["link"] = listener.accept(10.0, authkey=KEY, on_refused=refused.append)

        th = threading.Thread(target=serve)
        th.start()
        intruder = socket.create_connection(("127.0.0.1", port), timeout=5.0)
        hello = intruder.recv(len(AUTH_MAGIC) + 32)
        assert hello.startswith(AUTH_MAGIC)  # the challenge, not a message
        intruder.sendall(_frame(m.CaptureRequest(1, "initial1", 1.0, (400.0, 0.0, 300.0), (0.0, 0.0, 0.0)))
                         + _frame(m.Stop("x")) + b"\x00" * 40)
        intruder.settimeout(5.0)
        try:  # refused: the listener closed the connection (a reset, as the intruder's bytes went unread)
            assert intruder.recv(100) == b""
        except ConnectionResetError:
            pass
        intruder.close()
        client = tcp_connect("127.0.0.1", port, timeout=5.0, authkey=KEY)
        th.join(timeout=10.0)
    server = got["link"]
    with client, server:
        client.send(m.Hello("recognizer", 7))
        assert server.recv(timeout=5.0) == m.Hello("recognizer", 7)
        assert server.recv(timeout=0.1) is None and server.messages_received == 1
    assert len(refused) == 1 and "refused peer 127.0.0.1" in refused[0] and "\n" not in refused[0]
    assert any("refused peer" in r.getMessage() for r in caplog.records)


def test_wrong_key_and_fake_listener_are_both_caught():
    refused: list[str] = []
    with tcp_listen("127.0.0.1", 0) as listener:
        th = threading.Thread(target=lambda: pytest.raises(HostLinkError, listener.accept, 1.5, authkey=KEY,
                                                           on_refused=refused.append))
        th.start()
        with pytest.raises(AuthError):
            tcp_connect("127.0.0.1", listener.port, timeout=5.0, authkey=b"another-key-of-16-bytes")
        th.join(timeout=10.0)
    assert len(refused) == 1 and "wrong key" in refused[0]
    # a listener that does not hold the key cannot steer the recognizer either
    fake = socket.create_server(("127.0.0.1", 0))
    port = fake.getsockname()[1]

    def fake_server():
        conn, _ = fake.accept()
        conn.sendall(AUTH_MAGIC + b"\x01" * 32)
        conn.recv(64)
        conn.sendall(b"\x02" * 32)  # a guess at the answer
        time.sleep(0.5)
        conn.close()

    th = threading.Thread(target=fake_server)
    th.start()
    with pytest.raises(AuthError, match="does not hold the link key"):
        tcp_connect("127.0.0.1", port, timeout=5.0, authkey=KEY)
    th.join(timeout=5.0)
    fake.close()


def test_link_key_comes_from_the_environment_or_a_file(tmp_path, monkeypatch):
    monkeypatch.delenv("LABCTL_LINK_KEY", raising=False)
    cfg = HostLinkConfig(transport="tcp", key_file="link.key")
    with pytest.raises(HostLinkError, match="cannot read"):
        link_key(cfg, tmp_path)
    (tmp_path / "link.key").write_text("a-file-key-0123456789\n")
    assert link_key(cfg, tmp_path) == b"a-file-key-0123456789"
    monkeypatch.setenv("LABCTL_LINK_KEY", "env-key-wins-0123456789")
    assert link_key(cfg, tmp_path) == b"env-key-wins-0123456789"
    monkeypatch.setenv("LABCTL_LINK_KEY", "short")
    with pytest.raises(HostLinkError, match="too short"):
        link_key(cfg, tmp_path)
    monkeypatch.delenv("LABCTL_LINK_KEY")
    assert link_key(HostLinkConfig(), tmp_path) is None


# ---- garbage: the codec, the framing and the predictor ------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_codec_and_serial_framing_never_crash_on_garbage(data):
    try:
        msg = m.decode(data)
    except m.MessageError:
        msg = None
    if msg is not None:
        assert m.decode(m.encode(msg)) == msg
    deframer = SerialDeframer()
    for payload in deframer.feed(data) + deframer.feed(serial_frame(b"\x07ok")[:3] + data):
        assert isinstance(payload, bytes)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.binary(min_size=0, max_size=80), min_size=1, max_size=6))
def test_tcp_framing_survives_garbage_frames(frames):
    a, b = socket.socketpair()
    link = TcpLink(b)
    try:
        a.sendall(b"".join(TCP_HEADER.pack(len(f)) + f for f in frames) + _frame(m.FrameTaken(3, 1.0)))
        seen = []
        while True:
            msg = link.recv(timeout=2.0)
            assert msg is not None, "the good frame after the garbage must arrive"
            seen.append(msg)
            if msg == m.FrameTaken(3, 1.0):
                break
        assert link.frames_dropped + len(seen) == len(frames) + 1
        a.close()
        with pytest.raises(LinkClosed):
            link.recv(timeout=2.0)
    finally:
        a.close()
        link.close()


class _RecordingRobot(StillRobot):
    """A robot that records every command that could move it."""

    def __init__(self):
        self.moves = []

    def segment(self, *a, **k):
        self.moves.append(("segment", a))
        return (0.0, 1.0)



@pytest.fixture(scope="module")
def ctx():
    from labctl.config import load_lab
    from labctl.decisions.context import RunContext
    from labctl.workspace import sample_lab_path

    return RunContext.load(load_lab(sample_lab_path()))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.binary(max_size=120), min_size=1, max_size=20))
def test_garbage_messages_never_move_the_robot(ctx, blobs):
    """Whatever decodes from garbage, handed to the predictor as the live worker does, commands no motion
    and raises nothing but a message error (the worker drops those)."""
    from labctl.decisions.predictor import PredictorPlanner
    from labctl.runtime.live import plausible

    robot = _RecordingRobot()
    planner = PredictorPlanner(ctx, robot, lambda msg: None, lambda *a, **k: None, t_start=0.0)
    for i, blob in enumerate(blobs):
        try:
            msg = m.decode(blob)
        except m.MessageError:
            continue
        if plausible(msg, ctx):
            planner.on_message(msg, 0.1 * i)
    assert robot.moves == []
