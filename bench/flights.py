"""Cache of simulated benchmark flights, keyed by their parameters.

Why a cache: rendering a flight costs about 1-4 s of CPU per second of flight (the 10-minute memory flight
takes many minutes), while replaying it is what the suite measures. A flight is generated once into
`<cache>/<key>/` by `vio simulate` (in a temporary folder, renamed when complete, so an interrupted run
leaves no half dataset that would be taken for a finished one) and reused by every later run.
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from vio import VioError

log = logging.getLogger(__name__)

DEFAULT_CACHE = Path(os.environ.get("KESTREL_BENCH_CACHE", "/tmp/kestrel-bench/flights"))


@dataclass(frozen=True)
class FlightSpec:
    """Parameters of `vio simulate` that define a benchmark flight (equal specs give identical data)."""

    profile: str = "survey"
    duration_s: float = 30.0
    seed: int = 1
    variant: str = "clean"
    size: str = "752x480"

    @property
    def key(self) -> str:
        return f"{self.profile}-{self.variant}-seed{self.seed}-{self.duration_s:g}s-{self.size}"

    def simulate_args(self, out: Path) -> list[str]:
        return ["simulate", str(out), "--profile", self.profile, "--duration", f"{self.duration_s:g}",
                "--seed", str(self.seed), "--variant", self.variant, "--size", self.size, "--no-progress"]


def ensure_flight(spec: FlightSpec, cache: Path = DEFAULT_CACHE) -> Path:
    """Path of the dataset for `spec`, generating it with `vio simulate` when it is not cached yet."""
    final = Path(cache) / spec.key
    if (final / "mav0").is_dir():
        return final
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{spec.key}.partial-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    log.info("generating flight %s (not cached)", spec.key)
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "vio.app.cli", "-q", *spec.simulate_args(tmp)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        shutil.rmtree(tmp, ignore_errors=True)
        raise VioError(f"vio simulate for flight {spec.key} failed (exit {proc.returncode}): "
                       f"{proc.stderr.strip()[-500:]}")
    try:
        tmp.rename(final)
    except OSError:  # another suite finished the same flight first: keep theirs
        shutil.rmtree(tmp, ignore_errors=True)
    log.info("flight %s generated in %.0f s", spec.key, time.perf_counter() - t0)
    return final
