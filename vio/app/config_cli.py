"""`vio config check FILE` and `vio config show [FILE]`."""

from __future__ import annotations

import argparse
import sys

from vio import VioError
from vio.config import config_to_toml, load_config


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="config_cmd", metavar="ACTION", required=True)
    c = sub.add_parser("check", help="validate a TOML config file as `vio run` would at start (the files and "
                       "connections it names included)")
    c.add_argument("file")
    s = sub.add_parser("show", help="print the effective config (defaults merged with FILE)")
    s.add_argument("file", nargs="?")


def run(args: argparse.Namespace) -> int:
    from vio.app.cli import EXIT_CONFIG

    plan = None
    try:
        cfg = load_config(args.file)
        if args.config_cmd == "check":  # and what `vio run` checks at start: files it names, connection strings
            from vio.app.daemon.service import check_run_config, checkpoint_plan

            try:
                plan = checkpoint_plan(cfg, check_run_config(cfg).map_data)
            except VioError as e:
                raise VioError(f"{args.file}: {e}") from None
    except VioError as e:  # an invalid config has its own exit code, as in `vio run`
        print(f"vio config: error: {e}", file=sys.stderr)
        return EXIT_CONFIG
    if args.config_cmd == "check":
        print(f"{args.file}: OK")
        if plan is not None and plan.action:  # what `vio run` would do with it, said before it does
            print(f"note: {plan.ahead}")
    else:
        print(config_to_toml(cfg), end="")
    return 0
