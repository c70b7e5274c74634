"""The loop-closure stage: keyframe in -> (maybe) a verified loop edge, a re-optimised pose graph, and the
correction T_world_odom that maps odometry poses into the loop-corrected frame. No threads, no I/O.

Pipeline per keyframe: upright ORB -> bag of words -> best candidates older than exclude_recent_s ->
PnP RANSAC on the candidate's stereo landmarks -> gravity check -> drift gate (the correction may not exceed
what the odometry can have drifted since the candidate) -> temporal consistency (min_consistent verified
candidates in a window of keyframes whose corrections agree) -> loop edges into the graph -> incremental
re-solve (iSAM2; GNC re-decides the loop edges when the new ones do not fit). Relocalising (a loaded map, or
the flight before an estimator reset, not joined to this session yet): their best candidates are verified as
well, with the reloc_* gates (docs/loop-closure.md)."""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vio import VioError
from vio.calibration import StereoCalibration
from vio.config import LoopConfig
from vio.geometry import inv_T, make_T, so3_exp, so3_log, yaw_of
from vio.loop.database import BowIndex, BowVector
from vio.loop.features import FeatureExtractor, KeyframeFeatures
from vio.loop.output import CorrectionUncertainty
from vio.loop.posegraph import DecisionError, GraphNoise, PoseGraph
from vio.loop.verify import gravity_disagreement_deg, pnp, pnp_from, refine_edge
from vio.loop.vocabulary import Vocabulary
from vio.types import FeatureFrame

log = logging.getLogger(__name__)

# A map part (a flight's segment joined to the map's frame) placed by fewer loop edges than this rests on
# them: a laps flight grown onto laps flown the other way joined by 3 edges of 38 mm error each and sat 41 mm
# off (docs/loop-closure.md). It is saved, with a warning and the count in the map's header.
WEAK_JOIN_EDGES = 10


def _camera_mismatch(map_cam: dict, cam) -> str | None:
    """Why a map made with another camera will rarely place this flight (its features were seen at another size
    and scale), or None. Said, not refused: the same rig at another resolution still shares some views."""
    size, fx = (int(map_cam["width"]), int(map_cam["height"])), float(map_cam["fx"])
    if size == (cam.width, cam.height) and abs(fx / cam.fx - 1.0) <= 0.02:
        return None
    return (f"the map was made with a {size[0]}x{size[1]} camera (fx {fx:.0f} px), this flight's is "
            f"{cam.width}x{cam.height} (fx {cam.fx:.0f} px): its views are matched across the two and will rarely "
            "place this flight; make the map with this camera and size")


def _agree(T_identity: np.ndarray, max_m: float, max_deg: float) -> bool:
    """Is T_identity (the composition of two estimates of one relative pose, one inverted) near identity?"""
    return bool(np.linalg.norm(T_identity[:3, 3]) <= max_m and
                np.degrees(np.linalg.norm(so3_log(T_identity[:3, :3]))) <= max_deg)


def _mean_pose(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Midpoint of two nearby poses."""
    return make_T(A[:3, :3] @ so3_exp(0.5 * so3_log(A[:3, :3].T @ B[:3, :3])), 0.5 * (A[:3, 3] + B[:3, 3]))


@dataclass
class Keyframe:
    t_ns: int
    session: int
    feats: KeyframeFeatures
    path_m: float  # odometry path length from the session start


@dataclass
class _Candidate:
    i: int  # new node
    j: int  # old node
    T_j_i: np.ndarray
    correction: np.ndarray  # T_est_j @ T_j_i @ inv(T_est_i): where the edge puts node i
    inliers: int


@dataclass
class LoopStats:
    keyframes: int = 0
    queried: int = 0
    refused: dict = field(default_factory=lambda: dict.fromkeys(
        ("no candidate", "pnp", "two-way", "gravity", "drift gate", "inconsistent", "solve failed"), 0))
    accepted: int = 0
    spaced_out: int = 0  # odometry keyframes not taken (closer than [loop] spacing_* to the last one taken)
    switched_off: int = 0
    gnc_decisions: int = 0  # closures after which the robust decision ran (the others fitted: fast path)
    quick_fits: int = 0  # closures whose new edges already fitted the graph's estimate (no fit check either)
    detect_ms: list = field(default_factory=list)  # extraction + retrieval + verification per keyframe
    # the pose graph's upkeep per keyframe: its node, and every flush_every keyframes their iSAM2 update
    graph_ms: list = field(default_factory=list)
    optimize_ms: list = field(default_factory=list)  # the re-solve after a closure

    def to_dict(self) -> dict:
        def mean(x):
            return float(np.mean(x)) if x else 0.0
        return {"keyframes": self.keyframes, "spaced_out": self.spaced_out, "queried": self.queried,
                "refused": dict(self.refused),
                "accepted": self.accepted, "switched_off": self.switched_off,
                "gnc_decisions": self.gnc_decisions, "quick_fits": self.quick_fits,
                "detect_ms_mean": mean(self.detect_ms),
                "detect_ms_p95": float(np.percentile(self.detect_ms, 95)) if self.detect_ms else 0.0,
                "graph_ms_mean": mean(self.graph_ms),
                "optimize_ms_mean": mean(self.optimize_ms),
                "optimize_ms_max": float(max(self.optimize_ms)) if self.optimize_ms else 0.0}


class LoopCloser:
    def __init__(self, calib: StereoCalibration, cfg: LoopConfig, vocabulary: Vocabulary | None = None) -> None:
        self.cfg = cfg
        self.cam = calib.cam0
        self.baseline_m = calib.baseline_m
        self.vocab = vocabulary or Vocabulary.load(cfg.vocabulary or None)
        self.extractor = FeatureExtractor(calib.cam0, cfg.orb_features, cfg.fast_threshold, cfg.orb_levels,
                                          cfg.orb_level_scale)
        self.graph = PoseGraph(GraphNoise(odom_trans_per_m=cfg.odom_sigma_per_m, loop_trans_m=cfg.loop_sigma_m,
                                          loop_rot_rad=np.radians(cfg.loop_sigma_deg)))
        self.index = BowIndex(self.vocab.n_words)
        self.keyframes: list[Keyframe] = []
        self.stats = LoopStats()
        self.session = 0
        self._component: dict[int, int] = {}  # session -> component id (sessions joined by a loop edge)
        self._last_reset: int | None = None
        self._pending: list[_Candidate] = []
        self.map_keyframes = 0  # keyframes of a loaded map (the first ones)
        self._map_stamp: tuple | None = None  # the loaded map file as read (mapfile.file_stamp)
        self._own_stamp: tuple | None = None  # the map file as this run's last save_map left it
        self._redirect: dict[str, Path] = {}  # a map path found changed by another run -> where this run writes
        self._marginal_warned = False  # correction_uncertainty fell back to the loop sigmas (said once)
        self.map_camera_warning: str | None = None  # a loaded map made with another camera size or focal length
        self.map_mount_change: tuple[float, float] | None = None  # (deg, mm) the map's camera mount differed by
        self._map_parts: list[dict] = []  # a loaded map's parts (its header's), for the map saved after it
        self.relocalised_t_ns: int | None = None  # first keyframe joined to the loaded map
        self.saved_keyframes: list[int] = []  # indices of the keyframes the last save_map wrote
        self._own_node: dict[int, int] = {}  # this flight's keyframe stamp -> its node (for `settle`)
        self._join_counts: tuple[int, dict[int, int]] = (-1, {})  # `_join_edges`' cache (loop_version, counts)

    # --- the stage --------------------------------------------------------------------------------
    def add_keyframe(self, t_ns: int, T_world_body: np.ndarray, image: np.ndarray, ff: FeatureFrame | None,
                     reset_counter: int = 0) -> bool:
        """Add one keyframe (odometry pose); returns True when a closure was accepted (graph re-solved)."""
        t0 = time.perf_counter()
        c = self.cfg
        reset = self._last_reset is not None and reset_counter != self._last_reset
        if not reset and self._spaced_out(t_ns, T_world_body):
            self.stats.spaced_out += 1
            return False
        feats = self.extractor.extract(image, ff)
        bow = self.vocab.bow(feats.desc)
        if reset:
            self.session += 1  # an estimator reset: the odometry chain breaks
        self._last_reset = reset_counter
        first_ever = not self.keyframes
        t_graph = time.perf_counter()
        if first_ever or self.keyframes[-1].session != self.session:
            self._component.setdefault(self.session, self.session)
            prior = (1e-3, 1e-3) if first_ever else (np.radians(c.segment_prior_deg), c.segment_prior_m)
            i = self.graph.add_node(T_world_body, None, prior)
            path = 0.0
        else:
            prev = len(self.keyframes) - 1
            i = self.graph.add_node(T_world_body, prev)
            path = self.keyframes[prev].path_m + float(np.linalg.norm(
                T_world_body[:3, 3] - self.graph.odom[prev][:3, 3]))
        self._own_node[int(t_ns)] = i
        graph_s = time.perf_counter() - t_graph
        self.stats.graph_ms.append(graph_s * 1e3)
        kf = Keyframe(int(t_ns), self.session, feats, path)
        self.keyframes.append(kf)
        self.index.add(bow)
        self.stats.keyframes += 1
        before = (len(self.graph.edges), dict(self._component), self.relocalised_t_ns, self.stats.accepted)
        accepted = self._detect(i, bow)
        self.stats.detect_ms.append((time.perf_counter() - t0 - graph_s) * 1e3)
        if accepted:
            t1 = time.perf_counter()
            try:
                # a closure that joins two sessions (relocalisation, a segment after a reset) is solved now even when
                # its edges already fit (frames that nearly coincide: a take-off from the map's own pad): the
                # output takes a new frame only with a new estimate, and its uncertainty only from edges in iSAM2
                self.graph.optimize(defer=self._component == before[1])
            except DecisionError as e:
                # one closure whose graph does not solve costs that closure, not the stage for the rest of the
                # flight: its edges are taken back and the graph is as it was before this keyframe
                n = self.graph.drop_loops_from(before[0])
                _, self._component, self.relocalised_t_ns, self.stats.accepted = before
                self.stats.refused["solve failed"] += 1
                log.warning("loop closure at keyframe %d (t %.3f s) dropped, %d edges taken back: the pose graph "
                            "did not solve (%s)", i, t_ns * 1e-9, n, e)
                return False
            self.stats.optimize_ms.append((time.perf_counter() - t1) * 1e3)
            self._rejoin()
            if self.relocalised_t_ns is None and self.relocalised:  # joined, and the solve kept the join
                self.relocalised_t_ns = int(t_ns)
            self.stats.switched_off = sum(1 for e in self.graph.edges if e.kind == "loop" and e.weight < 0.5)
            self.stats.gnc_decisions = self.graph.decisions
            self.stats.quick_fits = self.graph.quick_fits
        return accepted

    def settle(self, t_ns: int, T_world_body: np.ndarray) -> None:
        """The odometry's smoothed pose of a keyframe as it left the odometry's window (`ProcessedFrame.settled`):
        the odometry edges between settled keyframes are taken from these (`settled_odometry`); a keyframe the
        stage did not take is ignored. Takes effect in the graph's next update (at the latest the next closure)."""
        i = self._own_node.get(int(t_ns))
        if i is not None and self.cfg.settled_odometry:
            self.graph.settle(i, T_world_body)

    def finish(self) -> None:
        """End of the flight: what is still pending (keyframes, settled odometry edges) goes into the graph's
        estimate, so that the corrected trajectory and a saved map include it."""
        if any(e.kind == "loop" for e in self.graph.edges):
            self.graph.refresh()

    def _spaced_out(self, t_ns: int, T_world_body: np.ndarray) -> bool:
        """A keyframe too close to the last one taken, in place, heading and time, to add a view (with
        `spacing_m` > 0). The odometry makes a keyframe every 0.2-0.4 s whatever the motion: a hover or a slow
        survey would fill the database with near-copies that each cost extraction and a verification. Always
        taken: the first, the first after an estimator reset (the caller's test), and every one while a loaded
        map or the flight before a reset is not joined yet (relocalisation wants every view)."""
        c = self.cfg
        if c.spacing_m <= 0 or not self.keyframes or len(self.keyframes) <= self.map_keyframes:
            return False
        if self._relocalising(self.session):
            return False
        last = self.graph.odom[-1]
        d = inv_T(last) @ T_world_body
        return (float(np.linalg.norm(d[:3, 3])) < c.spacing_m
                and float(np.degrees(np.linalg.norm(so3_log(d[:3, :3])))) < c.spacing_deg
                and (t_ns - self.keyframes[-1].t_ns) * 1e-9 < c.spacing_s)

    def _allowed(self, i: int):
        kf = self.keyframes[i]
        recent_ns = int(self.cfg.exclude_recent_s * 1e9)

        def ok(j: int) -> bool:
            o = self.keyframes[j]
            return j != i and (o.session != kf.session or kf.t_ns - o.t_ns > recent_ns)
        return ok

    def _detect(self, i: int, bow: BowVector) -> bool:
        c = self.cfg
        self._pending = [p for p in self._pending if i - p.i <= c.consistency_window]
        cands = self.candidates(i, bow)
        self.stats.queried += 1
        if not cands:
            self.stats.refused["no candidate"] += 1
            return False
        reason = "pnp"
        for j, _score in cands:
            cand, why = self.verify(i, j)
            if cand is None:
                reason = reason if why == "pnp" else why  # the last gate passed PnP and refused it, if any
                continue
            self._pending.append(cand)
            return self._consistent(i)
        self.stats.refused[reason] += 1
        return False

    def candidates(self, i: int, bow: BowVector) -> list[tuple[int, float]]:
        """Keyframe i's retrieval candidates (keyframe, score) in the order they are verified: the best `candidates`
        allowed (`_allowed`), and while its session is relocalising or confirming a join the best reloc_candidates of
        the other sessions; all with score >= min_score. Also what bench/loop_reloc.py --evidence verifies."""
        c = self.cfg
        ok = self._allowed(i)
        cands = self.index.query(bow, ok, c.candidates)
        mine = self._comp(self.keyframes[i].session)
        reloc = self._relocalising(self.keyframes[i].session)
        confirming = not reloc and self._confirming(self.keyframes[i].session)
        if c.reloc_candidates and (reloc or confirming):
            # not joined to a map / the flight before a reset yet: their best ones too, or this flight's own
            # keyframes crowd them out of the top `candidates`
            seen = {j for j, _ in cands}
            if reloc:
                other_frame = lambda j: self._comp(self.keyframes[j].session) != mine  # noqa: E731
            else:  # joined, not confirmed yet: the sessions it is joined to (a map's views) as well
                other_frame = lambda j: self.keyframes[j].session != self.keyframes[i].session  # noqa: E731
            cands += [(j, s) for j, s in self.index.query(bow, lambda j: ok(j) and other_frame(j), c.reloc_candidates)
                      if j not in seen]
        return [(j, s) for j, s in cands if s >= c.min_score]

    def verify(self, i: int, j: int) -> tuple[_Candidate | None, str]:
        """Keyframe j as a loop candidate of keyframe i through every gate (PnP, two-way, gravity, drift gate; the
        reloc_* ones for another frame, or the frame of a join not confirmed yet): (the candidate, "") or (None,
        the gate that refused it). Nothing is kept."""
        c = self.cfg
        kf, old = self.keyframes[i], self.keyframes[j]
        g = self.graph
        confirming = not self._relocalising(kf.session) and self._confirming(kf.session)
        # another frame, or the frame of a join not confirmed yet: the relocalisation rules (its own gates, no
        # matching guided by the placement under test)
        other = self._comp(old.session) != self._comp(kf.session) or (confirming and old.session != kf.session)
        min_inl = c.reloc_min_inliers if other else c.min_inliers
        kw = dict(max_hamming=c.max_hamming, reproj_px=c.reproj_threshold_px, min_inliers=min_inl,
                  guided_px=c.guided_radius_px)
        res = pnp(old.feats, kf.feats, self.cam.K, self.cam.T_body_cam, ratio=c.match_ratio, **kw)
        if res is None and not other and c.prior_radius_px > 0:
            # matched by projection from where the graph puts the new keyframe (verify.pnp `prior`)
            res = pnp(old.feats, kf.feats, self.cam.K, self.cam.T_body_cam, ratio=c.match_ratio,
                      prior=inv_T(g.estimate[j]) @ g.estimate[i], prior_px=c.prior_radius_px, **kw)
        if res is None:
            return None, "pnp"
        if c.guided_radius_px > 0:  # the other way matched by projection from this pose (verify.pnp_from)
            back = pnp_from(kf.feats, old.feats, self.cam.K, self.cam.T_body_cam, inv_T(res.T_old_new), **kw)
        else:
            back = pnp(kf.feats, old.feats, self.cam.K, self.cam.T_body_cam, ratio=c.match_ratio, **kw)
        two_way = (c.reloc_two_way_m, c.reloc_two_way_deg) if other else (c.two_way_m, c.two_way_deg)
        if back is None or not _agree(res.T_old_new @ back.T_old_new, *two_way):
            return None, "two-way"
        T_edge = _mean_pose(res.T_old_new, inv_T(back.T_old_new))
        if c.refine_edges:
            T_ref = refine_edge(old.feats, kf.feats, res, back, self.cam.K, self.baseline_m,
                                self.cam.T_body_cam, T_edge)
            # the two PnPs agreed within the two-way tolerance: a refinement that leaves it is not trusted
            if T_ref is not None and _agree(inv_T(T_edge) @ T_ref, *two_way):
                T_edge = T_ref
        res = dataclasses.replace(res, T_old_new=T_edge, inliers=min(res.inliers, back.inliers))
        tilt = gravity_disagreement_deg(g.estimate[j][:3, :3], g.odom[i][:3, :3], res.T_old_new[:3, :3])
        if tilt > c.gravity_max_deg:
            return None, "gravity"
        corr = g.estimate[j] @ res.T_old_new @ inv_T(g.estimate[i])
        if not other:
            since = abs(kf.path_m - old.path_m) if old.session == kf.session else float("inf")
            allowed_m = c.drift_gate_m + c.drift_gate_per_m * since
            if np.linalg.norm(corr[:3, 3]) > allowed_m or abs(np.degrees(yaw_of(corr[:3, :3]))) > c.drift_gate_deg:
                return None, "drift gate"
        return _Candidate(i, j, res.T_old_new, corr, res.inliers), ""

    def placement_unconfirmed(self) -> bool:
        """The newest keyframe's session is joined to another frame (a loaded map, the flight before a reset) by
        fewer than output_join_edges active loop edges: a first join can be a look-alike place (a repeated room: 25
        of 100 second flights were output 0.5 m or more off for a while at the first join, 3 from the second
        consistent set of edges, none from 8 edges), so its frame is not handed to the output yet."""
        return bool(self.keyframes) and not self.correction_segment()[1] and \
            self._few_join_edges(self.keyframes[-1].session, self.cfg.output_join_edges)

    def _confirming(self, session: int) -> bool:
        """This session is joined to another one by fewer than reloc_confirm_edges active loop edges."""
        return self._few_join_edges(session, self.cfg.reloc_confirm_edges)

    def _few_join_edges(self, session: int, n: int) -> bool:
        """A later session (not the first: the map's, or the flight's start) held by fewer than n > 0 active loop
        edges to the others."""
        return bool(n) and session > 0 and self._join_edges(session) < n

    def _consistent(self, i: int) -> bool:
        c = self.cfg
        newest = self._pending[-1]
        def agrees(p: _Candidate) -> bool:
            d_yaw = yaw_of(p.correction[:3, :3] @ newest.correction[:3, :3].T)
            return bool(np.linalg.norm(p.correction[:3, 3] - newest.correction[:3, 3]) <= c.consistency_m
                        and abs(np.degrees(d_yaw)) <= c.consistency_deg)
        confirming = self._confirming(self.keyframes[newest.i].session)
        def frames(p: _Candidate) -> tuple[int, int]:
            a, b = self.keyframes[p.i].session, self.keyframes[p.j].session
            if confirming and a != b:  # a join not confirmed yet: edges across it count as relocalisation
                return a, b
            return self._comp(a), self._comp(b)

        # only candidates of the newest one's kind count: within one frame, or between the same two frames (one
        # edge to a loaded map with one agreeing edge within the flight passed min_consistent, not
        # reloc_min_consistent, and joined the flight to the map: a review's finding)
        kind = frames(newest)
        agree = [p for p in self._pending if frames(p) == kind and agrees(p)]
        same = kind[0] == kind[1]
        if len({p.i for p in agree}) < (c.min_consistent if same else c.reloc_min_consistent):
            self.stats.refused["inconsistent"] += 1
            return False
        for p in agree:
            self.graph.add_loop(p.j, p.i, p.T_j_i, p.inliers, self._sigma_scale(p))
            self._join(self.keyframes[p.j].session, self.keyframes[p.i].session)
            self.stats.accepted += 1
        self._pending = [p for p in self._pending if p not in agree]
        return True

    def _sigma_scale(self, p: _Candidate) -> float:
        """Sigma multiplier of a loop edge from its PnP inliers: a PnP pose's error goes as 1 / sqrt(inliers).
        Within one session sqrt(sigma_inliers / inliers) between 0.5 and 2: tighter for an edge with many inliers,
        looser for a weak one (on sixteen re-fed flights the surveys' loop ATE -4 to -10 %). Between two sessions
        (to a loaded map, or across an estimator reset) sqrt(reloc_sigma_inliers / inliers) between 1 and 2, never
        tighter: such an edge sees a place from further off than a loop within one flight, and its first few decide
        where the whole session sits in the map's frame: with 12-20 inliers they were 30-70 mm off where 40-90
        inliers gave 3-8 mm (docs/loop-closure.md)."""
        inliers = max(p.inliers, 1)
        if self.keyframes[p.i].session == self.keyframes[p.j].session:
            ref, lo = self.cfg.sigma_inliers, 0.5
        else:
            ref, lo = self.cfg.reloc_sigma_inliers, 1.0
        if not ref:
            return 1.0
        return float(np.clip(np.sqrt(ref / inliers), lo, 2.0))

    def _relocalising(self, session: int) -> bool:
        """Some session (a loaded map, the flight before a reset) is not joined to `session` by a loop edge."""
        mine = self._comp(session)
        return any(self._comp(s) != mine for s in self._component)

    def _comp(self, session: int) -> int:
        while self._component.get(session, session) != session:
            session = self._component[session]
        return session

    def _rejoin(self) -> None:
        """Sessions joined by the loop edges GNC keeps, after a solve. A join is not forever: when GNC switches off
        the edges that placed a session in the map (a false relocalisation in a repeated room), that session is in
        a frame of its own again: it is not reported in the map, its pose carries no map placement, and it looks
        for the map with the relocalisation rules again (reloc candidates, inliers, consistency)."""
        self._component = {s: s for s in self._component}
        for e in self.graph.active_loops():
            if e.i != e.j:
                self._join(self.keyframes[e.i].session, self.keyframes[e.j].session)

    def _join(self, a: int, b: int) -> None:
        ra, rb = self._comp(a), self._comp(b)
        if ra != rb:
            self._component[max(ra, rb)] = min(ra, rb)

    # --- maps -------------------------------------------------------------------------------------
    def load_map(self, m) -> None:
        """Put a saved map's keyframes in, fixed at their saved poses (session 0); this flight becomes a new
        session with a loose prior, so its poses move into the map's frame once it relocalises."""
        if self.keyframes:
            raise ValueError("load the map before the first keyframe")
        poses = self._map_poses_for_this_mount(m)
        for t, T, f in zip(m.t_ns, poses, self._map_features_for_this_camera(m)):
            self.graph.add_node(T, None, (1e-4, 1e-4))
            self.keyframes.append(Keyframe(int(t), 0, f, 0.0))
            self.index.add(self.vocab.bow(f.desc))
        self._component[0] = 0
        self.map_keyframes = len(m.features)
        self.map_camera_warning = _camera_mismatch(m.header["camera"], self.cam)
        if self.map_camera_warning:
            log.warning("loop closure: %s", self.map_camera_warning)
        self._map_parts = list(m.header.get("parts") or [{"keyframes": len(m.features), "join_edges": None}])
        self._map_stamp = getattr(m, "stamp", None)
        self.session = 1
        self._last_reset = None

    def _map_features_for_this_camera(self, m) -> list[KeyframeFeatures]:
        """The map's keyframe features with their undistorted pixels re-expressed in this flight's pinhole
        (uv_now = K_now K_map^-1 uv_map). Verification projects into an old keyframe's image with this camera's
        K; a map made with another calibration of the camera (a focal length 0.8 % and a principal point 3 px
        off: under the size/focal warning) had its back-projection PnP biased and a relocalised flight sat twice
        as far off in the map's frame, unsaid (this test's finding). Pixel rays are what a map's uv mean; the
        stereo points are metric and stay."""
        c = m.header.get("camera", {})
        cam = self.cam
        fx, fy = float(c.get("fx", cam.fx)), float(c.get("fy", cam.fy))
        cx, cy = float(c.get("cx", cam.cx)), float(c.get("cy", cam.cy))
        if (fx, fy, cx, cy) == (cam.fx, cam.fy, cam.cx, cam.cy):
            return list(m.features)
        log.info("loop closure: the map's pixels (fx %.1f fy %.1f cx %.1f cy %.1f) are re-expressed in this "
                 "camera's (fx %.1f fy %.1f cx %.1f cy %.1f)", fx, fy, cx, cy, cam.fx, cam.fy, cam.cx, cam.cy)
        scale = np.array([cam.fx / fx, cam.fy / fy])
        shift = np.array([cam.cx, cam.cy]) - np.array([cx, cy]) * scale
        return [dataclasses.replace(f, uv=(np.asarray(f.uv, np.float64) * scale + shift).astype(f.uv.dtype))
                for f in m.features]

    def _map_poses_for_this_mount(self, m) -> np.ndarray:
        """The map's keyframe body poses for this flight's camera mount. A map stores body (IMU) poses and what its
        camera saw; with the camera re-mounted or the IMU changed since, today's T_body_cam applied to them put
        every map camera elsewhere, and a relocalised flight sat 0.3-0.5 m off in the map's frame, unsaid (a
        review's finding). The keyframes are placed by their cameras: T_world_body = T_world_body_map @
        T_body_cam_map @ inv(T_body_cam_now). A map without its mount (made before 2026-12-06) is taken as made
        with this one."""
        poses = np.asarray(m.T_world_body, dtype=float)
        T_map = m.header.get("camera", {}).get("T_body_cam")
        if T_map is None:
            log.info("loop closure: the map does not state its camera mount (an older map): this flight's "
                     "T_body_cam is taken for its keyframes")
            return poses
        T_map = np.array(T_map, dtype=float)
        T_now = np.asarray(self.cam.T_body_cam, dtype=float)
        D = T_map @ inv_T(T_now)
        deg = float(np.degrees(np.linalg.norm(so3_log(D[:3, :3]))))
        mm = float(np.linalg.norm(D[:3, 3])) * 1e3
        if deg <= 0.01 and mm <= 0.1:
            return poses
        self.map_mount_change = (deg, mm)
        log.warning("loop closure: the map was made with the camera %.2f deg and %.1f mm elsewhere on the body "
                    "(another mount or calibration): its keyframes are placed by their cameras for this one", deg, mm)
        return np.einsum("nij,jk->nik", poses, D)

    @property
    def relocalised(self) -> bool:
        """A loaded map and this flight's newest keyframe in one component (joined by a loop edge)."""
        return bool(self.map_keyframes) and bool(self.keyframes) and \
            self._comp(self.keyframes[-1].session) == self._comp(0)

    def map_frame_keyframes(self) -> list[int]:
        """Indices of the keyframes in the map's frame: the first session's and every session joined to it."""
        ref = self._comp(0)
        return [k for k, kf in enumerate(self.keyframes) if self._comp(kf.session) == ref]

    def save_map(self, path, prune_m: float = 0.0, prune_deg: float = 0.0, checkpoint: dict | None = None,
                 world_turn: np.ndarray | None = None) -> dict:
        """Write the keyframes whose poses are in the map's frame: those of the first session (a loaded map's,
        else this flight's start) and of every session a loop edge has joined to it. A segment after an
        estimator reset that never relocalised, or a flight that never relocalised in the loaded map, has
        poses in a frame of its own; saved beside the others it would put a later flight in the wrong place,
        so it is left out (and counted in the header's `left_out_keyframes`).

        With `prune_m` > 0, a keyframe of this flight whose camera is within `prune_m` and `prune_deg` of one
        already kept (the loaded map's, or an earlier one of this flight) is not saved (`pruned_keyframes`): a
        map grown by every flight in the same warehouse would otherwise grow by each flight's whole length.

        `checkpoint`: the run's identity, for a save in flight (`vio run`'s `[map] checkpoint_s`): the header marks
        the map as not final. A file this run saved before is compared with what this run left there, as a loaded
        one with what was loaded: another run's save over it in between is kept, and this run writes beside it
        (the same `alt` name for every later save).

        `world_turn`: the MAVLink output's turn and shift of a start in flight (world' = T @ world): a map of this
        flight's own frame (none loaded) is saved in the autopilot's frame, where its poses went. A restart that
        relocalises in it takes the turn back out of its correction (a loaded map's frame is the autopilot's,
        CorrectedOutput.frame_turn): a checkpoint of a process that had itself started in flight was in that
        process's own frame, and the next restart's poses went out off by its turn (a review's finding)."""
        from vio.loop.mapfile import file_stamp, save_map

        target, conflict = Path(path), ""
        if not self.map_frame_keyframes():
            # a flight that made no keyframe (never initialised, stopped at once: a daemon restarted before its
            # sensors came up) wrote a map of 0 keyframes, which load_map refuses as damaged, over the map there
            raise VioError(f"{path}: this flight made no keyframe (it never initialised or was too short), so there "
                           "is no map to save; " + ("the map that was there is kept" if target.exists()
                                                     else "nothing written"))
        real = os.path.realpath(target)
        ref = next((st for st in (self._own_stamp, self._map_stamp) if st is not None and st[0] == real), None)
        now = file_stamp(target)
        if real in self._redirect:
            target = self._redirect[real]
            conflict = f"{path} changed since this flight loaded or saved it: this flight's map is written to {target}"
        elif ref is not None and now is not None and now != ref:
            # two flights growing one map at once: the later save would drop the earlier one's keyframes unsaid
            alt = target.with_name(f"{target.stem}.{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}{target.suffix}")
            why = "loaded" if ref is self._map_stamp else "saved"
            conflict = (f"{target} changed since this flight {why} it (another run saved over it): this flight's "
                        f"map is written to {alt} instead, and {target} is kept as it is")
            log.warning("map: %s", conflict)
            self._redirect[real] = alt
            target = alt
        # a checkpoint says nothing of its own: every few seconds, it would repeat what the final save says once
        say, warn = (log.debug, log.debug) if checkpoint is not None else (log.info, log.warning)
        keep = self.map_frame_keyframes()
        left_out = len(self.keyframes) - len(keep)
        n_joined = len(keep)
        if prune_m > 0:
            keep = self._prune(keep, prune_m, prune_deg)
        pruned = n_joined - len(keep)
        self.saved_keyframes = keep
        if pruned:
            say("map %s: %d of this flight's keyframes not saved: within %.2f m and %.0f deg of a kept one",
                     path, pruned, prune_m, prune_deg)
        notes = []
        if left_out:
            notes.append(f"{left_out} keyframes left out: their odometry segment was never joined to the map's "
                         f"frame by a loop edge (an estimator reset, or no relocalisation in the loaded map)")
            warn("map %s: %s", path, notes[-1])
        parts = list(self._map_parts) if self.map_keyframes else []
        for s in sorted({self.keyframes[k].session for k in keep if k >= self.map_keyframes}):
            n = sum(1 for k in keep if self.keyframes[k].session == s)
            if not n:  # every keyframe of it pruned: the map has it already
                continue
            joins = None if not parts else self._join_edges(s)  # the first part is the frame's origin
            parts.append({"keyframes": n, "join_edges": joins})
            if joins is not None and joins < WEAK_JOIN_EDGES:
                notes.append(f"a part of {n} keyframes is joined to the rest by only {joins} loop edges: its place "
                             f"in the map's frame rests on them (it shared few views with the rest)")
                warn("map %s: %s; fly it where the map's views are, or leave it out", path, notes[-1])
        poses = [self.graph.estimate[k] for k in keep]
        if world_turn is not None and not self.map_keyframes:  # a loaded map's frame is the autopilot's already
            poses = [world_turn @ T for T in poses]
        h = save_map(target, [self.keyframes[k].t_ns for k in keep], poses,
                     [self.keyframes[k].feats for k in keep], self.vocab, self.cam, note="; ".join(notes),
                     parts=parts, checkpoint=checkpoint)
        if not conflict:
            self._own_stamp = file_stamp(target)  # this run's own save is no conflict for its next one
        return {**h, "left_out_keyframes": left_out, "pruned_keyframes": pruned, "path": str(target),
                "conflict": conflict}

    def _prune(self, keep: list[int], radius_m: float, max_deg: float) -> list[int]:
        """`keep` without this flight's keyframes whose camera is within radius_m and max_deg (the angle of the
        relative rotation) of a keyframe kept before it: the loaded map's all stay, this flight's in order."""
        T = np.einsum("nij,jk->nik", np.array([self.graph.estimate[k] for k in keep]), self.cam.T_body_cam)
        P, R = T[:, :3, 3], T[:, :3, :3]
        min_trace = 1.0 + 2.0 * np.cos(np.radians(max_deg))  # trace(Ra^T Rb) = 1 + 2 cos(angle)
        kept = np.zeros(len(keep), bool)
        kept[:sum(1 for k in keep if k < self.map_keyframes)] = True  # map keyframes come first, all stay
        for i in np.flatnonzero(~kept):
            j = np.flatnonzero(kept[:i])
            j = j[np.sum((P[j] - P[i]) ** 2, axis=1) <= radius_m ** 2]
            kept[i] = not (len(j) and (np.einsum("nab,ab->n", R[j], R[i]) >= min_trace).any())
        return [k for k, ok in zip(keep, kept) if ok]

    def _join_edges(self, session: int) -> int:
        """Active loop edges between this session's keyframes and any other session's.

        Asked up to four times a keyframe while a flight is placed in a map; the counts of every session come
        from one pass over the edges and are kept until a loop edge is added, taken back or re-weighted (a pass
        per question: 10 ms a keyframe at 18 000 edges, docs/loop-closure.md)."""
        version = self.graph.loop_version  # odometry edges (one a keyframe) change no count
        if self._join_counts[0] != version:
            counts: dict[int, int] = {}
            for e in self.graph.active_loops():
                a, b = self.keyframes[e.i].session, self.keyframes[e.j].session
                if a != b:
                    counts[a] = counts.get(a, 0) + 1
                    counts[b] = counts.get(b, 0) + 1
            self._join_counts = (version, counts)
        return self._join_counts[1].get(session, 0)

    # --- outputs ----------------------------------------------------------------------------------
    def correction(self) -> np.ndarray:
        """T_world_odom of the newest keyframe: loop-corrected pose = correction @ odometry pose."""
        if not len(self.graph):
            return np.eye(4)
        return self.graph.estimate[-1] @ inv_T(self.graph.odom[-1])

    def correction_segment(self) -> tuple[int, bool]:
        """(the newest keyframe's session, is it in a frame of its own): a session no loop edge joins to another one
        (a flight's first before any map placement, or a segment after an estimator reset not rejoined yet)."""
        if not self.keyframes:
            return 0, True
        s = self.keyframes[-1].session
        mine = self._comp(s)
        return s, not any(self._comp(o) == mine for o in self._component if o != s)

    def correction_uncertainty(self) -> CorrectionUncertainty | None:
        """How well the newest keyframe is placed in a frame that came to it through loop edges (a loaded map's, or
        this flight's before an estimator reset): its yaw and position covariance in the pose graph (the map's own
        keyframes held fixed), scaled by what the loop edges' residuals show of their actual errors
        (PoseGraph.loop_variance_factor: the graph's loop sigmas are wide, set for GNC). None in the frame the
        odometry itself started in (before a relocalisation, or in a
        flight's first segment): there the correction only takes drift out and the odometry's covariance holds."""
        if not self.keyframes:
            return None
        s = self.keyframes[-1].session
        if self._comp(s) == s:
            return None
        n = len(self.graph) - 1
        try:
            C = self.graph.marginal(n)
            if C is not None:
                C = C * self.graph.loop_variance_factor()
                if not np.isfinite(C).all():
                    raise RuntimeError("it is not finite")
        except RuntimeError as e:  # gtsam could not give it: one loop edge's sigmas, unscaled, rather than nothing
            if not self._marginal_warned:
                log.warning("loop closure: no marginal covariance from the pose graph (%s); the pose sent in the "
                            "map's frame carries one loop edge's sigmas instead", e)
                self._marginal_warned = True
            g = self.graph.noise
            C = np.diag([g.loop_rot_rad ** 2] * 3 + [g.loop_trans_m ** 2] * 3)
        if C is None:
            return None
        return CorrectionUncertainty.from_pose(self.graph.estimate[n], C)

    def corrected_trajectory(self, t_ns: np.ndarray, T_odom: np.ndarray) -> np.ndarray:
        """Odometry poses (N, 4, 4) at t_ns mapped with the final correction of the keyframe before each."""
        return corrected_poses(self, self.graph, t_ns, T_odom)

    def memory_per_keyframe_bytes(self) -> float:
        if not self.keyframes:
            return 0.0
        b = sum(k.feats.nbytes for k in self.keyframes) + sum(len(v) * 12 for v in self.index.vectors)
        return b / len(self.keyframes)


def corrected_poses(closer: LoopCloser, graph: PoseGraph, t_ns: np.ndarray, T_odom: np.ndarray) -> np.ndarray:
    """Odometry poses (N, 4, 4) at t_ns mapped with the correction (estimate @ odometry^-1) that `graph`, a
    graph over `closer`'s keyframes, gives the keyframe before each; a loaded map's keyframes are skipped
    (they are not this flight's). `graph` may be another solve of the same keyframes (bench/)."""
    m = closer.map_keyframes
    if len(closer.keyframes) <= m:
        return np.array(T_odom)
    kt = np.array([k.t_ns for k in closer.keyframes[m:]])
    corr = np.array([e @ inv_T(o) for e, o in zip(graph.estimate[m:], graph.odom[m:])])
    idx = np.clip(np.searchsorted(kt, t_ns, side="right") - 1, 0, len(kt) - 1)
    return np.einsum("nij,njk->nik", corr[idx], T_odom)
