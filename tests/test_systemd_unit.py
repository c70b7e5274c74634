"""The systemd unit, udev rule, example config and install script agree with each other and the daemon.

`systemd-analyze verify` runs when systemd is installed; the parsed checks below run everywhere, because a
unit that verifies can still be wrong for us (PrivateDevices hides the OAK, a missing WatchdogSec
silently disables the watchdog, a RuntimeDirectory that differs from status_file breaks `vio status`).
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from vio.app.cli import EXIT_CONFIG
from vio.config import load_config

SYSTEMD = Path(__file__).resolve().parents[1] / "systemd"
UNIT = SYSTEMD / "kestrel-vio.service"
RULE = SYSTEMD / "80-kestrel-oak.rules"
INSTALL = SYSTEMD / "install.sh"
CONFIG = SYSTEMD / "config.toml"


def parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """systemd's ini dialect: repeated keys accumulate (configparser would reject or overwrite them)."""
    sections: dict[str, dict[str, list[str]]] = {}
    current = None
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line[0] in "#;":
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        assert current is not None and "=" in line, f"{UNIT}:{lineno}: not 'Key=value' inside a section"
        key, value = (s.strip() for s in line.split("=", 1))
        current.setdefault(key, []).append(value)
    return sections


@pytest.fixture(scope="module")
def unit() -> dict[str, dict[str, list[str]]]:
    return parse_unit(UNIT.read_text())


def one(unit: dict, section: str, key: str) -> str:
    values = unit[section].get(key)
    assert values, f"[{section}] {key}= missing"
    return values[-1]


def test_unit_is_a_notify_service_with_watchdog(unit) -> None:
    assert one(unit, "Service", "Type") == "notify"
    assert one(unit, "Service", "NotifyAccess") == "main"
    watchdog = one(unit, "Service", "WatchdogSec")
    assert re.fullmatch(r"\d+s?", watchdog) and 2 <= int(watchdog.rstrip("s")) <= 60
    assert int(one(unit, "Service", "TimeoutStartSec")) >= 30  # time for the first pose
    assert one(unit, "Service", "Restart") == "on-failure"
    assert one(unit, "Service", "RestartPreventExitStatus") == str(EXIT_CONFIG)
    assert one(unit, "Install", "WantedBy") == "multi-user.target"


def test_unit_runs_vio_run_with_the_installed_config(unit) -> None:
    exec_start = one(unit, "Service", "ExecStart").split()
    assert exec_start[0].endswith("/venv/bin/vio") and exec_start[1:3] == ["run", "--config"]
    assert exec_start[3] == "/etc/kestrel-vio/config.toml"
    assert "/etc/kestrel-vio/config.toml" in INSTALL.read_text()


def test_unit_user_groups_and_devices(unit) -> None:
    user = one(unit, "Service", "User")
    assert user == "kestrel" and f"SERVICE_USER={user}" in INSTALL.read_text()
    groups = one(unit, "Service", "SupplementaryGroups").split()
    assert {"dialout", "plugdev"} <= set(groups)
    service = unit["Service"]
    for hides_devices in ("PrivateDevices", "DevicePolicy", "DeviceAllow", "ProtectClock"):
        assert hides_devices not in service, f"{hides_devices}= would hide the OAK or the UART"
    for hardening in ("ProtectSystem", "ProtectHome", "PrivateTmp", "NoNewPrivileges"):
        assert hardening in service
    assert one(unit, "Service", "ProtectSystem") == "strict"


def test_unit_directories_match_config_paths(unit) -> None:
    cfg = load_config(CONFIG)
    runtime = one(unit, "Service", "RuntimeDirectory")
    assert Path(cfg.run.status_file).parent == Path("/run") / runtime
    writable = one(unit, "Service", "ReadWritePaths").split()
    state = Path("/var/lib") / one(unit, "Service", "StateDirectory")
    assert str(state) in writable
    # the commented-out record/trajectory examples must land somewhere the sandbox lets us write
    for line in CONFIG.read_text().splitlines():
        m = re.match(r'#\s*(record_dir|trajectory_file)\s*=\s*"([^"]+)"', line)
        if m:
            assert any(m.group(2).startswith(w + "/") for w in writable), line


def test_udev_rule_covers_the_oak_for_the_service_group(unit) -> None:
    rules = [ln for ln in RULE.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    assert rules
    for rule in rules:
        assert 'SUBSYSTEM=="usb"' in rule and 'ATTRS{idVendor}=="03e7"' in rule
        group = re.search(r'GROUP="(\w+)"', rule)
        mode = re.search(r'MODE="(\d+)"', rule)
        assert mode and (mode.group(1) == "0666" or (group and group.group(1) in
                                                     one(unit, "Service", "SupplementaryGroups").split()))
    assert RULE.name in INSTALL.read_text()


def test_example_config_is_valid() -> None:
    cfg = load_config(CONFIG)
    assert cfg.source.kind == "oak" and cfg.mavlink.url


def test_install_script_dry_run_shows_every_step() -> None:
    r = subprocess.run(["bash", str(INSTALL), "--dry-run", "--enable"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    out = r.stdout
    for step in ("kestrel-vio.service /etc/systemd/system/", "80-kestrel-oak.rules /etc/udev/rules.d/",
                 "config.toml /etc/kestrel-vio/config.toml.example", "-m venv /opt/kestrel-vio/venv",
                 "systemctl daemon-reload", "vio config check /etc/kestrel-vio/config.toml",
                 "systemctl enable --now kestrel-vio"):
        assert step in out, step
    if subprocess.run(["id", "-u", "kestrel"], capture_output=True).returncode != 0:
        assert re.search(r"useradd --system .* kestrel$", out, re.M)
    r = subprocess.run(["bash", str(INSTALL), "--bogus"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "unknown option" in r.stderr


def test_install_script_dry_run_lines_are_the_commands_as_a_shell_reads_them() -> None:
    """`--dry-run` printed `useradd ... --comment Kestrel VIO service kestrel`: pasted, as its help invites, it was
    another command (three arguments, the user named 'VIO'). Each line now quotes its arguments."""
    import shlex

    r = subprocess.run(["bash", str(INSTALL), "--dry-run"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    lines = [shlex.split(ln[2:]) for ln in r.stdout.splitlines() if ln.startswith("+ ")]
    pip = next(a for a in lines if a[1:3] == ["install", "--upgrade"] and a[-1].endswith("[oak,serial]"))
    assert Path(pip[-1][:-len("[oak,serial]")]) == INSTALL.parents[1]
    if subprocess.run(["id", "-u", "kestrel"], capture_output=True).returncode != 0:
        useradd = next(a for a in lines if a[0] == "useradd")
        assert useradd[useradd.index("--comment") + 1] == "Kestrel VIO service" and useradd[-1] == "kestrel"


def test_install_script_prefix_says_the_drop_in_that_runs_it() -> None:
    """`--prefix D` said only "override ExecStart with 'systemctl edit kestrel-vio'": a drop-in with one more ExecStart=
    line is refused by systemd ("more than one ExecStart= setting") unless an empty one clears the unit's first; and
    `--prefix` with no folder ended in bash's "$2: unbound variable"."""
    r = subprocess.run(["bash", str(INSTALL), "--dry-run", "--prefix", "/srv/kv"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    assert "ExecStart=\nExecStart=/srv/kv/venv/bin/vio run --config /etc/kestrel-vio/config.toml" in \
        r.stderr.replace("\n    ", "\n"), r.stderr
    r = subprocess.run(["bash", str(INSTALL), "--dry-run", "--prefix"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--prefix needs a folder" in r.stderr and "unbound" not in r.stderr, r.stderr


@pytest.mark.skipif(shutil.which("shellcheck") is None, reason="shellcheck not installed")
def test_install_script_shellcheck() -> None:
    r = subprocess.run(["shellcheck", str(INSTALL)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_verify(tmp_path: Path) -> None:
    # verify also checks that ExecStart exists; point it at a real binary, keep everything else as shipped
    text = re.sub(r"^ExecStart=\S+", f"ExecStart={shutil.which('true')}", UNIT.read_text(), flags=re.M)
    unit_copy = tmp_path / UNIT.name
    unit_copy.write_text(text)
    r = subprocess.run(["systemd-analyze", "verify", str(unit_copy)], capture_output=True, text=True, timeout=60)
    problems = [ln for ln in (r.stdout + r.stderr).splitlines() if UNIT.name in ln or "Unknown" in ln]
    assert r.returncode == 0 and not problems, r.stdout + r.stderr
