"""The `fuelid` command: one subcommand per module in fuelid/commands.

COMMANDS gives each command's one-line help; its module defines add_arguments(parser) and run(args) -> int exit
code. Only the module of the command being run is imported, so `fuelid --help` stays fast.
"""
import argparse
import importlib
import os
import sys

from fuelid import __version__
from fuelid.errors import FuelidError
from fuelid.paths import os_error_message, readable_file, writable_file

# command -> its one-line help; the module fuelid.commands.<command> holds the rest. In the order of the data flow.
COMMANDS = {
    "convert": "convert recorded CAN logs (candump, ASC, BLF, TRC, MF4) and flow-meter captures to MCAP",
    "recover": "rewrite an MCAP log cut by a power loss or with damaged chunks as a valid, indexed file",
    "log": "log a CAN bus (and the flow meter) to rotated MCAP files until stopped; the in-cab daemon",
    "status": "show the logger daemon's health: uptime, frames/s, drops, decode errors, current file, serial, VIN",
    "replay": "play recorded CAN logs (candump, ASC, BLF, TRC, MCAP) onto a CAN bus with their original timing",
    "simulate": "simulate a truck trip: FMS CAN log (+ gas flow-meter capture) and its truth files",
    "dataset": "resample MCAP recordings to an identification data set (CSV or MATLAB .mat)",
    "identify": "identify a Box-Jenkins fuel-flow model (engine speed, torque -> fuel) from MCAP recordings",
    "compare": "compare model files with measurements (fit, whiteness, cycle fuel error) and static baselines",
    "diagnose": "diagnose a model on recordings: where it fails and which physical effect is missing (ranked, tested)",
    "report": "write the diagnosis of a model (and the models refitted with effects) as one offline HTML report",
    "export": "export a model.json for MATLAB: a script rebuilding it as an idpoly (--to matlab) or a .mat file "
              "(--to mat)",
    "online": "run the online BJ estimator (recursive prediction error or Kalman) over MCAP recordings",
    "warmup": "compile and cache the online estimators' numba kernels (run once after install, e.g. in an image)",
    "serve": "run the fleet server: truck uploads, per-truck model registry, identification jobs on Dask",
    "token": "create, list or revoke fleet API tokens (--data-dir/--database-url offline, else via --server)",
    "upload": "upload MCAP files to the fleet server (resumes cut uploads; idempotent by sha256)",
    "trucks": "list the fleet's trucks, or one truck's files and model versions (fleet server)",
    "fetch": "download a truck's fuel model (latest or --version V) and its report from the fleet server",
    "refit": "start identification jobs on the fleet server for one truck or the whole fleet (--all)",
}


# command -> the documentation page of its task (every `--help` ends with it)
GUIDES = {
    "convert": "docs/guide/log-and-convert.md",
    "recover": "docs/guide/log-and-convert.md",
    "log": "docs/guide/log-and-convert.md",
    "status": "docs/install/in-cab-logger.md",
    "replay": "docs/guide/log-and-convert.md",
    "simulate": "docs/guide/simulator.md",
    "dataset": "docs/guide/identify-and-compare.md",
    "identify": "docs/guide/identify-and-compare.md",
    "compare": "docs/guide/identify-and-compare.md",
    "diagnose": "docs/guide/diagnose.md",
    "report": "docs/guide/report.md",
    "export": "docs/guide/matlab-and-foxglove.md",
    "online": "docs/guide/online.md",
    "warmup": "docs/guide/online.md",
    "serve": "docs/install/fleet-server.md",
    "token": "docs/install/fleet-server.md",
    "upload": "docs/install/fleet-server.md",
    "trucks": "docs/install/fleet-server.md",
    "fetch": "docs/install/fleet-server.md",
    "refit": "docs/install/fleet-server.md",
}
REFERENCE = "docs/reference/cli.md"
EXIT_CODES = "exit status: 0 done, 1 error (one line on stderr), 2 wrong usage, 130 interrupted"


def epilog(command: str | None = None) -> str:
    """The last lines of a `--help`: where the command's guide is (paths in the fuelid source tree)."""
    if command is None:
        return f"Start with README.md; every command and option: {REFERENCE}. {EXIT_CODES}."
    return f"Guide: {GUIDES[command]}; every option: {REFERENCE}."


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    """The parser for `argv`: only the named command's module is imported (none for the overview help)."""
    parser = argparse.ArgumentParser(prog="fuelid", description="Truck CAN logger and fuel-flow model identification.",
                                     epilog=epilog())
    parser.add_argument("--version", action="version", version=f"fuelid {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, summary in COMMANDS.items():
        p = sub.add_parser(name, help=summary, description=summary, epilog=epilog(name))
        if name in argv[:1]:
            module = importlib.import_module(f"fuelid.commands.{name}")
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
                   "identify_model", "effects_file")
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
