"""Accuracy matrix: the estimator on many simulated flights, one table row per flight.

    python bench/accuracy_matrix.py [--only NAME ...] [--generate-only] [--rerun] [--doc docs/estimator.md]

Flights (60 s each; generated once by `vio simulate` into the bench flight cache, see bench/flights.py):
5 seeds x (survey, aggressive) on the default (realistic) variant, plus hard cases: the hard variant, a
camera-IMU time offset of +-10 ms that the calibration does *not* know (the replay's calibration says 0),
5 % dropped frames, a 0.08 rad/s gyro bias, strong motor vibration and large plain (low-texture) walls;
and, where ../shared/data is, EuRoC V1_01's and V1_02's real IMU and ground truth under rendered images
(`vio simulate --imu-from`, the whole recordings: 145 s and 83.5 s).

Replays run one after the other in this process with one thread for OpenCV/BLAS (the machine is shared:
start it under `nice`). Each result is kept as JSON in --out and reused unless --rerun, so an interrupted
matrix resumes. The table (ATE SE(3)/4-DoF, RPE, resets, coverage, real-time factor by wall clock and
by CPU time) is printed and, with --doc, written between the `accuracy-matrix` markers of that file.
A flight passes with ATE SE(3) <= 0.10 m and RPE <= 1 %.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.flights import DEFAULT_CACHE, FlightSpec, ensure_flight  # noqa: E402

log = logging.getLogger("accuracy_matrix")

ATE_MAX_M = 0.10
RPE_MAX_PCT = 1.0
BEGIN, END = "<!-- accuracy-matrix:begin -->", "<!-- accuracy-matrix:end -->"


@dataclass(frozen=True)
class MatrixFlight(FlightSpec):
    """A FlightSpec with extra `vio simulate` options (they become part of the cache key)."""

    extra: tuple[str, ...] = ()

    @property
    def key(self) -> str:
        tag = "".join(self.extra).replace("--", "_").replace(".", "p")
        return super().key + tag

    def simulate_args(self, out: Path) -> list[str]:
        return super().simulate_args(out) + list(self.extra)


SHARED_EUROC = Path(os.environ.get("KESTREL_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")) \
    / "euroc"
RECORDINGS = {"V1_01": "V1_01_easy_excerpt", "V1_02": "V1_02_medium_imu_gt"}  # real IMU + ground truth


@dataclass(frozen=True)
class RecordedFlight(MatrixFlight):
    """A recording's real IMU and ground truth with rendered images (`vio simulate --imu-from`), whole."""

    recording: str = "V1_02"

    @property
    def key(self) -> str:
        return f"recorded-{self.recording}-{self.variant}-seed{self.seed}-{self.size}"

    def simulate_args(self, out: Path) -> list[str]:
        return ["simulate", str(out), "--imu-from", str(SHARED_EUROC / RECORDINGS[self.recording]), "--duration",
                "3600", "--seed", str(self.seed), "--variant", self.variant, "--size", self.size, "--no-progress"]


@dataclass(frozen=True)
class Case:
    name: str
    flight: MatrixFlight
    calib_offset_known: bool = True  # False: replay with a calibration that claims no time offset
    note: str = ""


def cases(duration_s: float = 60.0) -> list[Case]:
    def f(profile: str, seed: int, variant: str = "realistic", *extra: str) -> MatrixFlight:
        return MatrixFlight(profile, duration_s, seed, variant, "752x480", tuple(extra))

    out = [Case(f"{p}-s{s}", f(p, s)) for p in ("survey", "aggressive") for s in range(1, 6)]
    out += [
        Case("survey-hard-s1", f("survey", 1, "hard"), note="hard variant"),
        Case("aggressive-hard-s1", f("aggressive", 1, "hard"), note="hard variant"),
        Case("aggr-offset+10ms", f("aggressive", 1, "realistic", "--time-offset-ms", "10"), False,
             "+10 ms offset, calibration says 0"),
        Case("aggr-offset-10ms", f("aggressive", 1, "realistic", "--time-offset-ms", "-10"), False,
             "-10 ms offset, calibration says 0"),
        Case("aggr-drop5", f("aggressive", 2, "realistic", "--drop-frames", "0.05"), note="5 % dropped frames"),
        Case("aggr-gyrobias0.08", f("aggressive", 3, "realistic", "--gyro-bias", "0.08"), note="gyro bias 0.08 rad/s"),
        Case("aggr-vibration1.5", f("aggressive", 4, "realistic", "--vibration", "1.5"), note="vibration 1.5 m/s^2"),
        Case("survey-plain0.5", f("survey", 5, "realistic", "--plain", "0.5"), note="half the walls plain"),
        Case("aggr-oak-mount", f("aggressive", 5, "realistic", "--imu-mount", "oak"),
             note="IMU x up, as in a forward-looking OAK (aggressive-s5's flight, same images and samples)"),
    ]
    # EuRoC's real IMU (vibration, biases, 18-60x its datasheet's noise) under rendered images; only where
    # ../shared/data is (KESTREL_SHARED_DATA), whole recordings whatever --duration says
    out += [Case(f"real-imu-{name}", RecordedFlight("recorded", 0.0, 1, "realistic", "752x480", recording=name),
                 note=f"EuRoC {name}'s IMU and ground truth, rendered images")
            for name, folder in RECORDINGS.items() if (SHARED_EUROC / folder / "mav0").is_dir()]
    return out


def replay_case(case: Case, path: Path, config) -> dict:
    """Replay one flight with `config` (a TOML path, a VioConfig, or None for the defaults); accuracy against
    its ground truth and the cost."""
    import cv2

    from vio import VioError
    from vio.app.replay import replay
    from vio.config import VioConfig, load_config
    from vio.evaluation import evaluate
    from vio.io.euroc import EurocDataset

    cv2.setNumThreads(1)
    ds = EurocDataset(path)
    true_offset_ms = ds.calibration.time_offset_ns * 1e-6
    if not case.calib_offset_known:
        ds = EurocDataset(path, dataclasses.replace(ds.calibration, time_offset_ns=0))
    cpu0 = time.process_time()
    res = replay(ds, config if isinstance(config, VioConfig) else load_config(config), progress=False)
    cpu_s = time.process_time() - cpu0
    d = res.stats_dict()
    d.pop("per_frame")
    row = {"name": case.name, "note": case.note, "flight": case.flight.key, "true_offset_ms": true_offset_ms,
           "est_offset_ms": d["time_offset_ms"]["final"],
           "frames": res.frames, "resets": res.resets, "keyframes": d["keyframes"], "data_s": res.data_s,
           "wall_s": res.wall_s, "cpu_s": cpu_s, "rtf_wall": res.realtime_factor,
           "rtf_cpu": res.data_s / cpu_s if cpu_s > 0 else float("inf"), "timing_ms": d["timing_ms"],
           "load_avg": os.getloadavg()[0], "calibration_refined": d.get("calibration_refined")}
    try:
        ev = evaluate(res.trajectory(), ds.groundtruth.trajectory)
        row.update(ate_se3_m=ev.ate_se3.trans_m.rmse, ate_4dof_m=ev.ate_4dof.trans_m.rmse,
                   ate_rot_deg=ev.ate_se3.rot_deg.rmse, rpe_pct=ev.rpe_trans_pct, coverage=ev.coverage,
                   path_m=ev.path_length_m)
    except VioError as e:
        row.update(ate_se3_m=float("nan"), ate_4dof_m=float("nan"), ate_rot_deg=float("nan"), rpe_pct=float("nan"),
                   coverage=0.0, path_m=float("nan"), error=str(e))
    row["pass"] = bool(row["ate_se3_m"] <= ATE_MAX_M and row["rpe_pct"] <= RPE_MAX_PCT)
    return row


def table(rows: list[dict]) -> str:
    head = ("| flight | ATE SE(3) [m] | ATE 4-DoF [m] | RPE [%] | resets | coverage | keyframes | RTF wall | "
            "RTF cpu | time offset true / final [ms] | pass |")
    lines = [head, "|" + "|".join([" --- "] * 11) + "|"]
    for r in rows:
        est = r.get("est_offset_ms")
        offset = f"{r['true_offset_ms']:+.1f} / " + ("-" if est is None else f"{est:+.1f}")
        lines.append(f"| {r['name']} | {r['ate_se3_m']:.3f} | {r['ate_4dof_m']:.3f} | {r['rpe_pct']:.2f} | "
                     f"{r['resets']} | {100 * r['coverage']:.1f} % | {r['keyframes']} | {r['rtf_wall']:.2f} | "
                     f"{r['rtf_cpu']:.2f} | {offset} | {'yes' if r['pass'] else '**no**'} |")
    n_pass = sum(r["pass"] for r in rows)
    lines.append("")
    lines.append(f"{n_pass} of {len(rows)} flights pass (ATE SE(3) <= {ATE_MAX_M:g} m and RPE <= {RPE_MAX_PCT:g} %); "
                 f"load average during the replays {min(r['load_avg'] for r in rows):.1f}-"
                 f"{max(r['load_avg'] for r in rows):.1f} on 2 cores.")
    return "\n".join(lines)


def write_doc(doc: Path, text: str) -> None:
    """Replace the text between the markers (append a section with them when they are missing)."""
    body = doc.read_text()
    block = f"{BEGIN}\n{text}\n{END}"
    if BEGIN in body and END in body:
        body = body[:body.index(BEGIN)] + block + body[body.index(END) + len(END):]
    else:
        body = body.rstrip("\n") + "\n\n## Accuracy matrix\n\n" + block + "\n"
    doc.write_text(body)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", help="case names to run (default: all)")
    ap.add_argument("--generate-only", action="store_true", help="only make sure the flights are cached")
    ap.add_argument("--rerun", action="store_true", help="replay again even when a result is stored")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="flight cache folder")
    ap.add_argument("--out", type=Path, default=Path("/tmp/kestrel-bench/matrix"), help="per-flight results")
    ap.add_argument("--config", help="TOML configuration for the estimator")
    ap.add_argument("--duration", type=float, default=60.0, help="flight length [s]")
    ap.add_argument("--doc", type=Path, help="write the table into this markdown file")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    logging.getLogger("vio").setLevel(logging.WARNING)
    from vio import VioError

    todo = [c for c in cases(args.duration) if not args.only or c.name in args.only]
    if args.list or not todo:
        for c in cases(args.duration):
            print(f"{c.name:<22} {c.flight.key}  {c.note}")
        return 0 if todo else 1
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        for c in todo:
            path = ensure_flight(c.flight, args.cache)
            if args.generate_only:
                continue
            res_file = args.out / f"{c.name}.json"
            if res_file.is_file() and not args.rerun:
                rows.append(json.loads(res_file.read_text()))
                continue
            row = replay_case(c, path, args.config)
            res_file.write_text(json.dumps(row, indent=1))
            log.info("%s: ATE %.3f m, RPE %.2f %%, %d resets, RTF %.2f (cpu %.2f)", c.name, row["ate_se3_m"],
                     row["rpe_pct"], row["resets"], row["rtf_wall"], row["rtf_cpu"])
            rows.append(row)
    except VioError as e:
        print(f"accuracy_matrix: {e}", file=sys.stderr)
        return 1
    if not rows:
        return 0
    text = table(rows)
    print(text)
    if args.doc:
        write_doc(args.doc, text)
    return 0 if all(r["pass"] for r in rows) else 2


if __name__ == "__main__":
    sys.exit(main())
