"""A trials sweep's report: ``report.png`` and a self-contained ``report.html`` in the sweep folder.

Reads the summary (``labctl.experiments.trials.summarize``: every trial's result under ``trials``) and
the sweep's ``spec.json`` (date, lab, library hash, seeds). It shows:

* when, which lab and library (its SHA-256), which trajectories, speeds and seeds;
* success with a Wilson 95 % interval (Wilson 1927: the binomial score interval, which stays inside
  [0, 1] and is honest at 0 or n successes out of n, where the normal approximation collapses to a
  point), overall, per speed and trajectory, and per object;
* every trial as a point: success against speed, time to identity against speed and against its
  lower bound;
* the confusion matrix (true object against the answer, "none" for no answer);
* the failures grouped by cause (numbers in the reason folded), each linked to its record;
* the two bounds in words (:data:`BOUND_TEXT`, :data:`QUINTIC_TEXT`).
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
import os
import re
import statistics
from collections import Counter, defaultdict
from pathlib import Path

from ..fsutil import atomic_write_bytes, atomic_write_text

__all__ = ["write_sweep_report", "render_sweep_figure", "sweep_figure", "wilson_interval", "failure_cause", "confusion",
           "BOUND_TEXT", "QUINTIC_TEXT"]

Z95 = 1.959963984540054  # the standard normal's 97.5 % quantile: a two-sided 95 % interval
NONE = "none"  # the confusion matrix's column for a trial with no answer

BOUND_TEXT = ("× lower bound: the time to identity over the honest lower bound of that trial (first sight of "
              "the object + the minimum time of each leg the robot flew, planned with the same speed, "
              "acceleration and jerk limits + one frame time per image). No run can beat it, so the ratio "
              "is at least 1; 1.25 means a quarter more than the physics allows.")
QUINTIC_TEXT = ("× quintic bound: the same, over the paper's bound (first sight + the time-optimal "
                "rest-to-rest quintic of each leg + frame times). It is no lower bound for this robot: the "
                "quintic's speed and acceleration peak for an instant only, while the jerk-limited profiles "
                "the run flies hold them, and a re-planned leg need not start or end at rest, so a run can be "
                "faster than it and the ratio can be below 1.")


def wilson_interval(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval (lower, upper) of a success rate of ``k`` out of ``n`` (95 % by default);
    (0, 1) for n = 0."""
    if n <= 0:
        return 0.0, 1.0
    p = k / n
    d = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / d
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    # at k = 0 and k = n the bound is exactly 0 and 1 (the formula gives them only to rounding)
    return (0.0 if k == 0 else max(0.0, centre - half)), (1.0 if k == n else min(1.0, centre + half))


def failure_cause(result: dict) -> str:
    """The cause of a failed trial, with its numbers folded (``#``) so alike failures group together; a
    wrong answer is "identified the wrong object"."""
    if result.get("identity") is not None:
        return "identified the wrong object"
    text = str(result.get("failure") or "no identity (no reason recorded)")
    return re.sub(r"-?\d+(?:\.\d+)?", "#", text)


def confusion(trials: list[dict]) -> tuple[list[str], list[str], dict[tuple[str, str], int]]:
    """(true objects, answers with "none" last, counts by (true, answer)) over ``trials``."""
    counts: Counter = Counter()
    for r in trials:
        counts[(str(r.get("true_identity")), str(r["identity"]) if r.get("identity") is not None else NONE)] += 1
    rows = sorted({t for t, _ in counts})
    cols = sorted({a for _, a in counts if a != NONE} | set(rows))
    if any(a == NONE for _, a in counts):
        cols.append(NONE)
    return rows, cols, dict(counts)


def _rate(rs: list[dict]) -> tuple[int, int, float, float]:
    k = sum(bool(r.get("correct")) for r in rs)
    lo, hi = wilson_interval(k, len(rs))
    return k, len(rs), lo, hi


def _pct(k: int, n: int, lo: float, hi: float) -> str:
    return f"{100 * k / n:.1f} % ({k}/{n}; 95 % CI {100 * lo:.1f}–{100 * hi:.1f} %)" if n else "-"


def render_sweep_figure(summary: dict) -> bytes:
    """The sweep figure as PNG bytes."""
    buf = io.BytesIO()
    sweep_figure(summary).savefig(buf, format="png", dpi=80)
    return buf.getvalue()


def sweep_figure(summary: dict):
    """The sweep figure (matplotlib ``Figure`` on the Agg canvas; no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    trials = summary.get("trials", [])
    fig = Figure(figsize=(15, 8.4), layout="constrained")
    FigureCanvasAgg(fig)
    (ax1, ax2, ax3), (ax4, ax5, ax6) = fig.subplots(2, 3)
    trajs = sorted({str(r.get("trajectory")) for r in trials})
    speeds = sorted({r["speed_mm_s"] for r in trials})
    width = (max(speeds) - min(speeds)) if len(speeds) > 1 else 2.0
    for j, tr in enumerate(trajs):
        rs = [r for r in trials if str(r.get("trajectory")) == tr]
        dx = (j - (len(trajs) - 1) / 2) * 0.012 * width  # trajectories side by side at each speed
        xs, ys, lo, hi = [], [], [], []
        for v in speeds:
            k, n, a, b = _rate([r for r in rs if r["speed_mm_s"] == v])
            if n:
                xs.append(v + dx)
                ys.append(100 * k / n)
                lo.append(max(0.0, 100 * (k / n - a)))  # never below 0: matplotlib refuses a negative bar
                hi.append(max(0.0, 100 * (b - k / n)))
        line = ax1.errorbar(xs, ys, yerr=[lo, hi], fmt="o-", capsize=3, label=tr)
        # every trial: 100 (correct) or 0, jittered so that none hides another
        for i, r in enumerate(rs):
            jit = ((i * 0.618) % 1 - 0.5) * 0.03 * width
            ax1.plot(r["speed_mm_s"] + dx + jit, 100.0 if r.get("correct") else 0.0, ".", ms=3, alpha=0.5,
                     color=line[0].get_color())
    ax1.set(xlabel="table speed (mm/s)", ylabel="success (%)", ylim=(-5, 105),
            title="success against speed (95 % Wilson interval; dots: trials)")
    if len(speeds) == 1:
        ax1.set_xlim(speeds[0] - 1, speeds[0] + 1)
    if trajs:
        ax1.legend(fontsize=8, loc="lower left")

    ok = [r for r in trials if r.get("correct") and r.get("time_to_identity_s") is not None]
    for tr in trajs:
        rs = [r for r in ok if str(r.get("trajectory")) == tr]
        ax2.plot([r["speed_mm_s"] for r in rs], [r["time_to_identity_s"] for r in rs], "o", ms=4, alpha=0.6,
                 label=tr)
    ax2.set(xlabel="table speed (mm/s)", ylabel="time to identity (s)",
            title=f"time to identity, every correct trial (n = {len(ok)})")
    if len(speeds) == 1:
        ax2.set_xlim(speeds[0] - 1, speeds[0] + 1)

    lb = [(r["lower_bound_s"], r["time_to_identity_s"]) for r in ok if r.get("lower_bound_s")]
    if lb:
        ax3.plot([a for a, _ in lb], [b for _, b in lb], "o", ms=4, alpha=0.6)
        top = max(max(a, b) for a, b in lb) * 1.05
        ax3.plot([0, top], [0, top], "k--", lw=1, label="= bound (no run below)")
        ax3.legend(fontsize=8, loc="upper left")
    ax3.set(xlabel="lower bound of the trial (s)", ylabel="time to identity (s)",
            title="time to identity against its lower bound")

    rows, cols, counts = confusion(trials)
    if rows:
        import numpy as np

        mat = np.array([[counts.get((t, a), 0) for a in cols] for t in rows])
        ax4.imshow(mat, cmap="Blues", aspect="auto")
        for i in range(len(rows)):
            for j in range(len(cols)):
                if mat[i, j]:
                    ax4.text(j, i, str(mat[i, j]), ha="center", va="center", fontsize=8,
                             color="white" if mat[i, j] > mat.max() / 2 else "black")
        ax4.set_xticks(range(len(cols)), cols, rotation=45, ha="right", fontsize=8)
        ax4.set_yticks(range(len(rows)), rows, fontsize=8)
    ax4.set(xlabel="answer", ylabel="true object", title="confusion matrix (trials)")

    stages = list(summary.get("stage_medians_s", {}).items())  # already in pipeline order
    ax5.barh([k for k, _ in stages][::-1], [v for _, v in stages][::-1])
    ax5.set(xlabel="median duration (s)", title="stages (correct trials)")

    causes = Counter(failure_cause(r) for r in trials if not r.get("correct"))
    if causes:
        items = causes.most_common(8)[::-1]
        ax6.barh([_short(c, 38) for c, _ in items], [n for _, n in items], color="tab:red")
        ax6.tick_params(axis="y", labelsize=7)
    else:
        ax6.text(0.5, 0.5, "no failures", ha="center", va="center", transform=ax6.transAxes)
    ax6.set(xlabel="trials", title="failures by cause")
    return fig


def _short(text: str, n: int) -> str:
    return text if len(text) <= n else text[: n - 1] + "…"


def _spec(sweep_dir: Path) -> dict:
    try:
        return json.loads((sweep_dir / "spec.json").read_text())
    except (OSError, ValueError):
        return {}


def _seeds(trials: list[dict]) -> str:
    seeds = sorted({int(r["seed"]) for r in trials if isinstance(r.get("seed"), int)})
    if not seeds:
        return "-"
    if seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 2:
        return f"{seeds[0]}–{seeds[-1]} ({len(seeds)} seeds)"
    return ", ".join(map(str, seeds))


def _date(sweep_dir: Path, spec: dict) -> str:
    if spec.get("created_utc"):
        return str(spec["created_utc"])
    m = re.match(r"trials-(\d{4})(\d\d)(\d\d)T(\d\d)(\d\d)(\d\d)Z", sweep_dir.name)
    return f"{m[1]}-{m[2]}-{m[3]} {m[4]}:{m[5]}:{m[6]} UTC" if m else "-"


def write_sweep_report(sweep_dir: Path | str, summary: dict) -> Path:
    """Write ``report.png`` and ``report.html`` into ``sweep_dir``; return the HTML path."""
    sweep_dir = Path(sweep_dir)
    png = render_sweep_figure(summary)
    atomic_write_bytes(sweep_dir / "report.png", png)
    esc = html.escape
    spec = _spec(sweep_dir)
    trials = summary.get("trials", [])
    k, n, lo, hi = _rate(trials)
    head = f"{summary['n']} of {summary.get('planned', summary['n'])} trials, success {_pct(k, n, lo, hi)}"
    if summary.get("interrupted"):
        head += " — interrupted (partial)"
    lib = spec.get("library_sha256")
    facts = {
        "date": _date(sweep_dir, spec),
        "lab": spec.get("lab", "-"),
        "library": (f"{spec.get('library', '')} (SHA-256 {lib[:16]}…)" if lib else "-"),
        "objects": ", ".join(spec.get("objects") or sorted({str(r.get("true_identity")) for r in trials})),
        "trajectories": ", ".join(sorted({str(r.get("trajectory")) for r in trials})),
        "speeds (mm/s)": ", ".join(f"{v:g}" for v in sorted({r["speed_mm_s"] for r in trials})),
        "seeds": _seeds(trials) + (f", from base seed {spec['seed']}" if "seed" in spec else ""),
    }
    facts_html = "".join(f"<tr><th>{esc(a)}</th><td>{esc(str(b))}</td></tr>" for a, b in facts.items())

    rows = []
    for r in summary.get("by_speed", []):
        rs = [t for t in trials if t["speed_mm_s"] == r["speed_mm_s"]]
        rows.append(f"<tr><td>{r['speed_mm_s']:g}</td><td>{r['n']}</td><td>{esc(_pct(*_rate(rs)))}</td>"
                    f"<td>{_fmt(r['time_to_identity_s_median'])}</td><td>{_fmt(r['ratio_to_lower_bound_median'])}</td>"
                    f"<td>{_fmt(r.get('ratio_to_quintic_bound_median'))}</td></tr>")
    by_traj = []
    groups: dict[tuple[str, float], list[dict]] = defaultdict(list)
    for t in trials:
        groups[(str(t.get("trajectory")), t["speed_mm_s"])].append(t)
    for (tr, v), rs in sorted(groups.items()):
        by_traj.append(f"<tr><td>{esc(tr)}</td><td>{v:g}</td><td>{esc(_pct(*_rate(rs)))}</td></tr>")
    by_obj = []
    for name in sorted({str(t.get("true_identity")) for t in trials}):
        rs = [t for t in trials if str(t.get("true_identity")) == name]
        tti = [t["time_to_identity_s"] for t in rs if t.get("correct") and t.get("time_to_identity_s") is not None]
        med = statistics.median(tti) if tti else None
        wrong = Counter(str(t["identity"]) for t in rs if t.get("identity") is not None and not t.get("correct"))
        by_obj.append(f"<tr><td>{esc(name)}</td><td>{len(rs)}</td><td>{esc(_pct(*_rate(rs)))}</td>"
                      f"<td>{_fmt(med)}</td><td>{esc(', '.join(f'{a} ×{c}' for a, c in wrong.items()) or '-')}</td>"
                      "</tr>")
    crow, ccol, counts = confusion(trials)
    conf = ("<table class=\"conf\"><tr><th>true \\ answer</th>" + "".join(f"<th>{esc(c)}</th>" for c in ccol)
            + "</tr>" + "".join(
                "<tr><th>" + esc(t) + "</th>" + "".join(
                    f"<td class=\"{'diag' if a == t else ('off' if counts.get((t, a)) else '')}\">"
                    f"{counts.get((t, a), '')}</td>" for a in ccol) + "</tr>" for t in crow) + "</table>")

    by_cause: dict[str, list[dict]] = defaultdict(list)
    for t in trials:
        if not t.get("correct"):
            by_cause[failure_cause(t)].append(t)
    fails = []
    for cause, rs in sorted(by_cause.items(), key=lambda kv: -len(kv[1])):
        items = []
        for f in rs:
            link = ""
            if f.get("record"):
                rel = os.path.relpath(f["record"], sweep_dir)
                link = f' <a href="{esc(rel)}/report.html">record</a>'
            what = f"identified as {f.get('identity')}" if f.get("identity") is not None else str(f.get("failure"))
            items.append(f"<li>trial {f.get('index')}, seed {f.get('seed')}, {esc(str(f.get('true_identity')))} "
                         f"on {esc(str(f.get('trajectory')))} at {f.get('speed_mm_s')} mm/s: {esc(what)}{link}</li>")
        fails.append(f"<h3>{esc(cause)} ({len(rs)})</h3><ul>{''.join(items)}</ul>")
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>labctl trials {esc(facts['date'])}</title>
<style>body{{font-family:sans-serif;margin:2em;max-width:1300px}}td,th{{padding:2px 10px;text-align:right;
border:1px solid #ddd}}table{{border-collapse:collapse;margin:.5em 0}}th{{background:#f4f4f4}}
.conf td.diag{{background:#cfe8cf}}.conf td.off{{background:#f6c8c8}}.note{{color:#333;max-width:60em}}
img{{max-width:100%}}</style></head><body>
<h1>labctl trials</h1><p><b>{esc(head)}</b></p>
<table id="facts">{facts_html}</table>
<img src="data:image/png;base64,{base64.b64encode(png).decode()}" alt="sweep figure">
<h2>By speed</h2>
<table id="by-speed"><tr><th>speed mm/s</th><th>n</th><th>success</th><th>time to identity (median, s)</th>
<th>× lower bound</th><th>× quintic bound</th></tr>{''.join(rows)}</table>
<p class="note" id="bound">{esc(BOUND_TEXT)}</p>
<p class="note" id="quintic">{esc(QUINTIC_TEXT)}</p>
<h2>By trajectory and speed</h2>
<table id="by-trajectory"><tr><th>trajectory</th><th>speed mm/s</th><th>success</th></tr>{''.join(by_traj)}</table>
<h2>By object</h2>
<table id="by-object"><tr><th>object</th><th>n</th><th>success</th><th>time to identity (median, s)</th>
<th>taken for</th></tr>{''.join(by_obj)}</table>
<h2>Confusion matrix</h2><p class="note">Rows: the object the simulator placed; columns: the answer
({NONE}: the run gave none). Green: correct; red: confused.</p>{conf}
<h2 id="failures">Failures by cause ({sum(len(v) for v in by_cause.values())})</h2>
{''.join(fails) or '<p>none</p>'}
</body></html>
"""
    out = sweep_dir / "report.html"
    atomic_write_text(out, page)
    return out


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.2f}"
