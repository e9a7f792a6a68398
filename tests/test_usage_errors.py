"""Click's usage errors are one ``labctl: error:`` line with exit 2, like every expected failure."""

from __future__ import annotations

import subprocess
import sys

import pytest


@pytest.mark.parametrize("args, words", [
    (["run", "--speed", "abc"], "'--speed'"),
    (["nosuch"], "No such command"),
    (["report"], "Missing argument"),
    (["trials", "--bogus"], "No such option"),
    (["vision", "learn-color", "x.png", "--camera", "sideways"], "--camera"),
])
def test_a_usage_error_is_one_line_and_exit_2(args, words):
    res = subprocess.run([sys.executable, "-m", "labctl", *args], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    lines = res.stderr.splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("labctl: error:") and words in lines[0] and "--help" in lines[0]


def test_a_run_without_identity_says_why_in_one_stderr_line_with_the_next_step(tmp_path):
    import shutil
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    lab = tmp_path / "lab"
    lab.mkdir()
    for name in ("drivers", "calibration", "object_library"):
        shutil.copytree(root / name, lab / name)
    text = (root / "lab.yaml").read_text()
    assert "  timeout_s: 90.0" in text
    (lab / "lab.yaml").write_text(text.replace("  timeout_s: 90.0", "  timeout_s: 0.5", 1))
    res = subprocess.run([sys.executable, "-m", "labctl", "--lab", str(lab), "run", "--virtual", "--trajectory",
                          "line"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 1
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("labctl: error: no identity:"), res.stderr
    rid = lines[0].rsplit("labctl report ", 1)[1].rstrip(")")
    assert (lab / "runs" / rid / "meta.json").is_file()
