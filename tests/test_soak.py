"""The live loop's long-lived parts in virtual time: every buffer stays bounded, no peer is lost.

The hour-long soak with RSS at start and end is ``python -m labctl.experiments.soak --hours 1``
(numbers in docs/notes/link_and_records.md); this is its short form, long enough for the robot's
DONE reports to pass their bound."""

from __future__ import annotations

import pytest

from labctl.config import load_lab
from labctl.experiments.soak import soak
from labctl.workspace import sample_lab_path


@pytest.mark.timeout(300)
def test_short_soak_keeps_every_buffer_bounded(tmp_path):
    r = soak(load_lab(sample_lab_path()), hours=160 / 3600, runs_dir=tmp_path, warmup_s=30.0, segment_every_s=0.5,
             segment_mm=10.0)
    assert r["virtual_s"] >= 160 and r["segments"] > 300  # more DONE reports than the bound holds
    b = r["buffers"]
    assert b["robot.done_ids"] == 256 and b["robot.faults"] == 0
    assert b["table.messages"] <= 200 and b["table.link.buffered"] < 4096 and b["robot.link.buffered"] < 4096
    assert r["peer_lost"] == []
    # the record: one durable event per tick, fsynced in batches by the writer thread, not per event
    assert r["record_events"] == r["ticks"] and 0 < r["record_fsyncs"] < r["ticks"] / 10
