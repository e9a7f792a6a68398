"""A trials sweep's report: ``report.png`` and a self-contained ``report.html`` in the sweep folder.

Reads only the summary (``labctl.experiments.trials.summarize``): success against speed, a histogram
of time to identity, stage medians in pipeline order, and the failed trials linked to their records.
"""

from __future__ import annotations

import base64
import html
import io
import os
from pathlib import Path

from ..fsutil import atomic_write_bytes, atomic_write_text

__all__ = ["write_sweep_report", "render_sweep_figure"]


def render_sweep_figure(summary: dict) -> bytes:
    """The sweep figure as PNG bytes (matplotlib on the Agg canvas; no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 3.6))
    FigureCanvasAgg(fig)
    ax1, ax2, ax3 = fig.subplots(1, 3)

    rows = summary.get("by_speed", [])
    speeds = [r["speed_mm_s"] for r in rows]
    rates = [100 * r["success_rate"] for r in rows]
    ax1.plot(speeds, rates, "o-")
    ax1.set(xlabel="table speed (mm/s)", ylabel="success (%)", title="success against speed")
    lo = min(rates, default=100.0)
    ax1.set_ylim(max(0.0, lo - 5.0), 101.0)
    if len(speeds) == 1:
        ax1.set_xlim(speeds[0] - 1, speeds[0] + 1)

    times = [t["time_to_identity_s"] for t in summary.get("trials", [])
             if t.get("correct") and t.get("time_to_identity_s") is not None]
    if times:
        ax2.hist(times, bins=min(30, max(5, len(times) // 3)))
    ax2.set(xlabel="time to identity (s)", ylabel="trials", title=f"time to identity (n = {len(times)})")

    stages = list(summary.get("stage_medians_s", {}).items())  # already in pipeline order
    ax3.barh([k for k, _ in stages][::-1], [v for _, v in stages][::-1])
    ax3.set(xlabel="median duration (s)", title="stages (correct trials)")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    return buf.getvalue()


def write_sweep_report(sweep_dir: Path | str, summary: dict) -> Path:
    """Write ``report.png`` and ``report.html`` into ``sweep_dir``; return the HTML path."""
    sweep_dir = Path(sweep_dir)
    png = render_sweep_figure(summary)
    atomic_write_bytes(sweep_dir / "report.png", png)
    esc = html.escape
    head = (f"{summary['n']} of {summary.get('planned', summary['n'])} trials, "
            f"success {100 * summary['success_rate']:.1f} %")
    if summary.get("interrupted"):
        head += " — interrupted (partial)"
    rows = "".join(
        f"<tr><td>{r['speed_mm_s']:g}</td><td>{r['n']}</td><td>{100 * r['success_rate']:.1f} %</td>"
        f"<td>{_fmt(r['time_to_identity_s_median'])}</td><td>{_fmt(r['ratio_to_lower_bound_median'])}</td></tr>"
        for r in summary.get("by_speed", []))
    fails = []
    for f in summary.get("failed", []):
        link = ""
        if f.get("record"):
            rel = os.path.relpath(f["record"], sweep_dir)
            link = f' <a href="{esc(rel)}/report.html">record</a>'
        why = f.get("failure") or f"identified as {f.get('identity')}"
        fails.append(f"<li>trial {f.get('index')} seed {f.get('seed')}, {esc(str(f.get('true_identity')))} at "
                     f"{f.get('speed_mm_s')} mm/s: {esc(str(why))}{link}</li>")
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>labctl trials</title>
<style>body{{font-family:sans-serif;margin:2em}}td,th{{padding:2px 10px;text-align:right}}</style></head><body>
<h1>labctl trials</h1><p>{esc(head)}</p>
<table><tr><th>speed mm/s</th><th>n</th><th>success</th><th>time to identity (median, s)</th>
<th>× lower bound</th></tr>{rows}</table>
<img src="data:image/png;base64,{base64.b64encode(png).decode()}" alt="sweep figure">
<h2>failures ({len(fails)})</h2><ul>{''.join(fails) or '<li>none</li>'}</ul>
</body></html>
"""
    out = sweep_dir / "report.html"
    atomic_write_text(out, page)
    return out


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.2f}"
