"""The `vio` command line: help, exit codes, and errors as one line on stderr (no traceback)."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from vio.app import cli
from vio.app.cli import EXIT_CONFIG, EXIT_FAILURE, EXIT_OK, EXIT_USAGE, main


def _vio(*args: str) -> subprocess.CompletedProcess:
    """The real entry point in a fresh interpreter (catches import-time problems main() would hide)."""
    return subprocess.run([sys.executable, "-m", "vio.app.cli", *args], capture_output=True, text=True, timeout=120)


def test_help_lists_the_available_commands():
    r = _vio("--help")
    assert r.returncode == 0 and r.stderr == ""
    for name in ("eval", "config"):
        assert name in r.stdout
    for name, (module, _) in cli.COMMANDS.items():
        if cli._module_available(module):
            assert re.search(rf"^ +{name}\b", r.stdout, re.M), f"{name} missing from vio --help"


def test_config_check_bad_file_in_a_subprocess(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[frontend]\nmax_featurs = 100\n")
    r = _vio("config", "check", str(bad))
    assert r.returncode == EXIT_CONFIG
    assert r.stdout == ""
    assert r.stderr.strip() == (f"vio config: error: {bad}: [frontend]: unknown key 'max_featurs' "
                                "(did you mean 'max_features'?)")


def test_no_command_prints_help(capsys):
    assert main([]) == EXIT_USAGE
    assert "COMMAND" in capsys.readouterr().out


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and "kestrel-vio" in capsys.readouterr().out


def test_unknown_command_and_missing_arguments_are_usage_errors(capsys):
    for argv in (["frobnicate"], ["eval"], ["config"]):
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == EXIT_USAGE
        assert "usage:" in capsys.readouterr().err
    # numeric options out of range: a usage error naming the option, not an internal error part-way (a QA sweep)
    for argv, says in ((["replay", "d", "-o", "t.tum", "--max-frames", "0"], "--max-frames: must be at least 1"),
                       (["calib", "check", "-", "d", "--max-frames", "-3"], "--max-frames: must be at least 1"),
                       (["calib", "time-offset", "d", "--max-offset-ms", "-5"], "must be a positive number"),
                       (["eval", "e.tum", "g", "--run", "0"], "--run: must be at least 1"),
                       # beyond a C int: "internal error: ValueError" in cv2.setNumThreads (a review's finding)
                       (["replay", "d", "--threads", "99999999999"], "--threads: 99999999999 is above 1024"),
                       # "internal error" ValueError / OverflowError, and -5 taken as 0 (a review's finding)
                       (["calib", "imu-noise", "d", "--start", "nan"], "--start: must be seconds from the recording"),
                       (["calib", "imu-noise", "d", "--start", "1e300"], "--start: must be seconds"),
                       (["calib", "imu-noise", "d", "--end", "-5"], "--end: must be seconds"),
                       (["calib", "time-offset", "d", "--max-offset-ms", "1e300"], "--max-offset-ms: must be at most"),
                       (["demo", "--seed", "-1"], "--seed: must be at least 0"),
                       # a hung daemon's last status never went stale: HEALTHY
                       (["status", "--stale-s", "1e300"], "--stale-s: must be at most 3600")):
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == EXIT_USAGE and says in capsys.readouterr().err, argv


def test_config_check_good_file(tmp_path, capsys):
    good = tmp_path / "good.toml"
    good.write_text("[frontend]\nmax_features = 120\n[source]\nkind = 'fake'\n"
                    "[mavlink]\nurl = 'udpout:127.0.0.1:14550'\n")
    assert main(["-q", "config", "check", str(good)]) == EXIT_OK
    out = capsys.readouterr()
    assert out.out.strip() == f"{good}: OK" and out.err == ""


@pytest.mark.parametrize("text, expected", [
    ("[backend]\nlag_s = 0.0\n", "[backend]: 'lag_s' = 0.0 is below the minimum 0.2"),
    ("[backend\n", "not valid TOML"),
    ("[nonsense]\n", "unknown section [nonsense]"),
    # a key above the first [section] header was called 'unknown section [rate_hz]' (a review)
    ("rate_hz = 5\n[source]\nkind = 'fake'\n", "unknown key 'rate_hz' at top level (above any [section] header): "
     "it is a key of [mavlink] and of [view]; move it to the one meant"),
    ("max_features = 500\n", "unknown key 'max_features' at top level (above any [section] header): it is a key of "
     "[frontend]; move it there"),
    ("max_featurs = 500\n", "did you mean [frontend] max_features?"),
    # [[x]] (an array of tables) is a header too: it was an unknown key "above any [section] header", and [[source]]
    # "expected a table of settings, got list"
    ("[[sourcex]]\nkind = 'fake'\n", "unknown section [[sourcex]] (did you mean [source]?)"),
    ("[[source]]\nkind = 'fake'\n", "[[source]] is a list of sections; write [source] (one pair of brackets)"),
    ("[backend]\nlag_s = nan\n", "[backend]: 'lag_s' = nan is not a number; give one from 0.2 to 60"),  # was 'below'
    ("[loop]\noutput = 'jump'\n", "[loop] output = 'jump' needs the loop stage, which is off"),
    # what `vio run` checks at start too (a review: these passed the check, and vio run retried them forever)
    ("[source]\nkind = 'euroc'\n", "needs 'dataset'"),
    ("[mavlink]\nurl = 'udp_out:127.0.0.1:14550'\n", "expected udpout:HOST:PORT"),
    ("[mavlink]\nurl = 'udpout:127.0.0.1'\n", "with a port 1-65535"),
    ("[mavlink]\nurl = 'udpout:127.0.0.1:146800'\n", "with a port 1-65535"),
    ("[mavlink]\nurl = '/dev/ttyAMA0:9216OO'\n", "baud rate"),
    ("[mavlink]\nurl = '/dev/ttyAMA0:0'\n", "baud rate '0' is not a positive whole number"),  # a QA walk-through
    ("[mavlink]\nurl = 'udpout:127.0.0.1:14550'\nmessages = ['ODOMETRY2']\n", "unknown ['ODOMETRY2']"),
    ("[mavlink]\nurl = 'udpout:127.0.0.1:14550'\nmessages = ['VISION_POSITION_ESTIMATE']\nlost_output = 'quality0'\n",
     "needs messages = ['ODOMETRY']"),
    ("[source]\nkind = 'fake'\ncalibration = '/nonexistent/calib.yaml'\n", "calib.yaml"),
    # the daemon started, the estimator thread died on it, unhealthy with no exit (a QA sweep)
    ("[loop]\nenabled = true\nvocabulary = '/nonexistent/vocab.npz'\n", "[loop] vocabulary: /nonexistent/vocab.npz"),
    ("[frontend]\nklt_window_px = 20\n", "must be odd"),  # ran as 21, unsaid
    # a QA sweep of the daemon: every state sent (and fused) twice; the pose log and the status in one file
    ("[mavlink]\nurl = 'udpout:127.0.0.1:14550'\nmessages = ['ODOMETRY', 'ODOMETRY']\n", "ODOMETRY named twice"),
    ("[source]\nkind = 'fake'\n[run]\nstatus_file = '/tmp/kv.json'\ntrajectory_file = '/tmp/kv.json'\n",
     "[run] trajectory_file and [run] status_file would be written to the same file"),
    ("[source]\nkind = 'fake'\nimu = 'mavlink'\nmavlink_imu_url = '/dev/ttyS0:921600'\n[mavlink]\nurl = '/dev/ttyS0'\n",
     "are one serial device"),
    ("[backend]\nkeyframe_min_interval_s = 1.0\nkeyframe_max_interval_s = 0.4\n", "must not exceed"),
    # a QA walk-through: an internal error (ValueError from float('a')), and a bool taken as 1 degree
    ("[mavlink]\nmount = 'rpy'\nmount_rpy_deg = ['a', 0, 0]\n", "[mavlink] mount_rpy_deg must be 3 finite numbers"),
    ("[mavlink]\nmount = 'rpy'\nmount_rpy_deg = [true, 0, 0]\n", "[mavlink] mount_rpy_deg must be 3 finite numbers"),
    ("[mavlink]\nmount_offset_m = [0.1, nan, 0]\n", "[mavlink] mount_offset_m must be 3 finite numbers"),
    # an integrator's walk-through: a serial IMU port that could never open passed, and was retried for ever; a baud
    # rate that cannot carry the IMU's rate lost frames all flight; one port for the IMU and the autopilot
    ("[source]\nkind = 'fake'\nimu = 'serial'\nserial_port = '/dev/ttyUSB0:921600'\n",
     "[source] serial_port = '/dev/ttyUSB0:921600' names the device only (the baud rate is serial_baud): serial_port = "
     "'/dev/ttyUSB0', serial_baud = 921600"),
    # one parser with the MAVLink link's (vio.serial_url): a tail that is no baud rate on a device of no such name
    # passed the hand-made split and was retried for ever
    ("[source]\nkind = 'fake'\nimu = 'serial'\nserial_port = '/dev/ttyUSB0:abc'\n",
     "[source] serial_port = '/dev/ttyUSB0:abc': no device of that name, and 'abc' after the colon is no baud rate "
     "(that is serial_baud): serial_port = '/dev/ttyUSB0'?"),
    ("[source]\nkind = 'fake'\nimu = 'serial'\nserial_port = 'ttyACM0'\n",
     "[source] serial_port = 'ttyACM0' is not a device path: give it whole, e.g. '/dev/ttyACM0'"),
    ("[source]\nkind = 'fake'\nimu = 'serial'\nserial_baud = 115200\n", "[source] serial_baud = 115200 carries at "
     "most 288 IMU frames a second (40 bytes of 10 bits each), fewer than serial_imu_rate_hz = 400"),
    ("[source]\nkind = 'fake'\nimu = 'serial'\nserial_port = '/dev/ttyAMA0'\n[mavlink]\nurl = '/dev/ttyAMA0:921600'\n",
     "[source] serial_port = '/dev/ttyAMA0' is the autopilot's port ([mavlink] url = '/dev/ttyAMA0:921600'): a serial "
     "IMU needs a port of its own; for the flight controller's IMU set [source] imu = 'mavlink'"),
])
def test_config_check_bad_files(tmp_path, capsys, text, expected):
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    assert main(["-q", "config", "check", str(bad)]) == EXIT_CONFIG
    out = capsys.readouterr()
    assert out.out == ""
    assert out.err.startswith(f"vio config: error: {bad}: ") and expected in out.err
    assert "Traceback" not in out.err and len(out.err.strip().splitlines()) == 1


def test_config_check_missing_file(tmp_path, capsys):
    assert main(["-q", "config", "check", str(tmp_path / "none.toml")]) == EXIT_CONFIG
    assert "none.toml: cannot read config" in capsys.readouterr().err


def test_broken_command_module_does_not_take_the_cli_down(tmp_path, monkeypatch, capsys):
    (tmp_path / "kestrel_broken_cmd.py").write_text("raise ImportError('needs libfoo')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(cli.COMMANDS, "broken", ("kestrel_broken_cmd", "a command whose module fails"))
    assert main(["-q", "config", "show"]) == EXIT_OK  # the others still work
    capsys.readouterr()
    assert main(["broken"]) == EXIT_FAILURE
    assert "vio broken: this command is unavailable" in capsys.readouterr().err


def test_unexpected_error_is_one_line_with_a_hint(monkeypatch, capsys):
    import vio.app.replay

    def boom(args):
        raise RuntimeError("matrix not\npositive definite")

    monkeypatch.setattr(vio.app.replay, "run", boom)
    assert main(["-q", "replay", "somewhere"]) == EXIT_FAILURE
    err = capsys.readouterr().err
    assert err == ("vio replay: internal error: RuntimeError: matrix not positive definite "
                   "(`vio -v replay ...` shows the traceback)\n")
    assert main(["-v", "replay", "somewhere"]) == EXIT_FAILURE
    err = capsys.readouterr().err
    assert "Traceback" in err and err.strip().endswith("vio replay: internal error: RuntimeError: matrix not "
                                                      "positive definite")


def test_interrupt_is_130(monkeypatch, capsys):
    import vio.app.replay

    def stop(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(vio.app.replay, "run", stop)
    assert main(["-q", "replay", "somewhere"]) == 130
    assert capsys.readouterr().err == "vio replay: interrupted\n"


def test_a_place_that_cannot_be_written_is_one_line_not_an_internal_error(tmp_path, capsys):
    """`vio simulate` / `record` / `calib import` into a read-only folder said "internal error: OSError ..." (a
    review's finding): an OSError that is the user's to fix (read-only, full, no permission, not a folder) is one
    error line naming the place, exit 1."""
    from vio.app.cli import main

    (tmp_path / "afile").write_text("x")
    assert main(["simulate", str(tmp_path / "afile" / "out"), "--duration", "1", "--size", "376x240"]) == 1
    err = capsys.readouterr().err
    assert "internal error" not in err and f"{tmp_path / 'afile'}" in err and err.count("\n") == 1, err
    # `vio demo --keep` simulated and replayed the whole flight before finding it could not write there
    for keep, says in ((tmp_path / "afile", "is a file, not a folder"),
                       (tmp_path / "afile" / "sub", "cannot make the folder")):
        assert main(["demo", "--keep", str(keep)]) == 1
        out = capsys.readouterr()
        assert f"--keep {keep}: {says}" in out.err and "simulating" not in out.out, out


def test_config_check_reads_a_euroc_source_as_vio_replay_would(tmp_path, capsys, v101_path):
    """A EuRoC source without its IMU file, or with a calibration for another image size, passed `config check`,
    and the daemon retried it forever (a review's finding): both are refused at start, naming the dataset."""
    import shutil

    broken = tmp_path / "noimu"
    (broken / "mav0" / "imu0").mkdir(parents=True)
    for c in ("cam0", "cam1"):
        (broken / "mav0" / c).symlink_to(v101_path / "mav0" / c)
    shutil.copy(v101_path / "mav0" / "imu0" / "sensor.yaml", broken / "mav0" / "imu0")
    half = tmp_path / "half.yaml"
    assert main(["-q", "calib", "import", "euroc", str(v101_path), "-o", str(tmp_path / "full.yaml")]) == 0
    text = (tmp_path / "full.yaml").read_text()
    import yaml

    c = yaml.safe_load(text)
    for cam in ("cam0", "cam1"):  # the same camera calibrated at half the size
        c[cam]["intrinsics"] = [v / 2 for v in c[cam]["intrinsics"]]
        c[cam]["resolution"] = [376, 240]
    half.write_text(yaml.safe_dump(c))
    capsys.readouterr()
    for src, says in ((f"dataset = '{broken}'", "imu0/data.csv"),
                      (f"dataset = '{v101_path}'\ncalibration = '{half}'", "752x480")):
        cfg = tmp_path / "c.toml"
        cfg.write_text(f"[source]\nkind = 'euroc'\n{src}\n")
        assert main(["-q", "config", "check", str(cfg)]) == EXIT_CONFIG
        err = capsys.readouterr().err
        assert "[source] dataset = " in err and says in err and "Traceback" not in err, err
    cfg.write_text(f"[source]\nkind = 'euroc'\ndataset = '{v101_path}'\n")
    assert main(["-q", "config", "check", str(cfg)]) == EXIT_OK


def test_quiet_means_no_progress_bar_either(tmp_path):
    """`-q` is "warnings and errors only", but simulate / replay drew their progress bars into logs and CI output
    unless --no-progress was given too."""
    flight = tmp_path / "f"
    r = _vio("-q", "simulate", str(flight), "--duration", "1", "--size", "188x120")
    assert r.returncode == 0 and r.stderr == "", r.stderr
    r = _vio("-q", "replay", str(flight), "-o", str(tmp_path / "t.tum"))
    assert "frame/s" not in r.stderr and "%|" not in r.stderr, r.stderr


def test_overwrite_map_without_a_map_to_write_is_a_usage_error(tmp_path, capsys):
    """`--overwrite-map` without `--save-map` (or [map] save) was accepted and did nothing (a QA walk-through):
    one line, exit 2, before the recording is read; with [map] save it is the flag it documents."""
    missing = str(tmp_path / "no_such_flight")
    assert main(["replay", missing, "-o", str(tmp_path / "t.tum"), "--overwrite-map"]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert err.strip() == ("vio replay: error: --overwrite-map: there is no map to write; give --save-map FILE "
                           "(or [map] save)")
    assert not (tmp_path / "t.tum").exists()
    cfg = tmp_path / "map.toml"
    cfg.write_text(f"[map]\nsave = '{tmp_path / 'room.npz'}'\n")
    assert main(["replay", missing, "--config", str(cfg), "--overwrite-map"]) == EXIT_FAILURE  # the missing data
    assert "--overwrite-map" not in capsys.readouterr().err


def test_option_mistakes_are_usage_errors_in_every_command(tmp_path, capsys):
    """An option value out of range or options that contradict each other exit 2 (argparse's usage-error code),
    in one line, before any work. A QA walk-through found them exiting 1 like a data problem (--workers 0 even ran
    on every CPU, --profile bogus simulated nothing after saying it would, --calibration with --calib ignored
    --calib)."""
    for argv, says in ((["batch", "f", "-o", str(tmp_path / "r"), "--workers", "0"], "--workers: must be at least 1"),
                       (["eval", "e.tum", "g", "--max-dt-ms", "0"], "--max-dt-ms: must be a positive number"),
                       (["eval", "e.tum", "g", "--max-dt-ms", "1e300"], "--max-dt-ms: must be at most 10000"),
                       (["eval", "e.tum", "g", "--max-gap-s", "-1"], "--max-gap-s: must be a positive number"),
                       (["record", str(tmp_path / "o"), "--duration", "0"], "--duration: must be a positive number"),
                       # an internal OverflowError after the recording had started (and a dataset folder made)
                       (["record", str(tmp_path / "o"), "--duration", "1e300"], "--duration: must be at most 1e+07"),
                       (["demo", "--profile", "bogus"], "invalid choice: 'bogus'"),
                       (["status", "--stale-s", "nan"], "--stale-s: must be a positive number"),
                       (["status", "--stale-s", "inf"], "--stale-s: must be a positive number")):
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == EXIT_USAGE and says in capsys.readouterr().err, argv
    calib = tmp_path / "c.yaml"
    calib.write_text("cam0: {}\n")
    for argv, says in ((["demo", "--duration", "1"], "--duration 1.0: 5 to 3600 s"),
                       (["demo", "--duration", "nan"], "--duration nan: 5 to 3600 s"),
                       (["demo", "--duration", "1e9"], "--duration 1000000000.0: 5 to 3600 s"),
                       (["replay", str(tmp_path), "--calibration", str(calib), "--calib", str(calib)],
                        "--calibration and --calib both give the calibration: give one"),
                       (["replay", str(tmp_path), "--calib", str(calib), str(calib)],
                        "--calib: our calibration is one"),
                       (["replay", str(tmp_path), "--view", str(tmp_path / "v.png")], "is an .rrd file"),
                       (["calib", "import", "euroc", str(tmp_path), "-o", str(tmp_path / "o.yaml"), "--size", "64x40"],
                        "--size: only a depthai calibration is rescaled"),
                       # named by the option, not SimConfig's field ("duration_s = -3.0 is outside"), and exit 2
                       (["simulate", str(tmp_path / "s"), "--duration", "-3"], "--duration -3.0 is outside [0.1, 3600"),
                       (["simulate", str(tmp_path / "s"), "--size", "10x10"], "--size width 10 is outside"),
                       (["simulate", str(tmp_path / "s"), "--right-dropout", "1:x"], "expected START:LENGTH"),
                       # internal errors (numpy's ValueError / OverflowError) or taken unsaid before (a review's)
                       (["simulate", str(tmp_path / "s"), "--seed", "-1"], "--seed -1 is not a whole number >= 0"),
                       (["simulate", str(tmp_path / "s"), "--scene-seed", "-3"], "--scene-seed -3 is not a whole"),
                       (["simulate", str(tmp_path / "s"), "--aliasing", "nan"], "--aliasing nan is outside [0, 1000]"),
                       (["simulate", str(tmp_path / "s"), "--aliasing", "inf"], "--aliasing inf is outside"),
                       (["simulate", str(tmp_path / "s"), "--aliasing", "-1"], "--aliasing -1.0 is outside"),
                       (["simulate", str(tmp_path / "s"), "--recorded-start", "nan"],
                        "--recorded-start nan is negative or not a number"),
                       # exit 1 after the folder was made and the scene built, before
                       (["simulate", str(tmp_path / "s"), "--scene", "hall", "--aliasing", "1.5"],
                        "--aliasing is for the room scene only")):
        assert main(argv) == EXIT_USAGE, argv
        err = capsys.readouterr().err
        assert says in err and len(err.strip().splitlines()) == 1, (argv, err)


def test_a_serial_device_named_by_its_usb_port_is_a_mavlink_url(tmp_path):
    """udev's /dev/serial/by-path/ names (the way to say which USB port when two adapters look alike) hold colons:
    `[mavlink] url = "/dev/serial/by-path/platform-xhci-hcd.1-usb-0:2:1.0:921600"` was refused, split at its first
    colon, as "baud rate '2:1.0:921600' is not a positive whole number" (exit 3, with or without a baud rate; an
    integrator's walk-through). The baud rate is what follows the last colon, and only when it is a number."""
    import os
    import pty

    from drivers.mavlink_link import open_connection
    from vio.app.endpoint_lock import output_endpoint_key
    from vio.serial_url import split_serial_url

    by_path = "/dev/serial/by-path/platform-xhci-hcd.1-usb-0:2:1.0"
    for url in (by_path, f"{by_path}:921600", f"{by_path}-port0:57600"):
        cfg = tmp_path / "c.toml"
        cfg.write_text(f"[source]\nkind = 'fake'\n[mavlink]\nurl = '{url}'\ncounter_file = ''\n"
                       f"[run]\nstatus_file = '{tmp_path / 'st.json'}'\n")
        r = _vio("config", "check", str(cfg))
        assert r.returncode == EXIT_OK and r.stderr == "", (url, r.stderr)
    # a serial IMU's port is read by the same parser: its by-path name keeps its colons
    cfg.write_text(f"[source]\nkind = 'fake'\nimu = 'serial'\nserial_port = '{by_path}'\n"
                   f"[run]\nstatus_file = '{tmp_path / 'st.json'}'\n")
    r = _vio("config", "check", str(cfg))
    assert r.returncode == EXIT_OK and r.stderr == "", r.stderr
    assert split_serial_url(f"{by_path}:921600") == (by_path, "921600") and split_serial_url(by_path) == (by_path, "")
    assert split_serial_url("/dev/ttyAMA0:921600") == ("/dev/ttyAMA0", "921600")
    assert split_serial_url("/dev/ttyAMA0:9216OO") == ("/dev/ttyAMA0", "9216OO")  # still a bad baud rate (above)
    # by-id names may hold colons too (an ESP32's serial number is its MAC address), and may not exist yet at start
    by_id = "/dev/serial/by-id/usb-Espressif_USB_JTAG_serial_debug_unit_F4:12:FA:5A:B2:C8-if00"
    assert split_serial_url(by_id) == (by_id, "") and split_serial_url(f"{by_id}:921600") == (by_id, "921600")
    cfg.write_text(f"[source]\nkind = 'fake'\nimu = 'serial'\nserial_port = '{by_id}'\n"
                   f"[run]\nstatus_file = '{tmp_path / 'st.json'}'\n")
    r = _vio("config", "check", str(cfg))
    assert r.returncode == EXIT_OK and r.stderr == "", r.stderr
    # a port that ends in a colon (a baud rate left out) can never open: refused
    cfg.write_text(f"[source]\nkind = 'fake'\nimu = 'serial'\nserial_port = '/dev/ttyUSB0:'\n"
                   f"[run]\nstatus_file = '{tmp_path / 'st.json'}'\n")
    r = _vio("config", "check", str(cfg))
    assert r.returncode == EXIT_CONFIG and "serial_port = '/dev/ttyUSB0:'" in r.stderr, r.stderr
    # the device opened is the port's, at the baud rate given: a pty behind a link named as udev names it
    master, slave = pty.openpty()
    try:
        link = tmp_path / "pci-0000:00:14.0-usb-0:2:1.0"
        link.symlink_to(os.ttyname(slave))
        url = f"/dev/../{link}:115200"
        conn = open_connection(url, source_system=1)
        try:
            assert conn.port.port == f"/dev/../{link}" and conn.port.baudrate == 115200
            assert output_endpoint_key(url) == output_endpoint_key(f"/dev/../{link}") == \
                f"serial:{os.path.realpath(os.ttyname(slave))}"
        finally:
            conn.close()
    finally:
        os.close(master)
        os.close(slave)


def test_a_path_written_with_a_tilde_is_refused_not_made_in_the_working_folder(tmp_path):
    """`record_dir = "~/records"` passed `vio config check`, and `vio run` recorded into a folder named '~' in its
    working directory (nothing expands '~' but a shell; an integrator's walk-through); `calibration = "~/c.yaml"` said
    'No such file' of a file the user's shell shows. Each path key starting with '~' is refused, with the expansion
    meant."""
    import os

    for section, key in (("run", "record_dir"), ("source", "calibration"), ("run", "trajectory_file"),
                         ("map", "save")):
        cfg = tmp_path / "c.toml"
        cfg.write_text(f"[{section}]\n{key} = '~/kestrel/x'\n")
        r = subprocess.run([sys.executable, "-m", "vio.app.cli", "run", "--config", str(cfg)], capture_output=True,
                           text=True, timeout=120, cwd=tmp_path)
        assert r.returncode == EXIT_CONFIG, (key, r.stderr)
        assert r.stderr.strip() == (f"vio run: configuration error: {cfg}: [{section}] {key} = '~/kestrel/x': '~' is "
                                    "not expanded in a configuration (the service's home is not yours either): give "
                                    f"the whole path, e.g. {os.path.expanduser('~/kestrel/x')!r}"), r.stderr
        assert not (tmp_path / "~").exists()


def test_a_path_over_the_file_system_s_name_limit_is_one_line_in_every_command(tmp_path, capsys):
    """A file or folder name over 255 bytes met the file system's ENAMETOOLONG in whichever look-up came first:
    `vio replay`, `batch`, `eval`, `calib import / imu-noise / check`, `loop train-vocab`, `simulate --imu-from`
    each ended in "internal error: OSError" (a review's finding). One line naming the path now, exit 1."""
    long = str(tmp_path / ("a" * 300))
    for argv in (["replay", long, "-o", str(tmp_path / "t.tum")], ["replay", str(tmp_path), "-o", long + ".tum"],
                 ["batch", long, "-o", str(tmp_path / "r")], ["eval", long, str(tmp_path)],
                 ["calib", "imu-noise", long], ["calib", "import", "euroc", long, "-o", str(tmp_path / "c.yaml")],
                 ["calib", "check", "-", long], ["loop", "train-vocab", str(tmp_path), "-o", long + ".npz"],
                 ["simulate", str(tmp_path / "s"), "--imu-from", long]):
        assert main(argv) != 0, argv
        err = capsys.readouterr().err
        assert "File name too long" in err and "internal error" not in err, (argv, err)
        assert len(err.strip().splitlines()) == 1, (argv, err)


def test_a_file_nested_thousands_deep_is_one_line_not_an_internal_error(tmp_path, capsys):
    """A configuration, calibration, status file or batch report nested 100000 deep (a damaged or hostile file)
    ended in "internal error: RecursionError" in tomllib / PyYAML / json (a review's finding)."""
    deep = "[" * 100000 + "]" * 100000
    (tmp_path / "c.toml").write_text(f"[mavlink]\nmount_rpy_deg = {deep}\n")
    (tmp_path / "c.yaml").write_text(f"cam0: {deep}\n")
    (tmp_path / "rep").mkdir()
    (tmp_path / "rep" / "report.json").write_text(f'{{"rows": {deep}}}')
    (tmp_path / "status.json").write_text(f'{{"state": {deep}}}')
    for argv, says in ((["config", "check", str(tmp_path / "c.toml")], "not a configuration (nested too deep"),
                       (["calib", "show", str(tmp_path / "c.yaml")], "not a calibration (nested too deep"),
                       (["batch", str(tmp_path), "-o", str(tmp_path / "r"), "--compare", str(tmp_path / "rep")],
                        "not a batch report (nested too deep"),
                       (["status", "--file", str(tmp_path / "status.json")], "nested too deep to be a status file")):
        assert main(argv) != 0, argv
        captured = capsys.readouterr()
        err = captured.err + captured.out
        assert says in err and "internal error" not in err, (argv, err)


def test_an_empty_path_is_a_usage_error_not_a_missing_option_or_the_working_folder(tmp_path, capsys, monkeypatch):
    """An empty path (`vio replay D -o "$OUT"` with OUT unset) was taken as not given (no trajectory, exit 0;
    `--calibration ""` flew the dataset's own) or as the working folder (`vio simulate ""` wrote a dataset into it,
    `vio batch F -o ""` its report) (a review's finding): a usage error naming the option now."""
    monkeypatch.chdir(tmp_path)
    for argv, option in ((["replay", "d", "-o", ""], "--output/-o"), (["replay", "d", "--stats", ""], "--stats"),
                         (["replay", "d", "--calibration", ""], "--calibration"), (["replay", ""], "dataset"),
                         (["replay", "d", "--load-map", ""], "--load-map"),
                         (["eval", "e", "g", "--json", ""], "--json"), (["simulate", ""], "OUT"),
                         (["batch", "f", "-o", ""], "--output/-o"),
                         # vio record "" recorded into the working folder; status --file "" read the default one
                         (["record", "", "--source", "fake", "--duration", "1"], "out"),
                         (["status", "--file", ""], "--file"),
                         # replayed without sending anything / showing anything, exit 0
                         (["replay", "d", "--mavlink", ""], "--mavlink"), (["replay", "d", "--view", ""], "--view")):
        with pytest.raises(SystemExit) as e:
            main(argv)
        err = capsys.readouterr().err
        assert e.value.code == EXIT_USAGE and f"argument {option}: " in err and "shell variable not set" in err, \
            (argv, err)
    assert list(tmp_path.iterdir()) == []


def test_calib_format_without_calib_or_of_no_format_is_a_usage_error(tmp_path, capsys):
    """`vio replay D --calib-format kalibr` without --calib was ignored, unsaid (the dataset's own calibration flown),
    and `--calib-format bogus` was exit 1 listing the formats without 'project', the default. An empty --left-topic
    (a shell variable not set) was read as not given."""
    for argv, says in ((["replay", str(tmp_path), "--calib-format", "kalibr"],
                        "--calib-format kalibr: there is no --calib to read"),
                       (["replay", str(tmp_path), "--calib", "c.yaml", "--calib-format", "bogus"],
                        "invalid choice: 'bogus' (choose from 'project', 'kalibr', 'euroc', 'opencv', 'depthai')"),
                       (["batch", str(tmp_path), "-o", str(tmp_path / "o"), "--calib-format", "kalibr"],
                        "--calib-format kalibr: there is no --calib to read"),
                       # read as not given: the [bag] default topic, unsaid
                       (["replay", str(tmp_path), "--left-topic", ""], "argument --left-topic: empty"),
                       (["batch", str(tmp_path), "-o", str(tmp_path / "o"), "--imu-topic", " "],
                        "argument --imu-topic: empty")):
        try:
            code = main(argv)
        except SystemExit as e:  # argparse's own usage errors
            code = e.code
        assert code == EXIT_USAGE and says in capsys.readouterr().err, argv
