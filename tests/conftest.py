"""Shared fixtures. Real EuRoC data lives in ../shared/data beside the repository; tests that need it
skip with a clear reason on a fresh clone that lacks it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("KESTREL_SHARED_DATA", REPO.parent / "shared" / "data"))
V101 = SHARED_DATA / "euroc" / "V1_01_easy_excerpt"
V102 = SHARED_DATA / "euroc" / "V1_02_medium_imu_gt"


def _need(path: Path) -> Path:
    if not (path / "mav0").is_dir():
        pytest.skip(f"real EuRoC data not found at {path} (set KESTREL_SHARED_DATA or place ../shared/data)")
    return path


@pytest.fixture(scope="session")
def v101_path() -> Path:
    return _need(V101)


@pytest.fixture(scope="session")
def v102_path() -> Path:
    return _need(V102)


@pytest.fixture(autouse=True)
def _root_log_level():
    """Each test starts from the root logger's level as the session had it: `vio run`'s main (called in-process by
    the daemon tests) sets it from `[run] log_level`, and a later test counting INFO records then also counted
    records from before its own `caplog.at_level` block (test_mavlink's mount-once test failed after them)."""
    import logging

    root = logging.getLogger()
    level = root.level
    yield
    root.setLevel(level)
