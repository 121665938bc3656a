"""The `fuelid` command: one subcommand per module in fuelid/commands.

Each command module defines HELP (one line), add_arguments(parser) and run(args) -> int exit code.
Command modules import their heavy dependencies inside run(), so `fuelid --help` stays fast.
"""
import argparse
import importlib
import os
import sys

from fuelid import __version__
from fuelid.errors import FuelidError

# name -> module under fuelid.commands; listed in the order of the data flow.
COMMANDS = [
    "convert",
    "recover",
    "log",
    "status",
    "replay",
    "simulate",
    "dataset",
    "identify",
    "compare",
    "diagnose",
    "report",
    "export",
    "online",
    "serve",
    "token",
    "upload",
    "trucks",
    "fetch",
    "refit",
]


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    """The parser for `argv`: only the named command's module is imported (all of them for the overview help)."""
    parser = argparse.ArgumentParser(prog="fuelid", description="Truck CAN logger and fuel-flow model identification.")
    parser.add_argument("--version", action="version", version=f"fuelid {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    chosen = [name for name in COMMANDS if name in argv[:1]] or COMMANDS
    for name in chosen:
        module = importlib.import_module(f"fuelid.commands.{name}")
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print(f"fuelid {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # one line on stderr, never a traceback (FUELID_DEBUG=1 shows it)
        if os.environ.get("FUELID_DEBUG"):
            raise
        kind = "" if isinstance(exc, (FuelidError, OSError)) else f"{type(exc).__name__}: "
        print(f"fuelid {args.command}: error: {kind}{exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
