"""Shared fixtures."""

from pathlib import Path

import pytest

from pacdp_testing import PUSHT_ZARR


@pytest.fixture
def pusht_zarr() -> Path:
    if not PUSHT_ZARR.exists():
        pytest.skip(f"shared PushT demos not found at {PUSHT_ZARR}")
    return PUSHT_ZARR
