"""The live view of a run: a local web page that follows the run's record folder as it is written.

The page (``labctl run --view``) reads nothing but the record folder, so it cannot change what the run
does: a :class:`RecordTail` reads ``events.jsonl`` incrementally (complete lines only, from where it
left off) and folds each event, read through its declaration in :mod:`labctl.records.events`, into a
small state; the images are the files the run writes anyway (``view_<id>.png``, ``standard_k.png``,
``silhouette_k.png``, atomic writes) and the fixed camera's ``live/fixed.jpg`` (see
:mod:`labctl.runtime.snapshot`). :class:`LiveViewServer` serves the page, ``/api/state`` (JSON) and
the images from a stdlib ``ThreadingHTTPServer`` in daemon threads; the page polls. Every request
carries a key made for this run (in the printed URL), so no other page in the browser can press
Stop. ``POST /api/stop`` calls the stop the command gave (``labctl run``: a SIGINT to its own main
thread, the very path Ctrl-C takes).
"""

from __future__ import annotations

import json
import os
import re
import secrets
import threading
import time
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from ..errors import LabctlError
from .events import spec

__all__ = ["RecordTail", "LiveViewServer", "LiveViewError", "page_html"]

EVENTS = "events.jsonl"
RESULT = "result.json"
LIVE_DIR = "live"
#: the mobile camera's images a run saves, newest last (the viewer shows them as they come)
_IMAGE = re.compile(r"^(view_\d+|initial[12]|standard_\d+|silhouette_\d+)\.png$")
_MAX_POINTS = 4000  # track/robot points kept for the plan view (a 90 s run at 30 Hz is 2700)


class LiveViewError(LabctlError):
    """The live view cannot start (its port is taken, say)."""


def _ellipse_row(d: Any) -> list | None:
    """``vision.ellipse.Ellipse.to_dict()`` as ``[cx, cy, a, b, theta]``, or None if it is not one."""
    try:
        return [float(d["center"][0]), float(d["center"][1]), float(d["axes"][0]), float(d["axes"][1]),
                float(d["angle_rad"])]
    except (KeyError, TypeError, IndexError, ValueError):
        return None


class RecordTail:
    """Follows one record folder: new complete lines of ``events.jsonl`` folded into :attr:`state`."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self._offset = 0
        self._partial = b""
        self.events_read = 0
        self.state: dict[str, Any] = {
            "stages": [], "track": [], "predict": None, "segments": [], "robot": [], "captures": {},
            "ellipses": {}, "truth": None, "table_progress": None, "devices_stopped": [], "aborted": None,
            "workers": [], "identity": None, "failure": None, "match": None, "t": None, "marker_lost": None,
        }
        self._folders = {
            "stage": self._stage, "track": self._track, "predict": self._predict, "segment": self._segment,
            "robot": self._robot, "capture_request": self._capture, "marker_candidates": self._candidates,
            "marker_pose": self._marker_pose, "sim_truth": self._truth, "table_progress": self._progress,
            "devices_stopped": self._stopped, "run_aborted": self._aborted, "worker_started": self._worker,
            "identity": self._identity, "failure": self._failure, "match": self._match,
            "marker_lost": self._lost,
        }

    def poll(self) -> int:
        """Read what the run appended since the last call; return the number of events folded in."""
        path = self.folder / EVENTS
        try:
            with path.open("rb") as f:
                f.seek(self._offset)
                data = f.read()
        except FileNotFoundError:
            return 0
        self._offset += len(data)
        data = self._partial + data
        lines = data.split(b"\n")
        self._partial = lines.pop()  # a line still being written (writes are whole, but be safe)
        n = 0
        for line in lines:
            if not line.strip():
                continue
            try:
                event = json.loads(line)
            except ValueError:
                continue
            name = event.get("event") if isinstance(event, dict) else None
            fold = self._folders.get(name) if isinstance(name, str) else None
            if fold is not None:
                fold(spec(event["event"]), event)
                n += 1
        self.events_read += n
        return n

    # ---- one folder per event; fields through the schema (a mistyped field reads as absent)

    def _clock(self, es, e) -> float | None:
        t = es.valid(e, "t")
        if t is not None:
            self.state["t"] = t if self.state["t"] is None else max(self.state["t"], t)
        return t

    def _stage(self, es, e):
        self.state["stages"].append({"t": self._clock(es, e), "stage": es.valid(e, "stage")})

    def _track(self, es, e):
        t, x, y, px = self._clock(es, e), es.valid(e, "x"), es.valid(e, "y"), es.valid(e, "px")
        if x is not None and y is not None:
            _append(self.state["track"], [t, x, y, *(px or [None, None])])

    def _predict(self, es, e):
        path = es.valid(e, "path")
        if path is not None:
            self.state["predict"] = {"t": self._clock(es, e), "path": [p[:2] for p in path if len(p) >= 2]}

    def _segment(self, es, e):
        self.state["segments"].append({"t": self._clock(es, e), "id": es.valid(e, "id"), "kind": es.valid(e, "kind"),
                                       "p": es.valid(e, "p"), "t_end": es.valid(e, "t_end")})

    def _robot(self, es, e):
        p = es.valid(e, "p")
        if p is not None:
            _append(self.state["robot"], [self._clock(es, e), *p])

    def _capture(self, es, e):
        vid, kind = es.valid(e, "view_id"), es.valid(e, "kind")
        if vid is not None:
            self.state["captures"][f"view_{vid}"] = {"t": self._clock(es, e), "kind": kind}

    def _candidates(self, es, e):
        vid, row = es.valid(e, "view_id"), _ellipse_row(es.valid(e, "ellipse"))
        if vid is not None and row is not None:
            self.state["ellipses"][f"view_{vid}"] = row
            self.state["ellipses"]["initial1"] = row  # the first initial image is this view (its own copy)

    def _marker_pose(self, es, e):
        rows = es.valid(e, "ellipses") or {}
        by_kind = {c["kind"]: name for name, c in self.state["captures"].items() if c.get("kind")}
        for image, row in rows.items():
            if row is not None and None not in row[:5]:
                self.state["ellipses"][image] = row[:5]
                if image in by_kind:  # "initial2" → the view_<id>.png it was taken as
                    self.state["ellipses"][by_kind[image]] = row[:5]

    def _truth(self, es, e):
        self.state["truth"] = {k: es.valid(e, k) for k in ("t", "robot_moving", "table_moving", "table_state")}
        self._clock(es, e)

    def _progress(self, es, e):
        self.state["table_progress"] = {k: es.valid(e, k) for k in ("acked", "sent", "total")}

    def _stopped(self, es, e):
        outcomes = es.valid(e, "outcomes") or []
        self.state["devices_stopped"].append({"role": es.valid(e, "role"), "reason": es.valid(e, "reason"),
                                              "outcomes": [{k: o.get(k) for k in ("device", "ok", "confirmed")}
                                                           for o in outcomes if isinstance(o, dict)]})

    def _aborted(self, es, e):
        after = es.valid(e, "devices_after_stop") or {}
        self.state["aborted"] = {"reason": es.valid(e, "reason"), "cause": es.valid(e, "cause"),
                                 "devices_stopped": es.valid(e, "devices_stopped"),
                                 "exit_code": es.valid(e, "exit_code"), "still_after_s": after.get("still_after_s")}

    def _worker(self, es, e):
        self.state["workers"].append({"role": es.valid(e, "role"), "pid": es.valid(e, "pid")})

    def _identity(self, es, e):
        self.state["identity"] = {"t": self._clock(es, e), "object": es.valid(e, "object"),
                                  "score": es.valid(e, "score")}

    def _failure(self, es, e):
        self.state["failure"] = {"t": self._clock(es, e), "reason": es.valid(e, "reason"),
                                 "stage": es.valid(e, "stage")}

    def _match(self, es, e):
        self.state["match"] = {"view": es.valid(e, "view"), "best": es.valid(e, "best"),
                               "candidates": es.valid(e, "candidates")}

    def _lost(self, es, e):
        self.state["marker_lost"] = self._clock(es, e)

    # ---- what the page asks for

    def images(self) -> list[dict]:
        """The mobile camera's saved images, oldest first: ``{"name", "mtime"}``."""
        out: list[dict] = []
        if not self.folder.is_dir():  # a sweep's first trial not started yet
            return out
        with os.scandir(self.folder) as it:
            for entry in it:
                if _IMAGE.match(entry.name):
                    try:
                        out.append({"name": entry.name, "mtime": entry.stat().st_mtime})
                    except FileNotFoundError:  # replaced meanwhile
                        continue
        return sorted(out, key=lambda d: (d["mtime"], d["name"]))

    def fixed(self) -> dict | None:
        """The fixed camera's latest snapshot (``live/fixed.json``'s frame time, seq and scale, and its mtime)."""
        meta = self.folder / LIVE_DIR / "fixed.json"
        jpg = self.folder / LIVE_DIR / "fixed.jpg"
        try:
            out = json.loads(meta.read_text())
            out["mtime"] = jpg.stat().st_mtime
        except (OSError, ValueError):
            return None
        return out if isinstance(out, dict) else None

    def result(self) -> dict | None:
        """``result.json``'s identity, failure and correctness, once the run wrote it."""
        try:
            res = json.loads((self.folder / RESULT).read_text())
        except (OSError, ValueError):
            return None
        return {k: res.get(k) for k in ("identity", "true_identity", "correct", "failure", "time_to_identity_s")}

    def snapshot(self) -> dict:
        """Everything the page draws, as JSON types."""
        self.poll()
        return {"run": self.folder.name, **self.state, "images": self.images(), "fixed": self.fixed(),
                "result": self.result(), "events_read": self.events_read}


def _append(points: list, item) -> None:
    points.append(item)
    if len(points) > _MAX_POINTS:
        del points[: len(points) - _MAX_POINTS]


class LiveViewServer:
    """The page, ``/api/state`` and the record's images, on ``host:port`` (0: a free port), in daemon threads.

    ``on_stop`` runs (once) on ``POST /api/stop``; None: the page has no Stop. ``folder`` may come later
    (:meth:`follow`): the port is taken first, so a taken port is refused before a record is made."""

    def __init__(self, folder: str | Path | None, host: str = "127.0.0.1", port: int = 0,
                 on_stop: Callable[[], None] | None = None, poll_s: float = 0.25):
        self.tail = RecordTail(folder) if folder is not None else None
        self.parent: Path | None = None  # follow_newest: the newest record under it
        self.key = secrets.token_urlsafe(16)
        self.on_stop = on_stop
        self.poll_s = poll_s
        self.stop_requested = threading.Event()
        self.polled = False  # a page asked for the state at least once
        self._lock = threading.Lock()
        try:
            self.httpd = ThreadingHTTPServer((host, port), _handler(self))
        except OSError as exc:
            raise LiveViewError(f"the live view cannot listen on {host}:{port}: {exc.strerror or exc} "
                                f"(another port: --view-port, 0 for any)") from None
        self.httpd.daemon_threads = True
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        """The page's address, with this run's key."""
        host, port = self.httpd.server_address[:2]
        host = host.decode() if isinstance(host, bytes) else host
        return f"http://{host}:{port}/?key={self.key}"

    def follow(self, folder: str | Path) -> LiveViewServer:
        """Follow the record folder ``folder`` (before :meth:`start`); return self."""
        self.tail = RecordTail(folder)
        return self

    def follow_newest(self, parent: str | Path) -> LiveViewServer:
        """Follow whichever record folder under ``parent`` was written to last (a trials sweep's ``trials/``:
        each trial in turn, the newest of those running in parallel); return self."""
        self.parent = Path(parent)
        self.tail = RecordTail(self.parent / "(waiting for the first trial)")
        return self

    def _newest(self) -> None:
        """Switch :attr:`tail` to the record under :attr:`parent` whose event log changed last."""
        if self.parent is None:
            return
        try:
            logs = [(p.stat().st_mtime, p.parent) for p in self.parent.glob(f"*/{EVENTS}")]
        except OSError:
            return
        if logs:
            folder = max(logs)[1]
            if self.tail is None or folder != self.tail.folder:
                self.tail = RecordTail(folder)

    def start(self) -> LiveViewServer:
        """Serve in a daemon thread (a folder to follow must be set); return self."""
        if self.tail is None:
            raise LiveViewError("the live view has no record folder to follow")
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="labctl-live-view", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving and release the port; a page that was polling gets two more polls first, so it
        shows how the run ended."""
        if self.polled:
            time.sleep(2 * self.poll_s)
        if self._thread is not None:
            self.httpd.shutdown()
            self._thread.join(timeout=2)
        self.httpd.server_close()

    def state(self) -> dict:
        """The state the page polls (one reader at a time: the tail is not thread-safe)."""
        assert self.tail is not None  # start() checked
        with self._lock:
            if self.parent is not None:
                self._newest()
            out = self.tail.snapshot()
            self.polled = True
        out["stop"] = {"available": self.on_stop is not None, "requested": self.stop_requested.is_set()}
        out["poll_s"] = self.poll_s
        return out

    def stop(self) -> bool:
        """Request the run's stop (once); False if it had been requested already or there is no stop."""
        if self.on_stop is None or self.stop_requested.is_set():
            return False
        self.stop_requested.set()
        self.on_stop()
        return True

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()


def _handler(view: LiveViewServer):
    class Handler(BaseHTTPRequestHandler):
        """One request to the live view."""

        server_version = "labctl-live-view"

        def log_message(self, *args):  # the run's terminal is not the place for access logs
            pass

        def _authorised(self, query: dict) -> bool:
            key = self.headers.get("X-Labctl-Key") or (query.get("key") or [""])[0]
            if secrets.compare_digest(key, view.key):
                return True
            self._send(HTTPStatus.FORBIDDEN, b"this page needs the key printed with its URL\n", "text/plain")
            return False

        def _send(self, status, body: bytes, ctype: str) -> None:
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def _json(self, obj) -> None:
            self._send(HTTPStatus.OK, json.dumps(obj, allow_nan=False).encode(), "application/json")

        def do_GET(self):  # noqa: N802 — http.server's name
            """The page, the state or an image."""
            url = urlsplit(self.path)
            query = parse_qs(url.query)
            if not self._authorised(query):
                return
            if url.path == "/":
                self._send(HTTPStatus.OK, page_html().encode(), "text/html; charset=utf-8")
            elif url.path == "/api/state":
                self._json(view.state())
            elif url.path.startswith("/img/") and view.tail is not None:
                name = url.path[len("/img/"):]
                if name == "live/fixed.jpg":
                    path, ctype = view.tail.folder / LIVE_DIR / "fixed.jpg", "image/jpeg"
                elif _IMAGE.match(name):
                    path, ctype = view.tail.folder / name, "image/png"
                else:
                    self._send(HTTPStatus.NOT_FOUND, b"no such image\n", "text/plain")
                    return
                try:
                    body = path.read_bytes()
                except OSError:
                    self._send(HTTPStatus.NOT_FOUND, b"not written yet\n", "text/plain")
                    return
                self._send(HTTPStatus.OK, body, ctype)
            else:
                self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain")

        def do_POST(self):  # noqa: N802
            """``/api/stop``: the run's stop, as Ctrl-C."""
            url = urlsplit(self.path)
            if not self._authorised(parse_qs(url.query)):
                return
            if url.path != "/api/stop":
                self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain")
                return
            if view.on_stop is None:
                self._send(HTTPStatus.CONFLICT, b"this view has no stop\n", "text/plain")
                return
            self._json({"stopping": True, "first": view.stop()})

    return Handler


def page_html() -> str:
    """The live view's page (``liveview.html`` beside this module): inline CSS and JS, no build step."""
    return (Path(__file__).with_name("liveview.html")).read_text(encoding="utf-8")
