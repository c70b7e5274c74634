"""`vio simulate OUT`: write a synthetic stereo + IMU flight (EuRoC layout) with exact ground truth."""

from __future__ import annotations

import argparse

from vio.argtypes import path_arg
from vio.sim import IMU_MOUNTS
from vio.sim.motion import PROFILES
from vio.sim.scene import SCENES

_VARIANT_HELP = ("realism preset: clean (textured, still images, EuRoC IMU noise), realistic (blur, noise, "
                 "exposure drift, vibration, some plain walls), hard (strong blur, exposure jumps, plain areas, "
                 "big biases, 5%% dropped frames); the options below override it")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", type=path_arg, metavar="OUT", help="dataset folder to create (OUT/mav0/...)")
    p.add_argument("--profile", choices=PROFILES, default="survey", help="flight profile (default: survey)")
    p.add_argument("--duration", type=float, default=30.0, help="flight length in s (default: 30)")
    p.add_argument("--seed", type=int, default=0, help="random seed; equal seeds give identical data")
    p.add_argument("--variant", choices=("clean", "realistic", "hard"), default="realistic", help=_VARIANT_HELP)
    p.add_argument("--rate", type=float, default=20.0, help="camera rate in Hz (default: 20)")
    p.add_argument("--imu-rate", type=float, default=200.0, help="IMU rate in Hz (default: 200)")
    p.add_argument("--still-start", type=float, default=2.0, metavar="S",
                   help="seconds at rest before moving (static initialisation; default: 2)")
    p.add_argument("--time-offset-ms", type=float, default=0.0,
                   help="camera-IMU time offset: t_imu = t_cam + offset (positive: image stamps early)")
    p.add_argument("--drop-frames", type=float, default=None, metavar="P",
                   help="probability that a frame loses an image: its left, its right or both (one of the three, "
                   "equally likely); 1 takes one image or both from every frame")
    p.add_argument("--camera-model", choices=("radtan", "equidistant"), default="radtan",
                   help="lens model of the simulated cameras (default: radtan, EuRoC's)")
    p.add_argument("--size", default="752x480", help="image size WxH (intrinsics scale with it)")
    p.add_argument("--gyro-bias", type=float, default=None, help="initial gyro bias magnitude [rad/s]")
    p.add_argument("--accel-bias", type=float, default=None, help="initial accel bias magnitude [m/s^2]")
    p.add_argument("--no-imu-noise", action="store_true", help="no white noise and no bias random walk")
    p.add_argument("--vibration", type=float, default=None, help="motor vibration amplitude [m/s^2]")
    p.add_argument("--blur-ms", type=float, default=None, help="exposure time for motion blur [ms]; 0 = sharp")
    p.add_argument("--image-noise", type=float, default=None, help="pixel noise sigma [grey levels]")
    p.add_argument("--plain", type=float, default=None, help="share of wall area painted plain (0..1)")
    p.add_argument("--scene-seed", type=int, default=None,
                   help="seed of the room (textures, boxes); default: --seed. Same value: the same room")
    p.add_argument("--aliasing", type=float, default=None, metavar="M",
                   help="aliasing room: walls, floor and ceiling repeat their texture every M metres "
                        "(places that look the same but are not; loop-closure tests)")
    p.add_argument("--scene", choices=SCENES, default="room",
                   help="room (10 x 8 x 4 m, default), hall (25 x 20 x 8 m machine hall: dim, far walls) or shelves "
                   "(the room with 8 identical shelf units every 2.4 m and walls repeating alike: aliasing)")
    p.add_argument("--calib-error", type=float, nargs="?", const=1.0, default=0.0, metavar="SCALE",
                   help="write a slightly wrong calibration (images use the true one, kept in "
                        "OUT/calibration_truth.yaml): extrinsics off by SCALE x 0.1 deg and 2 mm, intrinsics by "
                        "SCALE x 0.5 px (default SCALE 1, a typical Kalibr error)")
    p.add_argument("--stereo-error", type=float, default=0.0, metavar="PX",
                   help="write cam1's principal point cx PX pixels off (images use the true one, kept in "
                        "OUT/calibration_truth.yaml): a stereo calibration that drifted, biasing every disparity")
    p.add_argument("--right-dropout", action="append", default=[], metavar="START:LENGTH",
                   help="no right image from START s for LENGTH s (repeatable)")
    p.add_argument("--time-offset-drift-ms", type=float, default=0.0, metavar="MS",
                   help="the time offset drifts by +-MS around --time-offset-ms (a sinusoid, see --drift-period)")
    p.add_argument("--drift-period", type=float, default=60.0, metavar="S",
                   help="period of the time offset drift in s (default: 60)")
    p.add_argument("--stamp-jitter-ms", type=float, default=0.0, metavar="MS",
                   help="stamp each frame late by a random delay of mean and spread MS, its mean taken off (a camera "
                        "stamped on arrival at the host; the truth in OUT/time_offset_truth.csv)")
    p.add_argument("--stamp-stalls", default=None, metavar="EVERY_S:MS",
                   help="the camera's transfer stalls for MS ms every EVERY_S s on average; the frames due in a "
                        "stall are stamped together at its end (a USB camera stamped on arrival)")
    p.add_argument("--imu-mount", choices=sorted(IMU_MOUNTS), default="flu",
                   help="how the IMU sits on the vehicle: flu (square: x forward, z up; default) or oak (a "
                        "forward-looking Luxonis OAK: IMU x up, z backwards); the same flight either way")
    p.add_argument("--imu-from", type=path_arg, metavar="EUROC_DIR", default=None,
                   help="a real recording (EuRoC layout with imu0 and ground truth, e.g. ../shared/data/euroc/"
                        "V1_02_medium_imu_gt): its raw IMU and its ground-truth motion replace --profile and the IMU "
                        "model; the images are rendered along that motion (the variant's image settings apply)")
    p.add_argument("--recorded-start", type=float, default=0.0, metavar="S",
                   help="with --imu-from: start this many seconds into the recording's ground truth (default: 0)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset in OUT")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


# SimConfig's fields as the options that set them: its range errors named the field ("duration_s = -3.0 is outside
# [0.1, 3600]"), which no option is called
_OPTION_OF = {"duration_s": "--duration", "rate_hz": "--rate", "imu_rate_hz": "--imu-rate",
              "still_start_s": "--still-start", "time_offset_ms": "--time-offset-ms", "width": "--size width",
              "height": "--size height", "gyro_bias": "--gyro-bias", "accel_bias": "--accel-bias",
              "vibration": "--vibration", "plain_fraction": "--plain", "exposure_ms": "--blur-ms",
              "image_noise": "--image-noise", "drop_frames": "--drop-frames", "calib_error": "--calib-error",
              "stereo_error_px": "--stereo-error", "time_offset_drift_ms": "--time-offset-drift-ms",
              "time_offset_period_s": "--drift-period",
              "stamp_jitter_ms": "--stamp-jitter-ms", "recorded_start_s": "--recorded-start",
              "stamp_stall_every_s": "--stamp-stalls EVERY_S", "stamp_stall_ms": "--stamp-stalls MS",
              "seed": "--seed", "scene_seed": "--scene-seed", "aliasing_period_m": "--aliasing"}


def _size(text: str) -> tuple[int, int]:
    from vio import UsageError

    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size: expected WxH such as 752x480, got {text!r}") from None
    return w, h


def _window(text: str, flag: str = "--right-dropout", form: str = "START:LENGTH in seconds such as 20:5"
            ) -> tuple[float, float]:
    from vio import UsageError

    try:
        start, length = (float(x) for x in text.split(":"))
    except ValueError:
        raise UsageError(f"{flag}: expected {form}, got {text!r}") from None
    return start, length


def _stalls(text: str | None) -> dict:
    if text is None:
        return {}
    every, ms = _window(text, "--stamp-stalls", "EVERY_S:MS such as 10:120")
    return {"stamp_stall_every_s": every, "stamp_stall_ms": ms}


def run(args: argparse.Namespace) -> int:
    from vio import UsageError, VioError
    from vio.sim.generate import SimConfig, simulate

    w, h = _size(args.size)
    if args.imu_from is not None:
        model = {"--gyro-bias": args.gyro_bias, "--accel-bias": args.accel_bias, "--vibration": args.vibration,
                 "--no-imu-noise": args.no_imu_noise or None, "--imu-rate": None if args.imu_rate == 200.0 else 1}
        given = [k for k, v in model.items() if v is not None]
        if given:
            raise UsageError(f"{', '.join(given)}: the IMU of --imu-from is the recording's; these options change "
                           "only the simulated IMU")
    cfg = SimConfig(profile=args.profile, duration_s=args.duration, seed=args.seed, variant=args.variant,
                    rate_hz=args.rate, imu_rate_hz=args.imu_rate, still_start_s=args.still_start,
                    time_offset_ms=args.time_offset_ms, camera_model=args.camera_model, width=w, height=h,
                    imu_noise=not args.no_imu_noise, gyro_bias=args.gyro_bias, accel_bias=args.accel_bias,
                    vibration=args.vibration, plain_fraction=args.plain, exposure_ms=args.blur_ms,
                    image_noise=args.image_noise, drop_frames=args.drop_frames, scene_seed=args.scene_seed,
                    aliasing_period_m=args.aliasing, scene=args.scene, calib_error=args.calib_error,
                    stereo_error_px=args.stereo_error,
                    right_dropouts=tuple(_window(w) for w in args.right_dropout),
                    time_offset_drift_ms=args.time_offset_drift_ms, time_offset_period_s=args.drift_period,
                    stamp_jitter_ms=args.stamp_jitter_ms,
                    **_stalls(args.stamp_stalls),
                    imu_mount=args.imu_mount, imu_from=args.imu_from, recorded_start_s=args.recorded_start)
    try:  # every check of resolved() is on an option's value: a usage error (exit 2), named by the option
        cfg.resolved()
    except VioError as e:
        text = str(e).removeprefix("simulate: ")
        field = text.split(" ", 1)[0]
        rest = text[len(field):].removeprefix(" =")  # "--duration -3.0 is outside [0.1, 3600]"
        raise UsageError(_OPTION_OF[field] + rest if field in _OPTION_OF else text) from None
    summary = simulate(args.out, cfg, overwrite=args.overwrite, progress=not args.no_progress)
    print(summary.line())
    return 0
