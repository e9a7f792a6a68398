"""Shared test fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# every event a test writes, here and in the processes it starts, must match labctl.records.events
os.environ["LABCTL_STRICT_EVENTS"] = "1"

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
# Willson's reference set, copied from shared/data/tsai with its licence (BSD-3-Clause via NiftyCal)
TSAI_DATA = Path(__file__).resolve().parent / "data" / "tsai"


@pytest.fixture
def tsai_points():
    import numpy as np

    path = TSAI_DATA / "willson_ncc_cd_300pts.txt"
    return np.loadtxt(path)


@pytest.fixture
def run_with_events():
    """``run(lab, ctx, spec) -> (result, events)``: a virtual run and its record's events, (name, fields) in order."""
    from labctl.records.events import validate
    from labctl.records.record import to_jsonable
    from labctl.runtime.virtual import simulate_run

    def run(lab, ctx, spec):
        events = []

        class Rec:
            def event(self, name, **fields):
                validate(to_jsonable({"event": name, "wall": 0.0, **fields}))  # as RunRecord.event checks it
                events.append((name, fields))

            def save_image(self, name, image):
                pass

        return simulate_run(lab, ctx, spec, Rec()), events

    return run


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem):
    """A test against the GRBL simulator (its ``fw`` fixture) that fails while the simulator itself has gone
    silent runs once more on a new simulator, and says so (a warning naming the silent side). The oracle is
    probed only after a failure: a test that passes, or fails while the simulator still answers, is left as
    it is, so a product fault fails both runs and a flaky oracle never hangs or fails a landing alone."""
    import shutil
    import sys
    import warnings

    mod = sys.modules.get("test_grbl_firmware")
    fw = pyfuncitem.funcargs.get("fw")
    if mod is None or not isinstance(fw, mod.Firmware):
        return None
    args = {name: pyfuncitem.funcargs[name] for name in pyfuncitem._fixtureinfo.argnames}
    try:
        pyfuncitem.obj(**args)
        return True
    except Exception as exc:
        why = fw.silent_side()
        if why is None:
            raise
        first = f"{type(exc).__name__}: {str(exc)[:300]}"
    msg = f"{pyfuncitem.nodeid}: the GRBL simulator went silent ({why}); re-running on a new one after: {first}"
    warnings.warn(msg, stacklevel=1)
    fw.restart(why)
    if "ser2net" in args:
        args["ser2net"].retarget(fw.path)  # its connector names the old simulator's pty
    tmp = args.get("tmp_path")
    if tmp is not None:
        for p in tmp.iterdir():
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    pyfuncitem.obj(**args)
    return True


# The `slow` set: long end-to-end, statistical and repeated-variant tests, left out of a plain `pytest`
# (pyproject's addopts) and run by `.ci/nightly` (`pytest -m ""`). Each keeps a quicker sibling in the
# default run that exercises the same path: the second column names it. Seconds are one clean-clone run on
# 2 cores (docs/notes/run.md, 2026-12-02 (b)). A name here that matches no test stops the session.
SLOW = {
    # end to end on the served lab (the quick run: test_hil two workers over TCP, the sample-lab calibrate)
    "tests/test_rehearsal.py::test_rehearsal_follows_the_printed_next_steps": "131 s",
    "tests/test_hil.py::test_hil_calibrate_both_cameras_hand_eye_and_table": "79 s",
    "tests/test_hil.py::test_hil_run_with_serial_host_link_over_pty_null_modem_and_devices_on_tcp":
        "21 s; run_live 9600 bps",
    "tests/test_hil.py::test_hil_external_motion_no_table_two_labctl_worker_processes": "~9 s",
    "tests/test_hil_reconnect.py::test_table_link_back_within_reconnect_s_recovers_then_the_robot_link_that_stays_down_is_exit_3":
        "14 s; the link that stays down",
    "tests/test_fault_injection_hil.py::test_hil_fault_stops_everything_within_half_a_second[SIGINT-group-cruise]":
        "~12 s; test_fault_injection's twin",
    "tests/test_fault_injection_hil.py::test_hil_fault_stops_everything_within_half_a_second[SIGSTOP-predictor-intercept]":
        "~9 s; test_fault_injection's twin",
    "tests/test_fault_injection_hil.py::test_truth_log_sees_a_table_move_it_was_not_told_about": "~7 s",
    "tests/test_process_group_signals.py::test_a_signal_to_the_process_group_stops_and_confirms_both_devices[15-segment":
        "~8 s; [15-table_program], [1-segment]",
    "tests/test_process_group_signals.py::test_a_signal_to_the_process_group_stops_and_confirms_both_devices[2-segment":
        "~8 s; run_live's Ctrl-C",
    # devices behind real servers (quick: ser2net rfc2217 agreement and stop bytes; the firmware's own checks)
    "tests/test_ser2net_firmware.py::test_table_move_rides_out_a_ser2net_restart_and_lands_at_the_target": "30 s",
    "tests/test_ser2net_firmware.py::test_a_frozen_ser2net_bounds_the_stop_by_the_table_files_stop_total_s": "25 s",
    "tests/test_ser2net_firmware.py::test_every_table_command_agrees_with_the_firmware_through_ser2net[socket]":
        "16 s; [rfc2217]",
    "tests/test_ser2net_firmware.py::test_table_stream_rides_out_a_ser2net_restart_with_the_labs_reconnect_s": "15 s",
    "tests/test_grbl_firmware.py::test_interrupt_stops_the_table[2-stream]": "23-100 s; [1-move], [15-move]",
    "tests/test_grbl_firmware.py::test_work_offsets_and_report_masks_g53_moves": "~14 s",
    "tests/test_grbl_firmware.py::test_a_test_that_meets_a_wedged_simulator_runs_again_on_a_new_one":
        "21 s; the harness",
    "tests/test_grbl_firmware.py::test_a_silent_simulator_names_the_silent_side_and_is_restarted": "14 s; the harness",
    "tests/test_grbl_firmware.py::test_interrupt_stops_the_table[1-move]": "9 s; [15-move], the group SIGHUP",
    "tests/test_grbl_firmware.py::test_critical_alarm_status_never_resets_and_homing_times_out": "14 s; alarm 3",
    "tests/test_grbl_firmware.py::test_a_stop_waits_out_a_silent_link_and_confirms": "10 s; the brief drop",
    "tests/test_robot_arm_served.py::test_each_refusal_kind_gets_its_code_before_moving":
        "15 s; each arm rule's broken controller, the served STATUS joints",
    "tests/test_conformance_robot.py::test_reference_controller_with_the_arm_passes_every_rule_including_the_arms":
        "36 s; every rule without the arm, and each arm rule's broken controller",
    "tests/test_robot_arm_served.py::test_without_a_margin_passing_the_wrist_singularity_needs_a_configuration_change":
        "~5 s; each refusal kind",
    "tests/test_robot_bridge_example.py::test_bridge_with_the_arm_streams_joint_setpoints_of_the_checked_trajectory":
        "23 s; the skeleton's conformance",
    # sweeps, benches and reports (quick: the Dask resume, the process pool, the sweep folder)
    "tests/test_trials_dask.py::test_labctl_trials_on_a_local_cluster_survives_ctrl_c_and_resumes": "20 s",
    "tests/test_trials_sweep.py::test_dask_local_cluster_matches_serial": "~16 s; the Dask resume",
    "tests/test_trials_keep.py::test_keep_failures_keeps_only_the_failed_trials_records": "~12 s",
    "tests/test_trials_view.py::test_trials_view_follows_each_trial": "~13 s",
    "tests/test_live_view.py::test_live_view_in_chromium_follows_the_run_and_stop_stops_it": "~10 s",
    "tests/test_live_startup.py::test_the_startup_bench_reads_each_runs_phases_from_its_record": "18 s",
    "tests/test_bench_trials.py::test_the_breakdown_adds_up_and_unwraps": "~13 s",
    "tests/test_recognition_bench.py::test_new_cad_models_are_recognised_alongside_the_sample_objects": "~10 s",
    "tests/test_export_mcap.py::test_mcap_round_trips_through_the_mcap_reader": "~17 s",
    "tests/test_export_mcap.py::test_run_ids_and_bad_runs_are_one_line_exit_2[replay]": "~7 s; [export]",
    "tests/test_export_mcap.py::test_run_ids_and_bad_runs_are_one_line_exit_2[report]": "~7 s; [export]",
    "tests/test_packaged_lab.py::test_outside_any_workspace_records_go_to_the_user_folder_not_the_source_tree": "~10 s",
    "tests/test_run_early_end.py::test_a_run_whose_fixed_camera_never_sees_a_marker_fails_early_with_the_cause":
        "20 s; the ended table program",
    "tests/test_sim_effects.py::test_realistic_run_falls_back_to_a_suspect_marker_when_the_trusted_one_is_ambiguous":
        "14 s; one found placement",
    # statistics and teaching (quick: their smaller cells)
    "tests/test_library_symmetry.py::test_teach_object_refuses_a_round_part_in_one_line_and_writes_nothing": "~18 s",
    "tests/test_tracking_consistency.py::test_the_curve_covariance_is_the_posteriors_where_the_truth_follows_the_prior":
        "~16 s",
    "tests/test_tracking_family.py::test_family_informed_tracker_meets_the_confusable_cells[circle-4.0-4.0-1.3]":
        "~8 s",
    "tests/test_tracking_corner.py::test_a_corner_the_table_stops_at_settles_under_the_bound[50.0]": "~6 s; [12.0]",
    "tests/test_tracking_corner.py::test_a_corner_the_table_stops_at_settles_under_the_bound[100.0]": "~6 s; [12.0]",
    "tests/test_planning_safety.py::test_no_planned_segment_violates_the_workspace_or_limits": "~9 s; check_segment",
}


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Mark the :data:`SLOW` tests ``slow`` before ``-m`` selects; a stale name is an error, not a test
    quietly moved into the default run."""
    unmatched = set(SLOW)
    for item in items:
        for name in SLOW:
            if item.nodeid == name or item.nodeid.startswith(name):
                item.add_marker(pytest.mark.slow)
                unmatched.discard(name)
    whole_suite = {Path(a).resolve() for a in config.args} <= {REPO / "tests", REPO}
    if unmatched and whole_suite:
        raise pytest.UsageError(f"tests/conftest.py SLOW names no collected test: {sorted(unmatched)[0]}")
