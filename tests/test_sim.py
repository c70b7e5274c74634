"""Synthetic flight generator: exact IMU, render/projection consistency, dataset files, CLI."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from vio import VioError
from vio.app.cli import main
from vio.geometry import GRAVITY_M_S2, make_T, so3_exp, so3_log
from vio.io.euroc import EurocDataset
from vio.sim import default_calibration
from vio.sim.generate import T0_NS, SimConfig, simulate
from vio.sim.imu import ImuModel, synthesize
from vio.sim.motion import FLIGHT_BOX_HI, FLIGHT_BOX_LO, PROFILES, make_profile
from vio.sim.observe import observe, project_visible
from vio.sim.render import CameraRenderer
from vio.sim.scene import default_scene

# small images and coarse textures keep these tests fast; geometry does not depend on either
TINY = dict(width=188, height=120, texels_per_m=40.0)


@pytest.fixture(scope="module")
def scene():
    return default_scene(seed=3, ppm=60.0)


@pytest.fixture(scope="module")
def calib():
    return default_calibration(width=376, height=240)


def _integrate(motion, rate_hz: float, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Trapezoidal strapdown integration of the exact IMU from the true initial state."""
    t = np.arange(int(seconds * rate_hz) + 1) / rate_hz
    imu = synthesize(motion, t, ImuModel(noise=None), np.random.default_rng(0))
    R, v, p = motion.rotation(t[:1])[0], motion.velocity(t[:1])[0], motion.position(t[:1])[0]
    g, dt = np.array([0.0, 0.0, GRAVITY_M_S2]), 1.0 / rate_hz
    for i in range(len(t) - 1):
        R_next = R @ so3_exp(0.5 * (imu.gyro[i] + imu.gyro[i + 1]) * dt)
        v_next = v + 0.5 * (R @ imu.accel[i] + R_next @ imu.accel[i + 1]) * dt - g * dt
        p = p + 0.5 * (v + v_next) * dt
        v, R = v_next, R_next
    return p - motion.position(t[-1:])[0], so3_log(R.T @ motion.rotation(t[-1:])[0])


@pytest.mark.parametrize("profile", PROFILES)
def test_integrating_exact_imu_reproduces_truth(profile):
    motion = make_profile(profile, 6.0, seed=1, still_s=0.5)
    dp, dr = _integrate(motion, 200.0, 4.0)
    assert np.linalg.norm(dp) < 1e-3 and np.linalg.norm(dr) < 1e-4
    dp_fine, _ = _integrate(motion, 800.0, 4.0)
    assert np.linalg.norm(dp_fine) < np.linalg.norm(dp) / 4  # second-order scheme converges: signal exact


def test_derivatives_match_finite_differences():
    m = make_profile("aggressive", 10.0, seed=4, still_s=1.0)
    t, h = np.linspace(0.5, 9.5, 37), 1e-5
    assert np.allclose(m.velocity(t), (m.position(t + h) - m.position(t - h)) / (2 * h), atol=1e-6)
    assert np.allclose(m.acceleration(t), (m.velocity(t + h) - m.velocity(t - h)) / (2 * h), atol=1e-5)
    R0, R1 = m.rotation(t - h), m.rotation(t + h)
    w_fd = np.array([so3_log(a.T @ b) for a, b in zip(R0, R1)]) / (2 * h)
    assert np.allclose(m.angular_velocity_body(t), w_fd, atol=1e-6)


def test_still_start_then_moving():
    m = make_profile("survey", 20.0, seed=2, still_s=2.0)
    t = np.linspace(0, 2.0, 41)
    assert np.abs(m.velocity(t)).max() == 0 and np.abs(m.angular_velocity_body(t)).max() == 0
    f = m.specific_force_body(t)
    assert np.allclose(np.linalg.norm(f, axis=1), GRAVITY_M_S2)
    assert np.linalg.norm(m.velocity(np.array([8.0]))) > 0.1


@pytest.mark.parametrize("profile", PROFILES)
def test_profiles_fly_in_the_room_at_the_advertised_pace(profile, calib, scene):
    speeds, yaw_rates = [], []
    for seed in range(4):
        m = make_profile(profile, 60.0, seed=seed)
        lo, hi = m.position_bounds()
        assert np.all(lo >= FLIGHT_BOX_LO) and np.all(hi <= FLIGHT_BOX_HI)
        t = np.linspace(0, 60, 1201)
        T = m.pose(t)
        for cam in (calib.cam0, calib.cam1):
            p_cam = (T @ cam.T_body_cam)[:, :3, 3]
            room_lo, room_hi = scene.lo[0], scene.hi[0]
            assert np.all(p_cam - room_lo >= 1.0) and np.all(room_hi - p_cam >= 1.0)
            assert scene.contains(p_cam, margin=0.8).all()
        speeds.append(np.linalg.norm(m.velocity(t), axis=1).max())
        yaw_rates.append(np.abs(m.yaw_rate(t)).max())
    limits = {"hover": (0.0, 0.3, 0.0, 0.2), "survey": (0.35, 0.8, 0.1, 0.5), "aggressive": (1.0, 2.5, 1.5, 2.3),
              "mapping": (0.35, 0.8, 0.25, 0.45), "laps": (0.45, 0.8, 0.2, 0.6), "out-and-back": (0.4, 0.8, 0.25, 0.6)}
    v_lo, v_hi, w_lo, w_hi = limits[profile]
    assert v_lo <= min(speeds) and max(speeds) <= v_hi
    assert w_lo <= min(yaw_rates) and max(yaw_rates) <= w_hi


@pytest.mark.parametrize("model", ["radtan", "equidistant"])
def test_rendered_depth_reprojects_onto_its_pixel(model, scene):
    calib = default_calibration(model, width=376, height=240)
    r = CameraRenderer(calib.cam0, scene)
    T_wc = make_profile("aggressive", 20.0, seed=5).pose(np.array([9.0]))[0] @ calib.cam0.T_body_cam
    img, depth, _ = r.render(T_wc)
    assert img.shape == (240, 376) and np.isfinite(depth).all() and depth.min() > 0.5
    rng = np.random.default_rng(0)
    u, v = rng.integers(0, 376, 200), rng.integers(0, 240, 200)
    p_cam = depth[v, u, None] * np.stack([r.x[v, u], r.y[v, u], np.ones(200)], axis=1)
    assert np.abs(calib.cam0.project(p_cam) - np.stack([u, v], axis=1)).max() < 1e-3


def test_scene_points_are_drawn_where_the_calibration_projects_them(calib, scene):
    """Landmarks sampled on the surfaces, projected with the calibration, meet the rendered depth map."""
    r = CameraRenderer(calib.cam0, scene)
    m = make_profile("survey", 30.0, seed=6)
    checked = 0
    for t in (3.0, 11.0, 23.0):
        T_wc = m.pose(np.array([t]))[0] @ calib.cam0.T_body_cam
        _, depth, _ = r.render(T_wc)
        pts = scene.sample_points(3000, np.random.default_rng(int(t)))
        uv, vis, p_cam = project_visible(scene, calib.cam0, T_wc, pts)
        px = np.round(uv[vis]).astype(int)
        rendered = depth[px[:, 1], px[:, 0]]
        rel = np.abs(rendered - p_cam[vis, 2]) / p_cam[vis, 2]
        assert np.median(rel) < 0.005 and np.mean(rel < 0.03) > 0.9  # misses: points on an edge pixel
        checked += int(vis.sum())
    assert checked > 300


def test_stereo_images_agree_on_scene_points(calib, scene):
    """The same landmark has the same brightness in both (noise-free) images: extrinsics and intrinsics
    used for rendering are the calibration's."""
    m = make_profile("survey", 30.0, seed=7)
    T_wb = m.pose(np.array([12.0]))[0]
    imgs, uvs, vis = [], [], np.ones(4000, bool)
    pts = scene.sample_points(4000, np.random.default_rng(1))
    for cam in (calib.cam0, calib.cam1):
        T_wc = T_wb @ cam.T_body_cam
        img, _, _ = CameraRenderer(cam, scene).render(T_wc)
        uv, v, _ = project_visible(scene, cam, T_wc, pts)
        imgs.append(img)
        uvs.append(uv)
        vis &= v & (uv[:, 0] > 2) & (uv[:, 0] < cam.width - 3) & (uv[:, 1] > 2) & (uv[:, 1] < cam.height - 3)
    assert vis.sum() > 200

    def sample(img, uv):
        m = uv[vis].astype(np.float32).reshape(-1, 1, 2)
        return cv2.remap(img, m[..., 0], m[..., 1], cv2.INTER_LINEAR)[:, 0]

    a, b = sample(imgs[0], uvs[0]), sample(imgs[1], uvs[1])
    same = np.median(np.abs(a - b))
    shuffled = np.median(np.abs(a - np.roll(b, 7)))
    assert same < 1.5 and shuffled > 10 * same  # 1 px of extrinsic error gives ~4 grey levels


def test_observe_gives_consistent_stereo_features(calib, scene):
    m = make_profile("hover", 10.0, seed=8)
    T_wb = m.pose(np.array([5.0]))[0]
    pts = scene.sample_points(2000, np.random.default_rng(2))
    ff = observe(scene, calib, T_wb, pts, t_ns=123)
    assert ff.t_ns == 123 and len(ff.ids) > 100 and ff.n_stereo > 0.5 * len(ff.ids)
    s = np.isfinite(ff.depth_m)
    p0 = np.column_stack([(ff.uv0[s] - calib.cam0.K[:2, 2]) / [calib.cam0.fx, calib.cam0.fy], np.ones(s.sum())])
    p0 *= ff.depth_m[s, None]
    p1 = p0 @ calib.T_cam1_cam0[:3, :3].T + calib.T_cam1_cam0[:3, 3]
    uv1 = p1[:, :2] / p1[:, 2:] * [calib.cam1.fx, calib.cam1.fy] + calib.cam1.K[:2, 2]
    assert np.abs(uv1 - ff.uv1[s]).max() < 1e-6
    world = pts[ff.ids[s]]
    T_wc = T_wb @ calib.cam0.T_body_cam
    assert np.allclose(p0 @ T_wc[:3, :3].T + T_wc[:3, 3], world, atol=1e-9)


def test_dataset_reads_back_with_offset_drops_and_truth(tmp_path):
    cfg = SimConfig(profile="aggressive", duration_s=2.0, seed=3, variant="realistic", still_start_s=0.5,
                    time_offset_ms=5.0, drop_frames=0.4, **TINY)
    s = simulate(tmp_path / "d", cfg)
    ds = EurocDataset(tmp_path / "d")
    assert ds.calibration.time_offset_ns == 5_000_000
    assert s.frames == 41 and s.dropped_left + s.dropped_right > 0
    assert len(ds.cam0_t) == 41 - s.dropped_left and len(ds.cam1_t) == 41 - s.dropped_right
    assert len(ds.imu) == 401 and len(ds.groundtruth.trajectory) == 401
    # image stamps are shifted: t_imu = t_cam + offset lands exactly on the IMU grid
    assert np.isin(ds.cam0_t + ds.calibration.time_offset_ns, ds.imu.t_ns).all()
    assert ((ds.cam0_t - (T0_NS - 5_000_000)) % 50_000_000 == 0).all()
    gt = ds.groundtruth
    m = make_profile("aggressive", 2.0, seed=3, still_s=0.5)
    t = (gt.trajectory.t_ns - T0_NS) * 1e-9
    assert np.abs(gt.trajectory.p - m.position(t)).max() < 1e-9
    assert np.abs(gt.v_world - m.velocity(t)).max() < 1e-9
    # the IMU minus the true biases is the exact signal plus noise and vibration of the configured size
    resid = ds.imu.gyro - gt.gyro_bias - m.angular_velocity_body(t)
    assert 0.001 < resid.std() < 0.05
    kinds = [type(e).__name__ for e in ds.events()]
    assert kinds.count("StereoFrame") == len(ds.cam0_t) and kinds.count("ImuSample") == 401
    frame = next(ds.frames())
    assert frame.left.dtype == np.uint8 and frame.left.shape == (120, 188)


def test_same_seed_same_bytes_other_seed_differs(tmp_path):
    cfg = SimConfig(duration_s=0.3, variant="hard", **TINY)
    for name, c in (("a", cfg), ("b", cfg), ("c", dataclasses.replace(cfg, seed=1))):
        simulate(tmp_path / name, c)

    def content(name):
        mav0 = tmp_path / name / "mav0"
        return {p.relative_to(mav0).as_posix(): p.read_bytes() for p in sorted(mav0.rglob("*")) if p.is_file()}

    assert content("a") == content("b")
    assert content("a") != content("c")


def test_refuses_to_overwrite_without_flag(tmp_path):
    cfg = SimConfig(duration_s=0.2, variant="clean", **TINY)
    simulate(tmp_path / "d", cfg)
    with pytest.raises(VioError, match="overwrite"):
        simulate(tmp_path / "d", cfg)
    simulate(tmp_path / "d", dataclasses.replace(cfg, duration_s=0.1), overwrite=True)
    assert len(list((tmp_path / "d" / "mav0" / "cam0" / "data").iterdir())) == 3
    # a real recording (no simulation.yaml beside its mav0/): --overwrite replaced it (a QA sweep); never
    (tmp_path / "d" / "simulation.yaml").unlink()
    with pytest.raises(VioError, match="not a simulated flight"):
        simulate(tmp_path / "d", cfg, overwrite=True)
    assert len(list((tmp_path / "d" / "mav0" / "cam0" / "data").iterdir())) == 3


def test_bad_config_values_are_named():
    with pytest.raises(VioError, match="drop_frames"):
        SimConfig(drop_frames=1.5).resolved()
    with pytest.raises(VioError, match="variant"):
        SimConfig(variant="nice").resolved()


def test_imu_noise_has_the_configured_density():
    m = make_profile("hover", 30.0, seed=0, still_s=30.0)
    t = np.arange(6000) / 200.0
    calib = default_calibration()
    imu = synthesize(m, t, ImuModel(noise=calib.imu), np.random.default_rng(0))
    sig = calib.imu.discrete_sigmas()
    assert abs(np.std(imu.gyro - imu.gyro_bias, axis=0).mean() / sig["gyro"] - 1) < 0.05
    vib = synthesize(m, t, ImuModel(noise=None, vibration_m_s2=0.5), np.random.default_rng(0))
    assert 0.2 < np.std(vib.accel[:, 2]) < 1.0


def test_cli_writes_dataset_and_reports(tmp_path, capsys):
    out = tmp_path / "cli"
    rc = main(["simulate", str(out), "--duration", "0.5", "--size", "94x60", "--profile", "hover",
               "--variant", "clean", "--no-progress", "--time-offset-ms", "-2"])
    assert rc == 0
    assert "11 stereo frames" in capsys.readouterr().out
    assert EurocDataset(out).calibration.time_offset_ns == -2_000_000
    assert main(["simulate", str(out), "--duration", "0.5", "--size", "94x60", "--no-progress"]) == 1
    assert "overwrite" in capsys.readouterr().err
    assert main(["simulate", str(tmp_path / "x"), "--size", "big"]) == 2  # an option's value: a usage error
    assert "--size" in capsys.readouterr().err


def test_calib_error_perturbs_only_the_written_calibration(tmp_path):
    """The dataset states a calibration off by the typical Kalibr error; the images are those of the truth,
    which is kept beside the dataset."""
    from vio.calibration import load_calibration

    cfg = SimConfig(duration_s=0.2, variant="clean", seed=2, **TINY)
    simulate(tmp_path / "exact", cfg)
    simulate(tmp_path / "wrong", dataclasses.replace(cfg, calib_error=1.0))
    stated, truth = EurocDataset(tmp_path / "wrong").calibration, load_calibration(tmp_path / "wrong" /
                                                                                    "calibration_truth.yaml")
    exact = EurocDataset(tmp_path / "exact").calibration
    assert not (tmp_path / "exact" / "calibration_truth.yaml").exists()
    for s, t, e in ((stated.cam0, truth.cam0, exact.cam0), (stated.cam1, truth.cam1, exact.cam1)):
        np.testing.assert_allclose(t.T_body_cam, e.T_body_cam, atol=1e-12)
        D = s.T_body_cam @ np.linalg.inv(t.T_body_cam)  # the rig's error, in the body frame
        assert np.rad2deg(np.linalg.norm(so3_log(D[:3, :3]))) == pytest.approx(0.1, abs=1e-6)
        assert np.linalg.norm(D[:3, 3]) == pytest.approx(0.002, abs=1e-9)
        # 0.5 px at full size; TINY images are a quarter size but the error is stated in their pixels
        np.testing.assert_allclose(np.abs(np.subtract([s.fx, s.fy, s.cx, s.cy], [t.fx, t.fy, t.cx, t.cy])), 0.5,
                                   atol=1e-6)
    np.testing.assert_allclose(stated.T_cam1_cam0, truth.T_cam1_cam0, atol=1e-12)  # a rig error: stereo kept
    for cam in ("cam0", "cam1"):
        a = sorted((tmp_path / "exact" / "mav0" / cam / "data").iterdir())
        b = sorted((tmp_path / "wrong" / "mav0" / cam / "data").iterdir())
        assert [p.read_bytes() for p in a] == [p.read_bytes() for p in b]


def test_shelves_scene_repeats_the_same_view_every_2_4_m(calib):
    """The aliasing scene: two cameras 2.4 m apart along the shelves see the same image (identical shelf units,
    walls repeating alike), so only geometry and odometry can tell the places apart; every profile flies clear
    of the shelves."""
    from vio.sim.render import CameraRenderer
    from vio.sim.scene import shelves_scene

    scene = shelves_scene(seed=3, ppm=100.0)
    for profile in PROFILES:
        T = make_profile(profile, 60.0, seed=2).pose(np.linspace(0, 60, 601))
        assert scene.contains((T @ calib.cam0.T_body_cam)[:, :3, 3], margin=0.8).all()
    r = CameraRenderer(calib.cam0, scene)
    R = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # looking along +y at the shelves, x to the right
    a, b, c = (r.render(make_T(R, [x, 0.5, 1.8]))[0].astype(float) for x in (-1.2, 1.2, -0.5))
    assert np.mean(np.abs(a - b)) < 3.0  # 2.4 m apart: the same view
    assert np.mean(np.abs(a - c)) > 10.0  # 0.7 m apart: a different one


def test_simulate_refuses_aliasing_on_scenes_that_are_not_the_room(tmp_path, capsys):
    """An option's mistake: exit 2 before any work (it was exit 1 once the output folder was made)."""
    for scene in ("shelves", "hall"):
        assert main(["simulate", str(tmp_path / scene), "--scene", scene, "--aliasing", "1.5", "--duration", "1"]) == 2
        assert "--aliasing is for the room" in capsys.readouterr().err
        assert not (tmp_path / scene).exists()


def test_hall_is_large_dim_and_far(calib):
    """The hall keeps every profile's cameras clear of walls and pillars; what the cameras see is mostly
    beyond 5 m, and darker than the room."""
    from vio.sim.scene import hall_scene

    hall, room = hall_scene(seed=1, ppm=30.0), default_scene(seed=1, ppm=30.0)
    assert np.allclose(hall.hi[0] - hall.lo[0], (25.0, 20.0, 8.0))
    depths, means = [], {"hall": [], "room": []}
    for profile in PROFILES:
        m = make_profile(profile, 60.0, seed=2)
        T = m.pose(np.linspace(0, 60, 301))
        for cam in (calib.cam0, calib.cam1):
            assert hall.contains((T @ cam.T_body_cam)[:, :3, 3], margin=1.0).all()
        for name, scene in (("hall", hall), ("room", room)):
            img, depth, _ = CameraRenderer(calib.cam0, scene).render(T[150] @ calib.cam0.T_body_cam)
            means[name].append(img.mean())
            if name == "hall":
                depths.append(np.median(depth))
    assert min(depths) > 5.0
    assert np.mean(means["hall"]) < 0.6 * np.mean(means["room"])


def test_right_camera_dropouts_remove_right_images_only(tmp_path):
    cfg = SimConfig(duration_s=2.0, variant="clean", still_start_s=0.5, right_dropouts=((0.5, 0.5), (1.5, 0.2)),
                    **TINY)
    s = simulate(tmp_path / "d", cfg)
    ds = EurocDataset(tmp_path / "d")
    assert s.dropped_right == 14 and s.dropped_left == 0  # [0.5, 1.0) and [1.5, 1.7) at 20 Hz
    t = (ds.cam1_t - T0_NS) * 1e-9
    assert len(ds.cam0_t) == 41 and len(ds.cam1_t) == 41 - 14
    assert not ((t >= 0.5 - 1e-9) & (t < 1.0 - 1e-9)).any() and not ((t >= 1.5 - 1e-9) & (t < 1.7 - 1e-9)).any()
    with pytest.raises(VioError, match="right dropout"):
        SimConfig(right_dropouts=((1.0, 0.0),)).resolved()


def test_drifting_time_offset_is_stamped_and_recorded(tmp_path):
    cfg = SimConfig(duration_s=2.0, variant="clean", still_start_s=0.5, time_offset_ms=1.0,
                    time_offset_drift_ms=5.0, time_offset_period_s=2.0, **TINY)
    simulate(tmp_path / "d", cfg)
    ds = EurocDataset(tmp_path / "d")
    assert ds.calibration.time_offset_ns == 1_000_000  # the calibration states the mean
    truth = np.loadtxt(tmp_path / "d" / "time_offset_truth.csv", delimiter=",", dtype=np.int64)
    np.testing.assert_array_equal(truth[:, 0], ds.cam0_t)
    true_t = np.arange(41) * 0.05
    np.testing.assert_allclose(truth[:, 1], 1e6 + 5e6 * np.sin(2 * np.pi * true_t / 2.0), atol=1)
    assert np.isin(ds.cam0_t + truth[:, 1], ds.imu.t_ns).all()  # t_cam + true offset: the exposure instant
    assert truth[:, 1].max() - truth[:, 1].min() > 9e6


def test_stamp_jitter_delays_the_stamps_and_records_the_truth(tmp_path, capsys):
    """--stamp-jitter-ms: every frame stamped late by its own delay (mean taken off), the images and IMU those of
    the same flight without it; the true offset of each frame in time_offset_truth.csv."""
    cfg = SimConfig(duration_s=2.0, variant="clean", still_start_s=0.5, stamp_jitter_ms=3.0, **TINY)
    simulate(tmp_path / "j", cfg)
    simulate(tmp_path / "r", dataclasses.replace(cfg, stamp_jitter_ms=0.0))
    jit, ref = EurocDataset(tmp_path / "j"), EurocDataset(tmp_path / "r")
    assert jit.calibration.time_offset_ns == 0 and np.array_equal(jit.imu.t_ns, ref.imu.t_ns)
    moved = jit.cam0_t - ref.cam0_t  # later stamp: later by the delay beyond the mean
    truth = np.loadtxt(tmp_path / "j" / "time_offset_truth.csv", delimiter=",", dtype=np.int64)
    np.testing.assert_array_equal(truth[:, 0], jit.cam0_t)
    np.testing.assert_array_equal(truth[:, 1], -moved)
    assert np.all(np.diff(jit.cam0_t) > 0) and 1.5e6 < np.std(moved) < 4.5e6 and abs(np.mean(moved)) < 1e6
    assert moved.min() >= -3e6 and moved.max() <= 25e6 - 3e6  # exponential delays capped at half a period
    assert np.array_equal(cv2.imread(str(jit.cam0_files[10]), cv2.IMREAD_UNCHANGED),
                          cv2.imread(str(ref.cam0_files[10]), cv2.IMREAD_UNCHANGED))
    dataclasses.replace(cfg, stamp_jitter_ms=10.0).resolved()  # a fifth of the period: allowed
    with pytest.raises(VioError, match="stamp_jitter_ms = 10.5 is over a fifth of the frame period"):
        dataclasses.replace(cfg, stamp_jitter_ms=10.5).resolved()
    assert main(["simulate", str(tmp_path / "x"), "--stamp-jitter-ms", "-1"]) == 2  # usage, named by the option
    assert "--stamp-jitter-ms -1.0 is outside [0, 20]" in capsys.readouterr().err


def test_stamp_stalls_deliver_the_frames_due_in_a_stall_together_at_its_end(tmp_path, capsys):
    """--stamp-stalls EVERY_S:MS: the camera's transfer stalls for MS now and then (a USB camera); the frames due in a
    stall are stamped together at its end, 1 ms apart and in order, the others as before; the truth file says each
    frame's true offset."""
    cfg = SimConfig(duration_s=6.0, variant="clean", still_start_s=0.5, stamp_stall_every_s=1.0, stamp_stall_ms=120.0,
                    **TINY)
    simulate(tmp_path / "s", cfg)
    simulate(tmp_path / "r", dataclasses.replace(cfg, stamp_stall_every_s=0.0, stamp_stall_ms=0.0))
    st, ref = EurocDataset(tmp_path / "s"), EurocDataset(tmp_path / "r")
    late = st.cam0_t - ref.cam0_t
    truth = np.loadtxt(tmp_path / "s" / "time_offset_truth.csv", delimiter=",", dtype=np.int64)
    np.testing.assert_array_equal(truth[:, 0], st.cam0_t)
    np.testing.assert_array_equal(truth[:, 1], -late)
    steps = np.diff(st.cam0_t)
    assert np.all(steps >= 1_000_000) and np.sum(steps == 1_000_000) >= 2  # bursts, 1 ms apart, in order
    assert late.max() > 60e6 and np.all(late >= 0) and np.sum(late > 0) < 0.3 * len(late)  # most frames on time
    assert main(["simulate", str(tmp_path / "x"), "--stamp-stalls", "often"]) == 2
    assert "--stamp-stalls: expected EVERY_S:MS" in capsys.readouterr().err
    for bad in ({"stamp_stall_ms": 0.0}, {"stamp_stall_every_s": float("inf")}, {"stamp_stall_every_s": 0.2}):
        with pytest.raises(VioError, match="stamp stalls need both"):
            dataclasses.replace(cfg, **bad).resolved()


def test_cli_variant_options(tmp_path, capsys):
    out = tmp_path / "v"
    assert main(["simulate", str(out), "--duration", "0.5", "--size", "94x60", "--variant", "clean", "--no-progress",
                 "--scene", "hall", "--calib-error", "--right-dropout", "0.1:0.2", "--time-offset-drift-ms", "2"]) == 0
    assert "dropped left/right images 0/4" in capsys.readouterr().out
    assert (out / "calibration_truth.yaml").exists() and (out / "time_offset_truth.csv").exists()
    assert main(["simulate", str(tmp_path / "x"), "--right-dropout", "soon"]) == 2  # usage
    assert "--right-dropout" in capsys.readouterr().err


def test_oak_imu_mount_is_the_same_flight_in_the_imus_axes(tmp_path):
    """--imu-mount oak: the same images and samples, read in the axes of an IMU whose x axis is up; the
    cameras see from the same places (T_world_imu T_imu_cam unchanged)."""
    from vio.sim import IMU_MOUNTS

    cfg = SimConfig(profile="aggressive", duration_s=3.0, seed=4, **TINY)
    simulate(tmp_path / "flu", cfg)
    simulate(tmp_path / "oak", dataclasses.replace(cfg, imu_mount="oak"))
    a, b = EurocDataset(tmp_path / "flu"), EurocDataset(tmp_path / "oak")
    R = IMU_MOUNTS["oak"]
    assert np.allclose(R[:, 0], [0, 0, 1])  # IMU x up in the vehicle's FLU frame
    assert np.array_equal(a.frame(40).left, b.frame(40).left)
    assert np.allclose(b.imu.gyro, a.imu.gyro @ R) and np.allclose(b.imu.accel, a.imu.accel @ R)
    Ta, Tb = a.groundtruth.trajectory.poses(), b.groundtruth.trajectory.poses()
    assert np.allclose(Ta[:, :3, 3], Tb[:, :3, 3]) and np.allclose(Tb[:, :3, :3], Ta[:, :3, :3] @ R)
    for ca, cb in ((a.calibration.cam0, b.calibration.cam0), (a.calibration.cam1, b.calibration.cam1)):
        assert np.allclose(Ta[100] @ ca.T_body_cam, Tb[100] @ cb.T_body_cam)
    with pytest.raises(VioError, match="IMU mount"):
        SimConfig(imu_mount="sideways").resolved()


def test_stereo_error_states_cam1_principal_point_off_and_nothing_else(tmp_path):
    """--stereo-error: only cam1's cx in the written calibration moves (a disparity bias), the images are the
    truth's, the truth is kept beside the dataset; an error beyond 20 px is refused by name."""
    from vio import VioError
    from vio.calibration import load_calibration

    cfg = SimConfig(duration_s=0.2, variant="clean", seed=2, stereo_error_px=0.5, **TINY)
    simulate(tmp_path / "s", cfg)
    stated = EurocDataset(tmp_path / "s").calibration
    truth = load_calibration(tmp_path / "s" / "calibration_truth.yaml")
    assert stated.cam1.cx - truth.cam1.cx == pytest.approx(0.5, abs=1e-6)
    for k in ("fx", "fy", "cy"):
        assert getattr(stated.cam1, k) == pytest.approx(getattr(truth.cam1, k), abs=1e-9)
        assert getattr(stated.cam0, k) == pytest.approx(getattr(truth.cam0, k), abs=1e-9)
    assert stated.cam0.cx == pytest.approx(truth.cam0.cx, abs=1e-9)
    np.testing.assert_allclose(stated.cam1.T_body_cam, truth.cam1.T_body_cam, atol=1e-12)
    with pytest.raises(VioError, match="stereo_error_px"):
        simulate(tmp_path / "t", dataclasses.replace(cfg, stereo_error_px=25.0))


def test_simulate_into_a_file_or_through_one_says_so_before_the_flight_is_built(tmp_path, capsys):
    """`vio simulate OUT` with a file at OUT said 'OUT: File exists' (the folder could not be made), after the flight
    had been built; through a file, 'Not a directory'."""
    from vio.app.cli import main

    (tmp_path / "afile").write_text("notes\n")
    for out in (tmp_path / "afile", tmp_path / "afile" / "sub"):
        capsys.readouterr()
        assert main(["simulate", str(out), "--duration", "1", "--no-progress"]) == 1
        err = capsys.readouterr().err
        assert f"vio simulate: error: {out}: cannot write the dataset: {tmp_path / 'afile'} is a file, not a folder" \
            in err, err
    assert (tmp_path / "afile").read_text() == "notes\n"


def test_drop_frames_1_takes_one_image_or_both_from_every_frame(tmp_path, capsys):
    """`--drop-frames 1` dropped 15 left and 13 right images of 21 frames, read as 'not all' by a reviewer: the option
    drops, with probability P, the left, the right or both images of a frame (one of the three, equally likely), so
    at 1 every frame loses one image or both. --help says it in those words now."""
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "1 takes one image or both from every frame" in text, text
    assert main(["-q", "simulate", str(tmp_path / "d"), "--duration", "1", "--size", "188x120", "--drop-frames", "1",
                 "--no-progress"]) == 0
    rows = [{ln.split(",")[0] for ln in (tmp_path / "d" / "mav0" / c / "data.csv").read_text().splitlines()[1:]}
            for c in ("cam0", "cam1")]
    assert not rows[0] & rows[1] and rows[0] and rows[1]  # no frame kept both images; some kept one
