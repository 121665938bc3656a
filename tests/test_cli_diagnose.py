"""The diagnosis loop end to end through the commands a user runs, on a short simulated trip with a hidden DPF
regeneration: identify → diagnose names it → identify --effect → compare shows the error falling."""
import fcntl
import json
import os
import pty
import select
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path

import numpy as np
import pytest

from fuelid.cli import main
from tests.conftest import run_json


@pytest.fixture(scope="module")
def trip(tmp_path_factory):
    out = tmp_path_factory.mktemp("loop")
    assert main(["simulate", "--truth", "diesel_p320", "--cycle", "mixed", "--duration", "1200", "--seed", "2004",
                 "--effect", "dpf_regeneration=0.1", "-o", str(out / "trip.log.gz"), "--json"]) == 0
    assert main(["convert", str(out / "trip.log.gz"), "-o", str(out / "trip.mcap"), "--json"]) == 0
    return out


def test_identify_diagnose_add_the_effect_and_watch_the_error_fall(trip, capsys):
    data, before, after, saved = trip / "trip.mcap", trip / "before.json", trip / "after.json", trip / "diag.json"
    run_json(capsys, "identify", data, "-o", before)
    result = run_json(capsys, "diagnose", before, data)
    top = result["candidates"][0]
    assert top["id"] == "dpf_regeneration" and top["recommended"] and 3700 in top["spns"]
    assert top["status"] == "recommended" and "add dpf_regeneration (" in result["verdict"]
    assert top["held_out"]["passes"] and top["rmse_drop_percent"] >= 1
    assert run_json(capsys, "diagnose", before, data, "--jobs", 1) == result  # in one process: the same diagnosis
    strict = run_json(capsys, "diagnose", before, data, "--min-drop", 100)  # a fall no effect can reach
    assert "no missing effect recommended" in strict["verdict"]
    dpf = next(c for c in strict["candidates"] if c["effect"] == "dpf_regeneration")
    assert not dpf["recommended"] and dpf["status"] == "named, not recommended" and dpf["reason"] == "no_held_out_gain"
    for c in result["candidates"] + strict["candidates"]:  # the flag and the words are one status
        assert c["recommended"] is (c["status"] == "recommended") and c["explanation"].startswith(c["status"])
    saved.write_text(json.dumps(result))
    run_json(capsys, "identify", data, "--effects-from", saved, "-o", after)
    compared = run_json(capsys, "compare", before, after, data)
    rmse = [m["rmse"]["simulation"] for m in compared["models"]]
    floor = float(np.sqrt(np.mean(np.load(trip / "trip.truth.npz")["noise"] ** 2)))  # the simulator's noise H e
    assert (rmse[1] <= 0.75 * rmse[0] or rmse[1] <= 1.05 * floor) and rmse[1] < 0.85 * rmse[0]


def error_output_on_a_terminal(command: list[str]) -> str:
    """What `command` writes to its error output when that is a terminal (a pseudo-terminal of 120 columns); its
    standard output goes nowhere."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 30, 120, 0, 0))
    proc = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=slave)
    os.close(slave)
    shown, deadline = b"", time.monotonic() + 600
    try:
        while time.monotonic() < deadline:  # read as it runs: a full terminal buffer would stop the command
            if select.select([master], [], [], 1.0)[0]:
                try:
                    chunk = os.read(master, 65536)
                except OSError:  # the command has exited and closed the terminal
                    chunk = b""
                if not chunk:
                    break
                shown += chunk
            elif proc.poll() is not None:
                break
        assert proc.wait(timeout=30) == 0
    finally:
        os.close(master)
        if proc.poll() is None:  # past the deadline: no command is left running
            proc.kill()
            proc.wait()
    return shown.decode(errors="replace")


def test_on_a_terminal_diagnose_shows_each_model_it_builds(trip, capsys):
    data, model = trip / "trip.mcap", trip / "shown.json"
    run_json(capsys, "identify", data, "-o", model)
    shown = error_output_on_a_terminal([sys.executable, "-m", "fuelid.cli", "diagnose", str(model), str(data)])
    assert "diagnose:" in shown and "round 1: dpf_regeneration" in shown


def test_identify_says_in_one_plain_line_what_the_estimators_warnings_mean(trip, capsys):
    """The paper's orders on 20 min: near-cancelling pole-zero pairs. One plain note by default; the estimator's
    details with --verbose."""
    model = trip / "plain.json"
    assert main(["identify", str(trip / "trip.mcap"), "-o", str(model)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["note: the fit is fine, but some coefficients are not determined by these data (near-cancelling "
                   "poles and zeros); consider --orders auto (details: --verbose)"]
    assert main(["identify", str(trip / "trip.mcap"), "-o", str(model), "--verbose"]) == 0
    details = capsys.readouterr().err.strip().splitlines()[1:]
    assert details and all(line.startswith("  ") for line in details)
    assert any("pole-zero cancellation" in line for line in details)

    # diagnose's text: times in minutes since the start as in the report, whole candidate names, plurals
    result = run_json(capsys, "diagnose", model, trip / "trip.mcap")
    assert main(["diagnose", str(model), str(trip / "trip.mcap")]) == 0
    text = capsys.readouterr().out
    for s in result["where_it_fails"]["worst_segments"][:3]:
        assert f"  {s['t_start_min']:.2f}–{s['t_end_min']:.2f} min: RMS {s['rmse']:.2f} L/h" in text
    assert f"({result['test']['candidates_tested']} tested" in text and result["verdict"] in text
    shown = [c["effect"] for c in result["candidates"] if c.get("testable")][:8]
    assert all(f"  {name} " in text for name in shown)


def test_bad_input_is_one_line_on_stderr(trip, capsys):
    assert main(["diagnose", str(trip / "missing.json"), str(trip / "trip.mcap")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("fuelid diagnose: error:") and "\n" not in err
    with pytest.raises(SystemExit) as usage:
        main(["diagnose", str(trip / "missing.json"), str(trip / "trip.mcap"), "--jobs", "0"])
    assert usage.value.code == 2 and "--jobs: must be at least 1, got 0" in capsys.readouterr().err


EXAMPLE_EFFECTS = Path(__file__).resolve().parents[1] / "docs" / "effects-example.toml"


def test_effects_the_engineer_defines_are_tested_and_added(trip, capsys):
    """docs/effects-example.toml defines the DPF regeneration again (an on/off state scaling the fuel): tested
    beside the built-in one; one of the two is recommended, the other is explained by it (re-screened after it);
    `identify --effects-file --effect` adds it, and the model runs without the file afterwards."""
    data, before, mine = trip / "trip.mcap", trip / "before_file.json", trip / "mine.json"
    run_json(capsys, "identify", data, "-o", before)
    result = run_json(capsys, "diagnose", before, data, "--effects-file", EXAMPLE_EFFECTS)
    by_id = {c["effect"]: c for c in result["candidates"]}
    assert {"regen_from_file", "hot_intake_air", "parasitic_torque"} <= set(by_id)
    regen, builtin = by_id["regen_from_file"], by_id["dpf_regeneration"]
    assert regen["spns"] == [3700]
    assert sorted([regen["recommended"], builtin["recommended"]]) == [False, True]
    named, other = (regen, builtin) if regen["recommended"] else (builtin, regen)
    assert other["status"] == "explained by" and other["explained_by"] == named["id"]
    run_json(capsys, "identify", data, "--effects-file", EXAMPLE_EFFECTS, "--effect", "regen_from_file", "-o", mine)
    compared = run_json(capsys, "compare", before, mine, data)  # no --effects-file: the model carries it
    rmse = [m["rmse"]["simulation"] for m in compared["models"]]
    assert rmse[1] < 0.85 * rmse[0]


def test_a_bad_effect_file_is_one_line_naming_file_effect_and_field(trip, tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(EXAMPLE_EFFECTS.read_text().replace('above = 30.0', 'above = "hot"'))
    model = tmp_path / "model.json"
    model.write_text("{}")  # never read: the effect file is checked first
    assert main(["diagnose", str(model), str(trip / "trip.mcap"), "--effects-file", str(bad)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"fuelid diagnose: error: {bad}: effect 'hot_intake_air': x.above: must be a number, not 'hot'"]
    assert main(["identify", str(trip / "trip.mcap"), "-o", str(tmp_path / "m.json"), "--effect", "regen_from_file"]) != 0
    assert "unknown effect 'regen_from_file'" in capsys.readouterr().err
