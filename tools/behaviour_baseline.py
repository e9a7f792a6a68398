"""Behaviour baseline of the virtual runtime: record a fixed set of trials, or compare against it.

A refactor that claims to preserve behaviour (issue 29) must give, trial by trial and field by
field, the results committed before it started. This runs the fixed set through the CLI
(``labctl trials``, a stable interface whatever moves inside the package) and writes or compares
one JSON line per trial, plus a digest of each trial's event stream.

    python tools/behaviour_baseline.py record  [--set main,realistic,lib100] [--jobs 2]
    python tools/behaviour_baseline.py compare [--set ...]

Sets:
  main       line, arc, circle, zigzag x 4, 8, 12 mm/s x seeds 0-9 (120 trials), the sample lab
  realistic  line, zigzag x 8 mm/s x seeds 0-5 (12 trials), ``labctl init --preset realistic-camera``
  lib100     line x 8 mm/s x seeds 0-5 (6 trials), the 100-part generated library
             (``python -m labctl.bench.recognition DIR 100``, seed 15; built once under --work)

The comparison is exact (floats as JSON writes them). Fields that name where a record was written
are dropped; everything else counts.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BASELINE = ROOT / "tests" / "data" / "behaviour_baseline"

SETS = {
    "main": {"trajectory": "line,arc,circle,zigzag", "speed": "4,8,12", "n": 10, "lab": None},
    "realistic": {"trajectory": "line,zigzag", "speed": "8", "n": 6, "lab": "realistic"},
    "lib100": {"trajectory": "line", "speed": "8", "n": 6, "lab": "lib100"},
}
UNCOMPARED = {"record"}


def _labctl(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "labctl", *args], cwd=cwd, check=True,
                          capture_output=True, text=True)


def _lab(kind: str | None, work: Path) -> Path:
    if kind is None:
        return ROOT
    lab = work / f"lab-{kind}"
    if (lab / "lab.yaml").exists():
        return lab
    tmp = work / f"lab-{kind}.partial"
    shutil.rmtree(tmp, ignore_errors=True)
    if kind == "realistic":
        _labctl("init", "--preset", "realistic-camera", str(tmp))
    else:
        _labctl("init", str(tmp))
        lib = tmp / "object_library"
        shutil.rmtree(lib)
        lib.mkdir()
        print(f"  teaching the 100-part library into {lib} (several minutes)", file=sys.stderr)
        subprocess.run([sys.executable, "-m", "labctl.bench.recognition", str(lib), "100"], cwd=tmp,
                       check=True, capture_output=True)
    tmp.rename(lab)
    return lab


def _events_digest(record: Path) -> str:
    """SHA-256 of a trial's event stream, each event re-serialised with sorted keys and without its
    wall-clock stamp (``wall``, the one field that differs between runs of one seed)."""
    h = hashlib.sha256()
    for line in (record / "events.jsonl").read_text().splitlines():
        ev = json.loads(line)
        ev.pop("wall", None)
        h.update(json.dumps(ev, sort_keys=True).encode())
    return h.hexdigest()


def run_set(name: str, work: Path, jobs: int) -> list[dict]:
    s = SETS[name]
    lab = _lab(s["lab"], work)
    out = work / f"sweep-{name}"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    print(f"== {name}: {s['trajectory']} @ {s['speed']} mm/s x {s['n']} seeds on {lab}", file=sys.stderr)
    res = _labctl("--lab", str(lab), "trials", "--n", str(s["n"]), "--trajectory", s["trajectory"],
                  "--speed", s["speed"], "--seed", "0", "--jobs", str(jobs), "--json", cwd=out)
    summary = json.loads(res.stdout)
    folder = Path(summary["sweep"])
    rows = []
    for line in (folder / "results.jsonl").read_text().splitlines():
        r = json.loads(line)
        rec = r.get("record")
        if rec:
            r["events_sha256"] = _events_digest(Path(rec))
        rows.append({k: v for k, v in r.items() if k not in UNCOMPARED})
    rows.sort(key=lambda r: r["index"])
    shutil.rmtree(folder, ignore_errors=True)
    return rows


def _diff(a, b, path="") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{path}.{k}: {'missing before' if k not in a else 'missing after'}")
            else:
                out += _diff(a[k], b[k], f"{path}.{k}")
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _diff(x, y, f"{path}[{i}]")]
    return [] if a == b else [f"{path}: {a!r} -> {b!r}"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("action", choices=["record", "compare"])
    ap.add_argument("--set", default="main,realistic,lib100")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--work", type=Path, default=Path("/tmp/labctl-baseline"))
    ap.add_argument("--no-events", action="store_true", help="compare results only, not event digests")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    BASELINE.mkdir(parents=True, exist_ok=True)
    bad = 0
    for name in a.set.split(","):
        rows = run_set(name, a.work, a.jobs)
        path = BASELINE / f"{name}.jsonl"
        if a.action == "record":
            path.write_text("".join(json.dumps(r, sort_keys=True) + "\n" for r in rows))
            print(f"{name}: {len(rows)} trials recorded in {path.relative_to(ROOT)}")
            continue
        before = [json.loads(x) for x in path.read_text().splitlines()]
        if len(before) != len(rows):
            print(f"{name}: {len(before)} trials in the baseline, {len(rows)} now")
            bad += 1
            continue
        n_bad = n_events = 0
        for x, y in zip(before, rows):
            if a.no_events:
                x.pop("events_sha256", None), y.pop("events_sha256", None)
            d = _diff(x, y)
            ev = [e for e in d if e.startswith(".events_sha256")]
            n_events += bool(ev)
            d = [e for e in d if e not in ev]
            if d:
                n_bad += 1
                print(f"{name} trial {x['index']} (seed {x['seed']}, {x['trajectory']} @ {x['speed_mm_s']}): "
                      + "; ".join(d[:5]))
        print(f"{name}: {len(rows) - n_bad} of {len(rows)} trials identical field by field; "
              f"{len(rows) - n_events} of {len(rows)} event streams identical")
        bad += n_bad + n_events
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
