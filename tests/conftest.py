"""Shared fixtures. Real data lives in ../shared/data beside the repository (read-only)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data, or skip when the shared folder is not beside the repository."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not beside the repository")
    return SHARED_DATA


# The flow tests' session fixtures (one Prefect harness, the synthetic sessions, the warm
# catalog), registered here once: imported into each test module instead, pytest would build
# one instance per module, a 40-65 s build each.
from tests.flow_fixtures import prefect_harness, synth_root, warm  # noqa: E402, F401
