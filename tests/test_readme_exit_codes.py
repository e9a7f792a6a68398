"""The README's two exit-status tables agree with each other and with the code that sets the codes."""

from __future__ import annotations

import re
from pathlib import Path

from labctl.runtime.live import EXIT_DEVICE, EXIT_HANGUP, EXIT_INTERRUPTED, EXIT_TERMINATED

README = Path(__file__).resolve().parents[1] / "README.md"


def _table(after_heading: str) -> list[tuple[str, str]]:
    """The rows ``(first cell, second cell)`` of the first table under ``after_heading``."""
    text = README.read_text()
    start = text.index(after_heading)
    rows = []
    for line in text[start:].splitlines()[1:]:
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            if not set(cells[0]) <= set("- ") and cells[0] not in ("status", "how `labctl run` ends"):
                rows.append((cells[0], cells[1]))
        elif rows:
            break
    return rows


def test_the_exit_table_and_the_run_table_say_the_same_codes_as_the_code():
    contract = {int(code): meaning for code, meaning in _table("## Exit status")}
    run = {how: int(code) for how, code in _table("### Stopping and exit status")}
    by_signal = {"SIGINT": EXIT_INTERRUPTED, "SIGTERM": EXIT_TERMINATED, "SIGHUP": EXIT_HANGUP}
    for sig, code in by_signal.items():
        rows = [how for how in run if sig in how or (sig == "SIGINT" and "Ctrl-C" in how)]
        assert rows and all(run[how] == code for how in rows), (sig, rows)
        assert code in contract and (sig in contract[code] or (sig == "SIGINT" and "Ctrl-C" in contract[code])), \
            (sig, code, contract.get(code))
    assert "SIGTERM" not in re.sub(r"for `labctl table …`.*", "", contract[EXIT_INTERRUPTED])  # not for a run
    assert set(run.values()) <= set(contract) and EXIT_DEVICE in contract
