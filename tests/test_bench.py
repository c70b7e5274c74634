"""Benchmark suite: its pure parts (memory growth, ratios, verdicts, flight cache) and one smoke run of the whole
suite on a tiny flight. No timing assertions: the numbers are only checked for being there and sane."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from bench import run_suite  # noqa: E402
from bench.flights import FlightSpec, ensure_flight  # noqa: E402
from bench.live import memory_growth  # noqa: E402
from vio import VioError  # noqa: E402


def test_memory_growth_uses_plateau_medians() -> None:
    t = np.arange(0.0, 100.0, 0.5)
    rss = np.full_like(t, 200.0)
    rss[t > 40] += 3.0  # a real step of 3 MB
    rss[(t > 15) & (t < 16)] += 80.0  # a transient spike inside the early window: the median ignores it
    g = memory_growth(t, rss, 0.0, 100.0)
    assert g["early_mb"] == pytest.approx(200.0)
    assert g["growth_mb"] == pytest.approx(3.0)
    assert g["second_half_mb_per_10min"] == pytest.approx(0.0, abs=0.5)  # a step, not a leak
    leak = memory_growth(t, 200.0 + 0.01 * t, 0.0, 100.0)  # 0.01 MB/s = 6 MB per 10 min
    assert leak["second_half_mb_per_10min"] == pytest.approx(6.0)
    assert leak["growth_mb"] == pytest.approx(0.01 * (95 - 15), abs=0.02)
    g = memory_growth(t, rss, 45.0, 100.0)  # both windows after the step
    assert g["growth_mb"] == pytest.approx(0.0)


def test_memory_growth_rejects_too_short_traces() -> None:
    with pytest.raises(VioError, match="too few RSS samples"):
        memory_growth(np.array([0.0, 0.5]), np.array([1.0, 1.0]), 0.0, 1.0)
    with pytest.raises(VioError, match="no time span"):
        memory_growth(np.array([0.0]), np.array([1.0]), 5.0, 5.0)


def _run(name: str, ate: float, total_ms: list[float], wall_s: float) -> run_suite.RunResult:
    r = run_suite.RunResult(name, "ds", "0", ok=True, frames=len(total_ms), data_s=10.0, wall_s=wall_s, cpu_s=wall_s)
    r.per_frame_ms = {k: total_ms for k in run_suite.STAGES}
    r.timing_ms = {k: {} for k in run_suite.STAGES}
    r.accuracy = {"ate_se3_m": ate, "ate_4dof_m": ate, "rpe_pct": 2 * ate}
    return r


def test_ratios_this_over_other() -> None:
    this = {"f": _run("f", 0.2, [20.0] * 10, 5.0)}
    other = {"f": _run("f", 0.1, [10.0] * 10, 2.5), "g": _run("g", 0.1, [10.0], 1.0)}
    r = run_suite.ratios(this, other)
    assert set(r["flights"]) == {"f"}
    assert r["flights"]["f"]["ate_se3_m"] == pytest.approx(2.0)
    assert r["speed"]["total_ms_mean"] == pytest.approx(2.0)
    assert r["speed"]["rtf"] == pytest.approx((10 / 5.0) / (20 / 3.5))  # other pools f and g


def test_verdicts_pass_miss_and_missing() -> None:
    head = {"rtf_one_core": 3.5, "p99_frame_ms": 40.0, "latency_p50_ms": math.nan, "memory_growth_mb": 5.0,
            "synthetic_ate_m": None, "synthetic_rpe_pct": 0.5}
    v = run_suite.verdicts(head)
    assert v == {"rtf_one_core": "PASS", "p99_frame_ms": "MISS", "latency_p50_ms": "n/a",
                 "memory_growth_mb": "PASS", "synthetic_ate_m": "n/a", "synthetic_rpe_pct": "PASS",
                 "rtf_one_core_issue17": "MISS", "p99_frame_ms_issue17": "MISS"}


def test_compare_rejects_unknown_revision(tmp_path: Path) -> None:
    with pytest.raises(VioError, match="no-such-rev"):
        run_suite.worktree_for("no-such-rev", tmp_path)


def test_flight_cache_generates_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    spec = FlightSpec("hover", 3.0, 4, "clean", "188x120")
    path = ensure_flight(spec, tmp_path)
    assert (path / "mav0" / "cam0" / "data.csv").is_file() and path.name == spec.key
    assert not list(tmp_path.glob(".*partial*"))

    def no_subprocess(*a, **k):
        raise AssertionError("a cached flight was generated again")

    monkeypatch.setattr(subprocess, "run", no_subprocess)
    assert ensure_flight(spec, tmp_path) == path


def test_report_keeps_its_hand_written_part(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from bench import report

    path = tmp_path / "benchmarks.md"
    monkeypatch.setattr(report, "render", lambda res, rel: f"# generated {res['n']}\n")
    report.write_report({"n": 1}, path, tmp_path)
    assert path.read_text() == "# generated 1\n"  # nothing to keep yet
    path.write_text(path.read_text() + "\n" + report.KEPT_MARKER + "\n## Where the time goes\nby hand\n")
    report.write_report({"n": 2}, path, tmp_path)
    text = path.read_text()
    assert text.startswith("# generated 2\n") and "# generated 1" not in text
    assert text.endswith(report.KEPT_MARKER + "\n## Where the time goes\nby hand\n")


def test_suite_smoke_run_writes_report_and_json(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out, report = tmp_path / "results", tmp_path / "benchmarks.md"
    # ask for the real EuRoC excerpt where there is none: the report must say it was skipped
    monkeypatch.setattr(run_suite, "EUROC_EXCERPT", tmp_path / "no-euroc")
    monkeypatch.setitem(run_suite.PLANS, "smoke", dataclasses.replace(run_suite.PLANS["smoke"], euroc=True))
    rc = run_suite.main(["--plan", "smoke", "--out", str(out), "--report", str(report), "--work", str(tmp_path)])
    assert rc == 0
    res = json.loads((out / "suite.json").read_text())
    assert not res["headline"]["failed_runs"]
    assert set(res["verdicts"].values()) <= {"PASS", "MISS"}  # every target measured
    run = next(iter(res["runs"].values()))
    assert run["frames"] > 50 and 0 < run["accuracy"]["ate_se3_m"] < 1.0
    assert run["output_ms"]["n"] > 0 and run["timing_ms"]["total_ms"]["p99"] > 0
    assert res["speed"]["all_cores"]["frames"] == run["frames"]
    assert res["live"]["latency_ms"]["n"] > 10 and res["live"]["memory"]["peak_rss_mb"] > 50
    assert any("estimator.py" in r["function"] for r in res["profile"]["cumulative"])
    text = report.read_text()
    assert f"not found at {tmp_path / 'no-euroc'}: skipped" in text
    for heading in ("## Targets", "## Accuracy", "## Speed", "## Latency", "## Memory", "## Profile"):
        assert heading in text
    for png in [*res["plots"].values(), "memory_rss.png"]:
        assert (out / png).stat().st_size > 1000
        assert f"{out.name}/{png}" in text


def test_loop_bench_true_edge_floor_uses_exact_edges_between_the_same_keyframes() -> None:
    """bench/loop_closure.py's 'with exact loop edges' figure: the same graph with each active loop edge
    replaced by the truth. On a drifting circle with 5 cm-noisy closures it must land closer to the truth
    than the graph with the noisy edges (it would not if the edges were not replaced)."""
    from types import SimpleNamespace

    from bench.loop_closure import _with_true_edges
    from vio.evaluation import evaluate
    from vio.geometry import make_T, so3_exp
    from vio.loop.posegraph import PoseGraph
    from vio.trajectory import Trajectory

    rng = np.random.default_rng(1)
    n = 121
    truth = [make_T(so3_exp(np.array([0, 0, 2 * np.pi * k / 40])),
                    2 * np.array([np.cos(2 * np.pi * k / 40), np.sin(2 * np.pi * k / 40), 1.0])) for k in range(n)]
    g, prev, T = PoseGraph(), None, truth[0].copy()
    for k in range(n):
        if k:
            T = T @ np.linalg.inv(truth[k - 1]) @ truth[k] @ make_T(so3_exp(np.r_[0, 0, 8e-4]), np.r_[3e-3, 0, 0])
        prev = g.add_node(T, prev)
    for k in range(40, n):
        noise = make_T(so3_exp(rng.normal(0, 0.005, 3)), rng.normal(0, 0.05, 3))
        g.add_loop(k % 40, k, np.linalg.inv(truth[k % 40]) @ truth[k] @ noise)
    g.optimize()
    t_ns = np.arange(n, dtype=np.int64) * 250_000_000
    closer = SimpleNamespace(graph=g, map_keyframes=0,
                             keyframes=[SimpleNamespace(session=0, t_ns=int(t)) for t in t_ns])
    gt = Trajectory.from_poses(t_ns, np.array(truth))
    T_odom = np.array(g.odom)
    noisy = np.array([E @ np.linalg.inv(O) @ P for E, O, P in zip(g.estimate, g.odom, T_odom)])
    exact = _with_true_edges(closer, gt, t_ns, T_odom)
    ate = {name: evaluate(Trajectory.from_poses(t_ns, X), gt).ate_4dof.trans_m.rmse
           for name, X in (("odometry", T_odom), ("noisy", noisy), ("exact", exact))}
    assert ate["exact"] < 0.5 * ate["noisy"] and ate["exact"] < 0.2 * ate["odometry"], ate


def test_null_compare_scales_and_summary() -> None:
    """The null runs scale imu_noise_scale by 1, 1 +- 1e-4, 1 +- 2e-4...; the summary compares geometric means
    per flight, leaves out flights one side lacks or could not evaluate (NaN), and names those beyond 10 %."""
    from bench.null_compare import null_scales, summarise

    assert null_scales(1) == [1.0]
    assert null_scales(4) == pytest.approx([1.0, 1.0001, 0.9999, 1.0002])
    a = {"f1": [0.010, 0.040], "f2": [0.010, 0.010], "f3": [0.010], "f4": [0.010]}
    b = {"f1": [0.020, 0.020], "f2": [0.012, 0.012], "f3": [float("nan")], "f5": [0.010]}
    s = summarise(a, b)
    assert [r["flight"] for r in s["rows"]] == ["f1", "f2"]
    assert s["rows"][0]["a"] == pytest.approx(0.020) and s["rows"][0]["ratio"] == pytest.approx(1.0)
    assert s["rows"][1]["ratio"] == pytest.approx(1.2)
    assert s["geo_mean_ratio"] == pytest.approx(math.sqrt(1.2))
    assert s["worse"] == ["f2"] and s["better"] == []
    assert s["stderr_factor"] == pytest.approx(math.exp(abs(math.log(1.2)) / math.sqrt(2) / math.sqrt(2)))


def test_null_compare_refuses_an_unknown_case() -> None:
    r = subprocess.run([sys.executable, str(REPO / "bench" / "null_compare.py"), "--only", "no-such-flight"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "unknown case(s) no-such-flight" in r.stderr and "Traceback" not in r.stderr


def test_reloc_evidence_replays_the_join_rule_and_its_bound_refuses_every_lookalike() -> None:
    """bench/loop_reloc.py --evidence: on every verified candidate of a start's first 2 s, the loop stage's rule (the
    first verified candidate of each keyframe, reloc_min_consistent agreeing keyframes within consistency_window)
    joins where three look-alikes agree first; the bound (every look-alike refused) joins on the true place, later.
    A refused candidate, or agreement spread over more than the window, makes no join."""
    from bench.loop_reloc import _false_edge, _first_join
    from vio.config import VioConfig
    from vio.geometry import make_T

    cfg = VioConfig().loop
    assert (cfg.reloc_min_consistent, cfg.consistency_window) == (3, 5)
    la = {"refused": "", "inliers": 80, "lookalike": True, "correction": [1.5, 0.0, 0.0, 0.0]}
    true = {"refused": "", "inliers": 70, "lookalike": False, "correction": [0.0, 0.02, 0.0, 0.01]}
    refused = {"map_keyframe": 3, "refused": "two-way"}
    kfs = [{"t_s": 0.25 * k, "candidates": c} for k, c in
           enumerate([[la], [la, true], [refused, la, true], [refused, true], [true]])]
    assert _first_join(kfs, cfg, "first") == (0.5, False)
    assert _first_join(kfs, cfg, "oracle") == (0.75, True)
    assert _first_join(kfs[:2], cfg, "first") is None
    # three true keyframes, but the first and the last 6 keyframes apart: out of the consistency window
    spread = [{"t_s": 0.25 * k, "candidates": [true] if k in (0, 1, 7) else [refused]} for k in range(8)]
    assert _first_join(spread, cfg, "oracle") is None
    # the ground-truth test of an edge: within 0.2 m / 3 deg is the place, a texture period off is a look-alike
    G = make_T(np.eye(3), [1.0, 2.0, 0.5])
    assert not _false_edge(G, G, make_T(np.eye(3), [0.1, 0.0, 0.0]))
    assert _false_edge(G, G, make_T(np.eye(3), [1.5, 0.0, 0.0]))


def test_frame_clock_cases_prints_its_table(capsys):
    """bench/frame_clock_cases.py (docs/estimator.md "Frame stamps"): one row per case, and on plain arrival jitter
    the restamped stamps are nearer the exposures than the stamps as given."""
    from bench.frame_clock_cases import CASES, main

    assert main(["--seconds", "20"]) == 0
    rows = [line.split("|")[1:-1] for line in capsys.readouterr().out.splitlines()[2:]]
    assert [r[0].strip() for r in rows] == list(CASES)
    given, restamped = (float(rows[0][k].split("/")[0]) for k in (3, 4))
    assert restamped < 0.3 * given, rows[0]
