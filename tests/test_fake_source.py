"""`[source] kind = "fake"`: a simulated flight whose IMU and images agree, so `vio run` on a bench flies.

Unit checks of FakeSource (stamps, determinism, an endless IMU continuing across chunks, the truth) and
one end-to-end run: `vio run` with realtime = false plays ~15 s of flight as fast as the estimator takes
it; its trajectory file is within 0.1 m of the simulator's truth and no implausible speed is reported.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
from test_service import _need_pipeline, fly_fake

from drivers.fake import MAX_RENDER_LAG_S, FakeSource
from vio.evaluation import evaluate
from vio.trajectory import Trajectory, read_tum

T0 = 5_000_000_000


def test_fake_source_is_deterministic_and_its_imu_matches_the_truth() -> None:
    a = list(FakeSource(96, 64, duration_s=0.5, t0_ns=T0, realtime=False).messages())
    b = list(FakeSource(96, 64, duration_s=0.5, t0_ns=T0, realtime=False).messages())
    assert len(a) == len(b) == 101 + 11
    frames = [m for m in a if hasattr(m, "left")]
    assert [f.t_ns for f in frames] == [T0 + k * 50_000_000 for k in range(11)]
    for x, y in zip(a, b):
        assert x.t_ns == y.t_ns
        assert np.array_equal(x.left, y.left) if hasattr(x, "left") else np.array_equal(x.accel, y.accel)
    assert frames[3].left.std() > 10 and frames[3].right is not None  # a textured room, both cameras
    # an endless flight: the IMU continues across the synthesis chunks without a jump
    src = FakeSource(96, 64, t0_ns=T0, realtime=False)
    n = src._imu_n
    acc = np.array([src.imu(k).accel for k in range(n - 3, n + 3)])
    assert np.abs(np.diff(acc, axis=0)).max() < 0.5
    # the gyro is the truth's rotation rate (plus noise and a small bias)
    T = src.truth(np.array([src.imu_t_ns(k) for k in (3000, 3001)]))
    dR = T[0, :3, :3].T @ T[1, :3, :3]
    w_true = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / 2 * 200.0
    assert np.linalg.norm(src.imu(3000).gyro - w_true) < 0.05


def test_realtime_fake_source_keeps_up_at_20_hz() -> None:
    src = FakeSource(320, 200, realtime=True)
    src.start()
    try:
        t0, frames = time.monotonic(), []
        while time.monotonic() - t0 < 1.5:
            frames += [m for m in src.poll() if hasattr(m, "left")]
            time.sleep(0.005)
        lag_ms = max((time.monotonic_ns() - f.t_ns) / 1e6 for f in frames[-5:])
    finally:
        src.stop()
    # stamps on the host clock, released on time (a loaded machine makes the renderer skip, not lag)
    assert len(frames) + src.frames_late >= 28 and len(frames) >= 20
    assert lag_ms < MAX_RENDER_LAG_S * 1e3 + 150


def test_vio_run_fake_flight_tracks_the_simulator_truth(tmp_path: Path) -> None:
    _need_pipeline()
    traj = tmp_path / "traj.tum"
    rc, text = fly_fake(tmp_path, f"""[source]
kind = "fake"
realtime = false
fake_duration_s = 15.0
width = 320
height = 200
[run]
status_file = "{tmp_path / 'status.json'}"
trajectory_file = "{traj}"
""", 90, settle_s=0.5)  # the last frames through the output
    assert rc == 0 and "Traceback" not in text, text[-3000:]
    assert "implausible" not in text, text[-3000:]
    est = read_tum(traj)
    assert len(est) > 200, f"only {len(est)} poses; log:\n{text[-3000:]}"
    assert traj.read_text().startswith("# kestrel-vio run started ")  # where this run's frame starts in the file
    # the source's flight starts at the first stamp it delivered (t0 = host clock at start)
    src = FakeSource(320, 200, t0_ns=0)
    t_ns = np.arange(0, 15_000_000_001, 5_000_000)
    t0 = _t0_from_log(text)
    T = src.truth(t_ns)
    from vio.geometry import rot_to_quat_wxyz

    gt = Trajectory(t_ns + t0, T[:, :3, 3], rot_to_quat_wxyz(T[:, :3, :3]))
    res = evaluate(est, gt, max_dt_ms=3.0, crop_gt=True)
    print(f"\nfake flight through vio run: {len(est)} poses, ATE SE(3) {res.ate_se3.trans_m.rmse:.3f} m, "
          f"max {res.ate_se3.trans_m.max:.3f} m, path {res.path_length_m:.1f} m")
    assert res.path_length_m > 2.0  # it did fly
    assert res.ate_se3.trans_m.max < 0.1


def _t0_from_log(text: str) -> int:
    return int(re.search(r"fake source: .* t0_ns=(\d+)", text).group(1))
