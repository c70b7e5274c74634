"""The extras: a core install runs `vio demo` without them, and a missing one is named in one line.

A missing module is simulated by `sys.modules[name] = None`, which makes `import name` raise ImportError
as on a machine without it; the CLI cases run in a subprocess so the block cannot leak into other tests."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vio.extras import MissingExtra

ROOT = Path(__file__).resolve().parents[1]
EXTRA_MODULES = ("depthai", "serial", "allantools", "matplotlib")


def _vio_without(blocked: tuple[str, ...], *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    code = ("import sys\n"
            f"for m in {blocked!r}: sys.modules[m] = None\n"
            "from vio.app.cli import main\n"
            "rc = main(sys.argv[1:])\n"
            f"leaked = sorted(m for m in {blocked!r} if sys.modules.get(m) is not None)\n"
            "assert not leaked, leaked\n"
            "sys.exit(rc)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env,
                          timeout=timeout)


def _one_line_naming(stderr: str, extra: str) -> None:
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, stderr
    assert f"needs the [{extra}] extra: pip install 'kestrel-vio[{extra}]'" in lines[0], lines[0]


def test_imu_noise_without_allantools_names_the_tools_extra(tmp_path):
    rng = np.random.default_rng(0)
    n = 200 * 30
    t = 10**18 + np.arange(n) * 5_000_000
    data = np.column_stack([t, 1e-3 * rng.standard_normal((n, 3)), [0, 0, 9.81] + 1e-2 * rng.standard_normal((n, 3))])
    csv = tmp_path / "imu.csv"
    np.savetxt(csv, data, delimiter=",", fmt=["%d"] + ["%.9f"] * 6,
               header="timestamp [ns],w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z")
    r = _vio_without(("allantools",), "-q", "calib", "imu-noise", str(csv), "--output", str(tmp_path / "n.yaml"))
    assert r.returncode == 1, r.stdout + r.stderr
    _one_line_naming(r.stderr, "tools")
    assert "vio calib" in r.stderr


def test_demo_needs_no_extra():
    """The README's first command, `pip install -e . && vio demo`, on a core install."""
    r = _vio_without(EXTRA_MODULES, "-q", "demo", "--duration", "5", timeout=300)
    assert r.returncode == 0, r.stderr
    # -q: warnings and errors only (the simulation's and the replay's progress bars were drawn all the same)
    assert "frame/s" not in r.stderr and "rendering" not in r.stderr, r.stderr[-500:]


def test_help_lists_the_commands_without_extras():
    r = _vio_without(EXTRA_MODULES, "--help")
    assert r.returncode == 0, r.stderr
    assert "replay" in r.stdout and "simulate" in r.stdout and "calib" in r.stdout


@pytest.fixture
def blocked(monkeypatch):
    def block(*names: str) -> None:
        for name in names:
            monkeypatch.setitem(sys.modules, name, None)
    return block


def test_oak_source_without_depthai_names_the_oak_extra(blocked):
    from drivers.source import open_source
    from vio.config import SourceConfig

    blocked("depthai")
    src = open_source(SourceConfig(kind="oak", imu="oak"))
    with pytest.raises(MissingExtra, match=r"\[source\] kind = \"oak\" needs the \[oak\] extra: "
                                           r"pip install 'kestrel-vio\[oak\]'"):
        src.start()
    src.stop()


def test_depthai_calibration_without_depthai_names_the_oak_extra(blocked):
    from calib.importers import import_calibration

    blocked("depthai")
    with pytest.raises(MissingExtra, match=r"needs the \[oak\] extra"):
        import_calibration("depthai", [ROOT / "tests" / "data" / "depthai_calib.json"])


def test_serial_imu_without_pyserial_names_the_serial_extra(blocked):
    from drivers.serial_imu import _default_serial_factory

    blocked("serial")
    with pytest.raises(MissingExtra, match=r"\[source\] imu = \"serial\" needs the \[serial\] extra: "
                                           r"pip install 'kestrel-vio\[serial\]'"):
        _default_serial_factory("/dev/null", 921600, 0.1)


@pytest.mark.parametrize("module", ["matplotlib", "matplotlib.pyplot"])
def test_plots_without_matplotlib_name_the_tools_extra(blocked, tmp_path, module):
    from calib.time_offset import plot_time_offset

    blocked(module)
    with pytest.raises(MissingExtra, match=r"needs the \[tools\] extra: pip install 'kestrel-vio\[tools\]'"):
        plot_time_offset(None, tmp_path / "x.png")  # fails at the import, before the estimate is read


def test_pyproject_extras_and_one_version():
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    project = meta["project"]
    assert "version" not in project and "version" in project["dynamic"]
    assert meta["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "vio.__version__"}
    core = " ".join(project["dependencies"])
    extras = project["optional-dependencies"]
    from vio.extras import EXTRAS

    for module, extra in EXTRAS.items():
        dist = {"serial": "pyserial"}.get(module, module)
        assert dist not in core.lower(), f"{dist} must be in the [{extra}] extra only"
        assert any(d.lower().startswith(dist) for d in extras[extra]), (dist, extra)
    assert any(d.startswith("kestrel-vio[") and all(e in d for e in ("oak", "serial", "tools"))
               for d in extras["dev"])
    assert "gtsam>=4.3" in core


@pytest.mark.parametrize("module", ["rosbags.typesys", "mcap.reader"])
def test_bag_replay_without_rosbags_or_mcap_names_the_bags_extra(blocked, tmp_path, module):
    from vio.calibration import StereoCalibration
    from vio.io.bag import BagDataset

    bag = tmp_path / "flight.mcap"
    bag.write_bytes(b"")
    blocked(module)
    with pytest.raises(MissingExtra, match=r"needs the \[bags\] extra: pip install 'kestrel-vio\[bags\]'"):
        BagDataset(bag, StereoCalibration.__new__(StereoCalibration))


def test_replay_view_without_rerun_names_the_view_extra_and_keeps_an_old_trajectory(tmp_path):
    """The live view is asked for before any output file is opened: a missing extra must not cost the
    trajectory file of an earlier replay."""
    flight = tmp_path / "flight"
    r = _vio_without((), "-q", "simulate", str(flight), "--duration", "2", "--size", "188x120", "--no-progress")
    assert r.returncode == 0, r.stderr
    old = tmp_path / "old.tum"
    old.write_text("1.0 0 0 0 0 0 0 1\n")
    r = _vio_without(("rerun",), "-q", "replay", str(flight), "-o", str(old), "--view", str(tmp_path / "x.rrd"),
                     "--no-progress")
    assert r.returncode == 1, r.stdout + r.stderr
    _one_line_naming(r.stderr, "view")
    assert old.read_text() == "1.0 0 0 0 0 0 0 1\n"


def test_replay_view_without_rerun_is_refused_before_the_recording_is_opened(blocked, tmp_path, monkeypatch, capsys):
    """`vio replay --view` opened and read the recording (a bag: all its IMU and stamps), and loaded the map, before
    it asked for the [view] extra; now asked first, as --loop-plot asks for the [tools] extra."""
    import vio.app.replay as replay_mod
    from vio.app.cli import main

    def never(*a, **k):
        raise AssertionError("the recording was opened before the view was checked")

    monkeypatch.setattr(replay_mod, "open_dataset", never)
    blocked("rerun")
    for view in ([], [str(tmp_path / "x.rrd")]):  # serve, and a recording
        assert main(["-q", "replay", str(tmp_path / "flight"), "--view", *view, "--no-progress"]) == 1
        _one_line_naming(capsys.readouterr().err, "view")


@pytest.mark.parametrize("section, module, extra", [('kind = "oak"', "depthai", "oak"),
                                                    ('kind = "fake"\nimu = "serial"', "serial", "serial")])
def test_config_check_and_run_refuse_a_source_whose_extra_is_missing(tmp_path, section, module, extra):
    """vio run retried such a source forever ("degraded", unseen by systemd) while config check said OK."""
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"[source]\n{section}\n")
    for args in (("config", "check", str(cfg)), ("run", "--config", str(cfg))):
        r = _vio_without((module,), "-q", *args, timeout=60)
        assert r.returncode == 3, r.stdout + r.stderr
        assert f"needs the [{extra}] extra" in r.stderr and "Traceback" not in r.stderr


def test_record_with_a_serial_imu_without_its_extra_stops_at_once(tmp_path):
    """`vio record --config C` with `imu = "serial"` and no pyserial (docs/serial-imu.md's bench test on a plain
    install) retried the port for the whole --duration, recorded the cameras alone and only then failed (exit 1, a
    health dump); the OAK's extra was asked for at once. Now both are, before anything is written."""
    cfg = tmp_path / "c.toml"
    cfg.write_text('[source]\nkind = "fake"\nimu = "serial"\nserial_port = "/dev/ttyUSB0"\nwidth = 320\n'
                   "height = 200\n")
    out = tmp_path / "rec"
    r = _vio_without(("serial",), "-q", "record", str(out), "--duration", "3", "--config", str(cfg), timeout=60)
    assert r.returncode == 1, r.stdout + r.stderr
    _one_line_naming(r.stderr, "serial")
    assert not out.exists()


def test_config_check_and_run_refuse_the_live_view_without_its_extra(tmp_path):
    """`[view] enabled = true` without rerun: config check said OK and `vio run` stopped building its Service
    with exit 1, which systemd restarts for ever (it leaves only exit 3 alone)."""
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[source]\nkind = "fake"\n[run]\nstatus_file = "{tmp_path / "status.json"}"\n'
                   "[view]\nenabled = true\n")
    for args in (("config", "check", str(cfg)), ("run", "--config", str(cfg))):
        r = _vio_without(("rerun",), "-q", *args, timeout=60)
        assert r.returncode == 3, r.stdout + r.stderr
        _one_line_naming(r.stderr, "view")
        assert "[view] enabled = true" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("module", ["mcap", "rosbags"])
def test_config_check_and_run_refuse_an_mcap_recording_without_its_extra(tmp_path, module):
    """`[run] record_format = "mcap"` without the [bags] extra: config check said OK, and `vio run` started and
    its recorder failed at once. Refused at start now, only where a recording is made (a `record_dir`)."""
    cfg = tmp_path / "c.toml"
    head = f'[source]\nkind = "fake"\n[run]\nstatus_file = "{tmp_path / "status.json"}"\nrecord_format = "mcap"\n'
    cfg.write_text(head)
    r = _vio_without((module,), "-q", "config", "check", str(cfg), timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr  # no record_dir: nothing is recorded, nothing needed
    cfg.write_text(head + f'record_dir = "{tmp_path / "rec"}"\n')
    for args in (("config", "check", str(cfg)), ("run", "--config", str(cfg))):
        r = _vio_without((module,), "-q", *args, timeout=60)
        assert r.returncode == 3, r.stdout + r.stderr
        _one_line_naming(r.stderr, "bags")
        assert '[run] record_format = "mcap"' in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "rec").exists()


def test_a_noisy_native_import_is_quiet_and_logged(tmp_path, monkeypatch, capfd, caplog):
    """A module whose native code prints on import to descriptor 1 (not through Python): it is sent to a temporary
    file for the import and restored after it, also when it fails; its known line is logged at DEBUG, anything else
    at WARNING. Descriptor 2 is left alone (a native abort's message must reach the journal)."""
    import logging

    import vio.extras as extras

    for name, body in (("kv_noisy_ok", ""), ("kv_noisy_broken", "raise ImportError('no libfoo.so')\n")):
        (tmp_path / f"{name}.py").write_text(
            "import os\n"
            "os.write(1, b'[dai] [warning] USB protocol not available - in a container\\n')\n"
            "os.write(1, b'libfoo: something else\\n')\n"
            "os.write(2, b'libfoo: an abort message\\n')\n" + body)
        monkeypatch.setitem(extras.NOISY_IMPORTS, name, "USB protocol not available")
        monkeypatch.delitem(sys.modules, name, raising=False)
    monkeypatch.syspath_prepend(str(tmp_path))
    caplog.set_level(logging.DEBUG, logger="vio.extras")
    assert extras.require("kv_noisy_ok", "oak", "a test").__name__ == "kv_noisy_ok"
    with pytest.raises(MissingExtra):
        extras.require("kv_noisy_broken", "oak", "a test")
    os.write(1, b"fd 1 is back\n")
    os.write(2, b"fd 2 is back\n")
    out, err = capfd.readouterr()
    assert out == "fd 1 is back\n"
    assert err == "libfoo: an abort message\n" * 2 + "fd 2 is back\n"
    said = [(r.levelname, r.getMessage()) for r in caplog.records]
    for name in ("kv_noisy_ok", "kv_noisy_broken"):
        assert ("DEBUG", f"{name} (on import): [dai] [warning] USB protocol not available - in a container") in said
        assert ("WARNING", f"{name} (on import): libfoo: something else") in said


def test_config_check_of_an_oak_config_prints_only_its_verdict(tmp_path):
    """depthai's native logger printed "USB protocol not available ..." on stdout when imported (wherever USB is
    not mapped in: a container), before `vio config check`'s own "FILE: OK"."""
    pytest.importorskip("depthai")
    cfg = tmp_path / "oak.toml"
    cfg.write_text('[source]\nkind = "oak"\n')
    r = _vio_without((), "config", "check", str(cfg))
    assert r.returncode == 0, r.stderr
    assert (r.stdout, r.stderr) == (f"{cfg}: OK\n", "")
