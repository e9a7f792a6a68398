"""The declared event schema: every event written in labctl/ is declared, every event a run writes
validates, and a writer or reader that strays from the schema fails in one clear line."""

from __future__ import annotations

import ast
import json
import logging
from pathlib import Path

import numpy as np
import pytest

import labctl
from labctl.records import RunRecord, load_run, read_events
from labctl.records.events import NAMES, SCHEMA, EventSchemaError, compile_type, problem, spec, validate
from labctl.records.record import STRICT_ENV

PACKAGE = Path(labctl.__file__).resolve().parent
# the callables events are written through: RunRecord.event, and the ``log`` a worker is handed
WRITERS = {"event", "log", "live_log"}


def _literal_event_calls():
    """(file, line, name, keyword names, has **splat) of every call ``…event("name", …)`` / ``log("name", …)``."""
    calls = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.Call) or not node.args:
                continue
            f = node.func
            fname = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
            first = node.args[0]
            if fname in WRITERS and isinstance(first, ast.Constant) and isinstance(first.value, str):
                kws = [k.arg for k in node.keywords]
                calls.append((f"{path.relative_to(PACKAGE.parent)}:{node.lineno}", first.value,
                              [k for k in kws if k is not None], None in kws))
    return calls


def test_every_event_name_written_in_the_package_is_declared():
    calls = _literal_event_calls()
    written = {name for _, name, _, _ in calls}
    assert len(written) >= 41, sorted(written)  # a scan that missed the writers would pass vacuously
    undeclared = sorted(f"{where}: {name!r}" for where, name, _, _ in calls if name not in NAMES)
    assert not undeclared, "events written but not declared in labctl/records/events.py: " + ", ".join(undeclared)
    assert not NAMES - written, f"declared but never written: {sorted(NAMES - written)}"


def test_every_literal_field_is_declared_and_every_required_one_written():
    wrong = []
    for where, name, kws, splat in _literal_event_calls():
        es = SCHEMA[name]
        wrong += [f"{where}: {name}.{k} is not declared" for k in kws if k not in es.fields]
        if not splat:  # a **splat may carry the rest; checked at run time
            wrong += [f"{where}: {name} lacks required {k}" for k, f in es.fields.items()
                      if not f.optional and k not in kws]
    assert not wrong, "\n".join(wrong)


def test_schema_is_complete_and_its_types_parse():
    for name, es in SCHEMA.items():
        assert es.name == name and es.doc and "\n" not in es.doc
        for key, f in es.fields.items():
            assert key not in ("event", "wall")
            compile_type(f.type)  # raises on a malformed type


@pytest.mark.parametrize("text,good,bad", [
    ("number", [0, 1.5, -3], [True, "1", None, [1]]),
    ("integer", [0, 7], [1.0, False, None]),
    ("number?", [None, 2.0], ["x"]),
    ("array<number>[3]", [[1, 2, 3.5]], [[1, 2], [1, 2, "3"], (1, 2, 3), None]),
    ("array<number>[4,4]", [np.eye(4).tolist()], [np.eye(3).tolist(), [[0] * 4] * 3]),
    ("array<number?>[*,*]", [[[1, None], [2, 3]], []], [[1, 2]]),
    ("object<number?>", [{}, {"a": 1, "b": None}], [{"a": "x"}, [1]]),
    ("object<array<number?>[5]>", [{"i": [1, 2, 3, 4, 5]}], [{"i": [1, 2, 3]}]),
    ("array<string>", [[], ["a"]], [["a", 1]]),
    ("array<number>[2]?", [None, [1, 2]], [[1]]),
])
def test_field_types(text, good, bad):
    check = compile_type(text)
    assert all(check(v) for v in good)
    assert not any(check(v) for v in bad)


@pytest.mark.parametrize("text", ["foo", "array<number", "number[3]", "object<number>[2]", "array<number>[x]"])
def test_malformed_field_types_are_refused(text):
    with pytest.raises(ValueError, match="field type"):
        compile_type(text)


def test_validate_names_the_event_and_the_field():
    good = {"event": "track", "wall": 1.0, "t": 0.5, "x": 1.0, "y": 2.0, "px": [3.0, 4.0]}
    validate(good)
    for bad, msg in [({**good, "x": "1"}, r"event 'track': field 'x' = '1' is not number"),
                     ({k: v for k, v in good.items() if k != "px"}, r"event 'track': required field 'px' is missing"),
                     ({**good, "z": 1.0}, r"event 'track': field 'z' is not declared"),
                     ({**good, "event": "trak"}, r"event 'trak' is not declared"),
                     ({"wall": 1.0}, r"event None is not declared")]:
        with pytest.raises(EventSchemaError, match=msg):
            validate(bad)
    assert problem(good) is None


def test_readers_cannot_guess_a_name_or_a_field(tmp_path):
    rec = RunRecord.create(tmp_path)
    rec.event("track", t=0.0, x=1.0, y=2.0, px=[3.0, 4.0])
    run = load_run(rec.path)
    track = spec("track")
    assert track.get(run.of("track")[0], "x") == 1.0
    with pytest.raises(EventSchemaError, match="event 'track' has no field 'z'"):
        track.get(run.of("track")[0], "z")
    with pytest.raises(EventSchemaError, match="asked a 'robot' field of a 'track' event"):
        spec("robot").get(run.of("track")[0], "p")
    with pytest.raises(EventSchemaError, match="'trak' is not declared"):
        run.of("trak")
    with pytest.raises(EventSchemaError, match="'trak' is not declared"):
        spec("trak")
    assert spec("track").valid({"event": "track", "x": "oops"}, "x") is None  # wrong type reads as missing


def test_a_strict_record_refuses_an_undeclared_event_and_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv(STRICT_ENV, "1")
    rec = RunRecord.create(tmp_path)
    with pytest.raises(EventSchemaError, match=r"events.jsonl: event 'trak' is not declared"):
        rec.event("trak", t=0.0)
    with pytest.raises(EventSchemaError, match=r"event 'robot': field 'p' = \[1.0, 2.0\] is not array"):
        rec.event("robot", t=0.0, p=np.array([1.0, 2.0]))
    rec.event("robot", t=0.0, p=np.array([1.0, 2.0, 3.0]), planned=np.bool_(True))  # numpy made JSON first
    assert [e["event"] for e in read_events(rec.path)] == ["robot"]
    rec.close()


def test_outside_tests_a_mismatch_is_written_and_warned_of_once(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv(STRICT_ENV, "0")
    rec = RunRecord.create(tmp_path)
    with caplog.at_level(logging.WARNING, logger="labctl.records.record"):
        for i in range(3):
            rec.event("track", t=0.0, x=1.0, y=2.0, px=[1.0, 2.0], extra_field_xyz=1)
            rec.event("track", t=0.0, x=f"{i}", y=2.0, px=[1.0, 2.0])  # a different wrong value each time
    rec.close()
    assert len(read_events(rec.path)) == 6  # a run never loses its record to a writer's mistake
    warned = [r.getMessage() for r in caplog.records if r.name == "labctl.records.record"]
    assert len(warned) == 2, warned
    assert "field 'extra_field_xyz' is not declared" in warned[0] and "field 'x' = '0' is not number" in warned[1]


def test_an_unchecked_record_is_a_free_form_log(tmp_path):
    rec = RunRecord.create(tmp_path, checked=False)
    rec.event("anything", at_all=[1, "b"])
    assert read_events(rec.path)[0]["at_all"] == [1, "b"]
    rec.close()


def _validate_records(root: Path) -> dict[str, int]:
    counts: dict[str, int] = {}
    logs = sorted(root.rglob("events.jsonl"))
    assert logs
    for log in logs:
        for lineno, line in enumerate(log.read_text(encoding="utf-8").splitlines(), start=1):
            e = json.loads(line)
            why = problem(e)
            assert why is None, f"{log}:{lineno}: {why}"
            counts[e["event"]] = counts.get(e["event"], 0) + 1
    return counts


@pytest.mark.timeout(300)
def test_every_event_of_virtual_trials_validates(tmp_path):
    from labctl.experiments.trials import run_one
    from labctl.workspace import sample_lab_path

    root = str(sample_lab_path())
    specs = [{"trajectory": traj, "speed_mm_s": v, "seed": seed}
             for traj in ("line", "zigzag") for v in (8.0, 50.0) for seed in (0,)]
    for i, s in enumerate(specs):
        res = run_one(root, i, s, str(tmp_path))
        assert res["record"]
    counts = _validate_records(tmp_path)
    # the run's main events were there to check
    main = ("truth", "tracking_prior", "stage", "track", "predict", "plan", "segment", "robot", "capture_request",
            "marker_candidates", "marker_pose", "pose_received", "match", "identity", "table_progress")
    assert not [n for n in main if not counts.get(n)], counts
