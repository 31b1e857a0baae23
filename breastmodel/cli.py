"""``breastmodel`` command line: one sub-command per module in ``breastmodel.commands``."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from breastmodel import __version__
from breastmodel.commands import COMMANDS


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="breastmodel",
        description="Subject-specific breast biomechanics from MRI.",
    )
    parser.add_argument("--version", action="version", version=f"breastmodel {__version__}")
    parser.add_argument(
        "--log-level",
        default="INFO",
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="logging verbosity (default INFO)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"breastmodel.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"breastmodel.commands.{name}":
                raise
            continue  # a command not installed in this build
        p = module.add_parser(sub)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except (ValueError, OSError, RuntimeError) as exc:
        # One clear line for the user; the traceback only at DEBUG.
        logging.getLogger("breastmodel").debug("traceback", exc_info=True)
        print(f"error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
