"""The package as users get it: a built wheel, imported without the editable install's import hooks.

An editable install adds a finder that imports modules (importlib.util among them) before our code runs,
which once hid a crash of every `vio` command in plain installs."""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def unpacked_wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w",
                        str(out), str(ROOT)], capture_output=True, text=True, cwd=out)
    if r.returncode != 0:
        pytest.skip(f"cannot build a wheel here: {r.stderr.strip().splitlines()[-1:]}")
    wheel = next(out.glob("kestrel_vio-*.whl"))
    site = out / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    return site


def _run_plain(site: Path, *args: str) -> subprocess.CompletedProcess:
    """`python -S`: no .pth files, so no editable finder; the wheel and the venv's dependencies only."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), sysconfig.get_paths()["purelib"],
                                                        sysconfig.get_paths()["platlib"]])}
    return subprocess.run([sys.executable, "-S", *args], capture_output=True, text=True, env=env, cwd=site,
                          timeout=120)


def test_wheel_holds_the_three_packages(unpacked_wheel: Path) -> None:
    for pkg in ("vio", "drivers", "calib"):
        assert (unpacked_wheel / pkg / "__init__.py").exists(), pkg
    assert not (unpacked_wheel / "tests").exists()


def test_cli_runs_from_a_plain_install(unpacked_wheel: Path) -> None:
    r = _run_plain(unpacked_wheel, "-c", "import sys, vio.app.cli; sys.exit(vio.app.cli.main(sys.argv[1:]))", "--help")
    assert r.returncode == 0, r.stderr
    assert "replay" in r.stdout and "simulate" in r.stdout
    import_check = _run_plain(unpacked_wheel, "-c", "import vio, sys; print(vio.__file__)")
    assert str(unpacked_wheel) in import_check.stdout, import_check.stdout + import_check.stderr


def test_the_vio_script_names_the_app_layer_entry_point(unpacked_wheel: Path) -> None:
    """`[project.scripts] vio` points at a module that exists in the wheel and runs."""
    (entry_points,) = unpacked_wheel.glob("kestrel_vio-*.dist-info/entry_points.txt")
    line = next(raw for raw in entry_points.read_text().splitlines() if raw.replace(" ", "").startswith("vio="))
    target = line.split("=", 1)[1].strip()
    assert target == "vio.app.cli:main", target
    module, func = target.split(":")
    r = _run_plain(unpacked_wheel, "-c", f"import sys, {module}; sys.exit({module}.{func}(['--help']))")
    assert r.returncode == 0 and "replay" in r.stdout, r.stderr


def test_wheel_version_is_the_one_in_vio(unpacked_wheel: Path) -> None:
    """One version string: the wheel's metadata is read from vio.__version__."""
    from vio import __version__

    (info,) = unpacked_wheel.glob("kestrel_vio-*.dist-info")
    assert info.name == f"kestrel_vio-{__version__}.dist-info"
    meta = (info / "METADATA").read_text()
    assert f"\nVersion: {__version__}\n" in meta
    for extra in ("oak", "serial", "tools", "dev"):
        assert f"Provides-Extra: {extra}" in meta
