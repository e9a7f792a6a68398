"""The declared schema of a run record's events (``events.jsonl``), after Bluesky's event descriptors.

Every line of the log is ``{"event": name, "wall": <unix time>, **fields}``. :data:`SCHEMA` names
each event, its fields with their JSON types (and which may be absent), and says in one line what
the event means. Writers are checked by :meth:`labctl.records.RunRecord.event` (after numpy values
were made JSON, so the types here are JSON's); readers go through :func:`spec` and
:meth:`EventSpec.get`, which refuse a name or a field the schema does not declare.

Field types, a small grammar (``T`` is any type):

* ``number`` (an int or a float, never a bool), ``integer``, ``string``, ``boolean``, ``any``;
* ``object`` (any JSON object), ``object<T>`` (an object whose values are all ``T``);
* ``array<T>`` (any length), ``array<T>[3]``, ``array<T>[4,4]``, ``array<T>[*,2]`` (``*``: any length);
* a trailing ``?`` admits ``null`` (a NaN or an infinity is written as ``null``, and some values are None).

Times ``t`` are seconds on the run's clock (the virtual clock, or since the live run's ``origin``);
positions are millimetres in the world frame W; angles radians unless the name ends in ``_deg``.

To add an event: add an :class:`EventSpec` to ``_EVENTS`` below (name, one-line description, its
fields), write it, and run ``tests/test_records_events.py``, which checks that every event name
written as a literal in ``labctl/`` is declared and that every event of a few simulated runs
validates.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ..errors import LabctlError

__all__ = ["EventSchemaError", "Field", "EventSpec", "SCHEMA", "NAMES", "RESERVED", "spec", "problem", "validate",
           "compile_type", "check_type"]

#: fields every line carries, written by the record itself
RESERVED = ("event", "wall")


class EventSchemaError(LabctlError):
    """An event, or a reader's request, does not match the declared event schema."""


# ---- field types ------------------------------------------------------------------------------------

Check = Callable[[Any], bool]
_TYPE = re.compile(r"^(?P<base>[a-z]+)(?:<(?P<inner>.+)>)?(?:\[(?P<shape>[0-9*,]+)\])?(?P<null>\?)?$")


def _is_number(v: Any) -> bool:
    return type(v) is float or type(v) is int or (isinstance(v, int | float) and not isinstance(v, bool))


def _is_integer(v: Any) -> bool:
    return type(v) is int or (isinstance(v, int) and not isinstance(v, bool))


_LEAVES: dict[str, Check] = {
    "number": _is_number,
    "integer": _is_integer,
    "string": lambda v: isinstance(v, str),
    "boolean": lambda v: isinstance(v, bool),
    "any": lambda v: True,
}


def _split_top(text: str) -> tuple[str, str] | None:
    """``"array<number>[3]?"`` → the part inside the outermost ``<>`` and what follows it."""
    depth = 0
    for i, ch in enumerate(text):
        if ch == "<":
            depth += 1
        elif ch == ">":
            depth -= 1
            if depth == 0:
                return text[text.index("<") + 1: i], text[i + 1:]
    return None


def compile_type(text: str) -> Check:
    """A predicate for the JSON value of one field type (see the module docstring); ValueError if malformed."""
    text = text.strip()
    nullable = text.endswith("?")
    core = text[:-1] if nullable else text
    inner = rest = None
    if "<" in core:
        split = _split_top(core)
        if split is None:
            raise ValueError(f"unbalanced <> in field type {text!r}")
        inner, rest = split
        base = core[: core.index("<")]
    else:
        base, _, rest = core.partition("[")
        rest = f"[{rest}" if rest else ""
    shape: tuple[int | None, ...] | None = None
    if rest:
        if not (rest.startswith("[") and rest.endswith("]")) or not re.fullmatch(r"[0-9*,]+", rest[1:-1]):
            raise ValueError(f"bad shape in field type {text!r}")
        shape = tuple(None if d == "*" else int(d) for d in rest[1:-1].split(","))
    if base in _LEAVES:
        if inner is not None or shape is not None:
            raise ValueError(f"{base} takes no <> or shape in field type {text!r}")
        check = _LEAVES[base]
    elif base == "object":
        if shape is not None:
            raise ValueError(f"object takes no shape in field type {text!r}")
        values = None if inner is None else compile_type(inner)
        check = _object_check(values)
    elif base == "array":
        check = _array_check(compile_type(inner or "any"), shape or (None,))
    else:
        raise ValueError(f"unknown field type {text!r}")
    if nullable:
        inner_check = check
        return lambda v: v is None or inner_check(v)
    return check


def _object_check(values: Check | None) -> Check:
    if values is None:
        return lambda v: isinstance(v, dict)
    return lambda v: isinstance(v, dict) and all(values(x) for x in v.values())


def _array_check(item: Check, shape: tuple[int | None, ...]) -> Check:
    n, rest = shape[0], shape[1:]
    inner = item if not rest else _array_check(item, rest)

    def check(v: Any) -> bool:
        return isinstance(v, list) and (n is None or len(v) == n) and all(inner(x) for x in v)

    return check


def check_type(text: str, value: Any) -> bool:
    """Whether the JSON ``value`` has field type ``text``."""
    return compile_type(text)(value)


# ---- the schema ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Field:
    """One field of an event: its JSON type (the grammar above), units or meaning, and whether it may be absent."""

    type: str
    doc: str = ""
    optional: bool = False
    check: Check = field(init=False, repr=False, compare=False, default=_LEAVES["any"])

    def __post_init__(self) -> None:
        object.__setattr__(self, "check", compile_type(self.type))


def _f(type_: str, doc: str = "") -> Field:
    return Field(type_, doc)


def _opt(type_: str, doc: str = "") -> Field:  # may be absent from the line
    return Field(type_, doc, optional=True)


@dataclass(frozen=True)
class EventSpec:
    """One declared event: name, a one-line description, its fields (``wall`` and ``event`` are implicit)."""

    name: str
    doc: str
    fields: Mapping[str, Field]

    def __post_init__(self) -> None:
        clash = set(self.fields) & set(RESERVED)
        if clash:
            raise ValueError(f"event {self.name!r} declares reserved field(s) {sorted(clash)}")
        object.__setattr__(self, "_required", frozenset(k for k, f in self.fields.items() if not f.optional))

    def problem(self, event: Mapping[str, Any]) -> str | None:
        """What is wrong with ``event`` (one line naming the event and the field), or None."""
        fields = self.fields
        for key, value in event.items():
            f = fields.get(key)
            if f is None:
                if key not in RESERVED:
                    return f"event {self.name!r}: field {key!r} is not declared"
            elif not f.check(value):
                return f"event {self.name!r}: field {key!r} = {_short(value)} is not {f.type}"
        missing = self._required.difference(event)  # type: ignore[attr-defined]
        if missing:
            return f"event {self.name!r}: required field {sorted(missing)[0]!r} is missing"
        return None

    def declared(self, key: str) -> Field:
        """The declared field ``key``; EventSchemaError if this event has none (a reader's mistake)."""
        try:
            return self.fields[key]
        except KeyError:
            raise EventSchemaError(f"event {self.name!r} has no field {key!r} "
                                   f"(declared: {', '.join(self.fields)})") from None

    def get(self, event: Mapping[str, Any], key: str, default: Any = None) -> Any:
        """``event[key]`` (``default`` if absent) for a declared field; EventSchemaError for an undeclared
        one, or when ``event`` is not a ``self.name`` event."""
        self.declared(key)
        if event.get("event") != self.name:
            raise EventSchemaError(f"asked a {self.name!r} field of a {event.get('event')!r} event")
        return event.get(key, default)

    def valid(self, event: Mapping[str, Any], key: str) -> Any:
        """``event[key]`` if it is present and of its declared type, else None (a record written by an
        older or broken writer reads as the field missing, never as a crash)."""
        value = self.get(event, key)
        return value if value is not None and self.fields[key].check(value) else None


def _short(value: Any, n: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= n else text[: n - 1] + "…"


T = _f("number", "s, the run's clock")
VIEW_ID = _f("integer", "the capture request's number (the image's view_<id>.png)")
POSE3 = "array<number?>[3]"

_EVENTS = (
    # -- the predictor (Host 1: fixed camera, Kalman filter, planners, robot and table)
    EventSpec("tracking_prior", "the tracker's prior for the trajectory family, as the run starts",
              {"t": T, "family": _f("string?", "trajectory family the table will run (None: unknown)"),
               "curve_prior": _f("number", "prior probability of a curved leg")}),
    EventSpec("stage", "the run enters a stage (wait, track, intercept, initial, standard, match, done, failed)",
              {"t": T, "stage": _f("string")}),
    EventSpec("failure", "the run failed; the reason and the stage it failed in",
              {"t": T, "reason": _f("string"), "stage": _f("string")}),
    EventSpec("robot_stop_failed", "the robot's stop at the end of a run raised",
              {"t": T, "error": _f("string")}),
    EventSpec("segment", "a robot segment was accepted by the controller",
              {"t": T, "id": _f("integer", "segment id"), "kind": _f("string?", "what the move is for"),
               "t_end": _f("number", "planned end, s"),
               "t0c": _f("number?", "the controller's start, s (null: not reported)"),
               "t1c": _f("number?", "the controller's end, s (null: not reported)"),
               "p": _f(POSE3, "flange target position, mm W"),
               "rotvec": _f(POSE3, "flange target rotation vector, rad")}),
    EventSpec("plan", "an interception or view was planned",
              {"t": T, "kind": _f("string", "initial1, initial2 or standard"), "t_hit": _f("number", "arrival, s")}),
    EventSpec("arm_plan", "a segment sent to an arm, as the planner checked it in the arm's joint space",
              {"t": T, "id": _f("integer", "segment id"), "kind": _f("string?", "what the move is for"),
               "ratio": _f("number", "peak joint speed over its planned share of the limit"),
               "stretch": _f("number", "the segment's duration over the earliest arrival's (1: not slowed)"),
               "q_end_deg": _f("array<number>[6]", "the arm's configuration at the segment's end, deg")}),
    EventSpec("predict", "the object's predicted path from now to the horizon",
              {"t": T, "path": _f("array<number?>[*,*]", "[[x, y], ...] mm, table plane W")}),
    EventSpec("segment_held", "the second image's leg sent held (SEG hold=1, dialect 1.4): it runs at GO, after the "
              "first image's exposure",
              {"t": T, "id": _f("integer", "segment id"), "p": _f(POSE3, "flange target position, mm W"),
               "t_start": _f("number", "the start it was planned for, s (arrival, @DONE, exposure, GO)")}),
    EventSpec("hold_refused", "the controller refused a held segment or its GO; the leg is planned after the image",
              {"t": T, "error": _f("string")}),
    EventSpec("replan_refused", "a re-plan was refused by the controller or the safety checks; the old plan stands",
              {"t": T, "error": _f("string")}),
    EventSpec("standard_view_unreachable", "no safe path to the standard view of the chosen marker",
              {"t": T, "reason": _f("string?"), "code": _f("string")}),
    EventSpec("capture_request", "the predictor asks the recognizer to take a mobile-camera image",
              {"t": T, "view_id": VIEW_ID, "kind": _f("string", "initial1, initial2 or standard"),
               "T_w_c2": _f("array<number>[4,4]", "the mobile camera's pose, mm W"),
               "provisional": _opt("boolean", "true: requested at the controller's promised arrival, used only once "
                                   "its @DONE confirms it (capture_confirmed / capture_discarded)")}),
    EventSpec("capture_confirmed", "the @DONE of the segment came: the image requested at its arrival is used",
              {"t": T, "view_id": VIEW_ID}),
    EventSpec("capture_discarded", "no @DONE confirmed the image requested at the promised arrival: the recognizer "
              "forgets it (Discard) and the arrival is checked with STATUS",
              {"t": T, "view_id": VIEW_ID, "reason": _f("string")}),
    EventSpec("track", "a fixed-camera sighting of the object, filtered",
              {"t": T, "x": _f("number", "Kalman estimate, mm table plane W"), "y": _f("number", "mm"),
               "px": _f("array<number>[2]", "marker centroid in the fixed image, px")}),
    EventSpec("marker_lost", "the fixed camera has not seen the marker for longer than tracking.max_bridge_s: "
              "the track is lost (a later stage coasts on the prediction)",
              {"t": T, "coasting": _opt("boolean", "true: a later stage goes on, coasting on the prediction"),
               "gap_s": _opt("number", "s since the last sighting"),
               "frames": _opt("integer", "fixed-camera frames without a sighting since")}),
    EventSpec("track_bridged", "a gap in the fixed camera's sightings (the arm hid the marker) was bridged on the "
              "tracker's prediction: the track was kept",
              {"t": T, "t_start": _f("number", "the last sighting before the gap, s"),
               "t_end": _f("number", "the sighting that closed it, s"), "duration_s": _f("number", "s"),
               "frames": _f("integer", "fixed-camera frames without a sighting"),
               "stage": _f("string", "the run's stage when it closed")}),
    EventSpec("pose_received", "the predictor received a marker pose from the recognizer",
              {"t": T, "center_w": _f(POSE3, "mm W"), "normal_w": _f(POSE3, "unit vector W"),
               "ambiguous": _f("boolean", "the duality was not resolved"), "margin": _f("number?", "rad")}),
    EventSpec("identity", "the recognizer's answer as received",
              {"t": T, "object": _f("string"), "score": _f("number?", "silhouette mismatch, lower is better"),
               "candidates": _f("array<string>")}),
    EventSpec("ambiguous", "the recognizer could not tell these candidates apart in this view",
              {"t": T, "candidates": _f("array<string>")}),
    EventSpec("recognizer_failure", "the recognizer reported a failure (messages.FailureCode)",
              {"t": T, "code": _f("integer"), "text": _f("string")}),
    EventSpec("robot", "the mobile camera's flange position",
              {"t": T, "p": _f(POSE3, "mm W"), "planned": _opt("boolean", "from the plan, not a controller reply")}),
    EventSpec("table_progress", "the table's G-code program: lines acknowledged, sent, in total, in flight",
              {"t": T, "acked": _f("integer"), "sent": _f("integer"), "total": _f("integer"),
               "in_flight": _f("integer")}),
    EventSpec("table_program_ended", "the table's program ended: every line acknowledged and GRBL Idle "
              "(a live run then has run.after_program_s to identify)", {"t": T}),
    # -- the recognizer (Host 2: mobile camera, marker poses, silhouette matching)
    EventSpec("no_marker", "no marker in a mobile-camera image",
              {"t": T, "view_id": VIEW_ID, "kind": _f("string")}),
    EventSpec("response_check", "the camera response check of an initial image (written when the mobile camera's "
              "response is undeclared or a marker's edges lean as another response's would: "
              "`labctl vision learn-response` measures it)",
              {"t": T, "view_id": VIEW_ID, "declared": _f("boolean", "lab.response_declared: stated or learned"),
               "markers": _f("integer", "markers found (suspects included)"),
               "mismatched": _f("integer", "markers flagged response_mismatch"),
               "refused": _f("integer", "markers refused for pose by the undeclared response's covariance")}),
    EventSpec("marker_candidates", "the markers of the first initial image; the preferred one's two poses",
              {"t": T, "view_id": VIEW_ID, "ellipse": _f("object", "vision.ellipse.Ellipse.to_dict()"),
               "candidates": _f("array<object>", "the circle's two pose candidates (to_dict)"),
               "markers": _f("integer", "markers found")}),
    EventSpec("marker_pose", "a marker posed from the two initial images (duality resolved or not)",
              {"t": T, "view_id": VIEW_ID, "marker": _f("integer", "index in the first image's markers"),
               "ellipses": _f("object<array<number?>[5]>",
                             "{image: [cx, cy, a, b, theta]} px, semi-axes, rad from x towards y"),
               "center_w": _f(POSE3, "mm W"), "normal_w": _f(POSE3, "unit vector W"),
               "resolved": _f("boolean"), "index": _f("integer?", "the chosen candidate"),
               "margin_deg": _f("number?"), "threshold_deg": _f("number?"), "suspect": _f("boolean"),
               "scores_deg": _f("array<number?>"), "pose": _f("object?", "the chosen pose (to_dict)"),
               "consistency": _f("object?", "two-view check (to_dict); null: not checked")}),
    EventSpec("refuted", "candidates dropped: they need a marker facing up that no initial image showed",
              {"t": T, "view": _f("integer"), "candidates": _f("array<string>"), "reason": _f("string")}),
    EventSpec("standard_view_misaligned", "the standard view's marker is off centre or oblique",
              {"t": T, "view_id": VIEW_ID, "view": _f("integer", "standard view k"), "problem": _f("string")}),
    EventSpec("no_silhouette", "no usable silhouette in the standard view",
              {"t": T, "view_id": VIEW_ID, "error": _f("string")}),
    EventSpec("match", "the silhouette of standard view k matched against the library",
              {"t": T, "view_id": VIEW_ID, "view": _f("integer", "standard view k"),
               "scores": _f("object<number?>", "{object: mismatch}, lower is better"),
               "candidates": _f("array<string>"), "best": _f("string?"),
               "planned_marker_height_mm": _f("number?"),
               "marker_height_mm": _opt("number?", "measured in this view (the height gate on)"),
               "marker_height_sigma_mm": _opt("number?"), "height_tol_mm": _opt("number?")}),
    EventSpec("evidence", "over several views, one candidate's summed score leads by the margin",
              {"t": T, "view": _f("integer"), "leader": _f("string"), "views": _f("integer"),
               "totals": _f("object<number?>")}),
    # -- the runtimes
    EventSpec("truth", "the virtual run's ground truth: which object, where",
              {"t": T, "object": _f("string"), "placement": _f("object"), "seed": _f("integer")}),
    EventSpec("log", "a labctl logger's message in a live worker (driver and link warnings)",
              {"role": _f("string"), "level": _f("string"), "logger": _f("string"), "message": _f("string")}),
    EventSpec("devices_stopped", "a worker's exit path stopped its devices; each outcome",
              {"role": _f("string"), "t": _f("number?", "s, when the stop began"), "reason": _f("string"),
               "outcomes": _f("array<object>", "runtime.stopping outcomes"), "close_errors": _f("array<string>")}),
    EventSpec("worker_started", "a live worker process started",
              {"role": _f("string"), "pid": _f("integer")}),
    EventSpec("link_refused", "the host link refused a peer that failed authentication",
              {"line": _f("string")}),
    EventSpec("run_clock", "the origin (time.monotonic) every t of a live run is measured from",
              {"role": _f("string"), "origin": _f("number", "s, CLOCK_MONOTONIC")}),
    EventSpec("table_program", "the table's program was started (or none: the parts move by something else)",
              {"t": T, "trajectory": _f("string"), "speed_mm_s": _f("number"), "lines": _opt("integer")}),
    EventSpec("startup", "the predictor's start-up phases, unix time each",
              {"marks": _f("object<number>")}),
    EventSpec("message_dropped", "an implausible host-link message was dropped",
              {"t": T, "message": _f("string", "its repr, at most 200 characters")}),
    EventSpec("worker_error", "a live worker failed",
              {"role": _f("string"), "error": _f("string"), "traceback": _f("string")}),
    EventSpec("table_to_start", "the table was moved to the trajectory's start",
              {"t": T, "start": _f("array<number>[2]", "mm"), "was": _f("array<number?>[2]", "mm")}),
    EventSpec("sim_truth", "the live simulated lab's ground truth of motion changed",
              {"t": T, "robot_moving": _f("boolean"), "table_moving": _f("boolean"), "table_state": _f("string"),
               "robot_stop": _f("array<number>[2]?", "[start, end] s of the latest stop ramp")}),
    EventSpec("sim_stopped", "the live simulated lab stopped on its own (its supervisor vanished)",
              {"t": T, "reason": _f("string"), "robot_moving": _f("boolean"), "table_moving": _f("boolean"),
               "table_state": _f("string")}),
    EventSpec("run_aborted", "the supervisor aborted a live run and stopped the devices itself",
              {"t": _f("number", "s since the run's origin"), "reason": _f("string"), "cause": _f("string"),
               "devices_stopped": _f("array<string>", "devices confirmed still"),
               "stop_outcomes": _f("array<object>"), "stop_bytes": _f("array<object>"),
               "worker_stop_outcomes": _f("object"), "stop_commands_sent_s": _f("number"),
               "t_stop_sent": _f("number"), "devices_after_stop": _f("object?", "the simulator's view; null: none"),
               "exit_code": _f("integer")}),
    # -- experiments
    EventSpec("tick", "one soak tick", {"t": T, "n": _f("integer", "ticks so far")}),
)

#: every declared event by name
SCHEMA: Mapping[str, EventSpec] = {e.name: e for e in _EVENTS}
#: the declared event names
NAMES = frozenset(SCHEMA)
if len(SCHEMA) != len(_EVENTS):
    raise ValueError("an event is declared twice")


def spec(name: str) -> EventSpec:
    """The declared event ``name``; EventSchemaError if it is not declared."""
    try:
        return SCHEMA[name]
    except (KeyError, TypeError):
        raise EventSchemaError(f"event {name!r} is not declared in labctl.records.events") from None


def problem(event: Mapping[str, Any]) -> str | None:
    """What is wrong with one event (a JSON object as written), in one line, or None if it is valid."""
    name = event.get("event")
    es = SCHEMA.get(name) if isinstance(name, str) else None
    if es is None:
        return f"event {name!r} is not declared in labctl.records.events"
    return es.problem(event)


def validate(event: Mapping[str, Any]) -> None:
    """Raise EventSchemaError (naming the event and the field) unless ``event`` matches its declaration."""
    why = problem(event)
    if why is not None:
        raise EventSchemaError(why)
