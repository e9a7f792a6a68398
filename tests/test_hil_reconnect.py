"""A device link dropped mid-run, out of process (issue 12, Build 7; acceptance: "A link dropped
mid-run ends in recovery or a typed error within its configured time. It never hangs, and it never
moves after an unknown-position alarm").

``labctl sim serve --tcp --lab-out DIR`` serves the table and the robot controller behind
ser2net-style TCP bridges; its ``/control/link`` endpoint stops a device's bridge (the client's
connection and the port close, as when ser2net stops) and starts it again, optionally resetting
the controller meanwhile (a ser2net restart pulsing DTR). ``labctl run --trajectory line`` runs on
the written all-real lab (``reconnect_s`` set in the driver files); once the record shows the
intercept stage, the test drops a link and times the outcome against ``reconnect_s``: these are
functional bounds from the configuration, not speed benchmarks.

In CI: the table's link that does not come back (typed error, exit 3, bounded, record kept,
robot stopped, no process left); one run with a brief table drop it recovers from, then the
robot's link that does not come back. With ``LABCTL_HIL_LONG=1`` also: a brief table drop alone
(the run identifies), a table reset while away (ALARM, nothing moves), the robot's link alone.
Each test serves a lab of its own (a run leaves the controllers in its end state).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
import urllib.parse
import urllib.request
from pathlib import Path

import pytest
import yaml
from test_hil import Served, labctl

from labctl.records import read_events

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="ptys and the served lab need Linux")
long_only = pytest.mark.skipif(not os.environ.get("LABCTL_HIL_LONG"),
                               reason="longer HIL reconnect variants: set LABCTL_HIL_LONG=1")

RECONNECT_S = 4.0
#: after the configured window: the stop path (robot STOP and brake, the supervisor's own stop and
#: confirmation through fresh drivers, the record) and process exits on a loaded 2-core machine
MARGIN_S = 8.0


def _configure(lab: Path, reconnect_s: float = RECONNECT_S) -> None:
    for role in ("table", "robot"):
        f = lab / "drivers" / f"{role}.yaml"
        f.write_text(yaml.safe_dump({**yaml.safe_load(f.read_text()), "reconnect_s": reconnect_s}))


def _link(served: Served, device: str, up: bool, reset: bool = False) -> dict:
    query = urllib.parse.urlencode({"device": device, "up": int(up), **({"reset": 1} if reset else {})})
    req = urllib.request.Request(f"{served.info['link_control']}?{query}", method="POST")
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.loads(r.read())


def _events(run_dir: Path) -> list[dict]:
    path = run_dir / "events.jsonl"
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:  # a line being written
            pass
    return out


class DroppedRun:
    """``labctl run --trajectory line`` on ``lab``; at its intercept stage ``device``'s link drops
    (and comes back after ``down_s`` unless it is None; then ``then(self)`` if given); ``at`` picks
    another moment (the first time it accepts the record's events so far). Wall-clock
    times of the drop (``dropped["t_wall"]``) and the exit (``t_exit``)."""

    def __init__(self, served: Served, lab: Path, device: str, down_s: float | None, reset: bool = False,
                 timeout_s: float = 180.0, then=None, at=lambda evs: any(e.get("stage") == "intercept" for e in evs)):
        runs = lab / "runs"
        before = set(runs.iterdir()) if runs.exists() else set()
        proc = subprocess.Popen([sys.executable, "-m", "labctl", "--lab", str(lab), "--json", "run", "--trajectory",
                                 "line"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out: dict = {}
        reader = threading.Thread(target=lambda: out.update(zip(("stdout", "stderr"), proc.communicate())),
                                  daemon=True)
        reader.start()
        deadline = time.monotonic() + timeout_s
        self.run_dir = None
        try:
            while True:
                assert time.monotonic() < deadline, "the run never reached the intercept stage"
                assert proc.poll() is None, f"the run ended before the intercept stage: {proc.returncode}"
                new = sorted(set(runs.iterdir()) - before) if runs.exists() else []
                if new and at(_events(new[0])):
                    self.run_dir = new[0]
                    break
                time.sleep(0.05)
            self.dropped = _link(served, device, up=False, reset=reset)
            if down_s is not None:
                time.sleep(down_s)
                self.restored = _link(served, device, up=True)
            if then is not None:
                then(self)
            reader.join(max(0.0, deadline - time.monotonic()))
            assert not reader.is_alive(), "the run did not end"
        finally:
            if proc.poll() is None:
                proc.kill()
        self.t_exit = time.time()
        self.code, self.stdout, self.stderr = proc.returncode, out.get("stdout", ""), out.get("stderr", "")
        self.events = read_events(self.run_dir, strict=True)  # the record reads back whole
        self.drop_to_exit_s = self.t_exit - self.dropped["t_wall"]

    def first(self, name: str, contains: str = "") -> dict | None:
        return next((e for e in self.events if e["event"] == name and contains in json.dumps(e)), None)

    def wait_for_log(self, contains: str, timeout_s: float) -> dict:
        """While the run goes on: the first ``log`` event of its record containing ``contains``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.events = _events(self.run_dir)
            if (e := self.first("log", contains)) is not None:
                return e
            time.sleep(0.05)
        raise AssertionError(f"no {contains!r} in the record within {timeout_s:g} s")

    def log_wall(self, contains: str) -> float:
        e = self.first("log", contains)
        assert e is not None, f"no log event with {contains!r}"
        return e["wall"]

    def workers_gone(self) -> bool:
        pids = [e["pid"] for e in self.events if e["event"] == "worker_started"]
        assert len(pids) == 2
        for pid in pids:
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                continue
            return False
        return True


def _robot_still(lab: Path) -> bool:
    """The served robot, asked through the real driver after the run: at rest."""
    from labctl.config.lab import load_lab
    from labctl.drivers.robot import SerialRobot

    with SerialRobot.from_config(load_lab(lab).robot) as robot:
        return not robot.status().moving


def _table_state(lab: Path) -> dict:
    r = labctl("--json", "table", "status", lab=lab, timeout=60)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


@pytest.fixture
def served_lab(tmp_path):
    """A lab served over TCP in another process (its own per test: a run leaves the controllers in their
    end state), ``reconnect_s`` set in its driver files, the table unlocked and moved to the start."""
    lab = tmp_path / "served"
    with Served(lab, "--tcp", "--object", "tee", "--seed", "3") as served:
        _configure(lab)
        assert labctl("table", "move", "150", "200", "--unlock", lab=lab, timeout=60).returncode == 0
        yield served, lab


@pytest.mark.timeout(300)
def test_table_link_that_stays_down_ends_the_run_with_exit_3_in_bounded_time(served_lab):
    served, lab = served_lab
    run = DroppedRun(served, lab, "table", down_s=None)
    error = run.first("worker_error")
    assert error is not None and "LinkLost" in error["error"]
    detect = run.log_wall("link dropped") - run.dropped["t_wall"]
    typed = error["wall"] - run.dropped["t_wall"]
    print(f"table, no return: detected {detect:.2f} s, LinkLost {typed:.2f} s, exit {run.drop_to_exit_s:.2f} s "
          "after the drop", file=sys.stderr)
    assert run.code == 3, run.stderr
    err = run.stderr.strip().splitlines()
    assert len(err) == 1 and "LinkLost" in err[0] and f"within {RECONNECT_S:g} s" in err[0], err
    assert "robot stopped (confirmed)" in err[0] and "record kept" in err[0] and "Traceback" not in run.stderr
    # bounded: the window (plus one open attempt), then the stop path; never hangs
    assert 0 <= detect < 1.5, detect  # noticed at the table's status rate (5 Hz), not at the program's end
    assert RECONNECT_S <= typed - detect < RECONNECT_S + 1.0, (detect, typed)
    assert RECONNECT_S <= run.drop_to_exit_s < RECONNECT_S + MARGIN_S, run.drop_to_exit_s
    # the record is kept and says why; the robot was stopped and confirmed still
    aborted = run.first("run_aborted")
    assert aborted is not None and aborted["exit_code"] == 3 and "robot" in aborted["devices_stopped"]
    assert "LinkLost" in aborted["reason"]
    assert _robot_still(lab)
    assert run.workers_gone()
    assert served.proc.poll() is None  # the served lab (the "hardware") is still there


def _intercept_with_program_accepted(evs: list[dict]) -> bool:
    return any(e.get("stage") == "intercept" for e in evs) and any(
        e["event"] == "table_progress" and e["acked"] == e["total"] for e in evs)


@pytest.mark.timeout(300)
def test_table_link_back_within_reconnect_s_recovers_then_the_robot_link_that_stays_down_is_exit_3(served_lab):
    """One run, two drops: the table's link comes back after 1 s (the run reads GRBL's state again and
    goes on), then the robot's link drops for good (LinkLost, exit 3, the table stopped)."""
    served, lab = served_lab
    times = {}

    def drop_robot(run: DroppedRun) -> None:
        times["restored"] = run.wait_for_log("link restored", RECONNECT_S + 5.0)["wall"]
        times["robot_dropped"] = _link(served, "robot", up=False)["t_wall"]

    # at the intercept stage, once GRBL has acknowledged the whole program: a drop mid-program is abandoned by
    # design (LinkLost, "the program was abandoned"), which CI once met when the drop came with 4 of 5 lines acked
    run = DroppedRun(served, lab, "table", down_s=1.0, then=drop_robot, at=_intercept_with_program_accepted)
    detect = run.log_wall("link dropped") - run.dropped["t_wall"]
    back = times["restored"] - run.restored["t_wall"]
    robot_exit = run.t_exit - times["robot_dropped"]
    error = run.first("worker_error")
    assert error is not None and "LinkLost" in error["error"] and "robot@" in error["error"], error
    robot_typed = error["wall"] - times["robot_dropped"]
    print(f"table back after 1 s: detected {detect:.2f} s after the drop, restored {back:.2f} s after the "
          f"link came back; robot, no return: LinkLost {robot_typed:.2f} s, exit {robot_exit:.2f} s after the "
          "drop", file=sys.stderr)
    # the table: dropped, noticed, reconnected and its state read again (still running its line)
    assert 0 <= detect < 1.5, detect
    assert back < 2.5 + 1.0, back  # the next reconnect attempt (backoff ≤ 2 s) and the state read
    assert "state Run" in run.first("log", "link restored")["message"]
    assert run.first("worker_error", "grbl@") is None  # the table's drop did not end the run
    # the robot: a typed error in bounded time, the table stopped, the record kept
    assert run.code == 3, run.stderr
    err = run.stderr.strip().splitlines()
    assert len(err) == 1 and "LinkLost" in err[0] and "robot@" in err[0] and "record kept" in err[0], err
    # the server stamps the drop after cutting the link; the worker may see it first (3.999 s seen once under load)
    assert RECONNECT_S - 0.05 <= robot_typed < RECONNECT_S + 1.5, robot_typed
    assert RECONNECT_S <= robot_exit < RECONNECT_S + MARGIN_S, robot_exit
    aborted = run.first("run_aborted")
    assert aborted is not None and aborted["exit_code"] == 3 and "table" in aborted["devices_stopped"]
    assert run.workers_gone()
    assert _table_state(lab)["state"] in ("Idle", "Hold:0")


@long_only
@pytest.mark.timeout(300)
def test_table_link_back_within_reconnect_s_the_run_recovers_and_identifies(served_lab):
    served, lab = served_lab
    run = DroppedRun(served, lab, "table", down_s=1.0)
    back = run.log_wall("link restored") - run.restored["t_wall"]
    print(f"table back after 1 s, alone: restored {back:.2f} s after the link came back", file=sys.stderr)
    assert run.code == 0, run.stderr
    assert json.loads(run.stdout)["identity"] == served.truth["true_identity"]
    assert "state Run" in run.first("log", "link restored")["message"] and run.first("worker_error") is None


@long_only
@pytest.mark.timeout(300)
def test_table_reset_while_away_ends_in_an_alarm_and_nothing_moves(served_lab):
    served, lab = served_lab
    run = DroppedRun(served, lab, "table", down_s=0.5, reset=True)
    error = run.first("worker_error")
    assert error is not None and "GrblAlarm" in error["error"], error
    print(f"table reset while away: GrblAlarm {error['wall'] - run.dropped['t_wall']:.2f} s, exit "
          f"{run.drop_to_exit_s:.2f} s after the drop: {run.stderr.strip()}", file=sys.stderr)
    assert run.code == 3, run.stderr
    assert "GrblAlarm" in run.stderr and "position may be lost" in run.stderr
    assert run.drop_to_exit_s < RECONNECT_S + MARGIN_S
    st = _table_state(lab)
    time.sleep(1.0)
    st2 = _table_state(lab)
    assert st["state"] == st2["state"] == "Alarm" and st["position"] == st2["position"]  # nothing moved
    assert run.workers_gone()


@long_only
@pytest.mark.timeout(300)
def test_robot_link_that_stays_down_ends_the_run_with_exit_3_in_bounded_time(served_lab):
    served, lab = served_lab
    run = DroppedRun(served, lab, "robot", down_s=None)
    print(f"robot, no return: drop→exit {run.drop_to_exit_s:.2f} s", file=sys.stderr)
    assert run.code == 3, run.stderr
    err = run.stderr.strip().splitlines()
    assert len(err) == 1 and "LinkLost" in err[0] and "robot@" in err[0] and "record kept" in err[0], err
    assert run.drop_to_exit_s < RECONNECT_S + MARGIN_S
    aborted = run.first("run_aborted")
    assert aborted is not None and aborted["exit_code"] == 3 and "table" in aborted["devices_stopped"]
    assert run.workers_gone()
    st = _table_state(lab)
    assert st["state"] in ("Idle", "Hold:0")


@long_only
@pytest.mark.timeout(300)
def test_robot_link_back_quickly_recovers_or_ends_on_the_controllers_watchdog(served_lab):
    """A 0.2 s robot drop mid-intercept races the controller's 0.5 s watchdog: back in time, the run
    reads the state again (HELLO, STATUS) and goes on; too late, the arm was stopped and its segments
    are lost (RobotFault, exit 3, nothing resent). Either way within the window; the test says which."""
    served, lab = served_lab
    run = DroppedRun(served, lab, "robot", down_s=0.2, at=lambda evs: any(e["event"] == "segment" for e in evs))
    print(f"robot back after 0.2 s: exit {run.code} {run.drop_to_exit_s:.2f} s after the drop; "
          f"{run.stderr.strip() or json.loads(run.stdout)['identity']}", file=sys.stderr)
    assert run.first("log", "robot@") is not None  # the drop was noticed
    if run.code == 0:
        assert run.first("log", "link restored") is not None
        assert json.loads(run.stdout)["identity"] == served.truth["true_identity"]
    else:
        assert run.code == 3 and "RobotFault" in run.stderr and "nothing was sent again" in run.stderr, run.stderr
        assert run.drop_to_exit_s < RECONNECT_S + MARGIN_S
    assert run.workers_gone()
