"""Independent check of run records: each segment's recorded end configuration (arm_plan q_end_deg), put

Usage: python tools/arm_records_check.py SWEEP_FOLDER (a `labctl trials` folder with records).
through the hand-written UR10e DH (tests/arm_dh.py, no labctl arm code), must give the commanded pose of the
same segment id, lie inside the published joint limits (±360°), and the joint change per leg stay within the
published joint speeds over the leg's duration."""
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from arm_dh import rotation_angle, rotvec_matrix, sample_mount, ur10e_fk

T_w_base = sample_mount()
QD = np.radians([120, 120, 180, 180, 180, 180])
worst_p = worst_r = speed_ratio = 0.0
n = over = lim = 0
for ev in Path(sys.argv[1]).glob("trials/*/events.jsonl"):
    evs = [json.loads(l) for l in ev.read_text().splitlines() if l.strip()]
    segs = {e["id"]: e for e in evs if e["event"] == "segment"}
    plans = [e for e in evs if e["event"] == "arm_plan"]
    prev_q, prev_t = None, None
    for a in plans:
        s = segs[a["id"]]
        q = np.radians(a["q_end_deg"])
        T = ur10e_fk(q, T_w_base)
        worst_p = max(worst_p, float(np.linalg.norm(T[:3, 3] - np.asarray(s["p"]))))
        worst_r = max(worst_r, rotation_angle(T[:3, :3].T @ rotvec_matrix(s["rotvec"])))
        lim += int(np.any(np.abs(q) > 2 * math.pi))
        if prev_q is not None and math.isfinite(s["t1c"]) and math.isfinite(s["t0c"]):
            # a leg's least time at each joint's speed limit: |Δq| / qd_max ≤ the leg's duration
            r = float(np.max(np.abs(q - prev_q) / QD) / max(s["t1c"] - s["t0c"], 1e-9))
            speed_ratio = max(speed_ratio, r)
            over += r > 1
        prev_q = q
        n += 1
print(f"segments {n}; worst FK-vs-command {worst_p:.4f} mm, {math.degrees(worst_r):.4f} deg; "
      f"outside joint limits {lim}; legs whose joint change needs more than the published speed {over} "
      f"(worst mean-speed ratio {speed_ratio:.2f})")
