"""Shared test fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
# Willson's reference set, copied from shared/data/tsai with its licence (BSD-3-Clause via NiftyCal)
TSAI_DATA = Path(__file__).resolve().parent / "data" / "tsai"


@pytest.fixture
def tsai_points():
    import numpy as np

    path = TSAI_DATA / "willson_ncc_cd_300pts.txt"
    return np.loadtxt(path)
