"""IMU noise from Allan deviation (`vio calib imu-noise`).

Model (IEEE 952 / kalibr): on a log-log Allan deviation plot white noise (angle/velocity random walk)
has slope -1/2 and sigma(tau) = N / sqrt(tau), so N = sigma(1 s); a bias random walk has slope +1/2 and
sigma(tau) = K * sqrt(tau / 3), so K = sigma(3 s); in between, the flat minimum is the bias instability
B = min(sigma) / 0.664. N and K are kalibr's noise_density and random_walk.

Each is read from a straight line of the exact slope fitted (in log space, least squares on the offset
only) to the part of the curve whose local slope is near it. A recording too short to reach the +1/2
region yields no random walk measurement: we then report an upper bound (the line of slope +1/2 through
the last point lies above the true curve) and say so, rather than invent a figure.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vio import VioError
from vio.calibration import MIN_IMU_NOISE, ImuNoise

log = logging.getLogger(__name__)

BIAS_INSTABILITY_FACTOR = 0.664  # sqrt(2 ln 2 / pi): flicker floor of the Allan deviation
SLOPE_TOL = 0.2  # a point belongs to the -1/2 (+1/2) region when its local slope is within this of it
MIN_CLUSTERS = 9  # taus with fewer independent averages than this are too noisy to fit
STILL_SPEED_M_S = 0.05  # ground truth speed below which the body counts as still
STILL_GYRO_STD_RAD_S = 0.06  # without ground truth: windowed gyro std below this counts as still


@dataclass
class AxisFit:
    """Fitted Allan parameters of one axis."""

    noise_density: float  # N, units/sqrt(Hz)
    random_walk: float  # K, units/s/sqrt(Hz); an upper bound when random_walk_is_bound
    bias_instability: float  # B, units
    random_walk_is_bound: bool
    n_white_points: int
    n_rw_points: int


@dataclass
class AllanResult:
    rate_hz: float
    duration_s: float
    taus: np.ndarray
    gyro_adev: np.ndarray  # (n_tau, 3)
    accel_adev: np.ndarray  # (n_tau, 3)
    gyro_fits: list[AxisFit]
    accel_fits: list[AxisFit]
    noise: ImuNoise
    notes: list[str] = field(default_factory=list)


def allan_deviation(x: np.ndarray, rate_hz: float, taus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of rate samples x at the given taus (allantools' oadev).

    Returns (taus actually used, adev); taus are rounded to whole samples by allantools.
    """
    from vio.extras import require

    allantools = require("allantools", "tools", "the Allan deviation (vio calib imu-noise)")

    t, adev, _, _ = allantools.oadev(np.asarray(x, dtype=float), rate=rate_hz, data_type="freq", taus=taus)
    return np.asarray(t), np.asarray(adev)


def _log_taus(n: int, rate_hz: float, per_decade: int = 12) -> np.ndarray:
    tau0 = 1.0 / rate_hz
    tau_max = n * tau0 / MIN_CLUSTERS
    if tau_max <= 2 * tau0:
        raise VioError(f"IMU recording too short for an Allan analysis ({n} samples)")
    k = np.unique(np.round(np.logspace(0, np.log10(tau_max / tau0), int(per_decade * np.log10(tau_max / tau0)))))
    return k * tau0


def fit_axis(taus: np.ndarray, adev: np.ndarray) -> AxisFit:
    """N, K, B of one Allan deviation curve (see module doc)."""
    good = np.isfinite(adev) & (adev > 0)
    lt, la = np.log10(taus[good]), np.log10(adev[good])
    slope = np.gradient(la, lt)
    white = np.abs(slope + 0.5) < SLOPE_TOL
    if not white.any():  # no clean white-noise region: take the shortest taus, where white noise rules
        white = np.zeros_like(slope, dtype=bool)
        white[: max(3, len(slope) // 10)] = True
    # line of slope -1/2: log sigma = log N - 0.5 log tau  =>  log N = mean(log sigma + 0.5 log tau)
    N = 10 ** float(np.mean(la[white] + 0.5 * lt[white]))
    # the +1/2 region must lie after the minimum (at short tau the slope may wander through +1/2 too)
    i_min = int(np.argmin(la))
    rw = (np.abs(slope - 0.5) < SLOPE_TOL) & (np.arange(len(la)) > i_min)
    bound = not rw.any()
    if bound:
        # K * sqrt(tau/3) <= sigma(tau) at the longest tau measured
        K = float(10 ** la[-1] * math.sqrt(3.0 / 10 ** lt[-1]))
    else:
        K = 10 ** float(np.mean(la[rw] - 0.5 * (lt[rw] - math.log10(3.0))))
    B = float(10 ** la[i_min] / BIAS_INSTABILITY_FACTOR)
    return AxisFit(N, K, B, bound, int(white.sum()), int(rw.sum()))


def analyse_imu(imu, rate_hz: float | None = None) -> AllanResult:
    """Allan analysis of an `ImuData` (still recording) for all six axes; the ImuNoise takes the worst axis
    (the estimator must not trust any axis more than it deserves)."""
    t = np.asarray(imu.t_ns)
    if len(t) < 100:
        raise VioError(f"IMU recording too short for an Allan analysis ({len(t)} samples)")
    dt = np.diff(t) / 1e9
    if rate_hz is None:
        rate_hz = 1.0 / float(np.median(dt))
    if np.max(dt) > 5.0 / rate_hz:
        log.warning("IMU has gaps up to %.1f ms; Allan deviation assumes even sampling", np.max(dt) * 1e3)
    taus = _log_taus(len(t), rate_hz)
    for name, data in (("gyro", imu.gyro), ("accel", imu.accel)):
        for i, ax in enumerate("xyz"):
            if np.ptp(data[:, i]) == 0:  # its Allan deviation is all 0: an IndexError in the fit (an internal error)
                raise VioError(f"{name} {ax} reads {data[0, i]:g} in every one of the {len(t)} samples: a stuck or "
                               "dead axis, or a recording without sensor noise (a simulation): no noise to measure")
    g = [allan_deviation(imu.gyro[:, i], rate_hz, taus) for i in range(3)]
    a = [allan_deviation(imu.accel[:, i], rate_hz, taus) for i in range(3)]
    taus_used = g[0][0]
    gyro_adev = np.stack([x[1] for x in g], axis=1)
    accel_adev = np.stack([x[1] for x in a], axis=1)
    gf = [fit_axis(taus_used, gyro_adev[:, i]) for i in range(3)]
    af = [fit_axis(taus_used, accel_adev[:, i]) for i in range(3)]
    for name, fits in (("gyro", gf), ("accel", af)):
        for ax, f in zip("xyz", fits):
            for what, v in (("noise density", f.noise_density), ("random walk", f.random_walk)):
                if not v >= MIN_IMU_NOISE:  # the file written would be refused by `vio calib import` and replay
                    raise VioError(f"{name} {ax}: a {what} of {v:.3g} is below any IMU's (at least {MIN_IMU_NOISE:g}): "
                                   "the axis is stuck or its noise removed (filtered, simulated): no noise to measure")
    noise = ImuNoise(
        gyroscope_noise_density=max(f.noise_density for f in gf),
        gyroscope_random_walk=max(f.random_walk for f in gf),
        accelerometer_noise_density=max(f.noise_density for f in af),
        accelerometer_random_walk=max(f.random_walk for f in af),
        rate_hz=float(round(rate_hz, 3)),
    )
    duration = (t[-1] - t[0]) / 1e9
    notes = []
    short = taus_used <= 1.0
    shaky = [f"{name} {ax}" for name, fits in (("gyro", gf), ("accel", af)) for ax, f in zip("xyz", fits)
             if f.n_white_points < 0.5 * short.sum()]
    if shaky:
        notes.append(f"{', '.join(shaky)}: under half of the curve below 1 s has the white-noise slope -1/2 "
                     "(vibration, motion or on-sensor filtering); the noise density there is a rough figure")
    if any(f.random_walk_is_bound for f in gf + af):
        notes.append(f"recording ({duration:.1f} s) too short to reach the +1/2 slope on some axes: their random "
                     "walk is an upper bound; record >= 1 h still for a measurement")
    return AllanResult(rate_hz, duration, taus_used, gyro_adev, accel_adev, gf, af, noise, notes)


# ------------------------------------------------------------------------------------- data selection

def _longest_run(mask: np.ndarray) -> tuple[int, int]:
    """[start, stop) of the longest run of True."""
    best, cur_start = (0, 0), None
    for i, m in enumerate(np.append(mask, False)):
        if m and cur_start is None:
            cur_start = i
        elif not m and cur_start is not None:
            if i - cur_start > best[1] - best[0]:
                best = (cur_start, i)
            cur_start = None
    return best


def find_still_span(imu, groundtruth=None) -> tuple[int, int, str]:
    """(t_start_ns, t_end_ns, how) of the longest still part: from ground truth speed when the recording
    has it, else from the windowed gyro spread (which a vibrating airframe can fool: a warning says so)."""
    if groundtruth is not None and groundtruth.v_world is not None:
        speed = np.linalg.norm(groundtruth.v_world, axis=1)
        i0, i1 = _longest_run(speed < STILL_SPEED_M_S)
        if i1 - i0 >= 2:
            tg = groundtruth.trajectory.t_ns
            return int(tg[i0]), int(tg[i1 - 1]), f"ground truth |v| < {STILL_SPEED_M_S} m/s"
    win = max(int(round(0.5 / (np.median(np.diff(imu.t_ns)) / 1e9))), 10)
    n = len(imu.t_ns) // win
    if n == 0:
        raise VioError("IMU recording shorter than one 0.5 s window")
    stds = imu.gyro[: n * win].reshape(n, win, 3).std(axis=1).max(axis=1)
    i0, i1 = _longest_run(stds < STILL_GYRO_STD_RAD_S)
    if i1 == i0:
        raise VioError("no still part found in the IMU recording (gyro never quiet); give --start/--end")
    log.warning("still part found from the gyro spread alone; check it with --plot")
    return int(imu.t_ns[i0 * win]), int(imu.t_ns[i1 * win - 1]), f"gyro std < {STILL_GYRO_STD_RAD_S} rad/s"


def load_imu_for_allan(path: str | Path, start_s: float | None = None, end_s: float | None = None):
    """IMU of a EuRoC dataset (or a bare imu0 csv) cut to [start_s, end_s] seconds from its first sample;
    without bounds, a dataset is cut to its longest still part. Returns (ImuData, description)."""
    from vio.io.euroc import ImuData, find_mav0, read_groundtruth_csv, read_imu_csv

    path = Path(path)
    gt = None
    if path.is_file():
        imu = read_imu_csv(path)
    else:
        mav0 = find_mav0(path)
        imu = read_imu_csv(mav0 / "imu0" / "data.csv")
        gt_path = mav0 / "state_groundtruth_estimate0" / "data.csv"
        gt = read_groundtruth_csv(gt_path) if gt_path.is_file() else None
    t0 = int(imu.t_ns[0])
    if start_s is None and end_s is None and gt is not None:
        a, b, how = find_still_span(imu, gt)
    else:
        a = t0 + int((start_s or 0.0) * 1e9)
        b = int(imu.t_ns[-1]) if end_s is None else t0 + int(end_s * 1e9)
        how = "whole recording" if start_s is None and end_s is None else "given span"
    sel = (imu.t_ns >= a) & (imu.t_ns <= b)
    if sel.sum() < 100:
        raise VioError(f"{path}: only {int(sel.sum())} IMU samples in the span {(a - t0) / 1e9:.2f}.."
                       f"{(b - t0) / 1e9:.2f} s; need at least 100")
    desc = f"{path}: {(a - t0) / 1e9:.2f}..{(b - t0) / 1e9:.2f} s ({how}), {int(sel.sum())} samples"
    log.info("Allan analysis on %s", desc)
    return ImuData(imu.t_ns[sel], imu.gyro[sel], imu.accel[sel]), desc


# ------------------------------------------------------------------------------------------- output

def format_noise(result: AllanResult, source: str = "", reference: ImuNoise | None = None) -> str:
    lines = [f"Allan deviation: {source}" if source else "Allan deviation",
             f"  {result.duration_s:.1f} s at {result.rate_hz:.1f} Hz, "
             f"tau {result.taus[0]:.3g}..{result.taus[-1]:.3g} s"]
    for name, fits, unit in (("gyro", result.gyro_fits, "rad/s"), ("accel", result.accel_fits, "m/s^2")):
        for ax, f in zip("xyz", fits):
            bound = "<=" if f.random_walk_is_bound else "  "
            lines.append(f"  {name:5s} {ax}: noise density {f.noise_density:.3e} {unit}/sqrt(Hz)  random walk "
                         f"{bound}{f.random_walk:.3e} {unit}*sqrt(Hz)  "
                         f"bias instability {f.bias_instability:.3e} {unit}")
    n = result.noise
    lines.append("  kalibr imu.yaml (worst axis):")
    for key in ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
                "accelerometer_random_walk"):
        ref = f"   (reference {getattr(reference, key):.4e}, ratio {getattr(n, key) / getattr(reference, key):.2f})" \
            if reference is not None else ""
        lines.append(f"    {key}: {getattr(n, key):.4e}{ref}")
    lines += [f"  note: {m}" for m in result.notes]
    return "\n".join(lines)


def write_imu_yaml(noise: ImuNoise, path: str | Path) -> None:
    """kalibr imu.yaml (also read by `vio calib import kalibr` and, via rate_hz, as a EuRoC imu sensor.yaml)."""
    from vio.io.atomic import write_text_whole

    write_text_whole(
        path,
        "# IMU noise from `vio calib imu-noise` (Allan deviation; continuous-time, kalibr units)\n"
        f"accelerometer_noise_density: {noise.accelerometer_noise_density:.6e}  # m/s^2/sqrt(Hz)\n"
        f"accelerometer_random_walk: {noise.accelerometer_random_walk:.6e}  # m/s^3/sqrt(Hz)\n"
        f"gyroscope_noise_density: {noise.gyroscope_noise_density:.6e}  # rad/s/sqrt(Hz)\n"
        f"gyroscope_random_walk: {noise.gyroscope_random_walk:.6e}  # rad/s^2/sqrt(Hz)\n"
        f"update_rate: {noise.rate_hz:g}  # Hz\n"
        f"rate_hz: {noise.rate_hz:g}\n"
    )


def plot_allan(result: AllanResult, path: str | Path) -> None:
    from vio.extras import pyplot

    plt = pyplot("the Allan deviation plot")

    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    for ax, adev, fits, name, unit in ((axes[0], result.gyro_adev, result.gyro_fits, "gyroscope", "rad/s"),
                                       (axes[1], result.accel_adev, result.accel_fits, "accelerometer", "m/s^2")):
        t = result.taus
        for i, (lab, f) in enumerate(zip("xyz", fits)):
            line, = ax.loglog(t, adev[:, i], label=f"{lab}")
            ax.loglog(t, f.noise_density / np.sqrt(t), "--", color=line.get_color(), lw=0.8)
            ax.loglog(t, f.random_walk * np.sqrt(t / 3.0), ":", color=line.get_color(), lw=0.8)
        ax.axvline(1.0, color="grey", lw=0.5)
        ax.axvline(3.0, color="grey", lw=0.5)
        ax.set_ylim(np.nanmin(adev) / 3, np.nanmax(adev) * 3)
        ax.set_xlabel("tau [s]")
        ax.set_ylabel(f"Allan deviation [{unit}]")
        ax.set_title(f"{name}: -- N/sqrt(tau), .. K sqrt(tau/3)")
        ax.grid(True, which="both", lw=0.3)
        ax.legend()
    fig.suptitle(f"{result.duration_s:.0f} s at {result.rate_hz:.0f} Hz")
    from vio.evaluation import save_figure

    save_figure(plt, fig, path)  # under exactly the name given
