"""The live view (issue 18): `vio replay --view FILE.rrd` writes a recording that rerun's own reader reads back
with the expected entities, the trajectory is unchanged by the view, and a viewer that does not keep up makes
the frame loop drop view frames instead of waiting."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rerun")

from vio import VioError  # noqa: E402
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
    from vio.config import ViewConfig

    gate = threading.Event()
    view = LiveView(str(tmp_path / "x.rrd"), None, ViewConfig(queue_frames=2))
    view._log = lambda *a: gate.wait(10)  # the viewer thread hangs on its first item
    img = np.zeros((20, 30), np.uint8)
    view.submit(0, img, None, None, False, {})
    deadline = time.monotonic() + 5
    while len(view._q) and time.monotonic() < deadline:  # the thread has taken it and hangs
        time.sleep(0.01)
    for k in range(1, 20):
        view.submit(k, img, None, None, False, {})
    assert view.dropped == 19 - 2  # a queue of 2 behind the item the thread holds (the oldest go)
    assert view.stats()["submitted"] == 20
    gate.set()
    view.close()
    assert view.logged + view.thinned + view.dropped == 20  # every frame is accounted for


def test_the_view_thread_logs_at_its_rate_not_every_frame(tmp_path):
    """A replay faster than the view's rates: frames are thinned in the view thread (not dropped in the frame
    loop), the image goes out as a downscaled JPEG, and the last frame is still logged at close."""
    from vio.config import ViewConfig

    view = LiveView(str(tmp_path / "r.rrd"), None, ViewConfig(rate_hz=0.1, image_hz=0.1, queue_frames=100))
    img = np.full((40, 60), 128, np.uint8)
    view.submit(0, img, None, None, False, {"resets": 0})
    deadline = time.monotonic() + 5
    while view.logged == 0 and time.monotonic() < deadline:  # the first frame is logged at once
        time.sleep(0.01)
    for k in range(1, 50):
        view.submit(k * 50_000_000, img, None, None, False, {"resets": 0})
    view.close()
    assert view.dropped == 0 and view.logged == 2 and view.thinned == 48, view.stats()
    assert view.images == 2
    assert rrd_entities(tmp_path / "r.rrd")["/camera/left"] == 2
    import cv2
    import rerun.chunk

    ch = next(c for c in rerun.chunk.RrdReader(str(tmp_path / "r.rrd")).stream() if c.entity_path == "/camera/left")
    rb = ch.to_record_batch()
    assert rb.column("EncodedImage:media_type")[0].as_py() == ["image/jpeg"]
    jpg = np.array(rb.column("EncodedImage:blob")[0].as_py()[0], np.uint8)
    assert cv2.imdecode(jpg, cv2.IMREAD_UNCHANGED).shape == (20, 30)  # image_scale 0.5 by default


def test_loop_closure_view_logs_the_corrected_trajectory(flight):
    r = _replay(flight, "--loop", "--view", "loop.rrd")
    assert r.returncode == 0, r.stderr
    ents = rrd_entities(flight / "loop.rrd")
    assert {"/world/trajectory/loop", "/world/loop/keyframes", "/health/loop_closures",
            "/world/trajectory/odometry"} <= set(ents), sorted(ents)


class _Loop:
    """A loop worker stand-in: a pose graph of two segments with one accepted and one rejected loop edge."""

    keep_snapshot = False

    def __init__(self):
        from vio.app.loop_worker import LoopSnapshot

        self.snap = LoopSnapshot(4, 1, np.arange(12.0).reshape(4, 3), np.array([0, 0, 1, 1]),
                                 ((2, 0, 1.0), (3, 1, 0.1)))

    def snapshot(self):
        return self.snap


def test_loop_edges_and_corrected_keyframes_are_entities_of_their_own(tmp_path):
    from vio.types import NavState

    loop = _Loop()
    view = LiveView(str(tmp_path / "e.rrd"), None, loop=loop)
    assert loop.keep_snapshot is True  # the view asks the worker for snapshots
    st = NavState(t_ns=1, T_world_body=np.eye(4), v_world=np.zeros(3))
    for k in range(3):
        view.submit(k, None, None, st, k == 1, {})
    view.close()
    assert view.errors == 0
    ents = rrd_entities(tmp_path / "e.rrd")
    assert ents.get("/world/loop/edges", 0) >= 1 and ents.get("/world/trajectory/loop", 0) >= 1, sorted(ents)
    assert "/world/loop/keyframes" in ents and "/health/loop_closures" in ents


def test_replay_view_refuses_a_port_in_use_before_it_opens_the_recording(flight, tmp_path, monkeypatch, capsys):
    """`vio replay --view` (serve) with the web port held by another program opened and read the recording, then
    ended in "internal error: RuntimeError: Failed to create server: Address already in use". Now said first, in
    one line, before the recording is opened or any output file is written."""
    import socket

    import vio.app.replay as replay_mod
    from vio.app.cli import main

    def never(*a, **k):
        raise AssertionError("the recording was opened before the view was checked")

    monkeypatch.setattr(replay_mod, "open_dataset", never)
    old = tmp_path / "old.tum"
    old.write_text("# an earlier flight\n")
    with socket.socket() as held:
        held.bind(("0.0.0.0", 0))
        held.listen()
        port = held.getsockname()[1]
        cfg = tmp_path / "view.toml"
        cfg.write_text(f"[view]\nweb_port = {port}\n")
        assert main(["replay", str(flight / "sim"), "--view", "--config", str(cfg), "-o", str(old),
                     "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and f"port {port} ([view] web_port) is in use" in err, err
    assert "internal error" not in err and old.read_text() == "# an earlier flight\n"


def test_serving_on_the_grpc_port_or_a_privileged_port_is_said_as_what_it_is(monkeypatch):
    """A web port equal to the gRPC port passed the check (each probed alone is free) and failed when the servers
    started; a port this user may not open read "Permission denied: stop what holds it", though nothing held it."""
    import errno
    import socket

    from vio.app.view import GRPC_PORT, check_view
    from vio.config import ViewConfig

    with pytest.raises(VioError, match=f"web_port = {GRPC_PORT} is the port the live view's gRPC server takes"):
        check_view("serve", ViewConfig(web_port=GRPC_PORT))

    def refused(self, address):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(socket.socket, "bind", refused)
    with pytest.raises(VioError) as e:
        check_view("serve", ViewConfig(web_port=80))
    assert "port 80 ([view] web_port) may not be opened by this user" in str(e.value)
    assert "stop what holds it" not in str(e.value)


def test_daemon_view_section_is_off_by_default():
    from vio.config import VioConfig, config_from_dict

    assert VioConfig().view.enabled is False
    cfg = config_from_dict({"view": {"enabled": True, "target": "flight.rrd", "rate_hz": 4}})
    assert cfg.view.target == "flight.rrd" and cfg.view.rate_hz == 4.0
    with pytest.raises(VioError, match="image_scale"):
        config_from_dict({"view": {"image_scale": 2.0}})
    with pytest.raises(VioError, match="serve_memory_mb"):
        config_from_dict({"view": {"serve_memory_mb": 1}})


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
    deadline = time.monotonic() + 30
    while svc.view.logged < 8 and time.monotonic() < deadline:  # [view] rate_hz 5: about 2 s of flight
        time.sleep(0.05)
    svc.request_stop()
    runner.join(10)
    assert svc.view.logged >= 8
    ents = set(rrd_entities(tmp_path / "d.rrd"))
    assert {"/camera/left", "/camera/left/tracks", "/health/tracks", "/health/resets"} <= ents, sorted(ents)


def test_the_path_kept_for_the_view_is_bounded_and_ends_at_the_newest_pose(tmp_path, monkeypatch):
    import vio.app.view as view_module
    from vio.types import NavState

    monkeypatch.setattr(view_module, "_MAX_POINTS", 10)
    view = LiveView(str(tmp_path / "p.rrd"), None)
    for k in range(200):
        T = np.eye(4)
        T[0, 3] = k
        view.submit(k, None, None, NavState(t_ns=k, T_world_body=T, v_world=np.zeros(3)), True, {})
        if k % 8 == 0:
            time.sleep(0.01)
    view.close()
    assert view.errors == 0
    assert len(view._path) <= 10 + 16 and len(view._kf) <= 10 + 16  # the limit, plus one batch of the queue
    assert view._path[-1][0] == 199.0 and view._kf[-1][0] == 199.0
