"""``labctl sim serve``'s engine: both emulators on ptys, reachable by the real drivers."""

from __future__ import annotations

import threading

from labctl.config import load_lab
from labctl.drivers.grbl import GrblTable
from labctl.drivers.interfaces import Robot, Table
from labctl.drivers.robot import SerialRobot
from labctl.sim.emulators.serve import serve_forever
from labctl.workspace import sample_lab_path


def test_serve_forever_exposes_table_and_robot():
    lab = load_lab(sample_lab_path())
    ports: dict = {}
    ready = threading.Event()
    stop = threading.Event()

    def on_ready(p):
        ports.update(p)
        ready.set()

    th = threading.Thread(target=serve_forever, args=(lab,), kwargs={"baud": 115200, "on_ready": on_ready,
                                                                    "should_stop": stop.is_set}, daemon=True)
    th.start()
    try:
        assert ready.wait(10)
        assert set(ports) == {"table", "robot"} and all(p.startswith("/dev/") for p in ports.values())
        with GrblTable(ports["table"], 115200, reset_on_open=False) as table:
            assert isinstance(table, Table)
            assert table.info["version"].startswith("1.1h")
            assert table.status().state in ("Alarm", "Idle")
        with SerialRobot(ports["robot"], 115200) as robot:
            assert isinstance(robot, Robot)
            assert not robot.status().moving
    finally:
        stop.set()
        th.join(5)
    assert not th.is_alive()
