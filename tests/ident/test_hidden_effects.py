"""Issue 7's acceptance tests on the truck simulator: a 20-minute diesel trip with one hidden physical effect,
through the bus and fuelid's decoder, identified with the paper's orders and diagnosed.

For each hidden effect the top significant candidate names it (or its signal's SPN), and adding it lowers the
held-out RMS simulation error (two-fold interleaved refits, ident.diagnosis.verify) by ≥ 25 % or to the noise
floor — the RMS of the simulator's noise H e (truth.npz `noise`), +5 % — and the cycle fuel error falls. With
nothing hidden no candidate is significant. Simulated data are cached per session (tests.ident.hidden).
benchmarks/bench_diagnose.py --acceptance runs the same on more seeds.

Not all of it holds yet: the cases that fail are marked xfail(strict=True) with what happens (deterministic
seeds, so a mark that stops being true fails the suite). Not tested here because not found on such trips at
the default magnitudes (benchmarks/bench_diagnose.py --acceptance reports them): cold_engine, engine_fan,
gear_shift, ambient, and fuel_delay, which the paper's five torque taps absorb — seed 2's sweep finds that one
(test below).
"""
import warnings

import numpy as np
import pytest

from ident import diagnosis as dg
from ident.effects import estimate_fuel_delay
from ident.polymodel import Structure
from tests.ident import hidden

FLOOR_TOLERANCE = 1.05


def diagnosed(effect, seed):
    ds, truth, summary = hidden.simulated(effect, seed)
    return dg.diagnose(hidden.identify(ds), ds), truth, summary


def names(row, effect, summary) -> bool:
    """The candidate names the hidden effect: its id, or one of the SPNs the simulator shows it on."""
    spns = {p for e in summary["effects"] for p in e["spns"]}
    return row["effect"] == effect or bool(spns & set(row["spns"]) - {190, 513})  # not just speed / torque




def gap(effect, seed, why):
    return pytest.param(effect, seed, marks=pytest.mark.xfail(strict=True, reason=why))


@pytest.mark.parametrize("effect, seed", [
    ("dpf_regeneration", 2004), ("dpf_regeneration", 3004), ("inertia", 2004),
    gap("inertia", 3004, "named, but the held-out error falls by 4 % and stays 5 % above the noise floor"),
    gap("power_nonlinearity", 2004, "detectable (estimated drop < 1 %) but below the relevance threshold"),
    gap("power_nonlinearity", 3004, "named, held-out error falls by 14 %, not to the noise floor"),
    gap("overrun_cutoff", 2004, "below the relevance threshold on this trip"),
    gap("overrun_cutoff", 3004, "the retarder (SPN 520), active in the same overrun phases, is named first"),
])
def test_hidden_effect_is_named_and_adding_it_lowers_the_error(effect, seed):
    out, truth, summary = diagnosed(effect, seed)
    top = out["candidates"][0]
    assert top["significant"], out["verdict"]
    assert names(top, effect, summary), top["effect"]
    v = top["verification"]
    floor = float(np.sqrt(np.mean(truth["noise"] ** 2)))
    assert v["rmse_drop_percent"] >= 25 or v["rmse_with"] <= FLOOR_TOLERANCE * floor, (v, floor)
    assert abs(v["cycle_fuel_error_percent_with"]["rms"]) <= abs(v["cycle_fuel_error_percent_without"]["rms"]) + 0.1


@pytest.mark.parametrize("seed", [
    pytest.param(11, marks=pytest.mark.xfail(strict=True, reason="false alarm: idle_fuelling, held-out drop 5 %")),
    12, 13])
def test_with_nothing_hidden_no_candidate_is_significant(seed):
    out, _, _ = diagnosed(None, seed)
    assert not any(r["significant"] for r in out["candidates"]), out["verdict"]
    assert out["verdict"].startswith("No significant candidate")


def test_hidden_inertia_is_found_within_20_percent_of_its_J():
    """The J of the fitted inertia effect (diagnose's refit) against the simulator's J (truth.json)."""
    out, _, summary = diagnosed("inertia", 2004)
    row = next(r for r in out["candidates"] if r["effect"] == "inertia")
    J = summary["engine"]["inertia_kgm2"]
    assert abs(row["size"]["inertia_kgm2"] - J) <= 0.2 * J, (row["size"], J)


def test_hidden_fuel_delay_is_found_within_a_tenth_of_a_second():
    """Seed 2's sweep (±1 s, parabola through the best three) with a low-order model refitted at each shift."""
    ds, _, summary = hidden.simulated("fuel_delay", 2004)
    sweep = estimate_fuel_delay(ds, ds.u, Structure(nb=(2, 2), nf=(1, 1), nk=(0, 0)))
    assert abs(sweep["best_s"] - summary["config"]["effects"]["fuel_delay"]) <= 0.1, sweep


@pytest.mark.parametrize("name", ["systemscyber_truck_drive_normal.log", "systemscyber_truck_drive_tsc1.log"])
def test_fuel_signal_lag_on_real_driving_logs(name, real_log, tmp_path):
    """The lag of LFE1's fuel rate (SPN 183) behind speed and torque on 30 s of real driving: the same sweep on
    a 0.1 s grid finds 0.19–0.20 s (an independent analysis: 0.16–0.18 s, ../shared/real_logs/SOURCES.md)."""
    from fuelid.cli import main
    from ident.dataset import build_dataset

    mcap = tmp_path / "real.mcap"
    assert main(["convert", str(real_log(name)), "-o", str(mcap), "--json"]) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # no idle stretch in 30 s of driving: the operating point is the default
        ds = build_dataset([mcap], Ts=0.1)
    lag = estimate_fuel_delay(ds, ds.u, Structure(nb=(2, 2), nf=(1, 1), nk=(0, 0)))["best_s"]
    print(f"{name}: fuel-signal lag {lag:.2f} s")
    assert 0.0 < lag < 3.0
