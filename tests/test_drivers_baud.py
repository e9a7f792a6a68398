"""What the configured baud rate means on each transport, as ``labctl devices`` says it.

A device path runs at the driver file's ``baud``; ``socket://`` (ser2net's raw TCP) carries no rate, so
the server's connector line sets it; ``rfc2217://`` keeps the server's rate unless the table file's
``set_remote_baud`` asks to switch it (checked against the real ser2net in test_ser2net_firmware.py).
"""

from __future__ import annotations

import re

import pytest

from labctl.config import load_lab
from labctl.drivers.serial_link import baud_words, remote_baud
from labctl.runtime.devices import _where
from labctl.workspace import init_workspace


@pytest.mark.parametrize(("url", "who"), [("/dev/ttyUSB0", "local"), ("/dev/pts/3", "local"),
                                         ("socket://10.0.0.5:2000", "server"), ("rfc2217://host:4000", "rfc2217"),
                                         ("spy:///dev/ttyACM0", "local")])
def test_who_sets_the_rate(url, who):
    assert remote_baud(url) == who


def test_the_words_say_the_rate_only_where_it_takes_effect():
    assert baud_words("/dev/ttyUSB0", 115200) == "@ 115200 bps"
    assert baud_words("socket://h:2000", 9600) == "(baud set by the server)"
    assert baud_words("socket://h:2000", 9600, set_remote_baud=True) == "(baud set by the server)"  # TCP has none
    assert baud_words("rfc2217://h:4000", 9600) == "(baud set by the server)"
    assert baud_words("rfc2217://h:4000", 9600, set_remote_baud=True) == "@ 9600 bps (set on the server)"


@pytest.mark.parametrize(("port", "extra", "words"), [
    ("socket://127.0.0.1:2000", "", "socket://127.0.0.1:2000 (baud set by the server)"),
    ("rfc2217://127.0.0.1:4000?ign_set_control", "", "(baud set by the server)"),
    ("rfc2217://127.0.0.1:4000", "set_remote_baud: true\n", "@ 9600 bps (set on the server)"),
    ("/dev/ttyUSB0", "", "/dev/ttyUSB0 @ 9600 bps"),
])
def test_devices_where_line_over_each_transport(tmp_path, port, extra, words):
    lab_dir = init_workspace(tmp_path / "lab")
    table = lab_dir / "drivers" / "table.yaml"
    text = re.sub(r"(?m)^kind: sim", "kind: grbl", table.read_text())
    text = re.sub(r"(?m)^port: null", f"port: '{port}'", text)
    text = re.sub(r"(?m)^set_remote_baud: false\n", "", text)
    table.write_text(text + extra)
    kind, where = _where("table", load_lab(lab_dir))
    assert kind == "grbl" and where.endswith(words), where
    assert ("9600" in where) == ("bps" in words)
