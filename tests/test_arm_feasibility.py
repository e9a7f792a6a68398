"""Run records against an arm: the controller's trajectory recovered from a record, and ``labctl robot feasibility``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from fakes import run_cli

from labctl.config import load_lab
from labctl.config.arm import load_arm
from labctl.experiments.arm_feasibility import Trajectory, check_trial, read_events, recover_trajectory
from labctl.geometry import make_T, rot_x
from labctl.planning.arm import ArmModel

pytestmark = pytest.mark.timeout(300)

REPO = Path(__file__).resolve().parents[1]
UR10E = REPO / "drivers" / "arms" / "ur10e.yaml"


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """A lab and one recorded virtual trial (a line at 8 mm/s)."""
    import subprocess
    import sys

    lab = tmp_path_factory.mktemp("armlab") / "lab"
    env_cmd = [sys.executable, "-m", "labctl"]
    subprocess.run([*env_cmd, "init", str(lab)], check=True, capture_output=True, timeout=120)
    subprocess.run([*env_cmd, "--lab", str(lab), "trials", "--n", "1", "--trajectory", "line", "--speed", "8",
                    "-j", "1"], check=True, capture_output=True, timeout=240)
    (trials,) = list((lab / "runs").glob("trials-*"))
    return lab, trials


def test_recovered_trajectory_is_the_controllers(sweep):
    lab_root, trials = sweep
    lab = load_lab(lab_root)
    (rec,) = list((trials / "trials").iterdir())
    events = read_events(rec / "events.jsonl")
    traj = recover_trajectory(events, lab)
    segs = [e for e in events if e["event"] == "segment"]
    assert len(traj.profiles) == len(segs) >= 3
    assert traj.max_end_error_s <= 1.5e-4  # every segment ends when the run's controller said it would
    # the host's planned positions (its own copy of the controller's plan, re-timed by its latency estimate,
    # so a few ms off on a re-plan) lie close to the recovered path
    planned = [e for e in events if e["event"] == "robot" and e.get("planned") and traj.t[0] <= e["t"] <= traj.t[-1]]
    assert planned
    for e in planned:
        p = [np.interp(e["t"], traj.t, traj.poses[:, k, 3]) for k in range(3)]
        np.testing.assert_allclose(p, e["p"], atol=5.0)
    # at rest after each arrival (the robot's own reports, not the plan's), the flange is where the replay is
    rests = [e for e in events if e["event"] == "robot" and not e.get("planned") and e["t"] <= traj.t[-1]]
    assert rests
    for e in rests:
        p = [np.interp(e["t"], traj.t, traj.poses[:, k, 3]) for k in range(3)]
        np.testing.assert_allclose(p, e["p"], atol=0.01)
    # the run ends at rest at its last commanded target
    np.testing.assert_allclose(traj.poses[-1][:3, 3], segs[-1]["p"], atol=1e-6)
    np.testing.assert_allclose(traj.targets[-1][:3, 3], segs[-1]["p"])
    assert traj.poses.shape == (len(traj.t), 4, 4)
    assert np.all(np.diff(traj.t) > 0)


def test_a_path_over_the_base_axis_fails_at_the_shoulder_singularity():
    arm = ArmModel.from_config(load_arm(UR10E))
    down = rot_x(math.pi)
    xs = np.linspace(-500.0, 500.0, 501)
    poses = np.array([make_T(down, [x, 0.0, 600.0]) for x in xs])
    t = np.arange(len(xs)) * 0.004
    traj = Trajectory(t, poses, ["standard"] * len(xs), [poses[0], poses[-1]])
    q0 = arm.ik_solutions(poses[0])[0]
    res = check_trial(arm, traj, q0, "over-the-axis", {})
    assert res.n_reachable == 2  # both ends reachable: only the path between them is not
    assert not res.followed
    assert "shoulder singularity" in res.reason and res.failed_kind == "standard"
    # the same line beside the axis is followed
    beside = np.array([make_T(down, [x, -450.0, 600.0]) for x in xs])
    traj2 = Trajectory(t, beside, ["standard"] * len(xs), [beside[0]])
    res2 = check_trial(arm, traj2, arm.ik_solutions(beside[0])[0], "beside", {})
    assert res2.followed, res2.reason
    assert 0.0 < max(res2.speed_ratio)


def test_feasibility_command(sweep, capsys):
    lab_root, trials = sweep
    code, out, err = run_cli(capsys, "--lab", str(lab_root), "--json", "robot", "feasibility", str(trials),
                             "--arm", str(UR10E), "--base", "0,-600,350")
    assert code == 0, err
    res = json.loads(out)
    assert res["trials"] == 1 and res["targets"] >= 4
    assert res["targets_reachable_pct"] == 100.0
    assert res["followed_pct"] == 100.0 and res["within_speeds_pct"] == 100.0
    assert res["base_xyz_mm"] == [0.0, -600.0, 350.0]
    assert len(res["per_trial"]) == 1 and 0 < max(res["per_trial"][0]["speed_ratio"]) <= 1.0


def test_feasibility_defaults_to_the_labs_mount(sweep, capsys):
    """Without ``--base`` the arm stands where the lab's robot.yaml mounts it (the runs were flown there),
    not at the arm file's own default."""
    from labctl.config import load_lab

    lab_root, trials = sweep
    mount = load_lab(lab_root).robot.arm_base_xyz_mm
    assert mount is not None
    code, out, err = run_cli(capsys, "--lab", str(lab_root), "--json", "robot", "feasibility", str(trials),
                             "--arm", str(UR10E))
    assert code == 0, err
    res = json.loads(out)
    assert res["base_xyz_mm"] == [float(v) for v in mount]
    assert res["followed_pct"] == 100.0 and res["within_speeds_pct"] == 100.0


@pytest.mark.parametrize("args, message", [
    (["--base", "0,1"], "--base: expected three numbers"),
    (["--base", "0,a,1"], "--base: expected three numbers"),
    (["--base-rpy", "0,0,inf"], "--base-rpy: expected three numbers"),
])
def test_feasibility_bad_options_are_one_line(sweep, capsys, args, message):
    lab_root, trials = sweep
    code, out, err = run_cli(capsys, "--lab", str(lab_root), "robot", "feasibility", str(trials), "--arm", str(UR10E),
                             *args)
    assert code == 2
    assert err.strip().count("\n") == 0 and message in err


def test_feasibility_bad_inputs_are_one_line(sweep, capsys, tmp_path):
    lab_root, trials = sweep
    code, _, err = run_cli(capsys, "--lab", str(lab_root), "robot", "feasibility", str(tmp_path), "--arm", str(UR10E))
    assert code == 2 and "no run records" in err and err.strip().count("\n") == 0
    code, _, err = run_cli(capsys, "--lab", str(lab_root), "robot", "feasibility", str(trials), "--arm",
                           str(tmp_path / "none.yaml"))
    assert code == 2 and "file not found" in err and err.strip().count("\n") == 0


def test_mount_command_ranks_bases_by_the_views_they_reach(sweep, capsys):
    lab_root, trials = sweep
    code, out, err = run_cli(capsys, "--lab", str(lab_root), "--json", "robot", "mount", "--arm", str(UR10E),
                             "--runs", str(trials), "--base", "0,0,0", "--base", "600,-200,350",
                             "--base", "3000,0,0")
    assert code == 0, err
    res = json.loads(out)
    assert res["views"]["home"] == 1 and res["views"]["calibration"] >= 10 and res["views"]["runs"] >= 3
    assert res["bases"] == 3
    first, second, third = res["ranked"]
    assert first["base_xyz_mm"] == [600.0, -200.0, 350.0] and first["all"]
    assert res["reach_all"] == [[600.0, -200.0, 350.0]]
    # labctl's base frame misses calibration stations (one on the far side of the table, high ones)
    assert second["base_xyz_mm"] == [0.0, 0.0, 0.0] and 0 < second["missed"] < res["views"]["calibration"]
    assert third["reached"] == {"home": 0, "calibration": 0, "runs": 0}  # 3 m away


def test_mount_command_bad_base_is_one_line(sweep, capsys):
    lab_root, _ = sweep
    code, _, err = run_cli(capsys, "--lab", str(lab_root), "robot", "mount", "--arm", str(UR10E), "--base", "1,2")
    assert code == 2 and "--base: expected three numbers" in err and err.strip().count("\n") == 0


def test_mount_command_with_a_bad_target_file_is_one_line(sweep, capsys, tmp_path):
    import shutil

    lab_root, _ = sweep
    lab = tmp_path / "lab"
    shutil.copytree(lab_root, lab, ignore=shutil.ignore_patterns("runs"))
    (lab / "calibration" / "target.yaml").write_text("kind: pyramid\n")
    code, _, err = run_cli(capsys, "--lab", str(lab), "robot", "mount", "--arm", str(UR10E), "--base", "0,0,0")
    assert code == 2 and "target.yaml" in err and err.strip().count("\n") == 0
