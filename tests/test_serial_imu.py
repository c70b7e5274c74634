"""Serial IMU: protocol, resynchronising parser, clock sync, and the threaded source on a real pty."""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
import time
import tty
from pathlib import Path

import numpy as np
import pytest

from drivers.reference_sender import LinkFaults, corrupt_link, imu_frames
from drivers.serial_imu import SerialImuSource
from drivers.serial_protocol import IMU_FRAME_SIZE, FrameParser, crc16, encode_imu
from drivers.timesync import ClockSync, StreamMonitor
from vio.types import ImuSample

RATE = 400.0


def test_crc_is_ccitt_false() -> None:
    assert crc16(b"123456789") == 0x29B1  # the published check value of CRC-16/CCITT-FALSE


def test_encode_decode_round_trip_and_scale() -> None:
    f = encode_imu(7, 123456789, np.array([0.1, -0.2, 3.0]), np.array([-9.81, 0.0, 1e-5]))
    assert len(f) == IMU_FRAME_SIZE
    (raw,) = FrameParser().feed(f)
    assert raw.seq == 7 and raw.t_us == 123456789
    np.testing.assert_allclose(raw.gyro, [0.1, -0.2, 3.0], atol=1e-6)
    np.testing.assert_allclose(raw.accel, [-9.81, 0.0, 1e-5], atol=1e-5)


def test_byte_by_byte_feed_and_split_sync() -> None:
    frames = list(imu_frames(20, RATE))
    stream = b"\xa5" + b"".join(f.data for f in frames)  # a lone first sync byte is garbage
    p = FrameParser()
    got = [r.seq for i in range(len(stream)) for r in p.feed(stream[i:i + 1])]
    assert got == list(range(20))
    assert p.stats.bytes_discarded == 1 and p.stats.crc_errors == 0


def test_parser_recovers_every_good_frame_and_counts_every_bad_one() -> None:
    frames = list(imu_frames(4000, RATE))
    faults = LinkFaults(garbage=0.05, truncate=0.03, bitflip=0.03, baud_burst=0.02)
    stream, intact, damaged = corrupt_link(frames, faults, seed=3)
    assert damaged > 100 and intact[-1] == len(frames) - 1
    p = FrameParser()
    rng = np.random.default_rng(1)
    got, i = [], 0
    while i < len(stream):  # random read sizes, as a UART driver returns them
        n = int(rng.integers(1, 200))
        got += p.feed(stream[i:i + n])
        i += n
    assert [r.seq for r in got] == [frames[k].seq for k in intact]
    for r in got[:50]:
        f = frames[r.seq]
        np.testing.assert_allclose(r.gyro, f.gyro, atol=1e-6)
    s = p.stats
    assert s.seq_lost == damaged  # every damaged frame is accounted for
    assert s.crc_errors + s.bad_length > 0 and s.bytes_discarded > 0
    assert s.bytes_in == len(stream)


def test_clock_sync_recovers_offset_and_drift_from_positive_delays() -> None:
    rng = np.random.default_rng(0)
    offset_ns, drift = 5_000_000_000, 50e-6  # host runs 50 ppm fast against the device
    cs = ClockSync(block_s=1.0, window_s=20.0)
    t_dev = np.arange(0, int(30e9), int(2.5e6))
    delay = rng.exponential(2e6, size=len(t_dev)) + 3e5  # >= 0.3 ms, mean 2.3 ms, heavy tail
    host = offset_ns + t_dev * (1 + drift) + delay
    for td, th in zip(t_dev, host):
        cs.add(int(td), int(th))
    est = cs.estimate
    assert est is not None
    assert abs(est.drift_ppm - 50.0) < 5.0
    # converted stamps sit at the true sample time plus about the minimum latency, not the mean one
    err = np.array([cs.to_host(int(td)) - (offset_ns + td * (1 + drift)) for td in t_dev[-400:]])
    assert np.all(np.abs(err - 3e5) < 2e5), (err.min(), err.max())


def _feed_rate(cs: ClockSync, rate: float, seconds: float = 40.0, seed: int = 1) -> np.ndarray:
    """400 Hz device stamps from a clock running at `rate` x the host's, arriving 1-3 ms late; returns the stamp
    error (mapped - true) of the last 10 s."""
    rng = np.random.default_rng(seed)
    t_true = np.arange(0, int(seconds * 1e9), 2_500_000)
    t_dev = (t_true * rate).astype(np.int64)
    arrival = t_true + rng.uniform(1e6, 3e6, len(t_true)).astype(np.int64)
    err = []
    for k, (td, ta) in enumerate(zip(t_dev, arrival)):
        cs.add(int(td), int(ta))
        if t_true[k] >= (seconds - 10) * 1e9:
            err.append(cs.to_host(int(td)) - int(t_true[k]))
    return np.array(err)


@pytest.mark.parametrize("rate", [0.99, 1.02])
def test_clock_sync_follows_an_rc_oscillator_a_few_percent_off(rate, caplog) -> None:
    """An MCU on its internal RC oscillator runs up to ~2 % off. The fit used to be clamped at 0.1 %: on a 1 % slow
    clock every stamp came out ~185 ms early, unsaid (a review's finding). The warning says which way: it said
    "+0.38 %" for an ArduPilot SITL whose clock fell behind, and was read as one running fast."""
    cs = ClockSync()
    with caplog.at_level(logging.WARNING, logger="drivers.timesync"):
        err = _feed_rate(cs, rate)
    assert np.all(np.abs(err - 1e6) < 1e6), (err.min(), err.max())  # within the minimum latency (1 ms) +- 1 ms
    assert cs.problem is None and abs(cs.estimate.drift_ppm - 1e6 * (1 / rate - 1)) < 200
    said = [r.getMessage() for r in caplog.records if "check the device's oscillator" in r.getMessage()]
    assert len(said) == 1 and f"% {'slower' if rate < 1 else 'faster'} than the host's" in said[0], said


@pytest.mark.parametrize("stall", [(1.9, 3.1), (5.2, 7.4), (10.1, 11.3)])
def test_a_stalled_reader_does_not_bend_the_clock_fit(stall, caplog) -> None:
    """A reader that stalls 1-2 s (CPU, GIL) hands a burst over late: one high block minimum. A least-squares line
    that may reach 5 % followed it, 20-86 ms off for 20 s (a review's finding); the median slope does not."""
    cs = ClockSync()
    rng = np.random.default_rng(0)
    t_true = np.arange(0, int(25e9), 2_500_000)
    arrival = (t_true + rng.uniform(1e6, 3e6, len(t_true))).astype(np.int64)
    stalled = (t_true >= stall[0] * 1e9) & (t_true < stall[1] * 1e9)
    arrival[stalled] = int(stall[1] * 1e9) + 2_000_000
    err = []
    with caplog.at_level(logging.WARNING, logger="drivers.timesync"):
        for td, ta in zip(t_true, arrival):
            cs.add(int(td), int(ta))
            err.append(cs.to_host(int(td)) - int(td))
    err = np.abs(np.array(err, float))[~stalled & (t_true >= 1e9)] / 1e6
    assert err.max() < 5.0, err.max()
    assert cs.problem is None and not any("oscillator" in r.getMessage() for r in caplog.records)


def test_the_clock_fit_imports_nothing_while_the_sensor_streams() -> None:
    """The fit runs in the sensor's reader thread. Its first median slope (3 s in) imported scipy.stats there: 1.2 s
    of a loaded 2-core machine in which the MAVLink IMU read nothing, so every ArduPilot SITL flight began with 'no
    estimate for 0.5 s' and a 'VIO tracking lost' on the ground. A fresh interpreter with the sources' modules
    loaded, as the daemon's is when the samples start."""
    code = (
        "import sys\n"
        "import numpy as np\n"
        "import drivers.mavlink_imu, drivers.serial_imu  # the sources whose reader threads run the fit\n"
        "from drivers.timesync import ClockSync\n"
        "cs = ClockSync()\n"
        "before = set(sys.modules)\n"
        "t = np.arange(0, int(8e9), 2_500_000)\n"
        "for td in t:\n"
        "    cs.add(int(td), int(td) + 1_000_000 + int(td) % 2_000_000)\n"
        "assert cs.estimate is not None and cs.estimate.n_blocks >= 5, cs.estimate\n"
        "print(' '.join(sorted(set(sys.modules) - before)))\n")
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=root, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == [], f"imported while streaming: {res.stdout.split()[:8]}"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_median_slope_is_scipys_theil_sen(seed: int) -> None:
    """The same slope scipy.stats.theilslopes gives (blocks with equal device times included), bit for bit."""
    from scipy.stats import theilslopes

    from drivers.timesync import _theil_sen

    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 20, 21)).astype(np.float64) * 1e9
    d = rng.normal(0.0, 1e6, len(t)) + 3e-3 * t
    assert _theil_sen(t, d) == float(theilslopes(d, t).slope)
    assert _theil_sen(np.full(4, 5e9), d[:4]) == 0.0


def test_a_clock_rate_beyond_what_the_sync_follows_withholds_the_samples() -> None:
    """10 % off: no fit can be trusted; the source queues nothing (no IMU, no pose) and says why."""
    cs = ClockSync()
    _feed_rate(cs, 0.9, seconds=10)
    assert cs.problem and "beyond" in cs.problem and cs.as_dict()["problem"] == cs.problem
    src = SerialImuSource(port="/dev/null", clock=cs)
    frames = b"".join(encode_imu(k, 20_000_000 + 2500 * k, np.zeros(3), np.array([0, 0, 9.81])) for k in range(10))
    src.feed(frames, 30_000_000_000)
    assert src.poll() == [] and src.health()["clock_withheld"] == 10 and "beyond" in src.health()["last_error"]


def test_the_serial_imu_says_how_far_its_stamps_may_be_off() -> None:
    """SensorSource.stamp_uncertainty_s of the arrival-time fit, fed as the reader feeds it (4 frames per read every
    10 ms, 1-3 ms late): unknown (inf) before the first frame; under 1 ms on a healthy link and through a reader that
    stalls 0.4 s (the stamps are right: the output's 5 ms tolerance leaves everything sent as it was); when the
    device clock falls 100 ms behind (within 0.3 s, at 20 s), which the envelope takes for delay and does not
    follow until such blocks make half its 20 s window, over the 50 ms refusal bound within a second and for as long
    as the stamps are that far off; and inf while the clock runs beyond what the fit follows (no sample is delivered
    then)."""
    rng = np.random.default_rng(2)
    src = SerialImuSource(port="/dev/null")
    assert src.stamp_uncertainty_s() == float("inf")
    g, a = np.zeros(3), np.array([0.0, 0.0, 9.81])
    rows = []
    for read in range(2800):  # 28 s
        h = read * 10_000_000
        made = [h - 7_500_000 + 2_500_000 * i for i in range(4)]  # host time each frame was made
        lag = [100e6 * min(max((m / 1e9 - 20.0) / 0.3, 0.0), 1.0) for m in made]
        chunk = b"".join(encode_imu(4 * read + i, int((1e9 + m - d) / 1000), g, a) for i, (m, d) in
                         enumerate(zip(made, lag)))
        arrival = h + int(rng.uniform(1e6, 3e6))
        if 10.0 <= h / 1e9 < 10.4:  # the reader stalled: these reads come in at its end
            arrival = int(10.4e9) + 1_000_000
        src.feed(chunk, arrival)
        got = src.poll()
        if got and read % 5 == 0:
            rows.append((h / 1e9, (got[-1].t_ns - (h - 1e9)) / 1e6, src.stamp_uncertainty_s() * 1e3))
    r = np.array(rows)
    t, err, meas = r[:, 0], np.abs(r[:, 1] - np.median(r[(r[:, 0] > 2) & (r[:, 0] < 20), 1])), r[:, 2]
    healthy = (t > 2) & (t < 20)  # the stall at 10 s included
    assert err[healthy].max() < 2.0 and meas[healthy].max() < 1.0, (err[healthy].max(), meas[healthy].max())
    stepped = t > 21.0
    assert err[stepped].min() > 95 and meas[stepped].min() > 50, (err[stepped].min(), meas[stepped].min())
    src.clock.problem = "device clock runs -10.00 % against the host's"  # as _check_rate sets it
    assert src.stamp_uncertainty_s() == float("inf")


def test_clock_sync_restarts_on_device_reset() -> None:
    cs = ClockSync(block_s=0.1)
    for k in range(100):
        cs.add(k * 10_000_000, 1_000_000_000 + k * 10_000_000)
    cs.add(0, 2_000_000_000)  # device rebooted: its clock starts again at 0
    assert cs.resets == 1
    assert cs.to_host(0) == 2_000_000_000


@pytest.mark.parametrize("one_read", [False, True])
def test_a_reboot_inside_one_read_places_each_frame_with_its_own_clock(one_read) -> None:
    """An MCU reboot whose last frames before and first after arrived in one read(): all of them were placed with
    the fit restarted after the reboot, the old frames 9 s in the future, and every sample after them dropped as
    out of order for as long as the device had been up (a QA sweep). One read or two: the same samples, in time."""
    src = SerialImuSource("/dev/null")
    g, a = np.zeros(3), np.array([0.0, 0.0, 9.81])
    host0, lat = 1_000_000_000_000, 2_000_000
    seq, t_us = 0, 1_000_000
    for _ in range(1000):  # 10 s at 400 Hz, four frames a read
        chunk = b""
        for _ in range(4):
            chunk += encode_imu(seq, t_us, g, a)
            seq, t_us = seq + 1, t_us + 2500
        src.feed(chunk, host0 + (t_us - 1_000_000) * 1000 + lat)
    host_now = host0 + (t_us - 1_000_000) * 1000
    before = encode_imu(seq, t_us, g, a) + encode_imu(seq + 1, t_us + 2500, g, a)
    after = encode_imu(0, 1000, g, a) + encode_imu(1, 3500, g, a)  # rebooted: its clock restarts near 0
    if one_read:
        src.feed(before + after, host_now + 5_000_000 + lat)
    else:
        src.feed(before, host_now + 5_000_000 + lat)
        src.feed(after, host_now + 5_000_000 + lat)
    r, h = 6000, host_now + 5_000_000 + lat
    for k in range(200):  # 2 s after the reboot
        chunk = b""
        for _ in range(4):
            chunk += encode_imu(2 + k * 4, r, g, a)
            r += 2500
        h += 10_000_000
        src.feed(chunk, h)
    t = np.array([m.t_ns for m in src.poll()])
    assert t.max() <= h and np.all(np.diff(t) > 0)
    assert len(t) >= 4000 and src.health()["stream"]["non_monotonic"] <= 2


def test_stream_monitor_counts_gaps_jumps_and_reversals() -> None:
    m = StreamMonitor("imu", 200.0)
    stamps = [0, 5, 10, 30, 35, 35, 34, 2000, 2005]
    kept = [m.check(t * 1_000_000) for t in stamps]
    assert kept == [True, True, True, True, True, False, False, True, True]
    assert (m.gaps, m.missing_estimate, m.non_monotonic, m.jumps) == (1, 3, 2, 1)


def _pty_pair() -> tuple[int, str]:
    master, slave = os.openpty()
    tty.setraw(slave)
    tty.setraw(master)
    return master, os.ttyname(slave)


def test_source_on_pty_at_400hz_with_faults() -> None:
    """The threaded source reads a real pseudo-terminal fed at 400 Hz in real time through a faulty link."""
    master, path = _pty_pair()
    frames = list(imu_frames(int(1.5 * RATE), RATE, t0_us=time.monotonic_ns() // 1000))
    stream_parts = []
    intact_all: list[int] = []
    damaged_all = 0
    chunk = 8
    for j in range(0, len(frames), chunk):
        part, intact, damaged = corrupt_link(frames[j:j + chunk], LinkFaults(0.05, 0.02, 0.02, 0.02), seed=j)
        stream_parts.append(part)
        intact_all += [j + k for k in intact]
        damaged_all += damaged
    last_ok = intact_all[-1] == len(frames) - 1
    if not last_ok:
        stream_parts.append(frames[-1].data)  # resend the last frame so a trailing loss shows in the sequence
    want = len(intact_all) + (0 if last_ok else 1)
    src = SerialImuSource(path, 921600, nominal_rate_hz=RATE)
    src.start()
    try:
        t0 = time.monotonic()
        for j, part in enumerate(stream_parts):  # paced like the sensor: 8 frames every 20 ms
            due = t0 + (j + 1) * chunk / RATE
            time.sleep(max(0.0, due - time.monotonic()))
            os.write(master, part)
        got: list[ImuSample] = []
        deadline = time.monotonic() + 5.0
        while len(got) < want and time.monotonic() < deadline:
            got += src.poll()
            time.sleep(0.01)
    finally:
        src.stop()
        os.close(master)
    h = src.health()
    assert h["parser"]["frames_ok"] == want
    assert h["parser"]["seq_lost"] == damaged_all - (0 if last_ok else 1)
    assert len(got) + h["stream"]["non_monotonic"] == want
    t = np.array([s.t_ns for s in got])
    assert np.all(np.diff(t) > 0)
    # stamps are on the host clock (the sender stamped with monotonic us): only the pty latency and this
    # test's own pacing delays separate them; accuracy is tested deterministically in the ClockSync test
    assert 0 <= int(t[-1]) - frames[-1].t_us * 1000 < 250_000_000
    assert h["clock"]["blocks"] >= 1


def test_source_survives_missing_port_and_reports_it() -> None:
    src = SerialImuSource("/dev/does-not-exist-kestrel", 115200, backoff_max_s=0.05)
    src.start()
    deadline = time.monotonic() + 2.0
    while src.open_failures < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    src.stop()
    h = src.health()
    assert h["open_failures"] >= 2 and "does-not-exist-kestrel" in h["last_error"]
    assert src.poll() == []


def test_source_reconnects_after_unplug() -> None:
    """A port that raises mid-read (cable pulled) is reopened; data after the reconnect flows again."""
    frames = list(imu_frames(40, RATE, t0_us=time.monotonic_ns() // 1000))
    opened = []

    class FlakyPort:
        """Delivers its frames in real time (none before its device time), then fails if asked to."""

        def __init__(self, frames: list, fail: bool) -> None:
            self.frames, self.fail, self.in_waiting = list(frames), fail, 0

        def read(self, n: int) -> bytes:
            time.sleep(0.005)
            now_us = time.monotonic_ns() // 1000
            ready = [f for f in self.frames if f.t_us <= now_us]
            self.frames = self.frames[len(ready):]
            if not ready and not self.frames and self.fail:
                raise OSError(5, "Input/output error")
            return b"".join(f.data for f in ready)

        def close(self) -> None:
            pass

    def factory(port: str, baud: int, timeout: float) -> FlakyPort:
        opened.append(port)
        first = len(opened) == 1
        return FlakyPort(frames[:20] if first else frames[20:], fail=first)

    src = SerialImuSource("/dev/ttyFAKE", 921600, serial_factory=factory, nominal_rate_hz=RATE)
    src.start()
    got: list = []
    deadline = time.monotonic() + 3.0
    while len(got) < 40 and time.monotonic() < deadline:
        got += src.poll()
        time.sleep(0.01)
    src.stop()
    assert len(got) == 40 and src.disconnects == 1 and len(opened) >= 2


def test_c_sender_is_byte_identical() -> None:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    src = os.path.join(os.path.dirname(__file__), "..", "tools", "serial_imu_sender.c")
    exe = os.path.join(os.environ.get("TMPDIR", "/tmp"), f"kestrel_sender_{os.getpid()}")
    subprocess.run([cc, "-std=c99", "-Wall", "-Werror", "-DKESTREL_SENDER_MAIN", "-o", exe, src], check=True)
    try:
        frames = list(imu_frames(50, RATE, t0_us=2**40 + 17))
        lines = []
        for f in frames:
            g = np.round(f.gyro / 1e-6).astype(int)
            a = np.round(f.accel / 1e-5).astype(int)
            lines.append(" ".join(map(str, [f.seq, f.t_us, *g, *a])))
        res = subprocess.run([exe], input="\n".join(lines) + "\n", capture_output=True, text=True, check=True)
        assert res.stdout.split() == [f.data.hex() for f in frames]
    finally:
        os.unlink(exe)


def test_the_pty_bench_sender_sends_only_while_a_reader_listens() -> None:
    """docs/serial-imu.md's bench (`python -m drivers.reference_sender --pty`, then `vio record`): the pty buffered the
    frames sent before the recorder opened it, which then got seconds-old frames in one burst: its clock sync placed
    them late, dropped ~350 samples as non-monotonic, and once restarted itself ('device clock jumped by 0.501 s'; an
    integrator's walk-through). A UART nobody reads loses them: the sender now sends only while a reader has the pty
    open, so the first frame read is a fresh one."""
    import select
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "drivers.reference_sender", "--pty", "--rate", "400", "--seconds",
                             "20"], stdout=subprocess.PIPE, text=True)
    try:
        name = proc.stdout.readline().strip()
        time.sleep(1.0)  # a second of frames while nobody listens
        fd = os.open(name, os.O_RDONLY | os.O_NOCTTY)
        try:
            t_open_us = time.monotonic() * 1e6
            parser, frames = FrameParser(), []
            while not frames:
                assert select.select([fd], [], [], 5.0)[0], "no frame within 5 s of opening"
                frames = parser.feed(os.read(fd, 4096))
        finally:
            os.close(fd)
    finally:
        proc.kill()
        proc.wait(10)
    # the sender's device clock is time.monotonic in microseconds: the first frame read is from after the open
    assert frames[0].t_us > t_open_us - 50_000, (t_open_us - frames[0].t_us) / 1e6
