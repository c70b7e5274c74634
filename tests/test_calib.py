"""Calibration tools: importers round-trip on real-format files, show, checks, Allan deviation, time offset."""

from __future__ import annotations

import re
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from calib.importers import import_calibration, write_opencv_stereo
from calib.show import camera_axes, format_calibration
from vio import VioError
from vio.calibration import ImuNoise, load_calibration, save_calibration
from vio.geometry import inv_T, make_T, so3_exp

DATA = Path(__file__).parent / "data" / "calib"


def _same_calib(a, b, tol=1e-9) -> None:
    for ca, cb in ((a.cam0, b.cam0), (a.cam1, b.cam1)):
        np.testing.assert_allclose(ca.K, cb.K, atol=tol)
        np.testing.assert_allclose(ca.distortion, cb.distortion, atol=tol)
        np.testing.assert_allclose(ca.T_body_cam, cb.T_body_cam, atol=max(tol, 1e-9))
        assert (ca.width, ca.height, ca.distortion_model) == (cb.width, cb.height, cb.distortion_model)
    assert a.imu == b.imu
    assert a.time_offset_ns == b.time_offset_ns


def _roundtrip(calib, tmp_path):
    out = tmp_path / "calib.yaml"
    save_calibration(calib, out)
    back = load_calibration(out)
    _same_calib(calib, back)
    return back


# ------------------------------------------------------------------------------------------ importers

def test_kalibr_import_matches_published_euroc_values(tmp_path, v101_path):
    calib, notes = import_calibration("kalibr", [DATA / "kalibr_imu.yaml", DATA / "kalibr_camchain_imucam.yaml"])
    assert notes.messages == []
    # kalibr T_cam_imu is the inverse of EuRoC's T_BS; both files describe the same sensor
    euroc, _ = import_calibration("euroc", [v101_path])
    np.testing.assert_allclose(calib.cam0.T_body_cam, euroc.cam0.T_body_cam, atol=1e-9)
    np.testing.assert_allclose(calib.cam1.T_body_cam, euroc.cam1.T_body_cam, atol=1e-9)
    assert calib.time_offset_ns == -5_200_000  # timeshift_cam_imu -0.0052 s: t_imu = t_cam + shift
    assert calib.imu.gyroscope_noise_density == pytest.approx(1.6968e-4)
    assert calib.imu.rate_hz == 200.0
    assert calib.baseline_m == pytest.approx(0.1101, abs=2e-4)
    _roundtrip(calib, tmp_path)


def test_kalibr_inconsistent_chain_is_reported(tmp_path):
    text = (DATA / "kalibr_camchain_imucam.yaml").read_text()
    # shift cam1's T_cam_imu x translation by 5 cm so it disagrees with T_cn_cnm1
    text = text.replace("-0.04490198068248875", "0.00509801931751125")
    f = tmp_path / "camchain-imucam.yaml"
    f.write_text(text)
    calib, notes = import_calibration("kalibr", [f])
    assert any("disagree" in m for m in notes.messages)
    assert any("no imu.yaml" in m for m in notes.messages)
    assert calib.baseline_m == pytest.approx(0.1101, abs=2e-4)  # T_cn_cnm1 wins


def test_kalibr_errors_name_file_and_key(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text((DATA / "kalibr_camchain_imucam.yaml").read_text().replace("intrinsics:", "intrinsix:"))
    with pytest.raises(VioError, match=r"bad\.yaml: cam0: unknown key 'intrinsix' \(did you mean 'intrinsics'\?\)"):
        import_calibration("kalibr", [f])
    # a misspelt distortion key was read as no distortion, unsaid (a review's finding); a missing one too
    f.write_text((DATA / "kalibr_camchain_imucam.yaml").read_text().replace("distortion_coeffs:", "distortion_coefs:"))
    with pytest.raises(VioError, match=r"unknown key 'distortion_coefs' \(did you mean 'distortion_coeffs'\?\)"):
        import_calibration("kalibr", [f])
    # a QA sweep's: T_imu_cam (another tool's name, the inverse) gave two misleading warnings; a T_cam_imu whose last
    # row is wrong warned of a disagreement first; a third camera was left out unsaid
    f.write_text((DATA / "kalibr_camchain_imucam.yaml").read_text().replace("T_cam_imu:", "T_imu_cam:", 1))
    with pytest.raises(VioError, match=r"cam0: T_imu_cam is not a Kalibr camchain key"):
        import_calibration("kalibr", [f])
    lines = (DATA / "kalibr_camchain_imucam.yaml").read_text().splitlines()
    last = next(i for i, ln in enumerate(lines) if ln.strip() == "- [0, 0, 0, 1]")
    lines[last] = lines[last].replace("1]", "2]")
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(VioError, match=r"T_cam_imu is not a rigid transform"):
        import_calibration("kalibr", [f])
    text = (DATA / "kalibr_camchain_imucam.yaml").read_text()
    cam1 = text[text.index("cam1:"):]
    f.write_text(text + "\n" + cam1.replace("cam1:", "cam2:", 1))
    _, notes = import_calibration("kalibr", [f])
    assert any("cam2 left out" in m for m in notes.messages)
    g = tmp_path / "imu.yaml"
    g.write_text("accelerometer_noise_density: 0.01\nupdate_rate: 100\n")
    with pytest.raises(VioError, match=r"imu\.yaml: missing key 'gyroscope_noise_density'"):
        import_calibration("kalibr", [DATA / "kalibr_camchain_imucam.yaml", g])


def test_kalibr_values_of_the_wrong_type_are_named_in_one_line(tmp_path, capsys):
    """A camchain edited by hand with a camera that is not a mapping, a timeshift that is not a number, or
    intrinsics that are a word: `vio calib import` said 'internal error: TypeError' / 'ValueError', or counted the
    word's letters as intrinsics ('got 3 values')."""
    from vio.app.cli import main

    text = (DATA / "kalibr_camchain_imucam.yaml").read_text()
    cases = {
        "cam0: 5\ncam1: 6\n": r"cam0: expected a mapping of camera keys .*got int 5",
        "cam0: [1, 2]\ncam1: [3]\n": r"cam0: expected a mapping of camera keys .*got list \[1, 2\]",
        text.replace("timeshift_cam_imu: -0.0052", "timeshift_cam_imu: abc"):
            r"timeshift_cam_imu = \['abc', 'abc'\]: expected a number of seconds",
        text.replace("intrinsics: [458.654, 457.296, 367.215, 248.375]", "intrinsics: foo"):
            r"cam0: intrinsics must be a list \[fx, fy, cx, cy\], got 'foo'",
        # fx = 1 px and a number read from text, unsaid (a review's finding)
        text.replace("intrinsics: [458.654, 457.296,", "intrinsics: [true, 457.296,"):
            r"cam0: intrinsics must be four numbers \[fx, fy, cx, cy\], got \[True,",
        text.replace("intrinsics: [457.587, 456.134,", "intrinsics: ['457.5', 456.134,"):
            r"cam1: intrinsics must be four numbers",
        # 'internal error: OverflowError' (a review's finding)
        text.replace("timeshift_cam_imu: -0.0052", "timeshift_cam_imu: 1.0e+300"):
            r"timeshift_cam_imu = \['1e\+300', '1e\+300'\] s is beyond int64 nanoseconds",
    }
    f, out = tmp_path / "camchain.yaml", tmp_path / "c.yaml"
    for content, message in cases.items():
        f.write_text(content)
        capsys.readouterr()
        assert main(["calib", "import", "kalibr", str(f), "-o", str(out)]) == 1
        err = capsys.readouterr().err
        assert re.search(r"^vio calib: error: .*camchain\.yaml: " + message, err), err
        assert "internal error" not in err and len(err.strip().splitlines()) == 1 and not out.exists()


def test_another_tool_s_file_given_as_the_calibration_says_how_to_convert_it(v101_path, capsys):
    """`vio calib show` (and replay, run) of a EuRoC sensor.yaml, a depthai JSON, an OpenCV stereo file or a Kalibr
    imu.yaml said "unknown key 'sensor_type'; known keys: cam0, ..." (the Kalibr camchain alone was named), and of a
    dataset folder "cannot read (Is a directory)": neither says what to do."""
    from vio.app.cli import main

    for path, says in ((v101_path / "mav0/cam0/sensor.yaml", "a EuRoC sensor.yaml .*vio calib import euroc"),
                       (DATA.parent / "depthai_calib.json", r"a depthai \(OAK\) calibration.*import depthai"),
                       (DATA / "opencv_stereo.yaml", "an OpenCV stereo calibration.*vio calib import opencv"),
                       (DATA / "kalibr_imu.yaml", "a Kalibr imu.yaml.*vio calib import kalibr CAMCHAIN.yaml IMU.yaml"),
                       (v101_path, "is a folder, not a calibration file .*vio calib import euroc DATASET")):
        capsys.readouterr()
        assert main(["calib", "show", str(path)]) == 1
        err = capsys.readouterr().err
        assert re.search(f"^vio calib: error: {re.escape(str(path))}: {says}", err), err


def test_a_recordings_kestrel_yaml_given_as_the_calibration_says_where_the_calibration_is(tmp_path, capsys):
    """A recording's mav0/kestrel.yaml (`vio record` writes it: the time offset only) is the one file named like a
    Kestrel calibration in a recording; `vio calib check mav0/kestrel.yaml REC` said "missing key 'cam0'" (exit 4),
    which says not what to give instead (an integrator's walk-through of docs/first-flight.md)."""
    from vio.app.cli import main

    path = tmp_path / "kestrel.yaml"
    path.write_text("time_offset_ns: 0\n")
    assert main(["calib", "show", str(path)]) == 1
    err = capsys.readouterr().err
    assert re.search(f"^vio calib: error: {re.escape(str(path))}: a recording's kestrel.yaml .*not a calibration.*"
                     r"vio calib import euroc DATASET.*vio calib check - DATASET", err), err


def test_a_calibration_name_over_the_file_system_s_limit_is_one_line(tmp_path, capsys):
    """The folder check added for a dataset given as the calibration (Path.is_dir) raised on a name over 255 bytes:
    'internal error: OSError: [Errno 36] File name too long', where the read said it in one line before."""
    from vio.app.cli import main

    path = tmp_path / ("c" * 300)
    assert main(["calib", "show", str(path)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("vio calib: error: ") and "internal error" not in err and len(err.splitlines()) == 1, err


def test_euroc_import_roundtrip(tmp_path, v101_path):
    calib, _ = import_calibration("euroc", [v101_path])
    assert calib.cam0.fx == pytest.approx(458.654)
    assert calib.cam1.distortion[0] == pytest.approx(-0.28368365)
    assert calib.imu.accelerometer_random_walk == pytest.approx(3.0e-3)
    mav0 = v101_path / "mav0"
    by_files, _ = import_calibration(
        "euroc", [mav0 / "cam0/sensor.yaml", mav0 / "cam1/sensor.yaml", mav0 / "imu0/sensor.yaml"])
    _same_calib(calib, by_files)
    _roundtrip(calib, tmp_path)


def test_euroc_import_of_an_imu_yaml_with_a_bad_T_BS_says_so(tmp_path, v101_path, capsys):
    """imu0/sensor.yaml's T_BS as a bare list, or with 15 numbers: 'internal error: AttributeError' / 'ValueError'
    (the cameras' T_BS was checked, the IMU's not)."""
    from vio.app.cli import main

    mav0 = v101_path / "mav0"
    imu_text = (mav0 / "imu0/sensor.yaml").read_text()
    imu, out = tmp_path / "sensor.yaml", tmp_path / "c.yaml"
    bare_list = imu_text.replace("T_BS:", "T_BS: [1, 0, 0]\nold_T_BS:")
    fifteen = imu_text.replace("0.0, 0.0, 0.0, 1.0]", "0.0, 0.0, 0.0]")
    for content, message in ((bare_list, "expected 16 values .*got 3"), (fifteen, "expected 16 values .*got 15")):
        imu.write_text(content)
        capsys.readouterr()
        assert main(["calib", "import", "euroc", str(mav0 / "cam0/sensor.yaml"), str(mav0 / "cam1/sensor.yaml"),
                     str(imu), "-o", str(out)]) == 1
        err = capsys.readouterr().err
        assert re.search(r"^vio calib: error: .*sensor\.yaml: T_BS: " + message, err), err
        assert "internal error" not in err and not out.exists()


def test_opencv_import_units_and_convention(tmp_path):
    calib, notes = import_calibration("opencv", [DATA / "opencv_stereo.yaml"], translation_unit="mm")
    assert calib.baseline_m == pytest.approx(0.07512, abs=1e-4)
    # R, T from stereoCalibrate map cam0 points into cam1: T_cam1_cam0 must reproduce them
    np.testing.assert_allclose(calib.T_cam1_cam0[:3, 3], [-0.07512, 0.00021, -0.00034], atol=1e-9)
    assert calib.cam0.width == 1280 and calib.cam1.cy == pytest.approx(398.6)
    assert len(calib.cam0.distortion) == 5
    np.testing.assert_allclose(calib.cam0.T_body_cam, np.eye(4))
    assert any("no IMU extrinsics" in m for m in notes.messages)
    _roundtrip(calib, tmp_path)
    # the default unit (m) flags the mm file as implausible
    _, notes_m = import_calibration("opencv", [DATA / "opencv_stereo.yaml"])
    assert any("implausible" in m for m in notes_m.messages)
    # writer -> reader is the identity on the stereo part
    out = tmp_path / "stereo.yaml"
    write_opencv_stereo(calib, out)
    back, _ = import_calibration("opencv", [out])
    np.testing.assert_allclose(back.T_cam1_cam0, calib.T_cam1_cam0, atol=1e-12)
    np.testing.assert_allclose(back.cam1.K, calib.cam1.K)


def test_opencv_rational_model_is_kept_exactly(tmp_path):
    import cv2

    f = tmp_path / "rational.yml"
    fs = cv2.FileStorage(str(f), cv2.FILE_STORAGE_WRITE)
    fs.write("image_size", np.array([640, 400]))
    for k in ("K1", "K2"):
        fs.write(k, np.array([[400.0, 0, 320], [0, 400, 200], [0, 0, 1]]))
    fs.write("D1", np.array([[0.1, -0.2, 0.001, 0.002, 0.03, 0.5, 0, 0]]))
    fs.write("D2", np.array([[0.1, -0.2, 0.001, 0.002, 0.03, 0, 0, 0]]))
    fs.write("R", np.zeros((3, 1)))  # Rodrigues form
    fs.write("T", np.array([[-0.05], [0.0], [0.0]]))
    fs.release()
    calib, notes = import_calibration("opencv", [f])
    assert calib.cam0.distortion == (0.1, -0.2, 0.001, 0.002, 0.03, 0.5, 0.0, 0.0)  # k4 kept: rational model
    assert calib.cam1.distortion == (0.1, -0.2, 0.001, 0.002, 0.03)  # all-zero k4..k6 trimmed
    # the kept model projects exactly like OpenCV's own 8-coefficient call
    pts = np.array([[0.3, -0.2, 1.0], [-0.6, 0.4, 1.0]])
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), calib.cam0.K, np.array(calib.cam0.distortion))
    np.testing.assert_allclose(calib.cam0.project(pts), ref.reshape(-1, 2), atol=1e-9)
    np.testing.assert_allclose(calib.cam0.undistort_normalized(calib.cam0.project(pts)), pts[:, :2], atol=1e-6)


def test_opencv_missing_key(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text((DATA / "opencv_stereo.yaml").read_text().replace("K2:", "KK2:"))
    with pytest.raises(VioError, match=r"s\.yaml: missing key 'K2'"):
        import_calibration("opencv", [f])


def test_opencv_import_refuses_a_size_or_a_matrix_it_cannot_read(tmp_path, capsys):
    """`image_width: abc` read as 1.8e308 through OpenCV's FileNode.real() and was written as the calibration's width,
    exit 0; a YAML list at the top, or K1 as a word, was 'internal error: error: OpenCV ... isMap()'."""
    from vio.app.cli import main

    text = (DATA / "opencv_stereo.yaml").read_text()
    k1 = text[text.index("K1: !!opencv-matrix"):text.index("D1:")]
    cases = ((text.replace("image_width: 1280", "image_width: abc"),
              r"image_width / image_height must be whole numbers of pixels \[width, height\], got \['abc', 800.0\]"),
             (text.replace("image_width: 1280", "image_width: {a: 1}"), r"got \['a mapping', 800.0\]"),
             (text.replace("image_width: 1280", "image_width: 1280.5"), r"got \[1280.5, 800.0\]"),
             ("- 1\n- 2\n", r"not an OpenCV stereo calibration \(its top level is not a mapping of keys\)"),
             (text.replace(k1, 'K1: "abc"\n'), r"key 'K1' is not a matrix"),
             (text.replace(k1, "K1: {a: 1, b: 2}\n"), r"key 'K1' is not a matrix"))
    f, out = tmp_path / "stereo.yaml", tmp_path / "c.yaml"
    for content, message in cases:
        f.write_text(content)
        capsys.readouterr()
        assert main(["calib", "import", "opencv", str(f), "--translation-unit", "mm", "-o", str(out)]) == 1
        err = capsys.readouterr().err
        assert re.search(r"^vio calib: error: .*stereo\.yaml: .*" + message, err, re.M), err
        assert "internal error" not in err and not out.exists()
    f.write_text(text.replace("image_width: 1280\nimage_height: 800", "image_size: [1280, 800]"))
    assert main(["calib", "import", "opencv", str(f), "--translation-unit", "mm", "-o", str(out)]) == 0
    assert (load_calibration(out).cam0.width, load_calibration(out).cam0.height) == (1280, 800)


def test_opencv_import_of_another_tool_s_file_says_what_it_reads(tmp_path, capsys):
    """A Kalibr camchain, a JSON or an empty file given to the OpenCV importer ended in "internal error:
    SystemError: <class 'cv2.FileStorage'> returned a result with an exception set" (a QA sweep)."""
    from vio.app.cli import main

    cases = {"camchain.yaml": "cam0:\n  camera_model: pinhole\n   intrinsics: [1, 2, 3, 4]\n",
             "calib.json": "not json {", "empty.yaml": ""}
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        assert main(["calib", "import", "opencv", str(tmp_path / name), "-o", str(tmp_path / "out.yaml")]) == 1
        err = capsys.readouterr().err
        assert f"{name}: not an OpenCV FileStorage file" in err and "internal error" not in err, err
        assert "vio calib import kalibr" in err and not (tmp_path / "out.yaml").exists()


def _depthai_json(tmp_path, with_imu: bool = True, fisheye: bool = False) -> tuple[Path, np.ndarray, np.ndarray]:
    """A realistic OAK-D style calibration written by depthai itself (translations in cm)."""
    dai = pytest.importorskip("depthai")
    h = dai.CalibrationHandler()
    h.setBoardInfo("OAK-D-TEST", "R1")
    left, right, rgb = dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C, dai.CameraBoardSocket.CAM_A
    for sock, (fx, cx) in ((left, (798.1, 651.2)), (right, (797.4, 638.9)), (rgb, (1490.0, 960.0))):
        size = (1920, 1080) if sock == rgb else (1280, 800)
        h.setCameraIntrinsics(sock, [[fx, 0, cx], [0, fx + 0.6, 401.3], [0, 0, 1]], size[0], size[1])
        h.setCameraType(sock, dai.CameraModel.Fisheye if fisheye else dai.CameraModel.Perspective)
    d_left = [-4.21, 12.3, 0.0011, -0.0007, 4.6, -4.1, 12.0, 4.9, 0, 0, 0, 0, 0, 0]
    h.setDistortionCoefficients(left, d_left)
    h.setDistortionCoefficients(right, [0.02, -0.01, 0.0002, 0.0001, 0.003] + [0.0] * 9)
    h.setDistortionCoefficients(rgb, [0.0] * 14)
    R_rl = so3_exp(np.array([0.002, -0.004, 0.001]))
    h.setCameraExtrinsics(left, right, R_rl.tolist(), [-7.51, 0.02, -0.05], [-7.5, 0, 0])
    h.setCameraExtrinsics(right, rgb, np.eye(3).tolist(), [3.75, 0, 0], [3.75, 0, 0])
    T_right_left = make_T(R_rl, np.array([-0.0751, 0.0002, -0.0005]))
    T_left_imu = make_T(so3_exp(np.array([0.0, 0.0, np.pi / 2])), np.array([0.0105, -0.0021, 0.0082]))
    if with_imu:
        h.setImuExtrinsics(left, T_left_imu[:3, :3].tolist(), (T_left_imu[:3, 3] * 100).tolist(), [1, 0, 1])
    h.setStereoLeft(left, np.eye(3).tolist())
    h.setStereoRight(right, np.eye(3).tolist())
    path = tmp_path / "oak_calib.json"
    assert h.eepromToJsonFile(str(path))
    return path, T_right_left, T_left_imu


def test_depthai_import_metres_and_frames(tmp_path):
    path, T_right_left, T_left_imu = _depthai_json(tmp_path)
    calib, notes = import_calibration("depthai", [path])
    assert calib.cam0.width == 1280 and calib.cam0.fx == pytest.approx(798.1, abs=1e-3)
    np.testing.assert_allclose(calib.T_cam1_cam0, T_right_left, atol=1e-6)  # cm -> m and direction
    np.testing.assert_allclose(calib.cam0.T_body_cam, inv_T(T_left_imu), atol=1e-6)
    assert calib.baseline_m == pytest.approx(0.0751, abs=1e-4)
    assert not any("more than any OAK board's" in m for m in notes.messages)
    # the same file with its translations written in mm where depthai reads cm: 0.75 m, said (a review's finding)
    text = path.read_text()
    for cm in ("-7.51", "3.75", "-7.5"):
        text = text.replace(cm, str(float(cm) * 10))
    path.write_text(text)
    assert any("0.751 m, more than any OAK board's" in m for m in import_calibration("depthai", [path])[1].messages)
    # the full rational model survives (k4..k6 of an OAK lens are large; dropping them moves pixels by tens)
    assert calib.cam0.distortion[:5] == pytest.approx((-4.21, 12.3, 0.0011, -0.0007, 4.6), abs=1e-6)
    assert len(calib.cam0.distortion) == 8 and calib.cam0.distortion[5] == pytest.approx(-4.1, abs=1e-6)
    _roundtrip(calib, tmp_path)


def test_depthai_import_takes_the_sockets_the_oak_driver_streams(tmp_path):
    """A file naming CAM_C as its stereo left imported CAM_C's intrinsics as cam0's, while the OAK driver records
    CAM_B as cam0: a calibration swapped against the images, exit 0, unsaid (a QA sweep)."""
    import json

    path, _, _ = _depthai_json(tmp_path)
    d = json.loads(path.read_text())
    srd = d["stereoRectificationData"]
    srd["leftCameraSocket"], srd["rightCameraSocket"] = srd["rightCameraSocket"], srd["leftCameraSocket"]
    swapped = tmp_path / "swapped.json"
    swapped.write_text(json.dumps(d))
    calib, notes = import_calibration("depthai", [swapped])
    assert calib.cam0.fx == pytest.approx(798.1, abs=1e-3) and calib.cam1.fx == pytest.approx(797.4, abs=1e-3)
    assert any("streams CAM_B as cam0 and CAM_C as cam1" in m for m in notes.messages)
    assert not any("streams CAM_B" in m for m in import_calibration("depthai", [path])[1].messages)


def test_depthai_without_imu_and_fisheye(tmp_path):
    path, T_right_left, _ = _depthai_json(tmp_path, with_imu=False, fisheye=True)
    calib, notes = import_calibration("depthai", [path])
    np.testing.assert_allclose(calib.cam0.T_body_cam, np.eye(4))
    np.testing.assert_allclose(calib.T_cam1_cam0, T_right_left, atol=1e-6)
    assert calib.cam0.distortion_model == "equidistant" and len(calib.cam0.distortion) == 4
    assert any("no IMU extrinsics" in m for m in notes.messages)


def test_depthai_bad_file(tmp_path):
    pytest.importorskip("depthai")
    f = tmp_path / "x.json"
    f.write_text("{not json")
    with pytest.raises(VioError, match=r"x\.json"):
        import_calibration("depthai", [f])


def test_unknown_format_and_missing_file(tmp_path):
    with pytest.raises(VioError, match="unknown calibration format"):
        import_calibration("matlab", [DATA / "kalibr_imu.yaml"])
    with pytest.raises(VioError, match="file not found"):
        import_calibration("kalibr", [tmp_path / "nope.yaml"])


# ------------------------------------------------------------------------------------------------ show

def test_show_reports_geometry(v101_path):
    calib, _ = import_calibration("euroc", [v101_path])
    text = format_calibration(calib)
    assert "baseline       110.08 mm" in text
    assert "rotation angle 0.818 deg" in text
    axes = camera_axes(calib.cam0)
    # the VI-sensor cameras look along body +z (within 1.5 deg), image right is body +y
    assert axes["forward(z)"][0] == "+z" and axes["forward(z)"][1] < 2.0
    assert axes["right(x)"][0] == "+y"
    assert "UNITS" not in text
    # the same file written in millimetres: the baseline line alone (110080 mm) is easy to read past
    mm = [replace(c, T_body_cam=np.vstack([np.hstack([c.T_body_cam[:3, :3], 1000 * c.T_body_cam[:3, 3:]]),
                                                       [0, 0, 0, 1]])) for c in (calib.cam0, calib.cam1)]
    text = format_calibration(replace(calib, cam0=mm[0], cam1=mm[1]))
    assert "UNITS PROBLEM" in text and "millimetres" in text, text


def test_cli_import_and_show(tmp_path, capsys):
    from vio.app.cli import main

    out = tmp_path / "c.yaml"
    rc = main(["calib", "import", "kalibr", str(DATA / "kalibr_camchain_imucam.yaml"),
               str(DATA / "kalibr_imu.yaml"), "-o", str(out)])
    assert rc == 0 and out.is_file()
    assert main(["calib", "show", str(out)]) == 0
    assert "time offset      -5.200 ms" in capsys.readouterr().out
    assert main(["calib", "show", str(tmp_path / "missing.yaml")]) == 1
    # a file in millimetres was written with exit 0, and replay and run then refused it (a review's finding)
    import yaml

    mm = tmp_path / "mm.yaml"
    d = yaml.safe_load((DATA / "kalibr_camchain_imucam.yaml").read_text())
    for cam in ("cam0", "cam1"):
        T = np.array(d[cam]["T_cam_imu"], float)
        T[:3, 3] *= 1000
        d[cam]["T_cam_imu"] = T.tolist()
        d[cam].pop("T_cn_cnm1", None)
    mm.write_text(yaml.safe_dump(d))
    capsys.readouterr()
    out = tmp_path / "o.yaml"
    assert main(["calib", "import", "kalibr", str(mm), str(DATA / "kalibr_imu.yaml"), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert "millimetres" in err and "o.yaml not written" in err and not (tmp_path / "o.yaml").exists()


# ------------------------------------------------------------------------------------------------ Allan

def _synthetic_imu(duration_s, rate_hz, gyro_nk, accel_nk, seed=0):
    """Still IMU with white noise N and bias random walk K (continuous-time, kalibr units) per axis."""
    from vio.io.euroc import ImuData

    rng = np.random.default_rng(seed)
    n = int(duration_s * rate_hz)

    def channel(N, K):
        white = N * np.sqrt(rate_hz) * rng.standard_normal((n, 3))
        return white + np.cumsum(K / np.sqrt(rate_hz) * rng.standard_normal((n, 3)), axis=0)

    t = (np.arange(n) * 1e9 / rate_hz).astype(np.int64) + 10**18
    return ImuData(t, channel(*gyro_nk), channel(*accel_nk) + [0.0, 0.0, 9.81])


def test_allan_recovers_injected_noise(tmp_path):
    from calib.allan import analyse_imu, plot_allan, write_imu_yaml

    imu = _synthetic_imu(400.0, 200.0, (1.7e-3, 4e-4), (2e-3, 3e-3), seed=3)
    res = analyse_imu(imu)
    for f in res.gyro_fits:
        assert f.noise_density == pytest.approx(1.7e-3, rel=0.1)
    for f in res.accel_fits:
        assert f.noise_density == pytest.approx(2e-3, rel=0.1)
    assert 0.7 < res.noise.gyroscope_random_walk / 4e-4 < 1.6
    assert 0.7 < res.noise.accelerometer_random_walk / 3e-3 < 1.6
    assert res.noise.rate_hz == pytest.approx(200.0)
    out = tmp_path / "imu.yaml"
    write_imu_yaml(res.noise, out)
    back, _ = import_calibration("kalibr", [DATA / "kalibr_camchain_imucam.yaml", out])
    assert back.imu.gyroscope_noise_density == pytest.approx(res.noise.gyroscope_noise_density, rel=1e-5)
    plot_allan(res, tmp_path / "allan.png")
    assert (tmp_path / "allan.png").stat().st_size > 10_000


def test_allan_short_recording_gives_bound():
    from calib.allan import analyse_imu

    res = analyse_imu(_synthetic_imu(5.0, 200.0, (1.7e-4, 2e-5), (2e-3, 3e-3), seed=1))
    assert all(f.random_walk_is_bound for f in res.gyro_fits)
    assert any("upper bound" in n for n in res.notes)
    assert res.noise.gyroscope_noise_density == pytest.approx(1.7e-4, rel=0.3)


def test_allan_v101_uses_still_start(v101_path):
    from calib.allan import analyse_imu, load_imu_for_allan

    imu, desc = load_imu_for_allan(v101_path)
    span = (imu.t_ns[-1] - imu.t_ns[0]) / 1e9
    assert 4.5 < span < 5.4 and "ground truth" in desc  # motion starts 5.3 s in (GT |v| > 0.1 m/s)
    res = analyse_imu(imu)
    # rotor vibration, not sensor noise, dominates this span: well above the datasheet-like sensor.yaml
    assert res.noise.accelerometer_noise_density > 5 * 2.0e-3


# ------------------------------------------------------------------------------------------ time offset

def _rotation_only_recording(root: Path, offset_s: float, duration_s: float = 8.0, w: int = 320, h: int = 200,
                             seed: int = 0, gyro_bias=(0.01, -0.02, 0.015)):
    """EuRoC recording of a camera turning inside a textured sphere (no parallax), with a known offset.

    A frame stamped t_cam shows the orientation at IMU time t_cam + offset (t_imu = t_cam + offset).
    """
    import cv2
    from scipy.spatial.transform import Rotation

    from vio.calibration import CameraCalibration, ImuNoise, StereoCalibration
    from vio.io.euroc import EurocWriter
    from vio.types import ImuSample, StereoFrame

    rng = np.random.default_rng(seed)
    pano = np.zeros((512, 1024), np.float32)
    for s in (2, 4, 8, 16):
        pano += cv2.resize(rng.standard_normal((512 // s, 1024 // s)).astype(np.float32), (1024, 512),
                           interpolation=cv2.INTER_CUBIC)
    pano = cv2.normalize(pano, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    freq, amp, phase = rng.uniform(0.3, 1.2, (3, 3)), rng.uniform(0.1, 0.3, (3, 3)), rng.uniform(0, 6.3, (3, 3))

    def rotvec(t):  # orientation of the body in the world as a smooth rotation vector
        t = np.atleast_1d(t)[:, None, None]
        return np.sum(amp * np.sin(2 * np.pi * freq * t + phase), axis=2)

    def omega_body(t, eps=1e-5):
        R0, R1 = Rotation.from_rotvec(rotvec(t - eps)), Rotation.from_rotvec(rotvec(t + eps))
        return (R0.inv() * R1).as_rotvec() / (2 * eps)

    f = 0.6 * w
    T_bc = make_T(np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]), np.array([0.05, 0.0, 0.0]))
    cam = CameraCalibration(f, f, w / 2, h / 2, w, h, "radtan", (0, 0, 0, 0), T_bc, 20.0)
    cal = StereoCalibration(cam, cam, ImuNoise())  # the file does not know the offset
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(cam.K).T
    t_imu = np.arange(0.0, duration_s, 0.005)
    gyro = omega_body(t_imu) + np.asarray(gyro_bias) + 0.003 * rng.standard_normal((len(t_imu), 3))
    t_cam = np.arange(0.3, duration_s - 0.3, 0.05)
    base = 10**18
    with EurocWriter(root, cal) as wr:
        events = [(t, 0, i) for i, t in enumerate(t_imu)] + [(t, 1, i) for i, t in enumerate(t_cam)]
        for t, kind, i in sorted(events):
            t_ns = base + int(round(t * 1e9))
            if kind == 0:
                wr.write_imu(ImuSample(t_ns, gyro[i], np.array([0.0, 0.0, 9.81])))
                continue
            R_wc = Rotation.from_rotvec(rotvec(t + offset_s)[0]).as_matrix() @ T_bc[:3, :3]
            d = rays @ R_wc.T
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            mx = ((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (2 * np.pi) * 1024).astype(np.float32).reshape(h, w)
            my = ((np.pi / 2 - np.arcsin(np.clip(d[:, 2], -1, 1))) / np.pi * 512).astype(np.float32).reshape(h, w)
            img = cv2.remap(pano, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            wr.write_frame(StereoFrame(t_ns, img, None))  # left only: exercises the monocular path
    return root


@pytest.mark.parametrize("offset_ms", [8.0, -23.0])
def test_time_offset_recovers_injected_offset(tmp_path, offset_ms):
    from calib.time_offset import estimate_time_offset_dataset

    root = _rotation_only_recording(tmp_path / "rec", offset_ms / 1e3, duration_s=6.0)
    est = estimate_time_offset_dataset(root)
    assert est.observable
    assert est.offset_s * 1e3 == pytest.approx(offset_ms, abs=1.0)
    assert est.sigma_s < 1e-3
    np.testing.assert_allclose(est.gyro_bias, [0.01, -0.02, 0.015], atol=3e-3)


def test_time_offset_cli_and_static_warning(tmp_path, capsys, v101_path):
    from vio.app.cli import main

    root = _rotation_only_recording(tmp_path / "rec", 0.008, duration_s=4.0)
    assert main(["calib", "time-offset", str(root), "--plot", str(tmp_path / "to.png")]) == 0
    out = capsys.readouterr().out
    assert "t_imu = t_cam + offset" in out and (tmp_path / "to.png").is_file()
    assert "time_offset_ns: 8" in out  # 8 ms, told from zero: the value to paste
    root0 = _rotation_only_recording(tmp_path / "rec0", 0.0, duration_s=4.0)
    assert main(["calib", "time-offset", str(root0)]) == 0
    out = capsys.readouterr().out
    # an offset within its own uncertainty of zero is not offered for pasting (-2.5 +- 8.6 ms was: a review's)
    assert "time_offset_ns:" not in out and "the calibration's +0.00 ms agrees (within 2 sigma)" in out
    # compared with what the calibration states: a file saying +30 ms was told to keep it (a review's finding)
    from vio.io.euroc import EurocDataset

    save_calibration(replace(EurocDataset(root0).calibration, time_offset_ns=30_000_000), tmp_path / "late.yaml")
    assert main(["calib", "time-offset", str(root0), "--calibration", str(tmp_path / "late.yaml")]) == 0
    out = capsys.readouterr().out
    assert re.search(r"the calibration's \+30\.00 ms is off by -[23]\d\.\d\d ms .*set time_offset_ns: -?\d+", out), out
    # the V1_01 excerpt hardly moves: the tool must say the offset is not observable
    assert main(["calib", "time-offset", str(v101_path)]) == 0
    assert "too little rotation" in capsys.readouterr().out


def _still_imu_csv(csv):
    """30 s of a still IMU at 200 Hz as a plain csv: enough for an Allan analysis."""
    t = 10**18 + np.arange(6000) * 5_000_000
    rng = np.random.default_rng(0)
    np.savetxt(csv, np.column_stack([t, 1e-3 * rng.standard_normal((6000, 3)),
                                     [0, 0, 9.81] + 1e-2 * rng.standard_normal((6000, 3))]),
               delimiter=",", fmt=["%d"] + ["%.9f"] * 6, header="timestamp,wx,wy,wz,ax,ay,az")
    return csv


def test_calib_plots_without_the_tools_extra_are_refused_before_the_analysis(tmp_path, capsys, monkeypatch):
    """`vio calib time-offset --plot` / `imu-noise --plot` without matplotlib estimated and printed, (imu-noise)
    left -o unwritten, and only then failed "needs the [tools] extra": now said first, nothing printed."""
    from vio.app.cli import main

    root = _rotation_only_recording(tmp_path / "rec", 0.008, duration_s=4.0)
    csv = _still_imu_csv(tmp_path / "imu.csv")
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # as on a core install: import matplotlib fails
    for argv, what in ((["time-offset", str(root)], "the time-offset plot"),
                       (["imu-noise", str(csv), "-o", str(tmp_path / "imu.yaml")], "the Allan deviation plot")):
        assert main(["calib", *argv, "--plot", str(tmp_path / "p.png")]) == 1
        out, err = capsys.readouterr()
        assert out == "" and err.strip().splitlines() == [
            f"vio calib: error: {what} needs the [tools] extra: pip install 'kestrel-vio[tools]'"]
    assert not (tmp_path / "p.png").exists() and not (tmp_path / "imu.yaml").exists()


def test_calib_plots_go_to_the_file_named_and_an_unknown_format_is_refused_first(tmp_path, capsys):
    """`calib imu-noise --plot p` wrote p.png (a file nothing checked), `--plot p.txt` ended the analysis in an
    internal error (a review's finding): now the plot goes to exactly the name given and a format matplotlib cannot
    write is refused before the analysis, as for `vio eval --plot`."""
    from vio.app.cli import main

    csv = _still_imu_csv(tmp_path / "imu.csv")
    assert main(["calib", "imu-noise", str(csv), "--plot", str(tmp_path / "p.txt")]) == 1
    out, err = capsys.readouterr()
    assert out == "" and "a plot cannot be written as .txt" in err and "internal error" not in err
    assert main(["-q", "calib", "imu-noise", str(csv), "--plot", str(tmp_path / "p")]) == 0
    capsys.readouterr()
    assert (tmp_path / "p").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not (tmp_path / "p.png").exists()


# ------------------------------------------------------------------------------------------------ check

def _perturbed(calib, rotvec_cam1):
    """cam1 turned by a small rotation about its own axes (a miscalibrated stereo extrinsic)."""
    from dataclasses import replace

    T = calib.cam1.T_body_cam @ make_T(so3_exp(np.asarray(rotvec_cam1)), np.zeros(3))
    return replace(calib, cam1=calib.cam1.with_T_body_cam(T))


def test_check_passes_euroc_and_fails_bad_extrinsics(v101_path):
    from calib.check import check_calibration, format_report

    good = {r.name: r for r in check_calibration(v101_path, None, max_frames=6)}
    for name in ("stereo epipolar error", "rectified row alignment", "reprojection consistency",
                 "gravity magnitude when still", "gravity direction vs ground truth"):
        assert good[name].verdict == "PASS", format_report(list(good.values()))
    report = format_report(list(good.values()))  # checks with no figure said without one ("IMU units: nan" before)
    assert "nan" not in report and "PASS  IMU units: (accel about g" in report, report
    calib, _ = import_calibration("euroc", [v101_path])
    # 0.5 deg about cam1's x axis moves epipolar lines vertically by ~4 px
    bad = {r.name: r for r in check_calibration(v101_path, _perturbed(calib, [np.radians(0.5), 0, 0]),
                                                 max_frames=6)}
    assert bad["stereo epipolar error"].verdict == "FAIL" and bad["stereo epipolar error"].value > 2.0
    assert bad["rectified row alignment"].verdict == "FAIL"
    assert "overall: FAIL" in format_report(list(bad.values()))


def test_check_swapped_cameras_put_points_behind(v101_path):
    from dataclasses import replace

    from calib.check import check_calibration

    calib, _ = import_calibration("euroc", [v101_path])
    swapped = replace(calib, cam0=calib.cam1, cam1=calib.cam0)
    res = {r.name: r for r in check_calibration(v101_path, swapped, max_frames=4)}
    assert res["reprojection consistency"].verdict == "FAIL"


def test_check_resolution_mismatch(v101_path, tmp_path):
    from dataclasses import replace

    from calib.check import check_calibration

    calib, _ = import_calibration("euroc", [v101_path])
    small = replace(calib, cam0=replace(calib.cam0, width=640, cx=320.0))
    with pytest.raises(VioError, match="752x480 but the calibration is for 640x480"):
        check_calibration(v101_path, small, max_frames=2)


def test_time_offset_on_simulated_flight(tmp_path):
    """The project's simulator (realistic variant: blur, noise, gain drift, vibration) with 8 ms injected."""
    from calib.time_offset import estimate_time_offset_dataset
    from vio.sim.generate import SimConfig, simulate

    cfg = SimConfig(profile="aggressive", duration_s=10.0, time_offset_ms=8.0, width=376, height=240, seed=1)
    simulate(tmp_path / "sim", cfg, progress=False)
    est = estimate_time_offset_dataset(tmp_path / "sim")
    assert est.observable
    assert est.offset_s * 1e3 == pytest.approx(8.0, abs=1.0)


def test_depthai_conversion_scales_to_streamed_size(tmp_path):
    """The driver passes device.readCalibration() and its stream size: K must follow the resolution."""
    dai = pytest.importorskip("depthai")
    from calib.depthai_import import stereo_from_depthai

    path, T_right_left, _ = _depthai_json(tmp_path)
    full = stereo_from_depthai(dai.CalibrationHandler(str(path)))
    half = stereo_from_depthai(dai.CalibrationHandler(str(path)), size=(640, 400), cam_rate_hz=30.0)
    assert (half.cam0.width, half.cam0.height, half.cam0.rate_hz) == (640, 400, 30.0)
    assert half.cam0.fx == pytest.approx(full.cam0.fx / 2, rel=1e-6)
    np.testing.assert_allclose(half.T_cam1_cam0, T_right_left, atol=1e-6)


def test_cli_depthai_import_to_the_streamed_size(tmp_path, capsys):
    """An OAK streams 640x400 from a 1280x800 calibration: `vio calib import depthai --size` writes the file for
    what is streamed (a full-size file made vio run refuse every frame)."""
    pytest.importorskip("depthai")
    from vio.app.cli import main
    from vio.calibration import load_calibration

    path, _, _ = _depthai_json(tmp_path)
    out = tmp_path / "c.yaml"
    assert main(["calib", "import", "depthai", str(path), "--size", "640x400", "-o", str(out)]) == 0
    c = load_calibration(out)
    assert (c.cam0.width, c.cam0.height) == (640, 400) and c.cam0.fx == pytest.approx(798.1 / 2, abs=1e-3)
    for bad, says in ((["--size", "640"], "expected WIDTHxHEIGHT"),):
        assert main(["calib", "import", "depthai", str(path), *bad, "-o", str(tmp_path / "x.yaml")]) == 2  # usage
        assert says in capsys.readouterr().err and not (tmp_path / "x.yaml").exists()


def test_check_names_unit_mistakes(tmp_path):
    """`vio calib check` gives the diagnosis `vio replay` stops on: accel in g, a calibration in millimetres."""
    from calib.check import check_calibration
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "sim"
    simulate(data, SimConfig(profile="hover", duration_s=3.0, width=188, height=120, seed=4), progress=False)
    imu = data / "mav0" / "imu0" / "data.csv"
    lines = imu.read_text().splitlines()
    rows = [r.split(",") for r in lines[1:]]
    imu.write_text("\n".join([lines[0]] + [",".join(r[:4] + [repr(float(x) / 9.80665) for x in r[4:]])
                                           for r in rows]) + "\n")
    calib, _ = import_calibration("euroc", [data])
    T0, T1 = calib.cam0.T_body_cam.copy(), calib.cam1.T_body_cam.copy()
    T0[:3, 3] *= 1000
    T1[:3, 3] *= 1000
    mm = replace(calib, cam0=calib.cam0.with_T_body_cam(T0), cam1=calib.cam1.with_T_body_cam(T1))
    res = {r.name: r for r in check_calibration(data, mm, max_frames=2)}
    assert res["IMU units"].verdict == "FAIL" and "units of g, not m/s^2" in res["IMU units"].detail
    assert "units of g" in res["gravity magnitude when still"].detail
    assert res["stereo baseline"].verdict == "FAIL" and "millimetres" in res["stereo baseline"].detail
    assert res["camera-IMU lever arm"].verdict == "FAIL"
    assert res["camera-IMU time offset"].verdict == "PASS"
    late = replace(calib, time_offset_ns=500_000_000)  # 0.5 s: another unit, or the wrong clock
    res = {r.name: r for r in check_calibration(data, late, max_frames=2)}
    assert res["camera-IMU time offset"].verdict == "FAIL" and "500 ms" in res["camera-IMU time offset"].detail


def test_a_time_offset_that_is_not_whole_nanoseconds_is_refused(tmp_path):
    """0.005 (meant as seconds) was read as 0 unsaid (a review's finding)."""
    from vio import VioError
    from vio.calibration import load_calibration, save_calibration
    from vio.sim import default_calibration

    save_calibration(default_calibration(), tmp_path / "c.yaml")
    text = (tmp_path / "c.yaml").read_text()
    assert "time_offset_ns: 0" in text
    (tmp_path / "s.yaml").write_text(text.replace("time_offset_ns: 0", "time_offset_ns: 0.005"))
    with pytest.raises(VioError, match="whole nanoseconds.*5000000"):
        load_calibration(tmp_path / "s.yaml")
    (tmp_path / "f.yaml").write_text(text.replace("time_offset_ns: 0", "time_offset_ns: 5000000.0"))
    assert load_calibration(tmp_path / "f.yaml").time_offset_ns == 5_000_000


@pytest.mark.parametrize("edit,says", [
    (("time_offset_ns: 0", "time_offset_ms: 30"), r"unknown key 'time_offset_ms' \(did you mean 'time_offset_ns'\?\)"),
    (("gyroscope_noise_density:", "gyroscope_noise_densty:"), r"imu: unknown key 'gyroscope_noise_densty'"),
    (("distortion_coeffs:", "distortion_coefs:"), r"cam0: unknown key 'distortion_coefs'"),
    (("imu:", "imu_unused:"), r"unknown key 'imu_unused'"),
    (("T_body_cam:", "T_cam_imu: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n  T_body_cam:"),
     "both T_body_cam and T_cam_imu"),
])
def test_a_calibration_file_with_a_misspelt_or_doubled_key_is_refused(tmp_path, edit, says):
    """Each of these loaded and flew on a default (no distortion, the default IMU noise, no time offset), unsaid
    (a review's finding)."""
    from vio import VioError
    from vio.sim import default_calibration

    save_calibration(default_calibration(), tmp_path / "c.yaml")
    text = (tmp_path / "c.yaml").read_text()
    assert edit[0] in text
    (tmp_path / "bad.yaml").write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(VioError, match=says):
        load_calibration(tmp_path / "bad.yaml")


def test_a_calibration_file_without_imu_or_with_nan_distortion_is_refused(tmp_path):
    import yaml

    from vio import VioError
    from vio.sim import default_calibration

    save_calibration(default_calibration(), tmp_path / "c.yaml")
    d = yaml.safe_load((tmp_path / "c.yaml").read_text())
    del d["imu"]
    (tmp_path / "noimu.yaml").write_text(yaml.safe_dump(d))
    with pytest.raises(VioError, match="missing key 'imu'"):
        load_calibration(tmp_path / "noimu.yaml")
    d = yaml.safe_load((tmp_path / "c.yaml").read_text())
    d["cam0"]["distortion_coeffs"][0] = float("nan")  # ended a replay in "SVD did not converge"
    (tmp_path / "nan.yaml").write_text(yaml.safe_dump(d))
    with pytest.raises(VioError, match="distortion coefficients must be finite"):
        load_calibration(tmp_path / "nan.yaml")
    d = yaml.safe_load((tmp_path / "c.yaml").read_text())
    d["cam1"]["T_body_cam"][0][3] = float("inf")
    (tmp_path / "inf.yaml").write_text(yaml.safe_dump(d))
    with pytest.raises(VioError, match="cam1: T_body_cam is not a rigid transform"):
        load_calibration(tmp_path / "inf.yaml")

    for res in ([320.5, 200], [320, 200, 1], ["320", 200], [True, 200]):  # int() took 320.5 for 320, True for 1
        d = yaml.safe_load((tmp_path / "c.yaml").read_text())
        d["cam0"]["resolution"] = res
        (tmp_path / "res.yaml").write_text(yaml.safe_dump(d))
        with pytest.raises(VioError, match=r"cam0: resolution must be two whole numbers \[width, height\]"):
            load_calibration(tmp_path / "res.yaml")
    d = yaml.safe_load((tmp_path / "c.yaml").read_text())
    d["cam0"]["resolution"] = [float(x) for x in d["cam0"]["resolution"]]  # 752.0 is a whole number: read
    (tmp_path / "res.yaml").write_text(yaml.safe_dump(d))
    assert load_calibration(tmp_path / "res.yaml").cam0.width == int(d["cam0"]["resolution"][0])


def test_calib_refine_refuses_a_flight_without_rotation(tmp_path, capsys):
    """A hover never passes the extrinsic refinement's motion gate: no calibration is written, and the
    message says what recording would do."""
    from vio.app.cli import main
    from vio.sim.generate import SimConfig, simulate

    simulate(tmp_path / "hover", SimConfig(profile="hover", duration_s=3.0, variant="clean", width=376, height=240,
                                           texels_per_m=60.0, still_start_s=1.0))
    out = tmp_path / "refined.yaml"
    import cv2

    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(2)
        assert main(["calib", "refine", str(tmp_path / "hover"), "--output", str(out)]) == 1
        assert cv2.getNumThreads() == 1  # reproducible: as `vio replay`, one OpenCV thread (docs/evaluation.md)
    finally:
        cv2.setNumThreads(before)
    assert "enough rotation" in capsys.readouterr().err and not out.exists()


def test_check_compares_the_camera_imu_rotation_with_the_gyro(turning_flight):
    """An inverted T_cam_imu, a file that states no camera-IMU extrinsic (body = cam0) or a rig turned by 5 deg
    leave every stereo check passing, and flew at 0.3-6 m of error with the quality the autopilot fuses (a
    review's finding). The camera's turns between frames against the gyro's tell the rotation."""
    import dataclasses

    from calib.check import check_camera_imu_rotation
    from vio.io.euroc import EurocDataset

    data, stated = turning_flight()

    def rig(T0: np.ndarray) -> object:
        """both cameras moved together: the stereo pair as it was"""
        D = np.linalg.inv(stated.cam0.T_body_cam) @ T0
        return dataclasses.replace(stated, cam0=stated.cam0.with_T_body_cam(T0),
                                   cam1=stated.cam1.with_T_body_cam(stated.cam1.T_body_cam @ D))

    def check(calib) -> object:
        return check_camera_imu_rotation(EurocDataset(data, calibration=calib), calib)

    ok = check(stated)
    assert ok.verdict == "PASS" and ok.value < 0.5, ok
    turned = check(rig(stated.cam0.T_body_cam @ make_T(so3_exp(np.radians([5.0, 0, 0])), np.zeros(3))))
    assert turned.verdict == "FAIL" and 4.5 < turned.value < 5.5 and "inverted" in turned.detail, turned
    assert check(rig(np.eye(4))).verdict == "FAIL"  # body = cam0
    assert check(rig(np.linalg.inv(stated.cam0.T_body_cam))).verdict == "FAIL"  # T_cam_imu taken as T_imu_cam


def test_calib_refine_writes_refined_focal_lengths(tmp_path, capsys, turning_flight):
    """`vio calib refine --intrinsics` on a turning flight whose sensor.yaml is slightly wrong writes a loadable
    calibration with refined extrinsics and focal lengths (the principal point held) and says how far each moved."""
    from vio.app.cli import main
    from vio.calibration import load_calibration

    data, stated = turning_flight(calib_error=2.0)
    out = tmp_path / "refined.yaml"
    assert main(["calib", "refine", str(data), "--output", str(out), "--intrinsics"]) == 0
    text = capsys.readouterr().out
    assert "cam0 fx fy cx cy moved" in text and f"wrote {out}" in text
    refined = load_calibration(out)
    assert refined.cam0.fx != stated.cam0.fx and refined.cam1.fy != stated.cam1.fy
    assert abs(refined.cam0.cx - stated.cam0.cx) < 0.01 and abs(refined.cam1.cy - stated.cam1.cy) < 0.01
    assert not np.allclose(refined.cam0.T_body_cam, stated.cam0.T_body_cam)


def test_calib_refine_stereo_only_turns_cam1_back_and_holds_the_rest(tmp_path, capsys, turning_flight):
    """A recording whose cam1 principal point the sensor.yaml states 1 px off (a stereo calibration that drifted):
    `vio calib refine --stereo-only` writes a calibration in which only cam1's pose on the body moved, by about
    what 1 px of disparity is, and says so; with --stereo as well it refuses with a message."""
    import re

    from vio.app.cli import main
    from vio.calibration import load_calibration

    data, stated = turning_flight(stereo_error_px=1.0)
    out = tmp_path / "refined.yaml"
    assert main(["calib", "refine", str(data), "--output", str(out), "--stereo-only"]) == 0
    said = capsys.readouterr().out
    m = re.search(r"a disparity bias of ([-+0-9.]+) px \(\+- ([0-9.]+) px, 1 sigma\) taken out", said)
    px, sigma = float(m.group(1)), float(m.group(2))
    # stated 1 px right of the truth: disparities 1 px too large, found within a few sigma of it
    assert 0.4 < px < 1.5 and 0 < sigma < px / 3 and "too large (depths too short)" in said and f"wrote {out}" in said
    refined = load_calibration(out)
    np.testing.assert_allclose(refined.cam0.T_body_cam, stated.cam0.T_body_cam, atol=1e-9)
    assert not np.allclose(refined.cam1.T_body_cam[:3, :3], stated.cam1.T_body_cam[:3, :3], atol=1e-4)
    np.testing.assert_allclose(refined.cam1.T_body_cam[:3, 3], stated.cam1.T_body_cam[:3, 3], atol=1e-4)
    assert main(["calib", "refine", str(data), "--output", str(tmp_path / "x.yaml"), "--stereo-only",
                 "--stereo"]) == 2
    assert "--stereo-only refines cam1's rotation alone" in capsys.readouterr().err


def test_calib_refine_stereo_only_leaves_cam1_alone_when_the_recording_cannot_show_a_bias(tmp_path, capsys,
                                                                                         v101_path):
    """The real EuRoC excerpt barely moves: the refinement turns cam1 by some hundredths of a degree, but its
    uncertainty is as large, so `vio calib refine --stereo-only` says so and writes cam1 as calibrated."""
    import re

    from vio.app.cli import main
    from vio.io.euroc import EurocDataset

    data = v101_path
    out = tmp_path / "refined.yaml"
    assert main(["calib", "refine", str(data), "--output", str(out), "--stereo-only"]) == 0
    said = capsys.readouterr().out
    m = re.search(r"disparity bias ([-+0-9.]+) \+- ([0-9.]+) px \(1 sigma\).*under 3 sigma", said)
    assert m and abs(float(m.group(1))) < 3 * float(m.group(2)) and "cam1 left as calibrated" in said
    stated = EurocDataset(data).calibration
    np.testing.assert_allclose(load_calibration(out).cam1.T_body_cam, stated.cam1.T_body_cam, atol=1e-9)


def test_calib_check_disparity_finds_a_drifted_stereo_pair_that_every_other_check_passes(turning_flight, capsys):
    """cam1's principal point stated 1 px sideways: every right pixel moves along its epipolar line, so the
    epipolar, rectification and reprojection checks pass and the calibration looks fine; `--disparity` replays
    the recording, finds the bias (well over 3 sigma) and fails the check with what to do about it."""
    import re

    from vio.app.cli import main

    data, _ = turning_flight(stereo_error_px=1.0)
    assert main(["calib", "check", "-", str(data), "--max-frames", "10"]) == 0
    said = capsys.readouterr().out
    assert re.search(r"PASS  stereo epipolar error", said) and "overall: PASS" in said
    assert re.search(r"SKIP  stereo disparity bias: .*add --disparity", said)
    assert main(["calib", "check", "-", str(data), "--max-frames", "10", "--disparity"]) == 1
    said = capsys.readouterr().out
    m = re.search(r"FAIL  stereo disparity bias: ([0-9.]+) px .*\(([-+0-9.]+) \+- ([0-9.]+) px \(1 sigma\).*"
                  r"depths short.*--stereo-only", said)
    assert m and 0.4 < float(m.group(1)) < 1.5 and float(m.group(3)) < float(m.group(1)) / 3
    assert "overall: FAIL" in said


def test_calib_check_disparity_finds_two_cameras_whose_focal_lengths_disagree(turning_flight):
    """cam1's fx stated 1 % too long (cam0 as it was): the right pixels move along the epipolar lines in
    proportion to their distance from the centre, so the epipolar check passes; the stereo check's focal reading
    finds it (about 1 % of half the image width at the edge) and fails it, while the disparity row (the turn about
    cam1's y axis) stays small."""
    import dataclasses

    from calib.check import check_disparity, check_epipolar, collect_matches
    from vio.io.euroc import EurocDataset

    data, stated = turning_flight()
    wrong = dataclasses.replace(stated, cam1=dataclasses.replace(stated.cam1, fx=stated.cam1.fx * 1.01))
    m, _ = collect_matches(EurocDataset(data, calibration=wrong), wrong, 10)
    assert check_epipolar(wrong, m).verdict == "PASS"
    disparity, focal = check_disparity(data, wrong)
    edge_px = 0.01 * stated.cam1.width / 2
    print(disparity, focal, edge_px)
    assert focal.name == "stereo focal lengths" and focal.verdict == "FAIL", focal
    assert 0.5 * edge_px < focal.value < 1.5 * edge_px and "fx of the two cameras disagree" in focal.detail
    assert disparity.value < 0.5 * focal.value, disparity


def test_calib_outputs_never_replace_a_file_unasked_nor_fail_after_the_work(tmp_path, capsys):
    """`vio calib imu-noise -o` wrote its IMU lines over a whole calibration, and a read-only folder ended in an
    "internal error" after the work (a review's findings): an existing output needs --overwrite, and what cannot
    be written is refused first, in one line."""
    import os

    from vio.app.cli import main

    src = [str(DATA / "kalibr_camchain_imucam.yaml")]
    out = tmp_path / "calib.yaml"
    assert main(["calib", "import", "kalibr", *src, "-o", str(out)]) == 0
    kept = out.read_text()
    csv = tmp_path / "imu.csv"
    t = np.arange(4000) * 5_000_000
    rows = np.column_stack([t, np.random.default_rng(0).normal(0, 1e-3, (4000, 3)),
                            np.random.default_rng(1).normal(0, 1e-2, (4000, 3)) + [0, 0, 9.81]])
    csv.write_text("#timestamp,wx,wy,wz,ax,ay,az\n" + "\n".join(
        ",".join([str(int(r[0]))] + [f"{x:.6f}" for x in r[1:]]) for r in rows) + "\n")
    capsys.readouterr()
    for argv in (["calib", "import", "kalibr", *src, "-o", str(out)],
                 ["calib", "imu-noise", str(csv), "-o", str(out)]):
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert f"{out} exists: not replaced (--overwrite replaces it)" in err and "internal error" not in err
        assert out.read_text() == kept
    assert main(["calib", "import", "kalibr", *src, "-o", str(out), "--overwrite"]) == 0
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        assert main(["calib", "import", "kalibr", *src, "-o", str(ro / "c.yaml")]) == 1
        assert "cannot write there" in capsys.readouterr().err
    capsys.readouterr()
    if os.path.isdir("/proc/self"):  # where root cannot write either: the analysis ran, then the write failed
        for argv in (["calib", "import", "kalibr", *src, "-o", "/proc/c.yaml"],
                     ["calib", "imu-noise", str(csv), "-o", "/proc/i.yaml"]):
            assert main(argv) == 1, argv
            out_, err = capsys.readouterr()
            assert "/proc/" in err and "cannot write there" in err and not out_, (argv, out_, err)


def test_an_identity_camera_imu_extrinsic_is_warned_about_when_flown(caplog):
    """An import without camera-IMU extrinsics writes body = cam0; replayed, a real rig flew 4.2 m off with nothing
    said (a review's finding). The estimator says so at start."""
    import logging

    from vio.estimator import Estimator
    from vio.sim import default_calibration

    calib = default_calibration()
    with caplog.at_level(logging.WARNING, logger="vio.estimator"):
        Estimator(calib)
    assert "T_body_cam0 is the identity" not in caplog.text
    T1 = calib.cam1.T_body_cam @ np.linalg.inv(calib.cam0.T_body_cam)  # the stereo pair as it was
    body_cam0 = replace(calib, cam0=calib.cam0.with_T_body_cam(np.eye(4)), cam1=calib.cam1.with_T_body_cam(T1))
    with caplog.at_level(logging.WARNING, logger="vio.estimator"):
        Estimator(body_cam0)
    assert "T_body_cam0 is the identity" in caplog.text and "vio calib check" in caplog.text


def test_check_warns_of_imu_noise_densities_in_another_unit(v101_path):
    """Densities x1000 (or /1000) imported and passed every check (a review's finding): against the spread of the
    still span they stand out; the dataset's own pass."""
    from calib.check import check_calibration
    from vio.io.euroc import EurocDataset

    calib = EurocDataset(v101_path).calibration
    ok = {r.name: r for r in check_calibration(v101_path, calib, max_frames=2)}["IMU noise vs still spread"]
    assert ok.verdict == "PASS", ok
    for k, says in ((1000.0, "above what the sensor shows"), (1e-3, "below what the sensor shows")):
        imu = replace(calib.imu, accelerometer_noise_density=calib.imu.accelerometer_noise_density * k,
                      gyroscope_noise_density=calib.imu.gyroscope_noise_density * k)
        res = {r.name: r for r in check_calibration(v101_path, replace(calib, imu=imu), max_frames=2)}
        assert res["IMU noise vs still spread"].verdict == "WARN" and says in res["IMU noise vs still spread"].detail


def test_the_rotation_check_on_turns_about_one_axis_keeps_the_axis_sign(monkeypatch):
    """A survey turns about the vertical only: the check compares where that axis lies in the body. A camera
    mounted upside down (180 deg about its optical axis) flips the axis, and an unsigned comparison passed it (a
    review's finding). Synthetic yaw-only flight, the camera's turns handed in as the tool would measure them."""
    from types import SimpleNamespace as NS

    import calib.time_offset as time_offset
    from calib.check import check_camera_imu_rotation

    rng = np.random.default_rng(0)
    R_bc = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # camera looking forward on a level drone
    t_imu = np.arange(0, 60.0, 1 / 200)

    def w_cam(t):  # yaw about body z is a turn about the camera's -y
        return (0.6 * np.sin(2 * np.pi * 0.2 * t))[:, None] * np.array([0, -1.0, 0])

    gyro = w_cam(t_imu) @ R_bc.T + rng.normal(0, 1e-3, (len(t_imu), 3))
    tc = np.arange(1.0, 59.0, 1 / 20)
    theta = np.array([np.trapezoid(w_cam(np.linspace(a, b, 21)), np.linspace(a, b, 21), axis=0)
                      for a, b in zip(tc[:-1], tc[1:])])
    vis = NS(t0_ns=(tc[:-1] * 1e9).astype(np.int64), t1_ns=(tc[1:] * 1e9).astype(np.int64), theta_cam=theta)
    monkeypatch.setattr(time_offset, "visual_rotations", lambda ds, cam, step=1: vis)

    class Dataset(NS):
        def __len__(self):
            return len(tc)

    ds = Dataset(imu=NS(t_ns=(t_imu * 1e9).astype(np.int64), gyro=gyro))

    def check(R):
        return check_camera_imu_rotation(ds, NS(cam0=NS(T_body_cam=make_T(R, np.zeros(3))), time_offset_ns=0))

    ok = check(R_bc)
    assert ok.verdict == "PASS" and "one axis only" in ok.detail, ok
    assert check(R_bc @ so3_exp(np.array([0, 0, np.pi]))).verdict == "FAIL"  # upside down
    assert check(so3_exp(np.array([0, np.radians(5), 0])) @ R_bc).verdict == "FAIL"  # the vertical tilted 5 deg


def test_calib_check_exit_code_tells_a_check_that_could_not_run_from_a_fail(tmp_path, capsys, monkeypatch):
    """Exit 1 was both "a check FAILed" and "the check could not run" (a review's finding): a fleet script could
    not tell a wrong calibration from a missing recording. Could not run is now 4, said on stderr, no report."""
    from vio.app.cli import main
    from vio.io.euroc import EurocDataset
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "short"
    simulate(data, SimConfig(duration_s=2.0, width=320, height=200, variant="clean", still_start_s=1.0),
             progress=False)
    stated = EurocDataset(data).calibration
    assert main(["calib", "check", "-", str(data), "--max-frames", "5"]) == 0
    capsys.readouterr()
    other = tmp_path / "other_size.yaml"  # a calibration of another camera mode: the images do not fit it
    save_calibration(replace(stated, cam0=replace(stated.cam0, width=640, height=400),
                             cam1=replace(stated.cam1, width=640, height=400)), other)
    bad = tmp_path / "refused.yaml"
    bad.write_text(other.read_text() + "\nnot_a_key: 1\n")
    no_frames = tmp_path / "no_frames"  # cam0/data.csv with its header only: the IMU's checks alone said PASS
    shutil.copytree(data, no_frames)
    csv = no_frames / "mav0" / "cam0" / "data.csv"
    csv.write_text(csv.read_text().splitlines()[0] + "\n")
    for argv in (["-", str(tmp_path / "missing")], [str(tmp_path / "missing.yaml"), str(data)], [str(other), str(data)],
                 [str(bad), str(data)], ["-", str(no_frames)]):
        assert main(["calib", "check", *argv, "--max-frames", "5"]) == 4, argv
        said = capsys.readouterr()
        assert "vio calib: error: " in said.err and "overall:" not in said.out, (argv, said)
    import errno

    import calib.check

    for err in (OSError(errno.EIO, "I/O error"), RuntimeError("solver failed")):  # a review: these exited 1
        def broken(*a, err=err, **k):
            raise err
        monkeypatch.setattr(calib.check, "check_calibration", broken)
        for verbose in ([], ["-v"]):
            assert main([*verbose, "calib", "check", "-", str(data)]) == 4, (err, verbose)
            assert "overall:" not in capsys.readouterr().out


def test_a_camera_size_or_focal_length_no_camera_has_is_refused_in_one_line(tmp_path, v101_path, capsys):
    """A calibration 1e300 pixels wide (a project file or a EuRoC sensor.yaml) was taken: `vio calib show` printed a
    301-digit width and principal-point offset, `vio calib import euroc` wrote it out; a focal length of 1e300 px the
    same (a review's finding). CameraCalibration refuses both now, so every reader and importer does, in one line
    naming the file and camera."""
    import yaml

    from vio.app.cli import main
    from vio.sim import default_calibration

    save_calibration(default_calibration(), tmp_path / "c.yaml")
    cases = {"wide": ("cam0", "resolution", [1e300, 480], "resolution 1e+300x480 is beyond any camera's"),
             "tall": ("cam1", "resolution", [752, 40000], "resolution 752x40000 is beyond any camera's"),
             "fx": ("cam0", "intrinsics", [1e300, 200.0, 160.0, 100.0], "focal lengths fx=1e+300"),
             "fy": ("cam1", "intrinsics", [200.0, 1e6, 160.0, 100.0], "focal lengths fx=200, fy=1e+06 px are over 100")}
    for name, (cam, key, value, says) in cases.items():
        d = yaml.safe_load((tmp_path / "c.yaml").read_text())
        d[cam][key] = value
        (tmp_path / f"{name}.yaml").write_text(yaml.safe_dump(d))
        assert main(["calib", "show", str(tmp_path / f"{name}.yaml")]) == 1, name
        err = capsys.readouterr().err
        assert f"{name}.yaml: {cam}: {says}" in err and len(err.strip().splitlines()) == 1, err

    ds = tmp_path / "ds"
    for s in ("cam0", "cam1", "imu0"):
        (ds / "mav0" / s).mkdir(parents=True)
        shutil.copy(v101_path / "mav0" / s / "sensor.yaml", ds / "mav0" / s / "sensor.yaml")
    y = ds / "mav0" / "cam0" / "sensor.yaml"
    y.write_text(y.read_text().replace("resolution: [752, 480]", "resolution: [1.0e+300, 480]"))
    assert main(["calib", "import", "euroc", str(ds), "-o", str(tmp_path / "out.yaml")]) == 1
    err = capsys.readouterr().err
    assert "sensor.yaml: resolution 1e+300x480 is beyond any camera's" in err, err
    assert not (tmp_path / "out.yaml").exists()


def test_calib_refine_of_a_recording_without_readable_images_says_so(tmp_path, capsys):
    """`vio calib refine` of a recording whose left images are all missing said 'no keyframe had enough rotation to
    refine the extrinsics (a hover or straight flight)': the wrong cause, and the wrong remedy (a review's finding).
    It now says the estimator never initialised and how many images could not be read."""
    from vio.app.cli import main
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "flight"
    simulate(data, SimConfig(duration_s=2.0, width=188, height=120, variant="clean"), progress=False)
    for png in (data / "mav0" / "cam0" / "data").iterdir():
        png.unlink()
    out = tmp_path / "refined.yaml"
    assert main(["-q", "calib", "refine", str(data), "-o", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "the estimator never initialised (41 of 41 frames' images missing or unreadable" in err, err
    assert "rotation" not in err and not out.exists()


def test_calib_time_offset_of_a_recording_without_readable_images_says_so(tmp_path, capsys):
    """`vio calib time-offset` of a recording whose left images are all missing said 'only 0 usable frame pairs ...;
    too little texture?' (a review's finding): it now says how many images could not be read."""
    from vio.app.cli import main
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "flight"
    simulate(data, SimConfig(duration_s=2.0, width=188, height=120, variant="clean"), progress=False)
    for png in (data / "mav0" / "cam0" / "data").iterdir():
        png.unlink()
    assert main(["-q", "calib", "time-offset", str(data)]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "only 0 usable frame pairs" in err and "41 of 41 frames' images missing or unreadable" in err, err


def test_imu_noise_no_imu_has_is_refused_on_import_and_load(tmp_path, capsys):
    """A noise density of 1e-300 (or a random walk of 1e-20) was taken from kalibr's imu.yaml and from our calibration
    YAML: the pre-integration then trusted the IMU beyond any sensor, unsaid (a review's finding). Refused in one line
    naming the key."""
    from vio.app.cli import main

    imu = tmp_path / "imu.yaml"
    for key, value in (("gyroscope_noise_density", "1.0e-300"), ("accelerometer_random_walk", "1.0e-20")):
        text = (DATA / "kalibr_imu.yaml").read_text()
        imu.write_text(re.sub(rf"{key}: *\S+", f"{key}: {value}", text))
        assert main(["calib", "import", "kalibr", str(DATA / "kalibr_camchain_imucam.yaml"), str(imu), "-o",
                     str(tmp_path / "c.yaml"), "--overwrite"]) == 1, key
        err = capsys.readouterr().err
        assert f"{key} = {float(value):g} is below any IMU's" in err and len(err.strip().splitlines()) == 1, err
    ok = import_calibration("kalibr", [DATA / "kalibr_camchain_imucam.yaml", DATA / "kalibr_imu.yaml"])
    save_calibration(ok[0], tmp_path / "ok.yaml")
    text = (tmp_path / "ok.yaml").read_text()
    (tmp_path / "bad.yaml").write_text(re.sub(r"gyroscope_random_walk: *\S+", "gyroscope_random_walk: 1.0e-300", text))
    with pytest.raises(VioError, match=r"gyroscope_random_walk = 1e-300 is below any IMU's"):
        load_calibration(tmp_path / "bad.yaml")


def test_import_notes_are_logged_under_the_importers_name(caplog):
    """kalibr, EuRoC and OpenCV import notes were logged under calib.depthai_import (the one module that defined the
    notes), which sent a log filter or a reader looking at depthai for a kalibr file's warning."""
    with caplog.at_level("WARNING"):
        import_calibration("kalibr", [DATA / "kalibr_camchain_imucam.yaml"])
        import_calibration("opencv", [DATA / "opencv_stereo.yaml"])
    said = [(r.name, r.getMessage()) for r in caplog.records]
    assert any("no imu.yaml given" in m for _, m in said) and any("OpenCV stereo files" in m for _, m in said), said
    assert {name for name, _ in said} == {"calib.importers"}, said


def test_numbers_in_exponent_notation_without_a_dot_are_numbers(tmp_path):
    """PyYAML follows YAML 1.1, where `5e6` or `1146635e-4` (no dot) is text: `time_offset_ns: 5e6` was refused as
    "time_offset_ns = '5e6': whole nanoseconds" and an intrinsic written so as "must be four numbers, got [...,
    '1146635e-4']", numbers to the user and to YAML 1.2 (what kalibr's and OpenCV's writers follow). Read as numbers;
    a quoted one is still text."""
    ok = import_calibration("kalibr", [DATA / "kalibr_camchain_imucam.yaml", DATA / "kalibr_imu.yaml"])[0]
    save_calibration(ok, tmp_path / "ok.yaml")
    text = (tmp_path / "ok.yaml").read_text()
    assert "time_offset_ns: -5200000" in text and "- 458.654\n" in text
    (tmp_path / "e.yaml").write_text(text.replace("time_offset_ns: -5200000", "time_offset_ns: -52e5")
                                     .replace("- 458.654\n", "- 458654e-3\n"))
    c = load_calibration(tmp_path / "e.yaml")
    assert c.time_offset_ns == -5_200_000 and c.cam0.K[0, 0] == 458.654
    (tmp_path / "q.yaml").write_text(text.replace("- 458.654\n", "- '458654e-3'\n"))
    with pytest.raises(VioError, match="intrinsics must be four numbers"):
        load_calibration(tmp_path / "q.yaml")


def test_an_opencv_camera_matrix_kestrel_cannot_hold_is_refused(tmp_path, capsys):
    """K1 with a skew (K[0][1] = 5 px) or a last row other than 0 0 1 was imported as fx, fy, cx, cy alone, exit 0:
    a camera other than the one calibrated, unsaid. Refused in one line naming the file and the key."""
    from vio.app.cli import main

    text = (DATA / "opencv_stereo.yaml").read_text()
    src = tmp_path / "stereo.yaml"
    for old, new, says in (("795.20000000000005, 0., 641.70000000000005", "795.20000000000005, 5., 641.70000000000005",
                            "K1 has a skew of 5 px"),
                           ("797.10000000000002, 398.60000000000002, 0., 0., 1. ]",
                            "797.10000000000002, 398.60000000000002, 0., 0., 2. ]", "K2's last row is [0, 0, 2]")):
        assert old in text
        src.write_text(text.replace(old, new))
        assert main(["calib", "import", "opencv", str(src), "-o", str(tmp_path / "c.yaml"), "--translation-unit",
                     "mm"]) == 1
        err = capsys.readouterr().err
        assert f"{src}: {says}" in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "c.yaml").exists()


def test_an_opencv_stereo_rotation_that_is_none_names_the_file(tmp_path, capsys):
    """An R that is not a rotation (or a T with a NaN) in an OpenCV stereo file ended in "T_body_cam is not a rigid
    transform", naming neither the file nor R / T."""
    from vio.app.cli import main

    text = (DATA / "opencv_stereo.yaml").read_text()
    src = tmp_path / "stereo.yaml"
    for old, new, says in (("0.9999901500197903", "1.9999901500197903", "R is not a rotation matrix"),
                           ("data: [ -75.120000000000005", "data: [ .nan", "T has a non-finite value")):
        src.write_text(text.replace(old, new))
        assert main(["calib", "import", "opencv", str(src), "-o", str(tmp_path / "c.yaml")]) == 1
        err = capsys.readouterr().err
        assert f"{src}: {says}" in err and len(err.strip().splitlines()) == 1, err


def test_a_key_given_twice_in_a_calibration_yaml_is_refused(tmp_path, capsys):
    """A hand-edited camchain with `intrinsics:` given twice (a new line added, the old one left) was read with the
    last one, unsaid: PyYAML keeps the last of duplicate keys. Refused in one line naming the key and both lines."""
    from vio.app.cli import main

    text = (DATA / "kalibr_camchain_imucam.yaml").read_text()
    old = "  intrinsics: [458.654, 457.296, 367.215, 248.375]\n"
    assert old in text
    src = tmp_path / "camchain.yaml"
    src.write_text(text.replace(old, old + "  intrinsics: [460.0, 459.0, 367.215, 248.375]\n"))
    line = text[:text.index(old)].count("\n") + 1
    assert main(["calib", "import", "kalibr", str(src), "-o", str(tmp_path / "c.yaml")]) == 1
    err = capsys.readouterr().err
    assert f"{src}: key 'intrinsics' given twice (lines {line} and {line + 1})" in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "c.yaml").exists()
    ok = import_calibration("kalibr", [DATA / "kalibr_camchain_imucam.yaml"])[0]  # one key per mapping: fine
    save_calibration(ok, tmp_path / "ok.yaml")
    assert load_calibration(tmp_path / "ok.yaml").cam0.K[0, 0] == 458.654


def test_a_focal_length_no_lens_has_is_refused(tmp_path):
    """fx = 4.58 px (a typo of 458) for a 752 px wide image was taken (a field of view over 178 deg, or a fisheye
    seeing 80 rad to its edge), where 100x too long is refused."""
    ok = import_calibration("kalibr", [DATA / "kalibr_camchain_imucam.yaml"])[0]
    save_calibration(ok, tmp_path / "ok.yaml")
    text = (tmp_path / "ok.yaml").read_text()
    assert "- 458.654\n" in text
    (tmp_path / "bad.yaml").write_text(text.replace("- 458.654\n", "- 4.58654\n"))
    with pytest.raises(VioError, match=r"bad\.yaml: cam0: focal lengths fx=4\.58654, fy=457\.296 px: under 1/20 of "
                       r"the 752x480 image"):
        load_calibration(tmp_path / "bad.yaml")


def test_depthai_imu_noise_below_any_imus_is_taken_as_not_filled_in(tmp_path):
    """An OAK's EEPROM noise of 1e-20 (garbage where most devices leave 0) was taken; refused now by ImuNoise, it
    would stop the OAK's import and `vio run` altogether. It is treated as the zeros are: not filled in, the project
    defaults used, said."""
    import json

    d = json.loads((DATA.parent / "depthai_calib.json").read_text())
    for ax in ("x", "y", "z"):
        d["imuCalibrationParams"]["noise"]["gyroscope"][ax]["noiseDensity"] = 1e-20
    (tmp_path / "dai.json").write_text(json.dumps(d))
    calib, notes = import_calibration("depthai", [tmp_path / "dai.json"])
    assert calib.imu.gyroscope_noise_density == ImuNoise().gyroscope_noise_density
    assert any("gyroscope_noise_density" in m and "project defaults" in m for m in notes.messages), notes.messages


def test_allan_on_an_axis_without_noise_names_it(tmp_path):
    """A still recording where an axis reads the same value in every sample (a stuck or dead axis, a simulator's
    noise-free IMU) ended `vio calib imu-noise` in 'internal error: IndexError'; and one quieter than any IMU wrote
    noise figures `vio calib import` then refuses. Both are said in one line naming the axis."""
    from calib.allan import analyse_imu
    from vio.io.euroc import ImuData

    imu = _synthetic_imu(20.0, 200.0, (1.7e-4, 2e-5), (2e-3, 3e-3), seed=1)
    gyro = imu.gyro.copy()
    gyro[:, 2] = 0.001
    with pytest.raises(VioError, match=r"gyro z reads 0\.001 in every one of the 4000 samples"):
        analyse_imu(ImuData(imu.t_ns, gyro, imu.accel))
    gyro[:, 2] = 0.001 + 1e-13 * np.random.default_rng(0).standard_normal(len(gyro))
    with pytest.raises(VioError, match=r"gyro z: a noise density of [0-9.e+-]+ is below any IMU's"):
        analyse_imu(ImuData(imu.t_ns, gyro, imu.accel))


def test_calib_refine_on_a_recording_where_vision_never_worked_says_so(tmp_path, capsys):
    """`vio calib refine` of a recording whose left images carry nothing to track said 'no keyframe had enough
    rotation ... record with turns about at least two axes': the flight, not the images, blamed."""
    import cv2

    from vio.app.cli import main

    flight = tmp_path / "f"
    assert main(["-q", "simulate", str(flight), "--duration", "2", "--size", "188x120", "--no-progress"]) == 0
    for p in (flight / "mav0" / "cam0" / "data").iterdir():
        cv2.imwrite(str(p), np.full((120, 188), 128, np.uint8))
    capsys.readouterr()
    assert main(["-q", "calib", "refine", str(flight), "-o", str(tmp_path / "r.yaml")]) == 1
    err = capsys.readouterr().err
    assert "vision never worked (41 of 41 frames unusable: 41 image blurred or textureless)" in err, err
    assert "rotation" not in err and not (tmp_path / "r.yaml").exists()


def test_a_calibration_written_over_an_old_one_keeps_it_when_the_write_fails(tmp_path, monkeypatch) -> None:
    """save_calibration and write_imu_yaml wrote in place: a write that failed half way (a full SD card, a kill)
    left a truncated file where the old calibration was (the input review's note). Written whole now, through a
    link to the file it names; a device is still written into."""
    import calib.allan as allan
    import vio.calibration as vc
    from vio.sim import default_calibration

    calib = default_calibration()
    path = tmp_path / "calib.yaml"
    save_calibration(calib, path)
    old = path.read_text()

    class Unwritable(str):
        def encode(self, *a, **k):  # the disk filling up half way through the write
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(vc, "calibration_yaml", lambda c: Unwritable(old + "# new"))
    with pytest.raises((OSError, TypeError)):
        save_calibration(calib, path)
    assert path.read_text() == old and sorted(p.name for p in tmp_path.iterdir()) == ["calib.yaml"]
    monkeypatch.undo()
    (tmp_path / "link.yaml").symlink_to(path)
    save_calibration(calib, tmp_path / "link.yaml")  # written through the link: the link stays one
    assert (tmp_path / "link.yaml").is_symlink() and load_calibration(path).cam0.fx == calib.cam0.fx
    imu = tmp_path / "imu.yaml"
    allan.write_imu_yaml(calib.imu, imu)
    assert "gyroscope_noise_density" in imu.read_text()
    save_calibration(calib, "/dev/null")  # a device: written into, not replaced
