"""Effects fuelid's catalogue has no entry for (sim.effects.GENERIC_EFFECTS): does the diagnosis find them, and
does adding what it names help on another trip as much as adding the true effect would?

    python benchmarks/bench_generic_effects.py                      # seeds 5000-5002, both generic effects
    python benchmarks/bench_generic_effects.py --seeds 2 --first-seed 6000 --null-seeds 5   # and trips with nothing hidden

Per effect and seed: an identification trip (seed) and a validation trip (seed + 50), 20 minutes each on the
effect's route (sim.catalog.GENERIC_EFFECT_TRIPS), through the bus and fuelid's decoder (tests/ident/hidden.py);
the paper's orders. The diagnosis runs twice on the identification trip: with the built-in and generic
candidates only, and with docs/effects-example.toml's effects besides (the engineer's file). found = a
significant candidate names the effect's bus signal (and its SPN). Then the validation trip's RMS simulation
error of the model identified on the identification trip: as it is, with what each diagnosis named (every
significant candidate, as `identify --effects-from` adds them), and with the true effect (oracle: its exact form
on the bus signal, quantised as the bus sends it, from the example file). share = (base − named)/(base − oracle).
"""
import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fuelid.ident import diagnosis as dg  # noqa: E402
from fuelid.ident.effectfile import read_effects_file  # noqa: E402
from fuelid.ident.validation import evaluate  # noqa: E402
from fuelid.sim.effects import GENERIC_EFFECTS  # noqa: E402
from tests.ident import hidden  # noqa: E402

FILE = Path(__file__).resolve().parents[1] / "docs" / "effects-example.toml"
ORACLE = {"hot_intake_air": "hot_intake_air", "auxiliary_load": "parasitic_torque"}  # effect -> the file's id
VALIDATION_SEED_OFFSET = 50


def named(diagnosis) -> list:
    """The specs of every significant candidate, as `identify --effects-from` adds them."""
    return [c.spec or c.effect for c in diagnosis.candidates if c.significant]


def found(diagnosis, signal: str, spn: int) -> bool:
    return any(c.significant and signal in c.signals and spn in c.spns for c in diagnosis.candidates)


def validation_rmse(ds, val, effects, defined) -> float:
    model = hidden.identify(ds, effects=effects, defined=defined)
    return evaluate(model, val)["rmse"]["simulation"]


def null_trips(n: int, first_seed: int, defined):
    """Trips on each generic effect's route with nothing hidden: how often each diagnosis names something."""
    for routes_of in GENERIC_EFFECTS:
        alarms = {"generic": 0, "file": 0}
        for seed in range(first_seed, first_seed + n):
            ds, _, _ = hidden.simulated(None, seed, routes_of=routes_of)
            model = hidden.identify(ds)
            for k, d in (("generic", dg.diagnose(model, ds)), ("file", dg.diagnose(model, ds, effects=defined))):
                alarms[k] += bool(named(d))
                if named(d):
                    print(f"null seed {seed} on the {routes_of} route ({k}): named {','.join(named(d))}", flush=True)
        print(f"nothing hidden, {routes_of} route: named something in {alarms['generic']} of {n} trips without the "
              f"file, {alarms['file']} of {n} with it", flush=True)


def main(seeds: int, first_seed: int):
    defined = read_effects_file(FILE)
    print("effect          seed  built-in+generic: named (found)            with the file: named (found)"
          "            validation RMS [L/h]: base / generic-named / file-named / oracle   share generic / file")
    for effect, e in GENERIC_EFFECTS.items():
        signal, spn = e.signals[0], e.spns[0]
        for seed in range(first_seed, first_seed + seeds):
            ds, _, _ = hidden.simulated(effect, seed)
            val, _, _ = hidden.simulated(effect, seed + VALIDATION_SEED_OFFSET)
            model = hidden.identify(ds)
            plain, filed = dg.diagnose(model, ds), dg.diagnose(model, ds, effects=defined)
            base = evaluate(model, val)["rmse"]["simulation"]
            rm = {k: validation_rmse(ds, val, named(d), defined) if named(d) else base
                  for k, d in (("generic", plain), ("file", filed))}
            oracle = validation_rmse(ds, val, [ORACLE[effect]], defined)
            share = {k: (base - v) / (base - oracle) if base > oracle else float("nan") for k, v in rm.items()}
            print(f"{effect:15s} {seed:5d}  {','.join(named(plain)) or '-':34.34s} ({'yes' if found(plain, signal, spn) else 'no':3s})"
                  f"  {','.join(named(filed)) or '-':34.34s} ({'yes' if found(filed, signal, spn) else 'no':3s})"
                  f"  {base:6.3f} / {rm['generic']:6.3f} / {rm['file']:6.3f} / {oracle:6.3f}"
                  f"   {100 * share['generic']:5.0f} % / {100 * share['file']:5.0f} %", flush=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3, help="seeds per generic effect (default 3)")
    ap.add_argument("--first-seed", type=int, default=5000, help="first identification seed (default 5000)")
    ap.add_argument("--null-seeds", type=int, default=0, help="also trips with nothing hidden per route (default 0)")
    ap.add_argument("--first-null-seed", type=int, default=500, help="first null seed (default 500)")
    args = ap.parse_args()
    main(args.seeds, args.first_seed)
    null_trips(args.null_seeds, args.first_null_seed, read_effects_file(FILE))
