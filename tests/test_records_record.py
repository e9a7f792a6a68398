"""Run records: unique sortable folders, append-only fsynced JSON lines from several processes."""

from __future__ import annotations

import json
import multiprocessing
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from labctl.records import RecordError, RunRecord, load_run, read_events, to_jsonable


def test_create_names_are_unique_and_sortable_within_one_second(tmp_path):
    now = datetime(2025, 3, 14, 10, 15, 2, tzinfo=UTC)
    recs = [RunRecord.create(tmp_path, {"trajectory": "line"}, now=now) for _ in range(12)]
    names = [r.path.name for r in recs]
    assert names[0] == "20250314T101502Z"
    assert len(set(names)) == 12
    assert sorted(names) == names  # creation order == sort order
    later = RunRecord.create(tmp_path, now=datetime(2025, 3, 14, 10, 15, 3, tzinfo=UTC))
    assert sorted(names + [later.path.name])[-1] == later.path.name
    meta = json.loads((recs[3].path / "meta.json").read_text())
    assert meta["trajectory"] == "line" and meta["run_id"] == names[3]


def test_events_are_json_lines_with_numpy_values(tmp_path):
    rec = RunRecord.create(tmp_path, {"seed": np.int64(3)}, checked=False)  # free-form: "odd" is no declared event
    rec.event("worker_started", role="predictor", pid=123)
    rec.event("track", t=np.float32(0.5), x=np.float64(10.25), y=-3)
    rec.event("robot", t=1.0, p=np.array([1.0, 2.0, 3.0]))
    rec.event("odd", bad=float("nan"), path=Path("/x"), arr=np.eye(2, dtype=np.float32), flag=np.bool_(True))
    lines = rec.events_path.read_text().splitlines()
    assert len(lines) == 4
    objs = [json.loads(line) for line in lines]  # strict JSON: no NaN tokens
    assert objs[0] == {"event": "worker_started", "wall": objs[0]["wall"], "role": "predictor", "pid": 123}
    assert objs[1]["x"] == 10.25 and objs[1]["t"] == 0.5
    assert objs[2]["p"] == [1.0, 2.0, 3.0]
    assert objs[3]["bad"] is None and objs[3]["path"] == "/x" and objs[3]["arr"] == [[1, 0], [0, 1]]
    assert objs[3]["flag"] is True
    assert read_events(rec.path) == objs
    rec.close()


def test_event_argument_errors(tmp_path):
    rec = RunRecord.create(tmp_path)
    with pytest.raises(RecordError):
        rec.event("")
    with pytest.raises(RecordError):
        rec.event("x", event="y")
    with pytest.raises(RecordError):
        RunRecord.open(tmp_path / "missing")


def _append_many(run_dir: str, who: str, n: int) -> None:
    rec = RunRecord.open(run_dir, checked=False)
    blob = who * 3000  # long lines make any interleaving visible
    for i in range(n):
        rec.event("tick", who=who, i=i, blob=blob)
    rec.close()


def test_two_processes_append_without_interleaving(tmp_path):
    rec = RunRecord.create(tmp_path)
    ctx = multiprocessing.get_context("spawn")
    n = 150
    procs = [ctx.Process(target=_append_many, args=(str(rec.path), who, n)) for who in ("a", "b")]
    for p in procs:
        p.start()
    _append_many(str(rec.path), "c", n)  # and the parent at the same time
    for p in procs:
        p.join(timeout=60)
        assert p.exitcode == 0
    raw = rec.events_path.read_bytes().split(b"\n")
    assert raw[-1] == b""
    objs = [json.loads(line) for line in raw[:-1]]  # every line is one valid JSON object
    assert len(objs) == 3 * n
    for who in "abc":
        mine = [o["i"] for o in objs if o["who"] == who]
        assert mine == list(range(n))  # each writer's lines whole and in its order
        assert all(o["blob"] == who * 3000 for o in objs if o["who"] == who)


def test_record_survives_pickling_into_a_child(tmp_path):
    rec = RunRecord.create(tmp_path, checked=False)  # the child's copy stays unchecked too
    rec.event("first")
    ctx = multiprocessing.get_context("spawn")
    p = ctx.Process(target=_child_event, args=(rec,))
    p.start()
    p.join(timeout=60)
    assert p.exitcode == 0
    rec.event("last")
    assert [e["event"] for e in read_events(rec.path)] == ["first", "from_child", "last"]


def _child_event(rec):
    rec.event("from_child", pid=1)


def test_save_image_and_finish_are_atomic_files(tmp_path):
    import cv2

    rec = RunRecord.create(tmp_path)
    img = np.zeros((40, 60, 3), np.uint8)
    img[10:20, 5:25] = (0, 0, 255)
    p = rec.save_image("initial1", img)
    assert p.name == "initial1.png"
    assert np.array_equal(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), img)
    mask = np.zeros((40, 60), bool)
    mask[5:9, 5:9] = True
    m = cv2.imread(str(rec.save_image("silhouette_0.png", mask)), cv2.IMREAD_UNCHANGED)
    assert m.dtype == np.uint8 and m[6, 6] == 255 and m[0, 0] == 0
    for bad_name in ("../escape", "a/b", ""):
        with pytest.raises(RecordError):
            rec.save_image(bad_name, img)
    with pytest.raises(RecordError):
        rec.save_image("f", img.astype(np.float32))
    with pytest.raises(RecordError):
        rec.save_image("f", np.zeros((3, 3, 2), np.uint8))
    rec.finish({"identity": "cube", "time_to_identity_s": np.float64(7.5), "views": np.int32(1)})
    assert json.loads((rec.path / "result.json").read_text()) == {"identity": "cube", "time_to_identity_s": 7.5,
                                                                  "views": 1}
    assert not [q for q in rec.path.iterdir() if q.name.startswith(".")]  # no temp files left behind


def test_image_writer_writes_what_save_image_writes_in_order_and_waits_on_close(tmp_path):
    # the live recognizer's images go to disk in a thread: the same files, byte for byte, as the direct
    # write (decoded by OpenCV's reader, not the writer), each from the array as it was when queued
    import cv2

    rng = np.random.default_rng(5)
    direct, threaded = RunRecord.create(tmp_path / "a"), RunRecord.create(tmp_path / "b")
    writer = threaded.image_writer()
    images = {f"view_{k}": rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for k in range(1, 6)}
    images["silhouette_1"] = rng.random((48, 64)) > 0.5
    for name, img in images.items():
        direct.save_image(name, img)
        writer.save(name, img)
        if img.dtype == np.uint8:
            img[:] = 0  # the caller reuses its array: the queued copy is what was given
    writer.close()
    assert writer.written == len(images) and writer.error is None
    for name in images:
        a, b = (direct.path / f"{name}.png").read_bytes(), (threaded.path / f"{name}.png").read_bytes()
        assert a == b
        assert cv2.imread(str(threaded.path / f"{name}.png"), cv2.IMREAD_UNCHANGED).any()
    assert not [q for q in threaded.path.iterdir() if q.name.startswith(".")]
    with pytest.raises(RecordError):  # closed: nothing is queued that no thread will write
        writer.save("late", images["view_1"])


def test_image_writer_refuses_bad_images_at_once_and_reports_a_lost_write_on_close(tmp_path):
    rec = RunRecord.create(tmp_path)
    writer = rec.image_writer()
    for bad_name in ("../escape", "a/b", ""):
        with pytest.raises(RecordError):
            writer.save(bad_name, np.zeros((4, 4), np.uint8))
    with pytest.raises(RecordError):
        writer.save("f", np.zeros((4, 4), np.float32))
    (rec.path / "taken.png").mkdir()  # a directory where the image goes: its write fails in the thread
    writer.save("taken", np.zeros((4, 4), np.uint8))
    writer.save("fine", np.zeros((4, 4), np.uint8))
    with pytest.raises(RecordError, match="taken.png"):
        writer.close()
    assert (rec.path / "fine.png").is_file()  # one failed write does not stop the others


def test_read_events_skips_a_torn_last_line_unless_strict(tmp_path):
    rec = RunRecord.create(tmp_path, checked=False)
    rec.event("a")
    with open(rec.events_path, "ab") as fh:
        fh.write(b'{"event": "b", "x": 1')  # a crash mid-line
    assert [e["event"] for e in read_events(rec.path)] == ["a"]
    with pytest.raises(RecordError, match=":2:"):
        read_events(rec.path, strict=True)


def test_load_run_of_finished_and_unfinished_runs(tmp_path):
    rec = RunRecord.create(tmp_path, {"object": "cube"})
    rec.event("track", t=0.0, x=1.0, y=2.0, px=[3.0, 4.0])
    rec.save_image("initial1", np.zeros((8, 8), np.uint8))
    run = load_run(rec.path)
    assert not run.finished and run.result is None
    assert run.meta["object"] == "cube" and set(run.images) == {"initial1"}
    assert run.of("track")[0]["x"] == 1.0
    rec.finish({"identity": "cube"})
    assert load_run(rec.path).finished
    with pytest.raises(RecordError):
        load_run(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordError):
        load_run(tmp_path / "empty")


def test_to_jsonable_handles_nested_numpy():
    from dataclasses import dataclass

    @dataclass
    class P:
        a: np.ndarray

    out = to_jsonable({1: (np.float32(1.5), {np.str_("k"): [np.inf]}), "p": P(np.arange(3))})
    assert out == {"1": [1.5, {"k": [None]}], "p": {"a": [0, 1, 2]}}
    json.dumps(out, allow_nan=False)
