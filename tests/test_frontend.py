"""Stereo front end: geometry on synthetic scenes with exact truth, robustness to bad frames, real EuRoC data."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from vio.calibration import CameraCalibration, StereoCalibration
from vio.config import FrontendConfig, VioConfig
from vio.frontend import GyroPrior, StereoTracker, integrate_gyro
from vio.frontend.debug_view import TrackImageWriter
from vio.frontend.gyro import body_to_camera_rotation
from vio.frontend.ransac import temporal_inliers
from vio.frontend.runner import run_frontend
from vio.frontend.undistort import bearings, distort_px, undistort_px
from vio.geometry import inv_T, make_T, so3_exp
from vio.types import ImuSample, StereoFrame

W, H = 752, 480
RADTAN = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
EQUIDISTANT = (0.012, -0.006, 0.003, -0.0008)


def _calib(model: str = "radtan") -> StereoCalibration:
    """EuRoC-like head: cam1 11 cm to the right of cam0, turned by half a degree, different principal point."""
    dist = RADTAN if model == "radtan" else EQUIDISTANT
    T_body_cam0 = make_T(np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]), np.array([0.05, 0.0, 0.0]))
    T_cam0_cam1 = make_T(so3_exp([0.004, -0.008, 0.003]), np.array([0.11, 0.002, -0.001]))
    cam0 = CameraCalibration(458.0, 457.0, 367.0, 248.0, W, H, model, dist, T_body_cam0)
    cam1 = CameraCalibration(457.5, 456.0, 380.0, 255.0, W, H, model, dist, T_body_cam0 @ T_cam0_cam1)
    return StereoCalibration(cam0, cam1)


def _texture(seed: int = 0, size: int = 1536) -> np.ndarray:
    """Multi-scale noise with rectangles: corners at every scale, no repetition."""
    rng = np.random.default_rng(seed)
    img = np.zeros((size, size), np.float32)
    for s in (3, 9, 27):
        n = cv2.resize(rng.standard_normal((size // s, size // s)).astype(np.float32), (size, size),
                       interpolation=cv2.INTER_CUBIC)
        img += n * s ** 0.5
    img = (img - img.mean()) / img.std() * 35 + 128
    for _ in range(400):
        x, y = rng.integers(0, size, 2)
        w, h = rng.integers(8, 60, 2)
        cv2.rectangle(img, (int(x), int(y)), (int(x + w), int(y + h)), float(rng.integers(20, 235)), -1)
    return np.clip(cv2.GaussianBlur(img, (0, 0), 1.0), 0, 255).astype(np.uint8)


class PlaneScene:
    """Textured plane n . p = d (in the world frame) rendered through the real lens model by ray casting."""

    half_m = 6.0  # the texture covers [-half_m, half_m]^2 of the plane's (x, y)

    def __init__(self, d: float = 3.0, tilt: float = 0.25) -> None:
        self.n = np.array([0.0, -tilt, 1.0])
        self.d = d
        self.tex = _texture()
        ys, xs = np.mgrid[0:H, 0:W]
        self._pix = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
        self._rays: dict[int, np.ndarray] = {}

    def render(self, cam: CameraCalibration, T_world_cam: np.ndarray) -> np.ndarray:
        key = id(cam)
        if key not in self._rays:
            self._rays[key] = bearings(cam, undistort_px(cam, self._pix))
        rays = self._rays[key] @ T_world_cam[:3, :3].T
        o = T_world_cam[:3, 3]
        s = (self.d - self.n @ o) / (rays @ self.n)
        p = o + rays * s[:, None]
        scale = self.tex.shape[0] / (2 * self.half_m)
        mx = ((p[:, 0] + self.half_m) * scale).reshape(H, W).astype(np.float32)
        my = ((p[:, 1] + self.half_m) * scale).reshape(H, W).astype(np.float32)
        return cv2.remap(self.tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)

    def stereo(self, calib: StereoCalibration, T_world_cam0: np.ndarray, t_ns: int) -> StereoFrame:
        T_cam0_cam1 = inv_T(calib.cam0.T_body_cam) @ calib.cam1.T_body_cam
        return StereoFrame(t_ns, self.render(calib.cam0, T_world_cam0),
                           self.render(calib.cam1, T_world_cam0 @ T_cam0_cam1))

    def depth(self, uv0: np.ndarray) -> np.ndarray:
        """True cam0 depth of undistorted cam0 pixels when cam0 is at the world origin."""
        x = np.column_stack([(uv0[:, 0] - 367.0) / 458.0, (uv0[:, 1] - 248.0) / 457.0, np.ones(len(uv0))])
        return self.d / (x @ self.n)


def _homography(Hm: np.ndarray, uv: np.ndarray) -> np.ndarray:
    x = np.column_stack([uv, np.ones(len(uv))]) @ Hm.T
    return x[:, :2] / x[:, 2:]


def _inside(uv: np.ndarray, margin: float) -> np.ndarray:
    return (uv[:, 0] > margin) & (uv[:, 0] < W - margin) & (uv[:, 1] > margin) & (uv[:, 1] < H - margin)


@pytest.fixture(scope="module")
def scene() -> PlaneScene:
    return PlaneScene()


@pytest.fixture(scope="module")
def calib() -> StereoCalibration:
    return _calib()


# ------------------------------------------------------------------------------------------------ geometry

@pytest.mark.parametrize("model", ["radtan", "equidistant"])
def test_undistortion_round_trip(model: str) -> None:
    cam = _calib(model).cam0
    rng = np.random.default_rng(1)
    uv = rng.uniform([5, 5], [W - 5, H - 5], (500, 2))
    und = undistort_px(cam, uv)
    assert np.abs(distort_px(cam, und) - uv).max() < 1e-3
    # the undistorted pixel really is K times the ray that the lens model projects onto uv
    assert np.abs(cam.project(bearings(cam, und)) - uv).max() < 1e-3
    # distortion is not negligible at the border (so the test would notice a missing undistortion)
    assert np.abs(und - uv).max() > (20 if model == "radtan" else 1)


def test_stereo_depth_on_known_plane(scene: PlaneScene, calib: StereoCalibration) -> None:
    ff = StereoTracker(calib).process(scene.stereo(calib, np.eye(4), 1_000))
    assert ff.tracking_ok, ff.reason
    ok = np.isfinite(ff.depth_m)
    assert ok.sum() >= 150, f"only {ok.sum()} of {len(ok)} features have stereo depth"
    rel = np.abs(ff.depth_m[ok] - scene.depth(ff.uv0[ok])) / scene.depth(ff.uv0[ok])
    assert np.median(rel) < 0.01
    assert np.percentile(rel, 95) < 0.03
    # uv1 is the undistorted cam1 pixel of the same 3D point
    p0 = bearings(calib.cam0, ff.uv0[ok]) * ff.depth_m[ok, None]
    T_1_0 = calib.T_cam1_cam0
    p1 = p0 @ T_1_0[:3, :3].T + T_1_0[:3, 3]
    uv1 = p1[:, :2] / p1[:, 2:] * [calib.cam1.fx, calib.cam1.fy] + [calib.cam1.cx, calib.cam1.cy]
    assert np.median(np.linalg.norm(uv1 - ff.uv1[ok], axis=1)) < 0.5


def test_frames_without_stereo_keep_tracks_and_search_new_ones_later(scene: PlaneScene,
                                                                    calib: StereoCalibration) -> None:
    """stereo=False (frames the estimator cannot use as keyframes) reports no stereo but keeps tracking; tracks
    born on such a frame are searched on the next stereo frame, old ones resume from their last depth."""
    trk = StereoTracker(calib, FrontendConfig(max_features=150))
    T = np.eye(4)
    ff0 = trk.process(scene.stereo(calib, T, 1_000))
    assert ff0.n_stereo >= 100
    trk.cfg = dataclasses.replace(trk.cfg, max_features=200)  # room for new tracks on the mono frame
    T[0, 3] = 0.02
    ff1 = trk.process(scene.stereo(calib, T, 2_000), stereo=False)
    assert ff1.tracking_ok and ff1.n_stereo == 0 and np.all(np.isnan(ff1.uv1))
    assert len(np.intersect1d(ff0.ids, ff1.ids)) >= 0.9 * len(ff0.ids)
    born = np.setdiff1d(ff1.ids, ff0.ids)
    assert len(born) >= 20
    T[0, 3] = 0.04
    ff2 = trk.process(scene.stereo(calib, T, 3_000))
    ok = np.isfinite(ff2.depth_m)
    assert np.isin(born, ff2.ids[ok]).mean() > 0.8  # new tracks were searched although no longer new
    rel = np.abs(ff2.depth_m[ok] - scene.depth(ff2.uv0[ok])) / ff2.depth_m[ok]
    assert ok.sum() >= 150 and np.median(rel) < 0.05


def test_imu_prediction_keeps_tracks_in_fast_yaw(scene: PlaneScene, calib: StereoCalibration) -> None:
    """12 deg of yaw between frames (about 100 px): KLT from the gyro-predicted start keeps the tracks."""
    R = so3_exp([0.0, np.radians(12.0), 0.0])  # about cam0's y axis (down): the image pans sideways
    f0 = scene.stereo(calib, np.eye(4), 1_000)
    f1 = scene.stereo(calib, make_T(R, np.zeros(3)), 50_001_000)
    K = calib.cam0.K
    results = {}
    for use_prior in (True, False):
        tr = StereoTracker(calib)
        a = tr.process(f0)
        b = tr.process(f1, R if use_prior else None)
        common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
        results[use_prior] = len(common)
        if use_prior:
            pred_all = _homography(K @ R.T @ np.linalg.inv(K), a.uv0)  # pure rotation: infinite homography
            n_in = int(np.sum(_inside(pred_all, 25)))
            assert len(common) >= 0.9 * n_in, f"kept {len(common)} of {n_in} trackable features"
            pred = pred_all[ia]
            err = np.linalg.norm(b.uv0[ib] - pred, axis=1)[_inside(pred, 10)]
            assert np.median(err) < 0.3
            assert np.percentile(err, 99) < 2.0
            assert b.parallax_px < 1.0  # pure rotation: no parallax once rotation-compensated
    assert results[False] < 0.5 * results[True], "the test motion is too easy to show the prediction"


def test_gyro_integration_to_camera_rotation() -> None:
    w = np.array([0.3, -1.2, 2.5])
    t = np.arange(0, 101) * 1_000_000  # 1 kHz over 100 ms
    gyro = np.tile(w, (len(t), 1))
    R_b = integrate_gyro(t, gyro, 10_000_000, 60_000_000)
    assert np.allclose(R_b, so3_exp(w * 0.05), atol=1e-9)
    calib = _calib()
    prior = GyroPrior(calib.cam0.T_body_cam)
    assert prior.rotation(10_000_000, 60_000_000) is None  # nothing buffered: no prior
    for ti, g in zip(t, gyro):
        prior.add(ImuSample(int(ti), g, np.zeros(3)))
    R_c = prior.rotation(10_000_000, 60_000_000)
    R_bc = calib.cam0.T_body_cam[:3, :3]
    assert np.allclose(R_c, so3_exp(R_bc.T @ w * 0.05), atol=1e-9)
    assert np.allclose(body_to_camera_rotation(R_b, calib.cam0.T_body_cam), R_c)


def test_ransac_flags_outliers() -> None:
    rng = np.random.default_rng(3)
    K = _calib().cam0.K
    p = rng.uniform([-3, -2, 2], [3, 2, 8], (200, 3))
    T = make_T(so3_exp([0.02, -0.05, 0.01]), np.array([0.3, 0.05, 0.1]))  # cam_cur <- cam_prev
    q = p @ T[:3, :3].T + T[:3, 3]
    uv_a = (p / p[:, 2:]) @ K.T
    uv_b = (q / q[:, 2:]) @ K.T
    uv_a, uv_b = uv_a[:, :2] + rng.normal(0, 0.2, (200, 2)), uv_b[:, :2] + rng.normal(0, 0.2, (200, 2))
    bad = rng.choice(200, 20, replace=False)
    uv_b[bad] += rng.uniform(4, 15, (20, 2)) * rng.choice([-1, 1], (20, 2))
    inl = temporal_inliers(uv_a, uv_b, 1.0)
    assert (~inl[bad]).sum() >= 18
    good = np.setdiff1d(np.arange(200), bad)
    assert inl[good].mean() > 0.95


def test_ransac_survives_usac_assertion() -> None:
    """16 matches (10-frame drift check, heavily blurred synthetic flight) on which OpenCV 5's USAC_FAST asserts
    (`!model.empty()`): the front end keeps the matches instead of raising."""
    m = np.array([[-32.0, 259.1, 294.12, 320.18], [107.42, 67.22, 397.88, 148.63], [-2.6, 63.62, 322.92, 159.02],
                  [115.64, -47.95, 410.81, 45.78], [394.1, 176.19, 755.0, 247.54], [232.67, 36.9, 515.58, 96.45],
                  [111.17, 121.89, 399.32, 198.82], [-70.33, 132.09, 283.2, 217.27], [-57.92, 257.19, 276.31, 317.03],
                  [117.44, 10.4, 408.69, 95.23], [174.56, -4.2, 459.0, 69.65], [384.2, 58.44, 730.27, 79.57],
                  [174.33, 359.42, 434.48, 465.9], [265.45, -14.03, 553.5, 32.38], [-50.68, 79.61, 295.69, 175.64],
                  [-34.65, 176.03, 298.88, 250.51]])
    inl = temporal_inliers(m[:, :2], m[:, 2:], 0.35)
    assert inl.shape == (16,) and inl.all()


# ------------------------------------------------------------------------------------------- bad frames

def test_bad_frames_are_reported_and_tracking_recovers(scene: PlaneScene, calib: StereoCalibration) -> None:
    frames = [scene.stereo(calib, make_T(so3_exp([0, 0.002 * i, 0]), [0.01 * i, 0, 0]), 1_000 + i * 50_000_000)
              for i in range(4)]
    tr = StereoTracker(calib)
    first = tr.process(frames[0])
    assert first.tracking_ok and first.n_stereo > 100
    t = frames[1].t_ns

    # out of order: reported, tracks kept (the next frame continues them)
    late = tr.process(dataclasses.replace(frames[0], t_ns=first.t_ns))
    assert not late.tracking_ok and "not after" in late.reason and len(late.ids) == 0
    cont = tr.process(frames[1])
    assert cont.tracking_ok and np.median(cont.track_len) == 2

    # missing right image: mono observations only, still tracking
    mono = tr.process(dataclasses.replace(frames[2], right=None))
    assert mono.tracking_ok and len(mono.ids) > 100 and mono.n_stereo == 0
    assert np.all(np.isnan(mono.uv1)) and "mono" in mono.reason

    bad_images = {
        "dark": np.full((H, W), 3, np.uint8),
        "saturated": np.full((H, W), 255, np.uint8),
        "blurred": cv2.GaussianBlur(frames[3].left, (0, 0), 12),
    }
    for i, (word, img) in enumerate(bad_images.items()):
        t += 10_000_000_000
        ff = tr.process(StereoFrame(t + i, img, frames[3].right))
        # a blurred image is caught by its gradient energy or, failing that, by finding no corners
        assert not ff.tracking_ok and (word in ff.reason or "features" in ff.reason), ff.reason
        assert len(ff.ids) == 0
        # the next good frame re-detects from scratch: new ids, all tracks new
        t += 1
        good = tr.process(dataclasses.replace(frames[3], t_ns=t + i))
        assert good.tracking_ok and len(good.ids) >= 150 and good.n_stereo >= 100
        assert np.all(good.track_len == 1) and good.ids.min() > first.ids.max()

    # a wrong image size is a bad frame with a clear reason, not an exception
    small = tr.process(StereoFrame(t + 100, frames[3].left[:200], frames[3].right))
    assert not small.tracking_ok and "calibration" in small.reason


def test_gain_change_keeps_tracks(scene: PlaneScene, calib: StereoCalibration) -> None:
    f0 = scene.stereo(calib, np.eye(4), 1_000)
    f1 = scene.stereo(calib, make_T(so3_exp([0, 0.01, 0]), [0.02, 0, 0]), 50_001_000)
    dim = StereoFrame(f1.t_ns, cv2.convertScaleAbs(f1.left, alpha=0.6), cv2.convertScaleAbs(f1.right, alpha=0.6))
    tr = StereoTracker(calib)
    a = tr.process(f0)
    b = tr.process(dim)
    assert b.tracking_ok
    assert np.count_nonzero(b.track_len > 1) >= 0.9 * len(a.ids)


def test_debug_view_writes_images(tmp_path, scene: PlaneScene, calib: StereoCalibration) -> None:
    tr = StereoTracker(calib)
    writer = TrackImageWriter(tmp_path / "tracks", calib)
    for i in range(2):
        f = scene.stereo(calib, make_T(np.eye(3), [0.02 * i, 0, 0]), 1_000 + i * 50_000_000)
        writer.write(f, tr.process(f))
    files = sorted((tmp_path / "tracks").glob("*.png"))
    assert len(files) == 2
    img = cv2.imread(str(files[-1]))
    assert img.shape == (H, 2 * W, 3)
    assert np.count_nonzero(img[..., 1] != img[..., 2]) > 500  # coloured track marks were drawn


def test_config_is_respected(scene: PlaneScene, calib: StereoCalibration) -> None:
    cfg = dataclasses.replace(FrontendConfig(), max_features=60, clahe=True)
    ff = StereoTracker(calib, cfg).process(scene.stereo(calib, np.eye(4), 1_000))
    assert ff.tracking_ok and 0 < len(ff.ids) <= 60


# ------------------------------------------------------------------------------------------- real data

def test_real_euroc_excerpt_stereo_and_stable_tracks(v101_path) -> None:
    from vio.io.euroc import EurocDataset

    ds = EurocDataset(v101_path)
    out = [ff for _, ff in run_frontend(ds, max_frames=30)]
    assert all(ff.tracking_ok for ff in out)
    n_stereo = np.array([ff.n_stereo for ff in out])
    assert n_stereo.min() >= 120, f"stereo features per frame: min {n_stereo.min()}, mean {n_stereo.mean():.0f}"
    # the excerpt is practically static: tracks live on and stay put
    a, b = out[5], out[-1]
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    assert len(common) >= 0.9 * len(a.ids)
    assert np.median(np.linalg.norm(a.uv0[ia] - b.uv0[ib], axis=1)) < 0.3
    # room depths: the Vicon room is a few metres across
    d = np.concatenate([ff.depth_m[np.isfinite(ff.depth_m)] for ff in out])
    assert 1.0 < np.median(d) < 5.0


# ------------------------------------------------------------------------------------- drift vs truth

def _affine_pair(scale: float, angle_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Texture and its affine warp about a set of corner points; returns (img0, img1, pts0, pts1 true)."""
    tex = _texture(5, 640)[80:560, :]
    a = np.radians(angle_deg)
    A = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    c = np.array([320.0, 240.0])
    M = np.column_stack([A, c - A @ c + [3.3, -2.1]])  # img1(A x + t) = img0(x)
    img1 = cv2.warpAffine(tex, M, (640, 480), flags=cv2.INTER_LINEAR)
    pts0 = cv2.KeyPoint_convert(cv2.FastFeatureDetector_create(20, True).detect(tex)).astype(np.float64)
    pts0 = pts0[np.all(np.abs(pts0 - c) < [180, 120], axis=1)][:150]
    return tex, img1, pts0, pts0 @ A.T + M[:, 2]


def test_anchor_refinement_removes_translational_klt_bias() -> None:
    """A patch scaled by 15 % and turned by 8 deg: translational KLT lands off the true point (its bias grows with
    the deformation, the cause of the drift of long tracks); the affine refinement against the first patch
    brings it back."""
    from vio.frontend.anchor import AnchorRefiner

    img0, img1, p0, p1 = _affine_pair(1.15, 8.0)
    klt = dict(winSize=(21, 21), maxLevel=2, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))
    p_klt, st, _ = cv2.calcOpticalFlowPyrLK(img0, img1, p0.astype(np.float32).reshape(-1, 1, 2),
                                            p1.astype(np.float32).reshape(-1, 1, 2),
                                            flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **klt)
    ok = st.ravel() == 1
    p_klt = p_klt.reshape(-1, 2).astype(np.float64)
    err_klt = np.linalg.norm(p_klt - p1, axis=1)[ok]
    ref = AnchorRefiner(15, iterations=6)
    anchors = ref.build(img0, p0)
    pos, ncc, contrast = ref.refine(img1, p_klt, anchors)
    err_ref = np.linalg.norm(pos - p1, axis=1)[ok & (ncc > 0.85)]
    assert np.median(err_klt) > 0.15, "the deformation is too small to show the bias"
    assert len(err_ref) >= 0.8 * ok.sum()
    assert np.median(err_ref) < 0.4 * np.median(err_klt)
    assert np.median(err_ref) < 0.15
    assert np.median(contrast) == pytest.approx(1.0, abs=0.2)
    # the warp found is the true one
    s = np.linalg.svd(anchors.A[ok & (ncc > 0.85)], compute_uv=False)
    assert np.median(s, axis=0) == pytest.approx([1.15, 1.15], abs=0.05)


def test_outliers_against_truth_on_short_aggressive_flight(tmp_path) -> None:
    """4 s of the aggressive profile, rendered: observations stay on their first 3D point. Before the anchor
    refinement 9.7 % of the observations lay > 2 px from it (median 0.56 px); now 0.4 % (median 0.09 px), and 90 %
    within the back end's pixel_sigma."""
    from vio.frontend.evaluate import SimTruth, track_stats, truth_errors
    from vio.io.euroc import EurocDataset
    from vio.sim.generate import SimConfig, simulate

    simulate(tmp_path / "sim", SimConfig(profile="aggressive", duration_s=4.0, seed=1, still_start_s=0.5))
    ds = EurocDataset(tmp_path / "sim")
    ffs = [ff for _, ff in run_frontend(ds, keyframe_every=5)]
    err = truth_errors(ffs, SimTruth(tmp_path / "sim", ds.calibration))
    stats = track_stats(ffs)
    assert err["tracks_checked"] > 200
    assert err["outlier_observations_fraction"] < 0.015, err
    assert err["reprojection_error_median_px"] < 0.2, err
    # the back end weighs each observation by pixel_sigma: it must not claim the tracks are better than they are
    assert err["reprojection_error_p90_px"] < VioConfig().backend.pixel_sigma, err
    assert err["depth_rel_error_median_within_5m"] < 0.03, err
    assert stats["features_per_frame_median"] >= 120 and stats["track_length_median"] >= 8, stats


def test_gyro_bias_is_subtracted_and_validated() -> None:
    from vio import VioError

    calib = _calib()
    prior = GyroPrior(calib.cam0.T_body_cam)
    bias = np.array([0.01, -0.02, 0.03])
    t = np.arange(0, 101) * 1_000_000
    for ti in t:
        prior.add(ImuSample(int(ti), bias + [0.0, 0.0, 1.0], np.zeros(3)))
    prior.set_gyro_bias(bias)
    R_bc = calib.cam0.T_body_cam[:3, :3]
    assert np.allclose(prior.rotation(0, 50_000_000), so3_exp(R_bc.T @ [0.0, 0.0, 0.05]), atol=1e-9)
    with pytest.raises(VioError, match="gyro bias"):
        prior.set_gyro_bias([0.1, np.nan, 0.0])


def test_broken_right_image_gives_mono_and_keeps_the_tracker_consistent(scene: PlaneScene,
                                                                         calib: StereoCalibration) -> None:
    f0 = scene.stereo(calib, np.eye(4), 1_000)
    f1 = scene.stereo(calib, make_T(so3_exp([0, 0.01, 0]), [0.02, 0, 0]), 50_001_000)
    f2 = scene.stereo(calib, make_T(so3_exp([0, 0.02, 0]), [0.04, 0, 0]), 100_001_000)
    tr = StereoTracker(calib)
    a = tr.process(f0)
    two_channel = np.dstack([f1.right, f1.right])  # OpenCV cannot convert it: raises inside the stereo step

    def broken_loader():
        raise OSError("disk gone")

    for bad in (StereoFrame(f1.t_ns, f1.left, two_channel),
                StereoFrame(f1.t_ns, f1.left, None, load_right=broken_loader)):
        tr2 = StereoTracker(calib)
        tr2.process(f0)
        b = tr2.process(bad)
        assert b.tracking_ok and b.n_stereo == 0 and "mono only" in b.reason
        c = tr2.process(f2)  # tracking goes on from this frame's image and tracks
        assert c.tracking_ok and len(np.intersect1d(a.ids, c.ids)) >= 0.8 * len(a.ids)


def test_median_is_numpys_float() -> None:
    """The per-frame median (vio.frontend.median) must give np.median's float bit for bit: the replays'
    trajectories stay byte-identical only if it does. Odd and even lengths, wide ranges, ties, and NaN."""
    from vio.frontend.median import median

    rng = np.random.default_rng(7)
    for n in [*range(1, 40), 199, 200]:
        for _ in range(50):
            x = rng.normal(size=n) * 10.0 ** rng.integers(-6, 7)
            assert median(x) == float(np.median(x))
            r = np.round(x, 1)  # ties in the middle pair
            assert median(r) == float(np.median(r))
    assert np.isnan(median(np.array([1.0, np.nan, 2.0]))) and np.isnan(median(np.array([np.nan, 3.0, 1.0, 2.0])))
