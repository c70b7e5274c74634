"""The frame clock (vio/frame_clock.py) on stamp sequences whose true exposure times are known: what it moves, and
how far from the exposures the stamps it hands out are, against the stamps as given.

    nice python bench/frame_clock_cases.py [--seconds 60] [--seed 1]

No images and no estimator: each case is a 20 Hz camera's exposure times (or the SITL camera's: the SIM_STATEs the
simulator sends at the camera rate), the stamps a driver would give them, and the clock's output in `auto`
mode. The error of a stamp is its distance from its
exposure less the run's mean latency (a constant latency is the calibration's time offset, not the clock's).
Columns: frames restamped, fits started again, rms and largest error of the stamps as given and as restamped
(after the first 200 frames), frames more than 10 ms off, and stamps the clock handed out not after the one before (the
estimator drops those frames). Results are printed as a Markdown table (docs/estimator.md "Frame stamps").
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vio.frame_clock import FrameClock  # noqa: E402

T0 = 1_403_715_273_262_142_976  # a EuRoC-sized stamp
PERIOD = 50_000_000


def _grid(n: int, period: float = PERIOD) -> np.ndarray:
    return T0 + np.round(np.arange(n) * period).astype(np.int64)


def _exp(rng: np.random.Generator, mean_ns: float, n: int) -> np.ndarray:
    return np.round(rng.exponential(mean_ns, n)).astype(np.int64)


def _rate_change(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    first = _grid(n // 3)
    true = np.concatenate([first, first[-1] + np.round(np.arange(1, n - n // 3 + 1) * 1e9 / 30).astype(np.int64)])
    return true, true + _exp(rng, 1e6, len(true))


def _held(rng: np.random.Generator, n: int, held_ns: int) -> tuple[np.ndarray, np.ndarray]:
    true = _grid(n)
    delay = _exp(rng, 1e6, n)
    delay[n // 4::40] = held_ns  # now and then one frame held up (a USB transfer stalled)
    return true, true + delay


def _burst(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    true = _grid(n)
    arrived = true + _exp(rng, 2e6, n)
    arrived[:4] = arrived[4] - np.arange(4, 0, -1) * 1_000_000  # the stream's first frames delivered together
    return true, arrived


def _drift(rng: np.random.Generator, n: int, amp_ms: float, period_s: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n) * PERIOD
    true = T0 + t - np.round(amp_ms * 1e6 * np.sin(2 * np.pi * t * 1e-9 / period_s)).astype(np.int64)
    return true, true.copy()  # stamped on the device: exact, on a clock that drifts against the IMU's


def _irregular(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    true = T0 + np.cumsum(np.round(PERIOD + rng.normal(0, 1.5e6, n)).astype(np.int64))
    return true, true.copy()  # triggered at irregular times, each stamped exactly (its own time)


def _sitl(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The SITL camera since 49ef3cb: SIM_STATE sent at the camera rate on the simulator's clock (its 400 Hz loop
    rounds each send to 2.5 ms), each rendered and stamped on arrival (1 ms exponential delays) by the source's
    own on_sim_state, which must take every one."""
    from drivers.sitl_camera import SitlCameraSource

    class Msg:  # SIM_STATE at the home position, level
        lat_int = lon_int = 0
        lat = lon = alt = 0.0
        q1, q2, q3, q4 = 1.0, 0.0, 0.0, 0.0

    cam = SitlCameraSource("tcp:unused", (0.0, 0.0, 0.0), width=64, height=48, fps=15.0)
    cam.render = lambda T, t_ns: t_ns  # the stamp is all this needs
    sent = T0 + np.round(np.arange(n) * (1e9 / 15.0) / 2.5e6) * 2.5e6
    sent = sent.astype(np.int64)
    arrived = sent + _exp(rng, 1e6, n)
    taken = [k for k, t in enumerate(arrived) if cam.on_sim_state(Msg(), int(t)) is not None]
    return sent[taken], arrived[taken]


CASES: dict[str, Callable[[np.random.Generator, int], tuple[np.ndarray, np.ndarray]]] = {
    "3 ms exponential arrival jitter": lambda r, n: (lambda t: (t, t + _exp(r, 3e6, n)))(_grid(n)),
    "20 Hz -> 30 Hz after a third, 1 ms jitter": _rate_change,
    "a frame in 40 held up 45 ms, 1 ms jitter": lambda r, n: _held(r, n, 45_000_000),
    "a frame in 40 held up 48 ms, 1 ms jitter": lambda r, n: _held(r, n, 48_000_000),
    "first 4 frames delivered together, 2 ms jitter": _burst,
    "device stamps, offset drift 10 ms / 60 s": lambda r, n: _drift(r, n, 10, 60),
    "device stamps, offset drift 5 ms / 30 s": lambda r, n: _drift(r, n, 5, 30),
    "exact stamps of irregular exposures (1.5 ms)": _irregular,
    "SITL camera, 15 Hz (SIM_STATE at its rate, 1 ms arrival jitter)": _sitl,
}


def run_case(true: np.ndarray, given: np.ndarray, skip: int) -> dict:
    clock = FrameClock("auto")
    out = np.array([clock.restamp(int(t)) for t in given], np.int64)
    latency = float(np.mean(given - true))
    e_given = (given - true - latency)[skip:] * 1e-6
    e_out = (out - true - latency)[skip:] * 1e-6
    return {"restamped": clock.stats.restamped, "frames": len(out), "restarts": clock.stats.restarts,
            "given_rms": float(np.sqrt(np.mean(e_given ** 2))), "given_max": float(np.abs(e_given).max()),
            "out_rms": float(np.sqrt(np.mean(e_out ** 2))), "out_max": float(np.abs(e_out).max()),
            "given_10": int(np.sum(np.abs(e_given) > 10)), "out_10": int(np.sum(np.abs(e_out) > 10)),
            "out_of_order": int(np.sum(np.diff(out) <= 0))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=60.0, help="length of each stamp sequence (default 60)")
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args(argv)
    n = int(args.seconds * 20)
    print("| case | restamped | restarts | as given: rms / max ms (>10 ms) | restamped: rms / max ms (>10 ms) "
          "| out of order |")
    print("|---|---|---|---|---|---|")
    for name, make in CASES.items():
        true, given = make(np.random.default_rng(args.seed), n)
        r = run_case(true, given, skip=200)
        print(f"| {name} | {r['restamped']} of {r['frames']} | {r['restarts']} | {r['given_rms']:.2f} / "
              f"{r['given_max']:.1f} ({r['given_10']}) | {r['out_rms']:.2f} / {r['out_max']:.1f} ({r['out_10']}) "
              f"| {r['out_of_order']} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
