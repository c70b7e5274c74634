"""Compare two estimator configurations on the accuracy matrix, each flight replayed several times under null
perturbations, so that a flight's own chaos does not decide the verdict.

Why: a single 60 s flight's ATE moves by up to +-25 % under a change that means nothing physically (the
matrix at `imu_noise_scale` 2.0002 or 1.9998 instead of 2.0 had 3-5 of 19 flights more than 10 % worse and as
many better; docs/estimator.md, "The time offset state by default"). The pipeline's yes/no steps (keyframes,
RANSAC inlier sets, tracks kept or dropped) turn any tiny numeric difference into a different trajectory. So
each configuration is replayed `--runs` times with `imu_noise_scale` scaled by 1, 1 + 1e-4, 1 - 1e-4,
1 + 2e-4, ... (0.01 % steps: physically nothing), and flights are compared on the geometric mean of their
runs; the summary is the geometric mean of the per-flight ratios with its standard error.

    python bench/null_compare.py --b new.toml [--a old.toml] [--runs 3] [--only survey-s1 aggressive-s1]

Results are cached per configuration, run and flight under --out (a configuration is named by its file's
stem, "default" without one); --rerun replays again.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.accuracy_matrix import cases, replay_case  # noqa: E402
from bench.flights import DEFAULT_CACHE, ensure_flight  # noqa: E402

log = logging.getLogger("null_compare")
STEP = 1e-4  # relative change of imu_noise_scale between runs: physically nothing


def null_scales(runs: int) -> list[float]:
    """Factors on imu_noise_scale for the runs: 1, 1 + STEP, 1 - STEP, 1 + 2 STEP, ..."""
    out = [1.0]
    k = 1
    while len(out) < runs:
        out += [1.0 + k * STEP, 1.0 - k * STEP]
        k += 1
    return out[:runs]


def geo_mean(x: list[float]) -> float:
    return math.exp(sum(math.log(v) for v in x) / len(x))


def summarise(a: dict[str, list[float]], b: dict[str, list[float]]) -> dict:
    """Per flight: the geometric mean of each configuration's runs and their ratio b / a; over the flights
    both have: the geometric mean ratio, its standard error (as a factor) and the flights beyond +-10 %."""
    flights = [n for n in a if n in b and a[n] and b[n] and all(v > 0 and math.isfinite(v) for v in a[n] + b[n])]
    rows = [{"flight": n, "a": geo_mean(a[n]), "b": geo_mean(b[n]), "ratio": geo_mean(b[n]) / geo_mean(a[n])}
            for n in flights]
    logs = [math.log(r["ratio"]) for r in rows]
    if not logs:
        return {"rows": [], "geo_mean_ratio": float("nan"), "stderr_factor": float("nan"), "worse": [], "better": []}
    mean = sum(logs) / len(logs)
    sd = math.sqrt(sum((x - mean) ** 2 for x in logs) / (len(logs) - 1)) if len(logs) > 1 else float("nan")
    return {"rows": rows, "geo_mean_ratio": math.exp(mean), "stderr_factor": math.exp(sd / math.sqrt(len(logs))),
            "worse": [r["flight"] for r in rows if r["ratio"] > 1.1],
            "better": [r["flight"] for r in rows if r["ratio"] < 0.9]}


def _config(path: str | None, scale: float):
    from vio.config import VioConfig, load_config

    cfg = load_config(path) if path else VioConfig()
    return dataclasses.replace(cfg, backend=dataclasses.replace(cfg.backend,
                                                                imu_noise_scale=cfg.backend.imu_noise_scale * scale))


def _runs(label: str, config: str | None, todo, scales: list[float], args) -> dict[str, list[float]]:
    """ATE SE(3) [m] of each flight, one per run (cached as JSON under out/label/run-K/)."""
    out: dict[str, list[float]] = {}
    for k, scale in enumerate(scales):
        folder = args.out / label / f"run-{k}"
        folder.mkdir(parents=True, exist_ok=True)
        for c in todo:
            res = folder / f"{c.name}.json"
            if res.is_file() and not args.rerun:
                row = json.loads(res.read_text())
            else:
                row = replay_case(c, ensure_flight(c.flight, args.cache), _config(config, scale))
                res.write_text(json.dumps(row, indent=1))
                log.info("%s run %d (imu_noise_scale x%.4f) %s: ATE %.1f mm", label, k, scale, c.name,
                         row["ate_se3_m"] * 1e3)
            out.setdefault(c.name, []).append(row["ate_se3_m"])
    return out


def table(s: dict, label_a: str, label_b: str, runs: int) -> str:
    lines = [f"| flight | ATE {label_a} [mm] | ATE {label_b} [mm] | ratio |", "| --- | --- | --- | --- |"]
    for r in s["rows"]:
        ratio = f"**{r['ratio']:.2f}**" if r["ratio"] > 1.1 else f"{r['ratio']:.2f}"  # the flights beyond 10 %
        lines.append(f"| {r['flight']} | {r['a'] * 1e3:.1f} | {r['b'] * 1e3:.1f} | {ratio} |")
    lines += ["", f"Geometric means of {runs} null-perturbed runs per flight; over {len(s['rows'])} flights the "
              f"ratio {label_b} / {label_a} is {s['geo_mean_ratio']:.3f} (standard error x{s['stderr_factor']:.3f}); "
              f"more than 10 % worse: {', '.join(s['worse']) or 'none'}; more than 10 % better: "
              f"{', '.join(s['better']) or 'none'}."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", help="TOML configuration A (default: the built-in defaults)")
    ap.add_argument("--b", help="TOML configuration B (default: the built-in defaults)")
    ap.add_argument("--runs", type=int, default=3, help="null-perturbed replays per flight and configuration")
    ap.add_argument("--only", nargs="*", help="case names (default: all of bench/accuracy_matrix.py)")
    ap.add_argument("--duration", type=float, default=60.0, help="flight length [s]")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="flight cache folder")
    ap.add_argument("--out", type=Path, default=Path("/tmp/kestrel-bench/null_compare"), help="per-run results")
    ap.add_argument("--rerun", action="store_true", help="replay again even when a result is stored")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    logging.getLogger("vio").setLevel(logging.WARNING)
    from vio import VioError

    if args.runs < 1:
        print("null_compare: --runs must be at least 1", file=sys.stderr)
        return 1
    names = {c.name for c in cases(args.duration)}
    unknown = sorted(set(args.only or []) - names)
    if unknown:
        print(f"null_compare: unknown case(s) {', '.join(unknown)} (see bench/accuracy_matrix.py --list)",
              file=sys.stderr)
        return 1
    todo = [c for c in cases(args.duration) if not args.only or c.name in args.only]
    label_a = Path(args.a).stem if args.a else "default"
    label_b = Path(args.b).stem if args.b else "default"
    if label_a == label_b:
        label_b += "-b"
    scales = null_scales(args.runs)
    try:
        a = _runs(label_a, args.a, todo, scales, args)
        b = _runs(label_b, args.b, todo, scales, args)
    except VioError as e:
        print(f"null_compare: {e}", file=sys.stderr)
        return 1
    s = summarise(a, b)
    print(table(s, label_a, label_b, args.runs))
    (args.out / f"{label_a}-vs-{label_b}.json").write_text(json.dumps({"runs": args.runs, "scales": scales,
                                                                       "a": a, "b": b, **s}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
