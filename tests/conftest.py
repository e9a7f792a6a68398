"""Shared test fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# every event a test writes, here and in the processes it starts, must match labctl.records.events
os.environ["LABCTL_STRICT_EVENTS"] = "1"

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
# Willson's reference set, copied from shared/data/tsai with its licence (BSD-3-Clause via NiftyCal)
TSAI_DATA = Path(__file__).resolve().parent / "data" / "tsai"


@pytest.fixture
def tsai_points():
    import numpy as np

    path = TSAI_DATA / "willson_ncc_cd_300pts.txt"
    return np.loadtxt(path)


@pytest.fixture
def run_with_events():
    """``run(lab, ctx, spec) -> (result, events)``: a virtual run and its record's events, (name, fields) in order."""
    from labctl.records.events import validate
    from labctl.records.record import to_jsonable
    from labctl.runtime.virtual import simulate_run

    def run(lab, ctx, spec):
        events = []

        class Rec:
            def event(self, name, **fields):
                validate(to_jsonable({"event": name, "wall": 0.0, **fields}))  # as RunRecord.event checks it
                events.append((name, fields))

            def save_image(self, name, image):
                pass

        return simulate_run(lab, ctx, spec, Rec()), events

    return run
