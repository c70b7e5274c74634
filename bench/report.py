"""Markdown report of a benchmark suite run (the `suite.json` written by bench/run_suite.py)."""

from __future__ import annotations

import os
from pathlib import Path

from vio import VioError


def _f(x: float | None, nd: int = 2) -> str:
    return "-" if x is None else f"{x:.{nd}f}"


def _mpm(d: dict | None) -> str:
    """mean / p50 / p99 of a timing summary."""
    if not d:
        return "-"
    return f"{d['mean']:.1f} / {d['p50']:.1f} / {d['p99']:.1f}"


def _speed_row(label: str, r: dict) -> str:
    t = r.get("timing_ms") or r.get("stages_ms") or {}
    return (f"| {label} | {r.get('frames', '-')} | {_mpm(t.get('frontend_ms'))} | {_mpm(t.get('backend_ms'))} | "
            f"{_mpm(r.get('output_ms'))} | {_mpm(t.get('total_ms'))} | {_f(r.get('rtf'))} | {_f(r.get('rtf_cpu'))} |")


def _imread_share(prof: dict | None) -> str:
    row = next((r for r in (prof or {}).get("own", []) if r["function"] == "<imread>"), None)
    return f", {100 * row['tottime_s'] / prof['total_s']:.0f} % of the profiled replay" if row else ""


def render(res: dict, out_rel: str) -> str:
    """The report text; `out_rel` is the results folder relative to the report (for image links)."""
    from bench.run_suite import TARGETS

    info, head, verdict = res["info"], res["headline"], res["verdicts"]
    L = ["# Benchmarks", "",
         f"Measured with `{info['command']}` (plan `{info['plan']}`) on {info['date_utc']}, revision "
         f"`{info['git_rev']}`{' with uncommitted changes' if info['git_dirty'] else ''}; the suite took "
         f"{info['suite_wall_s'] / 60:.1f} min. Raw numbers: [`suite.json`]({out_rel}/suite.json). "
         "How each figure is measured is described at the end.", "",
         "| machine | |", "| --- | --- |",
         f"| CPU | {info['cpu']}, {info['cores']} cores |", f"| RAM | {info['ram_gb']} GB |",
         f"| software | Python {info['python']}, numpy {info['numpy']}, OpenCV {info['opencv']}, "
         f"gtsam {info['gtsam']} |",
         f"| load average (1/5/15 min) | start {' / '.join(f'{x:.2f}' for x in info['load_avg_start'])}, "
         f"end {' / '.join(f'{x:.2f}' for x in info['load_avg_end'])} |", ""]
    if info["load_avg_start"][0] > 1.5:
        L += [f"**Note:** the machine was shared (load {info['load_avg_start'][0]:.1f} at the start): wall-clock "
              "timings include waiting for the CPU. The CPU-time real-time factor is less affected.", ""]
    L += ["## Targets", "", "| target | measured | limit | result |", "| --- | --- | --- | --- |"]
    for tid, key, label, op, limit in TARGETS:
        extra = f" (CPU time: {_f(head.get('rtf_one_core_cpu'))})" if key == "rtf_one_core" else ""
        L.append(f"| {label} | {_f(head.get(key), 3)}{extra} | {op} {limit:g} | {verdict.get(tid, 'n/a')} |")
    if head.get("frame_to_output_p50_ms") is not None:
        L += ["", "Latency is measured on the poses as sent: between camera frames the daemon sends IMU-propagated "
              "states, so a message's `time_usec` is usually a recent IMU sample. The visual update itself (camera "
              "frame arrival until its state reaches the MAVLink output, the daemon's own measure) takes "
              f"{_f(head['frame_to_output_p50_ms'], 1)} ms at the median."]
    if head.get("failed_runs"):
        L += ["", f"Runs without a result: {', '.join(head['failed_runs'])} (see the tables)."]
    L += ["", "## Accuracy", "",
          "One `vio replay` per flight, on one core. ATE: RMSE of positions after SE(3) / 4-DoF alignment; RPE: "
          "mean translation drift in % of distance over the segment lengths the path allows "
          "(docs/evaluation.md).", "",
          "| flight | frames | ATE SE(3) [m] | ATE 4-DoF [m] | RPE [%] | RPE [deg/m] | coverage | resets | RTF "
          "| plot |",
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for key, r in res["runs"].items():
        plot = res["plots"].get(key)
        link = f"[png]({out_rel}/{plot})" if plot else ""
        if not r["ok"]:
            L.append(f"| {key} | {r['frames']} | failed: {r['error'][:120]} | | | | | | | |")
            continue
        a = r["accuracy"]
        L.append(f"| {key} | {r['frames']} | {_f(a['ate_se3_m'], 3)} | {_f(a['ate_4dof_m'], 3)} | "
                 f"{_f(a['rpe_pct'])} | {_f(a['rpe_deg_per_m'], 3)} | {100 * (a['coverage'] or 0):.0f} % | "
                 f"{r['resets']} | {_f(r['rtf'])} | {link} |")
    for note in res.get("notes", []):
        L += ["", note]
    sp = res["speed"]
    if len(sp.get("repeat_ate_se3_m") or []) > 1:
        L += ["", f"Repeatability: `{sp['one_core']['name']}` replayed {len(sp['repeat_ate_se3_m'])} times (one "
              "core, all cores, under cProfile) gave ATE SE(3) "
              f"{', '.join(_f(x, 4) for x in sp['repeat_ate_se3_m'])} m."]
    L += ["", "## Speed", "",
          "Per-frame times in ms as mean / p50 / p99. Front end and back end come from the replay's own stats; "
          "total is the whole `feed_frame` call; output is `MavlinkOutput.send_state` (ODOMETRY built, packed "
          "and sent over UDP loopback) per state. RTF = seconds of data per second of wall time; RTF (CPU) "
          "divides by the process's CPU time instead.", "",
          "| run | frames | front end | back end | output | total | RTF | RTF (CPU) |",
          "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    if sp.get("one_core_pooled"):
        L.append(_speed_row(f"one core, all {sp['one_core_pooled']['runs']} synthetic flights",
                            sp["one_core_pooled"]))
    L.append(_speed_row(f"one core, {sp['one_core']['name']}", sp["one_core"]))
    if sp.get("all_cores"):
        L.append(_speed_row(f"all cores, {sp['all_cores']['name']}", sp["all_cores"]))
    live = res.get("live")
    if live:
        lat, mem, ds = live["latency_ms"], live["memory"], live.get("daemon_status") or {}
        inner = ds.get("latency_ms") or {}
        L += ["", "## Latency (frame -> MAVLink)", "",
              f"`vio run` plays `{live['flight']}` in real time on one core and sends ODOMETRY (rate_hz default) "
              "to a loopback autopilot stub in the suite process, which compares each message's `time_usec` "
              "with its arrival time on the same CLOCK_MONOTONIC.", "",
              "| messages | rate [Hz] | median [ms] | p95 [ms] | p99 [ms] | max [ms] "
              "| daemon's own frame->state p50 / max [ms] | frames dropped | estimator resets |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
              f"| {lat['n']} | {_f(live['odometry_rate_hz'], 1)} | {_f(lat['p50'], 1)} | {_f(lat['p95'], 1)} | "
              f"{_f(lat['p99'], 1)} | {_f(lat['max'], 1)} | {_f(inner.get('p50'), 1)} / {_f(inner.get('max'), 1)} "
              f"| {(ds.get('source') or {}).get('frames_dropped', '-')} "
              f"| {(ds.get('estimator') or {}).get('daemon_resets', '-')} |",
              "", "The daemon's own figure is over its last 200 frames; resets and their reasons are in "
              "`daemon.log` of the run folder.",
              "", "## Memory", "",
              f"RSS of the same `vio run` process, sampled every 0.5 s over `{live['flight']}`. Growth = median of "
              "the last 10 % of the time from the first pose to the end of the data minus the median of 10-20 % "
              "into it.", "",
              "| peak RSS [MB] | early plateau [MB] | late plateau [MB] | growth [MB] "
              "| trend of the second half [MB / 10 min] | plot |",
              "| --- | --- | --- | --- | --- | --- |",
              f"| {_f(mem['peak_rss_mb'], 1)} | {_f(mem['early_mb'], 1)} | {_f(mem['late_mb'], 1)} | "
              f"{mem['growth_mb']:+.2f} | {_f(mem.get('second_half_mb_per_10min'))} "
              f"| [png]({out_rel}/memory_rss.png) |",
              "", "The trend is the slope of a straight line fitted to the second half of the trace: a one-time step "
              "(a pool or cache filling up) raises the growth figure but leaves the trend near zero, a leak does "
              "not."]
    prof = res.get("profile")
    if prof:
        L += ["", "## Profile", "",
              f"cProfile of one `vio replay` of `{sp['one_core']['name']}` on one core "
              f"({prof['total_s']:.1f} s profiled; profiling slows Python code down, so these are shares, "
              "not speeds).", ""]
        for kind, col in (("cumulative", "cumtime_s"), ("own", "tottime_s")):
            L += [f"Top {len(prof[kind])} by {kind} time:", "", "```",
                  f"{'seconds':>8} {'calls':>9}  function"]
            L += [f"{r[col]:8.2f} {r['ncalls']:9d}  {r['function']}" for r in prof[kind]]
            L += ["```", ""]
    cmp_ = res.get("compare")
    if cmp_:
        L += ["", f"## Comparison with `{cmp_['rev']}` ({cmp_['sha']})", "",
              "Ratios this / that revision on the same cached flights: > 1 is worse (ATE, RPE, times) or faster "
              "(RTF).", "", "| flight | ATE SE(3) | ATE 4-DoF | RPE |", "| --- | --- | --- | --- |"]
        for key, v in cmp_["ratios"]["flights"].items():
            L.append(f"| {key} | {_f(v['ate_se3_m'])} | {_f(v['ate_4dof_m'])} | {_f(v['rpe_pct'])} |")
        L += ["", "| speed | ratio |", "| --- | --- |"]
        L += [f"| {k} | {_f(x)} |" for k, x in cmp_["ratios"]["speed"].items()]
    L += ["", "## How it is measured", "",
          "Reproduce with `python bench/run_suite.py` (the first run generates the flights, about 2 GB under "
          "`/tmp/kestrel-bench`; `--wait-load 1.5` waits for an idle machine first), `--quick` for a shorter "
          "set, and `--compare REV` to add this/REV ratios for accuracy and speed.", "",
          "- Flights: `vio simulate` (profiles survey and aggressive, variants clean and realistic, seeds as "
          "listed), cached under `/tmp/kestrel-bench/flights` by their parameters; the EuRoC excerpt "
          "(V1_01_easy, 95 frames, nearly still) is evaluated against the part of the ground truth it spans.",
          "- One core: the replay process is pinned to CPU 0 (as `taskset -c 0`), OMP/OPENBLAS/MKL/NUMEXPR "
          "threads = 1 and `cv2.setNumThreads(1)`. All cores: no pinning, library defaults.",
          "- The replay's RTF includes reading the PNG images (`imread`" + _imread_share(prof) + "), which a live "
          "camera does not need. The left image is decoded before the frame reaches the estimator (outside the "
          "stage times); a right image is decoded only when the front end's stereo step asks for it (keyframes, "
          "about one frame in four), inside the front-end time.",
          "- The long memory flight uses 376x240 images to keep its generation time reasonable; memory growth "
          "comes from state that accumulates per frame or keyframe, which does not depend on the image size.",
          "- Latency includes waiting for the next slot of the MAVLink output schedule (`[mavlink] rate_hz`) and "
          "for the source's 5 ms polling; it is measured from the stamp of the newest sample a message is based "
          "on (frames, and IMU-propagated states in between).", ""]
    return "\n".join(L)


KEPT_MARKER = "<!-- written by hand: bench/report.py keeps everything from this line on -->"


def write_report(res: dict, path: Path, out_dir: Path) -> None:
    """Write the report; an existing report's hand-written part (from KEPT_MARKER on: analyses such as where
    the time goes, with the commands that measured them) is kept at its end."""
    rel = os.path.relpath(Path(out_dir).resolve(), Path(path).resolve().parent)
    try:
        old = path.read_text() if path.is_file() else ""
    except OSError:
        old = ""
    kept = old[old.index(KEPT_MARKER):] if KEPT_MARKER in old else ""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(render(res, rel) + ("\n" + kept if kept else ""))
    except OSError as e:
        raise VioError(f"{path}: cannot write the report ({e.strerror})") from None
