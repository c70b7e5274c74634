"""Top view of a loop-closure run: odometry, loop-corrected trajectory, ground truth, and the loop edges
(active ones green, switched-off ones red), so that a wrong closure can be seen where it would fold the map."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vio.evaluation import save_figure


def plot_loop(path: str | Path, T_odom: np.ndarray, T_loop: np.ndarray, kf_T: list[np.ndarray],
              edges: list[tuple[int, int, float]], T_gt: np.ndarray | None = None, title: str = "") -> None:
    """`kf_T`: the graph's keyframe poses (loop-corrected); `edges`: (i, j, weight) loop edges between them;
    `T_gt`: ground truth at the same stamps as T_odom, already in the estimate's frame (or None)."""
    from vio.extras import pyplot

    plt = pyplot("loop-closure plot (--loop-plot)")
    fig, ax = plt.subplots(figsize=(8, 8))
    if T_gt is not None:
        ax.plot(T_gt[:, 0, 3], T_gt[:, 1, 3], "k-", lw=1.2, label="ground truth")
    ax.plot(T_odom[:, 0, 3], T_odom[:, 1, 3], "-", color="tab:orange", lw=0.9, label="odometry")
    ax.plot(T_loop[:, 0, 3], T_loop[:, 1, 3], "-", color="tab:blue", lw=0.9, label="loop-corrected")
    for label, color, active in (("loop edge", "tab:green", True), ("switched off", "tab:red", False)):
        segs = [(kf_T[i][:3, 3], kf_T[j][:3, 3]) for i, j, w in edges if (w >= 0.5) == active]
        for k, (a, b) in enumerate(segs):
            ax.plot([a[0], b[0]], [a[1], b[1]], "-", color=color, lw=0.8, alpha=0.8,
                    label=f"{label} ({len(segs)})" if k == 0 else None)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    ax.set_title(title)
    save_figure(plt, fig, path)
