"""Shared pytest fixtures."""
from pathlib import Path

import pytest

#: Real depth recordings (SPEC section 8) live beside the project, never inside it.
SHARED_DATA = Path(__file__).parents[1].parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """Path to ../shared/data; skips the test when the folder is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data not found: real-data tests need the shared folder beside the project")
    return SHARED_DATA
