"""Hypothesis fuzzes the protocol parsers: no input crashes them; well-formed input round-trips."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.drivers.grbl_protocol import parse_line, parse_status, parse_version
from labctl.drivers.robot_protocol import format_request, parse_reply, parse_request
from labctl.sim.clock import VirtualClock
from labctl.sim.emulators.grbl import GrblEmulator

FUZZ = settings(max_examples=300, deadline=None)
grbl_alphabet = st.sampled_from(list("<>|:,.-0123456789IdleRunHoldAlarmMPosWPosFSBfWCOOvokerror[]MSG$=ALARM \r"))


@FUZZ
@given(st.text())
def test_grbl_parse_line_never_raises_on_any_text(text):
    msg = parse_line(text)
    assert msg.kind in {"ok", "error", "alarm", "status", "banner", "msg", "feedback", "setting", "startup",
                        "empty", "unknown"}


@FUZZ
@given(st.binary())
def test_grbl_parse_line_never_raises_on_any_bytes(data):
    parse_line(data)


@FUZZ
@given(st.text(grbl_alphabet, max_size=80))
def test_grbl_status_parser_on_near_miss_text(text):
    st_ = parse_status(text)
    if st_ is not None:
        assert st_.mpos is not None or st_.wpos is not None
    parse_line(text)
    parse_version([parse_line(text)])


@FUZZ
@given(st.sampled_from(["Idle", "Run", "Alarm", "Hold:0", "Hold:1", "Home"]),
       st.tuples(*[st.floats(-9999, 9999, allow_nan=False)] * 3), st.integers(0, 99999), st.integers(0, 30000))
def test_grbl_status_round_trip(state, pos, feed, spindle):
    text = f"<{state}|MPos:{pos[0]:.3f},{pos[1]:.3f},{pos[2]:.3f}|FS:{feed},{spindle}>"
    msg = parse_line(text)
    assert msg.kind == "status" and not msg.is_response
    assert msg.status.state_word == state
    assert all(abs(a - round(b, 3)) < 1e-9 for a, b in zip(msg.status.mpos, pos))
    assert msg.status.feed == feed


def test_grbl_replies_classified():
    assert parse_line("ok").is_response
    e = parse_line("error:22")
    assert e.kind == "error" and e.code == 22 and e.is_response
    a = parse_line("ALARM:2")
    assert a.kind == "alarm" and a.code == 2 and not a.is_response
    assert parse_line("Grbl 1.1h ['$' for help]").kind == "banner"
    assert parse_line("[MSG:Caution: Unlocked]").text == "Caution: Unlocked"
    assert parse_line("$110=6000.000").fields["value"] == 6000.0
    info = parse_version([parse_line("[VER:1.1h.20190830:]"), parse_line("[OPT:V,15,128]")])
    assert info == {"version": "1.1h.20190830", "options": "V", "planner_blocks": 15, "rx_buffer": 128}
    s = parse_line("<Idle|WPos:1.000,2.000,3.000|Bf:15,128|FS:0,0|WCO:10.000,0.000,0.000>").status
    assert s.machine_position() == (11.0, 2.0, 3.0) and s.rx_free == 128


def test_every_emulator_report_parses():
    clk = VirtualClock()
    g = GrblEmulator(clk, homing=False, settings={10: 3})
    g.read_output()
    g.receive(b"G1 X30 F600\n")
    for _ in range(40):
        clk.sleep(0.1)
        g.receive(b"?")
        for line in g.read_output().decode().split("\r\n"):
            if line:
                assert parse_line(line).kind in ("status", "ok"), line


@FUZZ
@given(st.text())
def test_robot_parsers_never_raise(text):
    r = parse_reply(text)
    assert r.kind in ("reply", "async", "unknown")
    r.floats()
    r.floats(3)
    parse_request(text)


@FUZZ
@given(st.binary())
def test_robot_reply_parser_on_bytes(data):
    parse_reply(data)


@FUZZ
@given(st.integers(0, 65535), st.lists(st.floats(-1e4, 1e4, allow_nan=False), max_size=14))
def test_robot_request_round_trip(seq, args):
    line = format_request(seq, "SEG", *args)
    req = parse_request(line)
    assert req.seq == seq and req.command == "SEG" and len(req.args) == len(args)
    assert all(abs(float(a) - b) <= 1e-6 + 1e-9 * abs(b) for a, b in zip(req.args, args))


def test_robot_replies_classified():
    ok = parse_reply("$12 ok 1.0 2.0")
    assert ok.kind == "reply" and ok.ok and ok.seq == 12 and ok.floats(2) == (1.0, 2.0)
    err = parse_reply("$3 E12 too fast")
    assert err.kind == "reply" and not err.ok and err.code == 12 and err.text == "too fast"
    assert parse_reply("@DONE 7").report == "DONE"
    assert parse_reply("$x ok").kind == "unknown"
