"""Shared test fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
TSAI_DATA = SHARED / "data" / "tsai"


@pytest.fixture
def tsai_points():
    import numpy as np

    path = TSAI_DATA / "willson_ncc_cd_300pts.txt"
    if not path.is_file():
        pytest.skip(f"reference data not found: {path}")
    return np.loadtxt(path)
