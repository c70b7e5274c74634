"""Relocalisation in a saved map: how soon, how often, and how accurately a second flight joins the map.

    python bench/loop_reloc.py [--starts 20] [--cache DIR] [--json out.json]
    python bench/loop_reloc.py --check f1.json f2_loop.tum f2.json FLIGHT2   # one replay's ATE in the map frame

Default mode: the map flight (survey or --map-profile mapping / laps, 40 s or --map-duration, seed 2, 376x240 or --size,
realistic) and a second flight in the same room (survey, 30 s, seed 12 or each of --second-seeds, scene seed 2:
other path and start) are
simulated once into --cache and replayed once each; their keyframes (image, features, odometry pose) are kept. The
map is the first flight's loop-corrected keyframes, saved and loaded through the map file. Each start feeds a fresh
loop stage, the map loaded, with the second flight's keyframes from start k on (starts spread evenly over its first
60 %: each start's first keyframe is a moving one). Reported per start: the delay from its first keyframe to the
keyframe that joined the map, and to the first keyframe at which it is joined by true edges with no false one active
("placed right": in a repeated room a first join can be three consistent look-alikes 1.5 m off, which GNC takes out
later and the first delay counts as relocalised), edges with an error against ground truth > 0.2 m or 3 deg (false)
at the end, and the ATE of the
relocalised keyframes in the map's frame (flight 1's ground-truth alignment applied, no alignment of their own)
against the second flight's odometry ATE (its own 4-DoF alignment). The odometry of a start is the one run's
odometry from that keyframe on (the estimator is not restarted per start: its pose at the start is already in its
own frame, which the new session's loose prior ignores).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


COVERED_DEG = 25.0  # a start "sees a mapped view" when a map keyframe within 1 m looked this close to its way
EVIDENCE_S = 2.0  # --evidence: the part of each start whose candidates are all verified (the 2 s)


def _false_edge(G_old: np.ndarray, G_new: np.ndarray, T_old_new: np.ndarray) -> bool:
    """Is a loop edge (T_old_new between keyframes whose ground-truth body poses are G_old, G_new) more than 0.2 m or
    3 deg off the truth: a look-alike place, not the place?"""
    from vio.geometry import inv_T, so3_log

    err = inv_T(inv_T(G_old) @ G_new) @ T_old_new
    return bool(np.linalg.norm(err[:3, 3]) > 0.2 or np.degrees(np.linalg.norm(so3_log(err[:3, :3]))) > 3)


def _evidence(calib, cfg, m, rec, start: int, G_map: list, gt) -> list[dict]:
    """Every retrieval candidate of each keyframe in a start's first EVIDENCE_S, each put through every gate
    (`LoopCloser.verify`; the loop stage stops at the first verified one) with no join ever made, so the flight stays
    relocalising throughout: per keyframe its time from the start and, per candidate in the order retrieved, the map
    keyframe, the gate that refused it, or its inliers, correction (x, y, z, yaw) and whether it is a look-alike.
    What a join rule could have known: `_first_join` replays rules on it."""
    from loop_closure import _gt_pose, _Recorder

    from vio.geometry import yaw_of
    from vio.loop.closer import LoopCloser

    kfs: list[dict] = []

    class AllCandidates(LoopCloser):
        def _detect(self, i, bow) -> bool:
            kf = self.keyframes[i]
            row = {"t_s": (kf.t_ns - self.keyframes[self.map_keyframes].t_ns) * 1e-9, "candidates": []}
            for j, _score in self.candidates(i, bow):
                cand, why = self.verify(i, j)
                c = {"map_keyframe": j, "refused": why}
                if cand is not None:
                    c.update(inliers=cand.inliers, lookalike=_false_edge(G_map[j], _gt_pose(gt, kf.t_ns), cand.T_j_i),
                             correction=[*map(float, cand.correction[:3, 3]), float(yaw_of(cand.correction[:3, :3]))])
                row["candidates"].append(c)
            kfs.append(row)
            return False

    t_end = rec.items[start][0] + int(EVIDENCE_S * 1e9)
    end = start + sum(1 for it in rec.items[start:] if it[0] <= t_end)
    part = _Recorder()
    part.items, part.settles = rec.items[:end], [x for x in rec.settles if x[0] <= end]
    cl = AllCandidates(calib, cfg)
    cl.load_map(m)
    part.feed(cl, start=start)
    return kfs


def _first_join(kfs: list[dict], cfg, rule: str) -> tuple[float, bool] | None:
    """(time, placed right) of the first join the consistency rule (reloc_min_consistent keyframes within
    consistency_window whose corrections agree within consistency_m / consistency_deg) makes on `_evidence`'s
    candidates, or None: with rule "first" the first verified candidate of each keyframe (the loop stage's rule),
    with "oracle" the first verified true one (every look-alike edge refused: what no rule can beat)."""
    pending: list[tuple[int, dict]] = []
    for k, row in enumerate(kfs):
        pending = [(n, c) for n, c in pending if k - n <= cfg.consistency_window]
        ok = [c for c in row["candidates"] if not c["refused"] and (rule == "first" or not c["lookalike"])]
        if not ok:
            continue
        new = ok[0]
        pending.append((k, new))

        def agrees(c: dict, new: dict = new) -> bool:
            dyaw = (c["correction"][3] - new["correction"][3] + np.pi) % (2 * np.pi) - np.pi
            return bool(np.linalg.norm(np.subtract(c["correction"][:3], new["correction"][:3])) <= cfg.consistency_m
                        and abs(np.degrees(dyaw)) <= cfg.consistency_deg)
        agree = [(n, c) for n, c in pending if agrees(c)]
        if len({n for n, _ in agree}) >= cfg.reloc_min_consistent:
            return row["t_s"], not any(c["lookalike"] for _, c in agree)
    return None


def check(map_stats: str, est2: str, stats2: str, ds2: str) -> int:
    """One replay pair (vio replay --save-map / --load-map): flight 2's ATE in the map's frame."""
    from vio.evaluation import load_trajectory
    from vio.io.euroc import EurocDataset

    A = np.array(json.load(open(map_stats))["loop"]["evaluation"]["ate_4dof"]["T_gtworld_estworld"])
    s2 = json.load(open(stats2))
    delay = s2["loop"]["relocalisation"]["delay_s"]
    if delay is None:
        print("flight 2 did not relocalise")
        return 1
    gt = EurocDataset(ds2).groundtruth.trajectory
    tr = load_trajectory(est2)
    k = tr.t_ns >= tr.t_ns[0] + int((delay + 0.5) * 1e9)  # after the relocalising keyframe (+ margin)
    p = (A[:3, :3] @ tr.p[k].T).T + A[:3, 3]
    g = np.array([gt.p[np.argmin(np.abs(gt.t_ns - t))] for t in tr.t_ns[k]])
    print(f"relocalised after {delay:.1f} s; ATE in the map's frame {np.sqrt(np.mean(np.sum((p - g) ** 2, 1))):.4f} m "
          f"over {int(k.sum())} poses; odometry ATE (own alignment) "
          f"{s2['evaluation']['ate_4dof']['trans_m']['rmse']:.4f} m")
    return 0


def _keyframes(data: Path, sim_kw: dict):
    from loop_closure import _Recorder

    from vio.app.replay import replay
    from vio.config import VioConfig
    from vio.io.euroc import EurocDataset
    from vio.sim.generate import SimConfig, simulate

    if not (data / "mav0").is_dir():
        simulate(data, SimConfig(variant="realistic", **{"profile": "survey", "width": 376, "height": 240, **sim_kw}),
                 overwrite=True, progress=False)
    rec = _Recorder()
    res = replay(EurocDataset(data), VioConfig(), progress=False, loop=rec)
    return rec, res


def multi_start(starts: int, cache: Path, aliasing: float | None = None, map_s: float = 40.0,
                map_profile: str = "survey", grow: tuple[int, ...] = (), size: tuple[int, int] = (376, 240),
                second_seeds: tuple[int, ...] = (12,), grow_profile: str = "survey", config: str | None = None,
                evidence: bool = False) -> dict:
    from loop_closure import _gt_pose

    from vio.config import VioConfig, load_config
    from vio.evaluation import evaluate
    from vio.io.euroc import EurocDataset
    from vio.loop.closer import LoopCloser
    from vio.loop.mapfile import load_map
    from vio.trajectory import Trajectory

    full = load_config(config) if config else VioConfig()
    cfg, prune = full.loop, (full.map.prune_m, full.map.prune_deg)  # [map] prune_*: the grown maps' saves
    tag = (f"-aliasing{aliasing}m" if aliasing else "") + ("" if size == (376, 240) else f"-{size[0]}x{size[1]}")
    px = {"width": size[0], "height": size[1]}
    d1 = cache / f"map-{map_profile}-seed2-{map_s:g}s{tag}"
    rec1, _ = _keyframes(d1, {"duration_s": map_s, "seed": 2, "aliasing_period_m": aliasing, "profile": map_profile,
                                **px})
    ds1 = EurocDataset(d1)
    gt1 = ds1.groundtruth.trajectory
    mapper = LoopCloser(ds1.calibration, cfg)
    rec1.feed(mapper)
    kt1 = np.array([k.t_ns for k in mapper.keyframes])
    ev1 = evaluate(Trajectory.from_poses(kt1, np.array(mapper.graph.estimate)), gt1)
    A = ev1.ate_4dof.T_gtworld_estworld
    ptag = f"-prune{prune[0]:g}m{prune[1]:g}deg" if prune[0] > 0 else ""
    map_path = cache / f"map-{map_profile}-{map_s:g}s{tag}{ptag}.npz"
    mapper.save_map(map_path, *prune)
    m = load_map(map_path)
    G1 = [_gt_pose(gt1, t) for t in m.t_ns]  # ground truth of each map keyframe (stamps repeat across flights)
    grown = []
    for seed in grow:  # more flights in the same room, each relocalised in the map so far and added to it
        d = cache / f"grow-{grow_profile}-seed{seed}-scene2-{map_s:g}s{tag}"
        rec, _ = _keyframes(d, {"duration_s": map_s, "seed": seed, "scene_seed": 2, "aliasing_period_m": aliasing,
                                  "profile": grow_profile, **px})
        gt = EurocDataset(d).groundtruth.trajectory
        cl = LoopCloser(ds1.calibration, cfg)
        cl.load_map(m)
        rec.feed(cl)
        map_path = cache / f"map-{map_profile}-{map_s:g}s{tag}-grown{len(grown) + 1}{ptag}.npz"
        h = cl.save_map(map_path, *prune)
        kept = [n for n in cl.saved_keyframes if n >= cl.map_keyframes]
        G1 += [_gt_pose(gt, cl.keyframes[n].t_ns) for n in kept]
        err = [np.linalg.norm((A @ cl.graph.estimate[n])[:3, 3] - _gt_pose(gt, cl.keyframes[n].t_ns)[:3, 3])
               for n in kept]
        m = load_map(map_path)
        grown.append({"seed": seed, "keyframes_added": h["keyframes"] - cl.map_keyframes,
                      "pruned": h["pruned_keyframes"], "map_bytes": map_path.stat().st_size,
                      "left_out": h["left_out_keyframes"], "relocalised_after_s": None if cl.relocalised_t_ns is None
                      else (cl.relocalised_t_ns - rec.items[0][0]) * 1e-9,
                      "keyframe_error_map_frame_m": float(np.sqrt(np.mean(np.square(err)))) if err else None})
        print(f"map grown by flight seed {seed}: +{grown[-1]['keyframes_added']} keyframes "
              f"({h['left_out_keyframes']} left out, {h['pruned_keyframes']} pruned), {len(m.features)} in all "
              f"({grown[-1]['map_bytes'] / 1e6:.2f} MB); " + (
                  "it never relocalised in the map" if cl.relocalised_t_ns is None else
                  "all of them pruned" if not kept else
                  f"their position error in the map's frame {grown[-1]['keyframe_error_map_frame_m']:.4f} m RMS"),
              flush=True)
    def false_edges(cl, G) -> int:
        n = 0
        for e in cl.graph.edges:
            if e.kind == "loop" and e.weight >= 0.5:
                n += _false_edge(G[e.i], G[e.j], e.T_i_j)
        return n

    def join_edges(cl, G) -> tuple[int, int]:
        """(true, false) active loop edges between the map and this flight: a join held by look-alikes alone
        (a repeated room) is a relocalisation in the wrong place, which the first join's time does not tell."""
        t = f = 0
        for e in cl.graph.edges:
            if e.kind == "loop" and e.weight >= 0.5 and (e.i < cl.map_keyframes) != (e.j < cl.map_keyframes):
                bad = _false_edge(G[e.i], G[e.j], e.T_i_j)
                t, f = t + (not bad), f + bad
        return t, f

    map_false = false_edges(mapper, [_gt_pose(gt1, t) for t in kt1])
    print(f"map: {len(kt1)} keyframes, {mapper.stats.accepted} loop edges ({map_false} false active), keyframe ATE "
          f"{ev1.ate_4dof.trans_m.rmse:.4f} m", flush=True)
    Tbc = ds1.calibration.cam0.T_body_cam
    C1 = np.array([G @ Tbc for G in G1])

    def nearest_view_deg(t_ns: int) -> float:
        """Smallest angle between this keyframe's optical axis (ground truth) and that of a map keyframe whose
        camera was within 1 m: how far off the map's views the second flight looks (inf: none within 1 m)."""
        c = _gt_pose(gt2, t_ns) @ Tbc
        near = np.linalg.norm(C1[:, :3, 3] - c[:3, 3], axis=1) <= 1.0
        if not near.any():
            return float("inf")
        return float(np.degrees(np.arccos(np.clip(C1[near, :3, 2] @ c[:3, 2], -1, 1))).min())

    rows, odom_ates = [], {}
    for seed in second_seeds:  # second flights: other paths and starts in the same room
        d2 = cache / f"second-survey-seed{seed}-scene2-30s{tag}"
        rec2, res2 = _keyframes(d2, {"duration_s": 30.0, "seed": seed, "scene_seed": 2,
                                       "aliasing_period_m": aliasing, **px})
        ds2 = EurocDataset(d2)
        gt2 = ds2.groundtruth.trajectory
        odom_ate = evaluate(Trajectory.from_poses(np.array([s.t_ns for s in res2.states]),
                                                  np.array([s.T_world_body for s in res2.states])),
                            gt2).ate_4dof.trans_m.rmse
        odom_ates[seed] = odom_ate
        items2 = rec2.items
        print(f"second flight seed {seed}: {len(items2)} keyframes, odometry ATE {odom_ate:.4f} m", flush=True)
        for s in np.linspace(0, 0.6 * len(items2), starts).astype(int):
            cl = LoopCloser(ds2.calibration, cfg)
            cl.load_map(m)
            placed: dict = {}

            def each(cl_, placed=placed, gt2=gt2) -> None:  # first joined, and first placed right (no look-alike)
                if "right_ns" in placed or not cl_.relocalised:
                    return
                Gn = G1 + [_gt_pose(gt2, k.t_ns) for k in cl_.keyframes[cl_.map_keyframes:]]
                n_true, n_false = join_edges(cl_, Gn)
                placed.setdefault("first_join_false", n_false > 0)
                if n_true and not n_false:
                    placed["right_ns"] = cl_.keyframes[-1].t_ns

            rec2.feed(cl, start=s, each=each)
            own = cl.keyframes[cl.map_keyframes:]
            G = G1 + [_gt_pose(gt2, k.t_ns) for k in own]
            false = false_edges(cl, G)
            row = {"second_seed": seed, "start_keyframe": int(s), "start_s": (own[0].t_ns - items2[0][0]) * 1e-9,
                   "relocalised": cl.relocalised_t_ns is not None, "delay_s": None, "ate_map_frame_m": None,
                   "false_edges_active": false, "first_join_on_lookalike": placed.get("first_join_false", False),
                   "placed_right_delay_s": (placed["right_ns"] - own[0].t_ns) * 1e-9 if "right_ns" in placed else None,
                   "nearest_map_view_deg": min(nearest_view_deg(k.t_ns) for k in own if k.t_ns <= own[0].t_ns + 2e9)}
            if cl.relocalised_t_ns is not None:
                row["delay_s"] = (cl.relocalised_t_ns - own[0].t_ns) * 1e-9
                k = [n for n, kf in enumerate(own) if kf.t_ns >= cl.relocalised_t_ns]
                p = np.array([(A @ cl.graph.estimate[cl.map_keyframes + n])[:3, 3] for n in k])
                g = np.array([G[cl.map_keyframes + n][:3, 3] for n in k])
                row["ate_map_frame_m"] = float(np.sqrt(np.mean(np.sum((p - g) ** 2, 1))))
                row["ate_ratio_to_odometry"] = row["ate_map_frame_m"] / odom_ate
            if evidence:
                kfs = _evidence(ds2.calibration, cfg, m, rec2, s, G1, gt2)
                row["evidence"] = {"keyframes": kfs, "first_rule": _first_join(kfs, cfg, "first"),
                                   "oracle": _first_join(kfs, cfg, "oracle")}
            rows.append(row)
            print(f"start at {row['start_s']:5.1f} s: " + (
                f"relocalised after {row['delay_s']:.2f} s, ATE in the map's frame {row['ate_map_frame_m']:.4f} m "
                f"({row['ate_ratio_to_odometry']:.2f}x)" if row["relocalised"] else "not relocalised")
                  + (" (first joined on look-alikes)" if row["first_join_on_lookalike"] else "")
                  + ("" if not row["relocalised"] else ", never placed right" if row["placed_right_delay_s"] is None
                     else f", placed right after {row['placed_right_delay_s']:.2f} s")
                  + f", false edges {false}; nearest map view in its first 2 s {row['nearest_map_view_deg']:.0f} deg",
                  flush=True)
    delays = [r["delay_s"] if r["relocalised"] else np.inf for r in rows]
    covered = [d for d, r in zip(delays, rows) if r["nearest_map_view_deg"] <= COVERED_DEG]
    ates = [r["ate_map_frame_m"] for r in rows if r["relocalised"]]
    ratios = [r["ate_ratio_to_odometry"] for r in rows if r["relocalised"]]
    out = {"map_s": map_s, "map_profile": map_profile, "aliasing_m": aliasing, "grown_by": grown,
           "grow_profile": grow_profile, "prune_m_deg": list(prune),
            "map_keyframes": len(rec1.items), "map_ate_m": ev1.ate_4dof.trans_m.rmse,
           "map_loop_edges": mapper.stats.accepted, "map_false_edges_active": map_false, "starts": rows,
           "second_seeds": list(second_seeds), "odometry_ate_m": odom_ates[second_seeds[0]],
           "odometry_ate_by_seed_m": odom_ates, "within_2s": int(sum(d <= 2.0 for d in delays)),
           "ate_ratio_median": float(np.median(ratios)) if ratios else None,
           "within_2x_odometry": int(sum(r <= 2.0 for r in ratios)),
           "relocalised": len(ates), "median_delay_s": float(np.median(delays)),
           "ate_map_frame_median_m": float(np.median(ates)) if ates else None,
           "ate_map_frame_max_m": float(max(ates)) if ates else None,
           "false_edges_active": int(sum(r["false_edges_active"] for r in rows)),
           "placed_right_within_2s": int(sum(r["placed_right_delay_s"] is not None and r["placed_right_delay_s"] <= 2.0
                                             for r in rows)),
           "placed_right": int(sum(r["placed_right_delay_s"] is not None for r in rows)),
           "first_join_on_lookalike": int(sum(r["first_join_on_lookalike"] for r in rows)),
           "covered_starts": len(covered), "covered_within_2s": int(sum(d <= 2.0 for d in covered))}
    print(f"{out['within_2s']}/{len(rows)} starts relocalised within 2 s ({out['relocalised']} at all, median delay "
          f"{out['median_delay_s']:.2f} s); ATE in the map's frame median {out['ate_map_frame_median_m']} m, max "
          f"{out['ate_map_frame_max_m']} m; against each flight's odometry ATE median {out['ate_ratio_median']:.2f}x, "
          f"{out['within_2x_odometry']} within 2x; false edges {out['false_edges_active']}")
    print(f"placed right (joined, no look-alike edge held) within 2 s: {out['placed_right_within_2s']}/{len(rows)} "
          f"({out['placed_right']} at all); first joined on look-alikes: {out['first_join_on_lookalike']}")
    print(f"starts whose first 2 s look within {COVERED_DEG:g} deg of a map view (camera within 1 m): "
          f"{out['covered_within_2s']}/{out['covered_starts']} relocalised within 2 s")
    if evidence:
        out["evidence"] = _evidence_summary(rows)
        e = out["evidence"]
        print(f"evidence, every candidate of the first {EVIDENCE_S:g} s verified: {e['true_edges']} true edges "
              f"(inliers median {e['true_inliers_median']}), {e['lookalike_edges']} look-alike (median "
              f"{e['lookalike_inliers_median']}); keyframes with both {e['keyframes_with_both']}, a look-alike "
              f"the strongest in {e['keyframes_lookalike_strongest']}; starts with a true edge "
              f"{e['starts_with_true_edge']}, with a look-alike {e['starts_with_lookalike']}; placed right within "
              f"{EVIDENCE_S:g} s, replayed: {e['first_rule_placed_right']} with the loop stage's rule (first join on "
              f"look-alikes {e['first_rule_lookalike']}), {e['oracle_placed_right']} with every look-alike refused "
              "(the bound)")
    return out


def _evidence_summary(rows: list[dict]) -> dict:
    """--evidence over all starts: how true and look-alike edges compare, and the placed-right count a rule could
    reach (`_first_join`)."""
    cands = [c for r in rows for k in r["evidence"]["keyframes"] for c in k["candidates"] if not c["refused"]]
    true = [c["inliers"] for c in cands if not c["lookalike"]]
    fake = [c["inliers"] for c in cands if c["lookalike"]]
    both = strongest = 0
    for r in rows:
        for k in r["evidence"]["keyframes"]:
            v = [c for c in k["candidates"] if not c["refused"]]
            t, f = [c["inliers"] for c in v if not c["lookalike"]], [c["inliers"] for c in v if c["lookalike"]]
            both += bool(t and f)
            strongest += bool(t and f and max(f) > max(t))

    def starts_with(lookalike: bool) -> int:
        return sum(any(not c["refused"] and c["lookalike"] == lookalike for k in r["evidence"]["keyframes"]
                       for c in k["candidates"]) for r in rows)

    def placed(rule: str) -> int:
        return sum(1 for r in rows if (j := r["evidence"][rule]) is not None and j[1] and j[0] <= EVIDENCE_S)
    return {"true_edges": len(true), "lookalike_edges": len(fake),
            "true_inliers_median": float(np.median(true)) if true else None,
            "lookalike_inliers_median": float(np.median(fake)) if fake else None,
            "keyframes_with_both": both, "keyframes_lookalike_strongest": strongest,
            "starts_with_true_edge": starts_with(False), "starts_with_lookalike": starts_with(True),
            "first_rule_placed_right": placed("first_rule"), "oracle_placed_right": placed("oracle"),
            "first_rule_lookalike": sum(1 for r in rows if (j := r["evidence"]["first_rule"]) is not None
                                        and not j[1] and j[0] <= EVIDENCE_S)}


def main(argv: list[str]) -> int:
    if argv[:1] == ["--check"]:
        return check(*argv[1:])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=int, default=20)
    ap.add_argument("--cache", default="/tmp/kestrel-loop-reloc")
    ap.add_argument("--aliasing", type=float, metavar="M", help="both flights in a room whose textures repeat "
                    "every M metres (vio simulate --aliasing): relocalisation must not take a look-alike place")
    ap.add_argument("--map-duration", type=float, default=40.0, metavar="S", help="length of the map flight")
    ap.add_argument("--map-profile", default="survey", choices=("survey", "mapping", "laps"),
                    help="the map flight: survey (heading within +-60 deg of a random one), mapping (heading "
                    "swept through +-180 deg: the room seen from every direction) or laps (round the room, "
                    "looking along the course)")
    ap.add_argument("--grow", type=int, nargs="*", default=[], metavar="SEED",
                    help="grow the map with more flights in the same room (--grow-profile, these seeds), each "
                    "relocalised in the map so far and saved with it (as --load-map A --save-map AB does)")
    ap.add_argument("--grow-profile", default="survey", choices=("survey", "mapping", "laps"),
                    help="the profile of the --grow flights (laps: a seed whose laps turn the other way than the "
                    "map flight's, e.g. 7 against the map's seed 2, sees every wall from the other side)")
    ap.add_argument("--size", default="376x240", help="image size WxH of the flights (default 376x240)")
    ap.add_argument("--second-seeds", type=int, nargs="+", default=[12], metavar="SEED",
                    help="second flights (survey, 30 s, scene seed 2), --starts starts each (default: 12)")
    ap.add_argument("--config", metavar="FILE", help="TOML configuration whose [loop] section the loop stages use "
                    "(and [map] prune_m / prune_deg the grown maps' saves)")
    ap.add_argument("--evidence", action="store_true", help=f"also re-feed each start's first {EVIDENCE_S:g} s with "
                    "every retrieval candidate verified and no join made: true and look-alike edges per keyframe, and "
                    "how many starts the loop stage's consistency rule, or one that refused every look-alike, places "
                    "right within that time (per start under 'evidence' in --json)")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    Path(args.cache).mkdir(parents=True, exist_ok=True)
    out = multi_start(args.starts, Path(args.cache), args.aliasing, args.map_duration, args.map_profile,
                      tuple(args.grow), tuple(int(v) for v in args.size.lower().split("x")), tuple(args.second_seeds),
                      args.grow_profile, args.config, args.evidence)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
