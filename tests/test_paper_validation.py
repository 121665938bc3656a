"""The seed paper's validation on the simulated replay logs, end to end through the commands a user runs:
convert the 1.5 h identification trip and the eleven 30-minute drive cycles, identify with the paper's orders,
compare on the cycles (Table I) and on the validation trip — on both engines: the paper's linear model as the
truth (the shipped diesel set) and the VECTO 325 kW map engine (map_ident_90min, map_valid_40min shipped; its
eleven cycles made here by `fuelid simulate --catalog map_cycle_NN`, a few minutes)."""
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from fuelid.cli import main
from fuelid.ident.dataset import build_dataset
from fuelid.ident.modelfile import load_model
from fuelid.ident.polymodel import simulate
from fuelid.ident.validation import fit_percent
from tests.conftest import run_json

LOGS = Path(__file__).resolve().parents[1] / "replay_logs"
CYCLES = [f"diesel_cycle_{i:02d}" for i in range(1, 12)]


@dataclass(frozen=True)
class TripSet:
    ident: str
    valid: str
    cycles: tuple
    cycles_shipped: bool


SETS = {"paper": TripSet("diesel_ident_90min", "diesel_valid_40min", tuple(CYCLES), True),
        "map": TripSet("map_ident_90min", "map_valid_40min", tuple(f"map_cycle_{i:02d}" for i in range(1, 12)), False)}


@pytest.fixture(scope="module", params=list(SETS))
def engine(request):
    return request.param


@pytest.fixture(scope="module")
def converted(engine, tmp_path_factory):
    trips = SETS[engine]
    out = tmp_path_factory.mktemp(engine)
    if not trips.cycles_shipped:
        assert main(["simulate", *[a for c in trips.cycles for a in ("--catalog", c)], "--dir", str(out)]) == 0
    for name in [trips.ident, trips.valid, *trips.cycles]:
        folder = LOGS if trips.cycles_shipped or name not in trips.cycles else out
        assert main(["convert", str(folder / f"{name}.log.gz"), "-o", str(out / f"{name}.mcap"), "--json"]) == 0
    return out


@pytest.fixture(scope="module")
def model_path(engine, converted):
    path = converted / "model.json"
    assert main(["identify", str(converted / f"{SETS[engine].ident}.mcap"), "--orders", "paper", "--model", "linear", "-o", str(path),
                 "--json"]) == 0
    return path


def test_table_one_cycle_fuel_error(engine, converted, model_path, capsys):
    """Table I. On the paper engine fuelid's cycle fuel error RMS is within the paper's 2.4 % and below the engine
    map's. The paper's map scored 8.1 %; here the gap is small (measured 0.51 % vs 0.72 %, ratio 0.71) because
    the simulated engine is the paper's linear model, whose static map integrates like the model itself (next
    test). On the map engine it is the other way round (measured 2.95 % vs 1.40 %): the linear model is a plane
    through a curved map, right on average on its mixed identification trip and off on other driving (README,
    On a real engine map)."""
    trips = SETS[engine]
    result = run_json(capsys, "compare", model_path, *[converted / f"{c}.mcap" for c in trips.cycles],
                      "--map-from", converted / f"{trips.ident}.mcap")
    cycles = result["models"][0]["cycle_fuel_error_percent"]  # per cycle id, plus "mean" and "rms"
    fmap = result["baselines"]["map"]
    assert len(cycles) - 2 == 11 and fmap["in_sample"] is False
    if engine == "paper":
        assert cycles["rms"] <= 2.4  # the paper: 2.4 %
        assert cycles["rms"] < 0.9 * fmap["cycle_fuel_error_percent"]["rms"]
    else:
        assert cycles["rms"] > 1.5 * fmap["cycle_fuel_error_percent"]["rms"]
        assert cycles["rms"] <= 4.0

def test_the_static_map_of_a_linear_engine_integrates_like_the_engine():
    """Why the map comes close here: the truth is the paper's linear model y = y0 + G(q) u + H e, and over a
    30-min cycle ∫ G(q) u dt = G(1) ∫ u dt up to a transient, so the perfect steady-state map of it — the plane
    y0 + G(1) u — makes the same cycle fuel error as the true dynamic model (to 0.01 percentage points)."""
    for name in CYCLES:
        truth = json.loads((LOGS / f"{name}.truth.json").read_text())["fuel_truth"]
        z = np.load(LOGS / f"{name}.truth.npz")
        gain = {k: np.sum(truth[k]["B"]) / np.sum(truth[k]["F"]) for k in ("Gw", "GT")}
        plane = (truth["output"]["operating_point"]
                 + gain["Gw"] * (z["engine_speed_bin_rpm"] - truth["inputs"]["W"]["operating_point"])
                 + gain["GT"] * (z["torque_true_bin_pct"] - truth["inputs"]["T"]["operating_point"]))
        error = lambda f: 100 * (f.sum() - z["fuel_measured"].sum()) / z["fuel_measured"].sum()  # noqa: E731, eq. 20
        assert abs(error(plane) - error(z["fuel_model"])) < 0.01, name


def test_validation_trip_fit_is_the_papers(engine, converted, model_path, capsys):
    """The paper: 91.2 % simulation fit on its validation trip. The map engine's curvature costs the linear model
    a few points (measured 85.9 %), and leaves structure the residuals show: the identification residuals pass
    the autocorrelation test, the validation residuals correlate with the speed input."""
    result = run_json(capsys, "compare", model_path, converted / f"{SETS[engine].valid}.mcap")
    metrics = result["models"][0]
    white = metrics["whiteness"]
    if engine == "paper":
        assert metrics["fit_percent"]["simulation"] >= 88.0
        assert white["autocorr_pass"] and all(white["crosscorr_pass"].values()), white
    else:
        assert 84.0 <= metrics["fit_percent"]["simulation"] < 88.0
        assert not white["crosscorr_pass"]["EEC1.EngSpeed"], white


def test_identified_model_simulates_the_noise_free_truth(engine, converted, model_path):
    """On the paper engine the model's simulation follows the simulator's noise-free fuel (truth.npz) better than
    the measurement itself does: it has learnt the engine, not the noise. The map engine adds no noise: the
    measurement differs from the truth by the ECU's LFE1 reporting only (0.1 s means, one period late; measured
    fit 90.8 %), and the model is further off (82.5 %): its error is the map's curvature, not noise."""
    model = load_model(model_path)
    ds = build_dataset([converted / f"{SETS[engine].valid}.mcap"])
    truth = np.load(LOGS / f"{SETS[engine].valid}.truth.npz")
    (seg,) = ds.segments()
    # Grid rows are bin means over [t, t + Ts), as is the truth (held over its bin): compare row by row.
    fuel_true = np.interp(ds.t[seg] - ds.t[seg][0], truth["t_s"], truth["fuel_true"])
    skip = model.structure.n_start + 100  # initial transient of the simulation
    fit_model = fit_percent(fuel_true[skip:], simulate(model, ds.u[seg])[skip:])
    fit_measured = fit_percent(fuel_true[skip:], ds.y[seg][skip:])
    if engine == "paper":
        assert fit_model >= 94.0 and fit_model > fit_measured + 3.0
    else:
        assert fit_measured >= 89.0 and 80.0 <= fit_model < fit_measured - 5.0


EFFECTS = (("inertia", 3.2), ("overrun_cutoff", 1.0), ("gear_shift", 0.3), ("fuel_delay", 0.4))


def simulated_dataset(cycle: str, duration_s: float, seed: int):
    """A trip of the simulator with EFFECTS, as the dataset of its 0.3 s truth series (reported torque, measured
    fuel, vehicle speed; no bus in between, which keeps this test fast)."""
    from fuelid.sim.trip import TripConfig, simulate

    z = simulate(TripConfig(cycle=cycle, duration_s=duration_s, seed=seed, effects=EFFECTS)).truth
    ns = (z["t_s"] * 1e9).round().astype(np.int64) + 1000
    records = [("/j1939/EC1", int(ns[0]), {"sa": 0, "EngReferenceTorque": 1600.0})]
    for i in range(len(ns)):
        records += [("/j1939/EEC1", int(ns[i]), {"sa": 0, "EngSpeed": float(z["engine_speed_rpm"][i]),
                                                 "ActualEngPercentTorque": float(z["torque_reported_pct"][i])}),
                    ("/j1939/LFE1", int(ns[i]), {"sa": 0, "EngFuelRate": float(z["fuel_measured"][i])}),
                    ("/j1939/CCVS1", int(ns[i]), {"sa": 0, "WheelBasedVehicleSpeed": float(z["speed_kmh"][i])})]
    return build_dataset(records)


def test_physical_effects_do_not_open_the_papers_map_gap():
    """With the effects a real engine has and the two-input model lacks (inertia hidden from the reported
    torque, overrun fuel cut-off, gear-shift fuelling, a 0.4 s fuel-signal delay), identified on a simulated
    1.5 h trip and tested on four 30-min cycles: fuelid stays within the paper's 2.4 %, and the map stays as
    close (measured: fuelid 0.71 %, map 0.65 % RMS) — these effects barely move integrated fuel, so the paper's
    8.1 % must come from what the simulator does not have (see README, Accuracy on the shipped data)."""
    from fuelid.ident.baseline import engine_map
    from fuelid.ident.identify import identify_model
    from fuelid.ident.polymodel import Structure
    from fuelid.ident.validation import error_table, evaluate, evaluate_static

    ident = simulated_dataset("mixed", 5400, 101)
    model = identify_model(ident, Structure(nb=(4, 5), nf=(5, 5), nk=(3, 0), nc=11, nd=11))
    fmap = engine_map(ident)
    errors = {"model": {}, "map": {}}
    for j, cycle in enumerate(["urban", "rural", "motorway", "mixed"]):
        ds = simulated_dataset(cycle, 1800, 1001 + j)
        errors["model"][j] = evaluate(model, ds)["cycle_fuel_error_percent"]["mean"]  # one cycle per trip
        errors["map"][j] = evaluate_static(fmap(ds.u), ds)["cycle_fuel_error_percent"]["mean"]
    rms = {k: error_table(v)["rms"] for k, v in errors.items()}
    assert rms["model"] <= 2.4
    assert abs(rms["map"] - rms["model"]) < 1.0, rms
