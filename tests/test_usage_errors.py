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
