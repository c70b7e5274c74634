"""`vio calib import|show|check|imu-noise|time-offset|refine`.

Heavy modules (cv2-based checks, allantools, matplotlib, depthai) are imported inside the actions so that
`vio --help` stays fast.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from vio.argtypes import positive_float_up_to, positive_int, seconds_from_start
from vio.evaluation import require_plot
from vio.io.outputs import check_new_file as check_output

log = logging.getLogger(__name__)

FORMATS = ("kalibr", "euroc", "depthai", "opencv")


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="calib_cmd", metavar="ACTION", required=True)

    s = sub.add_parser("import", help="convert kalibr/EuRoC/depthai/OpenCV calibration to the project's file",
                       description="kalibr: camchain-imucam.yaml [imu.yaml]; euroc: dataset folder or "
                       "cam0/cam1[/imu0] sensor.yaml; depthai: calibration JSON; opencv: stereo yaml/xml "
                       "(K1 D1 K2 D2 R T image size)")
    s.add_argument("format", choices=FORMATS)
    s.add_argument("files", nargs="+", type=Path)
    s.add_argument("-o", "--output", type=Path, required=True, help="project calibration YAML to write")
    s.add_argument("--overwrite", action="store_true", help="replace --output if it exists")
    s.add_argument("--cam-rate", type=float, default=20.0, help="camera frame rate [Hz] (files rarely say)")
    s.add_argument("--translation-unit", choices=("m", "cm", "mm"), default="m",
                   help="opencv only: unit of T (that of the calibration target)")
    s.add_argument("--size", metavar="WxH", help="depthai only: the resolution the camera streams ([source] "
                   "width x height); the intrinsics are scaled to it (default: the calibrated resolution)")

    s = sub.add_parser("show", help="print a calibration file in human-readable form")
    s.add_argument("file", type=Path)

    s = sub.add_parser("check", help="check a calibration against a EuRoC recording (PASS/WARN/FAIL)")
    s.add_argument("calibration", type=Path, help="project calibration YAML ('-' = the dataset's own)")
    s.add_argument("dataset", type=Path)
    s.add_argument("--max-frames", type=positive_int, default=40, help="stereo pairs to use (evenly spread)")
    s.add_argument("--disparity", action="store_true",
                   help="also replay the recording and check cam1 against cam0 with the estimator's stereo check: "
                   "the disparity bias and the focal lengths, which the epipolar checks cannot see (takes a replay: "
                   "about a quarter of its length)")
    s.add_argument("--config", type=Path, help="TOML configuration for the --disparity replay")
    s.add_argument("--strict", action="store_true", help="exit 1 on a WARN too (exit 1 is a FAIL; exit 4: the check "
                   "could not run, said on stderr)")

    s = sub.add_parser("imu-noise", help="IMU noise densities and random walks from Allan deviation")
    s.add_argument("dataset", type=Path, help="EuRoC dataset (or its imu0/data.csv)")
    s.add_argument("--start", type=seconds_from_start, default=None, help="first second to use (from the IMU start)")
    s.add_argument("--end", type=seconds_from_start, default=None, help="last second to use (from the IMU start)")
    s.add_argument("--plot", type=Path, help="write the Allan deviation plot (PNG)")
    s.add_argument("-o", "--output", type=Path, help="write kalibr-style imu.yaml with the fitted noise")
    s.add_argument("--overwrite", action="store_true", help="replace --output if it exists")

    s = sub.add_parser("time-offset", help="estimate the camera-IMU time offset (t_imu = t_cam + offset)")
    s.add_argument("dataset", type=Path)
    s.add_argument("--calibration", type=Path, help="project calibration YAML (default: the dataset's)")
    # a camera-IMU offset is tens of ms; 1e300 was said as "the IMU does not cover the frames", and 10^5 on a long
    # recording asked the search grid for gigabytes (a review's finding)
    s.add_argument("--max-offset-ms", type=positive_float_up_to(1000.0), default=100.0,
                   help="search range +- (at most 1000)")
    s.add_argument("--plot", type=Path, help="write the rate curves and correlation (PNG)")

    s = sub.add_parser("refine", help="refine the camera-IMU extrinsics (and time offset) by replaying a recording",
                       description="replays DATASET with the smoother refining T_body_cam0/T_body_cam1 "
                       "([backend] refine_extrinsics; only keyframes with enough rotation refine them) and "
                       "writes the calibration with the refined extrinsics and the in-flight time offset")
    s.add_argument("dataset", type=Path)
    s.add_argument("-o", "--output", type=Path, required=True, help="refined project calibration YAML to write")
    s.add_argument("--overwrite", action="store_true", help="replace --output if it exists")
    s.add_argument("--calibration", type=Path, help="project calibration YAML to start from (default: the dataset's)")
    s.add_argument("--config", type=Path, help="TOML configuration for the estimator")
    s.add_argument("--stereo", action="store_true", help="refine T_cam0_cam1 too (default: held)")
    s.add_argument("--stereo-only", action="store_true",
                   help="refine only cam1's rotation relative to cam0 ([backend] refine_stereo_rotation), the "
                   "camera-IMU extrinsic held: for a stereo calibration that drifted (a principal point or mount "
                   "off by a fraction of a pixel biases every depth); any recording that moves, no turns needed")
    s.add_argument("--intrinsics", action="store_true", help="refine the focal lengths of both cameras too "
                   "([backend] refine_intrinsics; cx, cy only with refine_principal_point; default: held)")


def _run_import(args: argparse.Namespace) -> int:
    from calib.importers import import_calibration
    from calib.show import format_calibration
    from vio import UsageError, VioError
    from vio.calibration import calibration_units_problem, save_calibration

    check_output(args.output, args.overwrite)
    kwargs = {"cam_rate_hz": args.cam_rate}
    if args.format == "opencv":
        kwargs["translation_unit"] = args.translation_unit
    if args.size:
        if args.format != "depthai":
            raise UsageError("--size: only a depthai calibration is rescaled on import (the others state their size)")
        w, _, h = args.size.lower().partition("x")
        if not (w.isdigit() and h.isdigit() and int(w) > 0 and int(h) > 0):
            raise UsageError(f"--size {args.size!r}: expected WIDTHxHEIGHT, e.g. 640x400")
        kwargs["size"] = (int(w), int(h))
    calib, notes = import_calibration(args.format, args.files, **kwargs)
    print(format_calibration(calib, title=f"imported {args.format}: {' '.join(map(str, args.files))}"))
    problem = calibration_units_problem(calib)
    if problem:  # it wrote such files and exited 0, and replay and run then refused them (a review's finding)
        raise VioError(f"{problem}; {args.output} not written (vio replay and vio run would refuse it): fix the "
                       "source file" + (" or --translation-unit" if args.format == "opencv" else ""))
    save_calibration(calib, args.output)
    if notes.messages:  # each was logged as a warning when it arose
        print(f"{len(notes.messages)} note(s) about assumptions/approximations: see the warnings above")
    print(f"wrote {args.output}")
    return 0


def _run_show(args: argparse.Namespace) -> int:
    from calib.show import format_calibration
    from vio.calibration import load_calibration

    print(format_calibration(load_calibration(args.file), title=str(args.file)))
    return 0


EXIT_NOT_CHECKED = 4  # `calib check` could not run (exit 1 is a check that FAILed): as `vio status` tells them apart


def _run_check(args: argparse.Namespace) -> int:
    from calib.check import check_calibration, format_report
    from vio.calibration import load_calibration

    if args.disparity:  # a replay whose verdict must not depend on what else the machine was doing
        from vio.frontend.runner import set_opencv_threads

        set_opencv_threads(1)

    try:
        calib = None if str(args.calibration) == "-" else load_calibration(args.calibration)
        results = check_calibration(args.dataset, calib, max_frames=args.max_frames, disparity=args.disparity,
                                    config=args.config)
    except Exception as e:  # said on stderr by the CLI (an internal error too), with this exit code: never a FAIL's 1
        e.exit_code = EXIT_NOT_CHECKED
        raise
    print(format_report(results))
    bad = ("FAIL", "WARN") if args.strict else ("FAIL",)
    return 1 if any(r.verdict in bad for r in results) else 0


def _reference_noise(dataset: Path):
    """The dataset's own imu0/sensor.yaml noise, to compare against (None when absent)."""
    from vio.io.euroc import read_imu_yaml

    yaml_path = (dataset / "mav0" / "imu0" / "sensor.yaml") if dataset.is_dir() else dataset.parent / "sensor.yaml"
    return read_imu_yaml(yaml_path) if yaml_path.is_file() else None


def _run_imu_noise(args: argparse.Namespace) -> int:
    from calib.allan import analyse_imu, format_noise, load_imu_for_allan, write_imu_yaml

    if args.output:
        check_output(args.output, args.overwrite, args.dataset)
    if args.plot:
        check_output(args.plot, True, args.dataset)
        require_plot(args.plot, "the Allan deviation plot")  # before the analysis, not after its printout
    imu, source = load_imu_for_allan(args.dataset, args.start, args.end)
    result = analyse_imu(imu)
    print(format_noise(result, source, _reference_noise(args.dataset)))
    if args.plot:
        from calib.allan import plot_allan

        plot_allan(result, args.plot)
        print(f"wrote {args.plot}")
    if args.output:
        write_imu_yaml(result.noise, args.output)
        print(f"wrote {args.output}")
    return 0


def _run_time_offset(args: argparse.Namespace) -> int:
    from calib.time_offset import estimate_time_offset_dataset

    if args.plot:
        check_output(args.plot, True, args.dataset)
        require_plot(args.plot, "the time-offset plot")
    est = estimate_time_offset_dataset(args.dataset, args.calibration, max_offset_s=args.max_offset_ms / 1e3)
    print(est.summary())
    if args.plot:
        from calib.time_offset import plot_time_offset

        plot_time_offset(est, args.plot)
        print(f"wrote {args.plot}")
    return 0


def _run_refine(args: argparse.Namespace) -> int:
    import dataclasses

    from calib.check import DISPARITY_SIGNIFICANT, disparity_told_from_zero
    from vio import UsageError, VioError
    from vio.calibration import load_calibration, save_calibration
    from vio.config import load_config
    from vio.consistency import replay_states
    from vio.estimator import stereo_check_line
    from vio.frontend.runner import set_opencv_threads

    if args.stereo_only and (args.stereo or args.intrinsics):
        raise UsageError("--stereo-only refines cam1's rotation alone: leave out --stereo and --intrinsics")

    check_output(args.output, args.overwrite, args.dataset)
    set_opencv_threads(1)  # the calibration written must not depend on what else the machine was doing
    cfg = load_config(args.config)
    cfg = dataclasses.replace(cfg, backend=dataclasses.replace(cfg.backend, refine_extrinsics=not args.stereo_only,
                                                               refine_stereo_extrinsic=args.stereo,
                                                               refine_stereo_rotation=args.stereo_only,
                                                               refine_intrinsics=args.intrinsics))
    run = replay_states(args.dataset, cfg.estimator,
                        calibration=load_calibration(args.calibration) if args.calibration else None)
    est, calib = run.estimator, run.dataset.calibration
    if not run.frame_states:  # a recording without readable images was said as "no keyframe had enough rotation"
        st = run.dataset.stats
        bad = st.missing_images + st.unreadable_images
        why = f" ({bad} of {len(run.dataset)} frames' images missing or unreadable, warned above)" if bad else ""
        raise VioError(f"{args.dataset}: the estimator never initialised{why}; nothing was refined")
    h = est.health()
    if h.frames_processed and h.frames_unusable >= h.frames_processed:  # was "no keyframe had enough rotation"
        top = sorted(h.unusable_reasons.items(), key=lambda kv: -kv[1])
        raise VioError(f"{args.dataset}: vision never worked ({h.frames_unusable} of {h.frames_processed} frames "
                       f"unusable: {', '.join(f'{n} {why}' for why, n in top[:4])}); nothing was refined")
    refined = est.refinement_stats()
    if args.stereo_only and not refined:
        raise VioError(f"{args.dataset}: the estimator never initialised; nothing was refined")
    if not args.stereo_only and (not refined or refined["refining_keyframes"] == 0):
        raise VioError(f"{args.dataset}: no keyframe had enough rotation to refine the extrinsics (a hover or "
                       "straight flight); record with turns about at least two axes")
    out = dataclasses.replace(est.refined_calibration(), time_offset_ns=int(est.time_offset_ns))
    if args.stereo_only:
        bias, sigma = refined["disparity_px"], refined.get("disparity_sigma_px")
        where = f"over {refined['refining_keyframes']} keyframes ({est.reset_counter} resets)"
        if not disparity_told_from_zero(bias, sigma):
            # what the recording cannot tell apart from zero is not a reason to change a calibration
            out = dataclasses.replace(out, cam1=calib.cam1)
            print(f"disparity bias {bias:+.2f} +- {sigma:.2f} px (1 sigma) {where}: under "
                  f"{DISPARITY_SIGNIFICANT:g} sigma, not shown by this recording (one that moves further, past near "
                  "and far texture, shows more); cam1 left as calibrated")
        else:
            told = "no uncertainty: the estimator was not running at the end" if sigma is None else \
                f"+- {sigma:.2f} px, 1 sigma"
            print(f"cam1 turned {refined['stereo_change_deg']:.4f} deg relative to cam0 {where}: a disparity bias of "
                  f"{bias:+.2f} px ({told}) taken out; the calibration's disparities were too "
                  f"{'large (depths too short)' if bias > 0 else 'small (depths too long)'}")
    else:
        print(f"T_body_cam0 moved {refined['cam0_change_deg']:.3f} deg, {refined['cam0_change_mm']:.2f} mm over "
              f"{refined['refining_keyframes']} refining keyframes ({est.reset_counter} resets); time offset "
              f"{calib.time_offset_ns * 1e-6:+.2f} -> {est.time_offset_ns * 1e-6:+.2f} ms")
        # the stereo pair is held as calibrated unless the stereo check (or --stereo) lets it go
        line = stereo_check_line(est.stereo_check_stats(), then="")
        if line:
            print(f"{line}; cam1 relative to cam0 moved {refined['stereo_change_deg']:.4f} deg")
    save_calibration(out, args.output)
    if args.intrinsics:
        for name, before, after in (("cam0", calib.cam0, out.cam0), ("cam1", calib.cam1, out.cam1)):
            print(f"{name} fx fy cx cy moved " + " ".join(f"{getattr(after, k) - getattr(before, k):+.2f}"
                                                         for k in ("fx", "fy", "cx", "cy")) + " px")
    print(f"wrote {args.output}")
    return 0


_ACTIONS = {"import": _run_import, "show": _run_show, "check": _run_check, "imu-noise": _run_imu_noise,
            "time-offset": _run_time_offset, "refine": _run_refine}


def run(args: argparse.Namespace) -> int:
    return _ACTIONS[args.calib_cmd](args)
