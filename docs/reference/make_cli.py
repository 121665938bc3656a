"""Write docs/reference/cli.md, the command-line reference, from the argparse definitions of `fuelid`.

    python docs/reference/make_cli.py           # rewrite docs/reference/cli.md
    python docs/reference/make_cli.py --check   # exit 1 if docs/reference/cli.md is not what this writes

The help strings in fuelid/commands/*.py are the source: edit them, then run this. tests/test_docs.py fails
when the file is out of date. An option's default is shown from argparse unless its help text states it.
"""
import argparse
import sys
from pathlib import Path

from fuelid import cli

OUT = Path(__file__).with_name("cli.md")

HEADER = """# Command-line reference

Generated from the argparse definitions by `python docs/reference/make_cli.py`; do not edit by hand (edit
the help strings in `fuelid/commands/*.py` and run it again: `tests/test_docs.py` fails when this page is out
of date). Units are in brackets; `fuelid COMMAND --help` prints the same text, `fuelid --help` the list of
commands and `fuelid --version` the version.

## Exit status

| code | meaning |
|---|---|
| 0 | done |
| 1 | error: one line on stderr, `fuelid COMMAND: error: …` (set `FUELID_DEBUG=1` for the traceback); also `status` when the logger is not running, `upload` when a file was refused, `refit --wait` when a job failed or is still running |
| 2 | wrong usage: an unknown option, a missing or malformed argument (argparse's message), or no command |
| 130 | interrupted (Ctrl-C) |

Every command that prints a result has `--json` (strict JSON on stdout), except `log` (a daemon: `status
--json` reports on it) and `report` and `export`, whose result is the file they write. Environment variables:
[environment.md](environment.md).

## Commands

| command | what it does |
|---|---|
"""


def subcommand_parsers() -> dict[str, argparse.ArgumentParser]:
    """Each command's parser, with its module's arguments (cli.build_parser adds them for the command named)."""
    parsers = {}
    for name in cli.COMMANDS:
        root = cli.build_parser([name])
        sub = next(a for a in root._actions if isinstance(a, argparse._SubParsersAction))
        parsers[name] = sub.choices[name]
    return parsers


def value_name(action: argparse.Action) -> str:
    """What follows the option (or stands for the positional): its metavar, choices, or dest."""
    if action.nargs == 0:
        return ""
    if action.metavar is not None:
        name = action.metavar
    elif action.choices is not None:
        name = "|".join(map(str, action.choices))
    else:
        name = action.dest.upper()
    return {"+": f"{name} …", "*": f"[{name} …]", "?": f"[{name}]"}.get(action.nargs, name)


def describe(action: argparse.Action) -> str:
    """The help text, with the argparse default appended unless the text states it."""
    text = (action.help or "").replace("%%", "%")
    default = action.default
    if default not in (None, False, [], argparse.SUPPRESS) and "default" not in text and action.option_strings:
        text += f" (default {default})"
    if action.required and action.option_strings:
        text += " (required)"
    if action.choices is not None and action.metavar is not None:
        text += f" (one of {', '.join(map(str, action.choices))})"
    return text


def synopsis(name: str, parser: argparse.ArgumentParser) -> str:
    """`fuelid NAME POSITIONALS required-options [options]`."""
    words = [f"fuelid {name}"]
    for action in parser._actions:
        if not action.option_strings:
            words.append(value_name(action))
        elif action.required:
            words.append(f"{action.option_strings[0]} {value_name(action)}".strip())
    if any(a.option_strings and not a.required and not isinstance(a, argparse._HelpAction) for a in parser._actions):
        words.append("[options]")
    return " ".join(words)


def cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def command_section(name: str, parser: argparse.ArgumentParser) -> list[str]:
    lines = [f"## fuelid {name}", "", cli.COMMANDS[name][0].upper() + cli.COMMANDS[name][1:] + ".", "",
             "```", synopsis(name, parser), "```", "",
             "| argument | value | meaning |", "|---|---|---|"]
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        label = ", ".join(f"`{o}`" for o in action.option_strings) or f"`{value_name(action)}`"
        value = f"`{value_name(action)}`" if action.option_strings and value_name(action) else ""
        lines.append(f"| {label} | {cell(value)} | {cell(describe(action))} |")
    guide = cli.GUIDES[name]
    lines += ["", f"Guide: [{guide}](../{guide.removeprefix('docs/')}).", ""]
    return lines


def render() -> str:
    parsers = subcommand_parsers()
    lines = [HEADER.rstrip("\n")]
    lines += [f"| [`{name}`](#fuelid-{name}) | {cell(summary)} |" for name, summary in cli.COMMANDS.items()]
    lines.append("")
    for name, parser in parsers.items():
        lines += command_section(name, parser)
    return "\n".join(lines).rstrip("\n") + "\n"


def main(argv=None) -> int:
    check = "--check" in (sys.argv[1:] if argv is None else argv)
    text = render()
    if check:
        if not OUT.exists() or OUT.read_text() != text:
            print(f"{OUT} is out of date: run python {Path(__file__).as_posix()}", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text)
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
