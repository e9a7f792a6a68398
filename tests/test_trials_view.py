"""``labctl trials --view``: the live view follows each trial of the sweep in turn (the newest record), and a
taken port or ``--no-record`` is refused in one line before anything runs."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import time
import urllib.request

from fakes import run_cli

from labctl.workspace import sample_lab_path


def test_trials_view_follows_each_trial(tmp_path):
    lab = tmp_path / "lab"
    shutil.copytree(sample_lab_path(), lab, ignore=shutil.ignore_patterns("runs"))
    proc = subprocess.Popen([sys.executable, "-m", "labctl", "--lab", str(lab), "--json", "trials", "--n", "3",
                             "--speed", "8", "--jobs", "1", "--view", "--view-port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = None
        deadline = time.monotonic() + 60
        while url is None and time.monotonic() < deadline:
            line = proc.stderr.readline()
            m = re.search(r"live view: (http://\S+)", line)
            url = m.group(1) if m else None
        assert url, "no live view URL on stderr"
        api = url.replace("/?key=", "/api/state?key=")
        seen: dict[str, set] = {}
        while proc.poll() is None and time.monotonic() < deadline + 120:
            try:
                with urllib.request.urlopen(api, timeout=5) as r:
                    st = json.loads(r.read())
            except OSError:
                break  # the sweep ended and closed the page
            seen.setdefault(st["run"], set()).update(s["stage"] for s in st["stages"])
            time.sleep(0.1)
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0
    summary = json.loads(out)
    names = {t["record"].rsplit("/", 1)[-1] for t in summary["trials"]}
    followed = set(seen) & names
    assert len(followed) >= 2, seen  # it moved from one trial to the next
    assert any("done" in stages for stages in seen.values())


def test_trials_view_without_records_is_refused(tmp_path, capsys):
    code, _, err = run_cli(capsys, "--lab", str(sample_lab_path()), "trials", "--n", "1", "--no-record", "--view")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--no-record" in err
