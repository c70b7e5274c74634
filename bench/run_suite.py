#!/usr/bin/env python3
"""Kestrel VIO benchmark suite: accuracy, speed per stage, frame-to-MAVLink latency, memory, profile.

    python bench/run_suite.py [--quick] [--out bench/results] [--report docs/benchmarks.md]
                              [--work /tmp/kestrel-bench] [--compare REV]

Every measurement runs in a subprocess (`vio replay` through bench/child.py, `vio run` through
bench/live.py) so that CPU affinity and thread limits hold from the first import: "one core" means the
process is pinned to CPU 0 (like `taskset -c 0`), OMP/OPENBLAS/MKL/NUMEXPR threads = 1 and
cv2.setNumThreads(1); "all cores" leaves both alone. Simulated flights are cached under --work by their
parameters. Results go to <out>/suite.json (+ PNG plots) and the Markdown report to --report.
`--compare REV` also runs the accuracy and speed part on REV (a git worktree under --work, imported through
PYTHONPATH) and prints/records the ratios this/REV.
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import math
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from bench.child import summary_ms  # noqa: E402
from bench.flights import FlightSpec, ensure_flight  # noqa: E402
from vio import VioError  # noqa: E402
from vio.evaluation import _json_safe  # noqa: E402

log = logging.getLogger("bench.run_suite")

EUROC_EXCERPT = Path(os.environ.get("KESTREL_SHARED_DATA", REPO.parent / "shared" / "data")) / "euroc" / \
    "V1_01_easy_excerpt"
ONE_CORE = {0}
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
               "VECLIB_MAXIMUM_THREADS", "TBB_NUM_THREADS")
STAGES = ("frontend_ms", "backend_ms", "total_ms")

# Targets: (id, headline key, label, comparison, limit); the first six from the "Benchmarks" issue, the
# last two are issue 17's tighter speed targets (with every new state on, PNG decoding included)
TARGETS = (
    ("rtf_one_core", "rtf_one_core", "real-time factor, one core", ">=", 3.0),
    ("p99_frame_ms", "p99_frame_ms", "p99 frame time, one core [ms]", "<=", 35.0),
    ("latency_p50_ms", "latency_p50_ms", "sensor stamp -> MAVLink arrival, median [ms]", "<=", 15.0),
    ("memory_growth_mb", "memory_growth_mb", "memory growth over the long flight [MB]", "<=", 5.0),
    ("synthetic_ate_m", "synthetic_ate_m", "synthetic ATE SE(3) RMSE, mean of flights [m]", "<=", 0.10),
    ("synthetic_rpe_pct", "synthetic_rpe_pct", "synthetic RPE, mean of flights [%]", "<=", 1.0),
    ("rtf_one_core_issue17", "rtf_one_core", "real-time factor, one core (issue 17)", ">=", 5.0),
    ("p99_frame_ms_issue17", "p99_frame_ms", "p99 frame time, one core [ms] (issue 17)", "<=", 20.0),
)


@dataclass(frozen=True)
class Plan:
    """What one suite run measures. `speed_flight` must be one of `flights`."""

    name: str
    flights: tuple[FlightSpec, ...]  # accuracy set, each replayed on one core
    speed_flight: FlightSpec  # also replayed on all cores and under cProfile
    live_flight: FlightSpec  # `vio run` in real time: latency and memory
    euroc: bool = True


def _grid(duration: float, seeds: tuple[int, ...], size: str = "752x480") -> tuple[FlightSpec, ...]:
    return tuple(FlightSpec(p, duration, s, v, size) for p in ("survey", "aggressive")
                 for v in ("clean", "realistic") for s in seeds)


PLANS = {
    "full": Plan("full", _grid(30.0, (1, 2)), FlightSpec("survey", 30.0, 1, "realistic"),
                 FlightSpec("survey", 600.0, 1, "realistic", "376x240")),
    "quick": Plan("quick", _grid(15.0, (1,)), FlightSpec("survey", 15.0, 1, "realistic"),
                  FlightSpec("survey", 60.0, 1, "realistic", "376x240")),
    # for tests/test_bench.py: the whole pipeline of the suite on one tiny flight
    "smoke": Plan("smoke", (FlightSpec("survey", 6.0, 1, "clean", "376x240"),),
                  FlightSpec("survey", 6.0, 1, "clean", "376x240"), FlightSpec("survey", 6.0, 1, "clean", "376x240"),
                  euroc=False),
}


@dataclass
class RunResult:
    """One replay: timings, accuracy and where its files are. `ev` (the EvalResult) is kept for plots only."""

    name: str
    dataset: str
    cpus: str
    ok: bool
    error: str = ""
    frames: int = 0
    data_s: float = 0.0
    wall_s: float = 0.0
    cpu_s: float = 0.0
    resets: int = 0
    vio_module: str = ""  # the vio package the replay imported (this tree, or the --compare worktree)
    timing_ms: dict = field(default_factory=dict)
    output_ms: dict = field(default_factory=dict)
    accuracy: dict = field(default_factory=dict)
    per_frame_total_ms: list = field(default_factory=list, repr=False)
    per_frame_ms: dict = field(default_factory=dict, repr=False)
    ev: object = field(default=None, repr=False)

    @property
    def rtf(self) -> float:
        return self.data_s / self.wall_s if self.wall_s > 0 else math.nan

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("ev", "per_frame_total_ms", "per_frame_ms"):
            d.pop(k)
        d["rtf"] = self.rtf
        d["rtf_cpu"] = self.data_s / self.cpu_s if self.cpu_s > 0 else math.nan
        return d


# ------------------------------------------------------------------------------------------------ running

def thread_env(one_core: bool, src_root: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src_root), PYTHONUNBUFFERED="1")
    for var in THREAD_VARS:
        if one_core:
            env[var] = "1"
        else:
            env.pop(var, None)
    return env


def run_replay(name: str, dataset: Path, run_dir: Path, src_root: Path, one_core: bool,
               profile: Path | None = None, crop_gt: bool = False) -> RunResult:
    """`vio replay` of `dataset` in a subprocess; per-stage timings, CPU time and accuracy against its GT."""
    from vio.evaluation import evaluate, load_trajectory
    from vio.trajectory import read_tum

    run_dir.mkdir(parents=True, exist_ok=True)
    tum, stats_path, out_json = run_dir / "traj.tum", run_dir / "stats.json", run_dir / "output.json"
    cmd = [sys.executable, str(REPO / "bench" / "child.py"), "--output-json", str(out_json)]
    if one_core:
        cmd += ["--cv-threads", "1"]
    if profile is not None:
        cmd += ["--profile", str(profile)]
    cmd += ["--", str(dataset), "--output", str(tum), "--stats", str(stats_path), "--no-progress"]
    res = RunResult(name, str(dataset), "0" if one_core else "all", ok=False)
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    with open(run_dir / "replay.log", "w") as logf:
        rc = subprocess.run(cmd, env=thread_env(one_core, src_root), cwd=run_dir, stdout=logf,
                            stderr=subprocess.STDOUT,
                            preexec_fn=(lambda: os.sched_setaffinity(0, ONE_CORE)) if one_core else None).returncode
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    res.cpu_s = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    if rc != 0 or not stats_path.is_file():
        res.error = f"replay exit {rc}: {(run_dir / 'replay.log').read_text()[-400:].strip()}"
        log.warning("%s: %s", name, res.error)
        return res
    st = json.loads(stats_path.read_text())
    res.frames, res.data_s, res.wall_s, res.resets = st["frames"], st["data_s"], st["wall_s"], st["resets"]
    per_frame = st.get("per_frame", [])
    res.per_frame_ms = {k: [f[k] for f in per_frame] for k in STAGES}
    res.timing_ms = {k: summary_ms(v) for k, v in res.per_frame_ms.items()}
    if out_json.is_file():
        oj = json.loads(out_json.read_text())
        res.output_ms, res.vio_module = oj.get("output_ms", {}), oj.get("vio_module", "")
    try:
        ev = evaluate(read_tum(tum), load_trajectory(dataset), crop_gt=crop_gt)
    except VioError as e:
        res.error = f"no accuracy: {e}"
        log.warning("%s: %s", name, res.error)
        return res
    res.ev, res.ok = ev, True
    res.accuracy = {"ate_se3_m": ev.ate_se3.trans_m.rmse, "ate_4dof_m": ev.ate_4dof.trans_m.rmse,
                    "rpe_pct": ev.rpe_trans_pct, "rpe_deg_per_m": ev.rpe_rot_deg_per_m, "coverage": ev.coverage,
                    "path_m": ev.path_length_m, "rpe_lengths_m": [r.length_m for r in ev.rpe]}
    log.info("%s: %d frames, RTF %.2f (cpu %.2f), ATE %.3f m, RPE %.2f %%", name, res.frames, res.rtf,
             res.data_s / max(res.cpu_s, 1e-9), ev.ate_se3.trans_m.rmse, ev.rpe_trans_pct)
    return res


def run_accuracy_and_speed(plan: Plan, work: Path, run_root: Path, src_root: Path) -> dict[str, RunResult]:
    """All one-core replays of the plan's flights (+ the EuRoC excerpt), keyed by flight key."""
    runs: dict[str, RunResult] = {}
    for spec in plan.flights:
        ds = ensure_flight(spec, work / "flights")
        runs[spec.key] = run_replay(spec.key, ds, run_root / spec.key, src_root, one_core=True)
    if plan.euroc:
        if (EUROC_EXCERPT / "mav0").is_dir():
            runs["euroc-V1_01_easy_excerpt"] = run_replay("euroc-V1_01_easy_excerpt", EUROC_EXCERPT,
                                                          run_root / "euroc", src_root, one_core=True, crop_gt=True)
        else:
            log.warning("EuRoC excerpt not found at %s: skipped", EUROC_EXCERPT)
    return runs


def pooled_speed(runs: list[RunResult]) -> dict:
    """Per-stage timings over all frames of `runs`, and the real-time factor of their summed data and time."""
    ok = [r for r in runs if r.timing_ms]
    if not ok:
        return {}
    data = sum(r.data_s for r in ok)
    return {"runs": len(ok), "frames": sum(r.frames for r in ok),
            "stages_ms": {k: summary_ms(np.concatenate([r.per_frame_ms[k] for r in ok])) for k in STAGES},
            "rtf": data / sum(r.wall_s for r in ok), "rtf_cpu": data / max(sum(r.cpu_s for r in ok), 1e-9)}


def profile_table(pstats_path: Path, top: int = 15) -> dict[str, list[dict]]:
    """Top functions of a cProfile dump by cumulative and by own time, with short file names."""
    import pstats

    st = pstats.Stats(str(pstats_path))
    rows = []
    for (file, line, func), (_cc, nc, tt, ct, _callers) in st.stats.items():
        if file.startswith("<frozen") or func == "_call_with_frames_removed":
            continue  # the import machinery (start-up) would crowd out the pipeline
        short = file
        for marker in ("site-packages/", str(REPO) + "/"):
            if marker in file:
                short = file.split(marker, 1)[1]
        rows.append({"function": f"{short}:{line}({func})" if line else func, "ncalls": nc, "tottime_s": tt,
                     "cumtime_s": ct})
    return {"cumulative": sorted(rows, key=lambda r: -r["cumtime_s"])[:top],
            "own": sorted(rows, key=lambda r: -r["tottime_s"])[:top], "total_s": st.total_tt}


def wait_for_low_load(limit: float, max_wait_s: float) -> None:
    """Timings are only comparable on an otherwise idle machine: wait for it, but not forever."""
    t0 = time.monotonic()
    while os.getloadavg()[0] >= limit and time.monotonic() - t0 < max_wait_s:
        log.info("load average %.2f >= %.2f: waiting", os.getloadavg()[0], limit)
        time.sleep(30)
    if os.getloadavg()[0] >= limit:
        log.warning("load average still %.2f after %.0f min: measuring anyway", os.getloadavg()[0], max_wait_s / 60)


def machine_info() -> dict:
    from importlib.metadata import version

    import cv2

    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), platform.processor() or "unknown")
    mem_kb = next((int(ln.split()[1]) for ln in Path("/proc/meminfo").read_text().splitlines()
                   if ln.startswith("MemTotal:")), 0)

    def git(*a: str) -> str:
        return subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True).stdout.strip()

    return {"date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "cpu": cpu, "cores": os.cpu_count(), "ram_gb": round(mem_kb / 2**20, 1),
            "python": platform.python_version(), "numpy": np.__version__, "opencv": cv2.__version__,
            "gtsam": version("gtsam"), "git_rev": git("rev-parse", "--short", "HEAD"),
            "git_dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
            "load_avg_start": os.getloadavg()}


# ------------------------------------------------------------------------------------------------ plots

def plot_rss(live: dict, path: Path) -> None:
    from vio.extras import pyplot

    plt = pyplot("the benchmark plots")

    tr, mem = live["rss_trace"], live["memory"]
    fig, ax = plt.subplots(figsize=(7, 3))
    ax.plot(tr["t_s"], tr["rss_mb"], lw=0.8)
    for key, colour in (("early", "tab:green"), ("late", "tab:red")):
        a, b = mem[f"{key}_window_s"]
        ax.axvspan(a, b, color=colour, alpha=0.15, label=f"{key} plateau {mem[f'{key}_mb']:.1f} MB")
    ax.set_xlabel("time since start [s]")
    ax.set_ylabel("RSS [MB]")
    ax.set_title(f"vio run RSS: growth {mem['growth_mb']:+.2f} MB, peak {mem['peak_rss_mb']:.0f} MB")
    ax.legend(loc="lower right")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------ compare

def worktree_for(rev: str, work: Path) -> Path:
    """A detached git worktree of `rev` under `work` (removed again after the comparison)."""
    p = subprocess.run(["git", "rev-parse", "--verify", f"{rev}^{{commit}}"], cwd=REPO, capture_output=True,
                       text=True)
    if p.returncode != 0:
        raise VioError(f"--compare {rev}: not a git revision of {REPO}")
    sha = p.stdout.strip()
    wt = work / "worktrees" / sha[:12]
    if not (wt / "vio").is_dir():
        shutil.rmtree(wt, ignore_errors=True)
        subprocess.run(["git", "worktree", "prune"], cwd=REPO, check=False)
        p = subprocess.run(["git", "worktree", "add", "--detach", str(wt), sha], cwd=REPO, capture_output=True,
                           text=True)
        if p.returncode != 0:
            raise VioError(f"--compare {rev}: git worktree add failed: {p.stderr.strip()}")
    return wt


def ratios(this: dict[str, RunResult], other: dict[str, RunResult]) -> dict:
    """this/other per flight (ATE, RPE) and for pooled speed; > 1 means this revision is worse/slower,
    except the real-time factors, where > 1 means faster."""

    def r(a: float, b: float) -> float:
        return a / b if b and math.isfinite(a) and math.isfinite(b) else math.nan

    flights = {}
    for key, a in this.items():
        b = other.get(key)
        if a.ok and b is not None and b.ok:
            flights[key] = {m: r(a.accuracy[m], b.accuracy[m]) for m in ("ate_se3_m", "ate_4dof_m", "rpe_pct")}
    sa, sb = pooled_speed(list(this.values())), pooled_speed(list(other.values()))
    speed = {}
    if sa and sb:
        speed = {f"{k}_{q}": r(sa["stages_ms"][k][q], sb["stages_ms"][k][q]) for k in STAGES for q in ("mean", "p99")}
        speed["rtf"], speed["rtf_cpu"] = r(sa["rtf"], sb["rtf"]), r(sa["rtf_cpu"], sb["rtf_cpu"])
    return {"flights": flights, "speed": speed}


# ------------------------------------------------------------------------------------------------ main

def headline(runs: dict[str, RunResult], speed: dict, live: dict | None) -> dict:
    synth = [r for k, r in runs.items() if not k.startswith("euroc") and r.ok]
    out = {
        "rtf_one_core": speed.get("rtf", math.nan),
        "rtf_one_core_cpu": speed.get("rtf_cpu", math.nan),
        "p99_frame_ms": speed.get("stages_ms", {}).get("total_ms", {}).get("p99", math.nan),
        "latency_p50_ms": live["latency_ms"]["p50"] if live else math.nan,
        "memory_growth_mb": live["memory"]["growth_mb"] if live else math.nan,
        "frame_to_output_p50_ms": ((live or {}).get("daemon_status") or {}).get("latency_ms", {}).get("p50"),
        "synthetic_ate_m": float(np.mean([r.accuracy["ate_se3_m"] for r in synth])) if synth else math.nan,
        "synthetic_rpe_pct": float(np.nanmean([r.accuracy["rpe_pct"] for r in synth])) if synth else math.nan,
    }
    out["failed_runs"] = [k for k, r in runs.items() if not r.ok]
    return out


def verdicts(head: dict) -> dict[str, str]:
    out = {}
    for tid, key, _label, op, limit in TARGETS:
        v = head.get(key, math.nan)
        if v is None or not math.isfinite(v):
            out[tid] = "n/a"
        else:
            out[tid] = "PASS" if (v >= limit if op == ">=" else v <= limit) else "MISS"
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="shorter flights, one seed, 60 s memory flight")
    ap.add_argument("--plan", choices=sorted(PLANS), help=argparse.SUPPRESS)
    ap.add_argument("--out", default=str(REPO / "bench" / "results"), help="JSON and plots (default bench/results)")
    ap.add_argument("--report", default=str(REPO / "docs" / "benchmarks.md"), help="Markdown report to write")
    ap.add_argument("--work", default="/tmp/kestrel-bench", help="flight cache, run outputs, worktrees")
    ap.add_argument("--compare", metavar="REV", help="also run accuracy and speed on git revision REV")
    ap.add_argument("--wait-load", type=float, metavar="L",
                    help="first wait (up to --wait-max minutes) until the 1-min load average is below L")
    ap.add_argument("--wait-max", type=float, default=30.0, metavar="MIN", help="longest wait for --wait-load")
    ap.add_argument("--skip", nargs="*", default=[], choices=("live", "profile", "allcores"),
                    help="leave parts out (e.g. while iterating)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)-7s %(name)s: %(message)s")
    plan = PLANS[args.plan or ("quick" if args.quick else "full")]
    if args.wait_load:
        wait_for_low_load(args.wait_load, args.wait_max * 60)
    try:
        return _run(plan, args)
    except VioError as e:
        print(f"bench/run_suite.py: error: {e}", file=sys.stderr)
        return 1


def _run(plan: Plan, args: argparse.Namespace) -> int:
    from bench.live import run_live
    from bench.report import write_report
    from vio.evaluation import plot

    work, out = Path(args.work), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%dT%H%M%S")
    run_root = work / "runs" / stamp
    info = machine_info()
    info["command"] = ("python bench/run_suite.py " + " ".join(
        a for a in (("--quick" if args.quick else ""), (f"--plan {args.plan}" if args.plan else ""),
                    (f"--compare {args.compare}" if args.compare else "")) if a)).strip()
    info["plan"] = plan.name
    if info["load_avg_start"][0] > 1.5:
        log.warning("load average %.2f: other work shares the CPUs, timings will be noisy", info["load_avg_start"][0])
    t_start = time.perf_counter()

    runs = run_accuracy_and_speed(plan, work, run_root, REPO)
    speed = {"one_core_pooled": pooled_speed([r for k, r in runs.items() if not k.startswith("euroc")])}
    speed_ds = ensure_flight(plan.speed_flight, work / "flights")
    speed["one_core"] = runs[plan.speed_flight.key].to_dict()
    repeats = [runs[plan.speed_flight.key]]  # the same flight replayed again: how repeatable accuracy is
    if "allcores" not in args.skip:
        repeats.append(run_replay(plan.speed_flight.key, speed_ds, run_root / "allcores", REPO, one_core=False))
        speed["all_cores"] = repeats[-1].to_dict()
    prof = None
    if "profile" not in args.skip:
        pfile = run_root / "profile" / "replay.pstats"
        pfile.parent.mkdir(parents=True, exist_ok=True)
        repeats.append(run_replay(plan.speed_flight.key, speed_ds, run_root / "profile", REPO, one_core=True,
                                  profile=pfile))
        if pfile.is_file():
            prof = profile_table(pfile)
    speed["repeat_ate_se3_m"] = [r.accuracy.get("ate_se3_m") for r in repeats if r.ok]
    live = None
    if "live" not in args.skip:
        live_ds = ensure_flight(plan.live_flight, work / "flights")
        live = run_live(live_ds, plan.live_flight.duration_s, run_root / "live", thread_env(True, REPO), ONE_CORE)
        live["flight"] = plan.live_flight.key
        plot_rss(live, out / "memory_rss.png")
        tr = live["rss_trace"]
        step = max(1, len(tr["t_s"]) // 300)
        live["rss_trace"] = {k: v[::step] for k, v in tr.items()}

    plots = {}
    first_seed = min(s.seed for s in plan.flights)
    for key, r in runs.items():
        if r.ok and (key.startswith("euroc") or f"-seed{first_seed}-" in key):
            plots[key] = f"traj_{key}.png"
            plot(r.ev, out / plots[key], title=f"{key}: ATE SE(3) {r.accuracy['ate_se3_m']:.3f} m")

    compare = None
    if args.compare:
        wt = worktree_for(args.compare, work)
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=wt, capture_output=True,
                             text=True).stdout.strip()
        try:
            other = run_accuracy_and_speed(plan, work, run_root / f"compare-{rev}", wt)
        finally:  # leave the shared repository's worktree list as it was
            subprocess.run(["git", "worktree", "remove", "--force", str(wt)], cwd=REPO, capture_output=True)
        compare = {"rev": args.compare, "sha": rev, "ratios": ratios(runs, other),
                   "runs": {k: r.to_dict() for k, r in other.items()}}
        _print_ratios(compare)

    notes = []
    if plan.euroc and not any(k.startswith("euroc") for k in runs):
        notes.append(f"The real EuRoC excerpt was not found at {EUROC_EXCERPT}: skipped.")
    head = headline(runs, speed["one_core_pooled"], live)
    info["load_avg_end"] = os.getloadavg()
    info["suite_wall_s"] = time.perf_counter() - t_start
    result = {"info": info, "plan": asdict(plan), "headline": head, "verdicts": verdicts(head),
              "runs": {k: r.to_dict() for k, r in runs.items()}, "speed": speed, "live": live, "profile": prof,
              "plots": plots, "compare": compare, "notes": notes}
    result = _json_safe(result)
    (out / "suite.json").write_text(json.dumps(result, indent=1) + "\n")
    write_report(result, Path(args.report), out)
    for tid, key, label, op, limit in TARGETS:
        v = head[key]
        print(f"{label:<50} {v if v is None else round(v, 3)!s:>10}  target {op} {limit:g}: "
              f"{result['verdicts'][tid]}")
    print(f"wrote {out / 'suite.json'} and {args.report} in {info['suite_wall_s']:.0f} s")
    return 0


def _print_ratios(compare: dict) -> None:
    print(f"this / {compare['rev']} ({compare['sha']}): ATE/RPE/time > 1 = worse; rtf > 1 = faster")
    for key, v in compare["ratios"]["flights"].items():
        print(f"  {key:<44} " + "  ".join(f"{m} {x:.2f}" for m, x in v.items()))
    for k, x in compare["ratios"]["speed"].items():
        print(f"  speed {k:<30} {x:.2f}")


if __name__ == "__main__":
    sys.exit(main())
