"""`vio` command line.

Each subcommand lives in its own module with `add_arguments(parser)` and `run(args) -> int`. Command
modules import heavy dependencies (gtsam, depthai, pymavlink, matplotlib) inside `run`, so that
`vio --help` stays fast and a broken optional dependency breaks only the command that needs it."""

from __future__ import annotations

import argparse
import errno
import importlib
import importlib.util
import logging
import os
import sys

from vio import VioError, __version__

# name -> (module, one-line help). Modules define add_arguments(parser) and run(args) -> exit code.
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("vio.app.simulate", "generate a synthetic stereo+IMU flight (EuRoC format) with known truth"),
    "replay": ("vio.app.replay", "run the estimator on a recorded EuRoC dataset; write trajectory and stats"),
    "batch": ("vio.app.batch", "replay many flights in parallel (local workers or Ray) into one report"),
    "demo": ("vio.app.demo", "simulate a short flight, replay it and print accuracy and speed"),
    "eval": ("vio.evaluation", "compare an estimated trajectory with ground truth (ATE, RPE, plot)"),
    "config": ("vio.app.config_cli", "check or show the configuration file"),
    "calib": ("calib.cli", "import, show and check calibrations; IMU noise; camera-IMU time offset"),
    "record": ("drivers.record", "record live sensors to a EuRoC dataset or an MCAP file"),
    "run": ("vio.app.daemon.service", "onboard daemon: sensors -> estimator -> MAVLink"),
    "status": ("vio.app.status", "show the health of a running `vio run`"),
    "loop": ("vio.app.loop_cli", "loop closure tools: train the place-recognition vocabulary"),
    "map": ("vio.app.map_cli", "inspect a saved loop-closure map (vio replay --save-map)"),
}

# Exit codes shared by all commands.
EXIT_OK = 0
# OSErrors that are the user's to fix (what they pointed a command at), said in one line, not as internal errors
# ENAMETOOLONG: a path given over the file system's limits, met in any of the look-ups a command makes (a review's
# finding: `vio replay`, `batch`, `eval`, `calib import / imu-noise / check`, ... each ended in an internal error)
_USER_OS_ERRORS = (errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EDQUOT, errno.ENOENT, errno.ENOTDIR,
                   errno.EISDIR, errno.EEXIST, errno.ENAMETOOLONG)
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_CONFIG = 3


def _module_available(module: str) -> bool:
    return importlib.util.find_spec(module.rsplit(".", 1)[0]) is not None and \
        importlib.util.find_spec(module) is not None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vio",
        description="Kestrel VIO: stereo visual-inertial odometry for drones.",
    )
    parser.add_argument("--version", action="version", version=f"kestrel-vio {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        if not _module_available(module):
            continue
        try:
            mod = importlib.import_module(module)
        except Exception as e:  # a broken optional module must not take the whole CLI down
            logging.getLogger(__name__).debug("command %s unavailable: %s", name, e)
            sub.add_parser(name, help=f"{help_text} (unavailable: {e})")
            continue
        p = sub.add_parser(name, help=help_text, description=help_text)
        mod.add_arguments(p)
        p.set_defaults(_module=module)
    return parser


def _one_line(text: str) -> str:
    """A message as one line (YAML and OpenCV errors span several)."""
    return " ".join(part.strip() for part in str(text).splitlines() if part.strip())


def main(argv: list[str] | None = None) -> int:
    """Run one command. Its errors end as one line on stderr and an exit code, never a traceback: a VioError
    (bad input, said in its message) exits EXIT_FAILURE; an unexpected exception also, with the traceback
    only under -v; Ctrl-C exits 130."""
    raw = sys.argv[1:] if argv is None else argv
    command = next((a for a in raw if not a.startswith("-")), "?")  # global options take no value
    verbose = False
    try:
        if not {"-v", "--verbose"} & set(raw):
            # OpenCV logs corrupt images to stderr itself; the reader counts and reports them (-v shows them)
            os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")
        parser = build_parser()
        args = parser.parse_args(argv)
        command, verbose = getattr(args, "command", None) or command, bool(args.verbose)
        level = logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
        if args.quiet and hasattr(args, "no_progress"):  # -q: warnings and errors only, no progress bar either
            args.no_progress = True
        logging.basicConfig(level=level, format="%(asctime)s %(levelname)-7s %(name)s: %(message)s")
        if getattr(args, "command", None) and not hasattr(args, "_module"):
            print(f"vio {args.command}: this command is unavailable in this installation", file=sys.stderr)
            return EXIT_FAILURE
        if not getattr(args, "command", None):
            parser.print_help()
            return EXIT_USAGE
        return int(importlib.import_module(args._module).run(args) or 0)
    except VioError as e:
        print(f"vio {command}: error: {_one_line(e)}", file=sys.stderr)
        return getattr(e, "exit_code", EXIT_FAILURE)  # a command may give its own (`calib check`: 4, not checked)
    except KeyboardInterrupt:
        print(f"vio {command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `vio ... | head`: the reader left; nothing more to say
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_FAILURE
    except Exception as e:
        if isinstance(e, OSError) and e.errno in _USER_OS_ERRORS and not verbose:
            # a place the user gave that cannot be written (read-only, full, no permission): their fix, not a bug
            where = f"{e.filename}: " if e.filename else ""
            print(f"vio {command}: error: {where}{e.strerror or e}", file=sys.stderr)
            return getattr(e, "exit_code", EXIT_FAILURE)
        if verbose:
            import traceback

            traceback.print_exc()
        hint = "" if verbose else f" (`vio -v {command} ...` shows the traceback)"
        print(f"vio {command}: internal error: {type(e).__name__}: {_one_line(e)}{hint}", file=sys.stderr)
        return getattr(e, "exit_code", EXIT_FAILURE)


if __name__ == "__main__":
    sys.exit(main())
