"""Keyframe pose graph in GTSAM: odometry edges (BetweenFactorPose3), gravity attitude factors on every
keyframe (roll/pitch stay where the IMU put them: 4-DoF behaviour) and loop edges, solved incrementally.

Two graphs, because a full-graph GNC solve costs seconds on a 10-minute flight (1.8 s at 2 400 keyframes):

- the **decision** graph: only the loop-touched keyframes (and their segment starts), joined by the
  odometry composed between them (relative pose and its propagated covariance), their attitude factors,
  priors and all loop edges under graduated non-convexity (GncLMOptimizer, truncated least squares). It
  decides, after every closure and for every loop edge ever added, which ones are inliers: a wrong closure
  accepted earlier is switched off after the fact. Its size grows with the number of loop edges, not with
  the flight.
- the **full** graph in gtsam.ISAM2: every keyframe, odometry, attitude factors and priors, plus the loop
  edges the decision graph holds as inliers (Gaussian). A switched-off edge is removed from iSAM2
  (removeFactorIndices), a re-admitted one added again; each closure only re-eliminates the part of the
  Bayes tree the new edges touch."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.stats import chi2

from vio.geometry import inv_T

log = logging.getLogger(__name__)

UP = np.array([0.0, 0.0, 1.0])


def _cholesky_else_qr(solve):
    """solve(linear solver type) with Cholesky, and again with QR if Cholesky finds the system indeterminate: a
    segment held only by its loose prior (100 m, 180 deg: a flight not yet relocalised in a loaded map) beside
    millimetre loop edges is too ill-conditioned for it (bench/loop_reloc.py --second-seeds 13 stopped the loop
    stage so). QR always would cost 1.7x the decision time (10 -> 17.6 ms mean on aggressive-realistic-seed3)."""
    try:
        return solve("MULTIFRONTAL_CHOLESKY")
    except RuntimeError as e:
        if "ndeterminate" not in str(e):
            raise
        return solve("MULTIFRONTAL_QR")


# loop_variance_factor's floor: an edge is never taken as better than 0.1x its sigmas (6 mm and 0.07 deg at the
# defaults; the bench's PnP edges are 6-10 mm off, their residuals read 0.11-0.21x the sigmas)
MIN_LOOP_VARIANCE_FACTOR = 0.01


class DecisionError(RuntimeError):
    """The decision solve after new loop edges failed. Raised before iSAM2 or any edge's weight is touched, so
    the caller can take the new edges back (`drop_loops_from`) and go on with the graph as it was."""


@dataclass(frozen=True)
class GraphNoise:
    odom_rot_rad: float = 0.002  # per edge
    odom_rot_per_rad: float = 0.01  # extra per radian turned
    odom_trans_m: float = 0.003  # per edge
    odom_trans_per_m: float = 0.01  # extra per metre flown
    attitude_rad: float = 0.01
    loop_rot_rad: float = 0.01
    loop_trans_m: float = 0.03
    gnc_inlier_probability: float = 0.99
    flush_every: int = 10  # keyframes buffered before they go into iSAM2 (a closure flushes at once)
    isam_iterations: int = 3  # iSAM2 updates after a closure at most (relinearisation of a large correction)
    fit_iterations: int = 2  # Gauss-Newton steps of the fast path's fit check (a pose graph is nearly linear)
    # new loop edges whose error at the current estimate is within this share of the TLS threshold go into iSAM2
    # without the fit check (the graph already agrees with them; in a lap that closes at every keyframe)
    quick_fit_share: float = 0.25
    relinearize_threshold: float = 0.01  # iSAM2 (measured: 0.001 costs 2-4x more for the same ATE)
    # loop edges that already fit the estimate wait for the next iSAM2 update (every flush_every keyframes, or the
    # next closure that takes the full path) instead of one update each: a lap closing at every keyframe
    defer_quick_fits: bool = True


def _sigmas(rot: float, trans: float) -> np.ndarray:
    return np.array([rot] * 3 + [trans] * 3)


@dataclass
class Edge:
    i: int
    j: int
    T_i_j: np.ndarray
    kind: str  # "odometry" | "loop"
    weight: float = 1.0  # GNC weight after the last decision (loop edges)
    inliers: int = 0  # PnP inliers (loop edges)
    sigma_scale: float = 1.0  # loop edge sigmas are the graph's times this (a weaker edge: fewer inliers)


def _adjoint(T: np.ndarray) -> np.ndarray:
    return gtsam.Pose3(T).AdjointMap()


class PoseGraph:
    def __init__(self, noise: GraphNoise = GraphNoise()) -> None:
        self.noise = noise
        self.odom: list[np.ndarray] = []  # odometry pose of each node (its own segment's frame)
        self.estimate: list[np.ndarray] = []  # current best pose of each node
        self.priors: dict[int, tuple[np.ndarray, float, float]] = {}  # node -> (pose, sigma rot, sigma trans)
        self.edges: list[Edge] = []
        self.last_decision_nodes = 0  # size of the last decision graph
        self.decisions = 0  # GNC decisions run (the slow path)
        self.quick_fits = 0  # closures whose new edges already fitted the estimate (no fit check)
        self.loop_version = 0  # +1 whenever a loop edge is added, taken back or re-weighted (callers' caches)
        self._segment: list[int] = []  # first node of each node's odometry segment
        # sum over the segment's edges up to the node of Ad(T_w_k) Sigma_k Ad(T_w_k)^T: the covariance of
        # the odometry composed from node a to node b is Ad(T_w_b^-1) (C_b - C_a) Ad(T_w_b^-1)^T
        self._cum: list[np.ndarray] = []
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(noise.relinearize_threshold)
        params.relinearizeSkip = 1
        params.setFactorization("QR")  # a new segment's loose prior (100 m, 180 deg) is ill-conditioned for Cholesky
        self._isam = gtsam.ISAM2(params)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._condensed_cache: dict[tuple, list] = {}
        self._in_isam: dict[int, int] = {}  # index in self.edges of a loop edge -> its iSAM2 factor index
        self._queued: dict[int, int] = {}  # a loop edge waiting in the pending factors -> its position there
        self._variance_factor = (-1, 1.0)  # (estimate_version, loop_variance_factor) of the last computation
        self.estimate_version = 0  # +1 each time the estimate is re-read from iSAM2 (closures, deferred edges)
        # The odometry edge into each node (index in self.edges; None at a segment start); where each node's
        # attitude factor and odometry edge are, ("att", node) / ("odom", edge): a position in the pending
        # factors or an iSAM2 index, so that `settle` can replace them; and each node's pose composed along the
        # odometry edges from its segment start (what the decision graph composes; = odom until settled)
        self._into: list[int | None] = []
        self._pending_at: dict[tuple[str, int], int] = {}
        self._isam_at: dict[tuple[str, int], int] = {}
        self._remove: list[int] = []  # iSAM2 factors to remove with the next update (replaced ones)
        self._chain: list[np.ndarray] = []
        self.settled: dict[int, np.ndarray] = {}  # node -> its smoothed odometry pose (`settle`)

    def __len__(self) -> int:
        return len(self.odom)

    def add_node(self, T_odom: np.ndarray, prev: int | None, prior: tuple[float, float] | None = None) -> int:
        """A keyframe; `prev`: the node the odometry continues from (an edge), else a new segment with `prior`
        (sigma rot, sigma trans) at its odometry pose."""
        i = len(self.odom)
        T_odom = np.array(T_odom, float)
        self.odom.append(T_odom)
        n = self.noise
        if prev is not None:
            T_rel = inv_T(self.odom[prev]) @ T_odom
            self._into.append(len(self.edges))
            self.edges.append(Edge(prev, i, T_rel, "odometry"))
            self.estimate.append(self.estimate[prev] @ T_rel)
            self._chain.append(self._chain[prev] @ T_rel)
            sig = self._odom_sigmas(T_rel)
            self._add_replaceable(("odom", len(self.edges) - 1), self._odom_factor(self.edges[-1], sig))
            A = _adjoint(T_odom)
            self._cum.append(self._cum[prev] + A @ np.diag(sig ** 2) @ A.T)
            self._segment.append(self._segment[prev])
        else:
            self._into.append(None)
            self._chain.append(T_odom.copy())
            self.estimate.append(T_odom.copy())
            rot, trans = prior if prior is not None else (1e-3, 1e-3)
            self.priors[i] = (T_odom.copy(), rot, trans)
            self._new_factors.add(self._prior(i))
            self._cum.append(np.zeros((6, 6)))
            self._segment.append(i)
        self._add_replaceable(("att", i), self._attitude(i))
        self._new_values.insert(i, gtsam.Pose3(self.estimate[i]))
        if self._new_values.size() >= n.flush_every:
            queued = bool(self._queued)
            self._isam_update()
            if queued:  # deferred loop edges went in: the estimate (and the correction) follows them now
                self._read_estimate()
        return i

    def settle(self, i: int, T_odom: np.ndarray) -> None:
        """Node i's odometry pose as the odometry's smoother left it (with lag_s of later data) instead of its estimate
        at i's own solve: its attitude factor takes the settled roll/pitch, and an odometry edge whose two ends are
        both settled is replaced by the relative pose of the settled poses (same sigmas: the composed covariance
        stays); `odom` (the pose the odometry reported, which the correction maps) is left alone."""
        self.settled[i] = np.array(T_odom, float)
        self._replace(("att", i), self._attitude(i))
        heads = [i] + ([i + 1] if i + 1 < len(self._into) and self._into[i + 1] is not None
                       and self.edges[self._into[i + 1]].i == i else [])
        changed = None
        for h in heads:
            k = self._into[h]
            if k is None or h not in self.settled or self.edges[k].i not in self.settled:
                continue
            e = self.edges[k]
            sig = self._odom_sigmas(e.T_i_j)
            e.T_i_j = inv_T(self.settled[e.i]) @ self.settled[h]
            self._replace(("odom", k), self._odom_factor(e, sig))
            changed = h if changed is None else min(changed, h)
        seg = self._segment[i]
        if changed is not None:
            for h in range(changed, len(self._chain)):
                if self._segment[h] != seg:
                    break
                e = self.edges[self._into[h]]
                self._chain[h] = self._chain[e.i] @ e.T_i_j
        # the decision graph's factors of i (attitude) and of the nodes whose composed odometry changed
        self._condensed_cache = {key: f for key, f in self._condensed_cache.items()
                                 if key[1] < i or self._segment[key[1]] != seg}

    def add_loop(self, i: int, j: int, T_i_j: np.ndarray, inliers: int = 0, sigma_scale: float = 1.0) -> None:
        """A loop edge: node j's pose in node i's frame. An edge from a node to itself constrains nothing; it is kept
        (the edge list stays in the caller's order) but switched off and never enters a solve."""
        e = Edge(i, j, np.array(T_i_j, float), "loop", inliers=inliers, sigma_scale=sigma_scale)
        if i == j:
            log.warning("loop edge from keyframe %d to itself ignored: it constrains nothing", i)
            e.weight = 0.0
        self.edges.append(e)
        self.loop_version += 1

    def _loops(self) -> list[int]:
        """Indices of the loop edges a solve can use (all but self-edges)."""
        return [k for k, e in enumerate(self.edges) if e.kind == "loop" and e.i != e.j]

    def drop_loops_from(self, first: int) -> int:
        """Take back the loop edges added since self.edges had `first` entries (not yet in iSAM2: after a
        DecisionError); returns how many."""
        tail = self.edges[first:]
        if any(e.kind != "loop" for e in tail) or any(k in self._in_isam for k in range(first, len(self.edges))):
            raise ValueError("only loop edges not yet solved can be taken back")
        del self.edges[first:]
        self.loop_version += 1
        return len(tail)

    def _odom_sigmas(self, T: np.ndarray) -> np.ndarray:
        n = self.noise
        ang = float(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(T[:3, :3]))))
        dist = float(np.linalg.norm(T[:3, 3]))
        return _sigmas(n.odom_rot_rad + n.odom_rot_per_rad * ang, n.odom_trans_m + n.odom_trans_per_m * dist)

    def _add_replaceable(self, key: tuple[str, int], f: gtsam.NonlinearFactor) -> None:
        self._pending_at[key] = self._new_factors.size()
        self._new_factors.add(f)

    def _replace(self, key: tuple[str, int], f: gtsam.NonlinearFactor) -> None:
        """Factor `key` replaced by f: in place while pending, else removed from iSAM2 with the next update."""
        if key in self._pending_at:
            self._new_factors.replace(self._pending_at[key], f)
        else:
            self._remove.append(self._isam_at.pop(key))
            self._add_replaceable(key, f)

    @staticmethod
    def _odom_factor(e: Edge, sigmas: np.ndarray) -> gtsam.NonlinearFactor:
        return gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(e.T_i_j), gtsam.noiseModel.Diagonal.Sigmas(sigmas))

    def _prior(self, i: int) -> gtsam.NonlinearFactor:
        T, rot, trans = self.priors[i]
        return gtsam.PriorFactorPose3(i, gtsam.Pose3(T), gtsam.noiseModel.Diagonal.Sigmas(_sigmas(rot, trans)))

    def _attitude(self, i: int) -> gtsam.NonlinearFactor:
        att = gtsam.noiseModel.Isotropic.Sigma(2, self.noise.attitude_rad)
        R = self.settled[i][:3, :3] if i in self.settled else self.odom[i][:3, :3]
        return gtsam.AttitudeFactorPose3(i, gtsam.Unit3(UP), att, gtsam.Unit3(R.T @ UP))

    def _loop_factor(self, e: Edge, decision: bool = False) -> gtsam.NonlinearFactor:
        """The edge's factor with its sigmas scaled by `sigma_scale`. For a decision (the fit checks and GNC) an
        edge is never held tighter than the graph's sigmas: GNC's TLS threshold is in sigmas, and with a few true
        edges held tight against several strong false ones it switched the true ones off (3 true and 3-5 false
        edges on a drifting lap, all at half the sigmas: 7 and 12 true edges off over 30 draws, none at the
        graph's; tests/test_loop.py). What a tighter edge is for, a better estimate, comes from iSAM2."""
        k = max(e.sigma_scale, 1.0) if decision else e.sigma_scale
        model = gtsam.noiseModel.Diagonal.Sigmas(_sigmas(self.noise.loop_rot_rad * k, self.noise.loop_trans_m * k))
        return gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(e.T_i_j), model)

    def _isam_update(self, remove: list[int] | None = None) -> gtsam.ISAM2Result:
        r = self._isam.update(self._new_factors, self._new_values, (remove or []) + self._remove)
        if self._pending_at or self._queued:
            idx = r.getNewFactorsIndices()
            for k, pos in self._pending_at.items():
                self._isam_at[k] = int(idx[pos])
            for k, pos in self._queued.items():
                self._in_isam[k] = int(idx[pos])
        self._pending_at, self._remove, self._queued = {}, [], {}
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        return r

    def _condensed(self, loops: list[int]) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The decision graph without its loop edges: the loop-touched keyframes and their segment starts,
        the odometry composed between consecutive ones (propagated covariance), attitude factors, priors."""
        ends = {v for k in loops for v in (self.edges[k].i, self.edges[k].j)}
        nodes = sorted(ends | {self._segment[v] for v in ends})
        self.last_decision_nodes = len(nodes)
        g = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        last_in_segment: dict[int, int] = {}
        for v in nodes:
            values.insert(v, gtsam.Pose3(self.estimate[v]))
            a = last_in_segment.get(self._segment[v])
            for f in self._condensed_factors(a, v):
                g.add(f)
            last_in_segment[self._segment[v]] = v
        return g, values

    def _condensed_factors(self, a: int | None, v: int) -> list:
        """Node v's factors in the decision graph (prior, attitude, odometry composed from node a); kept,
        since most of the decision graph is the same from one closure to the next."""
        key = (a, v)
        if key not in self._condensed_cache:
            fs = [self._attitude(v)]
            if v in self.priors:
                fs.append(self._prior(v))
            if a is not None:
                Ad = _adjoint(inv_T(self.odom[v]))
                cov = Ad @ (self._cum[v] - self._cum[a]) @ Ad.T
                fs.append(gtsam.BetweenFactorPose3(a, v, gtsam.Pose3(inv_T(self._chain[a]) @ self._chain[v]),
                                                   gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T))))
            self._condensed_cache[key] = fs
        return self._condensed_cache[key]

    def _decision_graph(self, known: gtsam.NonlinearFactorGraph,
                        loops: list[int]) -> tuple[gtsam.NonlinearFactorGraph, list[gtsam.NonlinearFactor]]:
        """The decision graph's `known` factors followed by the loop edges `loops` (at the decision sigmas)."""
        g = gtsam.NonlinearFactorGraph()
        g.push_back(known)
        factors = [self._loop_factor(self.edges[k], decision=True) for k in loops]
        for f in factors:
            g.add(f)
        return g, factors

    def _fits(self, known: gtsam.NonlinearFactorGraph, values: gtsam.Values, loops: list[int]) -> bool:
        """Least squares on the decision graph with the loop edges `loops` as inliers: does every one of
        them fit the solution (error under the TLS threshold GNC uses)?"""
        g, factors = self._decision_graph(known, loops)

        def solve(linear: str) -> gtsam.Values:
            params = gtsam.GaussNewtonParams()
            params.setMaxIterations(self.noise.fit_iterations)
            params.setLinearSolverType(linear)
            return gtsam.GaussNewtonOptimizer(g, values, params).optimize()

        result = _cholesky_else_qr(solve)
        bar = self._tls_cost_bar()
        return all(f.error(result) <= bar for f in factors)

    def _tls_cost_bar(self) -> float:
        """A loop edge's factor error (0.5 chi^2) at GNC's TLS inlier threshold."""
        return 0.5 * float(chi2.ppf(self.noise.gnc_inlier_probability, 6))

    def _decide(self, known: gtsam.NonlinearFactorGraph, values: gtsam.Values, loops: list[int]) -> list[float]:
        """GNC (TLS) weights of the loop edges `loops` (indices in self.edges) on the decision graph.

        Two starts of the same TLS problem: every edge free (an edge accepted earlier can be switched off after the
        fact), and the edges active so far held as inliers (if any); the weights whose solution has the lower TLS
        cost win. GNC from all-free alone can lose a few true edges to many wrong ones arriving at once: with three
        accepted edges on a drifting lap and twenty wild wrong ones it switched the three off on one draw in twenty
        and the graph fell back to the odometry (tests/test_loop.py)."""
        g, factors = self._decision_graph(known, loops)
        first_loop = known.size()
        held = [first_loop + m for m, k in enumerate(loops)  # accepted before: in iSAM2 (or waiting to go in)
                if self.edges[k].weight >= 0.5 and (k in self._in_isam or k in self._queued)]
        bar = self._tls_cost_bar()

        def run(inliers: list[int]) -> tuple[np.ndarray, float]:
            def solve(linear: str) -> tuple[np.ndarray, gtsam.Values]:
                params = gtsam.GncLMParams()
                base = params.baseOptimizerParams
                base.setLinearSolverType(linear)
                params.baseOptimizerParams = base
                params.setScheduler(gtsam.GncScheduler.SuperLinear)  # measured: 1.5-2.5x faster, same decisions
                params.setLossType(gtsam.GncLossType.TLS)
                params.setKnownInliers(list(range(first_loop)) + inliers)
                opt = gtsam.GncLMOptimizer(g, values, params)
                opt.setInlierCostThresholdsAtProbability(self.noise.gnc_inlier_probability)
                result = opt.optimize()
                return np.asarray(opt.getWeights()), result

            w, result = _cholesky_else_qr(solve)
            cost = float(known.error(result)) + sum(min(f.error(result), bar) for f in factors)
            return w, cost

        w, cost = run([])
        if held and any(w[i] < 0.5 for i in held):  # the free start dropped an accepted edge: is that better?
            w_held, cost_held = run(held)
            if cost_held < cost:
                w = w_held
        return [float(w[first_loop + m]) for m in range(len(loops))]

    def optimize(self, decide: bool = False, defer: bool = True) -> dict:
        """Bring the graph up to date after new loop edges. Fast path: least squares on the decision graph
        with the active and the new loop edges; if every one of them fits, they go into iSAM2 as they are.
        Otherwise (or with `decide`) GNC re-decides every loop edge ever added, switched-off ones included,
        and iSAM2's loop edges are brought in line: a wrong closure accepted earlier is switched off after
        the fact, a wrongly refused one comes back. `defer` = False: new edges that fit go into iSAM2 and the estimate
        now, never deferred (a closure that joins two sessions: the output must see the new frame and its
        uncertainty at once, even when the frames nearly coincide). Returns {'loop_weights': [...], 'decided': bool}."""
        loops = self._loops()
        every = [e for e in self.edges if e.kind == "loop"]  # the caller's edges, self-edges (off) included
        if loops and not decide and self._fit_already(loops):
            self.quick_fits += 1
            if self.noise.defer_quick_fits and defer:
                for k in loops:
                    if self.edges[k].weight >= 0.5 and k not in self._in_isam and k not in self._queued:
                        self._queued[k] = self._new_factors.size()
                        self._new_factors.add(self._loop_factor(self.edges[k]))
            else:
                self._sync(loops)
            return {"loop_weights": [e.weight for e in every], "decided": False}
        if self._queued:  # the full path starts from an iSAM2 that holds every edge accepted so far
            self._isam_update()
        if loops:
            try:
                known, values = self._condensed(loops)
                if decide or not self._fits(known, values, [k for k in loops if self.edges[k].weight >= 0.5]):
                    weights = self._decide(known, values, loops)
                    decide = True
                    for k, w in zip(loops, weights):
                        self.edges[k].weight = w
                    self.decisions += 1
                    self.loop_version += 1
            except RuntimeError as e:  # gtsam's solver errors (an indeterminate system that QR could not solve)
                raise DecisionError(f"{type(e).__name__}: {e}") from e
        self._sync(loops)
        return {"loop_weights": [e.weight for e in every], "decided": decide}

    def _fit_already(self, loops: list[int]) -> bool:
        """Every new (not yet solved) inlier loop edge fits the current estimate within quick_fit_share of the
        TLS threshold. The edges already in iSAM2 fit it (they were checked), and an edge the solution already
        agrees with moves it little, so the decision graph's check would pass; a first closure, a relocalisation
        or a wrong edge is far off the current estimate and takes the full path."""
        new = [k for k in loops if self.edges[k].weight >= 0.5 and k not in self._in_isam and k not in self._queued]
        if not new:
            return False
        bar = self.noise.quick_fit_share * self._tls_cost_bar()
        for k in new:
            e = self.edges[k]
            v = gtsam.Values()
            v.insert(e.i, gtsam.Pose3(self.estimate[e.i]))
            v.insert(e.j, gtsam.Pose3(self.estimate[e.j]))
            if self._loop_factor(e, decision=True).error(v) > bar:
                return False
        return True

    def _sync(self, loops: list[int]) -> None:
        """iSAM2 update: pending keyframes, loop edges with weight >= 0.5 in, the others out."""
        remove = [self._in_isam.pop(k) for k in loops if self.edges[k].weight < 0.5 and k in self._in_isam]
        added = [k for k in loops if self.edges[k].weight >= 0.5 and k not in self._in_isam and k not in self._queued]
        first_new = self._new_factors.size()
        for k in added:
            self._new_factors.add(self._loop_factor(self.edges[k]))
        idx = list(self._isam_update(remove).getNewFactorsIndices())
        for m, k in enumerate(added):
            self._in_isam[k] = int(idx[first_new + m])
        for _ in range(self.noise.isam_iterations - 1):  # relinearise a large correction, while it moves
            if not self._isam.update().getVariablesRelinearized():
                break
        self._read_estimate()

    def _read_estimate(self) -> None:
        self.estimate_version += 1
        values = self._isam.calculateEstimate()
        rows = gtsam.utilities.extractPose3(values)  # (N, 12): R row-major, t; keys 0..N-1 in order
        T = np.tile(np.eye(4), (len(rows), 1, 1))
        T[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
        T[:, :3, 3] = rows[:, 9:]
        self.estimate = list(T)

    def refresh(self) -> None:
        """Pending keyframes, replaced odometry edges and deferred loop edges into iSAM2 and the estimate re-read,
        with no new loop decision (between closures the estimate follows only deferred edges, at a flush)."""
        self._sync(self._loops())

    def marginal(self, i: int) -> np.ndarray | None:
        """6x6 covariance of node i's pose (GTSAM Pose3 tangent: rotation, translation, node frame) given the
        factors in iSAM2. A node still waiting for the next flush is reached from the newest solved node of its
        segment along the odometry (that node's covariance carried over, plus the composed odometry's); None if
        its segment has no solved node yet. Loop edges still pending are left out (the covariance is larger)."""
        a = i
        while not self._isam.valueExists(a):
            if self._into[a] is None:
                return None
            a = self.edges[self._into[a]].i
        C = np.asarray(self._isam.marginalCovariance(a))
        if a == i:
            return C
        Ad = _adjoint(inv_T(self._chain[i]) @ self._chain[a])  # node a's perturbation seen at node i
        Ai = _adjoint(inv_T(self.odom[i]))
        return Ad @ C @ Ad.T + Ai @ (self._cum[i] - self._cum[a]) @ Ai.T

    def loop_variance_factor(self) -> float:
        """How far the active loop edges' residuals at the estimate run from their sigmas: a 95 % upper bound on
        the a-posteriori variance factor (their chi-square over 6 (n - 1) degrees of freedom, one placement taken
        by the fit). The loop sigmas are set for the decisions (GNC's threshold is in sigmas) and run wide of the
        edges' actual errors (about 0.2x on the bench flights); a covariance scaled by this factor says what the
        edges show instead. 1 (the sigmas as set) while there are too few edges to tell; never below
        MIN_LOOP_VARIANCE_FACTOR (edges that agree with each other can still share one error, e.g. a calibration's)."""
        if self._variance_factor[0] == self.estimate_version:
            return self._variance_factor[1]
        loops = [e for e in self.active_loops() if e.i != e.j]
        dof = 6 * (len(loops) - 1)
        k = 1.0
        if dof > 0:
            v = gtsam.Values()
            for n in {n for e in loops for n in (e.i, e.j)}:
                v.insert(n, gtsam.Pose3(self.estimate[n]))
            k = max(sum(2.0 * self._loop_factor(e).error(v) for e in loops) / float(chi2.ppf(0.05, dof)),
                    MIN_LOOP_VARIANCE_FACTOR)
        self._variance_factor = (self.estimate_version, k)
        return k

    def active_loops(self) -> list[Edge]:
        return [e for e in self.edges if e.kind == "loop" and e.weight >= 0.5]
