"""Geometric verification of a place-recognition candidate: descriptor matches of the old keyframe's stereo
landmarks against the new keyframe's image, PnP RANSAC, and the gravity (roll/pitch) check."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from vio.geometry import inv_T
from vio.loop.features import KeyframeFeatures
from vio.loop.vocabulary import popcount_u64

_TRUE = np.ones(1, bool)


@dataclass(frozen=True)
class PnpResult:
    T_old_new: np.ndarray  # body pose of the new keyframe in the old keyframe's body frame
    inliers: int
    matches: int
    reproj_rmse_px: float
    pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))  # inlier (old, new) rows


def hamming_table(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) uint16 Hamming distances between two sets of binary descriptors (rows of bytes, a multiple
    of 8 a row): XOR and popcount on 64-bit words, two words' counts (each <= 64) added in uint8 before uint16.

    numpy counts bits with the CPU's popcount instruction: ~5.0 ns a pair of ORB descriptors with its temporaries,
    where cv2.batchDistance (opencv-python 5.1) took ~5.6 ns, and one table serves both directions of `match`
    (docs/loop-closure.md, "2026-12-07 stop 54")."""
    A = np.ascontiguousarray(a, np.uint8).view(np.uint64)
    BT = np.ascontiguousarray(np.ascontiguousarray(b, np.uint8).view(np.uint64).T)  # (words, len(b))
    out = np.zeros((len(A), BT.shape[1]), np.uint16)
    for k in range(0, BT.shape[0], 2):
        c = popcount_u64(A[:, k, None] ^ BT[k])
        if k + 1 < BT.shape[0]:
            c += popcount_u64(A[:, k + 1, None] ^ BT[k + 1])
        out += c
    return out


def match(old: KeyframeFeatures, new: KeyframeFeatures, max_hamming: int, ratio: float) -> np.ndarray:
    """(M, 2) index pairs (old landmark, new feature): ratio test and mutual best.

    From one table of every distance: per old landmark the nearest new feature (the first of equals) and the
    second-nearest distance (equal to the nearest when two are equally near), per new feature its nearest old
    landmark (the first of equals) for the mutual test; what cv2.batchDistance's K=2 and K=1 searches (BFMatcher's
    knnMatch) answered, in ~83 % of their time (the same pairs on the shelves flight's 169 calls; a test compares
    them on descriptors full of ties)."""
    has3 = old.landmark_rows
    if len(has3) < 4 or len(new.desc) < 4:
        return np.zeros((0, 2), np.int64)
    D = hamming_table(old.desc.take(has3, axis=0), new.desc)
    rows = np.arange(len(D))
    t = D.argmin(axis=1)  # the first of equally near ones
    best = D[rows, t]
    D[rows, t] = np.iinfo(D.dtype).max  # (put back below: the mutual test reads the whole table)
    second = D.min(axis=1)
    D[rows, t] = best
    q = np.flatnonzero((best <= max_hamming) & (best < ratio * second))
    if not len(q):
        return np.zeros((0, 2), np.int64)
    t = t.take(q)
    keep = D[:, t].argmin(axis=0) == q  # mutual best: the new feature's nearest old landmark is this one
    return np.column_stack([has3[q[keep]], t[keep]]).reshape(-1, 2)


def guided_pairs(old: KeyframeFeatures, new: KeyframeFeatures, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
                 max_hamming: int, radius_px: float) -> np.ndarray:
    """(M, 2) pairs (old landmark, new feature) found by projection: each of the old keyframe's 3D points, put into
    the new image with the pose (rvec, tvec), against the new features within `radius_px` of it; the smallest
    descriptor distance (<= max_hamming) wins, and a new feature chosen by several old points keeps the best of
    them (one to one, not a full mutual-best test).

    No ratio test: the pose already tells where a point must be, so a texture that repeats elsewhere in the image
    does not make its match ambiguous. Across a wide change of view the ratio test of `match` turns down most of
    the true matches; these are the ones it left out."""
    has3 = old.landmark_rows
    if not len(has3) or not len(new.uv):
        return np.zeros((0, 2), np.int64)
    # (gathers by `take` and methods instead of fancy indexing and np.* wrappers: the same arrays, ~15 % less time
    # on the shelves flight's 323 calls)
    R = cv2.Rodrigues(rvec)[0]
    p = old.p_cam.take(has3, axis=0) @ R.T + np.ravel(tvec)
    front = p[:, 2] > 1e-3
    if not front.all():
        has3, p = has3[front], p[front]
    uv = (p[:, :2] / p[:, 2:3]) @ K[:2, :2].T + K[:2, 2]
    u, v = uv[:, 0], uv[:, 1]
    # the new features within radius_px in x of each projection (features sorted by x), then the radius itself:
    # a few thousand pairs instead of an all-against-all distance table
    by_x, xs, ys = new.by_x
    lo = xs.searchsorted(u - radius_px, side="left")
    cnt = xs.searchsorted(u + radius_px, side="right") - lo
    rows = np.arange(len(uv)).repeat(cnt)
    start = cnt.cumsum() - cnt
    s = (lo - start).repeat(cnt) + np.arange(len(rows))  # positions in the x order
    dx, dy = xs.take(s) - u.take(rows), ys.take(s) - v.take(rows)
    near = dx * dx + dy * dy <= radius_px ** 2
    rows, s = rows[near], s[near]
    if not len(rows):
        return np.zeros((0, 2), np.int64)
    o = has3.take(rows)
    x = (old.desc.take(o, axis=0) ^ new.desc.take(by_x.take(s), axis=0)).view(np.uint64)  # (M, 4): 64-bit words
    pc = popcount_u64(x)  # (M, 4) uint8, each <= 64: two of them add up in uint8 without overflow
    ham = (pc[:, 0].astype(np.int64) + pc[:, 1]) + (pc[:, 2] + pc[:, 3])  # (sum(axis=1) is 3x slower on 4 columns)
    keep = ham <= max_hamming
    if not keep.any():
        return np.zeros((0, 2), np.int64)
    o, s, ham = o[keep], s[keep], ham[keep]
    # per old point (the candidates come grouped by it) its best candidate, ties to the one met first (further
    # left): the smallest ham * N + position in one pass ...
    n_new = len(by_x)
    first = np.flatnonzero(np.concatenate((_TRUE, o[1:] != o[:-1])))
    best = np.minimum.reduceat(ham * n_new + s, first)
    o, n, ham = o.take(first), by_x.take(best % n_new), best // n_new
    # ... then per new feature its best old point (ties to the first old point), in the new features' order
    order = ((n * (max_hamming + 1) + ham) * (int(o[-1]) + 1) + o).argsort()
    o, n = o.take(order), n.take(order)
    first = np.concatenate((_TRUE, n[1:] != n[:-1]))
    return np.column_stack([o[first], n[first]]).reshape(-1, 2)


def _cam_pose(T_old_new: np.ndarray, T_body_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rvec, tvec) that put the old camera's points into the new camera, from the body pose T_old_new."""
    T_nc_oc = inv_T(inv_T(T_body_cam) @ T_old_new @ T_body_cam)
    return cv2.Rodrigues(T_nc_oc[:3, :3])[0], T_nc_oc[:3, 3:].copy()


def pnp(old: KeyframeFeatures, new: KeyframeFeatures, K: np.ndarray, T_body_cam: np.ndarray, *,
        max_hamming: int, ratio: float, reproj_px: float, min_inliers: int, guided_px: float = 0.0,
        prior: np.ndarray | None = None, prior_px: float = 0.0) -> PnpResult | None:
    """The new keyframe's body pose in the old one's from the old keyframe's 3D points seen in the new image
    (descriptor matches, PnP RANSAC, Levenberg-Marquardt on the inliers); None when it is not verified.

    With `guided_px` > 0 the pose is then refined on the matches found by projection (`guided_pairs`), which
    across a wide change of view are about twice the ratio test's: kept where they give at least as many
    inliers. The RANSAC's inlier count decides whether the candidate is verified at all, so the guided
    matches make a verified pose more accurate without letting more candidates through.

    With a `prior` (T_old_new where the odometry puts the new keyframe) the RANSAC's matches are found by
    projection from it, within `prior_px` (`guided_pairs`), instead of by the ratio test: on blurred images most
    true matches fail the ratio test, while a look-alike place elsewhere does not project where the prior puts
    the old points. The RANSAC still decides the pose and the inlier count."""
    if prior is None:
        pairs = match(old, new, max_hamming, ratio)
    else:
        pairs = guided_pairs(old, new, K, *_cam_pose(prior, T_body_cam), max_hamming, prior_px)
    n_matches = len(pairs)
    if n_matches < min_inliers:
        return None
    obj, img = _points_of(old, new, pairs)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=60, reprojectionError=reproj_px,
                                             confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
    if not ok or inl is None or len(inl) < min_inliers:
        return None
    inl = inl[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    err = _reproj_err(obj[inl], img[inl], K, rvec, tvec)
    good = err <= reproj_px
    if np.count_nonzero(good) < min_inliers:
        return None
    pairs = pairs[inl]
    if guided_px > 0:
        g = guided_pairs(old, new, K, rvec, tvec, max_hamming, guided_px)
        g_obj, g_img = _points_of(old, new, g)
        n_good = int(np.count_nonzero(good))
        fit = _refit(g_obj, g_img, K, rvec, tvec, (reproj_px,), n_good)  # on what the pose explains
        if fit is not None and np.count_nonzero(fit[2] <= reproj_px) >= n_good:
            rvec, tvec, err = fit
            pairs, good, n_matches = g, err <= reproj_px, len(g)
    return _result(rvec, tvec, T_body_cam, err, good, pairs, n_matches)


def _points_of(old: KeyframeFeatures, new: KeyframeFeatures, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs' 3D points (old keyframe's cam0) and pixels (new keyframe's) as float64, what OpenCV's PnP takes
    (the rows taken are new arrays already: no second copy)."""
    return (old.p_cam[pairs[:, 0]].astype(np.float64, copy=False),
            new.uv[pairs[:, 1]].astype(np.float64, copy=False))


def _reproj_err(obj: np.ndarray, img: np.ndarray, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """Reprojection error [px] of each 3D point `obj` against its pixel `img` under the pose (rvec, tvec)."""
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, None)
    d = proj[:, 0] - img
    d *= d
    return np.sqrt(d[:, 0] + d[:, 1])  # np.linalg.norm(axis=1)'s sum and root, without its checks


def _refit(obj: np.ndarray, img: np.ndarray, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
           thresholds: tuple[float, ...], need: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Levenberg-Marquardt refits of (rvec, tvec) on the points within each threshold [px] of it in turn; the refit
    pose and every point's reprojection error under it, or None when fewer than `need` are within a threshold."""
    if len(obj) < need:
        return None
    for thr in thresholds:
        sel = _reproj_err(obj, img, K, rvec, tvec) <= thr
        if np.count_nonzero(sel) < need:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(obj[sel], img[sel], K, None, rvec.copy(), tvec.copy())
    return rvec, tvec, _reproj_err(obj, img, K, rvec, tvec)


def _result(rvec: np.ndarray, tvec: np.ndarray, T_body_cam: np.ndarray, err: np.ndarray, good: np.ndarray,
            pairs: np.ndarray, n_matches: int) -> PnpResult:
    T_newcam_oldcam = np.eye(4)
    T_newcam_oldcam[:3, :3] = cv2.Rodrigues(rvec)[0]
    T_newcam_oldcam[:3, 3] = np.ravel(tvec)
    T_old_new = T_body_cam @ inv_T(T_newcam_oldcam) @ inv_T(T_body_cam)
    return PnpResult(T_old_new, int(np.count_nonzero(good)), n_matches, float(np.sqrt(np.mean(err[good] ** 2))),
                     pairs[good])


def pnp_from(old: KeyframeFeatures, new: KeyframeFeatures, K: np.ndarray, T_body_cam: np.ndarray,
             T_old_new_guess: np.ndarray, *, max_hamming: int, reproj_px: float, min_inliers: int, guided_px: float
             ) -> PnpResult | None:
    """As `pnp`, but the matches are found by projection from a pose guess (`guided_pairs`), with no RANSAC: the
    other direction of an edge whose first PnP gave the guess. The pose is refit on the matches within
    `guided_px` of the guess, then on those within `reproj_px`; None when fewer than `min_inliers` are left."""
    rvec, tvec = _cam_pose(T_old_new_guess, T_body_cam)
    g = guided_pairs(old, new, K, rvec, tvec, max_hamming, guided_px)
    obj, img = _points_of(old, new, g)
    fit = _refit(obj, img, K, rvec, tvec, (guided_px, reproj_px), max(min_inliers, 6))
    if fit is None:
        return None
    rvec, tvec, err = fit
    good = err <= reproj_px
    if np.count_nonzero(good) < min_inliers:
        return None
    return _result(rvec, tvec, T_body_cam, err, good, g, len(g))


def gravity_disagreement_deg(R_world_old: np.ndarray, R_world_new: np.ndarray, R_old_new: np.ndarray) -> float:
    """Angle between the new keyframe's gravity direction from the odometry and through the loop edge.

    Roll and pitch are observed by the IMU in both keyframes, so a true edge must carry them over."""
    up = np.array([0.0, 0.0, 1.0])
    a = R_world_new.T @ up
    b = (R_world_old @ R_old_new).T @ up
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def refine_edge(old: KeyframeFeatures, new: KeyframeFeatures, fwd: PnpResult, back: PnpResult, K: np.ndarray,
                baseline_m: float, T_body_cam: np.ndarray, T_old_new: np.ndarray, *, sigma_px: float = 1.0,
                max_points: int = 200) -> np.ndarray | None:
    """T_old_new re-estimated from both PnPs' inliers at once: the relative camera pose and the matched points
    in one small bundle adjustment (one Gauss-Newton step of GTSAM's from the two PnPs' mean), each point seen
    in stereo (left pixel, and the right one its depth implies) in a keyframe that measured its depth, else
    by its left pixel.

    PnP treats its 3D points as exact; a far point's stereo depth is not (0.3 px of disparity is 60 cm at
    10 m), and that error shifts the point in the other image by the parallax the edge spans, which biases
    the translation. Here each depth weighs as much as its disparity allows. None when the solve fails."""
    import gtsam
    from gtsam.symbol_shorthand import L, X

    # one row per matched point: the forward inliers (old landmark, new feature), then the backward ones
    pairs = np.vstack([fwd.pairs, back.pairs[:, ::-1]]).reshape(-1, 2)
    _, first = np.unique(pairs, axis=0, return_index=True)
    pairs = pairs[np.sort(first)][:max_points]
    if len(pairs) < 6:
        return None
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Ks = gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, baseline_m)
    K2 = gtsam.Cal3_S2(fx, fy, 0.0, cx, cy)
    huber = gtsam.noiseModel.mEstimator.Huber.Create(1.345)
    n3 = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(3, sigma_px))
    n2 = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(2, sigma_px))
    T_oc_nc = inv_T(T_body_cam) @ T_old_new @ T_body_cam

    def observations(f: KeyframeFeatures, rows: np.ndarray) -> tuple[np.ndarray, list]:
        p = f.p_cam[rows]
        has3 = np.isfinite(p[:, 0])
        with np.errstate(invalid="ignore", divide="ignore"):
            u, v = fx * p[:, 0] / p[:, 2] + cx, fy * p[:, 1] / p[:, 2] + cy
            meas = np.column_stack([u, u - fx * baseline_m / p[:, 2], v])
        return p, [gtsam.StereoPoint2(*m) if h else f.uv[r] for m, h, r in zip(meas.tolist(), has3, rows)]

    p_old, obs_old = observations(old, pairs[:, 0])
    p_new, obs_new = observations(new, pairs[:, 1])
    init = np.where(np.isfinite(p_old[:, :1]), p_old, p_new @ T_oc_nc[:3, :3].T + T_oc_nc[:3, 3])
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    graph.add(gtsam.NonlinearEqualityPose3(X(0), gtsam.Pose3()))
    values.insert(X(0), gtsam.Pose3())
    values.insert(X(1), gtsam.Pose3(T_oc_nc))
    for k, (o, nw, p) in enumerate(zip(obs_old, obs_new, init)):
        for cam, z in ((X(0), o), (X(1), nw)):
            graph.add(gtsam.GenericStereoFactor3D(z, n3, cam, L(k), Ks) if isinstance(z, gtsam.StereoPoint2)
                      else gtsam.GenericProjectionFactorCal3_S2(z, n2, cam, L(k), K2))
        values.insert(L(k), p)
    params = gtsam.GaussNewtonParams()
    params.setMaxIterations(1)  # a second step moved the edges 0.8 mm (median) and no flight's ratio
    try:
        result = gtsam.GaussNewtonOptimizer(graph, values, params).optimize()
    except RuntimeError:
        return None
    return T_body_cam @ result.atPose3(X(1)).matrix() @ inv_T(T_body_cam)
