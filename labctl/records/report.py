"""A run's report: one figure (``report.png``) and a self-contained page (``report.html``).

What the report reads from the record, each through its declaration in
:mod:`labctl.records.events` (a name or a field the schema does not declare is an error, not a guess):

* events ``track``   — ``t`` (s), ``x``, ``y`` (mm, table plane in W): the Kalman estimate (paper §2);
* events ``predict`` — ``t``, ``path=[[x, y], ...]`` (mm): a predicted object path;
* events ``robot``   — ``t``, ``p=[x, y, z]`` (mm, W): the mobile camera / flange position;
* event  ``marker_pose`` — ``ellipses={"initial1": [cx, cy, a, b, theta], "initial2": [...]}``
  (pixels; a, b semi-axes; theta rad from the image x axis towards y), ``center_w``, ``normal_w``,
  ``resolved``, ``margin_deg`` (paper §3.2);
* event  ``match``   — ``scores={name: score}``, ``view`` (k) (paper §3.3);
* images ``initial1.png``, ``initial2.png``, ``standard_<k>.png``, ``silhouette_<k>.png``;
* events ``stage``   — ``t``, ``stage``: the stage timeline (the run's start is ``tracking_prior``'s ``t``);
* event  ``refuted`` — ``view``, ``candidates``, ``reason``: candidates a view dropped for a missing top marker;
* images ``fixed_last.png`` (a failed run's last fixed-camera frame) or ``live/fixed.jpg`` (the live view's);
* ``result.json``    — identity, true identity (the simulator's), correct, times, failure.

Why each library object fell out of a match is read from the ``match`` event: a finite score above the
answer's is "scored worse"; a null score is a gate, and an object missing from an earlier ambiguous
view's candidates was ruled out by that view. Which gate needs the library, which records do not
import: the CLI scores the recorded standard image again and passes ``gates`` (``{k: {object:
"height" | "shape"}}``, ``labctl.cli.report.match_gates``); without it the report says "gated out"
and names no gate.

A field of the wrong type (a record from an older or broken writer) reads as missing.
Anything missing is drawn and listed as "not reached", so a run that ended early still gets a
report of what happened up to the end.
"""

from __future__ import annotations

import base64
import html
import io
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.artist import Artist

from ..fsutil import atomic_write_bytes, atomic_write_text
from .events import spec
from .record import RunData, load_run

__all__ = ["write_report", "render_figure", "failure_reason", "explain", "timeline", "SECTIONS"]

SECTIONS = ("summary", "timeline", "paths", "markers", "standard", "scores", "events")
NOT_REACHED = "not reached"
_STD = re.compile(r"^standard_(\d+)$")
TRACK, PREDICT, ROBOT, MARKER_POSE, MATCH = (spec(n) for n in ("track", "predict", "robot", "marker_pose", "match"))
STAGE, FAILURE, PRIOR, REFUTED = (spec(n) for n in ("stage", "failure", "tracking_prior", "refuted"))
RESPONSE = spec("response_check")
FIXED_LAST = "fixed_last"  # a failed run's last fixed-camera frame (the runtimes save it)
MARKER_POSE_SHOWN = ("center_w", "normal_w", "resolved", "margin_deg")  # the pose's summary, in this order
for _k in MARKER_POSE_SHOWN:
    MARKER_POSE.declared(_k)


def _finite(vals) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) for v in vals)


def _track(run: RunData) -> np.ndarray:
    pts = []
    for e in run.of(TRACK.name):
        p = [TRACK.get(e, "t"), TRACK.get(e, "x"), TRACK.get(e, "y")]
        if _finite(p):
            pts.append(p)
    return np.array(pts, dtype=float).reshape(-1, 3)


def _predictions(run: RunData) -> list[np.ndarray]:
    out = []
    for e in run.of(PREDICT.name):
        try:
            path = np.asarray(PREDICT.get(e, "path"), dtype=float)
        except (TypeError, ValueError):
            continue
        if path.ndim == 2 and path.shape[1] >= 2 and len(path) >= 2 and np.all(np.isfinite(path[:, :2])):
            out.append(path[:, :2])
    return out


def _robot(run: RunData) -> np.ndarray:
    pts = []
    for e in run.of(ROBOT.name):
        p = ROBOT.get(e, "p")
        if isinstance(p, list) and len(p) == 3 and _finite(p):
            pts.append(p)
    return np.array(pts, dtype=float).reshape(-1, 3)


def _ellipses(run: RunData) -> dict[str, list[float]]:
    out: dict[str, list[float]] = {}
    for e in run.of(MARKER_POSE.name):
        ell = MARKER_POSE.get(e, "ellipses")
        if isinstance(ell, dict):
            for k, v in ell.items():
                if isinstance(v, list) and len(v) == 5 and _finite(v):
                    out[k] = v
    return out


def _standard_views(run: RunData) -> list[int]:
    return sorted(int(m.group(1)) for name in run.images if (m := _STD.match(name)))


def _last_scores(run: RunData) -> tuple[dict[str, float], dict | None]:
    for e in reversed(run.of(MATCH.name)):
        s = MATCH.get(e, "scores")
        if isinstance(s, dict):
            scores = {str(k): float(v) for k, v in s.items() if _finite([v])}
            if scores:
                return scores, e
    return {}, None


def _load_rgb(path: Path) -> np.ndarray | None:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        return None
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    elif img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img


def _show(ax, img: np.ndarray) -> None:
    """imshow without contrast stretching: grey levels as recorded."""
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    ax.imshow(img, cmap="gray" if img.ndim == 2 else None, vmin=0, vmax=255)


def _not_reached(ax, title: str, why: str = NOT_REACHED) -> None:
    ax.set_title(title)
    ax.text(0.5, 0.5, why, ha="center", va="center", transform=ax.transAxes, fontsize=12, color="0.45")
    ax.set_xticks([])
    ax.set_yticks([])


def _identity_name(run: RunData) -> str | None:
    ident = (run.result or {}).get("identity")
    return str(ident) if ident is not None else None


def failure_reason(run: RunData) -> str | None:
    """Why the run gave no identity, from the record (``result.json`` ``failure``, else the last event),
    or None for a run that identified its object."""
    res = run.result
    if res is None:
        last = run.events[-1].get("event") if run.events else None
        fails = run.of(FAILURE.name)
        why = FAILURE.valid(fails[-1], "reason") if fails else None
        return ("the run did not finish (no result.json)" + (f"; last event: {last}" if last else "; no events")
                + (f"; it failed: {why}" if why else ""))
    if res.get("identity") is not None:
        return None
    return str(res.get("failure") or "no identity (the record gives no reason)")


def verdict(run: RunData) -> str:
    """One line: what the run identified and whether that was right (the simulator's truth), or why it failed."""
    res = run.result or {}
    ident, truth = res.get("identity"), res.get("true_identity")
    reason = failure_reason(run)
    if reason is not None:
        fails = run.of(FAILURE.name)
        where = FAILURE.valid(fails[-1], "stage") if fails else None
        return ("FAILED" + (f" in stage {where}" if where else "") + ": " + _clip(reason, 160)
                + (f" (sim truth: {truth})" if truth is not None else ""))
    if truth is None:
        return f"identified {ident} (no ground truth: a real lab)"
    if res.get("correct", ident == truth):
        return f"identified {ident}: correct (sim truth: {truth})"
    return f"identified {ident}: WRONG (sim truth: {truth})"


@dataclass(frozen=True)
class Stage:
    """One stretch of the stage timeline: ``stage`` from ``t0`` to ``t1`` (s, the run's clock)."""

    stage: str
    t0: float
    t1: float
    clamped_s: float = 0.0  # how far t1 lay before t0 in the record (shown as a zero-length stretch)

    @property
    def duration_s(self) -> float:
        """Its length, s (never negative)."""
        return self.t1 - self.t0


def timeline(run: RunData) -> list[Stage]:
    """The stage timeline from the ``stage`` events, starting at the run's start (``tracking_prior``'s ``t``,
    the predictor's start, in ``wait``) and ending at ``done``/``failed`` (or the last stage event).

    A stage entered at a time before the previous one began is shown with zero length and says by how
    much (``clamped_s``): a live run's first frame can have been exposed up to a frame period before the
    predictor started its clock (the camera's latest frame is handed over as the loop begins); records
    written before the predictor counted such a frame from its start carry a negative ``wait``."""
    marks: list[tuple[str, float]] = []
    prior = run.of(PRIOR.name)
    if prior and _finite([PRIOR.get(prior[0], "t")]):
        marks.append(("wait", float(PRIOR.get(prior[0], "t"))))
    for e in run.of(STAGE.name):
        t, st = STAGE.valid(e, "t"), STAGE.valid(e, "stage")
        if t is not None and st is not None and _finite([t]):
            if marks and marks[-1][0] == st:
                continue  # the second initial image re-enters "initial": one stretch
            marks.append((str(st), float(t)))
    out: list[Stage] = []
    for (st, t0), (_, t1) in zip(marks, marks[1:], strict=False):
        start = out[-1].t1 if out else t0
        out.append(Stage(st, start, max(t1, start), max(0.0, start - t1)))
    return out


Gates = Mapping[int, Mapping[str, str]]


def explain(run: RunData, gates: Gates | None = None) -> list[dict]:
    """Each standard view's match, object by object, best first: ``{"view", "marker_height_mm",
    "height_tol_mm", "rows": [{"object", "score", "fate"}]}``; ``fate`` says why the object is or is not
    the answer (see the module docstring). ``gates``: for view k, the gate ("height" or "shape") that
    dropped each object with a null score."""
    res = run.result or {}
    out = []
    refuted: dict[int, tuple[list[str], str]] = {}
    for e in run.of(REFUTED.name):
        v, c, why = REFUTED.valid(e, "view"), REFUTED.valid(e, "candidates"), REFUTED.valid(e, "reason")
        if v is not None and c is not None:
            refuted[int(v)] = ([str(x) for x in c], str(why or "refuted"))
    previous: list[str] | None = None
    for e in run.of(MATCH.name):
        s = MATCH.valid(e, "scores")
        if s is None:
            continue
        view = MATCH.valid(e, "view")
        cands = [str(c) for c in (MATCH.valid(e, "candidates") or [])]
        best = MATCH.valid(e, "best")
        h, tol = MATCH.valid(e, "marker_height_mm"), MATCH.valid(e, "height_tol_mm")
        known = (gates or {}).get(int(view)) if view is not None else None
        dropped, why_refuted = refuted.get(int(view), ([], "")) if view is not None else ([], "")
        rows = []
        for name, score in s.items():
            name = str(name)
            finite = _finite([score])
            if name in dropped:
                fate = f"refuted: {why_refuted}"
            elif name == res.get("identity") and name in cands:
                fate = "the answer" if len(cands) == 1 else "the answer (" + ", ".join(cands) + " were close)"
            elif name in cands:
                fate = "a candidate: too close to the best to tell apart"
            elif finite:
                fate = "scored worse than " + (str(best) if best else "the threshold")
            elif previous is not None and name not in previous:
                fate = "ruled out by the previous view"
            elif known is None or name not in known:
                fate = "gated out (eccentricity, size" + (" or marker height" if h is not None else "") + \
                    "; run labctl report in the lab to tell which)"
            elif known[name] == "height":
                fate = (f"marker-height gate: no view whose silhouette fits rests its marker at the measured "
                        f"{h:.1f} ± {tol:.1f} mm" if h is not None and tol is not None else "marker-height gate")
            else:
                fate = "shape gate: eccentricity or size too far from the silhouette's"
            rows.append({"object": name, "score": float(score) if finite else None, "fate": fate})
        rows.sort(key=lambda r: (r["score"] is None, r["score"] if r["score"] is not None else 0.0, r["object"]))
        out.append({"view": view, "marker_height_mm": h, "height_tol_mm": tol, "rows": rows})
        previous = cands if len(cands) > 1 else None
    return out


def _draw_paths(ax, track: np.ndarray, preds: list[np.ndarray], robot: np.ndarray, legend: bool) -> None:
    """The object's tracked and predicted paths and the robot's x-y path on ``ax`` (mm, table plane W).
    The last prediction is drawn over the track (they coincide on a straight path) with its end, the
    predicted interception point, marked."""
    for i, p in enumerate(preds):
        last = i == len(preds) - 1
        ax.plot(p[:, 0], p[:, 1], "--", color="tab:orange", alpha=1.0 if last else 0.3, lw=2.0 if last else 0.8,
                zorder=4 if last else 2, label="predicted" if last else None)
    if preds:
        ax.plot(preds[-1][-1, 0], preds[-1][-1, 1], "x", color="tab:orange", ms=9, mew=2, zorder=5,
                label="predicted end")
    if len(track):
        ax.plot(track[:, 1], track[:, 2], ".-", color="tab:blue", ms=3, lw=1, zorder=3, label="tracked (KF)")
    if len(robot):
        ax.plot(robot[:, 0], robot[:, 1], "-", color="tab:green", zorder=1, label="robot (x-y)")
        ax.plot(robot[-1, 0], robot[-1, 1], "o", color="tab:green", zorder=1)
    ax.grid(True, alpha=0.3)
    if legend:
        ax.legend(loc="best", fontsize=8)


def _fixed_frame(run: RunData) -> np.ndarray | None:
    """The last fixed-camera frame the record holds: ``fixed_last.png`` (saved on a failure), else the
    live view's ``live/fixed.jpg``; None if neither."""
    if FIXED_LAST in run.images:
        return _load_rgb(run.images[FIXED_LAST])
    live = run.path / "live" / "fixed.jpg"
    return _load_rgb(live) if live.is_file() else None


def _draw_timeline(ax, stages: list[Stage]) -> None:
    """The stage timeline as bars on one line (s, the run's clock from its start)."""
    ax.set_title("Stage timeline")
    if not stages:
        ax.text(0.5, 0.5, NOT_REACHED, ha="center", va="center", transform=ax.transAxes, color="0.45")
        ax.set_yticks([])
        return
    t0 = stages[0].t0
    colors = {"wait": "0.75", "track": "tab:blue", "intercept": "tab:orange", "initial": "tab:purple",
              "standard": "tab:green", "match": "tab:olive", "failed": "tab:red"}
    for st in stages:
        ax.broken_barh([(st.t0 - t0, st.duration_s)], (0, 1), color=colors.get(st.stage, "0.5"))
        ax.text(st.t0 - t0 + st.duration_s / 2, 0.5, f"{st.stage}\n{st.duration_s:.2f} s", ha="center",
                va="center", fontsize=8)
    ax.set_xlim(0, max(stages[-1].t1 - t0, 1e-3))
    ax.set_yticks([])
    ax.set_xlabel("time since the run's start (s)")


def _draw_scores(ax, rows: list[dict], view, ident: str | None) -> None:
    """Scored objects as bars (best at the top) and the gated ones as named rows saying which gate."""
    n = len(rows)
    ys = np.arange(n)[::-1]
    scored = [(y, r) for y, r in zip(ys, rows, strict=True) if r["score"] is not None]
    ax.barh([y for y, _ in scored], [r["score"] for _, r in scored],
            color=["tab:red" if r["object"] == ident else "0.6" for _, r in scored])
    top = max((r["score"] for _, r in scored), default=1.0) or 1.0
    for y, r in zip(ys, rows, strict=True):
        if r["score"] is None:
            short = r["fate"].split(":")[0].split(" (")[0]  # the gate's name; its numbers are in the HTML table
            ax.text(0.02 * top, y, f"no score: {short}", va="center", fontsize=8, color="0.3")
    ax.set_yticks(ys, [r["object"] for r in rows])
    ax.set_ylim(-0.7, n - 0.3)  # the last row's label clear of the axis
    ax.set_xlim(0, 1.15 * top)
    ax.set_title("Match scores" + (f" (view {view})" if view is not None else ""))
    ax.set_xlabel("silhouette mismatch (lower is better)")


def render_figure(run: RunData, gates: Gates | None = None):
    """Draw the report figure (matplotlib ``Figure`` on the Agg canvas; no pyplot state). Its title is
    :func:`verdict`; a run that failed before any mobile image leads with its cause and the last
    fixed-camera frame, not with empty panels."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Ellipse

    views = _standard_views(run)
    reason = failure_reason(run)
    title = f"Run {run.meta.get('run_id', run.path.name)}: {verdict(run)}"
    if reason is not None and not views and not any(n in run.images for n in ("initial1", "initial2")):
        return _failed_figure(run, reason, title)
    n_std = max(1, min(len(views), 4))
    ncols = max(3, 2 + n_std)
    fig = Figure(figsize=(4.2 * ncols, 10.0), layout="constrained")
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(3, ncols, height_ratios=[1, 1, 0.28])
    _draw_timeline(fig.add_subplot(gs[2, :]), timeline(run))

    # paths on the table plane, in two panels whose axes fit their data: everything (robot and object),
    # and the object up close (its tracked and predicted paths are a stub next to the robot's travel)
    track, preds, robot = _track(run), _predictions(run), _robot(run)
    obj = np.vstack([track[:, 1:3]] + preds) if len(track) or preds else np.empty((0, 2))
    ax = fig.add_subplot(gs[0, 0])
    if len(obj) == 0 and len(robot) == 0:
        _not_reached(ax, "Robot and object paths")
    else:
        _draw_paths(ax, track, preds, robot, legend=False)
        ax.margins(0.06)  # limits from the data drawn, equal scale in x and y
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title("Robot and object paths (table plane, W)")
    ax = fig.add_subplot(gs[0, 1: ncols - 1])
    if len(obj) == 0:
        _not_reached(ax, "Tracked and predicted object path")
    else:
        _draw_paths(ax, track, preds, np.empty((0, 3)), legend=False)
        ax.margins(0.06)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (mm)")
        ax.set_title("Tracked and predicted object path, up close (W)")
    handles: dict[str, Artist] = {}
    for a_ in fig.axes:
        for h, lab in zip(*a_.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    if handles:
        ax.legend(handles.values(), handles.keys(), loc="best", fontsize=8)

    # match scores
    ax = fig.add_subplot(gs[0, ncols - 1])
    scores, ev = _last_scores(run)
    matches = [m_ for m_ in explain(run, gates) if any(r["score"] is not None for r in m_["rows"])]
    if not scores or not matches:
        _not_reached(ax, "Match scores")
    else:
        last = matches[-1]
        _draw_scores(ax, last["rows"], last["view"], _identity_name(run) or last["rows"][0]["object"])

    # the two marker images with their ellipses
    ellipses = _ellipses(run)
    for col, name in enumerate(("initial1", "initial2")):
        ax = fig.add_subplot(gs[1, col])
        img = _load_rgb(run.images[name]) if name in run.images else None
        if img is None:
            _not_reached(ax, f"Marker image {name}")
            continue
        _show(ax, img)
        ax.set_title(f"Marker image {name}")
        ax.set_xticks([])
        ax.set_yticks([])
        if name in ellipses:
            cx, cy, a, b, th = ellipses[name]
            ax.add_patch(Ellipse((cx, cy), 2 * a, 2 * b, angle=math.degrees(th), fill=False, color="cyan", lw=1.5))
            ax.plot([cx], [cy], "+", color="cyan")
        else:
            ax.text(0.02, 0.02, "ellipse not recorded", transform=ax.transAxes, color="yellow", fontsize=8)

    # standard view(s) with the silhouette outline
    shown = views[-n_std:] if views else [None]
    for j, k in enumerate(shown):
        ax = fig.add_subplot(gs[1, 2 + j])
        if k is None:
            _not_reached(ax, "Standard view")
            continue
        img = _load_rgb(run.images[f"standard_{k}"])
        if img is None:
            _not_reached(ax, f"Standard view {k}", "image unreadable")
            continue
        _show(ax, img)
        ax.set_xticks([])
        ax.set_yticks([])
        sil = run.images.get(f"silhouette_{k}")
        mask = _load_rgb(sil) if sil is not None else None
        if mask is not None:
            m = mask if mask.ndim == 2 else mask[..., 0]
            if m.shape == img.shape[:2] and m.max() > 0:
                ax.contour(m > 0, levels=[0.5], colors="lime", linewidths=1.2)
            ax.set_title(f"Standard view {k} with silhouette")
        else:
            ax.set_title(f"Standard view {k} (silhouette not recorded)")
    _suptitle(fig, title, reason, 4.2 * ncols)
    return fig


def _suptitle(fig, title: str, reason: str | None, width_in: float) -> None:
    """The verdict as the figure's title; a failure's whole cause below it, in red."""
    import textwrap

    if reason is None:
        ok = "WRONG" not in title
        fig.suptitle(title, fontsize=14, fontweight="bold", color="tab:green" if ok else "tab:red")
        return
    lines = textwrap.wrap(_clip(reason, 300), width=int(7.5 * width_in))  # ~7.5 characters per inch at 13 pt
    head = title.split(": ", 1)[0] + ": " + title.split(": ", 1)[1].split(": ", 1)[0]  # "Run X: FAILED in stage S"
    if (truth := title.rpartition("(sim truth: ")[2]) and truth != title:
        head += " (sim truth: " + truth
    fig.suptitle("\n".join([head] + lines), color="tab:red", fontsize=13, fontweight="bold")


def _failed_figure(run: RunData, reason: str, title: str):
    """A run that failed before any mobile image: the cause (title), the last fixed-camera frame, the paths
    so far and the stage timeline."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12.6, 7.0), layout="constrained")
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(2, 2, height_ratios=[1, 0.3])
    ax = fig.add_subplot(gs[0, 0])
    frame = _fixed_frame(run)
    if frame is None:
        _not_reached(ax, "Fixed camera, last frame", "no fixed-camera frame in the record")
    else:
        _show(ax, frame)
        ax.set_title("Fixed camera, last frame")
        ax.set_xticks([])
        ax.set_yticks([])
    ax = fig.add_subplot(gs[0, 1])
    track, preds, robot = _track(run), _predictions(run), _robot(run)
    if not len(track) and not preds and not len(robot):
        _not_reached(ax, "Robot and object paths", "the object was never tracked")
    else:
        _draw_paths(ax, track, preds, robot, legend=True)
        ax.margins(0.06)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title("Robot and object paths (table plane, W)")
    _draw_timeline(fig.add_subplot(gs[1, :]), timeline(run))
    _suptitle(fig, title, reason, 12.6)
    return fig


def _clip(text: str, n: int) -> str:
    return text if len(text) <= n else text[: n - 1] + "…"


def _png_bytes(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    return buf.getvalue()


def _kv_table(d: dict) -> str:
    rows = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(_fmt(v))}</td></tr>" for k, v in d.items())
    return f"<table>{rows}</table>"


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items())
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


def _section(sid: str, title: str, body: str) -> str:
    return f'<section id="{sid}"><h2>{html.escape(title)}</h2>{body}</section>\n'


def _nr(what: str = NOT_REACHED) -> str:
    return f'<p class="nr">{html.escape(what)}</p>'


def response_line(run: RunData) -> str | None:
    """The camera response in one line, from the run's ``response_check`` events (None when there are none:
    the mobile camera's response was declared and no marker leaned as another response's would)."""
    checks = run.of(RESPONSE.name)
    if not checks:
        return None
    seen = sum(int(RESPONSE.valid(e, "markers") or 0) for e in checks)
    bad = sum(int(RESPONSE.valid(e, "mismatched") or 0) for e in checks)
    refused = sum(int(RESPONSE.valid(e, "refused") or 0) for e in checks)
    undeclared = any(RESPONSE.valid(e, "declared") is False for e in checks)
    parts = []
    if bad:
        parts.append(f"{bad} of {seen} markers in {len(checks)} images look encoded with another response than the "
                     "mobile camera's driver file says")
    if undeclared:
        parts.append(f"the response is undeclared, so pose was conservative ({refused} of {seen} markers refused)")
    return "camera response: " + "; ".join(parts) + " — run `labctl vision learn-response`"


def _summary(run: RunData) -> str:
    """The result in words: the verdict, time to identity against its bound, views, where it failed."""
    res = run.result
    if res is None:
        return _nr("not reached: the run did not finish (no result.json)")
    esc = html.escape
    items = [f"<li><b>{esc(verdict(run))}</b></li>"]
    tti, bound = res.get("time_to_identity_s"), res.get("lower_bound_s")
    if _finite([tti]):
        line = f"time to identity {tti:.2f} s"
        if _finite([bound]) and bound:
            line += (f", {tti / bound:.2f}× the lower bound of {bound:.2f} s (first sight + the minimum-time legs "
                     "flown + frame times: no run can be faster)")
        items.append(f"<li>{esc(line)}</li>")
    if res.get("views") is not None:
        items.append(f"<li>standard views matched: {esc(str(res.get('views')))}</li>")
    fails = run.of(FAILURE.name)
    if fails and FAILURE.valid(fails[-1], "stage"):
        items.append(f"<li>failed in stage {esc(str(FAILURE.valid(fails[-1], 'stage')))}</li>")
    if (said := response_line(run)) is not None:
        items.append(f"<li>{esc(said)}</li>")
    fields = _kv_table({k: v for k, v in res.items() if k not in ("stages",)})
    return (f"<ul>{''.join(items)}</ul><details><summary>every result field (result.json)</summary>{fields}"
            f"<h3>Run</h3>{_kv_table(run.meta)}</details>")


def _timeline_html(run: RunData) -> str:
    stages = timeline(run)
    if not stages:
        return _nr()
    t0 = stages[0].t0
    rows = "".join(f"<tr><td>{html.escape(st.stage)}</td><td>{st.t0 - t0:.3f}</td><td>{st.t1 - t0:.3f}</td>"
                   f"<td>{st.duration_s:.3f}</td></tr>" for st in stages)
    notes = [f"<p class=\"note\">{html.escape(st.stage)} is shown as 0 s: the record has it end "
             f"{1000 * st.clamped_s:.1f} ms before it began (a live run's first frame, exposed before the "
             "predictor started its clock)</p>" for st in stages if st.clamped_s > 0]
    return ("<table><tr><th>stage</th><th>from (s)</th><th>to (s)</th><th>duration (s)</th></tr>"
            f"{rows}</table>" + "".join(notes))


def _html(run: RunData, png: bytes, gates: Gates | None = None) -> str:
    parts = []
    reason = failure_reason(run)
    if reason is not None:  # before the figure and every panel: why the run failed
        parts.append(f'<section id="failure"><h2>Run failed</h2><p class="failure">{html.escape(reason)}</p>'
                     "</section>\n")
    parts.append(_section("summary", "Result", _summary(run)))
    parts.append(_section("timeline", "Stage timeline", _timeline_html(run)))

    track, preds, robot = _track(run), _predictions(run), _robot(run)
    if len(track) or preds or len(robot):
        body = (f"<p>{len(track)} tracked points, {len(preds)} predictions, {len(robot)} robot samples.</p>")
    else:
        body = _nr()
    parts.append(_section("paths", "Tracked, predicted and robot paths", body))

    ellipses = _ellipses(run)
    rows = []
    for name in ("initial1", "initial2"):
        if name not in run.images:
            rows.append(f"<li>{name}: {NOT_REACHED}</li>")
        else:
            ell = ellipses.get(name)
            rows.append(f"<li>{name}: <a href=\"{name}.png\">{name}.png</a>; ellipse "
                        f"{html.escape(_fmt(ell)) if ell else 'not recorded'}</li>")
    poses = run.of(MARKER_POSE.name)
    if poses:
        shown = {k: v for k in MARKER_POSE_SHOWN if (v := MARKER_POSE.valid(poses[-1], k)) is not None}
        rows.append(f"<li>marker pose: {html.escape(_fmt(shown))}</li>")
    else:
        rows.append(f"<li>marker pose: {NOT_REACHED}</li>")
    parts.append(_section("markers", "Marker images and ellipses", "<ul>" + "".join(rows) + "</ul>"))

    views = _standard_views(run)
    if views:
        body = "<ul>" + "".join(
            f'<li>view {k}: <a href="standard_{k}.png">standard_{k}.png</a>, '
            + (f'<a href="silhouette_{k}.png">silhouette_{k}.png</a>' if f"silhouette_{k}" in run.images
               else "silhouette not recorded") + "</li>" for k in views) + "</ul>"
    else:
        body = _nr()
    parts.append(_section("standard", "Standard view and silhouette", body))

    body = ""
    for mv in explain(run, gates):
        if not any(r["score"] is not None for r in mv["rows"]):
            continue
        label = f"view {mv['view']}" if mv["view"] is not None else "match"
        if mv["marker_height_mm"] is not None:
            label += f" (marker measured {mv['marker_height_mm']:.1f} mm above the table)"
        table = "".join(f"<tr><th>{html.escape(r['object'])}</th>"
                        f"<td>{'—' if r['score'] is None else format(r['score'], '.4g')}</td>"
                        f"<td>{html.escape(r['fate'])}</td></tr>" for r in mv["rows"])
        body += (f"<h3>{html.escape(label)}</h3><table><tr><th>object</th><th>mismatch</th><th>why</th></tr>"
                 f"{table}</table>")
    body = ("<p>Silhouette mismatch per object, best first: lower is better; an object with no score was "
            "dropped by a gate before its silhouette was compared, and the row says which.</p>" + body) \
        if body else _nr()
    parts.append(_section("scores", "Match scores", body))

    counts: dict[str, int] = {}
    for e in run.events:
        counts[str(e.get("event"))] = counts.get(str(e.get("event")), 0) + 1
    last_event = run.events[-1].get("event") if run.events else None
    body = _kv_table(counts) + (f"<p>Last event: {html.escape(str(last_event))}</p>" if last_event
                                else _nr("no events"))
    parts.append(_section("events", "Event log", body))

    lead = parts.pop(0) if reason is not None else ""
    img = base64.b64encode(png).decode("ascii")
    title = html.escape(f"labctl run {run.meta.get('run_id', run.path.name)}: {verdict(run)}")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<style>body{{font-family:sans-serif;max-width:1400px;margin:1em auto}}table{{border-collapse:collapse}}
th,td{{border:1px solid #ccc;padding:2px 8px;text-align:left}}.nr{{color:#888;font-style:italic}}
.failure{{color:#b00;font-weight:bold;font-size:1.2em}}.note{{color:#555;font-size:.9em}}
img{{max-width:100%}}</style></head><body>
<h1>{title}</h1>
{lead}<figure id="figure"><img alt="run report figure" src="data:image/png;base64,{img}"></figure>
{"".join(parts)}</body></html>
"""


def write_report(run_dir: Path | str, *, png: bool = True,
                 gates: Gates | None = None) -> Path:
    """Write ``report.html`` (figure embedded as base64; images linked relative) and, with ``png``,
    ``report.png`` into the record; return the HTML path. Works on unfinished runs. ``gates``: which gate
    dropped each unscored object (:func:`explain`), to name it."""
    run = load_run(run_dir)
    fig = render_figure(run, gates)
    data = _png_bytes(fig)
    if png:
        atomic_write_bytes(run.path / "report.png", data)
    out = run.path / "report.html"
    atomic_write_text(out, _html(run, data, gates))
    return out
