"""The TOML configuration: defaults, `vio config show` round trip, and errors that name file and key."""

from __future__ import annotations

import dataclasses
import math

import pytest

from vio import VioError
from vio.app.cli import main
from vio.config import VioConfig, config_from_dict, config_to_toml, load_config


def _same(a: VioConfig, b: VioConfig) -> bool:
    """Equality that treats NaN as equal to NaN (defaults use NaN for 'not set')."""
    def norm(x):
        if isinstance(x, float) and math.isnan(x):
            return "nan"
        if isinstance(x, dict):
            return {k: norm(v) for k, v in x.items()}
        if isinstance(x, list):
            return [norm(v) for v in x]
        return x
    return norm(dataclasses.asdict(a)) == norm(dataclasses.asdict(b))


def test_defaults_load_and_are_valid():
    cfg = load_config(None)
    assert _same(cfg, VioConfig())
    # every default passes its own field's validation (a default outside its bounds is a bug)
    assert _same(config_from_dict(dataclasses.asdict(cfg), "defaults"), cfg)


def test_every_field_is_documented():
    for sec in dataclasses.fields(VioConfig):
        for f in dataclasses.fields(getattr(VioConfig(), sec.name)):
            assert f.metadata.get("help"), f"[{sec.name}] {f.name} has no help text"


def _show(capsys, path=None) -> str:
    assert main(["-q", "config", "show"] + ([str(path)] if path else [])) == 0
    return capsys.readouterr().out


def test_show_output_reloads_to_the_same_config(tmp_path, capsys):
    out = tmp_path / "shown.toml"
    out.write_text(_show(capsys))
    assert _same(load_config(out), VioConfig())


def test_show_of_a_file_reloads_to_that_file(tmp_path, capsys):
    src = tmp_path / "mine.toml"
    src.write_text(
        "[frontend]\nmax_features = 150\nclahe = true\n"
        "[source]\nkind = \"euroc\"\ndataset = 'C:\\data \"V1\"\\tab\there'\nfps = 30\n"
        "[mavlink]\nmount = \"rpy\"\nmount_rpy_deg = [180.0, 0.0, 90.0]\norigin_lat_deg = 47.5\n"
        "[run]\ntrajectory_file = \"\"\"two\nlines\"\"\"\n"
    )
    cfg = load_config(src)
    assert cfg.frontend.max_features == 150 and cfg.frontend.clahe is True
    assert cfg.source.fps == 30.0 and isinstance(cfg.source.fps, float)
    assert cfg.source.dataset == 'C:\\data "V1"\\tab\there'
    assert cfg.run.trajectory_file == "two\nlines"
    shown = tmp_path / "shown.toml"
    shown.write_text(_show(capsys, src))
    assert _same(load_config(shown), cfg)
    assert config_to_toml(load_config(shown)) == config_to_toml(cfg)


def _write(tmp_path, text: str):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("text, expected", [
    ("[frontend]\nmax_featurs = 100\n", "[frontend]: unknown key 'max_featurs' (did you mean 'max_features'?)"),
    ("[frontend]\nzzz = 1\n", "[frontend]: unknown key 'zzz'; known keys: max_features"),
    ("[frontend]\nmax_features = \"200\"\n", "[frontend]: 'max_features' must be int, got str '200'"),
    ("[frontend]\nmax_features = 200.5\n", "[frontend]: 'max_features' must be int, got float 200.5"),
    ("[frontend]\nclahe = 1\n", "[frontend]: 'clahe' must be bool, got int 1"),
    ("[backend]\nlag_s = true\n", "[backend]: 'lag_s' must be float, got bool True"),
    ("[frontend]\nmax_features = 5\n", "[frontend]: 'max_features' = 5 is below the minimum 10"),
    ("[frontend]\nmax_features = 100000\n", "[frontend]: 'max_features' = 100000 is above the maximum 2000"),
    ("[backend]\nlag_s = nan\n", "[backend]: 'lag_s' = nan is not a number; give one from 0.2 to 60"),
    ("[source]\nkind = \"webcam\"\n", "[source]: 'kind' = 'webcam' is not one of ['oak', 'euroc', 'fake', 'sitl']"),
    ("[frontnd]\nmax_features = 100\n", "unknown section [frontnd] (did you mean [frontend]?)"),
    ("[zebra]\n", "unknown section [zebra]; known sections: frontend"),
    ("frontend = 3\n", "[frontend]: expected a table of settings, got int"),
    ("[frontend]\nmax_features = \n", "not valid TOML"),
    ("[frontend]\nmax_features = 100\nmax_features = 120\n", "not valid TOML"),
])
def test_errors_name_file_and_key(tmp_path, text, expected):
    path = _write(tmp_path, text)
    with pytest.raises(VioError) as e:
        load_config(path)
    msg = str(e.value)
    assert msg.startswith(f"{path}: ")
    assert expected in msg


def test_bad_toml_names_the_line(tmp_path):
    path = _write(tmp_path, "[frontend]\nmax_features = 100\nclahe = yes\n")
    with pytest.raises(VioError, match=r"bad\.toml: not valid TOML .*line 3"):
        load_config(path)


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(VioError, match=r"nope\.toml: cannot read config"):
        load_config(tmp_path / "nope.toml")
    p = tmp_path / "bin.toml"
    p.write_bytes(b"\xff\xfe\x00junk")
    with pytest.raises(VioError, match=r"bin\.toml: not valid TOML"):
        load_config(p)


@pytest.mark.parametrize("text,match", [
    ("[mavlink]\nmount_rpy_deg = [180.0, 0.0, 0.0]\n", "set mount = 'rpy'"),
    # a quarter turn in radians reads as a 1.57 deg tilt, under the first pose's 45 deg mount warning
    ("[mavlink]\nmount = \"rpy\"\nmount_rpy_deg = [0.0, 1.5708, 0.0]\n",
     r"looks like radians .* \[0\.0, 90\.0, 0\.0\]"),
    ("[mavlink]\nmount = \"rpy\"\nmount_rpy_deg = [3.14159, 0.0, -1.5708]\n", "looks like radians"),
    ("[backend]\nvision_timeout_s = 2.0\nlost_timeout_s = 1.0\n", "must not exceed lost_timeout_s"),
    ("[loop]\nreloc_confirm_edges = 0\n", "needs reloc_confirm_edges >= it"),
    ("[frontend]\nmax_depth_m = 10.0\n", "must lie inside the front end"),
    ("[backend]\nimu_noise_adaptive = true\nimu_noise_scale = 8.0\nimu_noise_max_scale = 4.0\n",
     "below imu_noise_scale"),
    ("[source]\nimu = \"serial\"\nserial_port = \"\"\n", "needs \\[source\\] serial_port"),
    # the IMU clock gate's quality ramp runs from the tolerance to the bound: none left between them
    ("[mavlink]\nstamp_tolerance_ms = 50\n", r"stamp_tolerance_ms = 50 must be below max_stamp_error_ms = 50"),
    ("[mavlink]\nmax_stamp_error_ms = 20\nstamp_tolerance_ms = 30.5\n",
     r"stamp_tolerance_ms = 30\.5 must be below max_stamp_error_ms = 20: the quality falls"),
])
def test_contradicting_settings_are_refused(tmp_path, text, match):
    """A mounting given for the wrong mode would be silently ignored, and the IMU flown upside down."""
    f = tmp_path / "c.toml"
    f.write_text(text)
    with pytest.raises(VioError, match=match):
        load_config(f)


@pytest.mark.parametrize("tilt", [3.14, -1.57, 3.135, 4.7124])
def test_a_tilt_in_degrees_that_reads_as_radians_is_told_how_to_get_through(tmp_path, tilt):
    """A 3.14 deg tilt cannot be told from pi typed in radians: refused (safe), and the message gives a value
    0.02 deg away that passes, instead of a dead end."""
    import re

    f = tmp_path / "c.toml"
    f.write_text(f"[mavlink]\nmount = \"rpy\"\nmount_rpy_deg = [{tilt}, 0.0, 0.0]\n")
    with pytest.raises(VioError, match="looks like radians") as e:
        load_config(f)
    away = float(re.search(r"write (-?[0-9.]+): 0\.02 deg", str(e.value)).group(1))
    assert abs(away - tilt) <= 0.03
    f.write_text(f"[mavlink]\nmount = \"rpy\"\nmount_rpy_deg = [{away}, 0.0, 0.0]\n")
    assert load_config(f).mavlink.mount_rpy_deg == [away, 0.0, 0.0]


def test_the_estimator_gets_only_its_sections():
    from vio.config import EstimatorConfig, VioConfig
    from vio.estimator import Estimator
    from vio.sim import default_calibration

    est = Estimator(default_calibration(), VioConfig())
    assert isinstance(est.cfg, EstimatorConfig) and not hasattr(est.cfg, "mavlink")


def test_a_quality_sigma_beyond_a_metre_is_refused():
    """5 typed for 5 cm kept quality 100 until the position sigma reached 5 m (a review's finding)."""
    from vio import VioError
    from vio.config import config_from_dict

    with pytest.raises(VioError, match="quality_sigma_m.*maximum 1.0"):
        config_from_dict({"backend": {"quality_sigma_m": 5}})
    assert config_from_dict({"backend": {"quality_sigma_m": 0.1}}).backend.quality_sigma_m == 0.1


def test_a_config_saved_with_a_byte_order_mark_is_read(tmp_path, capsys):
    """A config edited in Windows Notepad starts with a BOM: `vio config check` said 'not valid TOML (Invalid
    statement (at line 1, column 1))', and `vio run` refused to start on it."""
    path = tmp_path / "config.toml"
    path.write_bytes(b"\xef\xbb\xbf" + b'[source]\r\nkind = "fake"\r\nfps = 15\r\n')
    assert main(["config", "show", str(path)]) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert 'kind = "fake"' in out and "fps = 15" in out
    assert load_config(path).source.fps == 15


def test_an_empty_bag_topic_is_a_configuration_error():
    """`[bag] left_topic = ""` passed `vio config check` and the replay of a bag then said "no left  topic" (an empty
    --left-topic on the command line is the default instead). Refused naming the key."""
    from vio.config import config_from_dict

    for key in ("left_topic", "right_topic", "imu_topic"):
        with pytest.raises(VioError, match=rf"\[bag\] {key} is empty: name the topic \(e\.g\. /"):
            config_from_dict({"bag": {key: " "}})
