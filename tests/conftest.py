"""Shared fixtures. Real EuRoC data lives in ../shared/data beside the repository; tests that need it
skip with a clear reason on a fresh clone that lacks it."""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

try:
    import fcntl  # POSIX: the xdist workers share each simulated flight under a flock
except ImportError:  # Windows has no fcntl: each worker simulates its own copy in its own folder (flight_cache)
    fcntl = None  # type: ignore[assignment]

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


@pytest.fixture(scope="session")
def simulated_flight(tmp_path_factory) -> Callable[..., Path]:
    """`simulated_flight(SimConfig)` -> the folder of that flight, simulated once per test run and shared by every
    test file and every xdist worker (the simulator is deterministic for a config): the same drifted-stereo-pair
    flight was simulated by tests/test_replay.py and tests/test_calib.py each. The tests only read it (what they
    write goes to their own tmp_path). Across workers: under the run's common base folder, one lock per flight."""
    from vio.sim.generate import simulate

    return simulated_flight_maker(flight_cache(tmp_path_factory.getbasetemp(), os.environ.get("PYTEST_XDIST_WORKER")),
                                  simulate)


def flight_cache(base: Path, worker: str | None) -> Path:
    """The folder simulated flights are kept in, made if absent: with fcntl, the run's common base folder above a
    local xdist worker's own (`popen-gwN`), shared under one flock per flight; without it (Windows), the worker's own
    base: each worker simulates its own copy, and nothing else writes there (a session's tests run one at a time)."""
    if fcntl is not None and worker and base.name.startswith("popen-"):
        base = base.parent
    cache = base / "simulated_flights"
    cache.mkdir(exist_ok=True)
    return cache


@contextlib.contextmanager
def _flight_lock(path: Path) -> Iterator[None]:
    """Held while a flight is looked for and simulated: another worker simulating it is waited for. No lock without
    fcntl, where no other worker shares the folder (flight_cache)."""
    if fcntl is None:
        yield
        return
    with open(path, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def simulated_flight_maker(cache: Path, simulate: Callable[..., object]) -> Callable[..., Path]:
    """`make(cfg)` -> the folder of that flight in `cache`, simulated by `simulate(folder, cfg, progress=False)` only
    when no complete one is there."""
    def make(cfg) -> Path:
        name = hashlib.sha256(repr(cfg).encode()).hexdigest()[:16]
        data, done = cache / name, cache / f"{name}.done"
        with _flight_lock(cache / f"{name}.lock"):
            if not done.exists():
                shutil.rmtree(data, ignore_errors=True)  # a worker that died part-way
                simulate(data, cfg, progress=False)
                done.write_text(repr(cfg))
        return data

    return make


@pytest.fixture(scope="session")
def turning_flight(simulated_flight) -> Callable[..., tuple[Path, object]]:
    """An 8 s aggressive flight (turns about every axis) at 376x240 whose sensor.yaml is wrong as `sim` says
    (`turning_flight(stereo_error_px=1.0)`: a drifted stereo pair); returns its folder and the calibration it
    states. Used by tests/test_calib.py and tests/test_replay.py: each distinct flight is simulated once a run."""
    from vio.io.euroc import EurocDataset
    from vio.sim.generate import SimConfig

    def make(**sim) -> tuple[Path, object]:
        data = simulated_flight(SimConfig(profile="aggressive", duration_s=8.0, variant="clean", width=376,
                                          height=240, still_start_s=1.0, seed=3, **sim))
        return data, EurocDataset(data).calibration

    return make


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
