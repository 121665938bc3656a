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
from fuelid.paths import os_error_message, readable_file, writable_file

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
        check_paths(args)
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print(f"fuelid {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # one line on stderr, never a traceback (FUELID_DEBUG=1 shows it)
        if os.environ.get("FUELID_DEBUG"):
            raise
        if isinstance(exc, OSError):
            message = os_error_message(exc)
        else:
            message = f"{'' if isinstance(exc, FuelidError) else type(exc).__name__ + ': '}{exc}"
        print(f"fuelid {args.command}: error: {message}", file=sys.stderr)
        return 1


# files every command that has them reads (--diagnosis differs: fetch writes it, report reads it)
INPUT_ARGUMENTS = ("inputs", "input", "model", "files", "flowmeter", "effects_from", "map_from", "config", "prior",
                   "identify_model")
OUTPUT_ARGUMENTS = ("output",)  # -o: the file a command writes


def check_paths(args) -> None:
    """The named input files are readable and the output's folder exists, before a command starts work, so
    that a wrong path is an error naming it (a command's own file options it checks itself)."""
    for name in INPUT_ARGUMENTS:
        value = getattr(args, name, None)
        for path in value if isinstance(value, list) else [value] if value is not None else []:
            readable_file(path)
    for name in OUTPUT_ARGUMENTS:
        if getattr(args, name, None) is not None:
            writable_file(args.output)


if __name__ == "__main__":
    sys.exit(main())
