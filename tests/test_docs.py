"""The documentation as tests: the CLI reference is what the argparse definitions say, every `--help` ends with
its guide page, the pages link to files that exist, and the README's quick tour and the fleet quick start run as
written (the ```sh blocks after a `<!-- test: NAME -->` comment, in a temporary folder beside the checkout's
replay_logs/ and docs/)."""
import contextlib
import importlib.util
import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from fuelid import cli

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
BIN = Path(sys.executable).parent  # the fuelid command of this environment


def make_cli():
    spec = importlib.util.spec_from_file_location("make_cli", ROOT / "docs" / "reference" / "make_cli.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_cli_reference_is_up_to_date():
    """docs/reference/cli.md is what make_cli.py writes now (else: python docs/reference/make_cli.py)."""
    assert (ROOT / "docs" / "reference" / "cli.md").read_text() == make_cli().render(), \
        "docs/reference/cli.md is out of date: run python docs/reference/make_cli.py"


def test_the_cli_reference_names_every_command_and_option():
    text = (ROOT / "docs" / "reference" / "cli.md").read_text()
    for name, parser in make_cli().subcommand_parsers().items():
        section = text.split(f"\n## fuelid {name}\n")[1].split("\n## ")[0]
        for action in parser._actions[1:]:  # after --help
            for option in action.option_strings:
                assert f"`{option}`" in section, (name, option)
            assert action.help, f"fuelid {name}: {action.option_strings or action.dest} has no help text"


@pytest.mark.parametrize("command", list(cli.COMMANDS))
def test_every_help_ends_with_its_guide_page(command, capsys):
    with pytest.raises(SystemExit):
        cli.main([command, "--help"])
    last = " ".join(capsys.readouterr().out.split()[-6:])
    page = cli.GUIDES[command]
    assert page in last, last
    assert (ROOT / page).is_file(), f"{page} does not exist"


LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_point_at_files(page):
    missing = [target for target in LINK.findall(page.read_text())
               if "://" not in target and not target.startswith("mailto:")
               and not (page.parent / target).exists()]
    assert not missing, f"{page.relative_to(ROOT)} links to missing files: {missing}"


# the words the project's own process leaves behind; documentation states what is true now
PROCESS_WORDS = re.compile(r"\b(session|sessions|helper-[0-9]+)\b|[0-9]{1,2} (Nov|Dec|Jan|Feb) |UTC|load average",
                           re.IGNORECASE)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_page_tells_how_the_work_was_organised(page):
    lines = [line for line in page.read_text().splitlines() if PROCESS_WORDS.search(line)]
    assert not lines, lines


def test_the_readme_stays_short():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 250


def test_the_readme_keeps_the_test_command_ci_runs():
    command = "python3 -m venv .venv && .venv/bin/pip install -q -e '.[test]' && .venv/bin/python -m pytest"
    assert command in (ROOT / "README.md").read_text()
    assert command in (ROOT / ".ci" / "run").read_text()


def marked_blocks(page: Path, name: str) -> str:
    """The ```sh blocks of `page` that follow a `<!-- test: NAME -->` line, joined."""
    blocks = re.findall(rf"<!-- test: {name} -->\s*```sh\n(.*?)```", page.read_text(), re.DOTALL)
    assert blocks, f"{page.relative_to(ROOT)} has no block marked <!-- test: {name} -->"
    return "\n".join(blocks)


def run_script(script: str, folder: Path, timeout: float) -> subprocess.CompletedProcess:
    """`script` under bash -e in `folder` (replay_logs/ and docs/ linked in), in its own process group, which is
    killed at the end whatever happened (a server started in the background included)."""
    for name in ("replay_logs", "docs"):
        (folder / name).symlink_to(ROOT / name)
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}"}
    env.pop("FUELID_SERVER", None)
    env.pop("FUELID_TOKEN", None)
    process = subprocess.Popen(["bash", "-euo", "pipefail", "-c", script], cwd=folder, env=env, text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        out, _ = process.communicate(timeout=timeout)
    finally:
        for sig in (signal.SIGTERM, signal.SIGKILL):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, sig)
        process.wait()
    return subprocess.CompletedProcess(process.args, process.returncode, out, None)


def test_the_readme_quick_tour_runs_as_written(tmp_path):
    """The tour: convert, identify, diagnose, identify --effects-from, compare, report, on the shipped trip."""
    result = run_script(marked_blocks(ROOT / "README.md", "tour"), tmp_path, timeout=900)
    assert result.returncode == 0, result.stdout[-3000:]
    assert (tmp_path / "out" / "report.html").stat().st_size > 100_000
    assert "RMS error fell from" in result.stdout


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_fleet_quick_start_runs_as_written_and_leaves_no_server(tmp_path):
    """docs/install/fleet-server.md's quick start, on a free port instead of 8000 (the machine may use 8000)."""
    pytest.importorskip("uvicorn")
    port = free_port()
    script = marked_blocks(ROOT / "docs" / "install" / "fleet-server.md", "fleet").replace("8000", str(port))
    result = run_script(script, tmp_path, timeout=900)
    assert result.returncode == 0, result.stdout[-3000:]
    assert (tmp_path / "model.json").is_file() and (tmp_path / "report.html").is_file()
    with socket.socket() as s:  # nothing listens on the port any more
        assert s.connect_ex(("127.0.0.1", port)) != 0
