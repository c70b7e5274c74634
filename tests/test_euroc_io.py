"""EuRoC ASL reader and writer: the real V1_01 excerpt, broken copies of it, and a writer round trip."""

from __future__ import annotations

import logging
import os
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from vio import VioError
from vio.calibration import CameraCalibration, ImuNoise, StereoCalibration
from vio.io.euroc import EurocDataset, EurocWriter
from vio.types import ImuSample, StereoFrame

N_FRAMES, N_IMU, N_GT = 95, 29120, 2895
T_FIRST = 1403715273262142976


@pytest.fixture(scope="module")
def v101(v101_path) -> EurocDataset:
    return EurocDataset(v101_path)


def test_reads_v101_excerpt(v101):
    ds = v101
    assert len(ds) == N_FRAMES and len(ds.imu) == N_IMU
    assert ds.frame_t[0] == T_FIRST and ds.frame_t[-1] == 1403715277962142976
    assert np.all(np.diff(ds.frame_t) > 0) and np.all(np.diff(ds.imu.t_ns) > 0)
    assert ds.imu.gyro[0] == pytest.approx([-0.0020943951023931952, 0.017453292519943295, 0.07749261878854824])
    assert ds.imu.accel[0] == pytest.approx([9.0874956666666655, 0.13075533333333333, -3.6938381666666662])
    gt = ds.groundtruth
    assert gt is not None and len(gt.trajectory) == N_GT
    assert gt.trajectory.p[0] == pytest.approx([0.878895, 2.1834, 0.948427])
    assert gt.gyro_bias[0] == pytest.approx([-0.00224703, 0.0215352, 0.0770299])
    c = ds.calibration
    assert (c.cam0.fx, c.cam0.fy, c.cam0.cx, c.cam0.cy) == (458.654, 457.296, 367.215, 248.375)
    assert (c.cam1.fx, c.cam1.fy, c.cam1.cx, c.cam1.cy) == (457.587, 456.134, 379.999, 255.238)
    assert (c.cam0.width, c.cam0.height, c.cam0.distortion_model) == (752, 480, "radtan")
    assert c.cam0.distortion == pytest.approx((-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05))
    assert c.cam0.T_body_cam[0] == pytest.approx([0.0148655429818, -0.999880929698, 0.00414029679422,
                                                  -0.0216401454975])
    assert c.baseline_m == pytest.approx(0.110, abs=0.001)
    assert c.imu.gyroscope_noise_density == 1.6968e-04 and c.imu.accelerometer_random_walk == 3.0e-3
    assert c.time_offset_ns == 0
    assert ds.stats.missing_images == ds.stats.unpaired_frames == 0


def test_events_in_time_order_imu_first(v101):
    t_end = int(v101.frame_t[9])
    events = list(v101.events(t_end_ns=t_end))
    frames = [e for e in events if isinstance(e, StereoFrame)]
    assert len(frames) == 10
    assert all(isinstance(e, (ImuSample, StereoFrame)) for e in events)
    t = [e.t_ns for e in events]
    assert t == sorted(t) and t[-1] == t_end
    for k, e in enumerate(events):
        if isinstance(e, StereoFrame):
            # every image stamp is also an IMU stamp: that IMU sample comes just before the frame
            assert isinstance(events[k - 1], ImuSample) and events[k - 1].t_ns == e.t_ns
    f = frames[0]
    assert f.left.shape == (480, 752) and f.left.dtype == np.uint8 and f.right.shape == (480, 752)
    n_imu = sum(isinstance(e, ImuSample) for e in events)
    assert n_imu == int(np.count_nonzero(v101.imu.t_ns <= t_end))


def test_events_defer_right_images_when_lazy(v101, monkeypatch):
    t_end = int(v101.frame_t[5])
    eager = [e for e in v101.events(t_end_ns=t_end) if isinstance(e, StereoFrame)]
    decoded: list[str] = []
    load = v101._load
    monkeypatch.setattr(v101, "_load", lambda path: (decoded.append(str(path)), load(path))[1])
    lazy = [e for e in v101.events(t_end_ns=t_end, lazy_right=True) if isinstance(e, StereoFrame)]
    assert [f.t_ns for f in lazy] == [f.t_ns for f in eager] == v101.frame_t[:6].tolist()
    assert all(f.right is None and f.load_right is not None for f in lazy)
    assert all("cam1" not in p for p in decoded)  # only left images so far
    assert np.array_equal(lazy[2].right_image(), eager[2].right)
    assert sum("cam1" in p for p in decoded) == 1
    assert all(np.array_equal(a.left, b.left) for a, b in zip(lazy, eager))


def test_events_after_last_frame_are_imu(v101):
    tail = list(v101.events(t_start_ns=int(v101.frame_t[-1]) + 1))
    assert len(tail) == int(np.count_nonzero(v101.imu.t_ns > v101.frame_t[-1]))
    assert all(isinstance(e, ImuSample) for e in tail)


# ------------------------------------------------------------------------------------------------ broken copies

def _copy(src: Path, dst: Path, link_images: str = "folder") -> Path:
    """A copy of the dataset with the csv/yaml files copied and the images linked (no 70 MB copy).

    link_images: 'folder' links each data/ folder; 'files' makes real data/ folders of per-image links,
    so single images can be removed or replaced.
    """
    for sub in ("cam0", "cam1", "imu0", "state_groundtruth_estimate0"):
        s, d = src / "mav0" / sub, dst / "mav0" / sub
        d.mkdir(parents=True)
        for f in s.iterdir():
            if f.is_file():
                shutil.copyfile(f, d / f.name)
        if (s / "data").is_dir():
            if link_images == "folder":
                os.symlink(s / "data", d / "data")
            else:
                (d / "data").mkdir()
                for img in (s / "data").iterdir():
                    os.symlink(img, d / "data" / img.name)
    return dst


def _edit_line(path: Path, lineno: int, new: str | None) -> None:
    lines = path.read_text().splitlines()
    if new is None:
        del lines[lineno - 1]
    else:
        lines[lineno - 1] = new
    path.write_text("\n".join(lines) + "\n")


def _restamp(path: Path, f) -> None:
    """Replace every stamp t of a csv by f(t)."""
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0]] + [f"{f(int(r.split(',')[0]))}{r[r.index(','):]}" for r in lines[1:]]) + "\n")


def _break(mav0: Path, case: str) -> str:
    """Apply one defect; return the text the error must contain."""
    imu = mav0 / "imu0" / "data.csv"
    cam0 = mav0 / "cam0" / "data.csv"
    lines = imu.read_text().splitlines()
    if case == "no_mav0":
        shutil.rmtree(mav0)
        return f"{mav0.parent}: no mav0/ folder"
    if case == "no_cam1":
        shutil.rmtree(mav0 / "cam1")
        return f"{mav0 / 'cam1'}: folder missing"
    if case == "no_imu_csv":
        imu.unlink()
        return f"{imu}: file not found"
    if case == "columns":
        _edit_line(imu, 5, lines[4].rsplit(",", 1)[0])
        return f"{imu}:5: expected 7 comma-separated values, got 6"
    if case == "not_number":
        parts = lines[6].split(",")
        parts[2] = "abc"
        _edit_line(imu, 7, ",".join(parts))
        return f"{imu}:7: column 3 value 'abc' is not a number"
    if case == "bad_stamp":
        _edit_line(imu, 3, "12x4" + lines[2][lines[2].index(","):])
        return f"{imu}:3: time stamp '12x4' is not an integer"
    if case == "unsorted":
        c = cam0.read_text().splitlines()
        c[3], c[4] = c[4], c[3]
        cam0.write_text("\n".join(c) + "\n")
        return f"{cam0}:5: out-of-order time stamp"
    if case == "duplicate":
        _edit_line(imu, 11, lines[9].rsplit(",", 1)[0] + ",1.5")
        return f"{imu}:11: duplicate time stamp"
    if case == "seconds":
        _edit_line(imu, 4, f"{int(lines[3].split(',')[0]) * 1e-9:.6f}" + lines[3][lines[3].index(","):])
        return "the stamps look like seconds, not integer nanoseconds"
    if case == "microseconds":
        _restamp(imu, lambda t: t // 1000)
        return "time stamps step by 5000 per sample: they look like microseconds, not nanoseconds"
    if case == "negative":
        _edit_line(imu, 2, "-5" + lines[1][lines[1].index(","):])
        return f"{imu}:2: time stamp -5 is not positive"
    if case == "beyond_int64":  # an OverflowError, "internal error" (a review's finding)
        _edit_line(imu, 6, "99999999999999999999999" + lines[5][lines[5].index(","):])
        return f"{imu}:6: time stamp '99999999999999999999999' is beyond int64 nanoseconds"
    if case == "cam_clock":
        _restamp(cam0, lambda t: t - 10**12)
        return "do not overlap (different clocks"
    if case == "binary":
        imu.write_bytes(b"\xff\xfe\x00garbage\x9c")
        return f"{imu}: not a text file"
    if case == "header_only":
        imu.write_text(lines[0] + "\n")
        return f"{imu}: fewer than 2 IMU samples"
    if case == "intrinsics":
        y = mav0 / "cam0" / "sensor.yaml"
        y.write_text(y.read_text().replace("intrinsics: [458.654, 457.296, 367.215, 248.375]", "intrinsics: [458.654]"))
        return f"{y}: intrinsics: expected 4 values [fx, fy, cx, cy], got 1"
    if case == "T_BS":
        y = mav0 / "cam1" / "sensor.yaml"
        y.write_text(y.read_text().replace("0.999598781151", "0.5"))
        return f"{y}: T_BS: not a rigid transform"
    if case == "no_yaml":
        (mav0 / "cam0" / "sensor.yaml").unlink()
        return f"{mav0 / 'cam0' / 'sensor.yaml'}: file not found"
    if case == "csv_is_folder":
        imu.unlink()
        imu.mkdir()
        return f"{imu}: is a folder, expected a csv file"
    if case == "old_last_line":  # a complete line from the past at the end: out of order, not a cut write
        imu.write_text("\n".join(lines + [lines[-5]]) + "\n")
        return f"{imu}:{len(lines) + 1}: out-of-order time stamp"
    if case == "yaml_text":
        y = mav0 / "cam0" / "sensor.yaml"
        y.write_text(y.read_text().replace("resolution: [752, 480]", "resolution: [wide, 480]"))
        return f"{y}: resolution: value 'wide' is not a number"
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["no_mav0", "no_cam1", "no_imu_csv", "columns", "not_number", "bad_stamp",
                                  "unsorted", "duplicate", "seconds", "microseconds", "negative", "beyond_int64",
                                  "cam_clock",
                                  "binary", "header_only", "intrinsics", "T_BS", "no_yaml", "yaml_text",
                                  "csv_is_folder", "old_last_line"])
def test_broken_dataset_errors(v101_path, tmp_path, case):
    root = _copy(v101_path, tmp_path / "ds")
    expected = _break(root / "mav0", case)
    with pytest.raises(VioError) as e:
        EurocDataset(root)
    assert expected in str(e.value)


def test_corrupt_and_missing_images_are_skipped_and_counted(v101_path, tmp_path, caplog):
    root = _copy(v101_path, tmp_path / "ds", link_images="files")
    t = np.loadtxt(v101_path / "mav0" / "cam0" / "data.csv", delimiter=",", dtype=np.int64, usecols=0)
    corrupt = root / "mav0" / "cam0" / "data" / f"{t[3]}.png"
    corrupt.unlink()
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\n" + b"broken" * 50)
    (root / "mav0" / "cam0" / "data" / f"{t[10]}.png").unlink()
    (root / "mav0" / "cam1" / "data" / f"{t[20]}.png").unlink()
    with caplog.at_level(logging.WARNING, logger="vio.io.euroc"):
        ds = EurocDataset(root)
        assert ds.stats.missing_images == 2
        frames = list(ds.frames(0, 25))
    assert ds.stats.unreadable_images == 1
    assert [f.t_ns for f in frames] == [int(x) for k, x in enumerate(t[:25]) if k not in (3, 10)]
    no_right = [f for f in frames if f.right is None]
    assert [f.t_ns for f in no_right] == [t[20]]
    text = caplog.text
    assert f"{corrupt}: unreadable image" in text
    assert f"image {t[10]}.png (t={t[10]}) listed but missing" in text
    assert len(ds.stats.warnings) == 3


# ------------------------------------------------------------------------------------------------ writer

def _calibration() -> StereoCalibration:
    T1 = np.eye(4)
    T1[0, 3] = 0.1
    cam0 = CameraCalibration(400.0, 401.5, 320.25, 200.75, 640, 400, "radtan", (-0.1, 0.01, 1e-4, -2e-4))
    cam1 = CameraCalibration(399.0, 400.5, 321.0, 199.5, 640, 400, "radtan", (-0.11, 0.012, 0.0, 0.0), T1)
    return StereoCalibration(cam0, cam1, ImuNoise(1e-4, 2e-5, 1e-3, 4e-3, 400.0), time_offset_ns=-1234567)


def test_writer_reader_round_trip(tmp_path):
    rng = np.random.default_rng(7)
    calib = _calibration()
    t0 = 1_600_000_000_000_000_000
    imgs = [(rng.integers(0, 256, (400, 640), dtype=np.uint8), rng.integers(0, 256, (400, 640), dtype=np.uint8))
            for _ in range(3)]
    imu = [ImuSample(t0 + k * 2_500_000, rng.normal(size=3), rng.normal(size=3) * 9.81) for k in range(60)]
    with EurocWriter(tmp_path / "rec", calib) as w:
        for s in imu:
            w.write_imu(s)
            if s.t_ns % 50_000_000 == 0 and len(imgs) > w.frames_written:
                left, right = imgs[w.frames_written]
                if w.frames_written == 1:  # a frame whose right image is decoded on demand loses nothing
                    w.write_frame(StereoFrame(s.t_ns, left, None, load_right=lambda r=right: r))
                else:
                    w.write_frame(StereoFrame(s.t_ns, left, right))
        w.write_groundtruth(t0, np.array([1.0, 2.0, 3.0]), np.array([1.0, 0, 0, 0]), np.zeros(3), np.zeros(3),
                            np.zeros(3))
        w.write_groundtruth(t0 + 10**8, np.array([1.5, 2.0, 3.0]), np.array([0.0, 1, 0, 0]), np.ones(3),
                            np.zeros(3), np.zeros(3))
    ds = EurocDataset(tmp_path / "rec")
    assert len(ds) == 3 and len(ds.imu) == 60
    assert np.array_equal(ds.imu.t_ns, [s.t_ns for s in imu])
    assert np.array_equal(ds.imu.gyro, [s.gyro for s in imu]) and np.array_equal(ds.imu.accel, [s.accel for s in imu])
    for f, (left, right) in zip(ds.frames(), imgs, strict=True):
        assert np.array_equal(f.left, left) and np.array_equal(f.right, right)
    c = ds.calibration
    assert c.time_offset_ns == calib.time_offset_ns
    for a, b in ((c.cam0, calib.cam0), (c.cam1, calib.cam1)):
        assert (a.fx, a.fy, a.cx, a.cy, a.width, a.height) == (b.fx, b.fy, b.cx, b.cy, b.width, b.height)
        assert a.distortion == b.distortion and np.array_equal(a.T_body_cam, b.T_body_cam)
    assert c.imu == calib.imu
    gt = ds.groundtruth
    assert gt is not None and np.array_equal(gt.trajectory.t_ns, [t0, t0 + 10**8])
    assert gt.trajectory.p[1] == pytest.approx([1.5, 2.0, 3.0]) and gt.v_world[1] == pytest.approx([1, 1, 1])


def test_kestrel_yaml_refuses_a_key_it_does_not_know(tmp_path):
    """`time_offset_ms: 5` in mav0/kestrel.yaml replayed with no offset, exit 0, unsaid (a QA sweep)."""
    from vio import VioError

    with EurocWriter(tmp_path / "rec", _calibration()) as w:
        for k in range(3):
            w.write_imu(ImuSample(1_000_000 + k * 5_000_000, np.zeros(3), np.array([0, 0, 9.81])))
    yaml = tmp_path / "rec" / "mav0" / "kestrel.yaml"
    assert EurocDataset(tmp_path / "rec").calibration.time_offset_ns == _calibration().time_offset_ns
    for text, says in (("time_offset_ms: 5\n", "unknown key 'time_offset_ms' (did you mean 'time_offset_ns'?)"),
                       ("- 5\n", "mapping"),
                       # vio replay's "internal error: OverflowError" (a review's finding)
                       ("time_offset_ns: 99999999999999999999999\n", "is beyond int64 nanoseconds")):
        yaml.write_text(text)
        with pytest.raises(VioError, match=re.escape(says)):
            _ = EurocDataset(tmp_path / "rec").calibration


@pytest.mark.parametrize("level", [0, 1, 6])
def test_writer_png_levels_are_lossless_and_level_0_is_stored(tmp_path, level):
    """Level 0 (the default) writes PNGs without deflate or row filters: fast to write and to read back, the
    size of the raw pixels; zlib levels shrink a smooth image. Every level reads back exactly."""
    ramp = np.add.outer(np.arange(400), np.arange(640)).astype(np.uint8)  # smooth: deflate halves it at least
    noise = np.random.default_rng(3).integers(0, 256, (400, 640), dtype=np.uint8)
    with EurocWriter(tmp_path / "rec", _calibration(), png_level=level) as w:
        w.write_frame(StereoFrame(1_000_000_000, ramp, noise))
    files = [next((tmp_path / "rec" / "mav0" / c / "data").glob("*.png")) for c in ("cam0", "cam1")]
    assert np.array_equal(cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED), ramp)
    assert np.array_equal(cv2.imread(str(files[1]), cv2.IMREAD_UNCHANGED), noise)
    size = files[0].stat().st_size
    if level == 0:
        assert 400 * 641 <= size < 400 * 641 * 1.01  # pixels + one filter byte per row + headers
    else:
        assert size < 400 * 641 / 2


def test_writer_refuses_a_png_level_outside_zlibs(tmp_path):
    with pytest.raises(VioError, match="PNG compression level must be 0-9, got 10"):
        EurocWriter(tmp_path / "rec", _calibration(), png_level=10)
    assert not (tmp_path / "rec").exists()


def test_writer_refuses_to_overwrite(tmp_path):
    EurocWriter(tmp_path / "rec", _calibration()).close()
    with pytest.raises(VioError, match="already holds a dataset"):
        EurocWriter(tmp_path / "rec", _calibration())


@pytest.mark.parametrize("case", ["gt_nan", "gt_columns", "gt_unsorted", "gt_empty"])
def test_damaged_ground_truth_is_dropped_with_a_note(v101_path, tmp_path, case):
    from vio.io.euroc import read_groundtruth_csv

    root = _copy(v101_path, tmp_path / "ds")
    gt = root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = gt.read_text().splitlines()
    if case == "gt_nan":
        parts = lines[1].split(",")
        parts[4] = "nan"
        _edit_line(gt, 2, ",".join(parts))
        expected = f"{gt}:2: column 5 value 'nan' is not a finite number"
    elif case == "gt_columns":
        _edit_line(gt, 5, ",".join(lines[4].split(",")[:5]))
        expected = f"{gt}:5: expected 8+ comma-separated values, got 5"
    elif case == "gt_unsorted":
        _edit_line(gt, 7, lines[2])
        expected = f"{gt}:7: out-of-order time stamp"
    else:
        gt.write_text(lines[0] + "\n")
        expected = f"{gt}: no ground-truth rows"
    with pytest.raises(VioError) as e:  # `vio eval`: the ground truth is its input
        read_groundtruth_csv(gt)
    assert expected in str(e.value)
    ds = EurocDataset(root)  # a replay: evaluation dropped, nothing else
    assert ds.groundtruth is None and expected in ds.groundtruth_problem
    assert ds.stats.notes == [f"ground truth not used (no evaluation): {ds.groundtruth_problem}"]
    assert len(ds) == N_FRAMES and len(ds.imu) == N_IMU


def test_cut_last_lines_repeats_and_nan_rows_are_repaired_and_noted(v101_path, tmp_path):
    root = _copy(v101_path, tmp_path / "ds")
    mav0 = root / "mav0"
    imu, cam0 = mav0 / "imu0" / "data.csv", mav0 / "cam0" / "data.csv"
    gt = mav0 / "state_groundtruth_estimate0" / "data.csv"
    lines = imu.read_text().splitlines()
    parts = lines[100].split(",")
    parts[4] = "inf"
    lines[100] = ",".join(parts)
    lines.insert(201, lines[200])  # an exact repeat
    imu.write_text("\r\n".join(lines)[:-25])  # CRLF, and the last line cut in its second-last value
    for path, keep in ((cam0, 25), (gt, 40)):
        text = path.read_text()
        path.write_text(text[: text.rstrip("\n").rindex("\n") + keep])
    ds = EurocDataset(root)
    assert len(ds.imu) == N_IMU - 2 and len(ds) == N_FRAMES - 1 and len(ds.groundtruth.trajectory) == N_GT - 1
    assert ds.stats.imu_rows_skipped == {"non-finite value": 1}
    text = "\n".join(ds.stats.notes)
    assert f"{imu}:{N_IMU + 2}: last line cut short (no newline at the end" in text
    assert f"{imu}: 1 exact repeats of the line before dropped" in text
    assert f"{imu}: 1 of {N_IMU - 1} IMU rows with a non-finite value skipped (first at line 101)" in text
    assert f"{cam0}:{N_FRAMES + 1}: last line cut short" in text
    assert f"{gt}:{N_GT + 1}: last line cut short" in text
    assert ds.stats.missing_images == 0 and ds.groundtruth.v_world is not None


@pytest.mark.parametrize("old, new, expected", [
    ("distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]",
     "distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359]", "radtan distortion needs 4, 5, 8"),
    ("rate_hz: 20", "rate_hz: fast", "rate_hz: value 'fast' is not a number"),
    ("rate_hz: 20", "rate_hz: -20", "camera rate_hz must be a positive number"),  # a QA sweep: accepted
    # a review's: "internal error: SVD did not converge" (p1), and a flight with no stereo match, exit 0 (k1)
    ("distortion_coefficients: [-0.28340811,", "distortion_coefficients: [-1.0e+10,", "beyond any lens's"),
    ("0.00019359, 1.76187114e-05]", "1.0e+300, 1.76187114e-05]", "beyond any lens's (at most 1000 in size)"),
    # a review's: an OverflowError in the time-offset estimator ("internal error")
    ("rate_hz: 20", "rate_hz: 1.0e+300", "camera rate_hz = 1e+300 is beyond any camera's"),
    ("T_BS:", "T_XX:", "missing key 'T_BS'"),
])
def test_camera_yaml_errors_name_file_and_key(v101_path, tmp_path, old, new, expected):
    root = _copy(v101_path, tmp_path / "ds")
    y = root / "mav0" / "cam0" / "sensor.yaml"
    assert old in y.read_text()
    y.write_text(y.read_text().replace(old, new))
    with pytest.raises(VioError) as e:
        EurocDataset(root)
    assert str(e.value).startswith(f"{y}: ") and expected in str(e.value)


def test_right_images_missing_are_told_from_unsynchronised_cameras(v101_path, tmp_path):
    """Three right images missing from a dataset whose cameras are triggered together: the note asked "are the two
    cameras triggered together, and stamped alike?" for 3 of 677 frames on every hard simulated flight (a QA run).
    When every right image pairs with a left one, it says the right camera dropped frames; shifted right stamps
    still ask about the trigger."""
    dropped = _copy(v101_path, tmp_path / "dropped")
    cam1 = dropped / "mav0" / "cam1" / "data.csv"
    for lineno in (31, 21, 11):  # three right images' csv lines, removed from the last
        _edit_line(cam1, lineno, None)
    ds = EurocDataset(dropped)
    assert ds.stats.unpaired_frames == 3
    note = next(n for n in ds.stats.notes if "have no right image" in n)
    assert f"3 of {N_FRAMES} left frames (3.2 %)" in note and "the right camera dropped or lost frames" in note
    shifted = _copy(v101_path, tmp_path / "shifted")
    _restamp(shifted / "mav0" / "cam1" / "data.csv", lambda t: t + 3_000_000)
    note = next(n for n in EurocDataset(shifted).stats.notes if "have no right image" in n)
    assert "are the two cameras triggered together" in note


def test_images_dropped_on_both_cameras_are_not_taken_for_unsynchronised_cameras(v101_path, tmp_path):
    """Three right images and two left ones lost, the cameras triggered together (the hard simulated variant loses
    left, right or both images): the two right images whose left was lost pair with nothing, and the note asked
    whether the cameras were triggered together and stamped alike, on every hard flight (a QA run). A lone right image
    a whole frame from every left one is a dropped left image."""
    root = _copy(v101_path, tmp_path / "both")
    for lineno in (31, 21, 11):
        _edit_line(root / "mav0" / "cam1" / "data.csv", lineno, None)
    for lineno in (41, 16):  # two left images whose right ones are there
        _edit_line(root / "mav0" / "cam0" / "data.csv", lineno, None)
    ds = EurocDataset(root)
    assert ds.stats.unpaired_frames == 3
    note = next(n for n in ds.stats.notes if "have no right image" in n)
    assert f"3 of {N_FRAMES - 2} left frames" in note and "2 right images no left one" in note
    assert "dropped or lost frames" in note and "triggered together" not in note


# 16-bit images: v8 written at another depth so that the right shift gives v8 back exactly (the low bits
# repeat the high ones, as a sensor's noise sets them)
DEPTHS = {
    "10-bit": lambda v: v.astype(np.uint16) << 2 | v >> 6,
    "12-bit": lambda v: v.astype(np.uint16) << 4 | v >> 4,
    "14-bit": lambda v: v.astype(np.uint16) << 6 | v >> 2,
    "16-bit": lambda v: v.astype(np.uint16) * 257,
    "12-bit MSB-aligned": lambda v: (v.astype(np.uint16) << 4 | v >> 4) << 4,
}


def _write_16bit(root: Path, images: list[np.ndarray]) -> EurocDataset:
    """A dataset of the given 16-bit stereo frames (left = right) and 0.3 s of IMU."""
    t0 = 1_600_000_000_000_000_000
    with EurocWriter(root, _calibration()) as w:
        for k in range(60):
            w.write_imu(ImuSample(t0 + k * 5_000_000, np.zeros(3), np.array([0.0, 0.0, 9.81])))
        for k, img in enumerate(images):
            w.write_frame(StereoFrame(t0 + 10_000_000 + k * 50_000_000, img, img))
    return EurocDataset(root)


@pytest.mark.parametrize("depth", list(DEPTHS))
def test_16bit_pngs_of_any_depth_decode_as_their_8bit_values(tmp_path, depth, caplog):
    """12-bit values in 16-bit PNGs came out >> 8: near-black images that every frame refused as "too dark". The
    shift is decided once, from the recording's first image, whichever frame is loaded first: a dark later frame
    (max 100 of 255) loaded first keeps the scale of the bright first one, and says which in one log line."""
    rng = np.random.default_rng(3)
    v8 = [rng.integers(0, 256, (40, 64), dtype=np.uint8), rng.integers(0, 100, (40, 64), dtype=np.uint8)]
    caplog.set_level(logging.INFO, logger="vio.io.images")
    ds = _write_16bit(tmp_path / "rec", [DEPTHS[depth](v) for v in v8])
    for k in (1, 0):
        f = ds.frame(k)
        assert f.left.dtype == np.uint8 and np.array_equal(f.left, v8[k]) and np.array_equal(f.right, v8[k])
    said = [r.getMessage() for r in caplog.records if "16-bit images" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith(f"{ds.mav0}: 16-bit images with ")
    assert ("MSB-aligned" in said[0]) == ("MSB" in depth)


def test_16bit_frame_brighter_than_the_first_is_clipped_not_wrapped_and_said_once(tmp_path, caplog):
    """A 12-bit recording with a frame holding values above 4095 that the scale's samples (the first frame and
    four spread over the recording) did not see: clipped to white (a wrap made the brightest parts black), with
    one warning for the recording."""
    usual = np.full((40, 64), 4095, np.uint16)
    brighter = np.full((40, 64), 2000, np.uint16)
    brighter[:, :8] = 9000  # 13 bits: 9000 >> 4 = 562, which wrapped to a dark 50 in 8 bits
    ds = _write_16bit(tmp_path / "rec", [usual, usual, usual, brighter, usual, usual])  # frame 3 is not sampled
    with caplog.at_level(logging.WARNING):
        ds.frame(0)  # decides (the image converted first counts too)
        a, b = ds.frame(3).left, ds.frame(3).left
    assert ds._to8.shift == 4
    assert np.array_equal(a, b) and np.all(a[:, :8] == 255) and np.all(a[:, 8:] == 2000 >> 4)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "values up to 9000, above the 12-bit range" in warned[0]
    assert len(ds.stats.warnings) == 1


def test_16bit_scale_is_decided_on_frames_spread_over_the_recording_not_a_dark_first_one(tmp_path):
    """A 16-bit camera whose first frame is nearly black (auto-exposure settling, a lens cap): decided on it alone,
    the scale was none at all and every later frame clipped to white (a review's finding). The first frame and
    four spread over the recording decide; a near-black frame's few small values do not make it "MSB-aligned"."""
    dark = np.zeros((40, 64), np.uint16)
    dark[5:7, 5:7] = (4, 8, 12, 8)[:2]  # a few small values whose low 2 bits are 0
    lit = np.random.default_rng(0).integers(1000, 40000, (40, 64)).astype(np.uint16)
    ds = _write_16bit(tmp_path / "rec", [dark] + [lit] * 8)
    img = ds.frame(0).left
    assert ds._to8.shift == 8 and img.max() == 0
    assert np.array_equal(ds.frame(4).left, (lit >> 8).astype(np.uint8))
    from vio.io.images import uint16_shift

    assert uint16_shift([dark]) == (0, "8-bit values (max 8)")  # alone: no light to call it MSB-aligned


def test_8bit_pngs_decode_byte_identical_and_decide_no_scale(v101):
    """The EuRoC 8-bit PNGs go through no 16-bit scale: the images the estimator sees are the files' bytes."""
    f = v101.frame(0)
    path = v101.cam0_files[0]
    assert np.array_equal(f.left, cv2.imread(str(path), cv2.IMREAD_UNCHANGED)) and v101._to8.shift is None


def test_a_time_offset_that_moves_the_camera_off_the_imu_is_named(v101_path):
    """A calibration's time_offset_ns of 1000 s (milliseconds written as nanoseconds, times 1e6) ended in "cam0
    stamps 1403715523.9..1403715528.6 s and IMU stamps 1403715523.9..1403715528.6 s do not overlap": the same
    span twice, the offset that moved them apart unnamed (a QA walk-through)."""
    import dataclasses

    calib = EurocDataset(v101_path).calibration
    with pytest.raises(VioError, match=r"the calibration's time_offset_ns = 1000000000000 \(\+1000\.000 s, t_imu = "
                       r"t_cam \+ offset\) moves every cam0 stamp outside the IMU's .* \(an offset in another unit"):
        EurocDataset(v101_path, dataclasses.replace(calib, time_offset_ns=10**12))


def test_an_image_folder_removed_under_the_writer_is_said_by_the_writer(tmp_path):
    """A recording folder being removed goes deepest first: an image write fails while the recording's root is
    still there, and the recorder's look at the root found nothing to say ('cannot write image' alone: a flaky CI
    run of test_removed_output_folders_stop_those_outputs_only). The writer says it, and the diagnosis does not
    say it twice."""
    import shutil

    from vio import VioError
    from vio.io.outputs import storage_diagnosis

    img = np.zeros((400, 640), np.uint8)
    with EurocWriter(tmp_path / "rec", _calibration()) as w:
        w.write_frame(StereoFrame(1_000_000_000, img, img))
        shutil.rmtree(tmp_path / "rec" / "mav0" / "cam0" / "data")  # the root still there, as mid-removal
        with pytest.raises(VioError) as e:
            w.write_frame(StereoFrame(1_050_000_000, img, img))
    said = str(e.value)
    assert "cannot write image (the recording folder was removed)" in said
    assert storage_diagnosis(tmp_path / "rec", said) == ""
    shutil.rmtree(tmp_path / "rec")
    assert storage_diagnosis(tmp_path / "rec") == " (the recording folder was removed)"


def test_an_imu_rate_no_imu_has_is_refused_naming_the_file(v101_path, tmp_path):
    """imu0/sensor.yaml's rate_hz of 1e300 was taken, unsaid (a review's finding); the camera's ended vio replay in
    an OverflowError (test_camera_yaml_errors_name_file_and_key)."""
    root = _copy(v101_path, tmp_path / "ds")
    y = root / "mav0" / "imu0" / "sensor.yaml"
    assert "rate_hz: 200" in y.read_text()
    y.write_text(y.read_text().replace("rate_hz: 200", "rate_hz: 1.0e+300"))
    with pytest.raises(VioError) as e:
        EurocDataset(root)
    assert str(e.value).startswith(f"{y}: ") and "IMU rate_hz = 1e+300 is beyond any IMU's" in str(e.value), e.value
    # a noise density of 1e300: "internal error: OverflowError" in the pre-integration (a review's finding)
    y.write_text(y.read_text().replace("rate_hz: 1.0e+300", "rate_hz: 200").replace(
        "gyroscope_noise_density: 1.6968e-04", "gyroscope_noise_density: 1.0e+300"))
    with pytest.raises(VioError) as e:
        EurocDataset(root)
    assert "IMU noise gyroscope_noise_density = 1e+300 is beyond any IMU's" in str(e.value), e.value


def test_ground_truth_beyond_any_place_on_earth_is_refused(tmp_path):
    """A ground-truth position of 1e300 m (finite) passed the reader and `vio eval` printed "ATE inf" with exit 0 (a
    review's note): refused in one line naming the file and line."""
    from vio.io.euroc import read_groundtruth_csv

    f = tmp_path / "data.csv"
    f.write_text("#timestamp,x,y,z,qw,qx,qy,qz\n1000,0,0,0,1,0,0,0\n2000,1e300,0,0,1,0,0,0\n")
    with pytest.raises(VioError, match=r"data\.csv:3: position 1e\+300 0 0 is beyond 1e\+09 m"):
        read_groundtruth_csv(f)


def test_the_daemons_record_dir_of_euroc_recordings_names_one_to_give(tmp_path):
    """`vio replay RECORD_DIR` (the daemon's [run] record_dir: one EuRoC recording per start, named by its UTC time)
    said only "no mav0/ folder: not a EuRoC ASL dataset"; a folder of MCAP recordings already named one to give."""
    for name in ("20261208T010000Z", "20261208T020000Z"):
        (tmp_path / "recs" / name / "mav0").mkdir(parents=True)
    with pytest.raises(VioError, match=r"recs: a folder of 2 EuRoC recordings, not a dataset: give one, e.g. vio "
                       r"replay .*recs/20261208T020000Z"):
        EurocDataset(tmp_path / "recs")
