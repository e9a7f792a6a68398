"""A rehearsal on the served lab needs only the commands the previous command printed: ``sim serve
--lab-out DIR`` → ``table home`` → ``calibrate`` (the served lab places the target itself, its object
goes back afterwards) → ``run``, which identifies the served object. On the way: a table in Alarm names
the command that homes it, and a refused prompt latches no STOP on the robot's controller (the next
calibrate would refuse one before moving)."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys

import pytest
import yaml
from test_hil import Served

pytestmark = [pytest.mark.skipif(sys.platform != "linux", reason="ptys and the served lab need Linux"),
              pytest.mark.timeout(900)]


def _do(command: str, *extra: str, timeout: float = 400) -> subprocess.CompletedProcess:
    """A printed ``labctl ...`` line, run as this interpreter's labctl (piped: ``key: value`` lines)."""
    argv = shlex.split(command)
    assert argv[0] == "labctl", command
    return subprocess.run([sys.executable, "-m", "labctl", *argv[1:], *extra], capture_output=True, text=True,
                          timeout=timeout)


def _next(out: str) -> str:
    found = re.findall(r"(?m)^next: (labctl .+)$", out)
    assert found, out[-1500:]
    return found[-1].strip()


def test_rehearsal_follows_the_printed_next_steps(tmp_path):
    lab = tmp_path / "served"
    with Served(lab) as served:
        step = served.info["next"]
        assert step == f"labctl --lab {lab} table home"
        # a shorter plan than the lab's (12 images, not 25) keeps the test short; not a command
        target_file = lab / "calibration" / "target.yaml"
        target = yaml.safe_load(target_file.read_text())
        target.update(fixed_positions_mm=[[300.0, 200.0], [440.0, 290.0]], robot_stations=5,
                      registration_positions_mm=[[300.0, 200.0], [120.0, 80.0], [480.0, 80.0]])
        target_file.write_text(yaml.safe_dump(target))

        # out of order: calibrating a table still in Alarm moves nothing and names the command that homes it
        r = _do(f"labctl --lab {lab} calibrate")
        assert r.returncode == 3 and f"next: labctl --lab {lab} calibrate --home" in r.stderr, r.stderr

        r = _do(step, timeout=120)  # table home
        assert r.returncode == 0, r.stderr
        calibrate = _next(r.stdout)
        assert calibrate == f"labctl --lab {lab} calibrate"

        # a refused prompt: the devices are read, no STOP is sent (it would latch on the robot's controller)
        r = _do(calibrate, "--prompt-command", "false")
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert "did not place the target" in r.stderr and "no STOP sent" in r.stderr
        assert "robot clear" not in r.stderr

        r = _do(calibrate)  # the served lab places the target; would refuse a latched robot before moving
        assert r.returncode == 0, r.stderr[-2000:]
        assert re.search(r"(?m)^scene_restored: true$", r.stdout), r.stdout[-1500:]
        assert re.search(r"(?m)^images: 12$", r.stdout)
        step = _next(r.stdout)
        assert step == f"labctl --lab {lab} run --trajectory line"

        r = _do(step, "--json", timeout=240)  # the object is back: the run finds and identifies it
        assert r.returncode == 0, r.stderr[-2000:]
        import json

        result = json.loads(r.stdout)
        assert result["identity"] == served.truth["true_identity"], result
