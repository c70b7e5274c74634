"""Trajectory evaluation: alignment, ATE, RPE, coverage, evo cross-check and the `vio eval` command."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest

from vio import VioError
from vio.app.cli import main
from vio.evaluation import align_4dof, associate, evaluate, load_trajectory
from vio.geometry import make_T, so3_exp
from vio.trajectory import Trajectory, write_tum

RATE_HZ = 50


def _flight(duration_s: float = 60.0, t0_ns: int = 1_700_000_000_000_000_000) -> Trajectory:
    """A smooth 3D figure with heading along the velocity and a little roll/pitch."""
    t = np.arange(int(duration_s * RATE_HZ)) / RATE_HZ
    p = np.stack([2.0 * np.sin(0.3 * t), 1.5 * np.sin(0.2 * t + 1.0), 1.0 + 0.3 * np.sin(0.5 * t)], axis=1)
    v = np.gradient(p, t, axis=0)
    yaw = np.arctan2(v[:, 1], v[:, 0])
    R = np.stack([so3_exp([0, 0, y]) @ so3_exp([0.1 * np.sin(0.7 * s), 0.05 * np.cos(0.4 * s), 0])
                  for y, s in zip(yaw, t)])
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, p
    return Trajectory.from_poses(t0_ns + np.round(t * 1e9).astype(np.int64), T)


def _line(n: int = 500, speed_m_s: float = 1.0) -> Trajectory:
    t = np.arange(n) / RATE_HZ
    p = np.stack([speed_m_s * t, np.zeros(n), np.ones(n)], axis=1)
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    return Trajectory(np.round(t * 1e9).astype(np.int64) + 10**18, p, q)


def _moved(traj: Trajectory, T_new_old: np.ndarray) -> Trajectory:
    return Trajectory.from_poses(traj.t_ns, T_new_old @ traj.poses())


@pytest.fixture(scope="module")
def gt() -> Trajectory:
    return _flight()


def test_self_is_zero(gt):
    r = evaluate(gt, gt)
    assert r.n_matched == len(gt)
    for a in (r.ate_4dof, r.ate_se3):
        assert a.trans_m.rmse < 1e-9 and a.trans_m.max < 1e-9
        assert a.rot_deg.max < 1e-4
    assert r.rpe and all(s.trans_pct < 1e-7 and s.rot_deg_per_m < 1e-4 for s in r.rpe)
    assert r.coverage == pytest.approx(1.0)
    assert r.longest_gap_s == pytest.approx(1 / RATE_HZ)
    assert r.path_length_m == pytest.approx(gt.path_length_m())


def test_rigid_transform_is_removed_by_se3_and_4dof_keeps_tilt(gt):
    T = make_T(so3_exp([0.2, -0.1, 1.3]), [5.0, -2.0, 0.7])
    r = evaluate(_moved(gt, T), gt)
    assert r.ate_se3.trans_m.rmse < 1e-6
    assert r.ate_se3.rot_deg.max < 1e-4
    assert np.allclose(r.ate_se3.T_gtworld_estworld, np.linalg.inv(T), atol=1e-6)
    # the 4-DoF fit cannot undo roll/pitch: a large error remains, and the relative errors do not care
    assert r.ate_4dof.trans_m.rmse > 0.05
    assert r.ate_4dof.rot_deg.mean > 5.0
    assert all(s.trans_pct < 1e-6 for s in r.rpe)


def test_yaw_and_translation_are_removed_by_4dof(gt):
    T = make_T(so3_exp([0, 0, -2.5]), [1.0, 2.0, 3.0])
    r = evaluate(_moved(gt, T), gt)
    assert r.ate_4dof.trans_m.rmse < 1e-9
    assert r.ate_4dof.rot_deg.max < 1e-4
    assert np.allclose(r.ate_4dof.T_gtworld_estworld, np.linalg.inv(T), atol=1e-9)


def test_4dof_differs_from_se3_when_roll_pitch_wrong(gt):
    """A 3 degree roll of the whole estimate: SE(3) hides it, 4-DoF shows it as ~3 degrees."""
    r = evaluate(_moved(gt, make_T(so3_exp([math.radians(3.0), 0, 0]), np.zeros(3))), gt)
    assert r.ate_se3.rot_deg.rmse < 1e-4
    assert r.ate_4dof.rot_deg.mean == pytest.approx(3.0, abs=0.05)
    assert r.ate_4dof.trans_m.rmse > 10 * r.ate_se3.trans_m.rmse + 0.01


def test_known_alternating_height_error(gt):
    """+-d in z on alternate poses: neither yaw nor a translation can remove it, so 4-DoF ATE is exactly d."""
    d = 0.05
    p = gt.p.copy()
    p[:, 2] += d * np.where(np.arange(len(gt)) % 2 == 0, 1.0, -1.0)
    r = evaluate(Trajectory(gt.t_ns, p, gt.q_wxyz), gt)
    assert r.ate_4dof.trans_m.rmse == pytest.approx(d, rel=1e-9)
    assert r.ate_4dof.trans_m.max == pytest.approx(d, rel=1e-9)
    assert r.ate_se3.trans_m.rmse == pytest.approx(d, rel=0.01)


def test_known_noise(gt):
    sigma = 0.02
    rng = np.random.default_rng(3)
    r = evaluate(Trajectory(gt.t_ns, gt.p + rng.normal(0, sigma, gt.p.shape), gt.q_wxyz), gt)
    assert r.ate_se3.trans_m.rmse == pytest.approx(sigma * math.sqrt(3), rel=0.05)
    assert r.ate_4dof.trans_m.rmse == pytest.approx(sigma * math.sqrt(3), rel=0.05)


def test_rpe_scale_drift_is_percent_of_distance():
    gt = _line()
    est = Trajectory(gt.t_ns, gt.p * [1.01, 1, 1], gt.q_wxyz)
    r = evaluate(est, gt, rpe_lengths_m=(1.0, 5.0))
    assert [s.length_m for s in r.rpe] == [1.0, 5.0]
    for s in r.rpe:
        assert s.trans_pct == pytest.approx(1.0, rel=1e-6)
        assert s.n_pairs > 0
    # 10 m path: no 20 m segments, so that length is left out
    assert [s.length_m for s in evaluate(est, gt, rpe_lengths_m=(2.0, 20.0)).rpe] == [2.0]


def test_rpe_yaw_drift_is_deg_per_metre():
    gt = _line()
    k_deg_per_m = 0.5
    dist = gt.p[:, 0] - gt.p[0, 0]
    T = gt.poses()
    T[:, :3, :3] = np.stack([so3_exp([0, 0, math.radians(k_deg_per_m * s)]) for s in dist])
    r = evaluate(Trajectory.from_poses(gt.t_ns, T), gt, rpe_lengths_m=(1.0, 3.0))
    for s in r.rpe:
        assert s.rot_deg_per_m == pytest.approx(k_deg_per_m, rel=1e-6)


def test_coverage_and_gaps(gt):
    t_s = (gt.t_ns - gt.t_ns[0]) * 1e-9
    keep = ((t_s >= 5.0) & (t_s < 20.0)) | (t_s >= 30.0)
    r = evaluate(gt.subset(np.flatnonzero(keep)), gt, rpe_lengths_m=(2.0,))
    span = t_s[-1]
    assert r.gt_span_s == pytest.approx(span)
    assert r.coverage == pytest.approx((span - 5.0 - 10.0 - 1 / RATE_HZ) / span, abs=1e-6)
    assert r.longest_gap_s == pytest.approx(10.0 + 1 / RATE_HZ, abs=1e-6)
    # segments across the gap are not counted
    full = evaluate(gt, gt, rpe_lengths_m=(2.0,))
    assert 0 < r.rpe[0].n_pairs < full.rpe[0].n_pairs - 100
    # cropping the ground truth to the estimate's span (+- max_dt: one more GT pose at 4.98 s) leaves only
    # the inner gap uncovered
    cropped = evaluate(gt.subset(np.flatnonzero(keep)), gt, rpe_lengths_m=(2.0,), crop_gt=True)
    assert cropped.gt_span_s == pytest.approx(span - 4.98)
    assert cropped.coverage == pytest.approx((span - 5.0 - 10.0 - 1 / RATE_HZ) / (span - 4.98), abs=1e-6)
    # max gap above the hole: counted as covered
    assert evaluate(gt.subset(np.flatnonzero(keep)), gt, max_gap_s=20.0).coverage > r.coverage + 0.15


def test_association_nearest_and_interpolated(gt):
    """Estimates 7 ms after each GT stamp: nearest pairing carries a timing error, interpolated GT none."""
    t = gt.t_ns[:-1] + 7_000_000
    est = gt.interpolate(t)
    idx, _ = associate(est, gt, 6_000_000)
    assert len(idx) == 0
    near = evaluate(est, gt, max_dt_ms=10.0)
    assert near.n_matched == len(est)
    assert near.ate_se3.trans_m.rmse > 1e-3
    interp = evaluate(est, gt, max_dt_ms=10.0, interpolate=True)
    assert interp.interpolated and interp.n_matched == len(est)
    assert interp.ate_se3.trans_m.rmse < 1e-9 and interp.ate_4dof.trans_m.rmse < 1e-9


def test_ground_truth_for_a_small_part_of_the_estimate_is_said(gt):
    """Ground truth cut to its last second: the ATE over those poses must not read as the flight's."""
    t_s = (gt.t_ns - gt.t_ns[0]) * 1e-9
    r = evaluate(gt, gt.subset(np.flatnonzero(t_s >= t_s[-1] - 1.0)))
    assert r.partial.startswith(f"only {r.n_matched} of the {len(gt.t_ns)} estimated poses have ground truth")
    assert "WARNING: only" in r.summary()
    assert evaluate(gt, gt).partial == "" and "WARNING" not in evaluate(gt, gt).summary()


def test_no_overlap_is_a_clear_error(gt):
    later = Trajectory(gt.t_ns + 10**12, gt.p, gt.q_wxyz)
    with pytest.raises(VioError, match=r"only 0 estimated poses have ground truth within 20 ms"):
        evaluate(later, gt)


def test_align_4dof_is_pure_yaw():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(50, 3))
    T = align_4dof(p, p @ so3_exp([0.3, 0.2, 0.1]).T)
    assert np.allclose(T[2, :3], [0, 0, 1]) and np.allclose(T[:3, 2], [0, 0, 1])


def _evo_ape_se3(est: Trajectory, gt: Trajectory, max_dt_s: float) -> float:
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    ref = PoseTrajectory3D(positions_xyz=gt.p, orientations_quat_wxyz=gt.q_wxyz, timestamps=gt.t_s)
    e = PoseTrajectory3D(positions_xyz=est.p, orientations_quat_wxyz=est.q_wxyz, timestamps=est.t_s)
    ref, e = sync.associate_trajectories(ref, e, max_diff=max_dt_s)
    e.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, e))
    return float(ape.get_statistic(metrics.StatisticsType.rmse))


def _noisy_moved(gt: Trajectory, seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    drift = np.cumsum(rng.normal(0, 0.002, gt.p.shape), axis=0)
    noisy = Trajectory(gt.t_ns, gt.p + drift, gt.q_wxyz)
    return _moved(noisy, make_T(so3_exp([0.05, -0.02, 0.9]), [0.4, -1.0, 0.2]))


def test_ate_se3_matches_evo(gt):
    est = _noisy_moved(gt, 1).subset(np.arange(0, len(gt), 3))
    ours = evaluate(est, gt, max_dt_ms=5.0).ate_se3.trans_m.rmse
    assert ours > 0.01
    assert ours == pytest.approx(_evo_ape_se3(est, gt, 0.005), abs=1e-6)


def test_ate_se3_matches_evo_on_euroc_v102(v102_path):
    gt = load_trajectory(v102_path)
    assert len(gt) == 16702
    est = _noisy_moved(gt, 2).subset(np.arange(0, len(gt), 10))
    est = Trajectory(est.t_ns + 3_000_000, est.p, est.q_wxyz)  # 3 ms stamp offset: nearest association
    ours = evaluate(est, gt, max_dt_ms=4.0)
    assert ours.n_matched == len(est)
    assert ours.ate_se3.trans_m.rmse == pytest.approx(_evo_ape_se3(est, gt, 0.004), abs=1e-6)


# ------------------------------------------------------------------------------------------------ loading + CLI

def test_load_euroc_csv_folder_and_tum(tmp_path, gt):
    csv = tmp_path / "gt.csv"
    rows = [f"{t}," + ",".join(repr(float(x)) for x in (*p, *q)) for t, p, q in zip(gt.t_ns[:20], gt.p, gt.q_wxyz)]
    csv.write_text("#timestamp,px,py,pz,qw,qx,qy,qz\n" + "\n".join(rows) + "\n")
    a = load_trajectory(csv)
    assert np.array_equal(a.t_ns, gt.t_ns[:20])
    assert np.allclose(a.p, gt.p[:20]) and np.allclose(a.q_wxyz, gt.q_wxyz[:20])
    (tmp_path / "ds" / "mav0" / "state_groundtruth_estimate0").mkdir(parents=True)
    (tmp_path / "ds" / "mav0" / "state_groundtruth_estimate0" / "data.csv").write_text(csv.read_text())
    assert np.array_equal(load_trajectory(tmp_path / "ds").t_ns, a.t_ns)
    write_tum(gt, tmp_path / "gt.tum")
    assert np.array_equal(load_trajectory(tmp_path / "gt.tum").t_ns, gt.t_ns)


def test_cli_writes_summary_json_and_plot(tmp_path, gt, capsys):
    write_tum(gt, tmp_path / "gt.txt")
    write_tum(_noisy_moved(gt, 4), tmp_path / "est.txt")
    rc = main(["-q", "eval", str(tmp_path / "est.txt"), str(tmp_path / "gt.txt"), "--plot",
               str(tmp_path / "e.png"), "--json", str(tmp_path / "e.json"), "--rpe-lengths", "1,5"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "ATE 4-DoF" in out and "ATE SE(3)" in out and "RPE     5 m" in out and "coverage" in out
    d = json.loads((tmp_path / "e.json").read_text())
    assert d["n_matched"] == len(gt)
    assert d["ate_se3"]["trans_m"]["rmse"] > 0 and len(d["rpe"]) == 2
    assert np.array(d["ate_se3"]["T_gtworld_estworld"]).shape == (4, 4)
    assert (tmp_path / "e.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_plot_goes_to_the_file_named_and_an_unknown_format_is_refused_first(tmp_path, gt, capsys):
    """`--plot e` (no suffix) printed nothing wrong but matplotlib wrote e.png, over whatever was there; `--plot
    e.txt` (and replay's `--loop-plot run.txt`) ended in an internal error after the whole evaluation or replay."""
    write_tum(gt, tmp_path / "gt.txt")
    write_tum(_noisy_moved(gt, 4), tmp_path / "est.txt")
    (tmp_path / "e.png").write_bytes(b"an older plot")
    assert main(["-q", "eval", str(tmp_path / "est.txt"), str(tmp_path / "gt.txt"), "--plot", str(tmp_path / "e")]) == 0
    assert (tmp_path / "e").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "e.png").read_bytes() == b"an older plot"
    capsys.readouterr()
    assert main(["-q", "eval", str(tmp_path / "est.txt"), str(tmp_path / "gt.txt"), "--plot",
                 str(tmp_path / "e.txt"), "--json", str(tmp_path / "e.json")]) == 1
    out = capsys.readouterr()
    assert "a plot cannot be written as .txt" in out.err and "internal error" not in out.err
    assert "ATE" not in out.out and not (tmp_path / "e.json").exists()  # refused before the evaluation


def test_cli_plot_without_the_tools_extra_is_refused_before_any_work(tmp_path, gt, capsys, monkeypatch):
    """--plot without matplotlib: the numbers were computed and printed and --json written, and only then "plots
    (--plot) needs the [tools] extra", exit 1. Asked for first now, as `vio replay --loop-plot` does."""
    write_tum(gt, tmp_path / "gt.txt")
    write_tum(_noisy_moved(gt, 4), tmp_path / "est.txt")
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # as on a core install: import matplotlib fails
    rc = main(["-q", "eval", str(tmp_path / "est.txt"), str(tmp_path / "gt.txt"), "--plot", str(tmp_path / "e.png"),
               "--json", str(tmp_path / "e.json")])
    assert rc == 1
    out, err = capsys.readouterr()
    assert out == "" and err.strip().splitlines() == [
        "vio eval: error: plots (--plot) needs the [tools] extra: pip install 'kestrel-vio[tools]'"]
    assert not (tmp_path / "e.json").exists() and not (tmp_path / "e.png").exists()


@pytest.mark.parametrize("case, message", [
    ("missing", "missing.txt: file not found"),
    ("malformed", "bad.txt:3: expected 8 values"),
    ("nonnumber", "bad.txt:1: not a number"),
    ("no_overlap", "only 0 estimated poses have ground truth"),
])
def test_cli_errors(tmp_path, gt, capsys, case, message):
    write_tum(gt, tmp_path / "gt.txt")
    est = tmp_path / "bad.txt"
    if case == "missing":
        est = tmp_path / "missing.txt"
    elif case == "malformed":
        est.write_text("# t x y z qx qy qz qw\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    elif case == "nonnumber":
        est.write_text("1.0 0 0 zero 0 0 0 1\n")
    else:
        write_tum(Trajectory(gt.t_ns - 10**12, gt.p, gt.q_wxyz), est)
    rc = main(["eval", str(est), str(tmp_path / "gt.txt")])
    err = capsys.readouterr().err
    assert rc == 1
    assert message in err and err.startswith("vio eval: error:")
    assert "Traceback" not in err


def test_hovering_flight_aligns_its_rotation_on_orientations():
    """A hover (positions within 1 cm) in a world turned 30 deg about z and 2 deg about x: a position fit
    cannot fix the rotation, so both ATEs take it from the orientations: the SE(3) rotation error is what
    the estimate has beyond a constant (about 0), the 4-DoF one the 2 deg tilt of the world that VIO must
    observe; a moving flight keeps the position fit."""
    rng = np.random.default_rng(3)
    n = 400
    t_ns = 1_700_000_000_000_000_000 + np.arange(n) * 20_000_000
    R_gt = np.stack([so3_exp(rng.normal(0, 0.05, 3)) for _ in range(n)])
    p_gt = np.array([0.5, 1.0, 1.2]) + rng.normal(0, 0.005, (n, 3))
    T_gt = np.tile(np.eye(4), (n, 1, 1))
    T_gt[:, :3, :3], T_gt[:, :3, 3] = R_gt, p_gt
    T_w = make_T(so3_exp([0.0, 0.0, math.radians(30)]) @ so3_exp([math.radians(2), 0, 0]), [3.0, -1.0, 0.2])
    T_est = np.linalg.inv(T_w) @ T_gt
    res = evaluate(Trajectory.from_poses(t_ns, T_est), Trajectory.from_poses(t_ns, T_gt))
    assert res.ate_se3.rotation_from == res.ate_4dof.rotation_from == "orientations"
    assert res.ate_se3.rot_deg.rmse < 0.01, res.ate_se3.rot_deg.rmse
    assert abs(res.ate_4dof.rot_deg.rmse - 2.0) < 0.05, res.ate_4dof.rot_deg.rmse
    assert "rotation aligned on orientations" in res.summary()
    moving = _flight(20.0)
    assert evaluate(moving, moving).ate_se3.rotation_from == "positions"


def test_a_file_vio_run_appended_several_runs_to_is_read_one_run_at_a_time(tmp_path, gt, capsys, caplog):
    """The daemon appends each run to its trajectory file, each in its own odometry frame, after a marker line;
    `vio eval` on such a file took both runs as one trajectory (ATE 1.67 m, exit 0, no word: a QA sweep)."""
    import logging

    from vio.geometry import make_T
    from vio.trajectory import RUN_MARKER

    write_tum(gt, tmp_path / "gt.txt")
    write_tum(_noisy_moved(gt, 4), tmp_path / "one.txt")
    other = Trajectory.from_poses(gt.t_ns, np.array([make_T(np.eye(3), np.array([5.0, 0, 0])) @ T
                                                      for T in gt.poses()]))  # a second run: another frame
    write_tum(other, tmp_path / "two.txt")
    half = len(gt) // 2
    runs = tmp_path / "runs.tum"
    body = [p.read_text().splitlines() for p in (tmp_path / "one.txt", tmp_path / "two.txt")]
    body = [[ln for ln in b if not ln.startswith("#")] for b in body]
    runs.write_text("\n".join([f"{RUN_MARKER} 2026-12-06T10:00:00+00:00 (pid 1): the poses below ...", *body[0][:half],
                               f"{RUN_MARKER} 2026-12-06T10:05:00+00:00 (pid 2): the poses below ...",
                               *body[1][half:]]) + "\n")
    with caplog.at_level(logging.WARNING):
        last = load_trajectory(runs)
    assert np.array_equal(last.t_ns, gt.t_ns[half:]) and "holds 2 runs" in caplog.text and "pid 2" in caplog.text
    assert np.array_equal(load_trajectory(runs, 1).t_ns, gt.t_ns[:half])
    assert main(["-q", "eval", str(runs), str(tmp_path / "gt.txt"), "--run", "1", "--json", str(tmp_path / "e.json")
                 ]) == 0
    assert json.loads((tmp_path / "e.json").read_text())["ate_4dof"]["trans_m"]["rmse"] < 0.5  # the 5 m jump: metres
    assert main(["-q", "eval", str(runs), str(tmp_path / "gt.txt"), "--run", "3"]) == 1
    assert "holds 2 runs, not run 3" in capsys.readouterr().err
    # a start that never tracked wrote its marker and no pose: it is a run as the file shows it (a review's finding:
    # --run 2 read the third marker's poses), said when asked for, and the default is still the last with poses
    lines = runs.read_text().splitlines()
    lines.insert(half + 1, f"{RUN_MARKER} 2026-12-06T10:03:00+00:00 (pid 9): the poses below ...")
    runs.write_text("\n".join(lines) + "\n")
    assert main(["-q", "eval", str(runs), str(tmp_path / "gt.txt"), "--run", "2"]) == 1
    assert "run 2 of 3 (started 2026-12-06T10:03:00+00:00 (pid 9)) holds no pose" in capsys.readouterr().err
    assert np.array_equal(load_trajectory(runs, 3).t_ns, gt.t_ns[half:])
    assert np.array_equal(load_trajectory(runs).t_ns, gt.t_ns[half:])
    # one run with its marker, as the daemon's first run writes it: read as it is, nothing said
    caplog.clear()
    (tmp_path / "single.tum").write_text(f"{RUN_MARKER} x (pid 1): ...\n" + "\n".join(body[0]) + "\n")
    with caplog.at_level(logging.WARNING):
        assert np.array_equal(load_trajectory(tmp_path / "single.tum").t_ns, gt.t_ns)
    assert "runs" not in caplog.text
    # --run 2 of a file of one run said 'holds 1 runs'
    assert main(["-q", "eval", str(tmp_path / "single.tum"), str(tmp_path / "gt.txt"), "--run", "2"]) == 1
    assert "single.tum: holds 1 run, not run 2" in capsys.readouterr().err


def test_max_gap_below_the_pose_spacing_is_refused_and_sparse_poses_are_not_all_gaps(tmp_path, gt, capsys):
    """--max-gap-s under the pose spacing printed "coverage 0.0 %" and "path shorter than every segment length" for a
    whole flight (a QA sweep); keyframe poses (further apart than the default 0.5 s) read the same by default."""
    write_tum(gt, tmp_path / "gt.txt")
    write_tum(gt, tmp_path / "est.txt")
    step = float(np.median(np.diff(gt.t_ns))) * 1e-9
    assert main(["-q", "eval", str(tmp_path / "est.txt"), str(tmp_path / "gt.txt"), "--max-gap-s", f"{step / 2:g}"]) \
        == 1
    assert "below the estimate's median pose spacing" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # a usage error (exit 2), as every option's range
        main(["-q", "eval", str(tmp_path / "est.txt"), str(tmp_path / "gt.txt"), "--max-gap-s", "0"])
    assert e.value.code == 2 and "--max-gap-s: must be a positive number" in capsys.readouterr().err
    sparse = gt.subset(np.arange(0, len(gt), int(round(0.6 / step))))  # a pose every 0.6 s, as keyframes come
    write_tum(sparse, tmp_path / "kf.txt")
    assert main(["-q", "eval", str(tmp_path / "kf.txt"), str(tmp_path / "gt.txt"), "--json", str(tmp_path / "e.json")
                 ]) == 0
    d = json.loads((tmp_path / "e.json").read_text())
    assert d["coverage"] > 0.8 and d["rpe"], d


def test_files_saved_with_a_byte_order_mark_are_read(tmp_path, gt, capsys):
    """A TUM file or a EuRoC ground-truth csv saved by a Windows editor starts with a BOM: the TUM header's '#' was
    not seen ("expected 8 values ..., got 10"), and the csv was taken for a TUM file ("got 42")."""
    write_tum(gt, tmp_path / "gt.txt")
    (tmp_path / "bom.txt").write_bytes(b"\xef\xbb\xbf" + (tmp_path / "gt.txt").read_bytes())
    rows = ["#timestamp,p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"]
    rows += [f"{t},{p[0]},{p[1]},{p[2]},{q[0]},{q[1]},{q[2]},{q[3]}" for t, p, q in zip(gt.t_ns, gt.p, gt.q_wxyz)]
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + "\r\n".join(rows).encode() + b"\r\n")
    for est, truth in (("bom.txt", "gt.txt"), ("gt.txt", "bom.csv")):
        assert main(["-q", "eval", str(tmp_path / est), str(tmp_path / truth)]) == 0, capsys.readouterr().err
        out = capsys.readouterr().out
        assert f"poses: {len(gt)} estimated, {len(gt)} ground truth, {len(gt)} matched" in out, out


def test_a_hover_written_w_first_is_named_too(tmp_path, capsys):
    """On a hover (a path too small to align on) the SE(3) ATE is aligned on the orientations, which absorbs a w-first
    file's near-constant misreading: `vio eval` printed a 4-DoF rotation error of ~135 deg and no hint (a walk-through
    with the EuRoC excerpt, 2 cm of path)."""
    rng = np.random.default_rng(3)
    n = 200
    t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 50_000_000
    p = 0.002 * rng.standard_normal((n, 3))
    # the EuRoC V1_01 excerpt's attitude (w x y z), turned by a few tenths of a degree at random
    q = np.array([0.0033, -0.8296, -0.018, -0.558]) + 0.003 * rng.standard_normal((n, 4))
    hover = Trajectory(t, p, q / np.linalg.norm(q, axis=1, keepdims=True))
    write_tum(hover, tmp_path / "gt.txt")
    lines = [f"{ti * 1e-9:.9f} " + " ".join(f"{x:.9f}" for x in (*pi, *qi)) for ti, pi, qi in zip(t, p, hover.q_wxyz)]
    (tmp_path / "wfirst.txt").write_text("\n".join(lines) + "\n")
    assert main(["-q", "eval", str(tmp_path / "wfirst.txt"), str(tmp_path / "gt.txt")]) == 0
    out = capsys.readouterr().out
    assert "path too small" in out and "if the estimate's quaternions are read w-first" in out, out
    assert main(["-q", "eval", str(tmp_path / "gt.txt"), str(tmp_path / "wfirst.txt")]) == 0
    assert "if the ground truth's quaternions are read w-first" in capsys.readouterr().out
    assert main(["-q", "eval", str(tmp_path / "gt.txt"), str(tmp_path / "gt.txt")]) == 0
    assert "w-first" not in capsys.readouterr().out


def test_a_tum_file_written_w_first_is_named_not_scored_silently(tmp_path, gt, capsys):
    """TUM holds qx qy qz qw; a tool writing qw qx qy qz (EuRoC's order) gives orientations about 180 deg off
    the truth with right positions, which read as the estimator's rotation error. The summary now says which
    file's quaternions agree when read w-first; a right file says nothing of it."""
    write_tum(gt, tmp_path / "gt.txt")
    lines = []
    for t, p, q in zip(gt.t_ns, gt.p, gt.q_wxyz):  # q is w x y z: written in that order
        lines.append(f"{t * 1e-9:.9f} " + " ".join(f"{x:.9f}" for x in (*p, *q)))
    (tmp_path / "wfirst.txt").write_text("\n".join(lines) + "\n")
    assert main(["-q", "eval", str(tmp_path / "wfirst.txt"), str(tmp_path / "gt.txt")]) == 0
    out = capsys.readouterr().out
    assert "WARNING: orientations disagree by" in out and "if the estimate's quaternions are read w-first" in out
    assert main(["-q", "eval", str(tmp_path / "gt.txt"), str(tmp_path / "wfirst.txt")]) == 0
    assert "if the ground truth's quaternions are read w-first" in capsys.readouterr().out
    write_tum(_noisy_moved(gt, 4), tmp_path / "est.txt")
    assert main(["-q", "eval", str(tmp_path / "est.txt"), str(tmp_path / "gt.txt")]) == 0
    assert "w-first" not in capsys.readouterr().out
