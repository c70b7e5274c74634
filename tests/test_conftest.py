"""The test suite's own support (tests/conftest.py): it must load where fcntl does not exist (Windows)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

CONFTEST = Path(__file__).with_name("conftest.py")


def _load_conftest(name: str):
    spec = importlib.util.spec_from_file_location(name, CONFTEST)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_conftest_loads_without_fcntl_and_each_worker_simulates_its_own_flight(monkeypatch, tmp_path) -> None:
    """conftest.py imported fcntl at module level: on Windows the whole suite failed to import. Without it (simulated:
    `import fcntl` raises ImportError) it loads, and the simulated-flight cache takes no lock: each xdist worker
    keeps its own copy in its own base folder, simulated once. With fcntl the workers share the run's folder."""
    monkeypatch.setitem(sys.modules, "fcntl", None)  # `import fcntl` raises ImportError, as on Windows
    mod = _load_conftest("conftest_without_fcntl")
    assert mod.fcntl is None
    made: list[Path] = []

    def simulate(data: Path, cfg: object, progress: bool) -> None:
        made.append(data)
        data.mkdir()

    folders = []
    for worker in ("gw0", "gw1"):
        base = tmp_path / f"popen-{worker}"
        base.mkdir()
        cache = mod.flight_cache(base, worker)
        assert cache == base / "simulated_flights"  # its own folder: no other process writes there
        make = mod.simulated_flight_maker(cache, simulate)
        folders.append(make("a flight"))
        assert make("a flight") == folders[-1] and folders[-1].is_dir()  # simulated once per worker
    assert made == folders and folders[0] != folders[1]
    assert not list(tmp_path.glob("popen-*/simulated_flights/*.lock"))  # no lock file either
    monkeypatch.delitem(sys.modules, "fcntl")
    with_fcntl = _load_conftest("conftest_with_fcntl")
    if with_fcntl.fcntl is not None:  # POSIX: the run's common folder, shared under a flock
        assert with_fcntl.flight_cache(tmp_path / "popen-gw0", "gw0") == tmp_path / "simulated_flights"
