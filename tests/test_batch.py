"""`vio batch` (issue 18): local worker processes and a local Ray instance give the same report; a failed flight
is a row with its error; --compare says what changed."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from vio.app.batch import TIMING_FIELDS, compare, run_batch


@pytest.fixture(scope="module")
def flights(tmp_path_factory) -> list[Path]:
    from vio.sim.generate import SimConfig, simulate

    root = tmp_path_factory.mktemp("batch")
    out = []
    for seed in (0, 1):
        simulate(root / f"f{seed}", SimConfig(duration_s=3.0, width=320, height=200, variant="clean", seed=seed,
                                              still_start_s=1.0))
        out.append(root / f"f{seed}")
    (root / "broken").mkdir()
    return [*out, root / "broken"]


def _deterministic(report: dict) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMING_FIELDS} for r in report["flights"]]


def test_local_workers_and_ray_give_the_same_report(flights, tmp_path):
    ray = pytest.importorskip("ray")
    local = run_batch([str(f) for f in flights], tmp_path / "local", workers=2, progress=False)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        on_ray = run_batch([str(f) for f in flights], tmp_path / "ray", workers=2, ray_address="local",
                           progress=False)
    finally:
        ray.shutdown()
    assert _deterministic(local) == _deterministic(on_ray)
    rows = local["flights"]
    assert [r["ok"] for r in rows] == [True, True, False]
    assert "no mav0/ folder" in rows[2]["error"]
    assert all(r["ate_m"] is not None and r["realtime_factor"] > 0 for r in rows[:2])
    assert local["summary"]["failed"] == 1 and local["summary"]["ok"] == 2
    for name in ("f0.tum", "f1.tum"):
        assert (tmp_path / "local" / "traj" / name).read_bytes() == (tmp_path / "ray" / "traj" / name).read_bytes()
    for d in ("local", "ray"):
        for f in ("report.md", "report.json", "report.png"):
            assert (tmp_path / d / f).stat().st_size > 0
    md = (tmp_path / "local" / "report.md").read_text()
    assert "| f0 |" in md and "| broken |" in md and "Summary:" in md
    assert on_ray["engine"] == "ray:local"


def _dies_on_crash(path: str, options: dict) -> dict:
    """replay_flight, but the worker process is killed (as by the kernel's OOM killer) for a flight named crash."""
    import os
    import signal

    from vio.app.batch import replay_flight

    if Path(path).name == "crash":
        os.kill(os.getpid(), signal.SIGKILL)
    return replay_flight(path, options)


def test_a_worker_that_dies_loses_only_its_own_flight(flights, tmp_path, monkeypatch):
    """One flight whose worker is killed broke the process pool, and every flight not finished by then (running
    beside it or waiting its turn) was a row 'worker failed: BrokenProcessPool': the rest of the batch was lost.
    They are run again now, each alone; only the killed flight is a failed row."""
    import vio.app.batch as batch

    monkeypatch.setattr(batch, "replay_flight", _dies_on_crash)
    (tmp_path / "crash").mkdir()
    report = run_batch([str(tmp_path / "crash"), str(flights[0]), str(flights[1])], tmp_path / "out", workers=2,
                       progress=False)
    rows = {r["flight"]: r for r in report["flights"]}
    assert rows["f0"]["ok"] and rows["f1"]["ok"], rows
    assert not rows["crash"]["ok"] and "its process died while replaying this flight" in rows["crash"]["error"]
    assert (tmp_path / "out" / "traj" / "f0.tum").is_file() and (tmp_path / "out" / "traj" / "f1.tum").is_file()


def test_a_compare_file_that_is_no_report_is_refused_before_any_replay(tmp_path, capsys):
    """`--compare` given a binary file was 'internal error: UnicodeDecodeError'; given another JSON (a status file)
    the whole batch ran and then stopped on 'internal error: KeyError: flights', compare.md never written."""
    from vio.app.cli import main

    cases = {"bin.dat": (bytes(range(256)), "not a text file"),
             "status.json": (b'{"state": "running"}', "no list of flights"),
             "odd.json": (b'{"flights": [{"flight": "a", "ok": true, "ate_m": "x", "rpe_pct": null, "resets": 0}]}',
                          "flight 1 lacks its name, ok, ate_m, rpe_pct or resets, or one is of another type")}
    for name, (content, says) in cases.items():
        (tmp_path / name).write_bytes(content)
        capsys.readouterr()
        assert main(["batch", str(tmp_path / "flight"), "-o", str(tmp_path / "out"), "--compare",
                     str(tmp_path / name)]) == 1
        err = capsys.readouterr().err
        assert f"vio batch: error: {tmp_path / name}: not a batch report ({says})" in err, err
        assert "internal error" not in err and not (tmp_path / "out").exists()


def test_compare_names_better_and_worse():
    def rep(ate0, ate1, ok1=True):
        row = {"flight": "a", "ok": True, "error": None, "ate_m": ate0, "rpe_pct": None, "resets": 0,
               "realtime_factor": 3.0}
        row1 = {**row, "flight": "b", "ate_m": ate1, "ok": ok1, "error": None if ok1 else "VioError: x"}
        return {"flights": [row, row1]}

    text = compare(rep(0.10, 0.10, ok1=False), rep(0.20, 0.10))  # a better, b fails now
    assert "1 better" in text and "1 worse" in text
    lines = {ln.split("|")[1].strip(): ln for ln in text.splitlines() if ln.startswith("| a") or ln.startswith("| b")}
    assert lines["a"].rstrip().endswith("better |") and "worse" in lines["b"]
    # matched by name, from another recording: said (day2/f read as day1/f, a review's finding)
    old, new = rep(0.1, 0.1), rep(0.1, 0.1)
    old["flights"][0].update(path="/day1/f", frames=601)
    new["flights"][0].update(path="/day2/f", frames=550)
    assert "another recording? path /day1/f -> /day2/f; frames 601 -> 550" in compare(new, old)
    # a NaN ATE on one side read "same" (NaN compares false with everything; the input review's note): a figure
    # that came back is better, one that went is worse, NaN on both sides the same
    text = compare(rep(0.1, float("nan")), rep(float("nan"), 0.1))
    lines = {ln.split("|")[1].strip(): ln for ln in text.splitlines() if ln.startswith("| a") or ln.startswith("| b")}
    assert lines["a"].rstrip().endswith("better |") and lines["b"].rstrip().endswith("worse |"), text
    assert "1 better, 1 worse, 0 the same" in compare(rep(0.1, float("nan")), rep(float("nan"), 0.1))
    assert "0 better, 0 worse, 2 the same" in compare(rep(float("nan"), 0.1), rep(float("nan"), 0.1))


def test_cli_batch_local_with_compare(flights, tmp_path):
    old = tmp_path / "old"
    old.mkdir()
    (old / "report.json").write_text(json.dumps({"flights": [{"flight": "f0", "ok": False, "error": "x",
                                                              "ate_m": None, "rpe_pct": None, "resets": None,
                                                              "realtime_factor": None}]}))
    r = subprocess.run([sys.executable, "-m", "vio.app.cli", "-q", "batch", str(flights[0]), "--output",
                        str(tmp_path / "new"), "--workers", "1", "--compare", str(old), "--no-progress"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "1 better" in r.stdout
    assert (tmp_path / "new" / "compare.md").is_file()


def test_the_driver_reads_the_inputs_and_writes_the_trajectories(flights, tmp_path):
    """A worker on another machine gets the config and calibration as objects and hands the trajectory back
    as text: it needs to see the flight and nothing else (docs/batch.md, pointing it at a cluster)."""
    from vio import VioError
    from vio.app.batch import replay_flight
    from vio.config import VioConfig

    with pytest.raises(VioError, match="cannot read config"):
        run_batch([str(flights[0])], tmp_path / "x", options={"config": str(tmp_path / "none.toml")}, progress=False)
    row = replay_flight(str(flights[0]), {"cfg": VioConfig(), "calibration": None})
    assert row["ok"], row["error"]
    assert row["tum"].startswith("# timestamp") and len(row["tum"].splitlines()) == row["poses"] + 1
    assert not list(tmp_path.glob("**/*.tum"))


def test_flights_of_one_name_are_two_rows_and_data_notes_show(flights, tmp_path):
    """day1/f and day2/f: one row name for both, and --compare matched them to the last old row; a recording
    with its right camera gone read "ok" with nothing said (a review's findings)."""
    import shutil

    for day in ("day1", "day2"):
        shutil.copytree(flights[0], tmp_path / day / "f")
    shutil.rmtree(tmp_path / "day2" / "f" / "mav0" / "cam1" / "data")
    (tmp_path / "day2" / "f" / "mav0" / "cam1" / "data").mkdir()
    (tmp_path / "day2" / "f" / "mav0" / "cam1" / "data.csv").write_text("#timestamp [ns],filename\n")
    report = run_batch([str(tmp_path / "day1" / "f"), str(tmp_path / "day2" / "f")], tmp_path / "out", workers=1,
                       progress=False)
    names = [r["flight"] for r in report["flights"]]
    assert names == ["f", "f-2"] and all(r["ok"] for r in report["flights"])
    shutil.copytree(flights[0], tmp_path / "day3" / "f-2")  # a flight really called f-2 comes after two f's
    again = run_batch([str(tmp_path / d / n) for d, n in (("day1", "f"), ("day3", "f-2"), ("day2", "f"))],
                      tmp_path / "out2", workers=1, progress=False)
    assert [r["flight"] for r in again["flights"]] == ["f", "f-2", "f-3"]
    assert len(list((tmp_path / "out2" / "traj").glob("*.tum"))) == 3
    # a second batch into a report folder: refused unless --overwrite, which takes the old trajectories too
    from vio import VioError

    with pytest.raises(VioError, match="holds a batch report already"):
        run_batch([str(tmp_path / "day1" / "f")], tmp_path / "out2", workers=1, progress=False)
    run_batch([str(tmp_path / "day1" / "f")], tmp_path / "out2", workers=1, progress=False, overwrite=True)
    assert [p.name for p in (tmp_path / "out2" / "traj").glob("*.tum")] == ["f.tum"]
    assert not report["flights"][0]["notes"] and "no right images" in report["flights"][1]["notes"][0]
    md = (tmp_path / "out" / "report.md").read_text()
    assert "no right images" in md and "with data notes 1" in md
    (tmp_path / "afile").write_text("x")
    from vio import VioError

    with pytest.raises(VioError, match="cannot make the report folder"):
        run_batch([str(flights[0])], tmp_path / "afile", workers=1, progress=False)


def test_frames_skipped_on_the_way_are_a_data_note(flights, tmp_path, capsys):
    """A missing, empty or wrong-size image left a row with no note while `vio replay` said '1 of N frames
    unusable' (a QA sweep); and a report folder inside a flight's mav0/ is refused before any replay."""
    import shutil

    from vio.app.cli import main

    shutil.copytree(flights[0], tmp_path / "f")
    first = sorted((tmp_path / "f" / "mav0" / "cam0" / "data").iterdir())[5]
    first.write_bytes(b"")
    report = run_batch([str(tmp_path / "f")], tmp_path / "out", workers=1, progress=False)
    row = report["flights"][0]
    assert row["ok"] and any("1 of" in n and "frames unusable: 1 image unreadable" in n for n in row["notes"]), row
    assert main(["batch", str(tmp_path / "f"), "-o", str(tmp_path / "f" / "mav0" / "report")]) == 1
    assert "into the recording" in capsys.readouterr().err
    assert not (tmp_path / "f" / "mav0" / "report").exists()


@pytest.mark.parametrize("with_tools", [True, False])
def test_it_prints_the_files_it_wrote(flights, tmp_path, monkeypatch, capsys, with_tools):
    """Without the [tools] extra (no matplotlib) it logged "no plot" and then printed "wrote DIR/report.md,
    report.json, report.png" though there was no report.png (a docs sweep); compare.md, which --compare writes,
    went unsaid."""
    from vio.app.cli import main

    if with_tools:
        pytest.importorskip("matplotlib")
    else:
        monkeypatch.setitem(sys.modules, "matplotlib", None)  # as on a core install: import matplotlib fails
    old = tmp_path / "old"
    old.mkdir()
    (old / "report.json").write_text(json.dumps({"flights": []}))
    out = tmp_path / "new"
    main(["-q", "batch", str(flights[0]), "-o", str(out), "--workers", "1", "--compare", str(old), "--no-progress"])
    said = capsys.readouterr().out.splitlines()[-1]
    png = ", report.png" if with_tools else ""
    assert said == f"wrote {out / 'report.md'}, report.json{png}, compare.md"
    assert (out / "report.png").is_file() == with_tools and (out / "compare.md").is_file()
    assert json.loads((out / "report.json").read_text())["files"] == ["report.md", "report.json"] + \
        (["report.png"] if with_tools else [])


def test_ray_without_the_fleet_extra_is_refused_before_the_old_report_goes(flights, tmp_path, monkeypatch, capsys):
    """`--ray ... --overwrite` without ray removed the old report and trajectories, and only then said "vio batch
    --ray needs the [fleet] extra"; without --overwrite it made the report folder for nothing."""
    from vio.app.cli import main

    old = tmp_path / "old"
    (old / "traj").mkdir(parents=True)
    for name, text in (("report.json", '{"flights": []}'), ("report.md", "kept"), ("traj/f0.tum", "kept")):
        (old / name).write_text(text)
    monkeypatch.setitem(sys.modules, "ray", None)  # as on an install without [fleet]: import ray fails
    for out, more in ((old, ["--overwrite"]), (tmp_path / "new", [])):
        assert main(["-q", "batch", str(flights[0]), "-o", str(out), "--ray", "local", "--no-progress", *more]) == 1
        assert capsys.readouterr().err.strip().splitlines() == [
            "vio batch: error: vio batch --ray needs the [fleet] extra: pip install 'kestrel-vio[fleet]'"]
    assert [(old / n).read_text() for n in ("report.json", "report.md", "traj/f0.tum")] == ['{"flights": []}', "kept",
                                                                                            "kept"]
    assert not (tmp_path / "new").exists()


def test_bags_no_worker_could_replay_are_refused_before_any_work(flights, tmp_path, monkeypatch, capsys):
    """Bags and MCAP files without --calib (or without the [bags] extra) were each replayed, failed and reported one
    by one, after the report folder was made (or, with --overwrite, the old report removed). Refused first now, in
    one line naming them; an MCAP file `vio record` made carries its calibration and is not refused."""
    from vio.app.cli import main
    from vio.io.bag import McapWriter, export_bag
    from vio.io.euroc import EurocDataset
    from vio.types import ImuSample

    ds = EurocDataset(flights[0])
    export_bag(ds, tmp_path / "a.bag", "ros1")
    export_bag(ds, tmp_path / "b.mcap", "mcap")
    with McapWriter(tmp_path / "recorded.mcap", calibration=ds.calibration) as w:
        for ev in ds.events():
            w.write_imu(ev) if isinstance(ev, ImuSample) else w.write_frame(ev)
    old = tmp_path / "old"
    (old / "traj").mkdir(parents=True)
    for name, text in (("report.json", '{"flights": []}'), ("traj/f0.tum", "kept")):
        (old / name).write_text(text)
    bags = [str(tmp_path / n) for n in ("a.bag", "b.mcap", "recorded.mcap")]
    for out, more in ((old, ["--overwrite"]), (tmp_path / "new", [])):
        assert main(["-q", "batch", str(flights[0]), *bags, "-o", str(out), "--no-progress", *more]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "a bag carries no camera-IMU calibration: give one with --calib" in err[0], err
        assert "a.bag, " in err[0] and "b.mcap:" in err[0] and "recorded.mcap" not in err[0], err
    for module in ("rosbags", "mcap"):  # as on an install without [bags] (its modules read here are blocked too)
        with monkeypatch.context() as m:
            for name in [n for n in sys.modules if n == module or n.startswith(f"{module}.")]:
                m.setitem(sys.modules, name, None)
            assert main(["-q", "batch", str(flights[0]), bags[2], "-o", str(old), "--no-progress",
                         "--overwrite"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "needs the [bags] extra: pip install 'kestrel-vio[bags]'" in err[0], err
    assert [(old / n).read_text() for n in ("report.json", "traj/f0.tum")] == ['{"flights": []}', "kept"]
    assert not (tmp_path / "new").exists()
    from vio.app.batch import check_bag_flights

    check_bag_flights([bags[2]], {})  # its own calibration: replayable


def test_a_ray_driver_without_the_bags_extra_hands_bags_to_its_workers(tmp_path, monkeypatch):
    """A Ray cluster's workers read the bags, with their own installs; the driver (a Ray client on a laptop, which
    may not even see the files) needs no [bags] extra, and the up-front check refused such a batch for the driver's
    missing extra. The check stands where the workers run on this machine (local processes, --ray local)."""
    pytest.importorskip("ray")
    import vio.app.batch as batch
    from vio import VioError

    calib = tmp_path / "calib.yaml"
    calib.write_text("")  # read by _load_inputs only: stubbed below
    monkeypatch.setattr(batch, "_load_inputs", lambda options: options)
    submitted: list[list[str]] = []

    def fake_ray(jobs, address, workers, progress):
        submitted.append([path for path, _tum, _opts in jobs])
        return [batch._failed_row(path, "not run here", tum) for path, tum, _opts in jobs]

    monkeypatch.setattr(batch, "_run_ray", fake_ray)
    for name in [n for n in sys.modules if n.split(".")[0] in ("rosbags", "mcap")] + ["rosbags", "mcap"]:
        monkeypatch.setitem(sys.modules, name, None)
    flights = ["/on/the/cluster/a.bag", "/on/the/cluster/b.mcap"]
    batch.run_batch(flights, tmp_path / "remote", ray_address="ray://head:10001", progress=False,
                    options={"calib": [str(calib)]})
    assert submitted == [flights]
    with pytest.raises(VioError, match=r"needs the \[bags\] extra"):
        batch.run_batch(flights, tmp_path / "here", ray_address="local", progress=False,
                        options={"calib": [str(calib)]})
    assert submitted == [flights] and not (tmp_path / "here").exists()
