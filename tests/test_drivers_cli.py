"""``labctl devices`` and ``labctl table …`` as a user runs them (table commands on a pty)."""

from __future__ import annotations

import json

import pytest
from fakes import fake_grbl, run_cli

run = run_cli


def test_devices_in_the_sample_lab_checks_in_process_emulators(capsys):
    code, out, _ = run(capsys, "--json", "devices")
    data = json.loads(out)
    assert code == 0 and data["ok"]
    roles = {d["role"]: d for d in data["devices"]}
    assert set(roles) == {"table", "robot", "fixed_camera", "mobile_camera"}
    assert "in-process emulator" in roles["table"]["verdict"]
    assert roles["table"]["identity"].startswith("Grbl 1.1h")
    assert roles["robot"]["identity"].startswith("labctl-robot")


def test_table_move_status_stream(capsys, tmp_path):
    prog = tmp_path / "prog.nc"
    moves = "".join(f"G1 X{50 + i * 0.5:.1f} Y{40 + i * 0.1:.1f}\n" for i in range(200))
    prog.write_text("G21\nG90\nG1 F3000\n" + moves)
    with fake_grbl(homing=True) as dev:
        code, out, err = run(capsys, "table", "move", "100", "50", "--feed", "3000", "--port", dev.path,
                             "--baud", "115200")
        assert code == 3 and "ALARM" in err and "--unlock" in err  # the power-up lock is never cleared silently
        code, out, err = run(capsys, "table", "move", "100", "50", "--feed", "3000", "--unlock", "--port", dev.path,
                             "--baud", "115200")
        assert code == 0, err
        with dev.lock:
            assert not dev.emulator.moving
        code, out, err = run(capsys, "table", "status", "--port", dev.path, "--baud", "115200", "--json")
        d = json.loads(out)
        assert code == 0 and d["state"] == "Idle" and d["position"] == {"x": 100.0, "y": 50.0, "z": 0.0}
        code, out, err = run(capsys, "--json", "table", "stream", str(prog), "--port", dev.path, "--baud", "115200")
        d = json.loads(out)
        assert code == 0 and d["lines"] == 203 and d["position"]["x"] == pytest.approx(149.5)
        with dev.lock:
            assert dev.emulator.rx_overflows == 0


def test_table_errors_are_one_line_with_device_exit_code(capsys):
    with fake_grbl(homing=False) as dev:
        code, out, err = run(capsys, "table", "move", "900", "50", "--feed", "3000", "--port", dev.path,
                             "--baud", "115200")
        assert code == 3 and "ALARM:2" in err and "Traceback" not in err
        code, out, err = run(capsys, "table", "reset", "--unlock", "--port", dev.path, "--baud", "115200", "--json")
        assert code == 0 and json.loads(out)["state"] == "Idle"
    code, out, err = run(capsys, "table", "status")
    assert code == 2 and "--port" in err  # the sample lab's table is simulated: no port


def test_reset_and_status_report_the_same_firmware_version(capsys):
    with fake_grbl() as dev:
        code, out, _ = run(capsys, "--json", "table", "status", "--port", dev.path, "--baud", "115200")
        assert code == 0
        status_version = json.loads(out)["version"]
        code, out, _ = run(capsys, "--json", "table", "reset", "--port", dev.path, "--baud", "115200")
        assert code == 0
        assert json.loads(out)["version"] == status_version and status_version.startswith("1.1h.")
