"""Loop closure (vio/loop/): robust pose graph, vocabulary on unseen images, verification gates, and a short
simulated loop flight replayed with and without loop closure."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from vio.geometry import make_T, so3_exp


def _circle(n: int, rng: np.random.Generator):
    """Ground truth on a 2 m circle and an odometry chain with a steady yaw and forward drift."""
    from vio.loop.posegraph import PoseGraph

    truth = [make_T(so3_exp(np.array([0, 0, 2 * np.pi * k / 40])),
                    2 * np.array([np.cos(2 * np.pi * k / 40), np.sin(2 * np.pi * k / 40), 1.0])) for k in range(n)]
    g, prev, T = PoseGraph(), None, truth[0].copy()
    for k in range(n):
        if k:
            drift = make_T(so3_exp(np.r_[0, 0, 8e-4] + rng.normal(0, 2e-4, 3)),
                           np.r_[3e-3, 0, 0] + rng.normal(0, 1e-3, 3))
            T = T @ np.linalg.inv(truth[k - 1]) @ truth[k] @ drift
        prev = g.add_node(T, prev)
    return g, truth


def _ate(g, truth) -> float:
    return float(np.sqrt(np.mean([np.sum((e[:3, 3] - t[:3, 3]) ** 2) for e, t in zip(g.estimate, truth)])))


@pytest.mark.parametrize("seed", range(8))
def test_pose_graph_closes_loops_and_switches_off_20_false_edges(seed):
    """Twenty random wrong edges injected at once into a lap closed by three true ones: GNC switches every wrong
    one off and keeps the true ones (on draw 5 GNC from all-free alone switched the three true ones off too and the
    graph fell back to the odometry; the start with the accepted edges held wins on TLS cost)."""
    rng = np.random.default_rng(seed)
    g, truth = _circle(121, rng)
    ate_odom = _ate(g, truth)
    for k in (40, 80, 120):
        g.add_loop(0, k, np.linalg.inv(truth[0]) @ truth[k])
    g.optimize()
    ate_true = _ate(g, truth)
    assert ate_true < 0.5 * ate_odom
    for _ in range(20):  # injection: random wrong edges between random keyframes
        a, b = (int(x) for x in rng.integers(0, 121, 2))
        g.add_loop(a, b, make_T(so3_exp(rng.normal(size=3) * 0.3), rng.normal(size=3)))
    w = g.optimize()["loop_weights"]
    assert w[:3] == [1.0, 1.0, 1.0] and max(w[3:]) < 0.5
    assert abs(_ate(g, truth) - ate_true) <= 0.1 * ate_true
    # roll and pitch stay on gravity (attitude factors)
    for e, o in zip(g.estimate, g.odom):
        assert np.degrees(np.arccos(np.clip((e[:3, :3].T @ [0, 0, 1]) @ (o[:3, :3].T @ [0, 0, 1]), -1, 1))) < 1.0


def test_join_edge_counts_follow_every_add_take_back_and_switch_off():
    """The loop stage counts each session's active edges to other sessions from a cache (asked up to four times a
    keyframe while placed in a map): it must see an edge added, edges taken back after a failed solve, and GNC
    switching edges off, exactly as counting every edge again does."""
    from types import SimpleNamespace as NS

    from vio.config import LoopConfig
    from vio.loop.closer import LoopCloser

    rng = np.random.default_rng(3)
    g, truth = _circle(121, rng)
    me = NS(graph=g, keyframes=[NS(session=0 if k < 60 else 1) for k in range(121)], cfg=LoopConfig(),
            _join_counts=(-1, {}))

    def counted(session):
        return LoopCloser._join_edges(me, session)

    def recount(session):
        return sum((me.keyframes[e.i].session == session) != (me.keyframes[e.j].session == session)
                   for e in g.edges if e.kind == "loop" and e.weight >= 0.5)

    assert counted(1) == 0
    for k in (80, 100, 120):  # session 1's views of session 0's start: true edges
        g.add_loop(0, k, np.linalg.inv(truth[0]) @ truth[k])
    g.add_loop(40, 70, np.linalg.inv(truth[40]) @ truth[70])
    assert counted(1) == counted(0) == recount(1) == 4
    g.optimize()
    first = len(g.edges)
    g.add_loop(10, 110, np.eye(4))
    assert counted(1) == 5
    assert g.drop_loops_from(first) == 1 and counted(1) == 4
    for _ in range(20):  # wrong edges across the join: GNC switches them off after they were counted
        a, b = int(rng.integers(0, 60)), int(rng.integers(60, 121))
        g.add_loop(a, b, make_T(so3_exp(rng.normal(size=3) * 0.3), rng.normal(size=3)))
    assert counted(1) == 24
    g.optimize()
    assert counted(1) == recount(1) == counted(0) == 4


def test_edges_held_tight_by_their_inliers_are_decided_at_the_graphs_sigmas():
    """An edge with many inliers is held at half the graph's sigmas in the estimate, but GNC decides at the graph's
    sigmas: with three true edges and three strong false ones, all held tight, TLS in the tight sigmas switched
    true edges off on 3 of 30 draws (the drifting odometry puts them several sigmas off). Decided at the graph's
    sigmas, no true edge is switched off and every false one is."""
    for seed in range(12):
        rng = np.random.default_rng(seed)
        g, truth = _circle(121, rng)
        for k in (40, 80, 120):
            g.add_loop(k % 40, k, np.linalg.inv(truth[k % 40]) @ truth[k], 240, 0.5)
        g.optimize(decide=True)
        ate_true = _ate(g, truth)
        for _ in range(3):
            a, b = (int(x) for x in rng.integers(0, 121, 2))
            g.add_loop(a, b, make_T(so3_exp(rng.normal(size=3) * 0.1), rng.normal(size=3) * 0.3), 240, 0.5)
            g.optimize()
        w = g.optimize(decide=True)["loop_weights"]
        assert w[:3] == [1.0, 1.0, 1.0] and max(w[3:]) < 0.5, (seed, w)
        assert _ate(g, truth) <= 1.1 * ate_true


def test_a_loop_edge_from_a_keyframe_to_itself_is_kept_switched_off():
    """Such an edge constrains nothing (an injection of random edges draws one now and then); it used to make the
    fit check insert the node twice and raise. It stays in the edge list, off, and the solves go on."""
    rng = np.random.default_rng(2)
    g, truth = _circle(60, rng)
    g.add_loop(0, 40, np.linalg.inv(truth[0]) @ truth[40])
    g.optimize()
    g.add_loop(33, 33, make_T(so3_exp(np.r_[0.1, 0, 0]), np.r_[0.2, 0, 0]))
    g.add_loop(1, 41, np.linalg.inv(truth[1]) @ truth[41])
    assert g.optimize()["loop_weights"] == [1.0, 0.0, 1.0]
    assert g.optimize(decide=True)["loop_weights"] == [1.0, 0.0, 1.0]
    assert len(g.active_loops()) == 2


def test_loop_edges_the_graph_already_agrees_with_skip_the_fit_check_and_a_wrong_one_does_not():
    """After the first closure, the next true edges of the same lap fit the current estimate and go into iSAM2
    at once (no decision-graph solve); the solution is the one the full path gives. A wrong edge is far off
    the estimate, takes the full path, and GNC switches it off."""
    import dataclasses

    from vio.loop.posegraph import GraphNoise

    for quick in (True, False):
        g, truth = _circle(90, np.random.default_rng(1))
        if not quick:
            g.noise = dataclasses.replace(GraphNoise(), quick_fit_share=0.0)  # the full path every time
        for k in range(40, 48):  # a second lap closing on the first at every keyframe
            g.add_loop(k - 40, k, np.linalg.inv(truth[k - 40]) @ truth[k])
            g.optimize()
        if quick:
            assert g.quick_fits >= 5, g.quick_fits  # all but the first closure (and its aftermath)
            g.refresh()  # the quick fits wait for the next iSAM2 update (defer_quick_fits)
            est_quick, ate_quick = np.array(g.estimate), _ate(g, truth)
        else:
            assert g.quick_fits == 0
            # the same least squares; the deferred edges were linearised at one point instead of eight (~1 mm)
            assert np.abs(np.array(g.estimate)[:, :3, 3] - est_quick[:, :3, 3]).max() < 2e-3
            assert abs(_ate(g, truth) - ate_quick) < 0.01 * ate_quick
    g, truth = _circle(90, np.random.default_rng(1))
    for k in range(40, 48):
        g.add_loop(k - 40, k, np.linalg.inv(truth[k - 40]) @ truth[k])
        g.optimize()
    n_quick = g.quick_fits
    g.add_loop(5, 60, make_T(so3_exp(np.r_[0, 0, 0.3]), np.r_[1.0, 0.5, 0.0]))  # a look-alike place
    w = g.optimize()["loop_weights"]
    assert g.quick_fits == n_quick and w[-1] < 0.5 and min(w[:-1]) >= 0.5


def test_settled_odometry_replaces_the_edges_and_attitude_factors_pending_or_already_solved():
    """Keyframes whose first odometry poses jitter (1 cm, 0.3 deg each, not accumulated: what a filter estimate
    carries) and whose settled poses are exact: once settled, with some nodes still pending and some already in
    iSAM2 (flushed every 10), the graph's odometry edges and attitude factors are the settled ones, the decision
    graph composes them, and with one exact loop edge the solution is the truth; `odom` (what the correction
    maps) stays the first poses."""
    from vio.loop.posegraph import PoseGraph

    rng = np.random.default_rng(3)
    n = 45
    truth = [make_T(so3_exp(np.array([0, 0, 2 * np.pi * k / 40])),
                    2 * np.array([np.cos(2 * np.pi * k / 40), np.sin(2 * np.pi * k / 40), 1.0])) for k in range(n)]
    first = [T @ make_T(so3_exp(rng.normal(0, np.radians(0.3), 3)), rng.normal(0, 0.01, 3)) for T in truth]
    first[0] = truth[0]
    errs = {}
    for settle in (False, True):
        g, prev = PoseGraph(), None
        for k in range(n):
            prev = g.add_node(first[k], prev)
            if settle and k >= 12:  # 12 keyframes late: the first ones are in iSAM2 by then, the later pending
                g.settle(k - 12, truth[k - 12])
        if settle:
            for k in range(n - 12, n):
                g.settle(k, truth[k])
            assert len(g.settled) == n
            for e in g.edges:
                np.testing.assert_allclose(e.T_i_j, np.linalg.inv(truth[e.i]) @ truth[e.j], atol=1e-9)
        g.add_loop(0, 40, np.linalg.inv(truth[0]) @ truth[40])
        g.optimize(decide=True)  # the decision graph's composed odometry, then iSAM2
        errs[settle] = max(float(np.linalg.norm(e[:3, 3] - t[:3, 3])) for e, t in zip(g.estimate, truth))
        for o, f in zip(g.odom, first):
            np.testing.assert_array_equal(o, f)
    assert errs[False] > 5e-3 and errs[True] < 1e-4, errs


@pytest.fixture(scope="module")
def loop_flight(tmp_path_factory):
    """A 36 s survey flight (a lissajous: it passes its own path) in a room the vocabulary never saw."""
    sim = pytest.importorskip("vio.sim.generate")
    data = tmp_path_factory.mktemp("loop") / "flight"
    sim.simulate(data, sim.SimConfig(profile="survey", duration_s=36.0, seed=2, width=376, height=240,
                                     variant="realistic"))
    return data


@pytest.fixture(scope="module")
def laps_flight(tmp_path_factory):
    """A 36 s flight of laps round a room the vocabulary never saw: it comes back to each view every ~20 s
    from the same direction (16 loop edges at 376x240). The 36 s survey above had 0 on 2026-12-03 (its
    revisits are few and from other directions at this size), which failed this test on a fresh install."""
    sim = pytest.importorskip("vio.sim.generate")
    data = tmp_path_factory.mktemp("laps") / "flight"
    sim.simulate(data, sim.SimConfig(profile="laps", duration_s=36.0, seed=2, width=376, height=240,
                                     variant="clean"))
    return data


def test_vocabulary_retrieves_the_same_place_in_unseen_images(loop_flight):
    import cv2

    from vio.io.euroc import EurocDataset
    from vio.loop.database import BowIndex
    from vio.loop.features import FeatureExtractor
    from vio.loop.vocabulary import Vocabulary

    ds = EurocDataset(loop_flight)
    ex, voc = FeatureExtractor(ds.calibration.cam0, 300), Vocabulary.load()
    gt = ds.groundtruth.trajectory
    idx = BowIndex(voc.n_words)
    files = ds.cam0_files[::10]
    t = ds.frame_t[::10]
    pos = np.array([gt.p[np.argmin(np.abs(gt.t_ns - ti))] for ti in t])
    for f in files:
        idx.add(voc.bow(ex.extract(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), None).desc))
    from vio.geometry import quat_wxyz_to_rot, roll_pitch_yaw

    k = [int(np.argmin(np.abs(gt.t_ns - ti))) for ti in t]
    yaw = np.array([roll_pitch_yaw(quat_wxyz_to_rot(gt.q_wxyz[j]))[2] for j in k])

    def same_place(a: int, b: int) -> bool:
        d_yaw = np.angle(np.exp(1j * (yaw[a] - yaw[b])))
        return bool(np.linalg.norm(pos[a] - pos[b]) < 0.5 and abs(np.degrees(d_yaw)) < 20)

    hits = total = 0
    for i in range(len(files)):
        if not any(same_place(i, j) for j in range(len(files)) if abs(j - i) > 3):
            continue  # no true revisit of this view in the flight
        best = idx.query(idx.vectors[i], lambda j, i=i: abs(j - i) > 3, 1)  # not the image itself or its neighbours
        hits += bool(best) and same_place(i, best[0][0])
        total += 1
    print(f"recall@1 on revisits: {hits}/{total}")
    assert total >= 5 and hits >= 0.5 * total


def _closer_with_landmark_image(loop_flight):
    """A loop stage that closes on one seen place (exclude_recent_s 1, min_consistent 1), one of the flight's
    images, and its FeatureFrame with every corner a stereo point 3 m away, so that the image carries landmarks."""
    import cv2

    from vio.config import LoopConfig
    from vio.io.euroc import EurocDataset
    from vio.loop.closer import LoopCloser
    from vio.types import FeatureFrame

    ds = EurocDataset(loop_flight)
    img = cv2.imread(str(ds.cam0_files[10]), cv2.IMREAD_GRAYSCALE)
    closer = LoopCloser(ds.calibration, LoopConfig(exclude_recent_s=1.0, min_consistent=1))
    uv = closer.extractor.extract(img, FeatureFrame.empty(0, "")).uv
    ff = FeatureFrame(0, np.arange(len(uv)), uv, uv, np.full(len(uv), 3.0), np.ones(len(uv), np.int64))
    return closer, img, ff


def test_false_place_is_refused_by_the_drift_gate(loop_flight):
    """The same image at a place 3 m away (two identical shelves): PnP passes, the drift gate refuses."""
    closer, img, ff = _closer_with_landmark_image(loop_flight)
    closer.add_keyframe(0, np.eye(4), img, ff)
    for k in range(1, 4):  # flying away: 1 m per keyframe, 2 s apart
        closer.add_keyframe(int(2e9 * k), make_T(np.eye(3), [1.0 * k, 0, 0]), np.zeros_like(img), None)
    assert not closer.add_keyframe(int(8e9), make_T(np.eye(3), [3.0, 0, 0]), img, ff)
    assert closer.stats.refused["drift gate"] == 1 and closer.stats.accepted == 0, closer.stats.refused


def test_spacing_takes_a_hovering_keyframe_only_every_spacing_s_and_always_the_one_after_a_reset(loop_flight):
    """With [loop] spacing_m set, a keyframe joins the loop stage once it is that far, spacing_deg turned or
    spacing_s later than the last one taken: a hover (keyframes every 0.4 s at one pose) adds one view every 2 s
    instead of five; slow flight (0.1 m per keyframe) one in two at 0.15 m; the first after an estimator reset is
    always taken (a new odometry segment needs its node). With spacing_m 0 (the default) every one is taken."""
    import dataclasses

    closer, img, ff = _closer_with_landmark_image(loop_flight)
    cfg = dataclasses.replace(closer.cfg, spacing_m=0.15, spacing_deg=5.0, spacing_s=2.0)
    closer.cfg = cfg
    for k in range(26):  # 10 s of hover
        closer.add_keyframe(int(0.4e9 * k), np.eye(4), img, ff)
    assert [round(k.t_ns * 1e-9, 1) for k in closer.keyframes] == [0.0, 2.0, 4.0, 6.0, 8.0, 10.0]
    assert closer.stats.spaced_out == 20 and closer.stats.keyframes == 6
    t = int(10.4e9)
    for k in range(1, 9):  # 0.1 m per keyframe
        closer.add_keyframe(t + int(0.4e9 * k), make_T(np.eye(3), [0.1 * k, 0, 0]), img, ff)
    assert [round(float(closer.graph.odom[n][0, 3]), 1) for n in range(6, len(closer.keyframes))] == [0.2, 0.4, 0.6,
                                                                                                        0.8]
    turned = make_T(so3_exp(np.radians([0, 0, 6.0])), [0.8, 0, 0])  # 6 deg, no travel
    closer.add_keyframe(t + int(4e9), turned, img, ff)
    assert len(closer.keyframes) == 11
    closer.add_keyframe(t + int(4.4e9), turned, img, ff, reset_counter=1)  # same place, after a reset
    assert len(closer.keyframes) == 12 and closer.keyframes[-1].session == 1
    from vio.io.euroc import EurocDataset

    every = type(closer)(EurocDataset(loop_flight).calibration, dataclasses.replace(cfg, spacing_m=0.0))
    for k in range(5):
        every.add_keyframe(int(0.4e9 * k), np.eye(4), img, ff)
    assert len(every.keyframes) == 5 and every.stats.spaced_out == 0


def test_so3_exp_of_one_vector_is_scipys_to_the_bit():
    """geometry.so3_exp's closed form for one vector (the loop stage's edge mean, the front end's gyro prediction)
    must give scipy's matrix exactly, or the loop stage's edges and the odometry would move: both sides of the
    small-angle series, the series' own edge, zero, a half turn, and what is not finite (scipy's answer)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(7)
    vecs = [rng.normal(size=(20000, 3)) * s for s in (1e-7, 3e-4, 5.8e-4, 1e-3, 0.02, 0.5, 2.0)]
    vecs.append(np.array([[0.0, 0.0, 0.0], [1e-3, 0.0, 0.0], [0.0, np.nextafter(1e-3, 1.0), 0.0], [0.0, 0.0, np.pi],
                          [1e-300, 0.0, 0.0], [-3.0, 2.0, 1.0]]))
    for V in vecs:
        ref = Rotation.from_rotvec(V).as_matrix()
        mine = np.array([so3_exp(v) for v in V])
        assert mine.tobytes() == ref.tobytes(), np.argwhere(mine != ref)[:3]  # bytes: -0.0 too
    for bad in ([np.nan, 0.0, 0.0], [np.inf, 0.0, 0.0]):
        with np.errstate(invalid="ignore"):
            np.testing.assert_array_equal(so3_exp(np.array(bad)), Rotation.from_rotvec(bad).as_matrix())
    np.testing.assert_array_equal(so3_exp(vecs[4][:5]), Rotation.from_rotvec(vecs[4][:5]).as_matrix())  # a stack


def test_inv_T_of_one_transform_is_the_stacks_einsum_to_the_bit():
    """geometry.inv_T's path for one 4x4 must give the bytes the stacked path (einsum) gives, -0.0 included (a zero
    translation under a rotation with negative entries), or loop edges and odometry would move."""
    from scipy.spatial.transform import Rotation

    from vio.geometry import inv_T

    rng = np.random.default_rng(5)
    n = 20000
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=2).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3)) * rng.choice([0.0, -0.0, 1e-3, 1.0, 100.0], size=(n, 1))
    T[::5, :3, :3] = [[-0.6, 0.8, 0.0], [-0.8, -0.6, 0.0], [-0.0, 0.0, 1.0]]
    T[::7, 1, 3] = -0.0
    stacked = inv_T(T)  # the einsum path
    one = np.array([inv_T(t) for t in T])
    assert one.tobytes() == stacked.tobytes(), np.argwhere(one != stacked)[:3]
    t = stacked[:, :3, 3]
    assert (np.signbit(t) & (t == 0)).any()  # the -0.0 case is in the sample
    # a column-major pose (gtsam's) keeps the general path: einsum sums it in another order, in its memory order
    for k in range(0, n, 97):
        F = np.asfortranarray(T[k])
        ref = stacked[k].copy()
        ref[:3, 3] = -np.einsum("ij,j->i", F[:3, :3].T, F[:3, 3])
        assert inv_T(F).tobytes(order="A") == np.asfortranarray(ref).tobytes(order="A") and inv_T(F).flags.f_contiguous


def test_bench_recording_refeeds_to_the_same_results_and_its_digest_sees_a_change(laps_flight, tmp_path):
    """bench/loop_closure.py --record / --refeed-timing, the check that a faster loop stage decides exactly as the
    one before: the recorded keyframes re-fed twice give the same digest and a CPU-time cost; one edge weighted
    differently, or one keyframe's pixel moved by one ulp, gives another digest."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.loop_closure import _Recorder, loop_digest, record, refeed_timing
    from vio.loop.closer import LoopCloser

    pkl = record(None, tmp_path, (376, 240), "room", laps_flight, None, tmp_path / "rec")
    rows = refeed_timing([pkl], 2)
    assert [r["run"] for r in rows] == [0, 1] and rows[0]["digest"] == rows[1]["digest"]
    assert rows[0]["accepted"] >= 1 and rows[0]["searched"] > 10 and rows[0]["detect_cpu_ms_mean"] > 0
    import pickle

    d = pickle.loads(pkl.read_bytes())
    rec = _Recorder()
    rec.items, rec.settles = d["items"], d["settles"]
    cl = LoopCloser(d["calibration"], d["loop"])
    rec.feed(cl)
    assert loop_digest(cl) == rows[0]["digest"]
    e = next(e for e in cl.graph.edges if e.kind == "loop")
    w = e.weight
    e.weight = np.nextafter(w, -np.inf)
    assert loop_digest(cl) != rows[0]["digest"]
    e.weight = w
    assert loop_digest(cl) == rows[0]["digest"]
    uv = cl.keyframes[3].feats.uv
    uv[0, 0] = np.nextafter(uv[0, 0], np.inf)
    assert loop_digest(cl) != rows[0]["digest"]


def test_replay_with_loop_closure_writes_both_trajectories_and_leaves_odometry_alone(laps_flight, tmp_path, capsys):
    from vio.app.cli import main

    out = {}
    for name, extra in (("off", []), ("on", ["--loop-output", str(tmp_path / "loop.tum"),
                                             "--save-map", str(tmp_path / "map.npz"),
                                             "--loop-plot", str(tmp_path / "loop.png")])):
        stats = tmp_path / f"{name}.json"
        assert main(["replay", str(laps_flight), "-o", str(tmp_path / f"{name}.tum"), "--stats", str(stats),
                     "--no-progress", *extra]) == 0
        import json

        out[name] = json.loads(stats.read_text())
    assert (tmp_path / "off.tum").read_bytes() == (tmp_path / "on.tum").read_bytes()
    loop = out["on"]["loop"]
    assert loop["accepted"] >= 1 and loop["switched_off"] == 0 and loop["dropped"] == 0 and loop["error"] is None
    assert loop["detect_ms_mean"] > 0 and loop["graph_ms_mean"] > 0  # the two costs, each on its own
    # a 36 s flight drifts about 1 cm, the size of a loop edge's own error: no accuracy claim here (bench/)
    odom = out["on"]["evaluation"]["ate_4dof"]["trans_m"]["rmse"]
    assert loop["evaluation"]["ate_4dof"]["trans_m"]["rmse"] < 3 * odom
    assert set(loop["end_drift_m"]) == {"odometry", "loop"} and 0 <= loop["end_drift_m"]["loop"] < 0.5
    assert (tmp_path / "loop.png").stat().st_size > 10_000  # the plot with its loop edges
    assert (tmp_path / "loop.tum").read_text().count("\n") == (tmp_path / "on.tum").read_text().count("\n")
    # the map: a versioned npz that `vio map info` reads, and a flight relocalises in (here the same one:
    # the mechanics; docs/loop-closure.md has the figures for a second flight with another start)
    from vio.loop.mapfile import load_map

    m = load_map(tmp_path / "map.npz")
    assert m.header["format"] == "kestrel-vio-map" and m.header["version"] == 1
    assert m.header["keyframes"] == loop["keyframes"] == len(m.features) == len(m.t_ns)
    assert main(["map", "info", str(tmp_path / "map.npz")]) == 0
    stats = tmp_path / "reloc.json"
    assert main(["replay", str(laps_flight), "--load-map", str(tmp_path / "map.npz"), "--max-frames", "300",
                 "--loop-output", str(tmp_path / "reloc.tum"), "--stats", str(stats), "--no-progress"]) == 0
    import json

    r = json.loads(stats.read_text())["loop"]["relocalisation"]
    assert r["relocalised"] and r["delay_s"] < 5.0
    out = capsys.readouterr().out
    assert "relocalisation: placed in the map" in out and "loop-corrected trajectory is in the map's frame" in out
    assert "refused: " in out and "{" not in out.split("loop closure:")[-1].splitlines()[0]  # words, not a dict
    assert "pose graph " in out.split("loop closure:")[-1].splitlines()[0]

    # a map that cannot be read stops the replay before any output file is opened: the old trajectory stays
    old = tmp_path / "keep.tum"
    old.write_text("# an earlier flight\n")
    bad = tmp_path / "bad.npz"
    bad.write_bytes((tmp_path / "map.npz").read_bytes()[:5000])  # a copy cut short
    assert main(["replay", str(laps_flight), "--load-map", str(bad), "-o", str(old), "--no-progress"]) == 1
    assert old.read_text() == "# an earlier flight\n"
    assert "truncated" in capsys.readouterr().err


def test_replay_checks_every_output_path_before_it_replays(laps_flight, tmp_path, capsys):
    """A typo in one output path used to surface after the whole replay and lose the map, stats and plot with it."""
    from vio.app.cli import main

    for bad, says in ((["--loop-output", str(tmp_path / "nodir" / "loop.tum")], "folder"),
                      (["--stats", str(tmp_path)], "is a folder"),
                      (["--loop-plot", str(tmp_path / "nodir" / "p.png")], "does not exist")):
        assert main(["replay", str(laps_flight), "--loop", "--save-map", str(tmp_path / "m.npz"), "-o",
                     str(tmp_path / "o.tum"), "--no-progress", *bad]) == 1
        out, err = capsys.readouterr()
        assert says in err and "replay:" not in out  # refused before the replay (which prints its summary)
        assert not (tmp_path / "m.npz").exists() and not (tmp_path / "o.tum").exists()
    # one file named twice: the map over the trajectory (or over a map it only loads) lost one of them, exit 0
    (tmp_path / "old.npz").write_bytes(b"a map")
    for args, says in ((["-o", str(tmp_path / "same"), "--save-map", str(tmp_path / "same")],
                        "the trajectory and the map would be written to the same file"),
                       (["-o", str(tmp_path / "old.npz"), "--load-map", str(tmp_path / "old.npz")],
                        "the trajectory would be written over the map it loads")):
        assert main(["replay", str(laps_flight), "--no-progress", *args]) == 1
        assert says in capsys.readouterr().err
        assert not (tmp_path / "same").exists() and (tmp_path / "old.npz").read_bytes() == b"a map"


def test_a_map_name_too_long_for_its_temporary_is_refused_before_the_work(tmp_path, capsys):
    """A map is written beside its name as .NAME.PID.tmp and renamed over it: a name of 245-255 bytes passed the
    start checks, and `vio replay --save-map` replayed the whole recording to end in "cannot write the map (File
    name too long); nothing written", while `vio run` said OK and failed every checkpoint and its final save in
    flight (a review's finding). Refused before any work, in both."""
    from vio.app.cli import main

    name = str(tmp_path / ("m" * 246 + ".npz"))  # 250 bytes: a valid name, its temporary is not
    assert main(["replay", str(tmp_path / "no-recording"), "--save-map", name, "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "is too long" in err and "shorter name" in err and "internal error" not in err, err
    (tmp_path / "c.toml").write_text(f"[map]\nsave = '{name}'\n")
    assert main(["-q", "config", "check", str(tmp_path / "c.toml")]) == 3
    assert "is too long" in capsys.readouterr().err
    ok = str(tmp_path / ("m" * 200 + ".npz"))
    (tmp_path / "c.toml").write_text(f"[map]\nsave = '{ok}'\n")
    assert main(["-q", "config", "check", str(tmp_path / "c.toml")]) == 0


def test_replay_refuses_a_loop_plot_format_it_cannot_write_before_it_replays(tmp_path, capsys):
    """`--loop-plot run.txt` ran the whole replay, wrote the map and stats, then ended in "internal error:
    ValueError: Format 'txt' is not supported". Now refused first, in one line."""
    from vio.app.cli import main
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "flight"
    simulate(data, SimConfig(duration_s=1.0, width=376, height=240, variant="clean"), progress=False)
    assert main(["replay", str(data), "--loop-plot", str(tmp_path / "run.txt"), "--save-map",
                 str(tmp_path / "m.npz"), "--no-progress"]) == 1
    out = capsys.readouterr()
    assert "a plot cannot be written as .txt" in out.err and "internal error" not in out.err
    assert "replay:" not in out.out and not (tmp_path / "m.npz").exists()


def test_a_flight_without_keyframes_does_not_save_an_empty_map_over_the_one_there(tmp_path, capsys):
    """A flight that made no keyframe (never initialised; a daemon stopped before its sensors came up) saved a map
    of 0 keyframes, which load_map refuses as damaged, over the map file there: `[map] save` lost the room's map
    on a restart at boot. Now nothing is written, the old map is kept and said to be."""
    from vio import VioError
    from vio.app.cli import main
    from vio.config import VioConfig
    from vio.loop.closer import LoopCloser
    from vio.sim import default_calibration
    from vio.sim.generate import SimConfig, simulate

    room = tmp_path / "room.npz"
    room.write_bytes(b"the room's map")
    cl = LoopCloser(default_calibration(), VioConfig().loop)
    with pytest.raises(VioError, match="this flight made no keyframe.*no map to save; the map that was there is kept"):
        cl.save_map(room)
    assert room.read_bytes() == b"the room's map"
    with pytest.raises(VioError, match="nothing written"):
        cl.save_map(tmp_path / "new.npz")
    assert not (tmp_path / "new.npz").exists()

    data = tmp_path / "flight"
    simulate(data, SimConfig(duration_s=1.0, width=376, height=240, variant="clean"), progress=False)
    assert main(["replay", str(data), "--save-map", str(room), "--overwrite-map", "--max-frames", "5", "--stats",
                 str(tmp_path / "s.json"), "--no-progress"]) == 1
    assert "map that was there is kept" in capsys.readouterr().err
    assert room.read_bytes() == b"the room's map" and (tmp_path / "s.json").exists()


def test_save_map_refuses_a_map_it_did_not_load_and_writes_through_a_link(tmp_path, capsys):
    """`vio replay --save-map room.npz` without `--load-map room.npz` replaced the room's map (the work of every
    flight that grew it) with this flight's alone, unsaid. Now refused before any work, one line, unless
    --overwrite-map; loading and saving the same file (by any name) grows it as before. And a map saved over a
    link replaced the link with a file, leaving the map it named (the one loaded through it) as it was: the save
    now goes through the link."""
    from vio.app.cli import main
    from vio.loop.mapfile import load_map
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "flight"
    simulate(data, SimConfig(duration_s=3.0, width=320, height=200, variant="clean", still_start_s=1.0),
             progress=False)
    room, tum = tmp_path / "room.npz", tmp_path / "old.tum"
    assert main(["replay", str(data), "--save-map", str(room), "--no-progress"]) == 0
    first = room.read_bytes()
    n_first = len(load_map(room).features)
    capsys.readouterr()
    tum.write_text("# an earlier flight\n")
    for cfg in (None, tmp_path / "save.toml"):  # the option, and [map] save in the configuration
        args = ["--save-map", str(room)] if cfg is None else ["--config", str(cfg)]
        if cfg is not None:
            cfg.write_text(f'[map]\nsave = "{room}"\n')
        assert main(["replay", str(data), *args, "-o", str(tum), "--no-progress"]) == 1
        out, err = capsys.readouterr()
        assert len(err.strip().splitlines()) == 1 and "a file is there already and this replay does not load it: " \
            "not replaced" in err and "--overwrite-map" in err, err
        assert "replay:" not in out and room.read_bytes() == first and tum.read_text() == "# an earlier flight\n"
    # grown: the map it loads, by another name too
    alias = tmp_path / "alias.npz"
    alias.symlink_to(room)
    assert main(["replay", str(data), "--load-map", str(alias), "--save-map", str(room), "--no-progress"]) == 0
    assert len(load_map(room).features) > n_first
    # through a link: the link stays a link, and the map it names is the one grown
    maps = tmp_path / "maps"
    maps.mkdir()
    (maps / "room.npz").write_bytes(first)
    link = tmp_path / "link.npz"
    link.symlink_to(maps / "room.npz")
    assert main(["replay", str(data), "--load-map", str(link), "--save-map", str(link), "--no-progress"]) == 0
    assert link.is_symlink() and link.resolve() == (maps / "room.npz").resolve()
    assert len(load_map(maps / "room.npz").features) > n_first
    assert sorted(p.name for p in maps.iterdir()) == ["room.npz"]  # no temporary file left beside it
    # --overwrite-map replaces a map it did not load, through a link too
    assert main(["replay", str(data), "--save-map", str(link), "--overwrite-map", "--max-frames", "30",
                 "--no-progress"]) == 0
    assert link.is_symlink() and len(load_map(maps / "room.npz").features) < n_first
    assert main(["replay", str(data), "--save-map", str(room), "--overwrite-map", "--max-frames", "30",
                 "--no-progress"]) == 0
    assert len(load_map(room).features) < n_first


def test_a_map_saved_through_a_link_is_checked_where_the_link_points_before_any_work(tmp_path, monkeypatch,
                                                                                     capsys):
    """A map is written through a link, beside the file it names; the folder checked before the replay was the
    link's own. A link into a folder that is not there (or not writable) passed, the whole flight was replayed,
    and the save failed at its end ("cannot write the map (No such file or directory)"). Refused first now, in
    one line, by `vio replay` and by `vio run`'s configuration check."""
    import vio.app.replay as replay_mod
    from vio import VioError
    from vio.app.cli import main
    from vio.app.daemon.service import check_run_config
    from vio.config import config_from_dict

    def never(*a, **k):
        raise AssertionError("the recording was opened before the map's folder was checked")

    monkeypatch.setattr(replay_mod, "open_dataset", never)
    (tmp_path / "flight").mkdir()
    link = tmp_path / "link.npz"
    link.symlink_to(tmp_path / "gone" / "room.npz")
    assert main(["replay", str(tmp_path / "flight"), "--save-map", str(link), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{link}: cannot write the map (a link to {tmp_path / 'gone' / 'room.npz'}): folder " \
        f"{tmp_path / 'gone'} does not exist" in err[0], err
    cfg = config_from_dict({"source": {"kind": "fake"}, "map": {"save": str(link)}})
    with pytest.raises(VioError, match=r"\[map\] save: .*link\.npz: cannot write the map \(a link to .*folder .*gone "
                       "does not exist"):
        check_run_config(cfg, warn=lambda m: None)


def test_a_map_is_never_saved_over_a_file_the_run_reads_but_the_map_it_grows(tmp_path, capsys):
    """`vio replay --calibration rig.yaml --save-map rig.yaml` wrote the map over the calibration: the map was allowed
    over any file the run read, as it is over the map it loads. `vio run` checked `[map] save` against nothing it
    reads: over `[source] calibration`, `[loop] vocabulary` or into the EuRoC recording it replays, `vio config
    check` said OK and the daemon wrote the map there at shutdown."""
    from vio.app.cli import main
    from vio.calibration import save_calibration
    from vio.io.euroc import EurocDataset
    from vio.loop.vocabulary import DEFAULT_PATH
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "flight"
    simulate(data, SimConfig(duration_s=1.0, width=376, height=240, variant="clean"), progress=False)
    rig = tmp_path / "rig.yaml"
    save_calibration(EurocDataset(data).calibration, rig)
    before = rig.read_bytes()
    assert main(["replay", str(data), "--calibration", str(rig), "--save-map", str(rig), "--no-progress"]) == 1
    out = capsys.readouterr()
    assert "the map would be written over the calibration" in out.err and "replay:" not in out.out
    assert rig.read_bytes() == before

    voc = tmp_path / "voc.npz"
    voc.write_bytes(DEFAULT_PATH.read_bytes())
    src = f"[source]\nkind = 'euroc'\ndataset = '{data}'\n"
    for text, says in ((f"{src}calibration = '{rig}'\n[map]\nsave = '{rig}'\n", "over [source] calibration"),
                       (f"{src}[loop]\nenabled = true\nvocabulary = '{voc}'\n[map]\nsave = '{voc}'\n",
                        "over [loop] vocabulary"),
                       (f"{src}[map]\nsave = '{data / 'mav0' / 'imu0' / 'data.csv'}'\n", "into the recording")):
        cfg = tmp_path / "c.toml"
        cfg.write_text(text)
        assert main(["config", "check", str(cfg)]) == 3, text
        assert says in capsys.readouterr().err, text
    cfg.write_text(f"{src}[map]\nsave = '{data / 'room.npz'}'\n")  # beside the recording's mav0/: allowed
    assert main(["-q", "config", "check", str(cfg)]) == 0


def test_saved_map_leaves_out_segments_never_joined_to_its_frame(loop_flight, tmp_path):
    """An estimator reset starts an odometry segment in a frame of its own; until a loop edge joins it to the
    first one its poses mean nothing in the map's frame, so the map must not hold them."""
    import cv2

    from vio.config import LoopConfig
    from vio.io.euroc import EurocDataset
    from vio.loop.closer import LoopCloser
    from vio.loop.mapfile import load_map

    ds = EurocDataset(loop_flight)
    closer = LoopCloser(ds.calibration, LoopConfig())
    img = cv2.imread(str(ds.cam0_files[10]), cv2.IMREAD_GRAYSCALE)
    for k in range(6):  # 3 keyframes, a reset, 3 more (no stereo points: no closure can join them)
        closer.add_keyframe(int(1e9 * k), make_T(np.eye(3), [0.5 * k, 0, 0]), img, None, reset_counter=k // 3)
    h = closer.save_map(tmp_path / "m.npz")
    m = load_map(tmp_path / "m.npz")
    assert h["left_out_keyframes"] == 3 and len(m.features) == 3 and list(m.t_ns) == [0, int(1e9), int(2e9)]
    assert "never joined" in m.header["note"]
    # a flight that never relocalised in a loaded map adds nothing to it when saved again
    again = LoopCloser(ds.calibration, LoopConfig())
    again.load_map(m)
    again.add_keyframe(int(9e9), np.eye(4), np.zeros_like(img), None)
    assert again.save_map(tmp_path / "m2.npz")["left_out_keyframes"] == 1
    assert len(load_map(tmp_path / "m2.npz").features) == 3


def test_a_map_grown_by_flights_over_the_same_place_keeps_only_new_views(loop_flight, tmp_path):
    """A map saved after every flight in one warehouse grew by each flight's whole length (a hover added a
    keyframe every 2 s at one spot). With [map] prune_m, a keyframe is saved only if no kept one (the loaded
    map's, or this flight's before it) saw from within prune_m and prune_deg; the loaded map's all stay."""
    import cv2

    from vio.config import LoopConfig
    from vio.io.euroc import EurocDataset
    from vio.loop.closer import LoopCloser
    from vio.loop.mapfile import load_map

    def yaw(deg: float) -> np.ndarray:
        return so3_exp(np.r_[0.0, 0.0, np.radians(deg)])

    ds = EurocDataset(loop_flight)
    img = cv2.imread(str(ds.cam0_files[10]), cv2.IMREAD_GRAYSCALE)
    first = LoopCloser(ds.calibration, LoopConfig())
    # a hover (four keyframes 2 s apart within 5 cm and 3 deg), a move of 0.5 m, a 30 deg turn on the spot
    poses = [make_T(yaw(0), [0, 0, 0]), make_T(yaw(3), [0.05, 0, 0]), make_T(yaw(-2), [0, 0.04, 0]),
             make_T(yaw(1), [0.02, 0.02, 0]), make_T(yaw(0), [0.5, 0, 0]), make_T(yaw(30), [0.5, 0, 0])]
    for k, T in enumerate(poses):
        first.add_keyframe(int(2e9 * k), T, img, None)
    assert first.save_map(tmp_path / "all.npz")["pruned_keyframes"] == 0  # off by default
    h = first.save_map(tmp_path / "m.npz", prune_m=0.15, prune_deg=10)
    m = load_map(tmp_path / "m.npz")
    assert h["pruned_keyframes"] == 3 and list(m.t_ns) == [0, int(8e9), int(10e9)]
    assert h["keyframes"] == 3 and m.header["parts"] == [{"keyframes": 3, "join_edges": None}]

    again = LoopCloser(ds.calibration, LoopConfig())
    again.load_map(m)
    for k, T in enumerate([make_T(yaw(2), [0.03, 0, 0]), make_T(yaw(0), [1.5, 0, 0]),
                           make_T(yaw(4), [1.52, 0, 0])]):
        again.add_keyframe(int(20e9 + 2e9 * k), T, img, None)
    again._join(1, 0)  # as a loop edge would: this flight relocalised in the map
    h = again.save_map(tmp_path / "m2.npz", prune_m=0.15, prune_deg=10)
    m2 = load_map(tmp_path / "m2.npz")
    # the map's three stay; of the flight only the new place (1.5 m) is saved, once
    assert h["pruned_keyframes"] == 2 and list(m2.t_ns) == [0, int(8e9), int(10e9), int(22e9)]
    assert [p["keyframes"] for p in m2.header["parts"]] == [3, 1]


def test_two_flights_growing_one_map_at_once_keep_both(loop_flight, tmp_path):
    """Two runs load m.npz and save over it: the later save used to drop the earlier one's flight, unsaid. Now a
    save finds the file changed since its run loaded it and writes beside it, keeping both."""
    import cv2

    from vio.config import LoopConfig
    from vio.io.euroc import EurocDataset
    from vio.loop.closer import LoopCloser
    from vio.loop.mapfile import load_map

    ds = EurocDataset(loop_flight)
    img = cv2.imread(str(ds.cam0_files[10]), cv2.IMREAD_GRAYSCALE)
    first = LoopCloser(ds.calibration, LoopConfig())
    for k in range(3):
        first.add_keyframe(int(1e9 * k), make_T(np.eye(3), [0.5 * k, 0, 0]), img, None)
    first.save_map(tmp_path / "m.npz")
    a, b = (LoopCloser(ds.calibration, LoopConfig()) for _ in range(2))
    a.load_map(load_map(tmp_path / "m.npz"))
    b.load_map(load_map(tmp_path / "m.npz"))
    ha = a.save_map(tmp_path / "m.npz")
    assert ha["path"] == str(tmp_path / "m.npz") and not ha["conflict"]
    assert a.save_map(tmp_path / "m.npz")["conflict"] == ""  # its own earlier save is no conflict
    before = (tmp_path / "m.npz").read_bytes()
    hb = b.save_map(tmp_path / "m.npz")
    assert "changed since this flight loaded it" in hb["conflict"] and hb["path"] != str(tmp_path / "m.npz")
    assert (tmp_path / "m.npz").read_bytes() == before and len(load_map(hb["path"]).features) == 3


def test_a_checkpointed_map_changed_by_another_run_is_kept_and_later_saves_go_to_one_name_beside(loop_flight,
                                                                                                 tmp_path):
    """`vio run` checkpoints its map into a file it did not load: a file another run saved over it in between
    is kept (as a map changed since it was loaded), and this run's checkpoints and final save go beside it, all
    to one name (not a new file every checkpoint). The checkpoint is marked in the header; the final save not."""
    import cv2

    from vio.config import LoopConfig
    from vio.io.euroc import EurocDataset
    from vio.loop.closer import LoopCloser
    from vio.loop.mapfile import load_map, run_identity

    ds = EurocDataset(loop_flight)
    img = cv2.imread(str(ds.cam0_files[10]), cv2.IMREAD_GRAYSCALE)
    run, other = LoopCloser(ds.calibration, LoopConfig()), LoopCloser(ds.calibration, LoopConfig())
    for k in range(3):
        run.add_keyframe(int(1e9 * k), make_T(np.eye(3), [0.5 * k, 0, 0]), img, None)
        other.add_keyframe(int(1e9 * k), make_T(np.eye(3), [0.5 * k, 0, 0]), img, None)
    path = tmp_path / "m.npz"
    ident = run_identity(None)
    h1 = run.save_map(path, checkpoint=ident)
    assert h1["path"] == str(path) and not h1["conflict"] and load_map(path).header["checkpoint"] == ident
    assert not run.save_map(path, checkpoint=ident)["conflict"]  # its own checkpoint is no conflict
    other.save_map(path)
    theirs = path.read_bytes()
    h2 = run.save_map(path, checkpoint=ident)
    assert "changed since this flight saved it" in h2["conflict"] and h2["path"] != str(path)
    h3 = run.save_map(path)
    assert h3["path"] == h2["path"] and path.read_bytes() == theirs
    assert "checkpoint" not in load_map(h3["path"]).header
    assert len(list(tmp_path.iterdir())) == 2


def test_saved_map_counts_the_loop_edges_that_placed_each_part_and_warns_of_a_weak_one(loop_flight, tmp_path,
                                                                                      caplog, capsys):
    """A segment after an estimator reset that closes on the first one through 3 edges is saved (it is in the
    map's frame), but the header says by how many edges each part is placed, the save warns that this one rests
    on few, and `vio map info` shows it; a map saved again after loading keeps the parts it had."""
    from vio.app.cli import main
    from vio.loop.closer import WEAK_JOIN_EDGES
    from vio.loop.mapfile import load_map

    closer, img, ff = _closer_with_landmark_image(loop_flight)
    closer.add_keyframe(0, np.eye(4), img, ff)
    for k in range(1, 4):  # away from the place, nothing to close on
        closer.add_keyframe(int(2e9 * k), make_T(np.eye(3), [1.0 * k, 0, 0]), np.zeros_like(img), None)
    for k in range(4):  # an estimator reset: a new origin 5 m off, back at the first place
        closer.add_keyframe(int(10e9 + 1e9 * k), make_T(np.eye(3), [5.0 + 0.01 * k, 0, 0]), img, ff, reset_counter=1)
    assert closer.relocalised_t_ns is None and closer.keyframes[-1].session == 1  # no loaded map: joins session 0
    joins = closer._join_edges(1)
    assert 1 <= joins < WEAK_JOIN_EDGES
    with caplog.at_level("WARNING", logger="vio.loop.closer"):
        closer.save_map(tmp_path / "m.npz")
    m = load_map(tmp_path / "m.npz")
    # the fourth keyframe after the reset came once the segment was joined, 1 cm from the third: spaced out
    assert m.header["parts"] == [{"keyframes": 4, "join_edges": None}, {"keyframes": 3, "join_edges": joins}]
    assert f"joined to the rest by only {joins} loop edges" in caplog.text and "rests on them" in m.header["note"]
    assert main(["map", "info", str(tmp_path / "m.npz")]) == 0
    out = capsys.readouterr().out
    assert "part 1: 4 keyframes over 6.0 s, the frame's origin" in out and "part 2: 3 keyframes over" in out
    assert f"joined by {joins}" in out
    # each part's time is its own (a grown map's parts are flights on clocks of their own), summed
    span2 = (m.t_ns[-1] - m.t_ns[4]) * 1e-9
    assert f"7 keyframes over {6.0 + span2:.1f} s of flight in 2 parts" in out, out
    assert "weak" in out
    again = type(closer)(_calib(loop_flight), closer.cfg)
    again.load_map(m)
    again.save_map(tmp_path / "m2.npz")
    assert load_map(tmp_path / "m2.npz").header["parts"] == m.header["parts"]


def _calib(flight):
    from vio.io.euroc import EurocDataset

    return EurocDataset(flight).calibration


def test_map_file_refuses_other_formats(tmp_path, capsys):
    from vio import VioError
    from vio.app.cli import main
    from vio.loop.mapfile import load_map

    (tmp_path / "random.kmap").write_bytes(np.random.default_rng(0).integers(0, 256, 4000, np.uint8).tobytes())
    (tmp_path / "empty.kmap").write_bytes(b"")
    for name, says in (("random.kmap", "not a Kestrel VIO map (not an .npz archive)"),
                       ("empty.kmap", "truncated"), ("", "is a folder"), ("none.kmap", "no such map file")):
        assert main(["map", "info", str(tmp_path / name)]) == 1
        err = capsys.readouterr().err
        assert says in err and "internal error" not in err and "allow_pickle" not in err, err

    # the right header over arrays that do not fit together: refused whole, never loaded with keyframes missing
    cam = '"camera": {"fx": 458.0, "fy": 457.0, "cx": 367.0, "cy": 248.0, "width": 752, "height": 480}'
    hdr = np.array('{"format": "kestrel-vio-map", "version": 1, ' + cam + '}')
    good = dict(header=hdr, kf_offsets=np.array([0, 3, 5]), desc=np.zeros((5, 32), np.uint8), uv=np.zeros((5, 2)),
                p_cam=np.zeros((5, 3)), kf_t_ns=np.array([1, 2]), kf_T_world_body=np.tile(np.eye(4), (2, 1, 1)))
    np.savez(tmp_path / "good.npz", **good)
    assert len(load_map(tmp_path / "good.npz").features) == 2
    for change, says in ((dict(desc=np.zeros((5, 16), np.uint8)), "descriptors"),
                         (dict(kf_offsets=np.array([0, 5, 3])), "offsets"),
                         (dict(kf_T_world_body=np.full((2, 4, 4), np.nan)), "poses"),
                         (dict(kf_T_world_body=np.tile(np.eye(4), (1, 1, 1))), "poses")):
        np.savez(tmp_path / "bad.npz", **{**good, **change})
        with pytest.raises(VioError, match=f"damaged map.*{says}"):
            load_map(tmp_path / "bad.npz")
    # a header whose parts do not split the keyframes (a review's: `vio map info` stopped on an IndexError, and a map
    # grown from it carried the damage on), or without its camera
    for header, says in (('"parts": [{"keyframes": 5, "join_edges": null}], ' + cam, "parts"),
                         ('"parts": [{"keyframes": 1, "join_edges": 2}, {"keyframes": 1, "join_edges": 3}], ' + cam,
                          "parts"),
                         ('"parts": "two", ' + cam, "parts"),
                         ('"parts": [{"keyframes": 1, "join_edges": null}, {"keyframes": "1", "join_edges": 0}], '
                          + cam, "parts"),
                         ('"camera": {"width": 0}', "camera"),
                         (cam.replace("752", "Infinity"), "camera")):
        bad_hdr = np.array('{"format": "kestrel-vio-map", "version": 1, ' + header + '}')
        np.savez(tmp_path / "bad.npz", **{**good, "header": bad_hdr})
        with pytest.raises(VioError, match=f"damaged map.*{says}"):
            load_map(tmp_path / "bad.npz")
        assert main(["map", "info", str(tmp_path / "bad.npz")]) == 1
        err = capsys.readouterr().err
        assert "damaged map" in err and "internal error" not in err, err
    np.savez(tmp_path / "x.npz", header=np.array('{"format": "other", "version": 1}'))
    with pytest.raises(VioError, match="not a Kestrel VIO map"):
        load_map(tmp_path / "x.npz")
    # a header that is not an object, or whose version is not a number: one line, not an AttributeError/TypeError
    for header, says in (("[1]", "not a Kestrel VIO map"),
                         ('{"format": "kestrel-vio-map", "version": null}', "version")):
        np.savez(tmp_path / "z.npz", **{**good, "header": np.array(header)})
        with pytest.raises(VioError, match=says):
            load_map(tmp_path / "z.npz")
    np.savez(tmp_path / "y.npz", header=np.array('{"format": "kestrel-vio-map", "version": 99}'))
    with pytest.raises(VioError, match="newer"):
        load_map(tmp_path / "y.npz")
    # a QA sweep's: a .npy array (TypeError), stamps running back within one flight ("7 keyframes over -7.2 s"),
    # and a header without the informative created_utc / vocabulary (map info's KeyError, TypeError)
    np.save(tmp_path / "arr.npy", np.zeros(3))
    for path, says in ((tmp_path / "arr.npy", "a .npy array"),):
        assert main(["map", "info", str(path)]) == 1
        err = capsys.readouterr().err
        assert says in err and "internal error" not in err, err
    one = '"parts": [{"keyframes": 2, "join_edges": null}], '
    np.savez(tmp_path / "back.npz", **{**good, "kf_t_ns": np.array([2, 1]), "header": np.array(
        '{"format": "kestrel-vio-map", "version": 1, ' + one + cam + '}')})
    with pytest.raises(VioError, match="stamps do not increase within flight 1"):
        load_map(tmp_path / "back.npz")
    # without parts (optional in version 1; maps grown before they existed): several flights' clocks, loaded, and
    # map info says it cannot tell the time flown instead of a negative one (a review's finding)
    np.savez(tmp_path / "old.npz", **{**good, "kf_t_ns": np.array([2, 1])})
    assert len(load_map(tmp_path / "old.npz").features) == 2
    assert main(["map", "info", str(tmp_path / "old.npz")]) == 0
    assert "over an unknown time (stamps of several flights" in capsys.readouterr().out
    two = '"parts": [{"keyframes": 1, "join_edges": null}, {"keyframes": 1, "join_edges": 4}], '
    np.savez(tmp_path / "grown.npz", **{**good, "kf_t_ns": np.array([9, 1]),  # two flights, two clocks: fine
                                        "header": np.array('{"format": "kestrel-vio-map", "version": 1, ' + two + cam
                                                           + ', "vocabulary": "v1"}')})
    assert len(load_map(tmp_path / "grown.npz").features) == 2
    assert main(["map", "info", str(tmp_path / "grown.npz")]) == 0
    out = capsys.readouterr().out
    assert "created at an unknown time" in out and "vocabulary: not stated" in out and "2 keyframes" in out, out



def test_map_info_of_a_header_whose_parts_leave_out_join_edges_or_whose_size_is_fractional(tmp_path, capsys):
    """The loader takes a part without `join_edges` as the frame's origin (None), but `vio map info` then stopped on
    'internal error: KeyError'; a camera 752.5 px wide was loaded and shown as such (sizes are whole pixels)."""
    from vio.app.cli import main

    cam = '"camera": {"fx": 458.0, "fy": 457.0, "cx": 367.0, "cy": 248.0, "width": 752, "height": 480}'
    arrays = dict(kf_offsets=np.array([0, 3, 5]), desc=np.zeros((5, 32), np.uint8), uv=np.zeros((5, 2)),
                  p_cam=np.zeros((5, 3)), kf_t_ns=np.array([1, 2]), kf_T_world_body=np.tile(np.eye(4), (2, 1, 1)))
    head = '{"format": "kestrel-vio-map", "version": 1, '
    np.savez(tmp_path / "m.npz", header=np.array(head + '"parts": [{"keyframes": 2}], ' + cam + '}'), **arrays)
    assert main(["map", "info", str(tmp_path / "m.npz")]) == 0
    assert "part 1: 2 keyframes over 0.0 s, the frame's origin" in capsys.readouterr().out
    np.savez(tmp_path / "f.npz", header=np.array(head + cam.replace("752", "752.5") + '}'), **arrays)
    assert main(["map", "info", str(tmp_path / "f.npz")]) == 1
    err = capsys.readouterr().err
    assert "damaged map (its header has no camera size" in err and "internal error" not in err, err


def test_a_map_whose_version_is_missing_zero_or_negative_is_refused_as_damaged(tmp_path, capsys):
    """Every map ever written says version 1 or more; a header with version 0, a negative one, or none at all was
    loaded as if it said 1 (and `vio map info` printed "version 0"). Refused now, one line, like other damage."""
    from vio.app.cli import main

    cam = '"camera": {"fx": 458.0, "fy": 457.0, "cx": 367.0, "cy": 248.0, "width": 752, "height": 480}'
    arrays = dict(kf_offsets=np.array([0, 3, 5]), desc=np.zeros((5, 32), np.uint8), uv=np.zeros((5, 2)),
                  p_cam=np.zeros((5, 3)), kf_t_ns=np.array([1, 2]), kf_T_world_body=np.tile(np.eye(4), (2, 1, 1)))
    for name, version, says in (("zero", '"version": 0, ', "version 0 is not a map format version"),
                                ("negative", '"version": -3, ', "version -3 is not a map format version"),
                                ("none", "", "states no format version")):
        path = tmp_path / f"{name}.npz"
        np.savez(path, header=np.array('{"format": "kestrel-vio-map", ' + version + cam + '}'), **arrays)
        assert main(["map", "info", str(path)]) == 1
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and f"{path}: damaged map" in err and says in err, err
    np.savez(tmp_path / "one.npz", header=np.array('{"format": "kestrel-vio-map", "version": 1, ' + cam + '}'),
             **arrays)
    assert main(["map", "info", str(tmp_path / "one.npz")]) == 0
    assert "version 1" in capsys.readouterr().out

def test_autopilot_output_modes():
    from vio.loop.output import CorrectedOutput
    from vio.types import NavState

    C = make_T(so3_exp(np.array([0, 0, 0.1])), [1.0, 0, 0])
    st = [NavState(int(k * 1e8), np.eye(4), np.array([1.0, 0, 0])) for k in range(40)]  # 10 Hz, 4 s
    assert CorrectedOutput("off").apply(st[0], C, 1) is st[0]
    jump = CorrectedOutput("jump")
    a, b = jump.apply(st[0], np.eye(4), 0), jump.apply(st[1], C, 1)
    assert a.reset_counter == 0 and b.reset_counter == 1 and np.allclose(b.T_world_body, C)
    assert jump.apply(st[2], C, 1).reset_counter == 1  # one jump per new correction
    blend = CorrectedOutput("blend", blend_rate_m_s=0.5, blend_rate_deg_s=5.0)
    out = [blend.apply(s, C, 1) for s in st]
    x = np.array([o.T_world_body[0, 3] for o in out])
    assert np.all(np.diff(x) <= 0.5 * 0.1 + 1e-9) and x[-1] == pytest.approx(1.0)  # bounded rate, then there
    assert all(o.reset_counter == 0 for o in out) and blend.remaining_m == 0.0
    walk = CorrectedOutput("blend", blend_rate_m_s=0.5, blend_rate_deg_s=5.0)
    walk.apply(st[0], C, 1), walk.apply(st[1], C, 1)  # one 0.1 s step of 0.05 m on a 1 m correction
    assert walk.remaining_m == pytest.approx(np.linalg.norm((C @ st[1].T_world_body)[:3, 3]) - 0.05, abs=0.01)
    # far from the odometry's origin a yaw correction turns the vehicle's position too: the bound holds at the
    # vehicle (hovering 20 m out, a 30 deg correction: it moved at 1.75 m/s with only the translation bounded)
    far = make_T(np.eye(3), [20.0, 0, 0])
    hover = [NavState(int(k * 2e7), far, np.zeros(3)) for k in range(5000)]  # 50 Hz, 100 s
    blend = CorrectedOutput("blend", blend_rate_m_s=0.2, blend_rate_deg_s=5.0)
    C = make_T(so3_exp(np.radians([0, 0, 30.0])), [0.5, -0.3, 0])
    q = np.array([blend.apply(s, C, 1).T_world_body[:3, 3] for s in hover])
    assert np.linalg.norm(np.diff(q, axis=0), axis=1).max() <= 0.2 * 0.02 + 1e-9
    assert np.allclose(q[-1], (C @ far)[:3, 3], atol=1e-6)  # and it gets there (10.5 m at 0.2 m/s: 53 s)


def test_aliasing_room_repeats_its_wall_texture():
    from vio.sim.scene import default_scene

    for plain in (0.0, 0.15):  # the realistic variant's plain patches stay off the repeated walls
        sc = default_scene(seed=1, ppm=50.0, plain_fraction=plain, aliasing_period_m=1.0)
        for f, face in enumerate(sc.faces):
            if face.box != 0 or face.hidden:
                continue
            u = np.linspace(face.u_range[0] + 0.1, face.u_range[1] - 1.2, 50)
            v = np.full_like(u, 0.5 * (face.v_range[0] + face.v_range[1]))
            x = (u * sc.ppm + sc.face_cx[f]).astype(int)
            y = (v * sc.ppm + sc.face_cy[f]).astype(int)
            a, b = sc.atlas[y, x], sc.atlas[y, x + int(sc.ppm)]  # one period apart
            assert np.allclose(a, b) and np.std(a) > 5.0, (plain, f, np.std(a))


def test_wrong_closure_accepted_first_is_switched_off_when_true_ones_arrive():
    """Incremental graph: a false edge to another segment fits (nothing contradicts it yet) and goes into
    iSAM2 on the fast path; true edges that arrive later contradict it, the GNC decision switches it off."""
    g, _ = _circle(80, np.random.default_rng(1))  # segment 0: keyframes 0-79
    truth = _circle(121, np.random.default_rng(2))[1]
    prev = None
    for k in range(80, 121):  # segment 1 (a relocalising flight): same circle, loose prior, 0.5 m off
        T = truth[k] @ make_T(np.eye(3), [0.5, 0.3, 0.0]) if prev is None else \
            g.odom[prev] @ np.linalg.inv(truth[k - 1]) @ truth[k]
        prev = g.add_node(T, prev, prior=(np.pi, 100.0) if prev is None else None)
    false = make_T(so3_exp(np.r_[0, 0, 0.4]), [0.8, -0.5, 0.1]) @ (np.linalg.inv(truth[5]) @ truth[85])
    g.add_loop(5, 85, false)
    r = g.optimize()
    assert not r["decided"] and r["loop_weights"] == [1.0]  # it fits: accepted on the fast path
    for a, b in ((50, 90), (51, 91), (52, 92), (60, 100), (61, 101)):
        g.add_loop(a, b, np.linalg.inv(truth[a]) @ truth[b])
    r = g.optimize()
    assert r["decided"] and r["loop_weights"][0] < 0.5 and min(r["loop_weights"][1:]) >= 0.5
    # the second segment sits where the true edges put it, not where the false one did
    rel = np.linalg.inv(g.estimate[52]) @ g.estimate[92]
    assert np.linalg.norm(rel[:3, 3] - (np.linalg.inv(truth[52]) @ truth[92])[:3, 3]) < 0.02
    assert np.linalg.norm(g.estimate[85][:3, 3] - (g.estimate[5] @ false)[:3, 3]) > 0.5


class _StubCloser:
    """What LoopWorker reads of a LoopCloser, for tests of the worker: no map, the correction `corr` (identity),
    in its own frame, never unconfirmed; tests override what they script."""

    map_keyframes, relocalised = 0, False

    def __init__(self):
        from vio.loop.closer import LoopStats

        self.graph = type("G", (), {"estimate_version": 0})()
        self.stats, self.corr = LoopStats(), np.eye(4)

    def correction(self):
        return self.corr

    def correction_uncertainty(self):
        return None

    def correction_segment(self):
        return 0, True

    def placement_unconfirmed(self):
        return False

    def finish(self):
        self.finished = True


def test_loop_worker_drains_its_queue_before_it_stops():
    """What is queued at close belongs in the map: close(wait) processes it, and says when the thread has
    stopped; out of time, the rest is dropped and counted, and the keyframe in hand is finished."""
    import time

    from vio.app.loop_worker import LoopWorker

    class Slow(_StubCloser):
        def __init__(self, s):
            super().__init__()
            self.s, self.done = s, 0

        def add_keyframe(self, *item):
            time.sleep(self.s)
            self.done += 1
            return False

    w = LoopWorker(Slow(0.02), max_queue=100)
    for k in range(10):
        w.submit(k, np.eye(4), None, None, 0)
    assert w.close(wait=True, timeout_s=5.0) and w.closer.done == 10 and w.dropped == 0 and w.closer.finished

    class FailsAtTheEnd(Slow):
        def finish(self):
            raise RuntimeError("indeterminate linear system")

    w = LoopWorker(FailsAtTheEnd(0.0), max_queue=100)  # the thread stops all the same, the error is kept
    w.submit(0, np.eye(4), None, None, 0)
    assert w.close(wait=True, timeout_s=5.0) and "indeterminate" in w.error
    w = LoopWorker(Slow(0.2), max_queue=100)
    for k in range(10):
        w.submit(k, np.eye(4), None, None, 0)
    assert w.close(wait=True, timeout_s=0.3, grace_s=1.0)
    assert w.closer.done + w.dropped == 10 and w.dropped >= 5


def test_a_join_not_confirmed_yet_is_not_handed_to_the_output():
    """A first join can be a look-alike place (a repeated room: 25 of 100 second flights output 0.5 m or more off
    for a while): while the loop stage says the placement is unconfirmed (fewer than output_join_edges), the worker
    keeps the correction it handed over, its version too; then it hands the new one over."""
    from vio.app.loop_worker import LoopWorker
    from vio.config import LoopConfig

    class Closer(_StubCloser):
        map_keyframes, relocalised, cfg, unconfirmed = 5, True, LoopConfig(), True

        def add_keyframe(self, *item):
            self.graph.estimate_version += 1
            self.corr = make_T(np.eye(3), [1.5, 0.0, 0.0])  # the join's frame
            return True

        def correction_segment(self):
            return 1, False

        def placement_unconfirmed(self):
            return self.unconfirmed

    c = Closer()
    w = LoopWorker(c, max_queue=10)
    w.submit(1, np.eye(4), None, None, 0)
    w._q.join()
    T, version, *_ = w.correction()
    assert np.allclose(T, np.eye(4)) and version == 0
    c.unconfirmed = False
    w.submit(2, np.eye(4), None, None, 0)
    w._q.join()
    T, version, *_ = w.correction()
    assert T[0, 3] == 1.5 and version == 2
    assert w.close(wait=True, timeout_s=5.0)


def test_the_correction_gets_a_new_version_when_it_moves_without_a_closure():
    """Loop edges the pose graph deferred (quick fits) reach the estimate at a later keyframe that closes nothing:
    the worker hands that correction out as a new version, so `[loop] output = jump` takes it; a keyframe that
    neither closes nor re-solves keeps the version, also when a new odometry segment resets the correction."""
    from vio.app.loop_worker import LoopWorker
    from vio.geometry import make_T

    class Closer(_StubCloser):
        def __init__(self):  # (closure accepted, graph re-solved, correction x)
            super().__init__()
            self.script = iter([(False, 0, 0.0), (True, 1, 0.1), (False, 1, 0.1), (False, 2, 0.12), (False, 2, 0.0)])

        def add_keyframe(self, *item):
            closed, self.graph.estimate_version, x = next(self.script)
            self.corr = make_T(np.eye(3), np.array([x, 0.0, 0.0]))
            return closed

    w = LoopWorker(Closer(), max_queue=10)
    versions = []
    for k in range(5):
        w.submit(k, np.eye(4), None, None, 0)
        w._q.join()
        versions.append(w.correction()[1])
    assert w.close(wait=True, timeout_s=5.0)
    # the last: a new odometry segment (an estimator reset) whose correction starts at identity, no solve
    assert versions == [0, 1, 1, 2, 2] and w.closures == 1


def test_vio_run_with_loop_closure_saves_a_map_on_sigterm(tmp_path):
    """The daemon with `[loop] enabled` and `[map] save`: on SIGTERM the loop thread drains its queue, the map
    is written, and `vio map info` reads it back with keyframes in it."""
    import json
    import subprocess
    import sys

    from test_service import REPO, _need_pipeline, fly_fake

    _need_pipeline()
    map_path = tmp_path / "room.map.npz"
    def fly(folder, loop: str, map_line: str) -> tuple[int, str]:
        return fly_fake(folder, f"""[source]
kind = "fake"
realtime = false
fake_duration_s = 6.0
width = 320
height = 200
[run]
status_file = "{folder / 'status.json'}"
[loop]
enabled = true
{loop}
[map]
{map_line}
""", 30)

    rc, text = fly(tmp_path, "", f'save = "{map_path}"')
    assert rc == 0 and "Traceback" not in text, text[-3000:]
    assert "map saved to" in text and map_path.is_file(), text[-3000:]
    # the loop stage's state in the health line and the status file (edges, no map loaded: no relocalisation)
    assert " | loop " in text and " edges" in text, text[-3000:]
    status = json.loads((tmp_path / "status.json").read_text())
    assert status["loop"]["output"] == "off" and status["loop"]["relocalised"] is None
    assert status["loop"]["keyframes"] > 0 and status["loop"]["loop_jumps"] == 0 and status["loop"]["error"] is None
    assert status["loop"]["placement_sigma_m"] is None  # its own frame: the odometry's covariance holds
    info = subprocess.run([sys.executable, "-m", "vio.app.cli", "map", "info", str(map_path), "--json"], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert info.returncode == 0, info.stderr[-2000:]
    header = json.loads(info.stdout)
    assert header["format"] == "kestrel-vio-map" and header["keyframes"] > 0 and header["landmarks_3d"] > 0
    # the same room again with the map and jump output: placed in the map, and how well is said (and sent)
    second = tmp_path / "second"
    second.mkdir()
    # (a map of 4 keyframes and a 30 s flight: its place is taken at 3 edges, not the default 8)
    rc, text = fly(second, 'output = "jump"\noutput_join_edges = 3', f'load = "{map_path}"')
    assert rc == 0 and "relocalised in the map" in text and "placement in the map confirmed" in text, text[-3000:]
    loop = json.loads((second / "status.json").read_text())["loop"]
    assert loop["relocalised"] is True and loop["confirmed"] is True and 0 < loop["placement_sigma_m"] < 0.1, loop
    assert ", in the map +-" in text, text[-3000:]


def test_reset_mid_flight_relocalises_into_the_frame_before_it(loop_flight, tmp_path):
    """Both cameras black for 5 s mid-flight: the estimator resets, and over a gap this long it keeps only the
    heading, so its new segment starts metres off (a new origin). The loop stage treats the segment as a new
    session and, once it sees the places of the first part again, joins it to them: the loop-corrected
    trajectory over the whole flight is in the frame from before the reset."""
    import json

    from vio.app.cli import main
    from vio.sim.faults import blackout, copy_dataset

    data = copy_dataset(loop_flight, tmp_path / "blackout")
    assert blackout(data, 18.0, 5.0) > 0
    stats = tmp_path / "s.json"
    assert main(["replay", str(data), "--loop-output", str(tmp_path / "loop.tum"), "--stats", str(stats),
                 "--no-progress"]) == 0
    s = json.loads(stats.read_text())
    assert s["resets"] >= 1
    loop = s["loop"]
    odom_ate = s["evaluation"]["ate_4dof"]["trans_m"]["rmse"]
    loop_ate = loop["evaluation"]["ate_4dof"]["trans_m"]["rmse"]
    print(f"reset flight: ATE odometry {odom_ate:.3f} m, loop-corrected {loop_ate:.3f} m; end drift "
          f"{loop['end_drift_m']}")
    assert odom_ate > 0.3  # the reset did start a new origin
    assert loop["accepted"] >= 1 and loop["switched_off"] == 0 and loop["error"] is None
    assert loop_ate < 0.05 and loop["end_drift_m"]["loop"] < 0.1


def test_bow_index_query_matches_a_brute_force_l1_ranking_across_merges():
    """The inverted file (sorted postings + unsorted tail, merged every TAIL images) must rank exactly as
    scoring every stored vector one by one."""
    from vio.loop.database import TAIL, BowIndex, BowVector, l1_score

    rng = np.random.default_rng(0)

    def vector() -> BowVector:
        w = np.unique(rng.integers(0, 500, rng.integers(0, 60))).astype(np.int64)
        x = rng.random(len(w))
        return BowVector(w, x / x.sum() if len(w) else x)

    idx, stored = BowIndex(500), []
    for _ in range(4 * TAIL + 5):
        stored.append(vector())
        idx.add(stored[-1])
        q = vector()
        got = idx.query(q, lambda j: j % 3 != 0, 5)
        s = np.array([l1_score(q, u) for u in stored])
        want = [j for j in np.argsort(-s, kind="stable") if j % 3 and s[j] > 0][:5]
        assert [j for j, _ in got] == [int(j) for j in want]
        assert np.allclose([x for _, x in got], s[want])
    assert idx.query(BowVector(np.zeros(0, np.int64), np.zeros(0)), lambda j: True, 3) == []


def test_vocabulary_words_descend_as_one_descriptor_at_a_time():
    """The vectorised descent (64-bit XOR/popcount blocks) picks the nearest child at every level, as the
    plain per-descriptor byte-table descent does, also for descriptors 256 bits from a centre."""
    from vio.loop.vocabulary import _POPCOUNT, Vocabulary

    v = Vocabulary.load()
    rng = np.random.default_rng(1)
    desc = np.vstack([rng.integers(0, 256, (300, 32), dtype=np.uint8), ~v.centres[1:3]])

    def one(x: np.ndarray) -> int:
        n = 0
        for _ in range(v.depth):
            children = n * v.k + 1 + np.arange(v.k)
            n = int(children[np.argmin([_POPCOUNT[np.bitwise_xor(x, v.centres[c])].sum() for c in children])])
        return n - v.first_leaf

    assert v.words(desc).tolist() == [one(x) for x in desc]


def test_one_call_descriptors_equal_upright_keypoints_made_one_by_one(loop_flight):
    """The single-level path makes its keypoints in one call (angle -1 deg) and predicts which rows compute()
    keeps: same descriptors and rows as upright (angle 0) keypoints made one by one, for points scattered over
    the image and on every pixel and half pixel around its border, where compute() drops some."""
    import cv2

    from vio.io.euroc import EurocDataset
    from vio.loop.features import PATCH, FeatureExtractor

    ds = EurocDataset(loop_flight)
    img = cv2.imread(str(ds.cam0_files[10]), cv2.IMREAD_GRAYSCALE)
    h, w = img.shape
    ex = FeatureExtractor(ds.calibration.cam0, 300)
    rng = np.random.default_rng(5)
    edge = np.arange(PATCH - 3, PATCH + 3, 0.5)
    mid_x, mid_y = np.full_like(edge, w / 2), np.full_like(edge, h / 2)
    uv = np.vstack([np.column_stack([rng.uniform(0, w, 400), rng.uniform(0, h, 400)]),
                    np.column_stack([edge, mid_y]), np.column_stack([w - edge, mid_y]),
                    np.column_stack([mid_x, edge]), np.column_stack([mid_x, h - edge])])
    uv = uv.astype(np.float32)
    desc, rows = ex._describe(img, uv, np.zeros(len(uv), np.int64))
    kps = [cv2.KeyPoint(float(u), float(v), float(PATCH), 0.0, 0.0, 0, i) for i, (u, v) in enumerate(uv)]
    kps, ref = ex.orb.compute(img, kps)
    assert 0 < len(rows) < len(uv)  # some dropped at the border
    assert rows.tolist() == [k.class_id for k in kps]
    assert np.array_equal(desc, ref)
    assert ex.slow_describes == 0  # the prediction held: no second pass


def _scale_consistent_matches(ex, img: np.ndarray, far: np.ndarray, s: float, x0: int, y0: int) -> int:
    """Mutual best descriptor matches between an image and the same view from further off (`far`: scaled by
    1/s, placed at x0, y0) that land within 3 px of where the scaling puts them."""
    import cv2

    from vio.frontend.undistort import distort_px

    a, b = ex.extract(img, None), ex.extract(far, None)
    m = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(a.desc, b.desc)
    pa = distort_px(ex.cam, np.array([a.uv[x.queryIdx] for x in m]).reshape(-1, 2))  # back to image pixels
    pb = distort_px(ex.cam, np.array([b.uv[x.trainIdx] for x in m]).reshape(-1, 2))
    return int(np.count_nonzero(np.linalg.norm((pa + 0.5) / s - 0.5 + [x0, y0] - pb, axis=1) <= 3.0))


def test_upright_keypoints_are_the_keypoints_convert_makes():
    """The stereo points' keypoints are made through `map` instead of cv2.KeyPoint.convert: every attribute the same
    (pixel, size, angle -1, response 1, level 0, class_id -1), fractional and integer pixels alike."""
    import cv2

    from vio.loop.features import PATCH, upright_keypoints

    rng = np.random.default_rng(7)
    uv = np.vstack([rng.uniform(0, 752, (300, 2)), rng.integers(0, 480, (50, 2))]).astype(np.float32)

    def attrs(kps: list) -> list[tuple]:
        return [(k.pt, k.size, k.angle, k.response, k.octave, k.class_id) for k in kps]
    assert attrs(upright_keypoints(uv, PATCH)) == attrs(cv2.KeyPoint.convert(uv, float(PATCH)))
    assert upright_keypoints(uv[:0], PATCH) == []


@pytest.mark.parametrize("levels", [1, 2])
def test_extracted_rows_keep_each_stereo_point_with_its_pixel_and_3d_point(loop_flight, levels):
    """`extract` puts the corners and the stereo points kept by the description back together row by row: on one
    level by slices (compute() keeps the points in order), on a pyramid by masks (compute() regroups the points by
    level, stereo points among the corners). Every row with a 3D point must carry that stereo point's own pixel,
    and every corner row none."""
    import cv2

    from vio.io.euroc import EurocDataset
    from vio.loop.features import FeatureExtractor
    from vio.types import FeatureFrame

    ds = EurocDataset(loop_flight)
    cam = ds.calibration.cam0
    img = cv2.imread(str(ds.cam0_files[10]), cv2.IMREAD_GRAYSCALE)
    rng = np.random.default_rng(3)
    n = 120
    uv0 = np.column_stack([rng.uniform(0, cam.width, n), rng.uniform(0, cam.height, n)])  # some near the border
    depth = rng.uniform(0.5, 6.0, n)
    depth[::7] = np.nan  # no stereo match: not described
    ff = FeatureFrame(0, np.arange(n, dtype=np.int64), uv0, uv0.copy(), depth, np.ones(n, np.int64))
    f = FeatureExtractor(cam, 300, levels=levels, level_scale=1.44).extract(img, ff)
    has3 = np.isfinite(f.p_cam[:, 0])
    assert 0 < np.count_nonzero(has3) < np.count_nonzero(np.isfinite(depth))  # some dropped at the border
    assert np.count_nonzero(~has3) > 100  # corners
    for uv, p in zip(f.uv[has3], f.p_cam[has3]):
        k = np.flatnonzero((uv0 == uv).all(axis=1))
        assert len(k) == 1 and np.isfinite(depth[k[0]])
        z = depth[k[0]]
        assert p.tolist() == [(uv[0] - cam.cx) / cam.fx * z, (uv[1] - cam.cy) / cam.fy * z, z]
    corner_uv = {tuple(u) for u in f.uv[~has3].tolist()}
    assert not corner_uv & {tuple(u) for u in uv0.tolist()}
    if levels == 1:  # corners first, then the stereo points
        assert not has3[:np.count_nonzero(~has3)].any()


def test_pyramid_levels_match_a_view_from_further_off(loop_flight):
    """`orb_levels` 2 at 1.44: corners found and described on a second, smaller level, so that a place seen
    from 1.73x further off (a map flown at another height) still matches; one level loses most matches."""
    import cv2

    from vio.io.euroc import EurocDataset
    from vio.loop.features import FeatureExtractor

    ds = EurocDataset(loop_flight)
    img = cv2.imread(str(ds.cam0_files[10]), cv2.IMREAD_GRAYSCALE)
    h, w = img.shape
    s = 1.73
    small = cv2.resize(img, (round(w / s), round(h / s)), interpolation=cv2.INTER_AREA)
    far = np.zeros_like(img)
    y0, x0 = (h - small.shape[0]) // 2, (w - small.shape[1]) // 2
    far[y0:y0 + small.shape[0], x0:x0 + small.shape[1]] = small
    cam = ds.calibration.cam0
    one = _scale_consistent_matches(FeatureExtractor(cam, 300), img, far, s, x0, y0)
    two = _scale_consistent_matches(FeatureExtractor(cam, 300, levels=2, level_scale=1.44), img, far, s, x0, y0)
    print(f"scale-consistent matches at 1/{s}: one level {one}, two levels {two}")
    assert two >= 2 * max(one, 10)


def test_corners_undistorted_from_the_pixel_table_are_undistort_px_s():
    """The extractor looks its corners' undistorted pixels up in a table of every integer pixel (FAST's corners lie
    on them): the same float64 values undistort_px gives the same points (radtan and equidistant lenses); a corner
    off the integer grid, outside the image or from an image of another size is undistorted directly."""
    from vio.calibration import CameraCalibration
    from vio.frontend.undistort import undistort_px
    from vio.loop.features import FeatureExtractor

    rng = np.random.default_rng(3)
    for model, dist in (("radtan", (-0.28, 0.07, 2e-4, 2e-5)), ("equidistant", (-0.01, 0.02, -0.01, 0.003))):
        cam = CameraCalibration(fx=320.0, fy=318.0, cx=161.0, cy=119.5, width=320, height=240, distortion=dist,
                                distortion_model=model)
        ex = FeatureExtractor(cam)
        uv = np.column_stack([rng.integers(0, 320, 500), rng.integers(0, 240, 500)]).astype(np.float32)
        got = ex._undistort_corners(uv, (240, 320))
        assert got.tobytes() == undistort_px(cam, uv.astype(np.float64)).tobytes()
        for odd, shape in ((uv + np.float32(0.5), (240, 320)), (np.vstack([uv, [[320, 5]]]), (240, 320)),
                           (uv, (480, 640))):
            np.testing.assert_array_equal(ex._undistort_corners(odd, shape), undistort_px(cam, odd.astype(float)))


def test_the_pixel_tables_kept_are_the_newest_cameras_not_every_one():
    """Every camera's table was kept for the life of the process (5.8 MB at 752x480): a `vio batch` worker over a
    calibration sweep grew by one per calibration. The newest PIXEL_TABLES_KEPT are kept; one in use stays."""
    import dataclasses

    from vio.calibration import CameraCalibration
    from vio.loop import features as F

    cam = CameraCalibration(fx=40.0, fy=40.0, cx=16.0, cy=12.0, width=32, height=24, distortion=(0.0, 0.0, 0.0, 0.0),
                            distortion_model="radtan")
    used = F.pixel_table(cam)
    for k in range(3 * F.PIXEL_TABLES_KEPT):
        F.pixel_table(dataclasses.replace(cam, fx=41.0 + k))
        assert F.pixel_table(cam) is used  # in use: kept, not made again
    assert len(F._PIXEL_TABLES) <= F.PIXEL_TABLES_KEPT


def test_spread_corners_orders_fast_integer_responses_as_the_float_key_does():
    """FAST's responses (integers 0..255) are sorted by a 16-bit key (cell << 8 | 255 - response) instead of the float
    key cell * 2**20 - response: the same picks in the same order, ties (kept in input order) and the responses 0
    and 255 included; responses that are not such integers take the float key. The other test here feeds uniform
    float responses only, which never reach the 16-bit key."""
    from vio.loop.features import GRID, _weakness, spread_corners

    def reference(uv, response, shape, n):  # the float key for every response (the code before the 16-bit key)
        h, w = shape
        cx, cy = GRID
        cell = np.minimum((uv[:, 1] * cy / h).astype(np.int64), cy - 1) * cx + \
            np.minimum((uv[:, 0] * cx / w).astype(np.int64), cx - 1)
        order = np.argsort(cell * float(1 << 20) - response, kind="stable")
        cell = cell[order]
        rank = np.arange(len(order)) - np.searchsorted(cell, cell)
        per = max(1, n // (cx * cy))
        first, rest = order[rank < per], order[rank >= per]
        rest = rest[np.argsort(-response[rest], kind="stable")][:max(0, n - len(first))]
        return np.concatenate([first, rest])[:n]

    rng = np.random.default_rng(5)
    fast = 0
    for k in range(400):
        m = int(rng.integers(0, 600))
        uv = (rng.random((m, 2)) * [752, 480]).astype(np.float32)
        response = [rng.integers(0, 256, m), rng.choice([0, 255, 16, 17], m), rng.random(m) * 300,
                    rng.integers(0, 3, m) * 127.5][k % 4].astype(np.float64)
        n = int(rng.integers(0, 700))
        fast += _weakness(response) is not None
        np.testing.assert_array_equal(spread_corners(uv, response, (480, 752), n),
                                      reference(uv, response, (480, 752), n), err_msg=f"set {k}")
    assert fast >= 190  # the integer sets took the 16-bit key


def test_corners_spread_over_the_image_and_survive_a_dim_one(loop_flight):
    """FAST corners: every grid cell with texture gets its share before the strongest rest (a bright patch
    cannot take them all), a dim copy of the image is searched again at half the threshold and still gives
    its 300, and a black image gives none (no error)."""
    import cv2

    from vio.io.euroc import EurocDataset
    from vio.loop.features import GRID, FeatureExtractor, spread_corners

    rng = np.random.default_rng(3)
    uv = np.column_stack([rng.uniform(0, 752, 4000), rng.uniform(0, 480, 4000)])
    response = rng.uniform(0, 1, 4000)
    response[(uv[:, 0] < 94) & (uv[:, 1] < 80)] += 10  # one cell far stronger than the rest
    pick = spread_corners(uv, response, (480, 752), 300)
    assert len(pick) == 300 and len(np.unique(pick)) == 300
    cells = np.minimum((uv[pick, 1] * GRID[1] / 480).astype(int), GRID[1] - 1) * GRID[0] + \
        np.minimum((uv[pick, 0] * GRID[0] / 752).astype(int), GRID[0] - 1)
    assert np.bincount(cells, minlength=GRID[0] * GRID[1]).min() >= 300 // (GRID[0] * GRID[1])

    ds = EurocDataset(loop_flight)
    img = cv2.imread(str(ds.cam0_files[10]), cv2.IMREAD_GRAYSCALE)
    ex = FeatureExtractor(ds.calibration.cam0, 300)
    dim = (img.astype(np.float32) * 0.35).astype(np.uint8)
    assert len(ex.fast.detect(dim, None)) < 600  # too few at the full threshold...
    assert len(ex.corners(dim)[0]) == 300  # ...so the second search at half of it fills the share
    uv0, octave = ex.corners(np.zeros_like(img))
    assert len(uv0) == 0 and len(octave) == 0
    assert len(ex.extract(np.zeros_like(img), None).desc) == 0

    # after a dim image the next is searched once at half the threshold and its strong corners picked from
    # that: the same corners as two searches by an extractor that saw nothing before (bright, dim, a shade
    # darker, bright again)
    seq = [img, dim, (img.astype(np.float32) * 0.3).astype(np.uint8), img, dim]
    ex = FeatureExtractor(ds.calibration.cam0, 300)
    for k, im in enumerate(seq):
        fresh = FeatureExtractor(ds.calibration.cam0, 300).corners(im)[0]
        np.testing.assert_array_equal(ex.corners(im)[0], fresh, err_msg=f"image {k}")
    assert ex._dim == [True]


def test_pose_graph_solves_a_loose_segment_prior_beside_tight_loop_edges():
    """Recorded from bench/loop_reloc.py (second flight seed 13, the laps map): a flight not yet relocalised in
    a loaded map (its segment held only by the loose 100 m / 180 deg prior) closes a loop on itself. With
    Cholesky alone the decision graph's least squares threw "indeterminate linear system" and the loop stage
    stopped for the rest of the flight; the solves now fall back to QR."""
    from pathlib import Path

    from vio.config import LoopConfig
    from vio.loop.posegraph import GraphNoise, PoseGraph

    z = np.load(Path(__file__).with_name("data") / "reloc_graph_loose_prior.npz")
    c = LoopConfig()
    g = PoseGraph(GraphNoise(odom_trans_per_m=c.odom_sigma_per_m, loop_trans_m=c.loop_sigma_m,
                             loop_rot_rad=np.radians(c.loop_sigma_deg)))
    for T, prev, prior in zip(z["T_odom"], z["prev"], z["prior"]):
        g.add_node(T, None if prev < 0 else int(prev), None if np.isnan(prior[0]) else tuple(prior))
    assert z["optimize_at"].tolist() == [[len(z["T_odom"]), len(z["loop_T"])]]
    for (i, j), T, n in zip(z["loop_ij"], z["loop_T"], z["loop_inliers"]):
        g.add_loop(int(i), int(j), T, int(n))
    out = g.optimize()
    assert out["loop_weights"] == [1.0, 1.0]
    assert np.isfinite(np.array(g.estimate)).all()


def _stereo_keyframe(P_cam: np.ndarray, desc: np.ndarray, rng: np.random.Generator, K: np.ndarray,
                     baseline_m: float, noise_px: float = 0.3):
    """KeyframeFeatures of points P_cam seen by a stereo pair: pixel and disparity each noise_px off, the 3D
    point back-projected from them (as the front end's stereo depth is)."""
    from vio.loop.features import KeyframeFeatures

    fx, cx, cy = K[0, 0], K[0, 2], K[1, 2]
    z = P_cam[:, 2]
    uv = P_cam[:, :2] / z[:, None] * fx + [cx, cy] + rng.normal(0, noise_px, (len(z), 2))
    zz = fx * baseline_m / (fx * baseline_m / z + rng.normal(0, noise_px, len(z)))
    return KeyframeFeatures(desc, uv, np.column_stack([(uv - [cx, cy]) / fx * zz[:, None], zz]))


def test_edge_refinement_weighs_far_stereo_depths_by_their_disparity():
    """Half the points 2-4 m away, half 8-15 m (where 0.3 px of disparity is 0.3-1 m of depth): PnP takes the
    far depths as exact and its translation is off by millimetres; the two-view adjustment halves that."""
    from vio.geometry import inv_T
    from vio.loop.closer import _mean_pose
    from vio.loop.verify import pnp, refine_edge

    K = np.array([[460.0, 0, 376], [0, 460, 240], [0, 0, 1]])
    b = 0.11
    T_old_new = make_T(so3_exp(np.radians([1.0, 6.0, 2.0])), np.array([0.5, 0.1, 0.2]))
    kw = dict(max_hamming=60, ratio=0.8, reproj_px=2.0, min_inliers=20)
    err_mean, err_refined = [], []
    for seed in range(30):
        rng = np.random.default_rng(seed)
        z = np.where(rng.random(150) < 0.5, rng.uniform(2, 4, 150), rng.uniform(8, 15, 150))
        P = np.column_stack([rng.uniform(-0.7, 0.7, 150) * z, rng.uniform(-0.45, 0.45, 150) * z, z])
        Pn = P @ T_old_new[:3, :3] - T_old_new[:3, :3].T @ T_old_new[:3, 3]  # in the new camera
        seen = (Pn[:, 2] > 1) & (np.abs(Pn[:, 0] / Pn[:, 2]) < 0.8) & (np.abs(Pn[:, 1] / Pn[:, 2]) < 0.5)
        desc = rng.integers(0, 256, (int(seen.sum()), 32), dtype=np.uint8)
        old = _stereo_keyframe(P[seen], desc, rng, K, b)
        new = _stereo_keyframe(Pn[seen], desc, rng, K, b)
        fwd, back = pnp(old, new, K, np.eye(4), **kw), pnp(new, old, K, np.eye(4), **kw)
        assert fwd is not None and back is not None and len(fwd.pairs) == fwd.inliers
        T_mean = _mean_pose(fwd.T_old_new, inv_T(back.T_old_new))
        T_ref = refine_edge(old, new, fwd, back, K, b, np.eye(4), T_mean)
        err_mean.append(np.linalg.norm(T_mean[:3, 3] - T_old_new[:3, 3]))
        err_refined.append(np.linalg.norm(T_ref[:3, 3] - T_old_new[:3, 3]))
    assert np.mean(err_refined) < 0.6 * np.mean(err_mean), (np.mean(err_refined), np.mean(err_mean))


def _flipped(desc: np.ndarray, bits: int, rng: np.random.Generator) -> np.ndarray:
    """Descriptors with `bits` random bits flipped in each (the same place seen from elsewhere)."""
    out = np.unpackbits(desc, axis=1)
    for row in out:
        row[rng.choice(256, bits, replace=False)] ^= 1
    return np.packbits(out, axis=1)


_WIDE_K = np.array([[460.0, 0, 376], [0, 460, 240], [0, 0, 1]])
_WIDE_T_OLD_NEW = make_T(so3_exp(np.radians([2.0, 25.0, 1.0])), np.array([0.8, 0.1, 0.3]))
_WIDE_KW = dict(max_hamming=60, ratio=0.8, reproj_px=2.0, min_inliers=20)


def _wide_view_pair(seed: int):
    """Old and new keyframe features of one place seen 25 deg apart: each descriptor 20 bits off in the new view,
    and for 60 % of the places a look-alike elsewhere in the new image (22 bits off: the ratio test's loss).
    Returns (old, new, number of true new features; the look-alikes come after them)."""
    from vio.loop.features import KeyframeFeatures

    rng = np.random.default_rng(seed)
    z = rng.uniform(2, 8, 300)
    P = np.column_stack([rng.uniform(-0.7, 0.7, 300) * z, rng.uniform(-0.45, 0.45, 300) * z, z])
    R, t = _WIDE_T_OLD_NEW[:3, :3], _WIDE_T_OLD_NEW[:3, 3]
    Pn = P @ R - R.T @ t
    seen = (Pn[:, 2] > 1) & (np.abs(Pn[:, 0] / Pn[:, 2]) < 0.8) & (np.abs(Pn[:, 1] / Pn[:, 2]) < 0.5)
    P, Pn = P[seen], Pn[seen]
    n = len(P)
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    old = _stereo_keyframe(P, desc, rng, _WIDE_K, 0.11)
    new = _stereo_keyframe(Pn, _flipped(desc, 20, rng), rng, _WIDE_K, 0.11)
    twin = rng.random(n) < 0.6
    uv_twin = rng.uniform([0, 0], [752, 480], (int(twin.sum()), 2))
    new = KeyframeFeatures(np.vstack([new.desc, _flipped(desc[twin], 22, rng)]), np.vstack([new.uv, uv_twin]),
                           np.vstack([new.p_cam, np.full((int(twin.sum()), 3), np.nan)]))
    return old, new, n


def test_guided_matching_finds_what_the_ratio_test_hid_and_sharpens_the_pose():
    """A repeated texture: 60 % of the places have a look-alike elsewhere in the new image (2 bits further than
    the true match), which the ratio test turns down. PnP on the rest verifies the candidate; matching again by
    projection finds the hidden ones (the pose says where each must be) and the refined pose is better. A
    candidate that PnP does not verify stays refused whatever guided matching could add."""
    from vio.loop.verify import pnp

    err, n_inl = {0.0: [], 8.0: []}, {0.0: [], 8.0: []}
    for seed in range(20):
        old, new, n = _wide_view_pair(seed)
        for px in err:
            res = pnp(old, new, _WIDE_K, np.eye(4), guided_px=px, **_WIDE_KW)
            assert res is not None and len(res.pairs) == res.inliers
            assert np.all(res.pairs[:, 1] < n)  # no look-alike among the inliers
            err[px].append(np.linalg.norm(res.T_old_new[:3, 3] - _WIDE_T_OLD_NEW[:3, 3]))
            n_inl[px].append(res.inliers)
        # verification is the RANSAC's: with min_inliers above what the ratio test leaves, guided matching
        # does not rescue the candidate
        strict = dict(_WIDE_KW, min_inliers=int(n_inl[0.0][-1]) + 5)
        assert pnp(old, new, _WIDE_K, np.eye(4), guided_px=8.0, **strict) is None
    assert np.mean(n_inl[8.0]) > 1.8 * np.mean(n_inl[0.0]), (np.mean(n_inl[8.0]), np.mean(n_inl[0.0]))
    assert np.mean(err[8.0]) < 0.85 * np.mean(err[0.0]), (np.mean(err[8.0]), np.mean(err[0.0]))


def test_match_from_one_distance_table_is_batch_distances_answer_with_ties():
    """`match` finds nearest, second-nearest and the mutual test in one numpy table of distances instead of
    cv2.batchDistance's K=2 and K=1 searches: the same pairs, on descriptors made to tie (a few bits flipped off a
    few bases, so that many distances are equal: which of equally near old landmarks is a new feature's nearest
    decides the mutual test; equally near new features fail the ratio test whichever is first), and the table is
    every pair's XOR bit count."""
    import cv2

    from vio.loop.features import KeyframeFeatures
    from vio.loop.verify import hamming_table, match

    def reference(old: KeyframeFeatures, new: KeyframeFeatures, max_hamming: int, ratio: float) -> np.ndarray:
        has3 = old.landmark_rows
        old_desc = old.desc[has3]
        dist, idx = cv2.batchDistance(old_desc, new.desc, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=2)
        q = np.flatnonzero((dist[:, 0] <= max_hamming) & (dist[:, 0] < ratio * dist[:, 1]))
        t = idx[q, 0].astype(np.int64)
        back = cv2.batchDistance(new.desc[t], old_desc, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=1)[1][:, 0]
        keep = back == q
        return np.column_stack([has3[q[keep]], t[keep]]).reshape(-1, 2)

    rng = np.random.default_rng(11)
    bases = rng.integers(0, 256, (6, 32), dtype=np.uint8)

    def descriptors(n: int) -> np.ndarray:
        d = bases[rng.integers(0, len(bases), n)].copy()
        flips = rng.integers(0, 256, (n, 3))  # three bits off a base: distances of a handful of values
        for k in range(3):
            d[np.arange(n), flips[:, k] // 8] ^= (1 << (flips[:, k] % 8)).astype(np.uint8)
        return d

    tested = 0
    for n_old, n_new in ((150, 400), (40, 5), (4, 4), (300, 60)):
        p = rng.uniform(1, 5, (n_old, 3))
        p[rng.random(n_old) < 0.3] = np.nan  # corners: no 3D point, not matched from
        old = KeyframeFeatures(descriptors(n_old), rng.uniform(0, 700, (n_old, 2)), p)
        new = KeyframeFeatures(descriptors(n_new), rng.uniform(0, 700, (n_new, 2)), np.full((n_new, 3), np.nan))
        a, b = old.desc, new.desc
        bits = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(axis=2)
        assert np.array_equal(hamming_table(a, b), bits)
        for max_hamming, ratio in ((60, 0.8), (4, 0.8), (60, 1.0), (2, 0.5)):
            got, want = match(old, new, max_hamming, ratio), reference(old, new, max_hamming, ratio)
            assert np.array_equal(got, want)
            tested += len(want)
    assert tested > 100  # pairs found, not only empty answers


def test_guided_pairs_are_the_rule_it_states_with_ties_and_repeats():
    """guided_pairs against the rule written out point by point: each old 3D point in front of the camera takes,
    among the new features within the radius (d^2 <= r^2) and max_hamming, the smallest descriptor distance, ties to
    the feature further left (smaller x; equal x: the lower row); a new feature chosen by several keeps the
    smallest distance, ties to the lower old row; pairs by new feature. Descriptors from a pool of 6 and pixels on
    a coarse grid, so that ties and equal x are common; the empty cases too."""
    from vio.loop.features import KeyframeFeatures
    from vio.loop.verify import guided_pairs

    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])

    def reference(old, new, r, max_ham):
        by_x = np.argsort(new.uv[:, 0], kind="stable")
        rank = np.empty(len(by_x), np.int64)
        rank[by_x] = np.arange(len(by_x))
        best = {}
        for o in np.flatnonzero(np.isfinite(old.p_cam[:, 0])):
            p = old.p_cam[o]
            if p[2] <= 1e-3:
                continue
            uv = p[:2] / p[2] @ K[:2, :2].T + K[:2, 2]
            cands = []
            for n in range(len(new.uv)):
                d = new.uv[n] - uv
                ham = int(np.unpackbits(old.desc[o] ^ new.desc[n]).sum())
                if d[0] * d[0] + d[1] * d[1] <= r * r and ham <= max_ham:
                    cands.append((ham, rank[n], n))
            if cands:
                ham, _, n = min(cands)
                if n not in best or (ham, o) < best[n]:
                    best[n] = (ham, o)
        return np.array([[best[n][1], n] for n in sorted(best)], np.int64).reshape(-1, 2)

    rng = np.random.default_rng(5)
    pool = rng.integers(0, 256, (6, 32), dtype=np.uint8)
    for trial in range(60):
        n_old, n_new = rng.integers(0, 25), rng.integers(0, 40)
        p = np.column_stack([rng.uniform(-0.5, 0.5, (n_old, 2)), rng.uniform(-0.2, 3, n_old)])
        p[rng.random(n_old) < 0.2] = np.nan
        old = KeyframeFeatures(pool[rng.integers(0, 6, n_old)], rng.uniform(0, 100, (n_old, 2)), p)
        new = KeyframeFeatures(pool[rng.integers(0, 6, n_new)], np.round(rng.uniform(0, 100, (n_new, 2)) / 4) * 4,
                               np.full((n_new, 3), np.nan))
        r, max_ham = float(rng.choice([4.0, 8.0, 40.0])), int(rng.choice([0, 60, 256]))
        got = guided_pairs(old, new, K, np.zeros(3), np.zeros(3), max_ham, r)
        np.testing.assert_array_equal(got, reference(old, new, r, max_ham), err_msg=f"trial {trial}")


def test_a_candidate_the_ratio_test_fails_is_matched_from_the_odometry_prior_and_a_wrong_prior_finds_nothing():
    """`[loop] prior_radius_px`: where the ratio test leaves too few matches for PnP (here: fewer than
    min_inliers), the old points are matched by projection from where the odometry puts the new keyframe (1 deg,
    5 cm off the truth): PnP RANSAC on those verifies the place, with no look-alike among its inliers and the
    pose within 3 cm of the truth. A prior 1.5 m off (a look-alike place elsewhere) finds nothing."""
    from vio.loop.verify import pnp

    for seed in range(10):
        old, new, n = _wide_view_pair(seed)
        base = pnp(old, new, _WIDE_K, np.eye(4), **_WIDE_KW)  # the ratio test's matches alone
        strict = dict(_WIDE_KW, min_inliers=int(base.inliers) + 5)
        assert pnp(old, new, _WIDE_K, np.eye(4), guided_px=8.0, **strict) is None
        prior = _WIDE_T_OLD_NEW @ make_T(so3_exp(np.radians([0.0, 1.0, 0.0])), np.array([0.05, 0.0, 0.0]))
        res = pnp(old, new, _WIDE_K, np.eye(4), guided_px=8.0, prior=prior, prior_px=40.0, **strict)
        assert res is not None and np.all(res.pairs[:, 1] < n)
        assert np.linalg.norm(res.T_old_new[:3, 3] - _WIDE_T_OLD_NEW[:3, 3]) < 0.03
        wrong = _WIDE_T_OLD_NEW @ make_T(np.eye(3), np.array([1.5, 0.0, 0.0]))
        assert pnp(old, new, _WIDE_K, np.eye(4), guided_px=8.0, prior=wrong, prior_px=40.0, **strict) is None


def test_the_other_way_matched_from_the_first_pose_agrees_with_it_and_a_wrong_pose_finds_nothing():
    """The edge's second PnP (new keyframe's points in the old image) is matched by projection from the first
    one's pose: on the true place it lands within the two-way tolerance of the first and of the truth; started
    from a pose 0.3 m / 3 deg off (a place that only looks alike) it finds too few matches and refuses."""
    from vio.geometry import inv_T
    from vio.loop.closer import _agree
    from vio.loop.verify import pnp, pnp_from

    kw = {k: _WIDE_KW[k] for k in ("max_hamming", "reproj_px", "min_inliers")}
    for seed in range(10):
        old, new, _ = _wide_view_pair(seed)
        fwd = pnp(old, new, _WIDE_K, np.eye(4), guided_px=8.0, **_WIDE_KW)
        back = pnp_from(new, old, _WIDE_K, np.eye(4), inv_T(fwd.T_old_new), guided_px=8.0, **kw)
        assert back is not None and back.inliers > fwd.inliers * 0.8
        assert _agree(fwd.T_old_new @ back.T_old_new, 0.03, 0.5)
        assert _agree(inv_T(_WIDE_T_OLD_NEW) @ inv_T(back.T_old_new), 0.03, 0.5)
        wrong = fwd.T_old_new @ make_T(so3_exp(np.radians([0.0, 3.0, 0.0])), np.array([0.3, 0.0, 0.0]))
        assert pnp_from(new, old, _WIDE_K, np.eye(4), inv_T(wrong), guided_px=8.0, **kw) is None


def test_a_closure_whose_graph_does_not_solve_is_dropped_and_the_stage_goes_on(loop_flight, monkeypatch, caplog):
    """The same image at the same place after a 4 m excursion: a true closure. Its decision solve fails once
    (as an ill-conditioned graph's did before the QR fallback); that closure is taken back, logged and
    counted, and the next one is accepted as if nothing had happened."""
    import dataclasses

    from vio.loop.posegraph import PoseGraph

    closer, img, ff = _closer_with_landmark_image(loop_flight)
    closer.add_keyframe(0, np.eye(4), img, ff)
    for k, x in enumerate((1.0, 2.0, 1.0), start=1):  # out and back, 2 s apart
        closer.add_keyframe(int(2e9 * k), make_T(np.eye(3), [x, 0, 0]), np.zeros_like(img), None)

    calls = []
    real_fits = PoseGraph._fits

    def fits_once_broken(self, *a, **k):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("Indeterminant linear system detected while working near variable 4")
        return real_fits(self, *a, **k)

    monkeypatch.setattr(PoseGraph, "_fits", fits_once_broken)
    # this edge already fits the estimate (1 cm): without the quick path, so that the decision solve runs
    closer.graph.noise = dataclasses.replace(closer.graph.noise, quick_fit_share=0.0)
    back = make_T(np.eye(3), [0.01, 0, 0])
    with caplog.at_level("WARNING", logger="vio.loop.closer"):
        assert not closer.add_keyframe(int(8e9), back, img, ff)
    assert closer.stats.refused["solve failed"] == 1 and closer.stats.accepted == 0
    assert not [e for e in closer.graph.edges if e.kind == "loop"]
    assert "did not solve" in caplog.text and "edges taken back" in caplog.text
    assert closer.add_keyframe(int(10e9), back, img, ff)  # the stage goes on: the next closure is accepted
    assert closer.stats.accepted >= 1 and len(calls) == 2
    assert [e for e in closer.graph.edges if e.kind == "loop" and e.weight >= 0.5]
    assert closer.correction()[0, 3] < 0  # pulled back toward the start, where the images say it is


def test_edges_to_another_session_with_few_inliers_weigh_less_and_place_the_session_closer():
    """A second flight joins a loaded map: its first edges see the map's places from further off, with few PnP
    inliers and centimetres of error (bench/loop_reloc.py: 12-20 inliers 30-70 mm off, 40-90 inliers 3-8 mm).
    Their sigmas grow as sqrt(reloc_sigma_inliers / inliers) (at most 2x; edges within one session keep the
    graph's rule), and the session's poses come out closer to the truth than with every edge weighed alike."""
    from types import SimpleNamespace

    from vio.config import LoopConfig
    from vio.loop.closer import LoopCloser, _Candidate
    from vio.loop.posegraph import GraphNoise, PoseGraph

    c = LoopConfig()
    me = SimpleNamespace(cfg=c, keyframes=[SimpleNamespace(session=0), SimpleNamespace(session=1),
                                           SimpleNamespace(session=1)])
    def scale(i, j, n):
        return LoopCloser._sigma_scale(me, _Candidate(i, j, np.eye(4), np.eye(4), n))
    assert scale(1, 0, 15) == pytest.approx(2.0) and scale(1, 0, 30) == pytest.approx(np.sqrt(2))
    assert scale(1, 0, 200) == 1.0  # many inliers: never tighter than the graph's between sessions
    off = SimpleNamespace(cfg=SimpleNamespace(reloc_sigma_inliers=0, sigma_inliers=0), keyframes=me.keyframes)
    assert LoopCloser._sigma_scale(off, _Candidate(1, 0, np.eye(4), np.eye(4), 15)) == 1.0
    assert LoopCloser._sigma_scale(off, _Candidate(2, 1, np.eye(4), np.eye(4), 15)) == 1.0

    rng = np.random.default_rng(3)
    truth = [make_T(so3_exp(np.r_[0, 0, 0.05 * k]), np.r_[0.2 * k, 0.05 * k, 1.5]) for k in range(30)]
    noise = GraphNoise(odom_trans_per_m=c.odom_sigma_per_m, loop_trans_m=c.loop_sigma_m,
                       loop_rot_rad=np.radians(c.loop_sigma_deg))
    errors = {}
    for weighed in (False, True):
        g = PoseGraph(noise)
        for k in range(10):  # the map: fixed
            g.add_node(truth[k], None, (1e-4, 1e-4))
        prev, T = None, make_T(so3_exp(np.r_[0, 0, 1.0]), np.r_[5.0, -3.0, 1.5])  # the new flight's own origin
        for k in range(10, 30):
            if k > 10:
                T = T @ np.linalg.inv(truth[k - 1]) @ truth[k] @ make_T(so3_exp(rng.normal(0, 1e-4, 3)),
                                                                        rng.normal(0, 5e-4, 3))
            prev = g.add_node(T, prev, (np.radians(c.segment_prior_deg), c.segment_prior_m) if k == 10 else None)
        bad = make_T(so3_exp(np.r_[0.0, 0.0, np.radians(0.5)]), np.r_[0.0, 0.04, 0.0])
        for m, k, n, err in [(2, 10, 13, bad), (3, 11, 16, bad), (4, 12, 14, bad),
                             (5, 15, 80, np.eye(4)), (6, 18, 75, np.eye(4)), (7, 21, 90, np.eye(4)),
                             (8, 24, 70, np.eye(4)), (9, 27, 85, np.eye(4))]:
            s = float(np.clip(np.sqrt(c.reloc_sigma_inliers / n), 1, 2)) if weighed else 1.0
            g.add_loop(m, k, np.linalg.inv(truth[m]) @ truth[k] @ err, n, s)
        g.optimize(decide=True)
        errors[weighed] = _ate(SimpleNamespace(estimate=g.estimate[10:]), truth[10:])
    print(f"session position error: edges alike {errors[False] * 1e3:.1f} mm, weighed by inliers "
          f"{errors[True] * 1e3:.1f} mm")
    assert errors[True] < 0.8 * errors[False]


def test_loop_edges_within_a_flight_weigh_by_their_inliers_both_ways():
    """Within one flight a loop edge's sigmas scale by sqrt(sigma_inliers / inliers) between 0.5 and 2: an edge
    with many PnP inliers is held tighter than the graph's sigmas, a weak one looser. On a lap whose weak edges
    carry centimetres of error and whose strong ones millimetres, the poses come out closer to the truth than
    with every edge weighed alike: the places seen twice agree better (their relative poses, what a loop edge
    corrects; the first lap's own drift no edge can see)."""
    from types import SimpleNamespace

    from vio.config import LoopConfig
    from vio.loop.closer import LoopCloser, _Candidate
    from vio.loop.posegraph import GraphNoise, PoseGraph

    c = LoopConfig()
    me = SimpleNamespace(cfg=c, keyframes=[SimpleNamespace(session=0)] * 3)

    def scale(n):
        return LoopCloser._sigma_scale(me, _Candidate(2, 0, np.eye(4), np.eye(4), n))
    assert scale(c.sigma_inliers) == pytest.approx(1.0)
    assert scale(15) == pytest.approx(2.0) and scale(4 * c.sigma_inliers) == pytest.approx(0.5)
    assert scale(5) == 2.0 and scale(10_000) == 0.5  # clipped

    rng = np.random.default_rng(5)
    n_kf = 40  # a lap of a 4 m circle, seen again from k = 20 on
    truth = [make_T(so3_exp(np.r_[0, 0, 2 * np.pi * k / 20]),
                    np.r_[2 * np.cos(2 * np.pi * k / 20), 2 * np.sin(2 * np.pi * k / 20), 1.5]) for k in range(n_kf)]
    noise = GraphNoise(odom_trans_per_m=c.odom_sigma_per_m, loop_trans_m=c.loop_sigma_m,
                       loop_rot_rad=np.radians(c.loop_sigma_deg))
    steps = [np.linalg.inv(truth[k - 1]) @ truth[k] @ make_T(so3_exp(rng.normal(0, 2e-3, 3)), rng.normal(0, 4e-3, 3))
             for k in range(1, n_kf)]
    edges = []
    for k in range(20, n_kf):
        weak = k % 2 == 0
        n = int(rng.integers(20, 26)) if weak else int(rng.integers(150, 240))
        err = make_T(so3_exp(rng.normal(0, np.radians(0.4 if weak else 0.05), 3)),
                     rng.normal(0, 0.03 if weak else 0.003, 3))
        edges.append((k - 20, k, n, err))
    errors = {}
    for weighed in (False, True):
        g = PoseGraph(noise)
        prev, T = g.add_node(truth[0], None, (1e-4, 1e-4)), truth[0]
        for k in range(1, n_kf):
            T = T @ steps[k - 1]
            prev = g.add_node(T, prev)
        for m, k, n, err in edges:
            s = float(np.clip(np.sqrt(c.sigma_inliers / n), 0.5, 2.0)) if weighed else 1.0
            g.add_loop(m, k, np.linalg.inv(truth[m]) @ truth[k] @ err, n, s)
        g.optimize(decide=True)
        assert all(e.weight > 0.5 for e in g.edges if e.kind == "loop")  # all true: none switched off either way
        errors[weighed] = np.sqrt(np.mean([np.sum((np.linalg.inv(g.estimate[m]) @ g.estimate[k] - np.linalg.inv(
            truth[m]) @ truth[k])[:3, 3] ** 2) for m, k, _, _ in edges]))
    print(f"places seen twice, relative position error: edges alike {errors[False] * 1e3:.1f} mm, weighed by "
          f"inliers {errors[True] * 1e3:.1f} mm")
    assert errors[True] < 0.85 * errors[False]


class _Recorder:
    """Stands in for the loop worker in a replay: keeps the keyframes and the settled poses handed over."""

    dropped, error = 0, None

    def __init__(self) -> None:
        self.items: list = []
        self.settled: list = []

    def submit(self, *item) -> None:
        self.items.append(item)

    def settle(self, settled) -> None:
        self.settled.extend(settled)

    def close(self) -> None:
        pass


def test_a_keyframe_solved_on_the_next_frame_reaches_the_loop_stage_as_one_solved_on_its_own_frame(laps_flight):
    """With `solve_next_frame` the replay hands the loop stage each keyframe when the frame after it is processed:
    the same keyframes, with their own frame's image, features and solved pose as without it."""
    import dataclasses

    from vio.app.replay import replay
    from vio.config import VioConfig
    from vio.io.euroc import EurocDataset

    got = {}
    for next_frame in (False, True):
        cfg = VioConfig()
        cfg = dataclasses.replace(cfg, backend=dataclasses.replace(cfg.backend, solve_next_frame=next_frame))
        rec = _Recorder()
        replay(EurocDataset(laps_flight), cfg, progress=False, max_frames=200, loop=rec)
        got[next_frame] = rec.items
    same, nxt = got[False], got[True]
    assert len(same) >= 20 and len(nxt) in (len(same), len(same) - 1)  # the last may wait for its next frame
    for (t_a, T_a, img_a, ff_a, r_a), (t_b, T_b, img_b, ff_b, r_b) in zip(same, nxt):
        assert t_a == t_b and ff_a.t_ns == ff_b.t_ns and r_a == r_b == 0
        assert img_a is img_b or np.array_equal(img_a, img_b)
        np.testing.assert_array_equal(ff_a.ids, ff_b.ids)
        np.testing.assert_allclose(T_a, T_b, atol=1e-9)


def test_keyframes_settle_once_in_order_with_better_relative_poses_than_at_their_solve(laps_flight):
    """The odometry hands the loop stage each keyframe's pose again as it leaves the smoother's window
    (`ProcessedFrame.settled`, and at the end of the recording the window's): every keyframe once, in order, and
    with lag_s of later data the poses of consecutive keyframes are closer to the truth relative to each other
    than at their own solve (about half the error on this flight): what the pose graph's odometry edges are made
    of (`[loop] settled_odometry`)."""
    from vio.app.replay import replay
    from vio.config import VioConfig
    from vio.geometry import inv_T
    from vio.io.euroc import EurocDataset

    rec = _Recorder()
    replay(EurocDataset(laps_flight), VioConfig(), progress=False, max_frames=200, loop=rec)
    first = {t: T for t, T, *_ in rec.items}
    ts = [t for t, _ in rec.settled]
    assert ts == sorted(set(ts)) and set(ts) <= set(first)
    # as each leaves the window, and the window's last ones when the recording ends (Estimator.flush)
    assert ts == sorted(first)
    gt = EurocDataset(laps_flight).groundtruth.trajectory

    def truth(t_ns: int) -> np.ndarray:
        from vio.geometry import quat_wxyz_to_rot

        k = int(np.argmin(np.abs(gt.t_ns - t_ns)))
        return make_T(quat_wxyz_to_rot(gt.q_wxyz[k]), gt.p[k])

    def rel_err_m(P: dict) -> float:
        e = [np.linalg.norm((inv_T(inv_T(truth(a)) @ truth(b)) @ inv_T(P[a]) @ P[b])[:3, 3])
             for a, b in zip(ts[:-1], ts[1:])]
        return float(np.sqrt(np.mean(np.square(e))))

    settled = dict(rec.settled)
    assert max(np.linalg.norm(settled[t][:3, 3] - first[t][:3, 3]) for t in ts) < 0.05  # the same flight
    assert rel_err_m(settled) < 0.8 * rel_err_m(first), (rel_err_m(settled), rel_err_m(first))


def test_keyframes_settled_in_a_call_that_then_resets_keep_their_settled_poses(laps_flight, monkeypatch):
    """A keyframe's solve marginalises (and so settles) older keyframes, then fails: the estimator resets, and the
    poses settled by that solve still reach the loop stage (the rest of the window never settles)."""
    from vio.app.replay import replay
    from vio.backend.smoother import SmootherFailure, VioSmoother
    from vio.config import VioConfig
    from vio.io.euroc import EurocDataset

    orig = VioSmoother.add_keyframe
    lost: list = []

    def failing(self, *a, **kw):
        est = orig(self, *a, **kw)
        if not lost and self.index >= 12 and self._settled:
            lost.extend(t for t, _ in self._settled)  # settled by this solve, not handed out yet
            raise SmootherFailure("test: the solve after the marginalisation fails")
        return est

    monkeypatch.setattr(VioSmoother, "add_keyframe", failing)
    rec = _Recorder()
    res = replay(EurocDataset(laps_flight), VioConfig(), progress=False, max_frames=200, loop=rec)
    assert res.resets >= 1 and lost
    got = {t for t, _ in rec.settled}
    assert set(lost) <= got


def test_correction_uncertainty_carries_yaw_and_position_errors_to_the_pose_sent():
    """A correction whose yaw and position are uncertain (covariance at a keyframe, world frame) moves every pose it
    maps: drawn errors applied to the correction give, at a pose 6 m from the keyframe, the body-tangent pose and
    world velocity scatter that `added_to` adds (yaw times the lever arm included); quality follows the sigma."""
    from vio.geometry import inv_T, so3_log
    from vio.loop.output import CorrectionUncertainty
    from vio.types import NavState

    rng = np.random.default_rng(4)
    L = rng.normal(0, 1, (4, 4)) * np.r_[0.01, 0.02, 0.02, 0.01][:, None]
    cov4 = L @ L.T + np.diag([1e-5, 1e-5, 1e-5, 1e-5])
    p_kf = np.array([1.0, 2.0, 1.5])
    unc = CorrectionUncertainty(cov4, p_kf)
    T = make_T(so3_exp(np.array([0.1, -0.05, 2.0])), p_kf + [4.0, -4.5, 0.3])
    st = NavState(0, T, np.array([1.5, -0.5, 0.2]), cov_pose=np.zeros((6, 6)), cov_vel=np.zeros((3, 3)), quality=90)
    e_pose, e_vel = [], []
    for d in rng.multivariate_normal(np.zeros(4), cov4, 20000):
        # the corrected world is off by a yaw d[0] about the keyframe and a shift d[1:]
        E = make_T(so3_exp(np.array([0, 0, d[0]])), p_kf + d[1:] - so3_exp(np.array([0, 0, d[0]])) @ p_kf)
        Tp = E @ T
        D = inv_T(T) @ Tp  # GTSAM Pose3 tangent: T_true = T_sent Exp(xi)
        e_pose.append(np.r_[so3_log(D[:3, :3]), D[:3, 3]])
        e_vel.append(E[:3, :3] @ st.v_world - st.v_world)
    out = unc.added_to(st, quality_sigma_m=0.05)
    np.testing.assert_allclose(out.cov_pose, np.cov(np.array(e_pose).T), atol=0.04 * np.abs(out.cov_pose).max())
    np.testing.assert_allclose(out.cov_vel, np.cov(np.array(e_vel).T), atol=0.04 * np.abs(out.cov_vel).max())
    sigma = np.sqrt(np.trace(out.cov_pose[3:, 3:]))
    assert sigma > 0.1 and out.quality == round(100 * 0.05 / sigma) < 90


def test_jump_output_holds_the_uncertainty_of_the_correction_it_holds():
    from vio.loop.output import CorrectedOutput, CorrectionUncertainty
    from vio.types import NavState

    st = NavState(0, np.eye(4), np.zeros(3), cov_pose=np.eye(6) * 1e-6)
    a = CorrectionUncertainty(np.eye(4) * 1e-4, np.zeros(3))
    b = CorrectionUncertainty(np.eye(4) * 1e-2, np.zeros(3))
    C = make_T(np.eye(3), [1.0, 0, 0])
    jump = CorrectedOutput("jump")
    assert np.allclose(jump.apply(st, C, 1).cov_pose, st.cov_pose)  # no uncertainty: the odometry's own frame
    first = jump.apply(st, C, 2, a)
    assert first.cov_pose[3, 3] == pytest.approx(1e-6 + 1e-4)
    assert np.allclose(jump.apply(st, C, 2, b).cov_pose, first.cov_pose)  # same version: the one it holds
    assert jump.apply(st, C, 3, b).cov_pose[3, 3] == pytest.approx(1e-6 + 1e-2)
    assert CorrectedOutput("off").apply(st, C, 3, b) is st


@pytest.mark.parametrize("mode", ["jump", "blend"])
def test_a_yaw_correction_turns_the_velocity_covariance_with_the_velocity(mode):
    """cov_vel is world-frame: under a 90 deg yaw correction the odometry's uncertain axis (x, 0.1 m/s) is y in the
    corrected frame; kept as it was, it was sent as the certain one (a review's finding)."""
    from vio.loop.output import CorrectedOutput
    from vio.types import NavState

    cov = np.diag([1e-2, 1e-4, 1e-4])
    C = make_T(so3_exp(np.r_[0, 0, np.pi / 2]), np.zeros(3))
    output = CorrectedOutput(mode, blend_rate_m_s=1.0, blend_rate_deg_s=1e6)
    output.apply(NavState(0, np.eye(4), np.array([1.0, 0, 0]), cov_vel=cov), C, 1)
    out = output.apply(NavState(1_000_000_000, np.eye(4), np.array([1.0, 0, 0]), cov_vel=cov), C, 1)
    assert output.remaining_deg == pytest.approx(0.0)  # the blend has turned by the whole correction in 1 s
    np.testing.assert_allclose(out.v_world, [0, 1, 0], atol=1e-9)
    np.testing.assert_allclose(np.diag(out.cov_vel), [1e-4, 1e-2, 1e-4], atol=1e-12)


def test_pose_graph_marginal_of_a_keyframe_not_yet_solved_equals_its_solved_one():
    """Keyframes wait for the next flush; their covariance is carried from the newest solved one along the odometry.
    Their yaw and position covariance (what the output uses) is what iSAM2 gives once they are in; roll and pitch
    are larger until their attitude factors go in with them."""
    from vio.loop.output import CorrectionUncertainty

    rng = np.random.default_rng(5)
    g, truth = _circle(20, rng)  # 20 solved (flush_every 10), with a loop edge
    g.add_loop(0, 19, np.linalg.inv(truth[0]) @ truth[19])
    g.optimize(decide=True)
    step = make_T(so3_exp(np.r_[0.01, 0.0, 2 * np.pi / 40]), np.r_[0.3, 0.02, 0.01])
    for i in range(20, 25):  # 5 more, pending
        g.add_node(g.odom[-1] @ step, i - 1)
    assert not g._isam.valueExists(20)
    pending = [g.marginal(i) for i in range(20, 25)]
    g.refresh()
    for i, C in zip(range(20, 25), pending):
        solved = g.marginal(i)
        a, b = (CorrectionUncertainty.from_pose(g.estimate[i], M).cov_yaw_position for M in (C, solved))
        np.testing.assert_allclose(a, b, rtol=0.1, atol=1e-2 * np.abs(b).max())
        assert np.all(np.diag(a) >= np.diag(b) * (1 - 1e-4)) and np.all(np.diag(C)[:2] >= np.diag(solved)[:2])


def test_a_relocalised_keyframes_uncertainty_covers_its_error_in_the_maps_frame():
    """A second flight placed in a fixed map by loop edges that are off by millimetres (as PnP edges are, far under
    the graph's 3 cm sigmas): the newest keyframe's yaw and position error in the map's frame, over 40 draws, against
    the covariance the output adds (the pose graph's marginal scaled by the loop edges' variance factor). The
    odometry's own covariance knows nothing of these edges (NEES in the hundreds); the raw marginal says far less
    than the edges show; the scaled one is about right."""
    from vio.loop.output import CorrectionUncertainty
    from vio.loop.posegraph import MIN_LOOP_VARIANCE_FACTOR, PoseGraph

    rng = np.random.default_rng(6)
    truth = [make_T(so3_exp(np.r_[0, 0, 0.08 * k]), np.r_[0.25 * k, 0.4 * np.sin(0.3 * k), 1.5]) for k in range(40)]
    nees: dict[str, list[float]] = {"raw": [], "scaled": []}
    for _ in range(40):
        g = PoseGraph()
        for k in range(20):  # the map, fixed at the truth
            g.add_node(truth[k], None, (1e-4, 1e-4))
        prev, T = None, make_T(so3_exp(np.r_[0, 0, 0.7]), np.r_[3.0, -2.0, 1.5])
        for k in range(20, 40):
            if k > 20:
                T = T @ np.linalg.inv(truth[k - 1]) @ truth[k] @ make_T(so3_exp(rng.normal(0, 1e-4, 3)),
                                                                        rng.normal(0, 3e-4, 3))
            prev = g.add_node(T, prev, (np.pi, 100.0) if k == 20 else None)
        for m, k in zip(range(2, 20, 3), range(21, 40, 3)):  # six edges, 6 mm and 0.2 deg off
            err = make_T(so3_exp(rng.normal(0, np.radians(0.2), 3)), rng.normal(0, 0.006, 3))
            g.add_loop(m, k, np.linalg.inv(truth[m]) @ truth[k] @ err)
        g.optimize(decide=True)
        n = len(g) - 1
        e = np.r_[np.arctan2(*(g.estimate[n][:3, :3] @ truth[n][:3, :3].T)[[1, 0], [0, 0]]),
                  truth[n][:3, 3] - g.estimate[n][:3, 3]]
        for name, k in (("raw", 1.0), ("scaled", g.loop_variance_factor())):
            c = CorrectionUncertainty.from_pose(g.estimate[n], g.marginal(n) * k).cov_yaw_position
            nees[name].append(float(e @ np.linalg.solve(c, e)))
    raw, scaled = np.mean(nees["raw"]), np.mean(nees["scaled"])
    exact = PoseGraph()  # edges with no error at all: the factor stops at its floor, never says "exact"
    for k in range(6):
        exact.add_node(truth[k], k - 1 if k else None)
    for m in range(3):
        exact.add_loop(m, m + 3, np.linalg.inv(truth[m]) @ truth[m + 3])
    exact.optimize(decide=True)
    assert exact.loop_variance_factor() == MIN_LOOP_VARIANCE_FACTOR
    print(f"yaw+position NEES (4 dof) of the newest keyframe: raw marginal {raw:.2f}, scaled {scaled:.2f}")
    assert raw < 0.5  # the graph's loop sigmas are far wider than these edges' errors
    assert 1.0 < scaled < 6.0  # honest-to-cautious (4 would be exact; the factor is a 95 % upper bound)


def test_correction_uncertainty_falls_back_to_a_loop_edges_sigmas_when_gtsam_cannot_give_a_marginal(caplog):
    """A marginal gtsam cannot compute must neither stop the loop stage nor send the pose with nothing added: one
    loop edge's sigmas (unscaled) go instead, and the log says so once. In the flight's own frame: nothing."""
    from types import SimpleNamespace

    from vio.loop.closer import LoopCloser
    from vio.loop.posegraph import GraphNoise

    def broken(i):
        raise RuntimeError("indeterminant system")

    class Graph:
        noise = GraphNoise()
        estimate = [np.eye(4), make_T(np.eye(3), [1.0, 2.0, 0.5])]
        marginal = staticmethod(broken)

        def __len__(self):
            return 2

    noise = Graph.noise
    me = SimpleNamespace(keyframes=[SimpleNamespace(session=0), SimpleNamespace(session=1)], graph=Graph(),
                         _comp=lambda s: 0, _marginal_warned=False)
    with caplog.at_level("WARNING", logger="vio.loop.closer"):
        a = LoopCloser.correction_uncertainty(me)
        b = LoopCloser.correction_uncertainty(me)
    np.testing.assert_allclose(np.diag(a.cov_yaw_position), [noise.loop_rot_rad ** 2] + [noise.loop_trans_m ** 2] * 3)
    np.testing.assert_allclose(a.p_world, [1.0, 2.0, 0.5])
    np.testing.assert_allclose(b.cov_yaw_position, a.cov_yaw_position)
    assert caplog.text.count("no marginal covariance") == 1
    me._comp = lambda s: s  # its own frame
    assert LoopCloser.correction_uncertainty(me) is None
    # a marginal that comes back NaN goes the same way (NaN read as quality 100 at the output: a review's finding)
    Graph.marginal = staticmethod(lambda i: np.full((6, 6), np.nan))
    Graph.loop_variance_factor = lambda self: 1.0
    me._comp = lambda s: 0
    np.testing.assert_allclose(LoopCloser.correction_uncertainty(me).cov_yaw_position, a.cov_yaw_position)


def test_a_flight_that_takes_off_where_the_map_did_gets_its_map_frame_and_uncertainty_at_the_join(laps_flight,
                                                                                                  tmp_path):
    """A second flight whose own frame nearly coincides with the map's (the same take-off pad; here the same
    flight): its first edges to the map already fit, and used to wait for the next flush (deferred quick fits).
    Meanwhile the output kept no map frame (no new version) and the placement uncertainty came from iSAM2 without
    the join's edges, i.e. from the new session's 100 m prior: metres (a review saw +-3.27 m and quality 2). A
    closure that joins sessions is solved at once: a new version at the join, and centimetres."""
    from vio.app.replay import replay
    from vio.config import VioConfig
    from vio.io.euroc import EurocDataset
    from vio.loop.closer import LoopCloser
    from vio.loop.mapfile import load_map

    ds = EurocDataset(laps_flight)
    rec = _Recorder()
    replay(ds, VioConfig(), progress=False, max_frames=400, loop=rec)
    cfg = VioConfig().loop
    mapper = LoopCloser(ds.calibration, cfg)
    for item in rec.items:
        mapper.add_keyframe(*item)
    mapper.save_map(tmp_path / "pad.npz")
    cl = LoopCloser(ds.calibration, cfg)
    cl.load_map(load_map(tmp_path / "pad.npz"))
    sigmas = []
    for item in rec.items:
        version = cl.graph.estimate_version
        cl.add_keyframe(*item)
        if cl.relocalised_t_ns is not None:
            if not sigmas:
                assert cl.graph.estimate_version > version  # solved at the join, not deferred
            u = cl.correction_uncertainty()
            assert u is not None
            sigmas.append(u.position_sigma_m)
    assert sigmas, "never relocalised"
    print(f"placement sigma over {len(sigmas)} keyframes: {min(sigmas) * 1e3:.1f}-{max(sigmas) * 1e3:.1f} mm")
    assert max(sigmas) < 0.05


def test_blend_holds_its_correction_through_an_estimator_reset_until_a_new_solve():
    """After an estimator reset the newest correction is the new segment's own (identity, no new version) until a
    closure joins it: blend walked towards it, away from the map, at its full rate, and dropped the uncertainty.
    Like jump, it keeps what it holds until a new version; the walk left is reported, heading included."""
    from vio.loop.output import CorrectedOutput, CorrectionUncertainty
    from vio.types import NavState

    C = make_T(so3_exp(np.radians([0, 0, 40.0])), [2.0, -1.0, 0])
    unc = CorrectionUncertainty(np.eye(4) * 1e-4, np.zeros(3))
    st = [NavState(int(k * 1e8), make_T(np.eye(3), [1.0, 0, 0]), np.zeros(3), cov_pose=np.eye(6) * 1e-6)
          for k in range(2000)]  # 10 Hz, 200 s hovering 1 m from the odometry's origin
    blend = CorrectedOutput("blend", blend_rate_m_s=0.2, blend_rate_deg_s=5.0)
    out = blend.apply(st[0], C, 1, unc)
    assert blend.remaining_deg == pytest.approx(40.0) and blend.remaining_m == pytest.approx(1.80, abs=0.01)
    for s in st[1:400]:
        out = blend.apply(s, C, 1, unc)
    assert np.allclose(out.T_world_body, C @ st[0].T_world_body) and blend.remaining_m == blend.remaining_deg == 0
    for s in st[400:800]:  # an estimator reset: the new segment's own correction, no new version
        after = blend.apply(s, np.eye(4), 1, None)
    assert np.allclose(after.T_world_body, out.T_world_body) and after.cov_pose[3, 3] == out.cov_pose[3, 3]
    C2 = make_T(so3_exp(np.radians([0, 0, 41.0])), [2.0, -1.1, 0])
    nxt = blend.apply(st[800], C2, 2, unc)  # the segment joined: a new version, walked to
    assert 0 < blend.remaining_deg < 1.0 and np.linalg.norm(nxt.T_world_body[:3, 3] - out.T_world_body[:3, 3]) < 0.03


def test_a_map_made_with_another_camera_is_said_to_rarely_place_the_flight(tmp_path, caplog):
    """A 376x240 map loaded for a 752x480 flight matched 2 of 72 candidates and said only "NOT placed" (a review's
    finding): the loop stage now says at load why it will rarely place the flight, and the replay repeats it."""
    import dataclasses

    from vio.config import VioConfig
    from vio.loop.closer import LoopCloser
    from vio.loop.features import KeyframeFeatures
    from vio.loop.mapfile import load_map, save_map
    from vio.loop.vocabulary import Vocabulary
    from vio.sim import default_calibration

    calib = default_calibration()
    c = calib.cam0
    small = dataclasses.replace(c, width=c.width // 2, height=c.height // 2, fx=c.fx / 2, fy=c.fy / 2, cx=c.cx / 2,
                                cy=c.cy / 2)
    f = KeyframeFeatures(np.zeros((3, 32), np.uint8), np.zeros((3, 2)), np.zeros((3, 3)))
    for cam, warned in ((small, True), (calib.cam0, False)):
        save_map(tmp_path / "m.npz", [1], [np.eye(4)], [f], Vocabulary.load(), cam)
        cl = LoopCloser(calib, VioConfig().loop)
        caplog.clear()
        with caplog.at_level("WARNING", logger="vio.loop.closer"):
            cl.load_map(load_map(tmp_path / "m.npz"))
        assert bool(cl.map_camera_warning) == warned and ("made with a 376x240 camera" in caplog.text) == warned


def test_a_map_made_with_another_calibration_of_the_camera_is_verified_in_this_ones_pixels(tmp_path):
    """A map's undistorted pixels are in the pinhole of the calibration it was made with. Loaded for a flight whose
    calibration differs by less than the size/focal warning (focal 0.8 %, principal point 3 px), verification
    projected into the map's images with this flight's K: the back PnP came out biased, and a relocalised flight
    sat twice as far off in the map's frame (14 -> 30 mm), unsaid. The loader now re-expresses the map's pixels
    in this camera's, so the same view verifies as the same pose; a header without the principal point is
    refused as damaged."""
    import dataclasses

    import cv2

    from vio import VioError
    from vio.config import VioConfig
    from vio.loop.closer import LoopCloser
    from vio.loop.features import KeyframeFeatures
    from vio.loop.mapfile import load_map, save_map
    from vio.loop.verify import pnp_from
    from vio.loop.vocabulary import Vocabulary
    from vio.sim import default_calibration

    calib = default_calibration()
    c = calib.cam0
    map_cam = dataclasses.replace(c, fx=c.fx * 1.008, fy=c.fy * 1.008, cx=c.cx + 3.0, cy=c.cy + 2.0)
    rng = np.random.default_rng(3)
    n = 80
    p = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.2, 1.2, n), rng.uniform(2, 6, n)])
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)

    def seen_by(cam) -> KeyframeFeatures:
        uv = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, None)[0].reshape(-1, 2)
        return KeyframeFeatures(desc, uv, p)

    save_map(tmp_path / "m.npz", [1], [np.eye(4)], [seen_by(map_cam)], Vocabulary.load(), map_cam)
    cl = LoopCloser(calib, VioConfig().loop)
    cl.load_map(load_map(tmp_path / "m.npz"))
    old = cl.keyframes[0].feats
    assert np.abs(old.uv - seen_by(c).uv).max() < 1e-3  # where this camera sees the map's points
    # the same view from the same place: the back PnP (this flight's landmarks into the map's image) is identity
    res = pnp_from(seen_by(c), old, c.K, c.T_body_cam, np.eye(4), max_hamming=50, reproj_px=2.0, min_inliers=20,
                   guided_px=8.0)
    assert res is not None
    R = res.T_old_new[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 0.01
    assert np.linalg.norm(res.T_old_new[:3, 3]) < 1e-3

    z = dict(np.load(tmp_path / "m.npz"))
    z["header"] = np.array(str(z["header"]).replace('"cx"', '"cx_"'))
    np.savez(tmp_path / "nocx.npz", **z)
    with pytest.raises(VioError, match="damaged map.*principal point"):
        load_map(tmp_path / "nocx.npz")


def _byte_flipped(data: bytes, at: int) -> bytes:
    """`data` with every bit of its byte `at` flipped (a byte damaged on disk)."""
    out = bytearray(data)
    out[at] ^= 0xFF
    return bytes(out)


def _load_each_byte_flipped(data: bytes, spots, path, load) -> None:
    """Write `data` to `path` with each byte in `spots` flipped in turn and `load` it: a flip in a field nothing
    checks (a date) loads, anything else must be a VioError (one line), never another exception."""
    from vio import VioError

    for at in spots:
        path.write_bytes(_byte_flipped(data, at))
        with contextlib.suppress(VioError):
            load(path)


def test_a_map_damaged_inside_a_compressed_array_or_with_float_offsets_is_a_one_line_error(tmp_path, capsys):
    """A byte flipped inside a map's compressed array (a damaged card) raised zlib.error, in an array's header
    tokenize.TokenError, in the archive's directory NotImplementedError, and kf_offsets stored as floats a TypeError
    on slicing: `vio map info`, `vio replay --load-map` and `vio run`'s [map] load check ended in "internal
    error". All are now refused as a damaged map, in one line."""
    import zipfile

    from vio import VioError
    from vio.app.cli import main
    from vio.loop.features import KeyframeFeatures
    from vio.loop.mapfile import load_map, save_map
    from vio.loop.vocabulary import Vocabulary
    from vio.sim import default_calibration

    rng = np.random.default_rng(0)
    feats = [KeyframeFeatures(np.tile(rng.integers(0, 256, (40, 32), dtype=np.uint8), (10, 1)),
                              rng.uniform(0, 300, (400, 2)), rng.uniform(1, 5, (400, 3))) for _ in range(3)]
    good = tmp_path / "m.npz"
    save_map(good, [1, 2, 3], [make_T(np.eye(3), [k, 0, 0]) for k in range(3)], feats, Vocabulary.load(),
             default_calibration().cam0)
    data = good.read_bytes()
    with zipfile.ZipFile(good) as zf:  # each array's first bytes (its .npy header) and the archive's directory
        spots = [i.header_offset + 30 + len(i.filename) + len(i.extra) + k for i in zf.infolist() for k in range(64)]
        spots += range(zf.start_dir, len(data))
    _load_each_byte_flipped(data, spots, tmp_path / "bad.npz", load_map)
    (tmp_path / "bad.npz").write_bytes(_byte_flipped(data, spots[64 * 4 + 30]))  # inside desc.npy's compressed data
    assert main(["map", "info", str(tmp_path / "bad.npz")]) == 1
    err = capsys.readouterr().err
    assert "truncated or damaged" in err and "internal error" not in err and len(err.strip().splitlines()) == 1, err
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"[source]\nkind = 'fake'\n[map]\nload = '{tmp_path / 'bad.npz'}'\n")
    assert main(["-q", "config", "check", str(cfg)]) == 3
    err = capsys.readouterr().err
    assert "[map] load:" in err and "internal error" not in err, err

    z = dict(np.load(good))
    np.savez(tmp_path / "f.npz", **{**z, "kf_offsets": z["kf_offsets"].astype(np.float64)})
    with pytest.raises(VioError, match="damaged map.*offsets"):
        load_map(tmp_path / "f.npz")


def _forged_npy_header(src: Path, dst: Path, member: str, shape: tuple, dtype) -> None:
    """`src` (an .npz) copied to `dst` with `member`'s .npy header declaring `shape` over 64 bytes of data."""
    import io
    import zipfile

    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            data = zin.read(info.filename)
            if info.filename == member:
                buf = io.BytesIO()
                np.lib.format.write_array_header_1_0(buf, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                                                           "fortran_order": False, "shape": shape})
                data = buf.getvalue() + bytes(64)
            zout.writestr(info.filename, data)


def test_a_map_with_arrays_of_the_wrong_rank_or_kind_or_sizes_it_cannot_hold_is_a_one_line_error(tmp_path, capsys):
    """A QA sweep of damaged maps (a review's): stamps or descriptors stored as one number, stamps as a column,
    an array header declaring 10^13 descriptors (a damaged or forged size) and a header nested 100000 deep ended in
    `vio map info` / `[map] load` as "internal error: TypeError / MemoryError / RecursionError"; stamps stored as
    floats (1.5, 2.5 ns) or beyond int64 (1e30) were cut to whole numbers or wrapped, and a camera `true` pixels
    wide was taken as 1 ("camera TruexTrue"), all loaded without a word."""
    from vio.app.cli import main

    cam = '"camera": {"fx": 458.0, "fy": 457.0, "cx": 367.0, "cy": 248.0, "width": 752, "height": 480}'
    hdr = np.array('{"format": "kestrel-vio-map", "version": 1, ' + cam + '}')
    good = dict(header=hdr, kf_offsets=np.array([0, 3, 5]), desc=np.zeros((5, 32), np.uint8), uv=np.zeros((5, 2)),
                p_cam=np.zeros((5, 3)), kf_t_ns=np.array([1, 2]), kf_T_world_body=np.tile(np.eye(4), (2, 1, 1)))
    np.savez(tmp_path / "good.npz", **good)
    assert main(["map", "info", str(tmp_path / "good.npz")]) == 0
    capsys.readouterr()
    cases = {"stamp_scalar": (dict(kf_t_ns=np.array(3)), "damaged map (keyframe stamps"),
             "stamp_column": (dict(kf_t_ns=np.array([[1], [2]])), "damaged map (keyframe stamps"),
             "stamp_float": (dict(kf_t_ns=np.array([1.5, 2.5])), "damaged map (keyframe stamps"),
             "stamp_huge": (dict(kf_t_ns=np.array([1e30, 2e30])), "damaged map (keyframe stamps"),
             "desc_scalar": (dict(desc=np.array(0, np.uint8)), "damaged map (descriptors"),
             "deep": (dict(header=np.array("[" * 100000 + "]" * 100000)), "not a Kestrel VIO map (its header"),
             "size_true": (dict(header=np.array(str(hdr).replace("752", "true").replace("480", "true"))),
                           "damaged map (its header has no camera size"),
             # a camera 1e300 pixels wide was taken ("camera 1e+300x480", a review's finding)
             "size_huge": (dict(header=np.array(str(hdr).replace("752", "1e300"))),
                           "damaged map (its header has no camera size (whole pixels, at most 32768"),
             "fx_huge": (dict(header=np.array(str(hdr).replace("458.0", "1e300"))),
                         "damaged map (its header's camera (fx 1e+300, fy 457, cx 367, cy 248 for 752x480) is no"),
             "cx_out": (dict(header=np.array(str(hdr).replace("367.0", "1e6"))), "damaged map (its header's camera")}
    for name, (change, _) in cases.items():
        np.savez(tmp_path / f"{name}.npz", **{**good, **change})
    _forged_npy_header(tmp_path / "good.npz", tmp_path / "huge.npz", "desc.npy", (10**13, 32), np.uint8)
    cases["huge"] = ({}, "more memory than")
    for name, (_, says) in cases.items():
        assert main(["map", "info", str(tmp_path / f"{name}.npz")]) == 1, name
        err = capsys.readouterr().err
        assert says in err and "internal error" not in err and len(err.strip().splitlines()) == 1, (name, err)
    cfg = tmp_path / "c.toml"  # `vio run`'s [map] load goes through the same check
    cfg.write_text(f"[source]\nkind = 'fake'\n[map]\nload = '{tmp_path / 'huge.npz'}'\n")
    assert main(["-q", "config", "check", str(cfg)]) == 3
    err = capsys.readouterr().err
    assert "[map] load:" in err and "more memory than" in err and "internal error" not in err, err


def test_a_map_path_that_is_a_pipe_or_a_device_is_a_one_line_error_not_a_hang(tmp_path):
    """`vio map info FIFO` (or [map] load / --load-map naming one) waited for ever for a writer to open the pipe:
    no message, no exit, and `vio run`'s start check would hang the same way (a review's finding). A map is a
    regular file (a zip archive needs seeking); a device, pipe or socket is refused in one line."""
    import subprocess
    import sys

    fifo = tmp_path / "map.npz"
    os.mkfifo(fifo)
    for path in (fifo, Path("/dev/zero")):
        r = subprocess.run([sys.executable, "-m", "vio.app.cli", "map", "info", str(path)], capture_output=True,
                           text=True, timeout=60, cwd=Path(__file__).resolve().parent.parent)
        assert r.returncode == 1 and "is not a regular file" in r.stderr, r.stderr
        assert "internal error" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_a_map_write_that_fails_half_way_keeps_the_map_that_was_there(tmp_path, monkeypatch):
    """A map grown in place ([map] load and save the same file): a full disk half-way through the write must not
    cost the old map (it was truncated first), and leaves no partial file behind."""
    import errno

    from vio import VioError
    from vio.loop import mapfile
    from vio.loop.features import KeyframeFeatures
    from vio.loop.vocabulary import Vocabulary
    from vio.sim import default_calibration

    cam, vocab = default_calibration().cam0, Vocabulary.load()
    f = KeyframeFeatures(np.zeros((3, 32), np.uint8), np.zeros((3, 2)), np.zeros((3, 3)))
    mapfile.save_map(tmp_path / "room.npz", [1], [np.eye(4)], [f], vocab, cam)
    before = (tmp_path / "room.npz").read_bytes()

    def full_disk(file, **arrays):
        file.write(b"PK\x03\x04 half a map")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(mapfile.np, "savez_compressed", full_disk)
    with pytest.raises(VioError, match="No space left on device.*the map that was there is kept"):
        mapfile.save_map(tmp_path / "room.npz", [1, 2], [np.eye(4)] * 2, [f, f], vocab, cam)
    assert (tmp_path / "room.npz").read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["room.npz"]
    monkeypatch.undo()
    assert len(mapfile.load_map(tmp_path / "room.npz").features) == 1


def test_a_session_whose_joining_edges_are_switched_off_is_in_a_frame_of_its_own_again():
    """The union of sessions followed every edge ever accepted: after GNC switched off a false relocalisation, the
    flight still counted as in the map (status, placement uncertainty from a 100 m prior) and looked for the map
    with the looser rules of a joined flight. Joins are now rebuilt from the edges GNC keeps."""
    from types import SimpleNamespace as NS

    from vio.config import LoopConfig
    from vio.loop.closer import LoopCloser
    from vio.loop.posegraph import Edge, PoseGraph

    me = NS(_component={0: 0, 1: 0, 2: 1}, map_keyframes=2, cfg=LoopConfig(),
            keyframes=[NS(session=0), NS(session=0), NS(session=1), NS(session=1), NS(session=2)],
            graph=NS(edges=[Edge(2, 0, np.eye(4), "odometry"), Edge(0, 2, np.eye(4), "loop", weight=0.0),
                            Edge(2, 4, np.eye(4), "loop", weight=1.0), Edge(3, 3, np.eye(4), "loop")]))
    me._comp = lambda s: LoopCloser._comp(me, s)
    me._join = lambda a, b: LoopCloser._join(me, a, b)
    me.graph.active_loops = lambda: PoseGraph.active_loops(me.graph)
    assert LoopCloser.relocalised.fget(me)  # session 2 joined through session 1 to the map, so far
    LoopCloser._rejoin(me)
    assert me._comp(1) == 1 and me._comp(2) == 1 and me._comp(0) == 0  # the edge to the map is off
    assert not LoopCloser.relocalised.fget(me)
    me.graph.edges[1].weight = 1.0  # GNC takes it back in
    LoopCloser._rejoin(me)
    assert me._comp(2) == 0 and LoopCloser.relocalised.fget(me)


def test_after_an_estimator_reset_a_solve_of_the_new_segments_own_frame_is_not_taken():
    """After a reset the correction held still maps the new segment (the reset keeps the last pose as origin), but
    the next solve (deferred edges flushed, a closure inside the new segment) gave that segment's own frame with a
    new version: blend walked the vehicle metres off the map with mm covariance and jump threw the map's frame
    away (a review's finding). A solve is taken again once the segment is joined, or for the same segment."""
    from vio.loop.output import CorrectedOutput, CorrectionUncertainty
    from vio.types import NavState

    C = make_T(so3_exp(np.radians([0, 0, 35.0])), [6.0, -4.0, 0])
    unc = CorrectionUncertainty(np.eye(4) * 1e-2, np.zeros(3))
    for mode in ("jump", "blend"):
        out = CorrectedOutput(mode, blend_rate_m_s=1e3, blend_rate_deg_s=1e6)
        st = [NavState(int(k * 1e8), make_T(np.eye(3), [1.0, 0, 0]), np.zeros(3), cov_pose=np.eye(6) * 1e-6)
              for k in range(6)]
        held = out.apply(st[0], C, 1, unc, 1, False)  # relocalised: session 1 joined to the map
        held = out.apply(st[1], C, 1, unc, 1, False)
        # estimator reset: session 2 in a frame of its own, and a solve (version 2) gives its own frame
        after = out.apply(st[2], np.eye(4), 2, None, 2, True)
        assert np.allclose(after.T_world_body, held.T_world_body)
        assert after.cov_pose[3, 3] == pytest.approx(held.cov_pose[3, 3]) and after.reset_counter == held.reset_counter
        C2 = make_T(so3_exp(np.radians([0, 0, 36.0])), [6.1, -4.0, 0])
        joined = out.apply(st[3], C2, 3, unc, 2, False)  # a closure joins session 2 to the map: taken
        out.apply(st[4], C2, 3, unc, 2, False)
        assert np.allclose(out.apply(st[5], C2, 3, unc, 2, False).T_world_body, C2 @ st[5].T_world_body)
        assert mode == "blend" or joined.reset_counter == held.reset_counter + 1
    # the flight's own segment: every solve is taken, in its own frame too (drift corrections before any map)
    out = CorrectedOutput("jump")
    s = NavState(0, np.eye(4), np.zeros(3))
    out.apply(s, make_T(np.eye(3), [0.1, 0, 0]), 1, None, 0, True)
    assert out.apply(s, make_T(np.eye(3), [0.2, 0, 0]), 2, None, 0, True).T_world_body[0, 3] == pytest.approx(0.2)


def test_a_restarted_output_applies_no_correction_and_takes_none_of_the_old_estimators_segments():
    """A re-created estimator (the daemon's fallback when reset() fails) has a frame no correction held maps."""
    from vio.loop.output import CorrectedOutput, CorrectionUncertainty
    from vio.types import NavState

    C = make_T(so3_exp(np.radians([0, 0, 35.0])), [6.0, -4.0, 0])
    unc = CorrectionUncertainty(np.eye(4) * 1e-2, np.zeros(3))
    s = NavState(0, np.eye(4), np.zeros(3), cov_pose=np.eye(6) * 1e-6)
    for mode in ("jump", "blend"):
        out = CorrectedOutput(mode, blend_rate_m_s=1e3, blend_rate_deg_s=1e6)
        out.apply(s, C, 4, unc, 1, False, 0)
        out.restart(3)  # the new estimator's keyframes go to the loop stage with counter 3 on
        sent = out.apply(s, C, 5, unc, 1, False, 0)  # a late solve of the old estimator's segment
        assert np.allclose(sent.T_world_body, np.eye(4)) and sent.cov_pose[3, 3] == pytest.approx(1e-6)
        # the loop stage still behind: the old estimator's reset segment (2, counter 1), even joined, is not taken
        assert np.allclose(out.apply(s, C, 6, unc, 2, False, 1).T_world_body, np.eye(4))
        C3 = make_T(np.eye(3), [0.3, 0, 0])
        out.apply(s, C3, 7, None, 3, True, 3)  # the new estimator's segment, its own frame: taken
        later = NavState(10**9, np.eye(4), np.zeros(3), cov_pose=np.eye(6) * 1e-6)
        assert out.apply(later, C3, 7, None, 3, True, 3).T_world_body[0, 3] == pytest.approx(0.3)


@pytest.mark.parametrize("mode", ["jump", "blend"])
def test_a_restarted_output_does_not_take_the_old_estimators_correction_while_a_join_is_unconfirmed(mode):
    """The daemon re-creates a failing estimator (no state came out while it failed, so the output had not taken
    the loop stage's last solve of the old estimator's keyframes), and the new estimator's first keyframe joins
    another frame by one edge at once (a take-off where the map was made): the worker keeps the correction it
    handed over while the join is unconfirmed, but labelled it with the new keyframe's reset_counter, so the output
    took the OLD estimator's correction for the new odometry: 2 m off, in a frame nothing maps (a review's
    finding)."""
    from vio.app.loop_worker import LoopWorker
    from vio.config import LoopConfig
    from vio.loop.output import CorrectedOutput
    from vio.types import NavState

    class Closer(_StubCloser):
        cfg = LoopConfig()
        seg, unconfirmed = (0, True), False

        def add_keyframe(self, t_ns, T, image, ff, counter):
            self.graph.estimate_version += 1
            if counter == 0:  # the old estimator's closure: drift taken out of its own frame
                self.corr = make_T(np.eye(3), [2.0, 0, 0])
            elif self.seg[0] == 0:  # the new estimator's first keyframe, joined to another frame by one edge
                self.corr = make_T(np.eye(3), [-3.0, 1.0, 0])
                self.seg, self.unconfirmed = (1, False), True
            return True

        def correction_segment(self):
            return self.seg

        def placement_unconfirmed(self):
            return self.unconfirmed

    c = Closer()
    w = LoopWorker(c, max_queue=10)
    out = CorrectedOutput(mode, blend_rate_m_s=1e3, blend_rate_deg_s=1e6)
    out.apply(NavState(0, np.eye(4), np.zeros(3)), *w.correction())
    w.submit(1, np.eye(4), None, None, 0)
    w._q.join()  # solved; no state applies it (the estimator is failing)
    out.restart(1)  # the daemon's new estimator: its keyframes go with reset_counter 1 on
    w.submit(2, np.eye(4), None, None, 1)
    w._q.join()
    sent = out.apply(NavState(10**8, np.eye(4), np.zeros(3)), *w.correction())
    assert np.allclose(sent.T_world_body, np.eye(4)), sent.T_world_body
    c.unconfirmed = False  # confirmed: the join's frame is handed over, and taken
    w.submit(3, np.eye(4), None, None, 1)
    w._q.join()
    sent = out.apply(NavState(2 * 10**8, np.eye(4), np.zeros(3)), *w.correction())
    assert np.allclose(sent.T_world_body[:3, 3], [-3.0, 1.0, 0])
    assert w.close(wait=True, timeout_s=5.0)


def test_a_blend_walks_no_further_over_a_gap_in_states_than_over_a_quarter_second():
    """A 30 s gap between two states (a stall) let the blend take one 6 m step (a review's finding)."""
    from vio.loop.output import MAX_BLEND_STEP_S, CorrectedOutput
    from vio.types import NavState

    out = CorrectedOutput("blend", blend_rate_m_s=0.2, blend_rate_deg_s=5.0)
    C = make_T(np.eye(3), [10.0, 0, 0])
    out.apply(NavState(0, np.eye(4), np.zeros(3)), C, 1)
    sent = out.apply(NavState(30 * 10**9, np.eye(4), np.zeros(3)), C, 1)
    assert sent.T_world_body[0, 3] == pytest.approx(0.2 * MAX_BLEND_STEP_S)


def test_jump_counts_no_jump_for_the_same_yaw_on_either_side_of_pi():
    from vio.loop.output import CorrectedOutput
    from vio.types import NavState

    out = CorrectedOutput("jump")
    s = NavState(0, np.eye(4), np.zeros(3))
    out.apply(s, make_T(so3_exp(np.r_[0, 0, np.pi - 1e-12]), np.zeros(3)), 1)
    out.apply(s, make_T(so3_exp(np.r_[0, 0, -np.pi + 1e-12]), np.zeros(3)), 2)
    assert out.jumps == 1


def test_one_non_finite_pose_does_not_stop_the_blend_for_the_rest_of_the_flight():
    """A state whose position is NaN (the MAVLink output refuses it, "a loss of tracking until it is whole again")
    went into the blend's walk: the applied correction became NaN, and every later pose with it, so the autopilot
    got no pose for the rest of the flight (a review's finding)."""
    from vio.loop.output import CorrectedOutput
    from vio.types import NavState

    C = make_T(so3_exp(np.array([0, 0, 0.1])), [1.0, 0, 0])
    out = CorrectedOutput("blend", blend_rate_m_s=0.5, blend_rate_deg_s=5.0)
    bad = np.eye(4)
    bad[0, 3] = np.nan
    sent = [out.apply(NavState(int(k * 1e8), bad if k == 5 else np.eye(4), np.zeros(3)), C, 1) for k in range(40)]
    assert all(np.isfinite(o.T_world_body).all() for k, o in enumerate(sent) if k != 5)
    x = np.array([o.T_world_body[0, 3] for k, o in enumerate(sent) if k != 5])
    assert np.all(np.abs(np.diff(x)) <= 0.5 * 0.2 + 1e-9) and x[-1] == pytest.approx(1.0)  # bounded, then there
    assert np.isfinite(out.remaining_m) and out.remaining_m == 0.0


@pytest.mark.parametrize("mode", ["jump", "blend"])
def test_a_non_finite_correction_is_not_taken(mode):
    """A correction with a NaN in it would make every pose sent NaN until the next solve (each refused by the
    MAVLink output): the one held is kept, and reset_counter does not move for it."""
    from vio.loop.output import CorrectedOutput
    from vio.types import NavState

    out = CorrectedOutput(mode, blend_rate_m_s=1e3, blend_rate_deg_s=1e6)
    C = make_T(np.eye(3), [0.5, 0, 0])
    out.apply(NavState(0, np.eye(4), np.zeros(3)), C, 1)
    sent = out.apply(NavState(10**8, np.eye(4), np.zeros(3)), np.full((4, 4), np.nan), 2)
    assert np.isfinite(sent.T_world_body).all() and sent.T_world_body[0, 3] == pytest.approx(0.5)
    assert sent.reset_counter == (1 if mode == "jump" else 0)
    C2 = make_T(np.eye(3), [0.7, 0, 0])
    sent = out.apply(NavState(2 * 10**8, np.eye(4), np.zeros(3)), C2, 3)  # the next solve is taken
    assert sent.T_world_body[0, 3] == pytest.approx(0.7) and sent.reset_counter == (2 if mode == "jump" else 0)


def test_jump_far_from_the_odometrys_origin_counts_every_step():
    """The jump test compared the new translation with np.allclose's default relative tolerance: 1 km from the
    odometry's origin a 9 mm step (10 km out: 9 cm) went out without a reset_counter increment, for the autopilot
    to fuse as a sudden error (a review's finding)."""
    from vio.loop.output import CorrectedOutput
    from vio.types import NavState

    out = CorrectedOutput("jump")
    s = NavState(0, np.eye(4), np.zeros(3))
    a = out.apply(s, make_T(np.eye(3), [1000.0, 0, 0]), 1)
    b = out.apply(s, make_T(np.eye(3), [1000.009, 0, 0]), 2)
    assert b.T_world_body[0, 3] - a.T_world_body[0, 3] == pytest.approx(0.009)
    assert b.reset_counter == a.reset_counter + 1
    assert out.apply(s, make_T(np.eye(3), [1000.009, 0, 0]), 3).reset_counter == b.reset_counter  # no step: none


def test_the_loop_stage_says_which_segment_its_correction_is_for_and_whether_it_is_joined():
    from vio.config import VioConfig
    from vio.loop.closer import LoopCloser
    from vio.loop.features import KeyframeFeatures
    from vio.sim import default_calibration

    cl = LoopCloser(default_calibration(), VioConfig().loop)
    f = KeyframeFeatures(np.zeros((3, 32), np.uint8), np.zeros((3, 2)), np.zeros((3, 3)))
    cl.extractor.extract = lambda image, ff: f
    cl._detect = lambda i, bow: False
    assert cl.correction_segment() == (0, True)
    cl.add_keyframe(0, np.eye(4), None, None, 0)
    assert cl.correction_segment() == (0, True)
    cl.add_keyframe(10**9, make_T(np.eye(3), [1.0, 0, 0]), None, None, 1)  # an estimator reset
    assert cl.correction_segment() == (1, True)
    cl._join(0, 1)
    assert cl.correction_segment() == (1, False)


def test_one_edge_to_a_loaded_map_is_not_made_consistent_by_an_edge_within_the_flight():
    """Temporal consistency counts candidates of the newest one's kind only: one map edge and one agreeing edge
    within the flight (frames that nearly coincide: a take-off from the map's pad) passed min_consistent (2) and
    joined the flight to the map on one edge, where reloc_min_consistent asks for 3 (a review's finding)."""
    from types import SimpleNamespace as NS

    from vio.config import VioConfig
    from vio.loop.closer import LoopCloser, _Candidate
    from vio.loop.features import KeyframeFeatures
    from vio.sim import default_calibration

    calib = default_calibration()
    cfg = VioConfig().loop
    assert cfg.min_consistent == 2 and cfg.reloc_min_consistent == 3
    cl = LoopCloser(calib, cfg)
    f = KeyframeFeatures(np.zeros((3, 32), np.uint8), np.zeros((3, 2)), np.zeros((3, 3)))
    cl.extractor.extract = lambda image, ff: f
    cl._detect = lambda i, bow: False
    n = 10
    cl.load_map(NS(t_ns=np.arange(n), T_world_body=[np.eye(4)] * n, features=[f] * n,
                   header={"camera": {"width": calib.cam0.width, "height": calib.cam0.height, "fx": calib.cam0.fx}}))
    for k in range(30):
        cl.add_keyframe(10**10 + k * 10**9, make_T(np.eye(3), [0.1 * k, 0, 0]), None, None, 0)
    eye = np.eye(4)
    cl._pending = [_Candidate(n + 28, 3, eye, eye, 15), _Candidate(n + 29, n + 5, eye, eye, 40)]
    assert not cl._consistent(n + 29)  # the newest (within the flight) has one of its kind
    cl._pending.append(_Candidate(n + 29, 4, eye, eye, 15))
    assert not cl._consistent(n + 29) and not cl.relocalised  # two map edges: reloc_min_consistent is 3
    assert not any(e.kind == "loop" for e in cl.graph.edges)
    cl._pending.append(_Candidate(n + 29, 5, eye, eye, 15))
    # three map edges agree (two from one keyframe count once): keyframes 38 and 39 only
    assert not cl._consistent(n + 29)
    cl._pending.append(_Candidate(n + 27, 6, eye, eye, 15))
    assert cl._consistent(n + 27) and cl.relocalised


def test_a_map_made_with_another_camera_mount_is_placed_by_its_cameras(tmp_path, caplog):
    """A map stores body poses: flown with the camera re-mounted (or the IMU changed), today's T_body_cam put every
    map camera elsewhere and a relocalised flight sat 0.3-0.5 m off in the map's frame, unsaid (a review's
    finding). The map now keeps its mount and its keyframes are placed by their cameras; an older map without it
    is taken as made with this mount; a mount that is not a rigid transform is a damaged map."""
    import dataclasses
    import json

    from vio import VioError
    from vio.config import VioConfig
    from vio.loop.closer import LoopCloser
    from vio.loop.features import KeyframeFeatures
    from vio.loop.mapfile import load_map, save_map
    from vio.loop.vocabulary import Vocabulary
    from vio.sim import default_calibration

    calib = default_calibration()
    f = KeyframeFeatures(np.zeros((3, 32), np.uint8), np.zeros((3, 2)), np.zeros((3, 3)))
    T_kf = [make_T(so3_exp(np.r_[0.1, -0.05, 0.3 * k]), [k, 2.0, 1.0]) for k in range(3)]
    old_mount = make_T(so3_exp(np.radians([0, 0, 10.0])), [0.1, 0, 0]) @ calib.cam0.T_body_cam
    save_map(tmp_path / "m.npz", [1, 2, 3], T_kf, [f] * 3, Vocabulary.load(),
             dataclasses.replace(calib.cam0, T_body_cam=old_mount))
    cl = LoopCloser(calib, VioConfig().loop)
    with caplog.at_level("WARNING", logger="vio.loop.closer"):
        cl.load_map(load_map(tmp_path / "m.npz"))
    assert "camera 10.00 deg and" in caplog.text and cl.map_mount_change[0] == pytest.approx(10.0, abs=0.01)
    for k in range(3):  # the map's cameras where they were
        np.testing.assert_allclose(cl.graph.odom[k] @ calib.cam0.T_body_cam, T_kf[k] @ old_mount, atol=1e-9)
    # the same mount: poses as saved; an older map without the mount: as saved
    for mount in (calib.cam0.T_body_cam, None):
        save_map(tmp_path / "s.npz", [1, 2, 3], T_kf, [f] * 3, Vocabulary.load(), calib.cam0)
        if mount is None:
            z = dict(np.load(tmp_path / "s.npz"))
            h = json.loads(str(z["header"]))
            del h["camera"]["T_body_cam"]
            np.savez(tmp_path / "s.npz", **{**z, "header": np.array(json.dumps(h))})
        cl = LoopCloser(calib, VioConfig().loop)
        cl.load_map(load_map(tmp_path / "s.npz"))
        assert cl.map_mount_change is None
        np.testing.assert_allclose(np.array(cl.graph.odom[:3]), np.array(T_kf), atol=1e-12)
    z = dict(np.load(tmp_path / "m.npz"))
    h = json.loads(str(z["header"]))
    h["camera"]["T_body_cam"] = [[2.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    np.savez(tmp_path / "bad.npz", **{**z, "header": np.array(json.dumps(h))})
    with pytest.raises(VioError, match="damaged map.*T_body_cam"):
        load_map(tmp_path / "bad.npz")


def test_a_damaged_vocabulary_file_is_one_line_error(tmp_path, capsys):
    """A [loop] vocabulary cut short, empty, or with a flipped byte ended `vio replay` / `vio config check` in an
    "internal error" (BadZipFile, EOFError, zlib.error, tokenize.TokenError, NotImplementedError): now the one-line
    error that says what to do."""
    import zipfile

    from vio import VioError
    from vio.app.cli import main
    from vio.loop.vocabulary import DEFAULT_PATH, Vocabulary

    good = DEFAULT_PATH.read_bytes()
    flipped = _byte_flipped(good, 4876)  # inside a compressed member: zlib's "invalid distance too far back"
    for name, data in (("cut.npz", good[: len(good) // 2]), ("empty.npz", b""), ("flip.npz", flipped)):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(VioError, match="cannot read the vocabulary.*train-vocab"):
            Vocabulary.load(tmp_path / name)
        cfg = tmp_path / "c.toml"
        cfg.write_text(f"[loop]\nenabled = true\nvocabulary = '{tmp_path / name}'\n")
        assert main(["-q", "config", "check", str(cfg)]) == 3
        err = capsys.readouterr().err
        assert "[loop] vocabulary:" in err and "internal error" not in err and len(err.strip().splitlines()) == 1
    # a flip in an array's .npy header (numpy's TokenError) or in the archive's directory (NotImplementedError)
    with zipfile.ZipFile(DEFAULT_PATH) as zf:
        spots = [i.header_offset + 30 + len(i.filename) + k for i in zf.infolist() for k in range(80)]
        spots += range(zf.start_dir, len(good))
    _load_each_byte_flipped(good, spots, tmp_path / "flip.npz", Vocabulary.load)


def test_a_vocabulary_that_does_not_fit_orb_descriptors_is_refused_at_load(tmp_path):
    """A vocabulary of another descriptor (512-bit, or float centres) loaded and retrieved nothing, silently (every
    keyframe "no candidate"); a k or idf that did not fit its centres stopped the loop stage mid-flight
    (IndexError, ZeroDivisionError) with the replay going on without loop closure. Refused at load, in one line."""
    from vio import VioError
    from vio.loop.vocabulary import DEFAULT_PATH, Vocabulary

    z = dict(np.load(DEFAULT_PATH))
    n = len(z["centres"])
    for change, says in ((dict(centres=np.zeros((n, 64), np.uint8)), r"\(4681, 64\) uint8"),
                         (dict(centres=np.zeros((n, 128), np.float32)), "float32"),
                         (dict(k=np.int64(4)), r"needs \(341, 32\)"),
                         (dict(k=np.int64(1)), "branching >= 2"),
                         (dict(depth=np.int64(0)), "depth >= 1"),
                         (dict(idf=z["idf"][:10]), "4096 finite weights"),
                         (dict(idf=np.full(4096, np.nan, np.float32)), "4096 finite weights")):
        np.savez(tmp_path / "v.npz", **{**z, **change})
        with pytest.raises(VioError, match=f"not a vocabulary of ORB descriptors.*{says}.*train-vocab"):
            Vocabulary.load(tmp_path / "v.npz")
    np.savez(tmp_path / "v.npz", **z)
    assert Vocabulary.load(tmp_path / "v.npz").n_words == 4096


def test_train_vocab_on_unreadable_images_says_how_many_it_could_read(tmp_path, capsys):
    """A recording whose images are all missing or unreadable ended in "too few images to train a vocabulary", which
    did not say that the images were there but could not be read, nor how many were tried."""
    from vio.app.cli import main
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "flight"
    simulate(data, SimConfig(duration_s=1.0, width=376, height=240, variant="clean"), progress=False)
    for f in (data / "mav0" / "cam0" / "data").glob("*.png"):
        f.write_bytes(b"not a png")
    assert main(["loop", "train-vocab", str(data), "-o", str(tmp_path / "v.npz"), "--every", "4"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "0 of the 6 left images taken (--every 4) could be read" in err and "missing or unreadable" in err, err


def test_train_vocab_cli_writes_the_file_it_names_and_refuses_bad_settings(tmp_path, capsys):
    """`-o voc.map` wrote voc.map.npz and printed voc.map; an existing file was replaced without asking; depth 0
    trained a one-word vocabulary (exit 0), branching 1 and every 0 ended in internal errors (a QA sweep)."""
    from vio.app.cli import main
    from vio.loop.vocabulary import Vocabulary
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "flight"
    simulate(data, SimConfig(duration_s=3.0, width=376, height=240, variant="clean"), progress=False)
    out = tmp_path / "voc.map"
    assert main(["-q", "loop", "train-vocab", str(data), "-o", str(out), "--every", "4", "--depth", "2"]) == 0
    assert str(out) in capsys.readouterr().out and out.is_file() and not (tmp_path / "voc.map.npz").exists()
    voc = Vocabulary.load(out)
    assert (voc.k, voc.depth) == (8, 2)
    before = out.read_bytes()
    assert main(["-q", "loop", "train-vocab", str(data), "-o", str(out), "--every", "4"]) == 1
    assert "exists: not replaced" in capsys.readouterr().err and out.read_bytes() == before
    for bad in (["--depth", "0"], ["--branching", "1"], ["--every", "0"], ["--features", "-3"]):
        with pytest.raises(SystemExit) as e:
            main(["loop", "train-vocab", str(data), "-o", str(tmp_path / "v2.npz"), *bad])
        assert e.value.code == 2 and "must be at least" in capsys.readouterr().err, bad
    assert main(["-q", "loop", "train-vocab", str(data), "-o", str(data / "mav0" / "voc.npz")]) == 1
    assert "into the recording" in capsys.readouterr().err
    # internal errors (MemoryError asking 260 PiB, numpy's "maximum dimension", OpenCV's C int) and a branching
    # beyond the descriptors said as "no ORB corners to speak of" (a review's finding)
    with pytest.raises(SystemExit) as e:
        main(["loop", "train-vocab", str(data), "-o", str(tmp_path / "v2.npz"), "--features", "999999999999999"])
    assert e.value.code == 2 and "--features: must be at most 100000" in capsys.readouterr().err
    for bad in (["--branching", "64", "--depth", "8"], ["--depth", "99999"]):
        assert main(["loop", "train-vocab", str(data), "-o", str(tmp_path / "v2.npz"), *bad]) == 2, bad
        err = capsys.readouterr().err
        assert "words, more than the 1048576 a vocabulary can have" in err and len(err.strip().splitlines()) == 1, err
    assert main(["-q", "loop", "train-vocab", str(data), "-o", str(tmp_path / "v2.npz"), "--every", "4",
                 "--branching", "100000", "--depth", "1"]) == 1
    assert "--branching 100000 needs 200000 descriptors or more" in capsys.readouterr().err
    assert not (tmp_path / "v2.npz").exists()


def test_train_vocab_reads_16_bit_images_as_the_replay_does(tmp_path, capsys):
    """12-bit values in 16-bit PNGs were read with OpenCV's >> 8 (near-black images, few corners): the vocabulary
    trained on them differed from the one the same images give at 8 bits. Now both give the same file."""
    import cv2

    from vio.app.cli import main
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "flight"
    simulate(data, SimConfig(duration_s=2.0, width=376, height=240, variant="clean"), progress=False)
    deep = tmp_path / "deep"
    shutil.copytree(data, deep)
    for f in sorted((deep / "mav0" / "cam0" / "data").glob("*.png")):
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        noise = np.random.default_rng(len(f.name)).integers(0, 16, img.shape, dtype=np.uint16)
        cv2.imwrite(str(f), img.astype(np.uint16) << 4 | noise)  # the same picture as 12-bit values
    outs = []
    for src in (data, deep):
        outs.append(tmp_path / f"{src.name}.npz")
        assert main(["-q", "loop", "train-vocab", str(src), "-o", str(outs[-1]), "--every", "4", "--depth", "2"]) == 0
    capsys.readouterr()
    a, b = np.load(outs[0]), np.load(outs[1])
    assert sorted(a.files) == sorted(b.files)
    for k in a.files:
        assert np.array_equal(a[k], b[k]), k


def test_train_vocab_on_images_without_corners_says_so(tmp_path, capsys):
    """All-black images gave no descriptors and an internal error (numpy's "need at least one array")."""
    import cv2

    from vio.app.cli import main
    from vio.sim.generate import SimConfig, simulate

    data = tmp_path / "flight"
    simulate(data, SimConfig(duration_s=1.0, width=376, height=240, variant="clean"), progress=False)
    for f in (data / "mav0" / "cam0" / "data").glob("*.png"):
        cv2.imwrite(str(f), np.zeros((240, 376), np.uint8))
    assert main(["-q", "loop", "train-vocab", str(data), "-o", str(tmp_path / "v.npz"), "--every", "2"]) == 1
    err = capsys.readouterr().err
    assert "no ORB corners" in err and "internal error" not in err
    assert not (tmp_path / "v.npz").exists()


def test_a_hard_link_to_the_loaded_map_is_the_map_it_grows(tmp_path):
    """The map-replacement check and the output-over-input check compared real paths, which a hard link does not
    share with its file: `--load-map room.npz --save-map alias.npz` (one file, two names) was refused as a map this
    replay does not load, and `-o` onto a hard link of the calibration would have emptied the calibration. Files
    are one when they are one inode (st_dev, st_ino); files not there yet by their real path."""
    from vio import VioError
    from vio.app.replay import check_map_not_replaced
    from vio.io.outputs import check_outputs, same_file

    room, alias, other = tmp_path / "room.npz", tmp_path / "alias.npz", tmp_path / "other.npz"
    room.write_bytes(b"the room's map")
    os.link(room, alias)
    other.write_bytes(b"another map")
    check_map_not_replaced(str(alias), str(room), "--save-map")  # grows the map it loads
    with pytest.raises(VioError, match="this replay does not load it"):
        check_map_not_replaced(str(other), str(room), "--save-map")
    assert same_file(room, alias) and not same_file(room, other)
    assert same_file(tmp_path / "new.tum", tmp_path / "." / "new.tum") and not same_file(room, tmp_path / "new")
    calib = tmp_path / "sensor.yaml"
    calib.write_text("the calibration")
    os.link(calib, tmp_path / "t.tum")
    with pytest.raises(VioError, match="the trajectory would be written over the calibration"):
        check_outputs({"the trajectory": str(tmp_path / "t.tum")}, reads={"the calibration": str(calib)})
    with pytest.raises(VioError, match="the trajectory and the stats would be written to the same file"):
        check_outputs({"the trajectory": str(calib), "the stats": str(tmp_path / "t.tum")})
    check_outputs({"the map": str(alias)}, reads={"the map it loads": str(room)}, grows={"the map": "the map it loads"})


def test_a_map_is_never_renamed_over_a_device_or_pipe(tmp_path, capsys):
    """`vio replay --save-map /dev/full --overwrite-map`, run as root, renamed the map over the device node (a QA
    walk-through: /dev/full became a 16 kB regular file). An existing target that is not a regular file is refused
    before the replay (vio replay, vio run's check) and by save_map itself. A pipe stands in for the device here."""
    from types import SimpleNamespace

    from vio import VioError
    from vio.app.cli import main
    from vio.io.outputs import check_outputs
    from vio.loop.mapfile import save_map

    fifo = tmp_path / "pipe.npz"
    os.mkfifo(fifo)
    with pytest.raises(VioError, match="is not a regular file"):
        check_outputs({"the map": str(fifo)}, renamed=("the map",))
    check_outputs({"the trajectory": str(fifo)}, renamed=("the map",))  # written into, not renamed over: fine
    assert main(["replay", str(tmp_path / "no_flight"), "--save-map", str(fifo), "--overwrite-map"]) == 1
    assert f"{fifo}: is not a regular file" in capsys.readouterr().err
    voc = SimpleNamespace(k=2, depth=1, centres=np.zeros((2, 32), np.uint8), idf=np.ones(2))
    cam = SimpleNamespace(fx=1.0, fy=1.0, cx=0.0, cy=0.0, width=2, height=2, T_body_cam=np.eye(4))
    with pytest.raises(VioError, match="is not a regular file"):
        save_map(fifo, [], np.zeros((0, 4, 4)), [], voc, cam)
    assert fifo.is_fifo() and sorted(p.name for p in tmp_path.iterdir()) == ["pipe.npz"]


def _map_contents() -> tuple:
    """mapfile.save_map's arguments for a map of two keyframes (what it reads of a vocabulary and a camera)."""
    from types import SimpleNamespace

    from vio.loop.features import KeyframeFeatures

    voc = SimpleNamespace(k=2, depth=1, centres=np.zeros((2, 32), np.uint8), idf=np.ones(2))
    cam = SimpleNamespace(fx=200.0, fy=200.0, cx=160.0, cy=100.0, width=320, height=200, T_body_cam=np.eye(4))
    feats = [KeyframeFeatures(np.zeros((3, 32), np.uint8), np.ones((3, 2), np.float32),
                              np.ones((3, 3), np.float32)) for _ in range(2)]
    return [1, 2], np.stack([np.eye(4)] * 2), feats, voc, cam


def test_a_saved_map_survives_a_power_cut_after_its_rename(tmp_path, monkeypatch):
    """A map (and a checkpoint: the same writer) was synced, then renamed over the old one, but the rename lived in
    the page cache until the kernel wrote the folder: a drone's power cut seconds after "map saved" could come back
    with the old map. The folder is synced after the rename; the status file (rewritten every second) is not."""
    import stat

    from vio.app.daemon.status import write_status_file
    from vio.loop.mapfile import load_map, save_map

    events: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        events.append("sync folder" if stat.S_ISDIR(os.fstat(fd).st_mode) else "sync file")
        real_fsync(fd)

    def replace(src, dst) -> None:
        events.append(f"rename to {Path(dst).name}")
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    save_map(tmp_path / "m.npz", *_map_contents())
    assert events == ["sync file", "rename to m.npz", "sync folder"], events
    assert len(load_map(tmp_path / "m.npz").t_ns) == 2
    assert os.listdir(tmp_path) == ["m.npz"]  # no temporary left
    events.clear()
    write_status_file(tmp_path / "status.json", {"state": "ok"})
    assert events == ["rename to status.json"]  # atomic, not synced: rewritten every second


def test_a_map_renamed_into_place_whose_folder_cannot_be_synced_is_not_said_lost(tmp_path, monkeypatch, caplog):
    """The folder's sync after the rename raising (EIO from a failing card) made save_map say 'cannot write the map
    (...); the map that was there is kept' of a map already replaced by the new one (and the daemon 'map not
    saved'). The new map is in place: it is returned as saved, and the lost durability is said in the log."""
    import errno
    import logging
    import stat

    from vio.loop.mapfile import load_map, save_map

    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        if stat.S_ISDIR(os.fstat(fd).st_mode):
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        real_fsync(fd)

    save_map(tmp_path / "m.npz", [5, 6], *_map_contents()[1:])  # the old map
    monkeypatch.setattr(os, "fsync", fsync)
    with caplog.at_level(logging.WARNING, logger="vio.io.atomic"):
        h = save_map(tmp_path / "m.npz", *_map_contents())
    assert h["keyframes"] == 2 and list(load_map(tmp_path / "m.npz").t_ns) == [1, 2]  # the new one
    assert "could not be synced" in caplog.text


def test_a_vocabulary_pipe_a_nan_in_a_map_header_and_partly_infinite_points_are_said_in_one_line(tmp_path, capsys):
    """Leftovers of the map-file review: `Vocabulary.load` of a pipe waited for ever for a writer (maps were guarded,
    vocabularies not); `vio map info --json` printed a header's NaN as NaN, which is not JSON; and a map whose
    stereo points were finite in x and infinite after it loaded (x is what tells a point: fed to the PnP)."""
    import subprocess
    import sys

    from vio.app.cli import main

    fifo = tmp_path / "vocab.npz"
    os.mkfifo(fifo)
    code = ("from vio import VioError\nfrom vio.loop.vocabulary import Vocabulary\n"
            f"try:\n    Vocabulary.load({str(fifo)!r})\nexcept VioError as e:\n    print(e)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       cwd=Path(__file__).resolve().parent.parent)
    assert "is not a regular file" in r.stdout and not r.stderr, (r.stdout, r.stderr)

    cam = '"camera": {"fx": 458.0, "fy": 457.0, "cx": 367.0, "cy": 248.0, "width": 752, "height": 480}'
    hdr = np.array('{"format": "kestrel-vio-map", "version": 1, "note": NaN, "gain": [Infinity, 1.0], ' + cam + '}')
    good = dict(header=hdr, kf_offsets=np.array([0, 3, 5]), desc=np.zeros((5, 32), np.uint8), uv=np.zeros((5, 2)),
                p_cam=np.zeros((5, 3)), kf_t_ns=np.array([1, 2]), kf_T_world_body=np.tile(np.eye(4), (2, 1, 1)))
    np.savez(tmp_path / "nan.npz", **good)
    assert main(["map", "info", "--json", str(tmp_path / "nan.npz")]) == 0

    def no_constant(name: str) -> None:
        raise ValueError(f"{name} is not JSON")
    info = json.loads(capsys.readouterr().out, parse_constant=no_constant)
    assert info["note"] is None and info["gain"] == [None, 1.0] and info["keyframes"] == 2, info

    p = np.zeros((5, 3))
    p[1] = np.nan  # no depth: a map holds such rows
    np.savez(tmp_path / "nodepth.npz", **{**good, "p_cam": p})
    assert main(["map", "info", str(tmp_path / "nodepth.npz")]) == 0
    capsys.readouterr()
    for row in ([1.0, np.inf, 2.0], [1.0, np.nan, 2.0], [-np.inf] * 3):
        p[2] = row
        np.savez(tmp_path / "inf.npz", **{**good, "p_cam": p})
        assert main(["map", "info", str(tmp_path / "inf.npz")]) == 1, row
        err = capsys.readouterr().err
        assert "damaged map (stereo points" in err and len(err.strip().splitlines()) == 1, err


def test_the_loop_worker_says_when_the_correction_is_into_a_loaded_maps_frame():
    """CorrectedOutput takes a start in flight's turn into the autopilot's frame out of a correction into a loaded map's
    frame (the autopilot's already), not out of one into the flight's own (a reset's segment joined back to the first):
    the worker hands over which of the two it is (LoopCloser.relocalised), with the correction, under its lock."""
    from vio.app.loop_worker import LoopWorker

    class Closer(_StubCloser):
        def add_keyframe(self, t_ns, T, image, ff, counter):
            self.graph.estimate_version += 1
            self.relocalised = t_ns >= 2
            return True

    w = LoopWorker(Closer(), max_queue=10)
    try:
        assert w.correction()[-1] is False
        w.submit(1, np.eye(4), None, None, 0)
        w._q.join()
        assert w.correction()[-1] is False
        w.submit(2, np.eye(4), None, None, 0)
        w._q.join()
        assert w.correction()[-1] is True
    finally:
        assert w.close(wait=True, timeout_s=5.0)


def test_a_map_with_unsigned_stamps_beyond_int64_is_refused_not_wrapped(tmp_path, capsys):
    """Keyframe stamps stored as uint64 at 2^63 or above wrapped to negative int64 in load_map's cast: `vio map info`
    said "0.0 s" of [2^63 + 5, 2^63 + 10] and "stamps of several flights" of [1, 2^64 - 1], and a flight
    relocalised in it with wrong stamps, unsaid (a review's finding). Refused as damaged in one line now; uint64
    stamps below 2^63 still load."""
    from vio.app.cli import main

    cam = '"camera": {"fx": 458.0, "fy": 457.0, "cx": 367.0, "cy": 248.0, "width": 752, "height": 480}'
    hdr = np.array('{"format": "kestrel-vio-map", "version": 1, ' + cam + '}')
    good = dict(header=hdr, kf_offsets=np.array([0, 3, 5]), desc=np.zeros((5, 32), np.uint8), uv=np.zeros((5, 2)),
                p_cam=np.zeros((5, 3)), kf_t_ns=np.array([1, 2], np.uint64),
                kf_T_world_body=np.tile(np.eye(4), (2, 1, 1)))
    np.savez(tmp_path / "u64.npz", **good)
    assert main(["map", "info", str(tmp_path / "u64.npz")]) == 0
    capsys.readouterr()
    for stamps in ([2**63 + 5, 2**63 + 10], [1, 2**64 - 1]):
        np.savez(tmp_path / "wrap.npz", **{**good, "kf_t_ns": np.array(stamps, np.uint64)})
        assert main(["map", "info", str(tmp_path / "wrap.npz")]) == 1, stamps
        err = capsys.readouterr().err
        assert "damaged map (keyframe stamp" in err and "beyond int64" in err, err
        assert len(err.strip().splitlines()) == 1, err


def test_a_map_with_complex_or_text_pixels_points_or_poses_is_refused_in_one_line(tmp_path, capsys):
    """Pixels, points or poses stored as complex numbers loaded with their imaginary parts dropped (only a numpy
    ComplexWarning on stderr) and text ones said "could not convert string to float" (a review's finding): each
    is now refused as damaged, naming the array and its type."""
    from vio.app.cli import main

    cam = '"camera": {"fx": 458.0, "fy": 457.0, "cx": 367.0, "cy": 248.0, "width": 752, "height": 480}'
    hdr = np.array('{"format": "kestrel-vio-map", "version": 1, ' + cam + '}')
    good = dict(header=hdr, kf_offsets=np.array([0, 3, 5]), desc=np.zeros((5, 32), np.uint8), uv=np.zeros((5, 2)),
                p_cam=np.zeros((5, 3)), kf_t_ns=np.array([1, 2]), kf_T_world_body=np.tile(np.eye(4), (2, 1, 1)))
    cases = {"uv": good["uv"] + 1j, "p_cam": good["p_cam"].astype(complex),
             "kf_T_world_body": good["kf_T_world_body"].astype(str)}
    for name, bad in cases.items():
        np.savez(tmp_path / "bad.npz", **{**good, name: bad})
        assert main(["map", "info", str(tmp_path / "bad.npz")]) == 1, name
        err = capsys.readouterr().err
        assert f"damaged map ({name} stored as" in err and len(err.strip().splitlines()) == 1, err


def test_a_map_saved_over_another_keeps_the_file_s_permissions(tmp_path):
    """A map (or any file replaced whole) was renamed over by a temporary made with the process's default mode: a map
    kept private (0600) came back readable to every user (0644), one shared with a group for writing (0664) no longer
    writable by the group (a review's finding). The replacement now keeps the target's permissions; a new file gets
    the default as before."""
    from vio.io.atomic import replace_atomically
    from vio.loop.mapfile import save_map

    path = tmp_path / "m.npz"
    save_map(path, *_map_contents())
    old = os.umask(0o022)
    try:
        for mode in (0o600, 0o664, 0o640):
            os.chmod(path, mode)
            save_map(path, *_map_contents())
            assert path.stat().st_mode & 0o7777 == mode, oct(path.stat().st_mode)
        fresh = tmp_path / "new.txt"
        replace_atomically(fresh, lambda f: f.write(b"x"), durable=False)
        assert fresh.stat().st_mode & 0o777 == 0o644
    finally:
        os.umask(old)


def test_a_map_with_a_keyframe_or_a_point_beyond_any_flight_is_refused(tmp_path, capsys):
    """A keyframe 1e300 m from the map's origin, or a stereo point 1e300 m from its camera (finite, rigid, stored as
    float64) loaded: `vio map info` printed the extent '1e+300' and a flight relocalised on it would be placed there
    (a review's finding). Refused as damaged in one line; a map of points without depth (NaN) still loads."""
    from vio.app.cli import main

    cam = '"camera": {"fx": 458.0, "fy": 457.0, "cx": 367.0, "cy": 248.0, "width": 752, "height": 480}'
    hdr = np.array('{"format": "kestrel-vio-map", "version": 1, ' + cam + '}')
    good = dict(header=hdr, kf_offsets=np.array([0, 3, 5]), desc=np.zeros((5, 32), np.uint8), uv=np.zeros((5, 2)),
                p_cam=np.full((5, 3), np.nan), kf_t_ns=np.array([1, 2]), kf_T_world_body=np.tile(np.eye(4), (2, 1, 1)))
    np.savez(tmp_path / "nodepth.npz", **good)
    assert main(["map", "info", str(tmp_path / "nodepth.npz")]) == 0
    capsys.readouterr()
    far_T = good["kf_T_world_body"].copy()
    far_T[1, 0, 3] = 1e300
    far_p = np.zeros((5, 3))
    far_p[2] = [0.0, 0.0, 1e300]
    for change, says in ((dict(kf_T_world_body=far_T), "damaged map (a keyframe 1e+300 m from the map's origin"),
                         (dict(p_cam=far_p), "damaged map (a stereo point 1e+300 m from its camera")):
        np.savez(tmp_path / "far.npz", **{**good, **change})
        assert main(["map", "info", str(tmp_path / "far.npz")]) == 1, says
        err = capsys.readouterr().err
        assert says in err and len(err.strip().splitlines()) == 1, err


def test_a_map_of_a_start_in_flight_is_saved_in_the_autopilots_frame(loop_flight, tmp_path):
    """A process started in flight sends its poses turned and shifted into the autopilot's frame, and the next
    restart that relocalises in its checkpoint takes its own turn out of the correction (the map's frame is taken
    as the autopilot's). Saved in the process's own frame, the map put that restart's poses off by the first
    restart's turn (a crash in flight after a restart in flight). The flight's own frame is saved turned; a loaded
    map's frame is not."""
    import cv2

    from vio.config import LoopConfig
    from vio.io.euroc import EurocDataset
    from vio.loop.closer import LoopCloser
    from vio.loop.mapfile import load_map

    ds = EurocDataset(loop_flight)
    closer = LoopCloser(ds.calibration, LoopConfig())
    img = cv2.imread(str(ds.cam0_files[10]), cv2.IMREAD_GRAYSCALE)
    poses = [make_T(np.eye(3), [0.5 * k, 0, 0]) for k in range(3)]
    for k, T in enumerate(poses):
        closer.add_keyframe(int(1e9 * k), T, img, None)
    c, s = np.cos(2.0), np.sin(2.0)
    turn = make_T(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), [3.0, -1.0, 0.5])
    closer.save_map(tmp_path / "m.npz", world_turn=turn)
    m = load_map(tmp_path / "m.npz")
    np.testing.assert_allclose(np.asarray(m.T_world_body), [turn @ T for T in poses], atol=1e-9)
    again = LoopCloser(ds.calibration, LoopConfig())
    again.load_map(m)
    again.save_map(tmp_path / "m2.npz", world_turn=turn)  # the loaded map's keyframes: its frame, not turned again
    np.testing.assert_allclose(np.asarray(load_map(tmp_path / "m2.npz").T_world_body), np.asarray(m.T_world_body),
                               atol=1e-9)
