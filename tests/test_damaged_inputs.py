"""`vio replay` on damaged copies of a short simulated flight, run as the user runs it (a fresh `vio`
process): bad input ends in one clear line and a non-zero exit, never a traceback; what can be repaired or
skipped is, with a warning, and the replay still writes its trajectory."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from vio.app.cli import EXIT_FAILURE

pytest.importorskip("vio.sim.generate")

W, H = 188, 120


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    from vio.sim.generate import SimConfig, simulate

    root = tmp_path_factory.mktemp("damaged") / "flight"
    simulate(root, SimConfig(profile="survey", duration_s=3.0, seed=3, width=W, height=H), progress=False)
    return root


def _vio(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.run([sys.executable, "-m", "vio.app.cli", *args], capture_output=True, text=True, timeout=timeout,
                          env=env)


def _replay_args(data: Path, *more: str) -> list[str]:
    return ["-q", "replay", str(data), "--output", str(data / "traj.tum"), "--stats", str(data / "stats.json"),
            "--no-progress", *more]


# ------------------------------------------------------------------------------------------------ damage

def _rows(path: Path) -> tuple[str, list[list[str]]]:
    lines = path.read_text().splitlines()
    return lines[0], [r.split(",") for r in lines[1:]]


def _put(path: Path, header: str, rows: list[list[str]], end: str = "\n") -> None:
    path.write_text("\n".join([header] + [",".join(r) for r in rows]) + end)


def _map_imu(mav0: Path, gyro=None, accel=None) -> None:
    imu = mav0 / "imu0" / "data.csv"
    header, rows = _rows(imu)
    out = []
    for r in rows:
        g, a = [float(x) for x in r[1:4]], [float(x) for x in r[4:7]]
        out.append([r[0]] + [repr(float(gyro(x) if gyro else x)) for x in g]
                   + [repr(float(accel(x) if accel else x)) for x in a])
    _put(imu, header, out)


def _restamp(path: Path, f) -> None:
    header, rows = _rows(path)
    _put(path, header, [[str(f(int(r[0])))] + r[1:] for r in rows])


def _cut_last_line(path: Path, keep: float = 0.6) -> None:
    text = path.read_text().rstrip("\n")
    last = text.rsplit("\n", 1)[1]
    path.write_text(text[: len(text) - len(last) + int(len(last) * keep)])


def _edit_yaml(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, (path, old)
    path.write_text(text.replace(old, new))


def _damage(mav0: Path, case: str) -> None:
    imu, cam0 = mav0 / "imu0" / "data.csv", mav0 / "cam0" / "data.csv"
    gt = mav0 / "state_groundtruth_estimate0" / "data.csv"
    yaml0 = mav0 / "cam0" / "sensor.yaml"
    images = sorted((mav0 / "cam0" / "data").iterdir())
    if case == "resolution":
        _edit_yaml(yaml0, f"resolution: [{W}, {H}]", f"resolution: [{2 * W}, {2 * H}]")
    elif case == "accel_in_g":
        _map_imu(mav0, accel=lambda a: a / 9.80665)
    elif case == "accel_in_mm":
        _map_imu(mav0, accel=lambda a: a * 1000)
    elif case == "gyro_in_deg":
        _map_imu(mav0, gyro=np.degrees)
    elif case == "all_zero_imu":
        _map_imu(mav0, gyro=lambda g: 0.0, accel=lambda a: 0.0)
    elif case == "nan_rows":
        header, rows = _rows(imu)
        for k in (50, 51, 300):
            rows[k][5] = "nan"
        rows[400][2] = "inf"
        _put(imu, header, rows)
    elif case == "gt_out_of_order":
        header, rows = _rows(gt)
        rows[10], rows[11] = rows[11], rows[10]
        _put(gt, header, rows)
    elif case == "gt_bad_numbers":
        header, rows = _rows(gt)
        rows[20][3] = "x1.5"
        _put(gt, header, rows)
    elif case == "gt_binary":
        gt.write_bytes(b"\x00\xff\xfe garbage \x9c\x00")
    elif case == "cut_imu":
        _cut_last_line(imu)
    elif case == "cut_cam0":
        _cut_last_line(cam0, 0.8)
    elif case == "cut_gt":
        _cut_last_line(gt, 0.5)
    elif case == "cut_imu_stamp":
        _cut_last_line(imu, 0.3)  # within the stamp: the cut stamp is out of order
    elif case == "corrupt_png":
        images[5].write_bytes(b"")
        images[9].write_bytes(b"\x89PNG\r\n\x1a\n" + b"broken" * 40)
    elif case == "stamps_in_seconds":
        _restamp(imu, lambda t: f"{t * 1e-9:.6f}")
    elif case == "imu_empty":
        imu.write_text("")
    elif case == "crlf_bom_spaces_commas":
        header, rows = _rows(imu)
        imu.write_bytes(("\ufeff" + header + "\r\n" + "".join(" , ".join(r) + " ,\r\n" for r in rows)).encode())
    elif case == "repeated_line":
        header, rows = _rows(imu)
        _put(imu, header, rows[:100] + [rows[99]] + rows[100:])
    elif case == "imu_microseconds":
        _restamp(imu, lambda t: t // 1000)
    elif case == "cam_negative_stamp":
        header, rows = _rows(cam0)
        rows[0][0] = "-" + rows[0][0]
        _put(cam0, header, rows)
    elif case == "cam_other_clock":
        _restamp(cam0, lambda t: t - 3600 * 10**9)
    elif case == "imu_stamp_jump":
        header, rows = _rows(imu)
        rows[200][0] = str(int(rows[200][0]) + 10**12)
        _put(imu, header, rows)
    elif case == "intrinsics_length":
        text = yaml0.read_text()
        start = text.index("intrinsics: [")
        yaml0.write_text(text[:start] + "intrinsics: [100.0, 100.0, 90.0]\n" + text[text.index("\n", start) + 1:])
    elif case == "T_BS_not_rotation":
        text = yaml0.read_text()
        start = text.index("data: [") + len("data: [")
        yaml0.write_text(text[:start] + "2.0" + text[text.index(",", start):])
    elif case == "yaml_garbage":
        yaml0.write_text("intrinsics: [1, 2\n  : : :\n")
    elif case == "calibration_in_mm":
        for cam in ("cam0", "cam1"):
            y = mav0 / cam / "sensor.yaml"
            d = __import__("vio.calibration", fromlist=["load_yaml"]).load_yaml(y)
            T = np.array(d["T_BS"]["data"], dtype=float).reshape(4, 4)
            T[:3, 3] *= 1000
            text = y.read_text()
            start, end = text.index("data: ["), text.index("]", text.index("data: ["))
            y.write_text(text[:start] + "data: [" + ", ".join(repr(float(x)) for x in T.ravel()) + text[end:])
    elif case == "all_images_unreadable":
        for p in images:
            p.write_bytes(b"")
    elif case == "missing_images":
        for p in images[3:6]:
            p.unlink()
    else:
        raise AssertionError(case)


def _damaged_copy(flight: Path, dst: Path, case: str) -> Path:
    shutil.copytree(flight, dst)
    _damage(dst / "mav0", case)
    return dst


def _one_error_line(r: subprocess.CompletedProcess) -> str:
    """The replay failed as it should: exit 1, no traceback, and one `vio replay: error:` line, the last."""
    assert "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert r.returncode == EXIT_FAILURE, r.stderr
    assert lines and lines[-1].startswith("vio replay: error: "), r.stderr
    assert sum(line.startswith("vio replay") for line in lines) == 1, r.stderr
    return lines[-1]


def _ran(r: subprocess.CompletedProcess, data: Path) -> None:
    """The replay succeeded despite the damage: exit 0, no traceback, a trajectory."""
    assert "Traceback" not in r.stderr, r.stderr
    assert r.returncode == 0, r.stderr
    assert len((data / "traj.tum").read_text().splitlines()) > 10


# ----------------------------------------------------------------------------------------- named faults

@pytest.mark.parametrize("case, expected", [
    ("resolution", f"images are {W}x{H} but the calibration is for {2 * W}x{2 * H}"),
    ("accel_in_g", "the data look like units of g, not m/s^2"),
    ("gyro_in_deg", "the data look like deg/s, not rad/s"),
    ("all_zero_imu", "accelerometer reads zero while still"),
    ("stamps_in_seconds", "the stamps look like seconds, not integer nanoseconds"),
])
def test_replay_stops_with_one_line(flight, tmp_path, case, expected):
    data = _damaged_copy(flight, tmp_path / case, case)
    r = _vio(*_replay_args(data))
    line = _one_error_line(r)
    assert expected in line
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr  # checked before the replay: nothing else said


@pytest.mark.parametrize("case, warning", [
    ("nan_rows", "4 of 601 IMU rows with a non-finite value skipped (first at line 52)"),
    ("cut_imu", "imu0/data.csv:602: last line cut short (no newline at the end"),
    ("cut_cam0", "cam0/data.csv:62: last line cut short (no newline at the end"),
    ("cut_gt", "state_groundtruth_estimate0/data.csv:602: last line cut short (no newline at the end"),
    ("corrupt_png", "2 of 61 frames unusable: 2 image unreadable"),
])
def test_replay_repairs_and_warns(flight, tmp_path, case, warning):
    data = _damaged_copy(flight, tmp_path / case, case)
    r = _vio(*_replay_args(data))
    _ran(r, data)
    assert warning in r.stderr
    assert "libpng" not in r.stderr and "imread" not in r.stderr  # OpenCV's own noise stays out


@pytest.mark.parametrize("case", ["gt_out_of_order", "gt_bad_numbers"])
def test_damaged_ground_truth_only_drops_the_evaluation(flight, tmp_path, case):
    import json

    data = _damaged_copy(flight, tmp_path / case, case)
    gt = data / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    r = _vio(*_replay_args(data))
    _ran(r, data)
    assert f"ground truth not used (no evaluation): {gt}:" in r.stderr
    assert "ATE" not in r.stdout and "no accuracy figures" in r.stdout
    d = json.loads((data / "stats.json").read_text())
    assert "evaluation" not in d and d["frames_unusable"] == 0
    if case != "gt_out_of_order":
        return
    r = _vio("eval", str(data / "traj.tum"), str(data))  # for `vio eval` the ground truth is the input
    assert r.returncode == EXIT_FAILURE and "Traceback" not in r.stderr
    assert r.stderr.strip().startswith(f"vio eval: error: {gt}:") and len(r.stderr.strip().splitlines()) == 1


def test_vision_that_never_worked_fails_the_replay(flight, tmp_path):
    import cv2

    data = _damaged_copy(flight, tmp_path / "grey", "missing_images")
    for p in (data / "mav0" / "cam0" / "data").iterdir():
        cv2.imwrite(str(p), np.full((H, W), 128, np.uint8))  # right size, nothing to track
    r = _vio(*_replay_args(data))
    line = _one_error_line(r)
    assert "vision never worked (61 of 61 frames unusable: 58 image blurred or textureless, 3 image missing)" in line
    assert "61 of 61 frames unusable" in r.stderr.splitlines()[-2]  # the one summary warning, just before
    import json

    d = json.loads((data / "stats.json").read_text())  # the stats still say what happened
    assert d["frames_unusable"] == 61 and d["unusable_reasons"]["image missing"] == 3


def test_ctrl_c_is_a_short_message_and_130(flight, tmp_path):
    # a shell without job control starts background jobs with SIGINT ignored, and children inherit that (this
    # test failed under `nohup bash -c ... &`): the replay gets the default disposition, as from a terminal
    # not -q: that turns the progress bar off too, and its first byte is how this test knows the replay runs
    p = subprocess.Popen([sys.executable, "-m", "vio.app.cli", "replay", str(flight), "--output",
                          str(tmp_path / "t.tum"), "--realtime"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        p.stderr.read(1)  # the log or the progress bar starts: the replay is running (3 s at sensor rate)
        time.sleep(0.5)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=60)
    finally:
        p.kill()
    text = err.decode()
    lines = [x for x in text.replace("\r", "\n").splitlines() if x.startswith("vio ")]
    assert p.returncode == 130, text
    assert "Traceback" not in text and lines == ["vio replay: interrupted"]


# ---------------------------------------------------------------------------------------------- fuzz

# case -> expected exit code and a text the one error line (exit 1) or stderr (exit 0) must contain (the
# first 30 frames are replayed)
FUZZ: dict[str, tuple[int, str]] = {
    "imu_empty": (1, "fewer than 2 IMU samples"),
    "crlf_bom_spaces_commas": (0, ""),
    "repeated_line": (0, "1 exact repeats of the line before dropped"),
    "imu_microseconds": (1, "they look like microseconds, not nanoseconds"),
    "cam_negative_stamp": (1, "cam0/data.csv:2: time stamp -"),
    "cam_other_clock": (1, "do not overlap"),
    "imu_stamp_jump": (1, "imu0/data.csv:203: out-of-order time stamp"),
    "cut_imu_stamp": (0, "last line cut short"),
    "accel_in_mm": (1, "the data look like mm/s^2, not m/s^2"),
    "calibration_in_mm": (1, "the extrinsics look like millimetres, not metres"),
    "intrinsics_length": (1, "intrinsics: expected 4 values [fx, fy, cx, cy], got 3"),
    "T_BS_not_rotation": (1, "T_BS: not a rigid transform"),
    "yaml_garbage": (1, "cam0/sensor.yaml: not valid YAML"),
    "gt_binary": (0, "ground truth not used"),
    "all_images_unreadable": (1, "vision never worked (30 of 30 frames unusable: 30 image unreadable)"),
    "missing_images": (0, "3 of 30 frames unusable: 3 image missing"),
}


@pytest.fixture(scope="module")
def fuzz_runs(flight, tmp_path_factory) -> dict[str, tuple[Path, subprocess.CompletedProcess]]:
    """Every fuzz case replayed once, in parallel processes (each is a fresh interpreter)."""
    base = tmp_path_factory.mktemp("fuzz")
    data = {case: _damaged_copy(flight, base / case, case) for case in FUZZ}
    with ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 2)) as pool:
        runs = dict(zip(data, pool.map(lambda d: _vio(*_replay_args(d, "--max-frames", "30")), data.values())))
    return {case: (data[case], runs[case]) for case in FUZZ}


@pytest.mark.parametrize("case", list(FUZZ))
def test_fuzz_damaged_dataset_never_gives_a_traceback(fuzz_runs, case):
    data, r = fuzz_runs[case]
    code, text = FUZZ[case]
    assert "Traceback" not in r.stderr, r.stderr
    if code == 0:
        _ran(r, data)
        assert text in r.stderr
    else:
        assert text in _one_error_line(r)


def test_swapped_cameras_are_said_and_a_right_calibration_is_not(flight, tmp_path):
    """cam0 and cam1 swapped in the calibration: no stereo match at all, and the flight ran on the left camera and
    the IMU with nothing said (a review's finding: the daemon showed "running", quality 100). Now the estimator
    warns once and its health (the daemon's status: degraded) carries it."""
    import json
    import shutil

    data = tmp_path / "swapped"
    shutil.copytree(flight, data, symlinks=True)
    a, b = (data / "mav0" / c / "sensor.yaml" for c in ("cam0", "cam1"))
    ta, tb = a.read_text(), b.read_text()
    a.write_text(tb)
    b.write_text(ta)
    r = _vio(*_replay_args(data)[1:])
    assert "Traceback" not in r.stderr
    assert "no stereo match in the last 10 frames that looked for one" in r.stderr, r.stderr[-2000:]
    assert json.loads((data / "stats.json").read_text())["estimator"]["stereo_warning"]
    good = tmp_path / "good"
    shutil.copytree(flight, good, symlinks=True)
    r = _vio(*_replay_args(good)[1:])
    assert r.returncode == 0 and "no stereo match" not in r.stderr
    assert json.loads((good / "stats.json").read_text())["estimator"]["stereo_warning"] is None


@pytest.mark.parametrize("still_s", [0.0, 1.5])
def test_right_camera_out_at_the_start_says_whether_anything_is_estimated(tmp_path, still_s):
    """Right camera out for the first seconds: a flight that starts moving cannot start without stereo depth, and
    the warning said "running on the IMU and the left camera alone" while no pose went out for 9 s (a QA run).
    Now it says the start waits for stereo; a flight that starts at rest starts on one camera and says so."""
    import json

    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "f"
    simulate(data, SimConfig(profile="aggressive", duration_s=6.0, width=320, height=200, variant="clean", seed=3,
                             still_start_s=still_s, right_dropouts=((0.0, 3.0),)), progress=False)
    r = _vio(*_replay_args(data))
    _ran(r, data)
    stats = json.loads((data / "stats.json").read_text())
    warned = [ln for ln in r.stderr.splitlines() if "stereo: no stereo match" in ln]
    assert len(warned) == 1, r.stderr[-3000:]
    # the frames had no right image at all: the calibration is not in question (it was told to look for a swap)
    assert "no right image arrived" in warned[0] and "swapped" not in warned[0], warned[0]
    if still_s:  # warned before the start (then not started), then started at rest on one camera: said
        assert "stereo: still none at the start: running on the IMU and the left camera alone" in r.stderr
        assert stats["estimator"]["stereo_warning"] is None  # matched again at 3 s, cleared
    else:
        assert "not started: a start in motion waits for stereo depth" in warned[0]
        assert "running on the IMU" not in r.stderr
        first = next(float(ln.split()[0]) for ln in (data / "traj.tum").read_text().splitlines()
                     if ln and not ln.startswith("#"))
        t0 = int((data / "mav0" / "cam0" / "data.csv").read_text().splitlines()[1].split(",")[0]) * 1e-9
        assert first - t0 >= 2.9, first - t0  # no pose before the right camera is back


def test_no_output_is_written_into_the_recording_it_reads(flight, tmp_path, capsys):
    """`-o .../state_groundtruth_estimate0/data.csv` replaced the ground truth with the estimate and printed its
    accuracy, `--show-tracks mav0/cam0/data` replaced the images, `eval --json` the estimate it read (a QA sweep's
    findings): every such output is refused before any work, even with --overwrite, and nothing is touched."""
    from vio.app.cli import main

    mav0 = flight / "mav0"
    before = {p: p.read_bytes() for p in sorted(mav0.rglob("*.csv")) + sorted(mav0.rglob("*.yaml"))}
    gt = mav0 / "state_groundtruth_estimate0" / "data.csv"
    est = tmp_path / "est.tum"
    est.write_text("# an estimate\n")
    cases = (["replay", str(flight), "-o", str(gt), "--no-progress"],
             ["replay", str(flight), "-o", str(mav0 / "imu0" / "new.tum"), "--no-progress"],
             ["replay", str(flight), "-o", str(tmp_path / "x.tum"), "--show-tracks", str(mav0 / "cam0" / "data")],
             ["replay", str(flight), "-o", str(tmp_path / "x.tum"), "--stats", str(flight / "simulation.yaml")],
             ["eval", str(est), str(flight), "--json", str(mav0 / "imu0" / "data.csv")],
             ["eval", str(est), str(gt), "--plot", str(mav0 / "cam0" / "data" / "plot.png")],
             # the dataset named by its mav0/ folder, which every reader takes too (a review's finding)
             ["eval", str(est), str(mav0), "--json", str(mav0 / "imu0" / "data.csv")],
             ["replay", str(mav0), "-o", str(mav0 / "x.tum"), "--no-progress"],
             ["calib", "refine", str(flight), "-o", str(mav0 / "cam0" / "sensor.yaml"), "--overwrite"],
             ["calib", "imu-noise", str(mav0 / "imu0" / "data.csv"), "-o", str(mav0 / "imu0" / "sensor.yaml"),
              "--overwrite"])
    for args in cases:
        assert main(args) == 1, args
        assert "would be written into the recording" in capsys.readouterr().err, args
    assert main(["eval", str(est), str(flight), "--json", str(est)]) == 1
    assert "the JSON would be written over the estimate" in capsys.readouterr().err
    assert est.read_text() == "# an estimate\n"
    assert {p: p.read_bytes() for p in before} == before
    assert not (mav0 / "imu0" / "new.tum").exists() and not (tmp_path / "x.tum").exists()
    assert len(list((mav0 / "cam0" / "data").iterdir())) == len(list((mav0 / "cam1" / "data").iterdir()))
    # beside the recording, in its own folder, is where users keep their runs: still written
    assert main(["-q", "replay", str(flight), "-o", str(flight / "est.tum"), "--no-progress", "--max-frames",
                 "10"]) == 0
    assert (flight / "est.tum").is_file()
    (flight / "est.tum").unlink()


def test_a_device_named_as_a_configuration_calibration_or_trajectory_is_one_line_not_a_hang(tmp_path):
    """`vio config check /dev/zero`, `vio calib show /dev/urandom`, `vio eval /dev/zero GT` (or a serial port named as
    `[source] calibration`) read the device for ever, memory growing: no message, no exit (a review's finding). A
    device is refused in one line; a pipe is still read (`--config <(...)`)."""
    for args, says in ((["config", "check", "/dev/zero"], "/dev/zero: is a device, not a configuration file"),
                       (["calib", "show", "/dev/urandom"], "/dev/urandom: is a device, not a calibration file"),
                       (["eval", "/dev/zero", str(tmp_path)], "/dev/zero: is a device, not a trajectory file"),
                       (["status", "--file", "/dev/zero"], "/dev/zero: cannot read status: is a device"),
                       (["batch", str(tmp_path), "-o", str(tmp_path / "r"), "--compare", "/dev/zero"],
                        "/dev/zero: is a device, not a batch report file")):
        r = _vio(*args, timeout=60)
        assert r.returncode != 0 and says in r.stderr, (args, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    fifo = tmp_path / "c.toml"
    os.mkfifo(fifo)
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    p = subprocess.Popen([sys.executable, "-m", "vio.app.cli", "config", "check", str(fifo)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=env)
    fifo.write_text("[source]\nkind = 'fake'\n")
    out, err = p.communicate(timeout=60)
    assert p.returncode == 0 and "OK" in out, (out, err)
    # but a status file is the daemon's regular file: `vio status --file PIPE` waited for a writer for ever
    r = _vio("status", "--file", str(fifo), timeout=60)
    assert r.returncode == 4 and f"{fifo}: cannot read status: is a pipe, not a status file" in r.stdout + r.stderr, r


def test_a_gap_in_the_data_is_not_waited_out_by_a_realtime_replay(flight, tmp_path):
    """`vio replay --realtime` (and --mavlink, which implies it) of a recording with a 1000 s gap in its stamps (a
    clock jump, a recorder paused) slept through the gap: no output, no message, a hang to the user (a review's
    finding). The gap is said in one warning and the data after it follow at once."""
    data = tmp_path / "gap"
    shutil.copytree(flight, data)
    t_cut = None
    for f in ("imu0", "cam0", "cam1", "state_groundtruth_estimate0"):
        p = data / "mav0" / f / "data.csv"
        lines = p.read_text().splitlines()
        t_cut = t_cut or int(lines[len(lines) // 2].split(",")[0])
        p.write_text("\n".join([lines[0]] + [f"{int(t) + (10**12 if int(t) >= t_cut else 0)},{rest}" for t, rest in
                                             (ln.split(",", 1) for ln in lines[1:])]) + "\n")
    r = _vio("replay", str(data), "-o", str(tmp_path / "t.tum"), "--no-progress", "--realtime", timeout=90)
    assert r.returncode == 0 and "realtime: a gap of 1e+03 s in the data" in r.stderr, r.stderr[-2000:]
    # the skipped seconds are not data time: the real-time factor said 300 after the gap
    m = re.search(r"([0-9.]+) s of data in [0-9.]+ s \(real-time factor ([0-9.]+)\)", r.stdout)
    assert m and float(m.group(1)) < 5 and 0.5 < float(m.group(2)) < 1.5, r.stdout


def test_a_right_image_of_the_wrong_size_is_said_and_counted(flight, tmp_path):
    """One right image of another size made that frame run on the left camera alone, with nothing said at -q and
    nothing in the stats (a review's finding). It is one warning line and a count in stats.json."""
    import json

    import cv2

    data = tmp_path / "right"
    shutil.copytree(flight, data)
    p = data / "mav0" / "cam1" / "data" / "1600000001450000000.png"  # one the front end reads (a keyframe's)
    cv2.imwrite(str(p), cv2.resize(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), (W // 2, H // 2)))
    r = _vio(*_replay_args(data))
    assert r.returncode == 0, r.stderr[-2000:]
    said = [ln for ln in r.stderr.splitlines() if "right image" in ln]
    assert len(said) == 1 and f"right image is {W // 2}x{H // 2}, calibration says {W}x{H}" in said[0], r.stderr
    d = json.loads((data / "stats.json").read_text())
    assert sum(d["right_image_unusable"].values()) >= 1, d["right_image_unusable"]


def test_a_failed_replay_keeps_an_earlier_trajectory_file(flight, tmp_path):
    """A replay that ended 'vision never worked' (exit 1) had already replaced an existing -o file with its IMU-only
    poses: the earlier run's trajectory lost for nothing. Over an existing file the replay streams into OUT.partial
    and renames it over OUT once it succeeds; failed, OUT is kept and the error line names OUT.partial."""
    import cv2

    data = _damaged_copy(flight, tmp_path / "grey", "missing_images")
    for p in (data / "mav0" / "cam0" / "data").iterdir():
        cv2.imwrite(str(p), np.full((H, W), 128, np.uint8))  # nothing to track
    out = tmp_path / "t.tum"
    out.write_text("# an earlier run\n1.0 0 0 0 0 0 0 1\n")
    r = _vio("-q", "replay", str(data), "-o", str(out), "--no-progress")
    line = _one_error_line(r)
    assert "vision never worked" in line and f"the poses so far are in {out}.partial; {out} is kept" in line, line
    assert out.read_text() == "# an earlier run\n1.0 0 0 0 0 0 0 1\n"
    assert (tmp_path / "t.tum.partial").read_text().startswith("# timestamp[s]")
    lo = tmp_path / "lo.tum"  # the loop-corrected trajectory, written at the end, replaced it the same way
    lo.write_text("# an earlier loop-corrected run\n")
    r = _vio("-q", "replay", str(data), "--loop-output", str(lo), "--no-progress")
    line = _one_error_line(r)
    assert f"the loop-corrected poses are in {lo}.partial; {lo} is kept" in line, line
    assert lo.read_text() == "# an earlier loop-corrected run\n" and (tmp_path / "lo.tum.partial").is_file()
    r = _vio("-q", "replay", str(flight), "-o", str(out), "--no-progress")  # a replay that works replaces it
    assert r.returncode == 0, r.stderr
    assert out.read_text().startswith("# timestamp[s]") and len(out.read_text().splitlines()) > 10
    assert not (tmp_path / "t.tum.partial").exists()  # streamed into again, then renamed


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
def test_an_image_that_is_a_pipe_is_skipped_not_waited_on(flight, tmp_path):
    """An image file that is a named pipe (or a device) made the replay wait for ever in cv2.imread, silent at -q.
    It is skipped as unreadable, with a warning naming it."""
    data = tmp_path / "fifo"
    shutil.copytree(flight, data)
    for name in ("1600000000000000000.png", "1600000001000000000.png"):  # the first one (the size check) and one
        p = data / "mav0" / "cam0" / "data" / name
        p.unlink()
        os.mkfifo(p)
    r = _vio(*_replay_args(data), timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "1600000001000000000.png: not a regular file (a pipe, device or folder); skipped" in r.stderr, r.stderr
