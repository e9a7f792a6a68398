"""Trials on a Dask LocalCluster (``--scheduler local``): one folder, resumable, results identical to serial.

A sweep of 6 trials on a 2-worker cluster is cut short (in process after 2 results; out of process by
Ctrl-C), then resumed on a fresh cluster: the resumed sweep runs only the missing trials and every
trial's result equals the serial sweep's, field by field."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest

from labctl.config import load_lab
from labctl.experiments.trials import RESULTS, Sweep, run_sweep
from labctl.workspace import sample_lab_path

distributed = pytest.importorskip("distributed")

SWEEP = dict(n=3, trajectory="line", speeds=[4.0, 12.0], objects=None, seed=60, record=False)  # 6 trials


def _lab(tmp_path):
    root = tmp_path / "lab"
    shutil.copytree(sample_lab_path(), root, ignore=shutil.ignore_patterns("runs"))
    return load_lab(root)


def _comparable(trials: list[dict]) -> list[dict]:
    return [{k: v for k, v in t.items() if k != "record"} for t in sorted(trials, key=lambda t: t["index"])]


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    lab = _lab(tmp_path_factory.mktemp("serial"))
    return run_sweep(lab, n_jobs=1, **SWEEP)


@pytest.mark.timeout(300)
def test_an_interrupted_dask_sweep_resumes_to_the_serial_results(tmp_path, serial):
    lab = _lab(tmp_path)
    seen: list[int] = []

    def interrupt_after_two(res, done, total):
        seen.append(res["index"])
        if done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt) as info:
        run_sweep(lab, n_jobs=2, scheduler="local", on_result=interrupt_after_two, **SWEEP)
    partial = info.value.summary
    assert partial["interrupted"] and partial["n"] == 2 and partial["planned"] == 6
    sweep = Sweep.open(partial["sweep"])
    assert sorted(sweep.results()) == sorted(seen)

    resumed_indices: list[int] = []
    resumed = run_sweep(lab, n=0, trajectory="", speeds=[], objects=None, resume=sweep.path, n_jobs=2,
                        scheduler="local", on_result=lambda r, d, t: resumed_indices.append(r["index"]))
    assert sorted(resumed_indices) == sorted(set(range(6)) - set(seen))  # done trials are skipped
    assert not resumed["interrupted"] and resumed["n"] == 6
    assert _comparable(resumed["trials"]) == _comparable(serial["trials"])
    assert resumed["by_speed"] == serial["by_speed"]
    lines = (sweep.path / RESULTS).read_text().splitlines()
    assert sorted(json.loads(x)["index"] for x in lines) == list(range(6))  # one line per trial, none twice


def _children(pid: int) -> set[int]:
    import psutil

    try:
        return {p.pid for p in psutil.Process(pid).children(recursive=True)}
    except psutil.NoSuchProcess:
        return set()


@pytest.mark.timeout(300)
def test_labctl_trials_on_a_local_cluster_survives_ctrl_c_and_resumes(tmp_path, serial):
    import psutil

    lab = _lab(tmp_path)
    cmd = [sys.executable, "-m", "labctl", "--lab", str(lab.root), "--json", "trials", "--n", "3",
           "--speed", "4,12", "--seed", "60", "--no-record", "--jobs", "2", "--scheduler", "local"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=os.environ.copy())
    workers: set[int] = set()
    try:
        deadline = time.monotonic() + 200
        results = None
        while time.monotonic() < deadline and proc.poll() is None:
            workers |= _children(proc.pid)
            found = list(lab.runs_dir.glob("trials-*/" + RESULTS)) if lab.runs_dir.exists() else []
            if found and len(found[0].read_text().splitlines()) >= 2:
                results = found[0]
                break
            time.sleep(0.2)
        assert results is not None, proc.stderr.read().decode() if proc.poll() is not None else "no results"
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err.decode()
    # nothing keeps running once labctl has stopped: the cluster's worker processes are gone too
    for pid in workers:
        try:
            psutil.Process(pid).wait(timeout=20)
        except psutil.NoSuchProcess:
            pass
    assert not [p for p in workers if psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE]
    done_before = set(Sweep.open(results.parent).results())
    assert 2 <= len(done_before) < 6

    out = subprocess.run([sys.executable, "-m", "labctl", "--lab", str(lab.root), "--json", "trials", "--resume",
                          str(results.parent), "--jobs", "2", "--scheduler", "local"],
                         capture_output=True, timeout=200, env=os.environ.copy())
    assert out.returncode == 0, out.stderr.decode()
    summary = json.loads(out.stdout)
    assert summary["n"] == 6 and not summary["interrupted"]
    assert _comparable(summary["trials"]) == _comparable(serial["trials"])
