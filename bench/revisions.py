#!/usr/bin/env python3
"""Speed of several git revisions on one dataset, replayed in turn on one core (interleaved rounds).

    python bench/revisions.py DATASET REV [REV ...] [--rounds 2] [--cpu 0] [--config FILE] [--json out.json]

Each revision is exported with `git archive` under --work and replayed by this tree's bench/realtime.py
with PYTHONPATH set to it; the rounds go revision after revision, so that load from other work on a shared
machine spreads over all of them instead of falling on one. Prints per revision the median over rounds of
the real-time factor (wall and CPU time) and of the per-frame p99 (wall, and thread CPU time where the
revision's replay records it). A revision whose replay predates the per-frame CPU time (`total_cpu_ms`) gets
that one measurement added to its exported copy (the same two lines as vio/app/replay.py has now), so that
old and new revisions are measured alike; nothing else of it is changed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def export(rev: str, work: Path) -> tuple[str, Path]:
    """The revision's tree under work/<sha> (reused when there), with the per-frame CPU time recorded."""
    sha = subprocess.run(["git", "rev-parse", "--short", f"{rev}^{{commit}}"], cwd=REPO, capture_output=True,
                         text=True)
    if sha.returncode != 0:
        raise SystemExit(f"bench/revisions.py: {rev}: not a git revision of {REPO}")
    name = sha.stdout.strip()
    out = work / name
    if not (out / "vio").is_dir():
        out.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "archive", name], cwd=REPO, capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(out)], input=archive, check=True)
    replay = out / "vio" / "app" / "replay.py"
    src = replay.read_text()
    if "total_cpu_ms" not in src:
        src = src.replace("            t0 = time.perf_counter()\n",
                          "            t0, c0 = time.perf_counter(), time.thread_time()\n", 1)
        src = src.replace('"total_ms": (time.perf_counter() - t0) * 1e3,',
                          '"total_ms": (time.perf_counter() - t0) * 1e3, '
                          '"total_cpu_ms": (time.thread_time() - c0) * 1e3,', 1)
        if "c0 = " not in src or "total_cpu_ms" not in src:
            print(f"{name}: its replay loop differs; no per-frame CPU time", file=sys.stderr)
        replay.write_text(src)
    return name, out


def run_once(tree: Path, dataset: str, cpu: int, config: str | None) -> dict:
    with tempfile.NamedTemporaryFile(suffix=".json") as f:
        cmd = [sys.executable, str(REPO / "bench" / "realtime.py"), dataset, "--cpu", str(cpu), "--json", f.name]
        if config:
            cmd += ["--config", config]
        env = dict(os.environ, PYTHONPATH=str(tree))
        p = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if p.returncode != 0:
            raise SystemExit(f"bench/revisions.py: replay with {tree} failed: {p.stderr.strip()[-300:]}")
        d = json.loads(Path(f.name).read_text())
    per = d["per_frame"]
    cpu_ms = [x["total_cpu_ms"] for x in per if "total_cpu_ms" in x]
    return {"rtf": d["realtime_factor"], "rtf_cpu": d["realtime_factor_cpu"],
            "p99_ms": float(np.percentile([x["total_ms"] for x in per], 99)),
            "p99_cpu_ms": float(np.percentile(cpu_ms, 99)) if cpu_ms else float("nan"),
            "mean_cpu_ms": float(np.mean(cpu_ms)) if cpu_ms else float("nan"),
            "frames": d["frames"], "keyframes": d["keyframes"], "load": os.getloadavg()[0]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("revs", nargs="+")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--cpu", type=int, default=0, help="the CPU to pin the replays to (default 0)")
    ap.add_argument("--config", help="TOML configuration for every replay")
    ap.add_argument("--work", default="/tmp/kestrel-bench/revisions", help="where the revisions are exported")
    ap.add_argument("--json", help="write every run's figures here")
    args = ap.parse_args(argv)
    trees = [export(r, Path(args.work)) for r in args.revs]
    runs: dict[str, list[dict]] = {name: [] for name, _ in trees}
    for k in range(args.rounds):
        for name, tree in trees:
            r = run_once(tree, args.dataset, args.cpu, args.config)
            runs[name].append(r)
            print(f"round {k + 1} {name}: RTF {r['rtf']:.2f} (CPU {r['rtf_cpu']:.2f}), p99 {r['p99_ms']:.1f} ms "
                  f"(CPU {r['p99_cpu_ms']:.1f} ms), load {r['load']:.1f}", flush=True)
    print(f"{'revision':<10} {'RTF':>6} {'RTF CPU':>8} {'p99 ms':>7} {'p99 CPU ms':>11} {'mean CPU ms':>12}")
    for name, rs in runs.items():
        med = {k: float(np.median([r[k] for r in rs])) for k in ("rtf", "rtf_cpu", "p99_ms", "p99_cpu_ms",
                                                                 "mean_cpu_ms")}
        print(f"{name:<10} {med['rtf']:6.2f} {med['rtf_cpu']:8.2f} {med['p99_ms']:7.1f} {med['p99_cpu_ms']:11.1f} "
              f"{med['mean_cpu_ms']:12.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"dataset": args.dataset, "runs": runs}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
