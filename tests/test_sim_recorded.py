"""Flights rendered along a recording's ground truth with its real IMU (`vio simulate --imu-from`)."""

from __future__ import annotations

import numpy as np
import pytest

from vio.app.cli import main
from vio.geometry import make_T
from vio.io.euroc import EurocDataset
from vio.sim import _R_FLU_EUROC, default_calibration
from vio.sim.generate import SimConfig, simulate

TINY = dict(width=188, height=120, texels_per_m=40.0)


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A small recording in EuRoC layout (a simulated one: IMU, ground truth with velocities and biases)."""
    out = tmp_path_factory.mktemp("rec") / "source"
    simulate(out, SimConfig(profile="survey", duration_s=4.0, seed=5, variant="realistic", **TINY))
    return out


def test_recorded_flight_keeps_the_recordings_imu_and_truth(source, tmp_path):
    simulate(tmp_path / "r", SimConfig(imu_from=str(source), recorded_start_s=1.0, duration_s=2.0, variant="clean",
                                       **TINY))
    src, rec = EurocDataset(source), EurocDataset(tmp_path / "r")
    # the IMU is the recording's, sample for sample, over the flight's two seconds and 50 ms either side
    t0 = src.groundtruth.trajectory.t_ns[0] + 1_000_000_000
    sel = (src.imu.t_ns >= t0 - 50_000_000) & (src.imu.t_ns <= t0 + 2_050_000_000)
    assert len(rec.imu) == sel.sum() == 421
    assert rec.imu.t_ns[0] < rec.cam0_t[0] and rec.imu.t_ns[-1] > rec.cam0_t[-1]
    assert not rec.stats.notes, rec.stats.notes
    np.testing.assert_array_equal(rec.imu.gyro, src.imu.gyro[sel])
    np.testing.assert_array_equal(rec.imu.accel, src.imu.accel[sel])
    assert np.all(np.diff(rec.imu.t_ns) == np.diff(src.imu.t_ns[sel]))
    # the truth is the recording's moved as a rigid whole: relative motion, heights and biases unchanged
    g_src = src.groundtruth.trajectory.interpolate(src.imu.t_ns[sel])
    g_rec = rec.groundtruth.trajectory
    T_src, T_rec = g_src.poses(), g_rec.poses()
    rel = [np.linalg.inv(T_src[0]) @ T_src[k] for k in (200, 400)]
    rel_rec = [np.linalg.inv(T_rec[0]) @ T_rec[k] for k in (200, 400)]
    np.testing.assert_allclose(rel_rec, rel, atol=1e-6)
    np.testing.assert_allclose(g_rec.p[:, 2], g_src.p[:, 2], atol=1e-9)
    np.testing.assert_allclose(rec.groundtruth.gyro_bias, src.groundtruth.gyro_bias[sel], atol=1e-9)
    # 41 stereo frames, cameras mounted as EuRoC's rig on the recording's IMU frame
    assert len(rec.cam0_t) == len(rec.cam1_t) == 41
    flu = default_calibration(width=188, height=120).cam0.T_body_cam
    np.testing.assert_allclose(rec.calibration.cam0.T_body_cam, make_T(_R_FLU_EUROC.T, np.zeros(3)) @ flu, atol=1e-9)
    assert next(rec.frames()).left.std() > 5  # rendered texture, not a blank image


def test_recorded_flight_refuses_what_it_cannot_do(source, tmp_path, capsys):
    def run(*extra):
        rc = main(["simulate", str(tmp_path / "out"), "--size", "94x60", "--no-progress", "--overwrite", *extra])
        return rc, capsys.readouterr().err

    rc, err = run("--imu-from", str(source), "--vibration", "1")
    assert rc == 2 and "--vibration" in err and "recording's" in err and "Traceback" not in err  # options: usage
    rc, err = run("--imu-from", str(source), "--recorded-start", "3.5")
    assert rc == 1 and "leaves less than 1 s" in err
    no_gt = tmp_path / "no_gt"
    (no_gt / "mav0" / "imu0").mkdir(parents=True)
    (no_gt / "mav0" / "imu0" / "data.csv").write_text((source / "mav0" / "imu0" / "data.csv").read_text())
    rc, err = run("--imu-from", str(no_gt))
    assert rc == 1 and "ground truth" in err
    # a path wider than the room cannot be placed in it
    wide = tmp_path / "wide"
    for sub in ("imu0", "state_groundtruth_estimate0"):
        (wide / "mav0" / sub).mkdir(parents=True)
    (wide / "mav0" / "imu0" / "data.csv").write_text((source / "mav0" / "imu0" / "data.csv").read_text())
    lines = (source / "mav0" / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines()
    stretched = [lines[0]] + [",".join([c[0], str(float(c[1]) + 15 * k / len(lines)), *c[2:]])
                              for k, c in enumerate(x.split(",") for x in lines[1:])]
    (wide / "mav0" / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(stretched) + "\n")
    rc, err = run("--imu-from", str(wide))
    assert rc == 1 and "does not fit in the room scene" in err


@pytest.fixture(scope="module")
def v102_flight(v102_path, tmp_path_factory):
    out = tmp_path_factory.mktemp("v102") / "v102"
    simulate(out, SimConfig(imu_from=str(v102_path), duration_s=20.0, width=376, height=240))
    return out


def test_real_imu_flight_is_tracked(v102_flight):
    """EuRoC V1_02's own IMU (vibration, biases, ~30-60x its datasheet's noise) under rendered images: the
    estimator tracks it and reads the IMU as shaking (adaptive noise engaged)."""
    from vio.app.replay import replay
    from vio.config import VioConfig
    from vio.evaluation import evaluate

    ds = EurocDataset(v102_flight)
    res = replay(ds, VioConfig(), progress=False)
    ev = evaluate(res.trajectory(), ds.groundtruth.trajectory)
    assert res.resets == 0
    assert ev.ate_se3.trans_m.rmse < 0.05, ev.ate_se3.trans_m.rmse  # 0.020 m measured, path 15 m
    assert res.extra["imu_white_scale"] is not None  # the pre-integration noise follows the real IMU


def test_reset_on_a_real_drones_mount_keeps_position_and_heading(v102_flight, tmp_path):
    """Both cameras dark for 2 s mid-flight on EuRoC's mount (IMU x axis up): the estimator resets and
    continues from where it was. The heading it carries over must be the vehicle's: Euler yaws, which the
    re-anchoring used to compare, are off by degrees on this mount (by 130 deg with an axis exactly up)."""
    from vio.consistency import pose_nees, replay_states
    from vio.geometry import yaw_between
    from vio.sim.faults import blackout, copy_dataset

    path = copy_dataset(v102_flight, tmp_path / "black")
    assert blackout(path, 10.0, 2.0) > 0
    r = replay_states(path)
    assert r.estimator.reset_counter >= 1
    gt = r.dataset.groundtruth.trajectory
    frames = r.frame_states
    nees = pose_nees(frames, gt.t_ns, gt.poses(), realign_on_reset=False)
    t_back = int(r.dataset.frame_t[0]) + int(12.5e9)
    before = [s for s in frames if s.t_ns < t_back - int(3e9)][-1]
    after = [s for s in frames if s.t_ns >= t_back][0]
    G = gt.interpolate(np.array([before.t_ns, after.t_ns])).poses()
    # heading change through the reset, estimate against truth
    turn_err = np.degrees(yaw_between(after.T_world_body[:3, :3] @ before.T_world_body[:3, :3].T,
                                      G[1][:3, :3] @ G[0][:3, :3].T))
    late = nees.t_ns > t_back
    print(f"heading error across the reset {turn_err:+.2f} deg, position error after it max "
          f"{nees.error_position_m[late].max():.3f} m, resets {r.estimator.reset_counter}")
    assert abs(turn_err) < 1.0
    assert nees.error_position_m[late].max() < 0.15


def test_a_recording_whose_imu_ends_early_is_refused(source, tmp_path, capsys):
    """A recording whose IMU stops before its ground truth ends (a gap in its stamps, an IMU log cut short) gave a
    dataset of 30 s of frames over 1.5 s of IMU, exit 0: the IMU was only checked for gaps inside the span it had."""
    cut = tmp_path / "cut"
    for sub in ("imu0", "state_groundtruth_estimate0"):
        (cut / "mav0" / sub).mkdir(parents=True)
    lines = (source / "mav0" / "imu0" / "data.csv").read_text().splitlines()
    (cut / "mav0" / "imu0" / "data.csv").write_text("\n".join(lines[: len(lines) // 2]) + "\n")
    gt = source / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    (cut / "mav0" / "state_groundtruth_estimate0" / "data.csv").write_text(gt.read_text())
    rc = main(["simulate", str(tmp_path / "out"), "--size", "94x60", "--no-progress", "--imu-from", str(cut)])
    err = capsys.readouterr().err
    assert rc == 1 and "the IMU does not cover 0-4 s of the ground truth" in err and "from 0.00 s to 2.00 s" in err, err


def test_a_gap_in_the_recordings_ground_truth_is_refused(source, tmp_path, capsys):
    """Ground truth with a 0.5 s hole (a motion-capture dropout) was interpolated in a straight line across it and the
    images rendered along that line, while the IMU measured the real motion: a flight whose images and IMU disagree,
    exit 0."""
    holed = tmp_path / "holed"
    for sub in ("imu0", "state_groundtruth_estimate0"):
        (holed / "mav0" / sub).mkdir(parents=True)
    (holed / "mav0" / "imu0" / "data.csv").write_text((source / "mav0" / "imu0" / "data.csv").read_text())
    lines = (source / "mav0" / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines()
    t0 = int(lines[1].split(",")[0])
    kept = [ln for ln in lines[1:] if not 2.0e9 < int(ln.split(",")[0]) - t0 < 2.5e9]
    (holed / "mav0" / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join([lines[0], *kept]) + "\n")
    rc = main(["simulate", str(tmp_path / "out"), "--size", "94x60", "--no-progress", "--imu-from", str(holed)])
    err = capsys.readouterr().err
    assert rc == 1 and "the ground truth has a gap of 0.5" in err, err
