"""Run records: ``runs/<UTC timestamp>/`` with an append-only event log, images and a result.

Layout of one record::

    runs/20250314T101502Z/          sortable UTC start time (``-001``, ``-002`` … if taken)
        meta.json                   what was asked for (written once, atomically)
        events.jsonl                one JSON object per line, appended; fsynced in batches by a thread
        initial1.png …              the images decisions were made on (atomic writes)
        result.json                 the final result (atomic; absent if the run never finished)
        report.html, report.png     written by :func:`labctl.records.report.write_report`

Several processes may append to the same ``events.jsonl``: each opens it with ``O_APPEND`` and
writes each line with a single ``os.write``, which the kernel appends whole, so lines from
different workers never interleave. The write happens in the caller, in order, at once: a killed
process (even SIGKILL) leaves the log complete up to its last event, because the kernel already
holds the line. Durability against a power cut (``durable=True``) costs nothing in the caller's
loop: a writer thread fsyncs the log at most every ``fsync_period_s`` (batching every event
written meanwhile), and :meth:`RunRecord.close` — called on every exit path, and at interpreter
exit for records still open — does the last fsync.

Every event is checked against its declaration in :mod:`labctl.records.events` (name, fields, types)
as it is written. A mismatch raises :class:`~labctl.records.events.EventSchemaError` when the
environment sets ``LABCTL_STRICT_EVENTS=1`` (the test suite does, for itself and every process it
starts); otherwise the event is written as given and the mismatch logged once as a warning, so a
run never loses its record, nor its motion, to a writer's mistake.
"""

from __future__ import annotations

import atexit
import dataclasses
import json
import logging
import math
import os
import re
import threading
import time
import weakref
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import LabctlError
from ..fsutil import atomic_write_bytes, atomic_write_text
from .events import EventSchemaError, problem, spec

__all__ = ["RecordError", "RunRecord", "ImageWriter", "RunData", "read_events", "load_run", "to_jsonable", "EVENTS",
           "META", "RESULT"]

EVENTS = "events.jsonl"
META = "meta.json"
RESULT = "result.json"
_NAME_OK = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
#: set to 1 to make an event that does not match its declaration raise (tests, debugging)
STRICT_ENV = "LABCTL_STRICT_EVENTS"
_log = logging.getLogger(__name__)
_WARNED: set[str] = set()  # schema mismatches already warned about in this process


def strict_events() -> bool:
    """Whether an event that does not match the schema raises (``LABCTL_STRICT_EVENTS=1``) or is only warned of."""
    return os.environ.get(STRICT_ENV, "") not in ("", "0")


class RecordError(LabctlError):
    """A run record cannot be created, written or read."""


def to_jsonable(obj: Any) -> Any:
    """``obj`` with numpy scalars/arrays, tuples, paths and dataclasses turned into JSON types.

    Non-finite floats become ``null`` (strict JSON has no NaN); unknown objects become ``str(obj)``.
    """
    if obj is None or isinstance(obj, bool | str | int):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple | set | frozenset):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(dataclasses.asdict(obj))
    return str(obj)


def _dumps_json(obj: Any) -> str:
    """``obj`` (already JSON types) as one compact line."""
    return json.dumps(obj, allow_nan=False, ensure_ascii=False, separators=(",", ":"))


def _timestamp(now: datetime | None = None) -> str:
    now = now or datetime.now(UTC)
    return now.astimezone(UTC).strftime("%Y%m%dT%H%M%SZ")


_OPEN: weakref.WeakSet = weakref.WeakSet()  # records with a log open in this process


@atexit.register
def _close_open_records() -> None:  # the last fsync on a normal interpreter exit
    for rec in list(_OPEN):
        try:
            rec.close()
        except Exception:  # noqa: BLE001, S110 — an exit hook must not raise; nothing is left to report to
            pass


class RunRecord:
    """Writer for one run's folder. Picklable: a child process re-opens the log on first use."""

    #: longest time a written event waits for its fsync (s); the loop that logs never waits
    fsync_period_s = 0.25

    def __init__(self, path: Path | str, *, durable: bool = True, checked: bool = True) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise RecordError(f"no run record at {self.path}")
        self.durable = durable
        self.checked = checked  # False: a free-form log (tests of the record itself), no schema
        self._init_state()

    def _init_state(self) -> None:
        self._fd: int | None = None
        self._fd_pid: int | None = None
        self._lock = threading.Lock()
        self._dirty = False
        self._sync_fd: int | None = None
        self._syncer: threading.Thread | None = None
        self._stop = threading.Event()
        self.fsyncs = 0  # how many fsyncs the writer thread and close() did (batches, not events)
        self.sync_error: str | None = None
        self._strict = strict_events()

    # ---- creation ---------------------------------------------------------------------------

    @classmethod
    def create(cls, runs_dir: Path | str, meta: dict | None = None, *, now: datetime | None = None,
               durable: bool = True, checked: bool = True) -> RunRecord:
        """Make ``runs_dir/<UTC timestamp>[-NNN]/`` with ``meta.json``; unique even within one second."""
        runs_dir = Path(runs_dir)
        try:
            runs_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RecordError(f"cannot create runs folder {runs_dir}: {exc.strerror or exc}") from exc
        stamp = _timestamp(now)
        for k in range(1000):
            path = runs_dir / (stamp if k == 0 else f"{stamp}-{k:03d}")
            try:
                os.mkdir(path)  # atomic claim: fails if another run took this name
                break
            except FileExistsError:
                continue
            except OSError as exc:
                raise RecordError(f"cannot create run folder {path}: {exc.strerror or exc}") from exc
        else:
            raise RecordError(f"more than 1000 runs started at {stamp} in {runs_dir}")
        header = {"created_utc": datetime.now(UTC).isoformat(timespec="milliseconds"), "run_id": path.name,
                  **(meta or {})}
        atomic_write_text(path / META, json.dumps(to_jsonable(header), indent=2, allow_nan=False) + "\n")
        (path / EVENTS).touch()
        return cls(path, durable=durable, checked=checked)

    @classmethod
    def open(cls, run_dir: Path | str, *, durable: bool = True, checked: bool = True) -> RunRecord:
        """Attach to an existing record (e.g. from a worker process) to add events and images."""
        return cls(run_dir, durable=durable, checked=checked)

    @property
    def events_path(self) -> Path:
        """Path of the record's event log."""
        return self.path / EVENTS

    # ---- pickling: the fd belongs to one process ----------------------------------------------

    def __getstate__(self):
        return {"path": self.path, "durable": self.durable, "checked": self.checked}

    def __setstate__(self, state):
        self.path = state["path"]
        self.durable = state["durable"]
        self.checked = state.get("checked", True)
        self._init_state()

    def _events_fd(self) -> int:
        pid = os.getpid()
        if self._fd is None or self._fd_pid != pid:  # first use, or we are a forked child
            flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_CLOEXEC", 0)
            try:
                self._fd = os.open(self.events_path, flags, 0o644)
            except OSError as exc:
                raise RecordError(f"cannot open {self.events_path}: {exc.strerror or exc}") from exc
            self._fd_pid = pid
            if self.durable:  # the writer thread fsyncs through its own descriptor: close() never races it
                self._sync_fd = os.dup(self._fd)
                self._stop = threading.Event()
                self._syncer = threading.Thread(target=self._sync_loop, name="record-fsync", daemon=True)
                self._syncer.start()
            _OPEN.add(self)
        return self._fd

    def _sync_loop(self) -> None:
        while not self._stop.wait(self.fsync_period_s):
            self._sync()

    def _sync(self) -> None:
        with self._lock:
            if not self._dirty or self._sync_fd is None:
                return
            self._dirty = False
            fd = self._sync_fd
        try:
            os.fsync(fd)
            self.fsyncs += 1
        except OSError as exc:  # kept for close() to raise: a lost fsync is never silent
            self.sync_error = f"cannot fsync {self.events_path}: {exc.strerror or exc}"

    # ---- writing ------------------------------------------------------------------------------

    def event(self, name: str, **fields) -> dict:
        """Append ``{"event": name, "wall": <unix time>, **fields}`` as one line (written at once, in
        order; fsynced by the writer thread within ``fsync_period_s``). Returns the line.

        The line, once made JSON, is checked against ``name``'s declaration in
        :mod:`labctl.records.events` (see the module docstring for what a mismatch does)."""
        if not isinstance(name, str) or not name:
            raise RecordError(f"event name must be a non-empty string, not {name!r}")
        if "event" in fields or "wall" in fields:
            raise RecordError("'event' and 'wall' are reserved for the event name and its time")
        line = {"event": name, "wall": time.time(), **fields}
        obj = to_jsonable(line)
        if self.checked:
            why = problem(obj)
            if why is not None:
                self._schema_mismatch(why)
        data = (_dumps_json(obj) + "\n").encode("utf-8")
        with self._lock:
            fd = self._events_fd()
            try:
                written = os.write(fd, data)  # one write with O_APPEND: the line lands whole
                if written != len(data):
                    raise RecordError(f"short write to {self.events_path} ({written}/{len(data)} bytes)")
                self._dirty = True
            except OSError as exc:
                raise RecordError(f"cannot append to {self.events_path}: {exc.strerror or exc}") from exc
        return line

    def _schema_mismatch(self, why: str) -> None:
        if self._strict:
            raise EventSchemaError(f"{self.events_path}: {why}")
        key = why.split(" = ", 1)[0]  # the event and field, not the value
        if key not in _WARNED:  # once per event, field and process: a track event comes 30 times a second
            _WARNED.add(key)
            _log.warning("run record %s: %s (written as given)", self.path.name, why)

    def save_image(self, name: str, image: np.ndarray) -> Path:
        """Write ``image`` (uint8/uint16 gray, BGR or BGRA; bool masks as 0/255) as PNG ``name``.

        Encoded in memory and written through a temporary file + ``os.replace``, so a reader never
        sees half a PNG.
        """
        fname, img = self._checked_image(name, image)
        return self._write_png(fname, img)

    def _checked_image(self, name: str, image: np.ndarray) -> tuple[str, np.ndarray]:
        """The PNG file name and the array to encode; RecordError for a bad name, dtype or shape."""
        fname = name if name.lower().endswith(".png") else f"{name}.png"
        if not _NAME_OK.match(fname):
            raise RecordError(f"image name {name!r} must be a plain file name")
        img = np.asarray(image)
        if img.dtype == bool:
            img = img.astype(np.uint8) * 255
        if img.dtype not in (np.uint8, np.uint16):
            raise RecordError(f"image {fname}: dtype {img.dtype} (need uint8, uint16 or bool)")
        if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] in (1, 3, 4))) or img.size == 0:
            raise RecordError(f"image {fname}: shape {img.shape} is not an image")
        return fname, img

    def _write_png(self, fname: str, img: np.ndarray) -> Path:
        import cv2

        ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
        if not ok:
            raise RecordError(f"image {fname}: PNG encoding failed")
        path = self.path / fname
        atomic_write_bytes(path, buf.tobytes())
        return path

    def image_writer(self) -> ImageWriter:
        """A writer that saves this record's images in a thread (:class:`ImageWriter`)."""
        return ImageWriter(self)

    def finish(self, result: dict) -> Path:
        """Write ``result.json`` atomically (numpy values converted); return its path."""
        path = self.path / RESULT
        atomic_write_text(path, json.dumps(to_jsonable(result), indent=2, allow_nan=False) + "\n")
        return path

    def flush(self) -> None:
        """fsync now every event written so far (the writer thread would within ``fsync_period_s``)."""
        if self._fd_pid == os.getpid():
            self._sync()
        if self.sync_error:
            raise RecordError(self.sync_error)

    def close(self) -> None:
        """Stop the writer thread, fsync what is left and close the log (safe to call twice)."""
        if self._fd_pid != os.getpid():
            self._fd = self._sync_fd = self._syncer = None
            self._fd_pid = None
            return
        self._stop.set()
        if self._syncer is not None and self._syncer is not threading.current_thread():
            self._syncer.join(timeout=5.0)
        self._sync()
        with self._lock:
            for fd in (self._fd, self._sync_fd):
                if fd is not None:
                    os.close(fd)
            self._fd = self._sync_fd = self._syncer = None
            self._fd_pid = None
        _OPEN.discard(self)
        if self.sync_error:
            raise RecordError(self.sync_error)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __repr__(self) -> str:
        return f"RunRecord({str(self.path)!r})"


class ImageWriter:
    """A record's images encoded and written by one thread, in the order given, so that a live worker's reply
    does not wait for a PNG encode and an fsync (10–110 ms each on a shared machine; docs/notes/run.md,
    "2026-12-02 (c)"). :meth:`save` checks the name and the array at once (the same :class:`RecordError` as
    :meth:`RunRecord.save_image`) and keeps a copy; :meth:`close` — on every way out of the worker — waits
    until every queued image is on disk and raises the first write error, if any. Each file is written
    atomically as by :meth:`RunRecord.save_image`, with the same bytes."""

    def __init__(self, record: RunRecord):
        self.record = record
        self._queue: list[tuple[str, np.ndarray]] = []
        self._cv = threading.Condition()
        self._closing = False
        self._thread: threading.Thread | None = None
        self.error: str | None = None
        self.written = 0

    def save(self, name: str, image: np.ndarray) -> None:
        """Queue ``image`` as PNG ``name`` (a copy: the caller may reuse its array)."""
        fname, img = self.record._checked_image(name, image)
        with self._cv:
            if self._closing:
                raise RecordError(f"image {fname}: the record's image writer is closed")
            self._queue.append((fname, np.array(img, copy=True)))
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name="record-images", daemon=True)
                self._thread.start()
            self._cv.notify()

    def _loop(self) -> None:
        while True:
            with self._cv:
                while not self._queue and not self._closing:
                    self._cv.wait()
                if not self._queue:
                    return
                fname, img = self._queue[0]
            try:
                self.record._write_png(fname, img)
                self.written += 1
            except (OSError, RecordError) as exc:
                self.error = self.error or f"image {fname}: {exc}"
            with self._cv:
                self._queue.pop(0)
                self._cv.notify_all()

    def close(self, timeout_s: float = 30.0) -> None:
        """Write what is queued (waits up to ``timeout_s``), then stop; RecordError if an image was not written."""
        with self._cv:
            self._closing = True
            self._cv.notify_all()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=timeout_s)
        with self._cv:
            left = [f for f, _ in self._queue]
        if left:
            self.error = self.error or f"{len(left)} image(s) not written within {timeout_s:g} s: {', '.join(left)}"
        if self.error:
            raise RecordError(self.error)


# ---- reading --------------------------------------------------------------------------------------


def read_events(run_dir: Path | str, *, strict: bool = False) -> list[dict]:
    """All events of a record in file order.

    A line that is not a JSON object (e.g. torn by a power cut) is skipped, or raises
    :class:`RecordError` with ``strict=True``. A missing log reads as no events.
    """
    path = Path(run_dir) / EVENTS
    if not path.is_file():
        return []
    events = []
    with open(path, "rb") as fh:
        for lineno, raw in enumerate(fh, start=1):
            if not raw.strip():
                continue
            try:
                obj = json.loads(raw)
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                if strict:
                    raise RecordError(f"{path}:{lineno}: not JSON ({exc})") from exc
                continue
            if not isinstance(obj, dict) or "event" not in obj:
                if strict:
                    raise RecordError(f"{path}:{lineno}: not an event object")
                continue
            events.append(obj)
    return events


@dataclasses.dataclass
class RunData:
    """A record read back: ``result`` is None for a run that did not finish."""

    path: Path
    meta: dict
    events: list[dict]
    result: dict | None
    images: dict[str, Path]

    @property
    def finished(self) -> bool:
        """True when the run wrote its result."""
        return self.result is not None

    def of(self, name: str) -> list[dict]:
        """The events called ``name``, in order; EventSchemaError if no such event is declared
        (:mod:`labctl.records.events`), so a reader never asks for an event no writer writes."""
        spec(name)
        return [e for e in self.events if e.get("event") == name]


def _read_json(path: Path) -> dict | None:
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RecordError(f"{path}: unreadable ({exc})") from exc
    return data if isinstance(data, dict) else None


def load_run(run_dir: Path | str) -> RunData:
    """Read a whole record: meta, events, result (or None) and its PNG images by stem."""
    path = Path(run_dir)
    if not path.is_dir() or not ((path / META).is_file() or (path / EVENTS).is_file()):
        raise RecordError(f"{path} is not a run record (no {META} or {EVENTS})")
    images = {p.stem: p for p in sorted(path.glob("*.png")) if not p.name.startswith((".", "report"))}
    return RunData(path=path, meta=_read_json(path / META) or {}, events=read_events(path),
                   result=_read_json(path / RESULT), images=images)
