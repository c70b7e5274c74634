"""The motion check (vio.motion_check) on a replay: what it read, what it cost, and a trajectory against SITL truth.

    python bench/motion_check.py readings DATASET [--config TOML]
    python bench/motion_check.py truth TRAJ.tum RAW.npz [--align-s 15]

`readings` replays DATASET with `MotionCheck.add` wrapped: resets and their reasons, keyframes compared, how many
disagreeing streaks began and the longest, the reading with the most sigma and the one furthest apart in m/s, and the
check's CPU time a keyframe against the replay's CPU time (the figures in docs/estimator.md, "Motion check").
`truth` compares a TUM trajectory with an ArduPilot SITL run's truth (`raw.npz`, array `truth` = t_ns, north, east,
down, ...; the same clock as the recording): errors by time window, 4-DoF aligned on the first --align-s seconds
(a runaway must not bend the alignment), and the ATE aligned on the whole flight.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vio.evaluation import align_4dof  # noqa: E402

WINDOWS_S = ((0, 15), (15, 17), (17, 30), (30, 60), (60, 120), (120, 240), (0, 1e9))


def readings(dataset: str, config: str | None) -> None:
    import vio.motion_check as mc
    from vio.app.replay import replay
    from vio.config import load_config
    from vio.io.euroc import EurocDataset

    checks: list[mc.MotionCheck] = []
    spent: list[float] = []
    streaks = {"began": 0, "longest": 0}
    init, add = mc.MotionCheck.__init__, mc.MotionCheck.add

    def counted_init(self, *a, **kw):
        init(self, *a, **kw)
        checks.append(self)

    def timed_add(self, *a, **kw):
        t0 = time.process_time()
        out = add(self, *a, **kw)
        spent.append(time.process_time() - t0)
        streaks["began"] += len(self.streak) == 1
        streaks["longest"] = max(streaks["longest"], len(self.streak))
        return out

    mc.MotionCheck.__init__, mc.MotionCheck.add = counted_init, timed_add
    t0 = time.process_time()
    res = replay(EurocDataset(dataset), cfg=load_config(config) if config else None, progress=False)
    cpu = time.process_time() - t0
    worst = [c.worst for c in checks if c.worst is not None]
    most_sigma = max(worst, key=lambda r: r.n_sigma, default=None)
    ms = np.array(spent) * 1e3
    print(f"{dataset}: {res.resets} resets; {sum(c.readings for c in checks)} keyframes compared, disagreeing streaks "
          f"begun {streaks['began']}, longest {streaks['longest']}")
    print(f"  most sigma: {most_sigma.describe() if most_sigma else None}")
    if len(ms):
        print(f"  cost: {len(ms)} calls, mean {ms.mean():.3f} ms, p95 {np.percentile(ms, 95):.3f}, max {ms.max():.3f}; "
              f"{100 * ms.sum() / 1e3 / cpu:.2f} % of the replay's CPU ({cpu / max(len(res.states), 1) * 1e3:.1f} ms "
              "a frame)")


def truth(traj: str, raw: str, align_s: float) -> None:
    rows = np.array([[float(x) for x in line.split()[:4]] for line in open(traj) if line.strip()
                     and not line.startswith("#")])
    tr = np.load(raw)["truth"]
    t_gt = tr[:, 0] * 1e-9
    p_gt = np.column_stack([tr[:, 1], -tr[:, 2], -tr[:, 3]])  # NED -> z up (the yaw is aligned anyway)
    t, p = rows[:, 0], rows[:, 1:4]
    ok = (t >= t_gt[0]) & (t <= t_gt[-1])
    t, p = t[ok], p[ok]
    g = np.column_stack([np.interp(t, t_gt, p_gt[:, k]) for k in range(3)])
    el = t - t[0]
    for name, sel in ((f"aligned on the first {align_s:g} s", el < align_s), ("aligned on the whole flight", el >= 0)):
        T = align_4dof(p[sel], g[sel])
        e = np.linalg.norm(p @ T[:3, :3].T + T[:3, 3] - g, axis=1)
        print(f"{traj}: {name}")
        for lo, hi in WINDOWS_S:
            m = (el >= lo) & (el < hi)
            if m.any():
                span = "all" if hi > 1e8 else f"{lo}-{hi} s"
                print(f"  {span:>10}: rmse {np.sqrt(np.mean(e[m] ** 2)):8.3f} m  max {e[m].max():8.3f} m")
    print(f"  estimate at most {np.linalg.norm(p - p[0], axis=1).max():.1f} m from its start "
          f"(truth {np.linalg.norm(g - g[0], axis=1).max():.2f} m)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("readings")
    r.add_argument("dataset")
    r.add_argument("--config")
    t = sub.add_parser("truth")
    t.add_argument("traj")
    t.add_argument("raw")
    t.add_argument("--align-s", type=float, default=15.0)
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if a.cmd == "readings":
        readings(a.dataset, a.config)
    else:
        truth(a.traj, a.raw, a.align_s)


if __name__ == "__main__":
    main()
