"""Issue 17: the typed accessors that replaced unchecked Optional reads, and the OpenClose contract."""

import pytest

from labctl.drivers.grbl_protocol import parse_line, parse_status
from labctl.drivers.interfaces import OpenClose


def test_status_report_accessor():
    msg = parse_line("<Run|MPos:1.000,2.000,3.000|FS:500,0>")
    assert msg.kind == "status" and msg.report.state == "Run" and msg.report.mpos == (1.0, 2.0, 3.0)
    with pytest.raises(ValueError, match="not a status report"):
        _ = parse_line("ok").report


def test_code_accessor():
    assert parse_line("error:20").number == 20
    assert parse_line("ALARM:3").number == 3
    assert parse_line("$110=500.000").number == 110
    with pytest.raises(ValueError, match="without a code"):
        _ = parse_line("ok").number


def test_machine_position_from_work_position():
    # GRBL 1.1 interface.md: MPos = WPos + WCO (the report's own WCO, else the one remembered)
    st = parse_status("<Idle|WPos:1.000,2.000,3.000|FS:0,0|WCO:10.000,20.000,30.000>")
    assert st is not None and st.machine_position() == (11.0, 22.0, 33.0)
    st = parse_status("<Idle|WPos:1.000,2.000,3.000|FS:0,0>")
    assert st is not None and st.machine_position() is None
    assert st.machine_position((-1.0, -2.0, -3.0)) == (0.0, 0.0, 0.0)


def test_open_close_requires_both():
    class OnlyOpen(OpenClose):
        def open(self) -> None:
            pass

    with pytest.raises(TypeError):
        OnlyOpen()  # type: ignore[abstract]

    calls = []

    class Both(OpenClose):
        def open(self) -> None:
            calls.append("open")

        def close(self) -> None:
            calls.append("close")

    with Both() as dev:
        assert isinstance(dev, Both)
    assert calls == ["open", "close"]
