"""Trials sweeps: identical results whatever the executor (serial, process pool, Dask), one folder
per sweep, resume after an interruption."""

from __future__ import annotations

import json
import shutil

import pytest

from labctl.config import load_lab
from labctl.experiments.trials import RESULTS, Sweep, run_sweep
from labctl.workspace import sample_lab_path as _sample_lab_path

N = 2  # trials per speed: enough to interleave on two workers


@pytest.fixture(scope="module")
def sample_lab_path():
    return _sample_lab_path()


def _lab(tmp_path, sample_lab_path):
    root = tmp_path / "lab"
    shutil.copytree(sample_lab_path, root, ignore=shutil.ignore_patterns("runs"))
    return load_lab(root)


def _comparable(summary: dict) -> list[dict]:
    return [{k: v for k, v in t.items() if k != "record"} for t in summary["trials"]]


@pytest.fixture(scope="module")
def serial(tmp_path_factory, sample_lab_path):
    lab = _lab(tmp_path_factory.mktemp("serial"), sample_lab_path)
    return lab, run_sweep(lab, n=N, trajectory="line", speeds=[8.0], objects=None, seed=40, n_jobs=1)


def test_sweep_is_one_folder(serial):
    lab, s = serial
    d = lab.runs_dir / s["sweep"].split("/")[-1]
    assert d.name.startswith("trials-")
    for f in ("spec.json", "summary.json", "report.html", "report.png", RESULTS):
        assert (d / f).is_file(), f
    assert sorted(p.name for p in (d / "trials").iterdir()) == ["00000-seed40", "00001-seed41"]
    assert json.loads((d / "summary.json").read_text())["n"] == N
    assert s["n"] == N and not s["interrupted"]


def test_process_pool_matches_serial(tmp_path, sample_lab_path, serial):
    _, ref = serial
    lab = _lab(tmp_path, sample_lab_path)
    got = run_sweep(lab, n=N, trajectory="line", speeds=[8.0], objects=None, seed=40, n_jobs=2)
    assert _comparable(got) == _comparable(ref)
    assert got["by_speed"] == ref["by_speed"]


def test_dask_local_cluster_matches_serial(tmp_path, sample_lab_path, serial):
    distributed = pytest.importorskip("distributed")
    _, ref = serial
    lab = _lab(tmp_path, sample_lab_path)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        got = run_sweep(lab, n=N, trajectory="line", speeds=[8.0], objects=None, seed=40, record=False,
                        scheduler=cluster.scheduler_address)
    assert _comparable(got) == _comparable(ref)


def test_resume_runs_only_what_is_missing(tmp_path, sample_lab_path, serial):
    _, ref = serial
    lab = _lab(tmp_path, sample_lab_path)
    calls = []

    def interrupt_after_first(res, done, total):
        calls.append(res["index"])
        if done == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt) as info:
        run_sweep(lab, n=N, trajectory="line", speeds=[8.0], objects=None, seed=40, on_result=interrupt_after_first)
    partial = info.value.summary
    assert partial["interrupted"] and partial["n"] == 1 and partial["planned"] == N
    sweep = Sweep.open(partial["sweep"])
    with open(sweep.path / RESULTS, "a") as f:  # a torn line from a crash mid-append is ignored
        f.write('{"index": 1, "trunc')
    resumed = run_sweep(lab, n=0, trajectory="", speeds=[], objects=None, resume=sweep.path,
                        on_result=lambda r, d, t: calls.append(r["index"]))
    assert calls == [0, 1]
    assert _comparable(resumed) == _comparable(ref)
    assert not resumed["interrupted"]
