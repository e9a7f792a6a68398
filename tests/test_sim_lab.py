"""The one simulated-lab builder (``labctl.sim.lab``), its truth logger, and the trajectory settings."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from labctl.config import load_lab
from labctl.config.lab import TRAJECTORIES, FamilyPrior, TrajectoryStarts
from labctl.sim.clock import VirtualClock
from labctl.sim.lab import Scene, SimLab, TruthFile, TruthLogger
from labctl.workspace import init_workspace, sample_lab_path


@pytest.fixture(scope="module")
def lab():
    return load_lab(sample_lab_path())


def test_trajectory_names_are_one_list_and_every_setting_has_each():
    assert [f.name for f in dataclasses.fields(TrajectoryStarts)] == list(TRAJECTORIES)
    assert [f.name for f in dataclasses.fields(FamilyPrior)] == list(TRAJECTORIES)
    starts = TrajectoryStarts()
    assert starts.get("zigzag") == (150.0, 170.0) and starts.get("external") is None
    assert starts.get("/some/file.gcode") is None


def test_trajectory_starts_are_read_from_lab_yaml(tmp_path):
    import yaml

    from labctl.runtime.simlab import trajectory_program

    root = init_workspace(tmp_path / "lab")
    cfg = yaml.safe_load((root / "lab.yaml").read_text())
    cfg["run"]["trajectory_start_mm"] = {"arc": [250.0, 120.0]}  # only arc set: the others keep their defaults
    (root / "lab.yaml").write_text(yaml.safe_dump(cfg))
    lab = load_lab(root)
    assert lab.config.run.trajectory_start_mm.arc == (250.0, 120.0)
    start, lines = trajectory_program("arc", 8.0, lab)
    assert start == (250.0, 120.0) and "G0 X250 Y120" in lines
    assert trajectory_program("line", 8.0, lab)[0] == (150.0, 200.0)  # the others keep their defaults
    assert trajectory_program("external", 8.0, lab) == ((150.0, 200.0), [])


def test_the_live_run_goes_to_the_start_it_is_given():
    from labctl.drivers.interfaces import TableStatus
    from labctl.runtime.live import _to_start

    class Table:
        streamed: list = []

        def status(self):
            return TableStatus("Idle", (10.0, 20.0, 0.0))

        def stream(self, lines):
            self.streamed.append(lines)

        def wait_idle(self, timeout_s):
            pass

    events = []
    t = Table()
    _to_start(t, (250.0, 120.0), lambda name, **f: events.append((name, f)), lambda: 1.0)
    assert t.streamed == [["G21G90", "G0X250.000Y120.000"]] and events[0][1]["start"] == [250.0, 120.0]
    _to_start(t, None, lambda *a, **k: events.append(a), lambda: 1.0)  # a G-code file: where it starts itself
    assert len(t.streamed) == 1


def test_one_camera_alone_renders_what_the_whole_lab_renders(lab):
    from labctl.runtime.devices import open_device

    for role in ("fixed", "mobile"):
        whole = SimLab.build(lab, VirtualClock(0.0), scene=Scene.test_block(lab, 0)).cameras[role]
        alone = open_device(f"{role}_camera", lab)
        assert alone.world.table_position is not whole.world.table_position  # no emulators behind it
        whole.open(), alone.open()
        for _ in range(2):
            a, b = whole.grab(), alone.grab()
            assert (a.t, a.seq) == (b.t, b.seq) and np.array_equal(a.image, b.image)


def test_a_single_device_is_built_alone(lab):
    sim = SimLab.build(lab, VirtualClock(), devices=("table",), table_start_mm=(0.0, 0.0))
    assert sim.robot_emu is None and sim.robot is None and sim.world is None and not sim.cameras
    assert sim.table.link.name.endswith("sim://table")
    with pytest.raises(ValueError):
        SimLab.build(lab, VirtualClock(), devices=("arm",))


class _Lab:
    """Scripted device states, as SimLab.device_state / robot_stop give them."""

    def __init__(self, states):
        self.states = list(states)
        self.ramp = None

    def device_state(self):
        st = self.states.pop(0)
        self.ramp = st.pop("ramp", self.ramp)
        return st

    def robot_stop(self):
        return self.ramp


def _states():
    still = {"robot_moving": False, "table_moving": False, "table_state": "Idle"}
    moving = {**still, "robot_moving": True}
    return [{"t": 0.0, **moving}, {"t": 0.01, **moving, "ramp": [0.01, 0.2]}, {"t": 0.02, **moving},
            {"t": 0.25, **still}, {"t": 0.26, **still}]


def test_truth_logger_for_the_record_holds_changes_of_motion_only():
    lines = []
    logger = TruthLogger(_Lab(_states()), lines.append, first_line=False, ramp_is_change=False)
    states = [logger.sample() for _ in range(5)]
    assert [(x["t"], x["robot_moving"], x["robot_stop"]) for x in lines] == [(0.25, False, [0.01, 0.2])]
    assert states[3]["robot_still_since"] == 0.25 and states[2]["robot_still_since"] is None
    assert "robot_stop" not in states[0] and states[0]["table_still_since"] == 0.0


def test_truth_logger_for_a_file_writes_the_first_sample_and_each_new_ramp(tmp_path):
    sink = TruthFile(tmp_path / "truth.jsonl", origin=100.0)
    logger = TruthLogger(_Lab(_states()), sink.write)
    for _ in range(5):
        logger.sample()
    sink.close(logger)
    rows = [json.loads(x) for x in (tmp_path / "truth.jsonl").read_text().splitlines()]
    assert [r.get("mono") for r in rows[:3]] == [100.0, 100.01, 100.25]
    assert rows[1]["robot_stop"] == [100.01, 100.2] and rows[1]["robot_moving"] is True
    assert rows[-1]["end"] is True and rows[-1]["samples"] == 5 and rows[-1]["max_gap_s"] == pytest.approx(0.23)
