"""`vio batch FLIGHT... --output DIR [--workers N | --ray ADDRESS] [--compare OTHER_REPORT]`

Replays many recordings (EuRoC folders, bags, MCAP files) in parallel and writes one report to DIR:
`report.md` (a table: ATE, RPE, resets, real-time factor per flight, and a summary), `report.json` (the same
and more, the input of `--compare`), `report.png` (ATE and real-time factor per flight; only with the [tools]
extra) and each flight's trajectory in `traj/`. Local worker processes (concurrent.futures) by default;
`--ray ADDRESS` hands the flights to a Ray cluster as remote tasks (`--ray local` starts a local Ray instance
with --workers CPUs, `--ray auto` joins the cluster this machine belongs to). A flight that fails is a row with
its error.

Every replay runs single-threaded (one BLAS/OpenCV thread per worker), so one flight's result is the same
whichever engine ran it and however many ran beside it.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from pathlib import Path

from vio import VioError
from vio.argtypes import path_arg, positive_int, topic_arg
from vio.io.inputs import read_user_file

log = logging.getLogger(__name__)

# fields of a row that depend on the machine and the load, not on the estimator
TIMING_FIELDS = ("wall_s", "realtime_factor", "worker")
_ROW_FIELDS = ("flight", "path", "ok", "error", "notes", "frames", "poses", "resets", "data_s", "ate_m",
               "ate_rot_deg", "rpe_pct", "rpe_length_m", "coverage") + TIMING_FIELDS


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("flights", nargs="+", type=path_arg, metavar="FLIGHT", help="EuRoC folders, ROS bags or MCAP files")
    p.add_argument("--output", "-o", required=True, type=path_arg, metavar="DIR", help="report folder (created)")
    p.add_argument("--overwrite", action="store_true", help="replace the report already in --output (its "
                   "trajectories go too)")
    p.add_argument("--workers", type=positive_int, default=None, metavar="N",
                   help="local worker processes (default: the number of CPUs)")
    p.add_argument("--ray", metavar="ADDRESS", help="run on a Ray cluster: ray://HOST:10001, auto, or local")
    p.add_argument("--config", type=path_arg, metavar="FILE", help="TOML configuration for every replay")
    p.add_argument("--calib", nargs="+", metavar="FILE", help="calibration for bags (see vio replay --calib)")
    from vio.app.replay import CALIB_FORMATS

    p.add_argument("--calib-format", default=None, choices=CALIB_FORMATS, help="format of --calib (default: project)")
    p.add_argument("--left-topic", type=topic_arg, help="bag topics, as vio replay's (default: [bag] in --config)")
    p.add_argument("--right-topic", type=topic_arg)
    p.add_argument("--imu-topic", type=topic_arg)
    p.add_argument("--compare", type=path_arg, metavar="REPORT", help="another batch's report.json (or its folder): "
                   "what got better or worse")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


# one thread per replay: set in the workers' environment before they start, since OpenBLAS reads it when numpy
# is first imported (2 workers with 2 busy-waiting BLAS threads each ran slower than 1 worker on 2 cores)
THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def replay_flight(path: str, options: dict) -> dict:
    """Replay one flight; a row of the report, with the trajectory's TUM text under "tum" (what was estimated,
    also when the flight failed). Never raises: a failure is the row's `error`. Reads only the flight:
    `options` carries the VioConfig ("cfg") and calibration ("calibration") that the driver loaded, so a
    worker on another machine needs the flight's path and nothing else of the driver's files."""
    import tempfile

    from vio.frontend.runner import set_opencv_threads

    set_opencv_threads(1)

    row: dict = {k: None for k in _ROW_FIELDS}
    row.update(flight=Path(path).name, path=str(path), ok=False, worker=f"{os.uname().nodename}:{os.getpid()}",
               tum="")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="vio-batch-") as tmp:
        _replay_into(row, path, Path(tmp) / "traj.tum", options)
        if (Path(tmp) / "traj.tum").is_file():
            row["tum"] = (Path(tmp) / "traj.tum").read_text()
    if row["wall_s"] is None:
        row["wall_s"] = round(time.perf_counter() - t0, 3)
    return row


def _replay_into(row: dict, path: str, out_tum: Path, options: dict) -> None:
    try:
        from vio.app.replay import TumSink, open_dataset, replay

        cfg = options["cfg"]
        dataset = open_dataset(path, options.get("calibration"), options.get("topics"), cfg.bag)
        # what was repaired, skipped or cut when it was opened (a truncated recording, unpaired right images): a
        # row that reads "ok" must say it too
        row["notes"] = list(dataset.stats.notes)
        tum = TumSink(out_tum)
        try:
            res = replay(dataset, cfg, [tum], progress=False)
        finally:
            tum.close()
        row.update(frames=res.frames, poses=len(res.states), resets=res.resets, data_s=round(res.data_s, 3),
                   wall_s=round(res.wall_s, 3), realtime_factor=round(res.realtime_factor, 3))
        unusable = res.unusable_summary()  # frames skipped on the way (missing, unreadable, wrong-size images)
        if unusable:
            row["notes"].append(unusable)
        problem = res.vision_problem()
        if problem:
            raise VioError(problem)
        if dataset.groundtruth is not None and len(res.states) >= 3:
            from vio.evaluation import evaluate

            ev = evaluate(res.trajectory(), dataset.groundtruth.trajectory)
            row.update(ate_m=float(ev.ate_4dof.trans_m.rmse), ate_rot_deg=float(ev.ate_4dof.rot_deg.rmse),
                       coverage=float(ev.coverage))
            if ev.rpe:
                row.update(rpe_pct=float(ev.rpe[0].trans_pct), rpe_length_m=float(ev.rpe[0].length_m))
        row["ok"] = True
    except Exception as e:  # a failed flight is a row, never a lost batch
        row["error"] = f"{type(e).__name__}: {' '.join(str(e).split())}" if not isinstance(e, VioError) else \
            " ".join(str(e).split())


def _run_local(jobs: list[tuple[str, str, dict]], workers: int, progress) -> list[dict]:
    import concurrent.futures as cf
    import multiprocessing as mp

    rows: list[dict | None] = [None] * len(jobs)
    saved = {k: os.environ.get(k) for k in THREAD_ENV}
    os.environ.update(THREAD_ENV)  # inherited by the spawned workers
    try:
        return _run_pool(cf, mp, jobs, workers, progress, rows)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _run_pool(cf, mp, jobs, workers: int, progress, rows: list) -> list[dict]:
    """Each flight in a worker process; each row to `progress` as it comes. A worker that dies (killed, out of
    memory, a crash in native code) breaks the whole pool: every flight not finished by then failed with
    BrokenProcessPool, those still waiting their turn too (one flight that ran out of memory lost the rest of the
    batch). Those flights are run again, each in a process of its own, so that only a flight that kills its own
    worker is a failed row."""
    from concurrent.futures.process import BrokenProcessPool

    # spawn: a fresh interpreter per worker, as a Ray worker is (no state forked from the parent)
    ctx = mp.get_context("spawn")
    broken: list[int] = []
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        futs = {pool.submit(replay_flight, jobs[k][0], jobs[k][2]): k for k in range(len(jobs))}
        for f in cf.as_completed(futs):
            k = futs[f]
            try:
                rows[k] = _store(f.result(), jobs[k][1])
            except BrokenProcessPool:
                broken.append(k)
                continue
            except Exception as e:
                rows[k] = _failed_row(jobs[k][0], f"worker failed: {type(e).__name__}: {e}", jobs[k][1])
            progress(rows[k])
    if not broken:
        return rows
    broken.sort()
    log.warning("batch: a worker process died (killed, out of memory or crashed): the %d flights not finished then "
                "run again, each in a process of its own", len(broken))

    def alone(k: int) -> dict:
        with cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx) as one:
            try:
                return _store(one.submit(replay_flight, jobs[k][0], jobs[k][2]).result(), jobs[k][1])
            except BrokenProcessPool:
                return _failed_row(jobs[k][0], "worker failed: its process died while replaying this flight "
                                   "(killed, out of memory, or a crash in native code)", jobs[k][1])
            except Exception as e:
                return _failed_row(jobs[k][0], f"worker failed: {type(e).__name__}: {e}", jobs[k][1])

    with cf.ThreadPoolExecutor(max_workers=workers) as threads:
        for k, row in zip(broken, threads.map(alone, broken)):
            rows[k] = row
            progress(row)
    return rows  # type: ignore[return-value]


def _store(row: dict, out_tum: str) -> dict:
    """The driver writes each trajectory (a cluster's workers need not see the output folder). The row is named
    as its trajectory file: two flights called flight.mcap in two folders are two rows (compare keys on it)."""
    row["flight"] = Path(out_tum).stem
    tum = row.pop("tum", "")
    if tum:
        try:
            Path(out_tum).write_text(tum)
        except OSError as e:  # the row says so; the batch goes on
            row.update(ok=False, error=f"{out_tum}: cannot write the trajectory ({e.strerror})")
    return row


def _failed_row(path: str, error: str, out_tum: str) -> dict:
    row: dict = {k: None for k in _ROW_FIELDS}
    row.update(flight=Path(out_tum).stem, path=str(path), ok=False, error=error)
    return row


def _run_ray(jobs: list[tuple[str, str, dict]], address: str, workers: int, progress) -> list[dict]:
    from vio.extras import require

    ray = require("ray", "fleet", "vio batch --ray")
    started = False
    if not ray.is_initialized():
        if address == "local":
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
        started = True
    try:
        task = ray.remote(num_cpus=1, max_retries=0, runtime_env={"env_vars": THREAD_ENV})(replay_flight)
        refs = {task.remote(path, opts): k for k, (path, _tum, opts) in enumerate(jobs)}
        rows: list[dict | None] = [None] * len(jobs)
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                k = refs[ref]
                try:
                    rows[k] = _store(ray.get(ref), jobs[k][1])
                except Exception as e:  # the task's worker died
                    rows[k] = _failed_row(jobs[k][0], f"ray task failed: {type(e).__name__}: {e}", jobs[k][1])
                progress(rows[k])
    finally:
        if started:
            ray.shutdown()
    return rows  # type: ignore[return-value]


def run_batch(flights: list[str], out_dir: str | Path, *, workers: int | None = None, ray_address: str | None = None,
              options: dict | None = None, progress: bool = True, overwrite: bool = False) -> dict:
    """Replay `flights`, write the report files into `out_dir`, return the report.

    A folder that holds a report already is refused unless `overwrite` (a second run replaced the first's report
    unsaid and left its trajectories of flights no longer run beside the new ones: a review's finding); with it,
    the old report and trajectories go before the replays."""
    out = Path(out_dir)
    if ray_address:  # the [fleet] extra, asked for before --overwrite removes the old report or a folder is made
        from vio.extras import require

        require("ray", "fleet", "vio batch --ray")
    # the extras this machine has are the workers' only where they run here (local processes, a local Ray)
    check_bag_flights(flights, options or {}, workers_here=ray_address in (None, "local"))
    if (out / "report.json").exists():
        if not overwrite:
            raise VioError(f"--output {out}: holds a batch report already; --overwrite replaces it (compare with it: "
                           f"--compare {out}, with another --output)")
        for old in [out / n for n in ("report.json", "report.md", "report.png", "compare.md")] + \
                sorted((out / "traj").glob("*.tum")):
            old.unlink(missing_ok=True)
    try:
        (out / "traj").mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise VioError(f"--output {out}: cannot make the report folder ({e.strerror})") from None
    workers = max(1, workers or os.cpu_count() or 1)
    options = _load_inputs(options or {})
    taken: set[str] = set()
    jobs = []
    for f in flights:
        stem = Path(f).name or "flight"
        tag, k = stem, 1
        while tag in taken:  # a/f, b/f-2, c/f: f, f-2, f-3 (never two rows, or two trajectories, of one name)
            k += 1
            tag = f"{stem}-{k}"
        taken.add(tag)
        jobs.append((str(f), str(out / "traj" / f"{tag}.tum"), options))
    bar = None
    if progress and sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), unit="flight", desc="batch", leave=False)
    last = [time.monotonic()]
    done = [0]

    def tick(row: dict) -> None:
        done[0] += 1
        if bar is not None:
            bar.update(1)
        elif time.monotonic() - last[0] >= 5 or done[0] == len(jobs):
            log.info("batch: %d of %d flights done (last: %s, %s)", done[0], len(jobs), row["flight"],
                     "ok" if row["ok"] else row["error"])
            last[0] = time.monotonic()

    wall0 = time.perf_counter()
    try:
        rows = _run_ray(jobs, ray_address, workers, tick) if ray_address else _run_local(jobs, workers, tick)
    finally:
        if bar is not None:
            bar.close()
    report = {"engine": f"ray:{ray_address}" if ray_address else f"local:{workers}", "workers": workers,
              "wall_s": round(time.perf_counter() - wall0, 3), "flights": rows, "summary": summarise(rows)}
    write_report(report, out)
    return report


def check_bag_flights(flights: list[str], options: dict, workers_here: bool = True) -> None:
    """Refuse, before any work (VioError, one line naming the flights), bags and MCAP files that no worker could
    replay: without the [bags] extra, or without a calibration (no --calib, and not an MCAP file `vio record`
    made, which carries its own). Each such flight was replayed, failed and reported one by one, after the
    report folder was made or the old report removed. A flight this machine cannot see (a Ray client's driver)
    is left to its worker, and so is the extra where the workers run elsewhere (`workers_here` False: a Ray
    cluster's workers have their own installs; a driver that submits bags to them need not read any)."""
    from vio.io.bag import BAG_SUFFIXES, is_bag, recorded_calibration

    bags = [f for f in flights if Path(f).suffix in BAG_SUFFIXES or is_bag(f)]
    if not bags:
        return
    from vio.extras import require

    if workers_here:
        what = f"vio batch on bags and MCAP files ({_names(bags)})"
        require("rosbags.typesys", "bags", what)
        require("mcap.reader", "bags", what)
    if options.get("calibration") is not None or options.get("calib"):
        return
    missing = []
    for f in bags:
        p = Path(f)
        if p.suffix == ".mcap" and p.is_file():
            try:
                if recorded_calibration(p) is not None:
                    continue
            except VioError:  # a recorded calibration that does not read: the flight's row says so
                continue
        elif p.suffix == ".mcap" or not p.exists():
            continue  # not seen here, or an MCAP file only its worker sees
        missing.append(f)
    if missing:
        raise VioError(f"{_names(missing)}: a bag carries no camera-IMU calibration: give one with --calib (an MCAP "
                       "file recorded by vio record carries its own); nothing replayed")


def _names(paths: list[str], most: int = 3) -> str:
    """'a.bag, b.mcap and 4 more'."""
    more = f" and {len(paths) - most} more" if len(paths) > most else ""
    return ", ".join(paths[:most]) + more


def _load_inputs(options: dict) -> dict:
    """The config and calibration files, read once here by the driver: a bad file fails the batch at once
    (one line), and the workers get the objects, not paths they may not see."""
    from vio.app.replay import load_calib_args
    from vio.config import load_config

    out = {k: v for k, v in options.items() if k not in ("config", "calib", "calib_format")}
    out["cfg"] = options.get("cfg") or load_config(options.get("config"))
    if "calibration" not in out:
        out["calibration"] = load_calib_args(options.get("calib"), options.get("calib_format", "project"))
    return out


def summarise(rows: list[dict]) -> dict:
    import numpy as np

    ok = [r for r in rows if r["ok"]]

    def stat(key: str) -> dict | None:
        x = np.array([r[key] for r in ok if r[key] is not None], dtype=float)
        if not len(x):
            return None
        return {"mean": float(x.mean()), "median": float(np.median(x)), "max": float(x.max()), "n": int(len(x))}

    return {"flights": len(rows), "ok": len(ok), "failed": len(rows) - len(ok), "ate_m": stat("ate_m"),
            "rpe_pct": stat("rpe_pct"), "resets": int(sum(r["resets"] or 0 for r in ok)),
            "realtime_factor": stat("realtime_factor")}


def _fmt(v, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def markdown(report: dict) -> str:
    lines = [f"# vio batch: {report['summary']['ok']} of {report['summary']['flights']} flights ok "
             f"({report['engine']}, {report['wall_s']:.1f} s)", "",
             "| flight | ATE 4-DoF rmse [m] | RPE [%] | resets | real-time factor | frames | error / data notes |",
             "| --- | ---: | ---: | ---: | ---: | ---: | --- |"]
    for r in report["flights"]:
        said = "; ".join([r["error"]] if r["error"] else []) or "; ".join(r.get("notes") or [])
        lines.append(f"| {r['flight']} | {_fmt(r['ate_m'], 4)} | {_fmt(r['rpe_pct'], 2)} | {_fmt(r['resets'])} | "
                     f"{_fmt(r['realtime_factor'], 2)} | {_fmt(r['frames'])} | {said} |")
    s = report["summary"]

    def m(key: str, digits: int) -> str:
        return "-" if s[key] is None else f"mean {s[key]['mean']:.{digits}f}, median {s[key]['median']:.{digits}f}, " \
                                          f"max {s[key]['max']:.{digits}f}"

    lines += ["", f"Summary: ATE [m] {m('ate_m', 4)}; RPE [%] {m('rpe_pct', 2)}; resets {s['resets']}; "
              f"real-time factor {m('realtime_factor', 2)}; failed {s['failed']}; with data notes "
              f"{sum(1 for r in report['flights'] if r.get('notes'))}.", ""]
    return "\n".join(lines)


def write_report(report: dict, out: Path) -> None:
    """Write report.md, report.png (only with the [tools] extra) and report.json into `out`, the JSON last so that
    `report["files"]` (there and in `report`) names the files written: `vio batch` prints them, and it said
    report.png where none was written."""
    (out / "report.md").write_text(markdown(report))
    files = ["report.md", "report.json"]
    try:
        plot(report, out / "report.png")
        files.append("report.png")
    except VioError as e:  # no matplotlib: the table and JSON are the report
        log.warning("no plot: %s", e)
    report["files"] = files
    (out / "report.json").write_text(json.dumps(report, indent=1))


def plot(report: dict, path: Path) -> None:
    from vio.extras import pyplot

    plt = pyplot("the batch report's plot")
    rows = report["flights"]
    names = [r["flight"] for r in rows]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(max(6, 0.6 * len(rows) + 4), 3.5))
    a1.bar(names, [r["ate_m"] or 0.0 for r in rows], color=["C0" if r["ok"] else "C3" for r in rows])
    a1.set_ylabel("ATE 4-DoF rmse [m]")
    a2.bar(names, [r["realtime_factor"] or 0.0 for r in rows], color="C1")
    a2.set_ylabel("real-time factor")
    for a in (a1, a2):
        a.tick_params(axis="x", rotation=60)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def load_report(path: str | Path) -> dict:
    p = Path(path)
    if p.is_dir():
        p = p / "report.json"
    try:
        report = json.loads(read_user_file(p, "batch report", limit=None).decode("utf-8"))  # not a device: a hang
    except OSError as e:
        raise VioError(f"{p}: cannot read the report ({e.strerror})") from None
    except UnicodeDecodeError:  # a binary file: was an internal error
        raise VioError(f"{p}: not a batch report (not a text file)") from None
    except json.JSONDecodeError as e:
        raise VioError(f"{p}: not a batch report ({e})") from None
    except RecursionError:  # nested thousands deep: was an internal error (a review's finding)
        raise VioError(f"{p}: not a batch report (nested too deep to be one)") from None
    problem = _report_problem(report)
    if problem:  # a JSON of another kind (a status file) failed with a KeyError after the whole batch had run
        raise VioError(f"{p}: not a batch report ({problem})")
    return report


def _report_problem(report: object) -> str | None:
    """What keeps `report` from being compared with (compare() reads these keys of each old row), or None."""
    if not isinstance(report, dict) or not isinstance(report.get("flights"), list):
        return "no list of flights"
    number = (int, float)
    for k, row in enumerate(report["flights"]):
        if not isinstance(row, dict) or not isinstance(row.get("flight"), str) or not isinstance(row.get("ok"), bool) \
                or any(not (row.get(key) is None or isinstance(row.get(key), number) and
                            not isinstance(row.get(key), bool)) for key in ("ate_m", "rpe_pct", "resets")):
            return f"flight {k + 1} lacks its name, ok, ate_m, rpe_pct or resets, or one is of another type"
    return None


def _finite(x) -> float | None:
    """A report's figure, None where there is none (null, NaN, inf, not a number)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def compare(new: dict, old: dict, tol: float = 0.05) -> str:
    """Markdown: per flight (by name) ATE, RPE, resets and real-time factor before -> after, and a verdict.
    A change of more than `tol` (relative) in ATE or RPE, or any change in resets or success, counts."""
    before = {r["flight"]: r for r in old["flights"]}
    lines = ["| flight | ATE [m] before -> after | RPE [%] | resets | real-time factor | verdict |",
             "| --- | --- | --- | --- | --- | --- |"]
    tally = {"better": 0, "worse": 0, "same": 0, "new": 0}
    for r in new["flights"]:
        o = before.get(r["flight"])
        if o is None:
            verdict = "new"
        else:
            score = 0
            for key in ("ate_m", "rpe_pct"):
                a, b = _finite(o[key]), _finite(r[key])
                if a is not None and b is not None:
                    if abs(b - a) > tol * max(abs(a), 1e-9):
                        score += 1 if b < a else -1
                elif (a is None) != (b is None) and o["ok"] == r["ok"]:
                    # a figure on one side only (NaN in a report: NaN compares false with everything, so a flight
                    # whose ATE came back read "same", the input review's note); a success change scores below
                    score += 1 if a is None else -1
            if (o["resets"] or 0) != (r["resets"] or 0):
                score += 1 if (r["resets"] or 0) < (o["resets"] or 0) else -1
            if o["ok"] != r["ok"]:
                score += 2 if r["ok"] else -2
            verdict = "better" if score > 0 else "worse" if score < 0 else "same"
        tally[verdict] += 1
        o = o or {}

        def pair(key: str, d: int, o=o, r=r) -> str:
            return f"{_fmt(o.get(key), d)} -> {_fmt(r[key], d)}"

        # rows are matched by name: one of another recording (another path, another frame count) is said so, or
        # day2/f read as day1/f got "worse" with no word (a review's finding)
        other = [f"{k} {o.get(k)} -> {r.get(k)}" for k in ("path", "frames")
                 if o and o.get(k) is not None and r.get(k) is not None and o.get(k) != r.get(k)]
        note = f" (another recording? {'; '.join(other)})" if other else ""
        lines.append(f"| {r['flight']} | {pair('ate_m', 4)} | {pair('rpe_pct', 2)} | {pair('resets', 0)} | "
                     f"{pair('realtime_factor', 2)} | {verdict}{note}{' (' + r['error'] + ')' if r['error'] else ''} |")
    gone = sorted(set(before) - {r["flight"] for r in new["flights"]})
    head = (f"Compared with the earlier report: {tally['better']} better, {tally['worse']} worse, {tally['same']} "
            f"the same, {tally['new']} new" + (f", {len(gone)} no longer run ({', '.join(gone)})" if gone else ""))
    return "\n".join([head, "", *lines, ""])


def run(args: argparse.Namespace) -> int:
    from vio.app.replay import check_calib_format
    from vio.io.outputs import check_outputs

    check_calib_format(args)
    options = {"config": args.config, "calib": args.calib, "calib_format": args.calib_format or "project",
               "topics": (args.left_topic, args.right_topic, args.imu_topic)}
    old = load_report(args.compare) if args.compare else None  # a bad --compare fails before hours of replay
    check_outputs({}, recordings=tuple(args.flights), folders={"the batch report": args.output})
    report = run_batch(args.flights, args.output, workers=args.workers, ray_address=args.ray, options=options,
                       progress=not args.no_progress, overwrite=args.overwrite)
    print(markdown(report))
    files = list(report["files"])
    if old is not None:
        text = compare(report, old)
        (Path(args.output) / "compare.md").write_text(text)
        files.append("compare.md")
        print(text)
    print(f"wrote {Path(args.output) / files[0]}, {', '.join(files[1:])}")
    return 0 if report["summary"]["failed"] == 0 else 1
