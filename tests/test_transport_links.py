"""Host links over real channels: a multiprocessing pipe, TCP on 127.0.0.1, and ptys."""

from __future__ import annotations

import multiprocessing
import random
import threading
import time

import pytest

from labctl.config.devices import HostLinkConfig
from labctl.decisions.messages import (
    CaptureRequest,
    FrameTaken,
    Heartbeat,
    Hello,
    Identity,
    MarkerPose,
    Stop,
    encode,
)
from labctl.runtime.transport import (
    SERIAL_OVERHEAD,
    TCP_HEADER,
    HostLinkError,
    LinkClosed,
    SerialHostLink,
    local_pair,
    open_link,
    pty_null_modem,
    serial_frame,
    tcp_connect,
    tcp_listen,
)

SAMPLE = [
    Hello("predictor", 4242),
    CaptureRequest(1, "initial1", 12.25, (400.0, 20.0, 350.0), (3.0, 0.1, -0.2)),
    FrameTaken(1, 12.26),
    MarkerPose(1, (412.5, -10.0, 35.0), (0.0, 0.6, 0.8), False, 4.5),
    Identity(3, 0.97, 7, (3, 5)),
    Stop("done"),
]


def exchange(a, b):
    """Send SAMPLE a->b and a heartbeat b->a; check content, order, counters and the log hook."""
    log = []
    a.log_hook = lambda d, m, n: log.append((d, type(m).__name__, n))
    for msg in SAMPLE:
        a.send(msg)
    got = [b.recv(timeout=5.0) for _ in SAMPLE]
    assert got == SAMPLE
    b.send(Heartbeat("recognizer", 1, 0.5))
    assert a.recv(timeout=5.0) == Heartbeat("recognizer", 1, 0.5)
    assert b.recv(timeout=0.05) is None  # nothing more: a timeout, not an error
    assert a.bytes_sent == b.bytes_received
    assert b.bytes_sent == a.bytes_received
    assert a.messages_sent == len(SAMPLE) and b.messages_received == len(SAMPLE)
    assert [e[0] for e in log] == ["send"] * len(SAMPLE) + ["recv"]
    assert sum(n for d, _, n in log if d == "send") == a.bytes_sent
    return log


# ---- local ----------------------------------------------------------------------------------------


def test_local_pair_in_process():
    a, b = local_pair()
    with a, b:
        log = exchange(a, b)
        assert log[0][2] == len(encode(SAMPLE[0]))  # local pipes count message bytes
    with pytest.raises(LinkClosed):
        a.send(Stop(""))


def _echo_worker(link):
    msg = link.recv(timeout=10.0)
    link.send(msg)
    link.send(Heartbeat("recognizer", 7, 1.0))
    link.close()


def test_local_pair_across_processes_and_peer_exit():
    ctx = multiprocessing.get_context("spawn")
    a, b = local_pair()
    proc = ctx.Process(target=_echo_worker, args=(b,))
    proc.start()
    b.close()  # the parent's copy of the worker's end
    try:
        a.send(SAMPLE[3])
        assert a.recv(timeout=20.0) == SAMPLE[3]
        assert a.recv(timeout=5.0) == Heartbeat("recognizer", 7, 1.0)
        proc.join(timeout=10.0)
        with pytest.raises(LinkClosed):
            a.recv(timeout=2.0)
    finally:
        if proc.is_alive():
            proc.kill()
        a.close()


def test_open_link_local_needs_an_end():
    cfg = HostLinkConfig(transport="local")
    with pytest.raises(HostLinkError, match="local_pair"):
        open_link(cfg, "predictor")
    a, b = local_pair()
    assert open_link(cfg, "predictor", local_end=a) is a
    a.close()
    b.close()
    with pytest.raises(HostLinkError):
        open_link(cfg, "boss", local_end=a)


# ---- TCP ------------------------------------------------------------------------------------------


def test_tcp_exchange_and_frame_bytes():
    with tcp_listen("127.0.0.1", 0) as listener:
        client = tcp_connect("127.0.0.1", listener.port, timeout=5.0)
        server = listener.accept(timeout=5.0)
    with client, server:
        log = exchange(server, client)
        assert log[0][2] == len(encode(SAMPLE[0])) + TCP_HEADER.size
        client.send(SAMPLE[2])
        time.sleep(0.2)
        assert server.recv(timeout=0) == SAMPLE[2]


def test_tcp_peer_close_is_link_closed():
    with tcp_listen("127.0.0.1", 0) as listener:
        client = tcp_connect("127.0.0.1", listener.port, timeout=5.0)
        server = listener.accept(timeout=5.0)
    client.send(FrameTaken(2, 3.0))
    client.close()
    assert server.recv(timeout=5.0) == FrameTaken(2, 3.0)  # delivered before the close
    with pytest.raises(LinkClosed):
        server.recv(timeout=5.0)
    server.close()


def test_tcp_garbage_frame_is_dropped_not_fatal():
    import socket

    with tcp_listen("127.0.0.1", 0) as listener:
        raw = socket.create_connection(("127.0.0.1", listener.port), timeout=5.0)
        server = listener.accept(timeout=5.0)
    with server:
        junk = b"\xee\x01\x02"
        good = encode(FrameTaken(9, 1.0))
        raw.sendall(TCP_HEADER.pack(len(junk)) + junk + TCP_HEADER.pack(len(good)) + good)
        assert server.recv(timeout=5.0) == FrameTaken(9, 1.0)
        assert server.frames_dropped == 1
        raw.close()


def test_tcp_timeouts_are_explicit():
    with tcp_listen("127.0.0.1", 0) as listener:
        port = listener.port
        t0 = time.monotonic()
        with pytest.raises(HostLinkError, match="no peer connected"):
            listener.accept(timeout=0.2)
        assert time.monotonic() - t0 >= 0.2
    # nobody listens now: connecting retries, then gives up with a HostLinkError
    with pytest.raises(HostLinkError, match="could not connect"):
        tcp_connect("127.0.0.1", port, timeout=0.3, retry_s=0.05)


def test_tcp_connect_retries_until_the_listener_appears():
    with tcp_listen("127.0.0.1", 0) as probe:
        port = probe.port
    result = {}

    def late_listener():
        time.sleep(0.3)
        cfg = HostLinkConfig(transport="tcp", host="127.0.0.1", tcp_port=port)
        result["server"] = open_link(cfg, "predictor", connect_timeout=5.0, authkey=b"a-shared-test-key-123")

    th = threading.Thread(target=late_listener)
    th.start()
    cfg = HostLinkConfig(transport="tcp", host="127.0.0.1", tcp_port=port)
    client = open_link(cfg, "recognizer", connect_timeout=5.0, authkey=b"a-shared-test-key-123")
    th.join(timeout=10.0)
    server = result["server"]
    with client, server:
        client.send(Hello("recognizer", 1))
        assert server.recv(timeout=5.0) == Hello("recognizer", 1)


# ---- serial over a pty null modem -------------------------------------------------------------------


def test_serial_exchange_over_ptys():
    with pty_null_modem() as modem:
        cfg_a = HostLinkConfig(transport="serial", port=modem.port_a, baud=9600)
        a = open_link(cfg_a, "predictor")
        b = SerialHostLink.open(modem.port_b, 9600)
        with a, b:
            log = exchange(a, b)
            assert log[0][2] == len(encode(SAMPLE[0])) + SERIAL_OVERHEAD
            assert modem.bytes_a_to_b == a.bytes_sent
            a.send(SAMPLE[2])
            time.sleep(0.2)
            assert b.recv(timeout=0) == SAMPLE[2]  # a zero timeout still takes what has arrived
            assert b.recv(timeout=0) is None


def test_serial_open_bad_port_is_link_error(tmp_path):
    with pytest.raises(HostLinkError, match="cannot open serial port"):
        SerialHostLink.open(str(tmp_path / "no-such-tty"))
    with pytest.raises(HostLinkError, match="needs a port"):
        open_link(HostLinkConfig(transport="serial", port=None), "recognizer")


class BitFlipper:
    """Corrupt one random bit in every ``every``-th chunk the cable carries (seeded)."""

    def __init__(self, every: int, seed: int):
        self.every, self.rng, self.n, self.hits = every, random.Random(seed), 0, 0

    def __call__(self, chunk: bytes) -> bytes:
        self.n += 1
        if self.n % self.every:
            return chunk
        self.hits += 1
        out = bytearray(chunk)
        out[self.rng.randrange(len(out))] ^= 1 << self.rng.randrange(8)
        return bytes(out)


def test_serial_drops_corrupted_frames_and_keeps_going():
    flipper = BitFlipper(every=3, seed=11)
    n = 30
    with pty_null_modem(corrupt=flipper) as modem:
        a = SerialHostLink.open(modem.port_a)
        b = SerialHostLink.open(modem.port_b)
        with a, b:
            sent = [Heartbeat("predictor", i, i * 0.2) for i in range(n)]
            got = []
            for msg in sent:
                a.send(msg)  # one frame per chunk: wait for each before the next
                r = b.recv(timeout=0.3)
                if r is not None:
                    got.append(r)
            a.send(Stop("end"))  # its leading 00 closes a frame whose trailing 00 was hit
            tail = b.recv(timeout=1.0)
            while tail is not None and not isinstance(tail, Stop):
                got.append(tail)
                tail = b.recv(timeout=1.0)
    assert flipper.hits == n // 3
    seqs = [m.seq for m in got]
    assert seqs == sorted(set(seqs))  # no duplicates, order kept, nothing invented
    assert all(m == sent[m.seq] for m in got)
    lost = n - len(got)
    assert 1 <= lost <= 2 * flipper.hits
    assert b.frames_dropped >= lost / 2


def test_serial_resyncs_after_line_noise():
    rng = random.Random(5)
    noise = bytes(rng.randrange(256) for _ in range(300))
    first = [True]

    def noisy(chunk: bytes) -> bytes:
        if first[0]:
            first[0] = False
            return noise + chunk  # a burst of noise right before the first frame
        return chunk

    with pty_null_modem(corrupt=noisy) as modem:
        a = SerialHostLink.open(modem.port_a)
        b = SerialHostLink.open(modem.port_b)
        with a, b:
            a.send(SAMPLE[3])
            assert b.recv(timeout=2.0) == SAMPLE[3]
            assert b.frames_dropped >= 1
            assert b.bytes_received == len(noise) + len(serial_frame(encode(SAMPLE[3])))
            a.send(SAMPLE[4])
            assert b.recv(timeout=2.0) == SAMPLE[4]


def test_paced_null_modem_takes_at_least_the_wire_time():
    # correctness of the pacing model (10 bits per byte), not a speed target
    with pty_null_modem(baud=9600) as modem:
        a = SerialHostLink.open(modem.port_a)
        b = SerialHostLink.open(modem.port_b)
        with a, b:
            t0 = time.monotonic()
            nbytes = sum(a.send(m) for m in SAMPLE)
            for m in SAMPLE:
                assert b.recv(timeout=5.0) == m
            assert time.monotonic() - t0 >= nbytes * 10 / 9600 * 0.95
