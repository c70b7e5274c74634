"""The live view (issue 18): `vio replay --view FILE.rrd` writes a recording that rerun's own reader reads back
with the expected entities, the trajectory is unchanged by the view, and a viewer that does not keep up makes
the frame loop drop view frames instead of waiting."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rerun")

from vio.app.view import LiveView, rrd_entities  # noqa: E402

EXPECTED = {"/camera/left", "/camera/left/tracks", "/world/body", "/world/trajectory/odometry", "/world/keyframes",
            "/world/landmarks", "/world/covariance", "/health/resets", "/health/tracks", "/health/stereo"}


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    from vio.sim.generate import SimConfig, simulate

    root = tmp_path_factory.mktemp("view")
    simulate(root / "sim", SimConfig(duration_s=3.0, width=320, height=200, variant="clean", still_start_s=1.0))
    return root


def _replay(root: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vio.app.cli", "-q", "replay", "sim", "--no-progress", *args],
                          cwd=root, capture_output=True, text=True, timeout=120)


def test_replay_view_writes_an_rrd_with_the_expected_entities(flight):
    r = _replay(flight, "-o", "view.tum", "--view", "out.rrd")
    assert r.returncode == 0, r.stderr
    assert "view:" in r.stdout
    ents = rrd_entities(flight / "out.rrd")
    assert set(ents) >= EXPECTED, sorted(ents)
    assert ents["/camera/left"] >= 1
    plain = _replay(flight, "-o", "plain.tum")
    assert plain.returncode == 0, plain.stderr
    assert (flight / "view.tum").read_bytes() == (flight / "plain.tum").read_bytes()


def test_a_stuck_viewer_drops_frames_instead_of_blocking(tmp_path):
    gate = threading.Event()
    view = LiveView(str(tmp_path / "x.rrd"), None, queue_size=2)
    view._log = lambda *a: gate.wait(10)  # the viewer thread hangs on its first item
    img = np.zeros((20, 30), np.uint8)
    for k in range(20):
        view.submit(k, img, None, None, False, {})
    assert view.dropped >= 20 - 2 - 1  # queue of 2, plus the item the thread holds
    assert len(view.submit_ms) == 20
    gate.set()
    view.close()
    assert view.logged + view.dropped == 20


def test_daemon_view_section_is_off_by_default():
    from vio.config import VioConfig, config_from_dict

    assert VioConfig().view.enabled is False
    cfg = config_from_dict({"view": {"enabled": True, "target": "flight.rrd"}})
    assert cfg.view.target == "flight.rrd"


def test_daemon_streams_the_view_to_an_rrd(tmp_path):
    import time

    from drivers.fake import FakeSource
    from vio.app.daemon.service import Service
    from vio.app.sdnotify import SdNotifier
    from vio.config import config_from_dict

    cfg = config_from_dict({"run": {"status_file": ""}, "view": {"enabled": True, "target": str(tmp_path / "d.rrd")}})

    def source():
        s = FakeSource(width=160, height=100)
        s.start()
        return s

    svc = Service(cfg, source_factory=source, notifier=SdNotifier(""))
    runner = threading.Thread(target=svc.run)
    runner.start()
    deadline = time.monotonic() + 20
    while svc.view.logged < 20 and time.monotonic() < deadline:
        time.sleep(0.05)
    svc.request_stop()
    runner.join(10)
    assert svc.view.logged >= 20
    ents = set(rrd_entities(tmp_path / "d.rrd"))
    assert {"/camera/left", "/camera/left/tracks", "/health/tracks", "/health/resets"} <= ents, sorted(ents)
