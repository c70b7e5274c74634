"""`vio record`: bit-exact round trip through a EuRoC dataset, and what a signal or a kill leaves behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drivers import fake
from drivers.fake import EurocSource, FakeSource
from drivers.record import record
from vio import VioError
from vio.io.euroc import EurocDataset
from vio.types import ImuSample, StereoFrame

T0 = 1_000_000_000_000


def _fake(**kw) -> FakeSource:
    return FakeSource(width=160, height=100, fps=20, imu_rate_hz=200, duration_s=1.0, t0_ns=T0,
                      realtime=False, **kw)


def test_record_replay_round_trip_is_bit_exact(tmp_path: Path) -> None:
    stats = record(_fake(), tmp_path / "ds")
    ds = EurocDataset(tmp_path / "ds")
    want = list(_fake().messages())
    want_imu = [m for m in want if isinstance(m, ImuSample)]
    want_frames = [m for m in want if isinstance(m, StereoFrame)]
    assert stats.imu == len(want_imu) == len(ds.imu) == 201
    assert stats.frames == len(want_frames) == len(ds) == 21
    np.testing.assert_array_equal(ds.imu.t_ns, [m.t_ns for m in want_imu])
    assert np.array_equal(ds.imu.gyro, np.array([m.gyro for m in want_imu]))  # exact, not approximately
    assert np.array_equal(ds.imu.accel, np.array([m.accel for m in want_imu]))
    got_frames = list(ds.frames())
    for a, b in zip(got_frames, want_frames):
        assert a.t_ns == b.t_ns
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    # the calibration travels with the data
    c0, w0 = ds.calibration.cam0, _fake().calibration().cam0
    np.testing.assert_allclose(c0.K, w0.K)
    np.testing.assert_allclose(c0.T_body_cam, w0.T_body_cam, atol=1e-12)
    assert abs(ds.calibration.baseline_m - _fake().calibration().baseline_m) < 1e-12
    # events() merges the streams back in time order, as `vio replay` consumes them
    ev = list(ds.events())
    assert len(ev) == 222 and all(a.t_ns <= b.t_ns for a, b in zip(ev, ev[1:]))


def test_record_stops_on_event_and_refuses_to_overwrite(tmp_path: Path) -> None:
    stop = threading.Event()
    src = FakeSource(width=64, height=64, fps=20, realtime=True)
    src.start()  # builds the simulated flight (about a second) before the clock of the test runs
    threading.Timer(0.4, stop.set).start()
    stats = record(src, tmp_path / "ds", stop=stop)
    assert stats.frames >= 3 and stats.imu >= 40
    assert len(EurocDataset(tmp_path / "ds").imu) == stats.imu
    with pytest.raises(VioError, match="refusing to overwrite"):
        record(_fake(), tmp_path / "ds")
    # --overwrite replaces the old recording whole: its images stayed beside the new CSVs (a review's finding)
    old_pngs = {p.name for p in (tmp_path / "ds" / "mav0" / "cam0" / "data").iterdir()}
    stop2 = threading.Event()
    src2 = FakeSource(width=64, height=64, fps=20, realtime=True)
    src2.start()
    threading.Timer(0.3, stop2.set).start()
    again = record(src2, tmp_path / "ds", stop=stop2, overwrite=True)
    pngs = {p.name for p in (tmp_path / "ds" / "mav0" / "cam0" / "data").iterdir()}
    assert len(pngs) == again.frames == len(EurocDataset(tmp_path / "ds")) and old_pngs


def test_euroc_source_replays_a_dataset_unchanged(v101_path: Path, tmp_path: Path) -> None:
    src = EurocSource(v101_path, realtime=False, batch=500)
    ds = EurocDataset(v101_path)
    t_end = int(ds.frame_t[10])
    stats = record(src, tmp_path / "copy", duration_s=(t_end - int(ds.imu.t_ns[0])) / 1e9)
    copy = EurocDataset(tmp_path / "copy")
    assert stats.frames == len(copy) == 11
    n = len(copy.imu)
    np.testing.assert_array_equal(copy.imu.t_ns, ds.imu.t_ns[:n])
    assert np.array_equal(copy.imu.gyro, ds.imu.gyro[:n])
    assert np.array_equal(copy.frame(3).left, ds.frame(3).left)


def _start_recorder(tmp_path: Path, out: Path) -> subprocess.Popen:
    cfg = tmp_path / "rec.toml"
    cfg.write_text('[source]\nkind = "fake"\nwidth = 160\nheight = 100\nfps = 20.0\nimu_rate_hz = 200.0\n')
    return subprocess.Popen([sys.executable, "-m", "vio.app.cli", "record", str(out), "--config", str(cfg),
                             "--duration", "60"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _wait_rows(path: Path, rows: int, proc: subprocess.Popen, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.is_file() and path.read_text().count("\n") > rows:
            return
        if proc.poll() is not None:
            raise AssertionError(f"recorder exited early: {proc.stdout.read().decode()}")
        time.sleep(0.05)
    raise AssertionError(f"recorder wrote fewer than {rows} rows to {path} in {timeout_s} s")


def test_killed_recorder_leaves_a_readable_dataset(tmp_path: Path) -> None:
    """SIGKILL (power cut) after a few seconds: everything but about the last second is readable."""
    out = tmp_path / "ds"
    proc = _start_recorder(tmp_path, out)
    try:
        imu_csv = out / "mav0" / "imu0" / "data.csv"
        _wait_rows(imu_csv, 10, proc)
        time.sleep(2.5)
        t_kill = time.monotonic_ns()
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    ds = EurocDataset(out)
    # stamps are host monotonic ns of the recorder, the same clock as ours: at most ~1 s was lost
    assert t_kill - int(ds.imu.t_ns[-1]) < 1_200_000_000
    assert (ds.imu.t_ns[-1] - ds.imu.t_ns[0]) > 2.0e9
    assert len(ds) >= 40 and len(list(ds.frames())) == len(ds)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_flushes_and_exits_cleanly(tmp_path: Path, sig: signal.Signals) -> None:
    """SIGTERM, and SIGHUP (`vio record` over ssh whose session ends: it killed the recorder, exit 129, the data since
    the last flush lost, 0.56 s, and the IMU csv cut mid-row; an integrator's walk-through): flushed, exit 0."""
    out = tmp_path / "ds"
    proc = _start_recorder(tmp_path, out)
    try:
        _wait_rows(out / "mav0" / "imu0" / "data.csv", 10, proc)
        time.sleep(0.5)
        proc.send_signal(sig)
        t_term = time.monotonic_ns()
        rc = proc.wait(timeout=15)
        log = proc.stdout.read().decode()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert rc == 0, log
    assert f"{sig.name} received: finishing the recording" in log and "recorded" in log
    ds = EurocDataset(out)
    assert t_term - int(ds.imu.t_ns[-1]) < 100_000_000  # flushed up to the signal, not the last fsync
    assert (out / "mav0" / "imu0" / "data.csv").read_bytes().endswith(b"\n")


class _LateCamera(FakeSource):
    """The IMU streams 0.5 s before the first camera frame (an OAK's cameras boot after its IMU)."""

    def poll(self):
        return [m for m in super().poll() if isinstance(m, ImuSample) or m.t_ns >= T0 + 500_000_000]


def test_duration_counts_from_the_later_stream_and_an_empty_stream_fails_the_command(tmp_path: Path, caplog) -> None:
    stats = record(_LateCamera(width=160, height=100, fps=20, imu_rate_hz=200, duration_s=2.0, t0_ns=T0,
                               realtime=False), tmp_path / "late", duration_s=1.0)
    assert stats.frames == 21  # 1 s of video (0.5-1.5 s), not 0.5 s
    # `vio record` whose IMU never delivers: the frames are kept, but the command fails and says why
    pytest.importorskip("serial")
    from vio.app.cli import main

    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[source]\nkind = "fake"\nwidth = 160\nheight = 100\nimu = "serial"\n'
                   f'serial_port = "{tmp_path / "ttyNOPE0"}"\n')
    with caplog.at_level("ERROR"):
        rc = main(["record", str(tmp_path / "noimu"), "--duration", "1", "--config", str(cfg)])
    assert rc == 1 and any("no IMU sample was recorded" in r.getMessage() for r in caplog.records)
    assert (tmp_path / "noimu" / "mav0" / "cam0" / "data.csv").exists()
    (tmp_path / "afile").write_text("x")
    assert main(["record", str(tmp_path / "afile"), "--duration", "1", "--config", str(cfg)]) == 1


def test_an_existing_recording_is_refused_before_the_source_opens(tmp_path: Path, monkeypatch, capsys) -> None:
    """`vio record` opened the source (an OAK takes seconds) before the writer refused an existing OUT (a QA sweep):
    now said first, for both formats, and the old data is untouched."""
    import drivers.source
    from vio.app.cli import main

    (tmp_path / "old" / "mav0" / "imu0").mkdir(parents=True)
    (tmp_path / "old" / "mav0" / "imu0" / "data.csv").write_text("kept\n")
    (tmp_path / "old.mcap").write_bytes(b"kept")
    opened = []
    monkeypatch.setattr(drivers.source, "open_source", lambda cfg: opened.append(cfg))
    for argv in (["record", str(tmp_path / "old"), "--source", "fake"],
                 ["record", str(tmp_path / "old.mcap"), "--source", "fake", "--format", "mcap"]):
        assert main([*argv, "--duration", "1"]) == 1
        assert "refusing to overwrite recorded data" in capsys.readouterr().err
    assert not opened
    assert (tmp_path / "old" / "mav0" / "imu0" / "data.csv").read_text() == "kept\n"
    assert (tmp_path / "old.mcap").read_bytes() == b"kept"


def test_an_output_that_cannot_be_written_is_refused_before_the_source_opens(tmp_path: Path, monkeypatch,
                                                                            capsys) -> None:
    """`vio record` into a place it cannot write opened the source (an OAK takes seconds), then failed at the first
    write with "what was written before stays readable" where nothing was (a QA sweep). Said first, one line,
    exit 1 as the command's other refusals of OUT, nothing left behind. Tried by writing (os.access says yes to
    root in a mode-555 folder and in /proc)."""
    import drivers.source
    from vio.app.cli import main

    (tmp_path / "afile").write_text("x")
    opened = []
    monkeypatch.setattr(drivers.source, "open_source", lambda cfg: opened.append(cfg))
    cases = [([str(tmp_path / "afile" / "rec")], f"{tmp_path / 'afile'} is a file, not a folder"),
             ([str(tmp_path / "afile" / "r.mcap"), "--format", "mcap"], "is a file, not a folder"),
             # the MCAP writer makes no folder (the EuRoC one makes OUT and its parents)
             ([str(tmp_path / "none" / "r.mcap"), "--format", "mcap"], f"folder {tmp_path / 'none'} does not exist")]
    if Path("/proc/self").is_dir():  # Linux: no file can be made in /proc, by root neither
        cases += [(["/proc/kestrel-vio-test-rec"], "folder /proc cannot be written"),
                  (["/proc/kestrel-vio-test.mcap", "--format", "mcap"], "folder /proc cannot be written")]
    if os.geteuid() != 0:  # root writes in a mode-555 folder
        (tmp_path / "ro").mkdir(mode=0o555)
        cases.append(([str(tmp_path / "ro" / "rec")], f"folder {tmp_path / 'ro'} cannot be written"))
    for argv, says in cases:
        assert main(["record", *argv, "--source", "fake", "--duration", "1"]) == 1, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"vio record: error: {argv[0]}: cannot record there: ") \
            and says in err[0], err
    assert not opened
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["afile"] + (["ro"] if os.geteuid() != 0 else []))
    assert not (tmp_path / "ro").exists() or not list((tmp_path / "ro").iterdir())  # the try left nothing


def test_a_full_disk_while_recording_mcap_is_one_line_not_an_internal_error(tmp_path: Path) -> None:
    """A file size limit (or a full disk) during an MCAP recording ended in "internal error: OSError: [Errno 27]
    File too large" (a QA sweep); the EuRoC writer named its file. Now one line, exit 1, and the part written
    before stays readable."""
    import resource

    pytest.importorskip("mcap")
    cfg = tmp_path / "c.toml"
    cfg.write_text('[source]\nkind = "fake"\nwidth = 160\nheight = 100\nrealtime = false\n')
    out = tmp_path / "r.mcap"
    limit = 400_000

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    r = subprocess.run([sys.executable, "-m", "vio.app.cli", "-q", "record", str(out), "--config", str(cfg),
                        "--format", "mcap", "--duration", "20"], capture_output=True, text=True, timeout=120,
                       preexec_fn=small_files)
    assert r.returncode == 1 and "cannot write the recording (File too large)" in r.stderr, r.stderr
    assert "internal error" not in r.stderr and 0 < out.stat().st_size <= limit


def test_the_span_said_is_the_recording_with_both_streams(tmp_path: Path, monkeypatch, caplog) -> None:
    """`vio record --duration 10` with a serial IMU said 'over 12.21 s': the IMU samples from before the first camera
    frame were counted. The span said is now the one `--duration` counts (from the stream that started last), and
    the other stream's lead is said beside it."""
    import drivers.source
    from vio.app.cli import main

    monkeypatch.setattr(drivers.source, "open_source", lambda cfg: _LateCamera(
        width=160, height=100, fps=20, imu_rate_hz=200, duration_s=3.0, t0_ns=T0, realtime=False))
    cfg = tmp_path / "c.toml"
    cfg.write_text('[source]\nkind = "fake"\n')
    with caplog.at_level("INFO"):
        assert main(["record", str(tmp_path / "rec"), "--duration", "1", "--config", str(cfg)]) == 0
    said = next(r.getMessage() for r in caplog.records if r.getMessage().startswith("recorded "))
    assert "IMU samples over 1.00 s (from the first stereo frame; IMU from 0.50 s before it) to" in said, said


def test_the_lead_said_is_from_the_streams_first_stamps_not_the_first_received() -> None:
    """The lead of the stream that started first was counted from the first message received: a later IMU sample
    handed over before an earlier frame made a frames' lead 0 (not said), or shorter than it was."""
    from drivers.record import RecordStats

    st = RecordStats(first_frame_t_ns=T0, first_imu_t_ns=T0 + 300_000_000, last_imu_t_ns=T0 + 1_300_000_000)
    assert st.lead_s == pytest.approx(0.3) and st.leading_stream == "stereo frames" and st.span_s == pytest.approx(1.0)
    st = RecordStats(first_frame_t_ns=T0 + 200_000_000, first_imu_t_ns=T0, last_imu_t_ns=T0 + 1_200_000_000)
    assert st.lead_s == pytest.approx(0.2) and st.leading_stream == "IMU"
    assert RecordStats(first_imu_t_ns=T0, last_imu_t_ns=T0 + 1).leading_stream is None


def test_an_output_name_over_the_file_system_s_limit_is_refused_in_one_line(tmp_path: Path, monkeypatch,
                                                                           capsys) -> None:
    """A name over 255 bytes in OUT was 'internal error: OSError: [Errno 36] File name too long': Path.exists()
    raises it, in the refusal of a recorded OUT and in folder_problem's check of an MCAP file's folder, which said
    it caught a name over the limits."""
    import drivers.source
    from vio.app.cli import main
    from vio.io.outputs import folder_problem

    long = tmp_path / ("n" * 300)
    opened = []
    monkeypatch.setattr(drivers.source, "open_source", lambda cfg: opened.append(cfg))
    for argv in ([str(long / "rec")], [str(long)], [str(long / "r.mcap"), "--format", "mcap"],
                 [f"{long}.mcap", "--format", "mcap"]):
        capsys.readouterr()
        assert main(["record", *argv, "--source", "fake", "--duration", "1"]) == 1, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"vio record: error: {argv[0]}: cannot record there: ") \
            and "File name too long" in err[0], err
    assert not opened
    assert "File name too long" in (folder_problem(long, made=False) or "")


def test_an_imu_unplugged_while_recording_fails_the_command_and_says_so(tmp_path: Path) -> None:
    """A serial IMU (a pty speaking the framed protocol) that goes away part-way: `vio record` said "recorded 161
    stereo frames and 931 IMU samples over 8.00 s", exit 0, though the IMU had stopped before the first frame (an
    integrator's walk-through). Now an error names the stream that stopped, how long before the end, and its driver's
    error; exit 1; what was recorded is kept and replays up to the IMU's end."""
    import pty
    import tty

    pytest.importorskip("serial")
    from drivers.reference_sender import imu_frames

    master, slave = pty.openpty()
    tty.setraw(slave)
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[source]\nkind = "fake"\nwidth = 160\nheight = 100\nimu = "serial"\n'
                   f'serial_port = "{os.ttyname(slave)}"\n')
    out = tmp_path / "rec"
    proc = subprocess.Popen([sys.executable, "-m", "vio.app.cli", "record", str(out), "--config", str(cfg),
                             "--duration", "4"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        t_start = time.monotonic()
        frames = imu_frames(10**6, 400.0, t0_us=int(t_start * 1e6))
        cam0 = out / "mav0" / "cam0" / "data.csv"
        k, stop_at = 0, None
        while stop_at is None or time.monotonic() < stop_at:  # 400 Hz in real time until 1 s of camera frames
            due = t_start + k / 400.0
            time.sleep(max(0.0, due - time.monotonic()))
            os.write(master, next(frames).data)
            k += 1
            if stop_at is None and k % 40 == 0 and cam0.is_file() and cam0.read_text().count("\n") > 20:
                stop_at = time.monotonic() + 0.2
            assert time.monotonic() - t_start < 60 and proc.poll() is None, "no camera frames recorded"
        os.close(master)  # the cable pulled: the port goes away
        os.close(slave)
        master = slave = -1
        rc = proc.wait(timeout=60)
        log = proc.stdout.read().decode()
    finally:
        for fd in (master, slave):
            if fd >= 0:
                os.close(fd)
        if proc.poll() is None:
            proc.kill()
    assert rc == 1, log
    said = next((line for line in log.splitlines() if "the IMU stopped" in line), log)
    assert "s before the end of the recording (" in said and "serial IMU port" in said and "have no IMU" in said, said
    assert "Traceback" not in log
    ds = EurocDataset(out)  # kept, and readable
    last_frame = int(cam0.read_text().splitlines()[-1].split(",")[0])
    assert len(ds) > 20 and ds.imu.t_ns[-1] < last_frame - 1_000_000_000


class _Silent(FakeSource):
    """A stream silent between two stamps (`imu` or frames), the other going on."""

    def __init__(self, imu: bool, from_s: float, to_s: float) -> None:
        super().__init__(width=160, height=100, fps=20, imu_rate_hz=200, duration_s=4.0, t0_ns=T0, realtime=False)
        self.kind = ImuSample if imu else StereoFrame
        self.window = (T0 + int(from_s * 1e9), T0 + int(to_s * 1e9))

    def poll(self):
        lo, hi = self.window
        return [m for m in super().poll() if not (isinstance(m, self.kind) and lo < m.t_ns < hi)]


@pytest.mark.parametrize("imu, to_s, rc, says", [
    (False, 9.0, 1, "the stereo frames stopped 2.50 s before the end of the recording: the last 2.50 s of IMU have no "
                    "stereo frames"),
    (True, 3.0, 0, "the IMU had a gap of 1.50 s (ending 3.00 s into the recording): a replay resets there"),
])
def test_a_stream_that_stops_or_pauses_is_said(tmp_path: Path, monkeypatch, caplog, imu, to_s, rc, says) -> None:
    import drivers.source
    from vio.app.cli import main

    monkeypatch.setattr(drivers.source, "open_source", lambda cfg: _Silent(imu, 1.5, to_s))
    cfg = tmp_path / "c.toml"
    cfg.write_text('[source]\nkind = "fake"\n')
    with caplog.at_level("INFO"):
        assert main(["record", str(tmp_path / "rec"), "--config", str(cfg)]) == rc
    assert any(says in r.getMessage() for r in caplog.records), [r.getMessage() for r in caplog.records]


def test_a_full_disk_while_recording_euroc_says_so_and_keeps_what_was_written(tmp_path: Path) -> None:
    """A full disk in a EuRoC recording said only `vio record: error: OUT/mav0/cam1/data/T.png: cannot write image`
    (cv2.imwrite says no more), where `vio run`'s recorder says 'disk full' (an integrator's walk-through). Now the
    line says what most likely happened and that the recording so far stays readable; it is. A small tmpfs is the
    full disk (mounting needs root: skipped without)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(disk)], capture_output=True).returncode:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        cfg = tmp_path / "c.toml"
        cfg.write_text('[source]\nkind = "fake"\nwidth = 640\nheight = 400\nrealtime = false\n')
        out = disk / "rec"
        r = subprocess.run([sys.executable, "-m", "vio.app.cli", "-q", "record", str(out), "--config", str(cfg),
                            "--duration", "20"], capture_output=True, text=True, timeout=120)
        last = r.stderr.strip().splitlines()[-1]
        assert r.returncode == 1 and last.startswith(f"vio record: error: {out}: cannot write the recording ("), \
            r.stderr
        # an image that does not fit (640x400 PNGs, stored: 256 kB each) fails before a csv's next 4 kB page
        assert "cannot write image (disk full: " in last and "No space left on device" in last, last
        assert last.endswith("stopped; what was written before stays readable"), last
        assert "Traceback" not in r.stderr
        ds = EurocDataset(out)
        assert len(ds) > 5 and len(ds.imu.t_ns) > 50
    finally:
        subprocess.run(["umount", str(disk)], capture_output=True)


def test_a_calibration_for_another_image_size_is_refused_before_recording(tmp_path: Path) -> None:
    """`[source] calibration` for 320x200 images, the camera streaming 160x100: `vio record` wrote the file's size
    into the recording's sensor.yaml, exit 0, and `vio replay` then refused the recording ('images are 160x100 but the
    calibration is for 320x200'; an integrator's walk-through). Refused before the source opens now, as `vio run`
    refuses it, in one line; nothing is written."""
    from vio.calibration import save_calibration

    calib = tmp_path / "c320.yaml"
    save_calibration(FakeSource(width=320, height=200, fps=20, imu_rate_hz=200, duration_s=1.0,
                                realtime=False).calibration(), calib)
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[source]\nkind = "fake"\nwidth = 160\nheight = 100\nrealtime = false\ncalibration = "{calib}"\n')
    out = tmp_path / "rec"
    r = subprocess.run([sys.executable, "-m", "vio.app.cli", "record", str(out), "--config", str(cfg), "--duration",
                        "1"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1, r.stderr
    assert r.stderr.strip() == (f"vio record: error: {cfg}: [source] calibration = '{calib}' is for 320x200 images, "
                                "but the camera streams [source] width x height = 160x100: set width/height to the "
                                "calibrated size, or import the calibration for the streamed one (vio calib import "
                                "depthai FILE --size 160x100 -o CALIB.yaml)"), r.stderr
    assert not out.exists()


def test_a_calibration_of_another_camera_is_said_while_recording(tmp_path: Path) -> None:
    """A `[source] calibration` whose focal lengths are 1.4x the streaming camera's (another lens, another unit's
    import) went into the recording unsaid (an integrator's walk-through). Said once the source reports its own,
    as `vio run` says it; the recording goes on with the file (it wins, as in `vio run`)."""
    import dataclasses

    from vio.calibration import save_calibration

    own = FakeSource(width=160, height=100, fps=20, imu_rate_hz=200, duration_s=1.0, realtime=False).calibration()
    calib = tmp_path / "other.yaml"
    save_calibration(dataclasses.replace(own, cam0=dataclasses.replace(own.cam0, fx=own.cam0.fx * 1.4)), calib)
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[source]\nkind = "fake"\nwidth = 160\nheight = 100\nrealtime = false\ncalibration = "{calib}"\n')
    r = subprocess.run([sys.executable, "-m", "vio.app.cli", "record", str(tmp_path / "rec"), "--config", str(cfg),
                        "--duration", "1"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    said = [line for line in r.stderr.splitlines() if "ERROR" in line and "is not this fake source's camera" in line]
    assert len(said) == 1 and f"its cam0 focal length fx is {own.cam0.fx * 1.4:.1f} px, the camera's " \
        f"{own.cam0.fx:.1f} px" in said[0], r.stderr


def test_a_second_reader_of_the_serial_imu_is_refused_not_sharing_its_bytes(tmp_path: Path) -> None:
    """`vio record` run beside the service (docs/first-flight.md says to stop it first; forgotten) opened the serial
    IMU's port too, and the two readers split its bytes: the daemon's IMU fell from 400 to ~150 Hz with three
    estimator resets, and the recording was as torn, exit 0 (an integrator's walk-through). The port is held
    exclusively now: the second reader is refused with one line saying who may hold it, the first flies on."""
    pytest.importorskip("serial")
    sender = subprocess.Popen([sys.executable, "-m", "drivers.reference_sender", "--pty", "--rate", "400",
                               "--seconds", "120"], stdout=subprocess.PIPE, text=True)
    daemon = None
    try:
        port = sender.stdout.readline().strip()
        cfg = tmp_path / "c.toml"
        cfg.write_text(f'[source]\nkind = "fake"\nwidth = 160\nheight = 100\nimu = "serial"\nserial_port = "{port}"\n'
                       f'[run]\nstatus_file = "{tmp_path / "status.json"}"\n[mavlink]\ncounter_file = ""\n')
        log_path = tmp_path / "daemon.log"
        with open(log_path, "w") as log:
            daemon = subprocess.Popen([sys.executable, "-m", "vio.app.cli", "run", "--config", str(cfg)],
                                      stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        assert _wait_for(lambda: f"serial IMU port {port} open" in log_path.read_text(), 60), log_path.read_text()
        r = subprocess.run([sys.executable, "-m", "vio.app.cli", "record", str(tmp_path / "rec"), "--config", str(cfg),
                            "--duration", "2"], capture_output=True, text=True, timeout=120)
        assert r.returncode == 1, r.stderr
        assert f"serial IMU port {port} is held by another process (a running vio run, or vio record" in r.stderr
        assert daemon.poll() is None and f"serial IMU port {port} lost" not in log_path.read_text(), \
            log_path.read_text()[-3000:]
    finally:
        if daemon is not None:
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(15)
        sender.kill()
        sender.wait(10)


def _wait_for(cond, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.05)
    return False



def test_record_never_writes_into_the_dataset_its_euroc_source_replays(tmp_path: Path, capsys) -> None:
    """`vio record DATASET --overwrite` with `[source] kind = 'euroc'` replaying DATASET deleted its images as it read
    them (0 of 41 left, exit 1), and an MCAP file went into its mav0/ (a review's finding). Refused before the
    source opens, --overwrite or not; the dataset is left whole."""
    from vio.app.cli import main
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "flight"
    simulate(data, SimConfig(duration_s=2.0, width=188, height=120, variant="clean"), progress=False)
    images = sorted((data / "mav0" / "cam0" / "data").iterdir())
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"[source]\nkind = 'euroc'\ndataset = '{data}'\nrealtime = false\n")
    for argv in ([str(data), "--overwrite"], [str(data / "mav0" / "x.mcap"), "--format", "mcap"]):
        assert main(["-q", "record", *argv, "--config", str(cfg), "--duration", "1"]) == 1, argv
        err = capsys.readouterr().err
        assert f"would be written into the recording {data}" in err and len(err.strip().splitlines()) == 1, err
    assert sorted((data / "mav0" / "cam0" / "data").iterdir()) == images
    assert not (data / "mav0" / "x.mcap").exists()


def test_record_help_says_an_mcap_recording_replays_without_calib(capsys) -> None:
    """`vio record --help` said an MCAP recording replays with `vio replay OUT --calib ...`; the recorder writes its
    calibration into the file (kestrel-calibration.yaml, docs/formats.md) and `vio replay OUT` uses it, and our own
    EuRoC and MCAP recordings replay alike (an integrator's walk-through)."""
    from vio.app.cli import main

    with pytest.raises(SystemExit):
        main(["record", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "--calib ..." not in out and "vio replay OUT` reads it back with its calibration" in out, out


def _with_a_gap(root: Path, gap_ns: int) -> int:
    """Move every stamp from the middle of the recording on by `gap_ns` (a recorder paused, a clock jump); returns
    the first moved stamp."""
    t_cut = None
    for f in ("imu0", "cam0", "cam1"):
        p = root / "mav0" / f / "data.csv"
        lines = p.read_text().splitlines()
        t_cut = t_cut or int(lines[len(lines) // 2].split(",")[0])
        p.write_text("\n".join([lines[0]] + [f"{int(t) + (gap_ns if int(t) >= t_cut else 0)},{rest}" for t, rest in
                                             (ln.split(",", 1) for ln in lines[1:])]) + "\n")
    return t_cut


def test_a_realtime_euroc_source_does_not_wait_out_a_gap_in_the_recording(tmp_path: Path, caplog) -> None:
    """`vio run` with `[source] kind = "euroc"` waited through a gap in the recording's stamps in real time (an hour's
    gap, an hour of silence; past [run] source_timeout_s the daemon reopened the source, which played the recording
    from its start again), where `vio replay --realtime` skips it. The gap is shortened to GAP_KEPT_S (still a gap to
    the estimator, which restarts across it as after any IMU gap), with one warning."""
    GAP_KEPT_S = getattr(fake, "GAP_KEPT_S", 1.0)

    record(_fake(), tmp_path / "ds")
    _with_a_gap(tmp_path / "ds", 3600 * 10**9)
    n = len(list(EurocDataset(tmp_path / "ds").events()))
    src = EurocSource(tmp_path / "ds", realtime=True)
    src.start()
    got: list = []
    deadline = time.monotonic() + 1.0 + GAP_KEPT_S + 3.0  # 1 s of data, the shortened gap, a margin
    with caplog.at_level("WARNING", logger="drivers.fake"):
        while not src.finished and time.monotonic() < deadline:
            got += src.poll()
            time.sleep(0.005)
    assert src.finished and len(got) == n, f"{len(got)} of {n} messages in {deadline - time.monotonic() + 5:.1f} s"
    t = np.array([m.t_ns for m in got])
    steps = np.diff(np.sort(t))
    assert abs(steps.max() / 1e9 - GAP_KEPT_S) < 0.01 and np.sort(steps)[-2] < 0.01 * 1e9
    said = [r.getMessage() for r in caplog.records if r.name == "drivers.fake"]
    assert len(said) == 1 and "a gap of 3.6e+03 s" in said[0] and "not waited out" in said[0], said


def test_an_overwrite_that_records_nothing_keeps_the_recording_it_was_to_replace(tmp_path: Path, caplog) -> None:
    """`vio record OUT --overwrite` deleted the old recording as the writer opened, before any data came: a source
    that failed at once left nothing where a recording had been (the input review's note). The old one is kept beside
    until the new one has data, and put back when it ends with none; a recording with data replaces it whole."""
    record(_fake(), tmp_path / "ds", duration_s=0.5)
    old = sorted(p.name for p in (tmp_path / "ds" / "mav0" / "cam0" / "data").iterdir())
    assert old
    stopped = threading.Event()
    stopped.set()  # the source fails (or the user stops) before its first message
    with caplog.at_level("WARNING", logger="vio.io.euroc"):
        stats = record(_fake(), tmp_path / "ds", stop=stopped, overwrite=True,
                       calibration=EurocDataset(tmp_path / "ds").calibration)
    assert stats.frames == 0 and stats.imu == 0
    assert sorted(p.name for p in (tmp_path / "ds" / "mav0" / "cam0" / "data").iterdir()) == old
    assert "nothing was recorded; the recording that was there is kept" in caplog.text, caplog.text
    assert sorted(p.name for p in (tmp_path / "ds").iterdir()) == ["mav0"]
    again = record(_fake(), tmp_path / "ds", duration_s=0.3, overwrite=True)
    assert again.frames > 0 and len(EurocDataset(tmp_path / "ds")) == again.frames
    assert sorted(p.name for p in (tmp_path / "ds").iterdir()) == ["mav0"]  # the old one removed once data came


def test_an_mcap_overwrite_that_records_nothing_keeps_the_file_it_was_to_replace(tmp_path: Path, caplog) -> None:
    """The same for `vio record OUT.mcap --overwrite`: the file was truncated as the writer opened."""
    pytest.importorskip("mcap")
    out = tmp_path / "r.mcap"
    record(_fake(), out, duration_s=0.3, fmt="mcap")
    old = out.read_bytes()
    stopped = threading.Event()
    stopped.set()
    with caplog.at_level("WARNING", logger="vio.io.bag"):
        record(_fake(), out, stop=stopped, overwrite=True, fmt="mcap",
               calibration=EurocDataset(_recorded(tmp_path)).calibration)
    assert out.read_bytes() == old and "nothing was recorded; the file that was there is kept" in caplog.text
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("r.")) == ["r.mcap"]
    record(_fake(), out, duration_s=0.6, fmt="mcap", overwrite=True)  # the fake source repeats itself: longer
    assert len(out.read_bytes()) > len(old) and not (tmp_path / "r.mcap.replaced").exists()


def _recorded(tmp_path: Path) -> Path:
    """A small EuRoC recording of the fake source (for its calibration)."""
    if not (tmp_path / "cal" / "mav0").is_dir():
        record(_fake(), tmp_path / "cal", duration_s=0.2)
    return tmp_path / "cal"
