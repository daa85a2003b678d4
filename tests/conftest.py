"""Shared fixtures: the real camera data beside the checkout, temporary outputs."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("RADIOMAP_SHARED_DATA", REPO.parent / "shared" / "data"))


def shared_path(*parts: str) -> Path:
    """A path under ../shared/data; skips the calling test with a reason when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real camera data {path} is absent (it lives in ../shared/data beside the checkout)")
    return path


@pytest.fixture
def shared_data() -> Path:
    return shared_path()
