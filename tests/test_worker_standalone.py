"""``labctl worker``: the two-PC set-up's link options and its refusal to drive simulated devices."""

from __future__ import annotations

import subprocess
import sys

import pytest

from labctl.config import load_lab
from labctl.errors import UserInputError
from labctl.runtime.standalone import link_config
from labctl.workspace import sample_lab_path


def test_link_option_overrides_the_host_link():
    lab = load_lab(sample_lab_path())
    tcp = link_config(lab, "tcp://10.0.0.2:6000")
    assert (tcp.transport, tcp.host, tcp.tcp_port) == ("tcp", "10.0.0.2", 6000)
    ser = link_config(lab, "/dev/ttyS0")
    assert (ser.transport, ser.port, ser.baud) == ("serial", "/dev/ttyS0", 9600)
    with pytest.raises(UserInputError):
        link_config(lab, "tcp://nohostport")
    with pytest.raises(UserInputError):  # the sample lab's link is local: a lone worker needs --link
        link_config(lab, None)


def test_worker_refuses_simulated_devices_in_one_line():
    r = subprocess.run([sys.executable, "-m", "labctl", "--lab", str(sample_lab_path()), "worker", "predictor",
                        "--link", "tcp://127.0.0.1:5799"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert len(r.stderr.strip().splitlines()) == 1 and "sim" in r.stderr
