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
* ``result.json``    — shown as the summary (identity, true identity, correct, times, stages).

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
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.artist import Artist

from ..fsutil import atomic_write_bytes, atomic_write_text
from .events import spec
from .record import RunData, load_run

__all__ = ["write_report", "render_figure", "failure_reason", "SECTIONS"]

SECTIONS = ("summary", "paths", "markers", "standard", "scores", "events")
NOT_REACHED = "not reached"
_STD = re.compile(r"^standard_(\d+)$")
TRACK, PREDICT, ROBOT, MARKER_POSE, MATCH = (spec(n) for n in ("track", "predict", "robot", "marker_pose", "match"))
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
        return "the run did not finish (no result.json)" + (f"; last event: {last}" if last else "; no events")
    if res.get("identity") is not None:
        return None
    return str(res.get("failure") or "no identity (the record gives no reason)")


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


def render_figure(run: RunData):
    """Draw the report figure (matplotlib ``Figure`` on the Agg canvas; no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Ellipse

    views = _standard_views(run)
    n_std = max(1, min(len(views), 4))
    ncols = max(3, 2 + n_std)
    fig = Figure(figsize=(4.2 * ncols, 8.4), layout="constrained")
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(2, ncols)

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
    if not scores:
        _not_reached(ax, "Match scores")
    else:
        names = sorted(scores, key=lambda n: scores[n])  # best (lowest) first, drawn at the top
        ident = _identity_name(run) or names[0]
        colors = ["tab:red" if n == ident else "0.6" for n in names]
        ax.barh(names[::-1], [scores[n] for n in names][::-1], color=colors[::-1])
        view = MATCH.get(ev, "view") if ev else None
        ax.set_title("Match scores" + (f" (view {view})" if view is not None else ""))
        ax.set_xlabel("silhouette mismatch (lower is better)")

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
    title = f"Run {run.meta.get('run_id', run.path.name)}"
    reason = failure_reason(run)
    if reason is not None:  # a failed run's figure leads with why, above its "not reached" panels
        import textwrap

        lines = textwrap.wrap(_clip(reason, 300), width=int(7.5 * 4.2 * ncols))  # ~7.5 characters per inch at 13 pt
        fig.suptitle("\n".join([f"{title}: FAILED"] + lines), color="tab:red", fontsize=13, fontweight="bold")
    else:
        fig.suptitle(title)
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


def _html(run: RunData, png: bytes) -> str:
    parts = []
    reason = failure_reason(run)
    if reason is not None:  # before the figure and every panel: why the run failed
        parts.append(f'<section id="failure"><h2>Run failed</h2><p class="failure">{html.escape(reason)}</p>'
                     "</section>\n")
    summary = _kv_table(run.result) if run.result is not None else _nr("not reached: the run did not finish "
                                                                       "(no result.json)")
    parts.append(_section("summary", "Result", summary + "<h3>Run</h3>" + _kv_table(run.meta)))

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
    for e in run.of(MATCH.name):
        s = MATCH.get(e, "scores")
        valid = {str(k): float(v) for k, v in s.items() if _finite([v])} if isinstance(s, dict) else {}
        if valid:
            view = MATCH.get(e, "view")
            label = f"view {view}" if view is not None else "match"
            body += f"<h3>{html.escape(label)}</h3>" + _kv_table(dict(sorted(valid.items(), key=lambda kv: kv[1])))
    body = ("<p>Silhouette mismatch per object, best first: lower is better.</p>" + body) if body else _nr()
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
    title = html.escape(f"labctl run {run.meta.get('run_id', run.path.name)}")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<style>body{{font-family:sans-serif;max-width:1400px;margin:1em auto}}table{{border-collapse:collapse}}
th,td{{border:1px solid #ccc;padding:2px 8px;text-align:left}}.nr{{color:#888;font-style:italic}}
.failure{{color:#b00;font-weight:bold;font-size:1.2em}}
img{{max-width:100%}}</style></head><body>
<h1>{title}</h1>
{lead}<figure id="figure"><img alt="run report figure" src="data:image/png;base64,{img}"></figure>
{"".join(parts)}</body></html>
"""


def write_report(run_dir: Path | str, *, png: bool = True) -> Path:
    """Write ``report.html`` (figure embedded as base64; images linked relative) and, with ``png``,
    ``report.png`` into the record; return the HTML path. Works on unfinished runs."""
    run = load_run(run_dir)
    fig = render_figure(run)
    data = _png_bytes(fig)
    if png:
        atomic_write_bytes(run.path / "report.png", data)
    out = run.path / "report.html"
    atomic_write_text(out, _html(run, data))
    return out
