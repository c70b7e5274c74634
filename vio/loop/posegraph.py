"""Keyframe pose graph in GTSAM: odometry edges (BetweenFactorPose3), gravity attitude factors on every
keyframe (roll/pitch stay where the IMU put them: 4-DoF behaviour), loop edges under graduated
non-convexity (GncLMOptimizer, truncated least squares) so that a wrong closure is switched off after the
fact; the odometry, priors and attitude factors are known inliers."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from vio.geometry import inv_T

UP = np.array([0.0, 0.0, 1.0])


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


def _sigmas(rot: float, trans: float) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([rot] * 3 + [trans] * 3))


@dataclass
class Edge:
    i: int
    j: int
    T_i_j: np.ndarray
    kind: str  # "odometry" | "loop"
    weight: float = 1.0  # GNC weight after the last optimisation (loop edges)
    inliers: int = 0  # PnP inliers (loop edges)


class PoseGraph:
    def __init__(self, noise: GraphNoise = GraphNoise()) -> None:
        self.noise = noise
        self.odom: list[np.ndarray] = []  # odometry pose of each node (its own segment's frame)
        self.estimate: list[np.ndarray] = []  # current best pose of each node
        self.priors: dict[int, tuple[np.ndarray, float, float]] = {}  # node -> (pose, sigma rot, sigma trans)
        self.edges: list[Edge] = []
        self.last_iterations = 0

    def __len__(self) -> int:
        return len(self.odom)

    def add_node(self, T_odom: np.ndarray, prev: int | None, prior: tuple[float, float] | None = None) -> int:
        """A keyframe; `prev`: the node the odometry continues from (an edge), else a new segment with `prior`
        (sigma rot, sigma trans) at its odometry pose."""
        i = len(self.odom)
        self.odom.append(np.array(T_odom, float))
        if prev is not None:
            T_rel = inv_T(self.odom[prev]) @ T_odom
            self.edges.append(Edge(prev, i, T_rel, "odometry"))
            self.estimate.append(self.estimate[prev] @ T_rel)
        else:
            self.estimate.append(np.array(T_odom, float))
            rot, trans = prior if prior is not None else (1e-3, 1e-3)
            self.priors[i] = (np.array(T_odom, float), rot, trans)
        return i

    def add_loop(self, i: int, j: int, T_i_j: np.ndarray, inliers: int = 0) -> None:
        self.edges.append(Edge(i, j, np.array(T_i_j, float), "loop", inliers=inliers))

    def _odom_noise(self, T: np.ndarray) -> gtsam.noiseModel.Base:
        n = self.noise
        ang = float(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(T[:3, :3]))))
        dist = float(np.linalg.norm(T[:3, 3]))
        return _sigmas(n.odom_rot_rad + n.odom_rot_per_rad * ang, n.odom_trans_m + n.odom_trans_per_m * dist)

    def optimize(self) -> dict:
        """Re-solve the whole graph; returns {'loop_weights': [...], 'iterations': n}."""
        n = self.noise
        g = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        for i, T in enumerate(self.estimate):
            values.insert(i, gtsam.Pose3(T))
        for i, (T, rot, trans) in self.priors.items():
            g.add(gtsam.PriorFactorPose3(i, gtsam.Pose3(T), _sigmas(rot, trans)))
        att = gtsam.noiseModel.Isotropic.Sigma(2, n.attitude_rad)
        for i, T in enumerate(self.odom):
            g.add(gtsam.AttitudeFactorPose3(i, gtsam.Unit3(UP), att, gtsam.Unit3(T[:3, :3].T @ UP)))
        loop_index = []
        for e in self.edges:
            model = self._odom_noise(e.T_i_j) if e.kind == "odometry" else _sigmas(n.loop_rot_rad, n.loop_trans_m)
            if e.kind == "loop":
                loop_index.append(g.size())
            g.add(gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(e.T_i_j), model))
        if loop_index:
            params = gtsam.GncLMParams()
            params.setLossType(gtsam.GncLossType.TLS)
            loops = set(loop_index)
            params.setKnownInliers([k for k in range(g.size()) if k not in loops])
            opt = gtsam.GncLMOptimizer(g, values, params)
            opt.setInlierCostThresholdsAtProbability(n.gnc_inlier_probability)
            result = opt.optimize()
            w = np.asarray(opt.getWeights())
            loop_edges = [e for e in self.edges if e.kind == "loop"]
            for e, k in zip(loop_edges, loop_index):
                e.weight = float(w[k])
        else:
            result = gtsam.LevenbergMarquardtOptimizer(g, values).optimize()
        self.estimate = [result.atPose3(i).matrix() for i in range(len(self.odom))]
        return {"loop_weights": [e.weight for e in self.edges if e.kind == "loop"]}

    def active_loops(self) -> list[Edge]:
        return [e for e in self.edges if e.kind == "loop" and e.weight >= 0.5]
