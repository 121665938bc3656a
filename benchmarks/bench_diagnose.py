"""Diagnosis time (fuelid diagnose) against trip length and the number of candidate effects, and issue 7's
acceptance run on more seeds than the test suite.

    python benchmarks/bench_diagnose.py                  # timing (best of 3): 15/30/60/90-min trips, 90 min with a fuel delay, three days, with fewer candidates
    python benchmarks/bench_diagnose.py --acceptance     # every hidden effect on --seeds seeds, pairs, --null-seeds null trips, --null-pairs null pairs
    python benchmarks/bench_diagnose.py --acceptance --first-seed 4000 --first-null-seed 300 --null-seeds 30  # fresh seeds
    python benchmarks/bench_diagnose.py --acceptance --seeds 1 --null-seeds 0 --null-pairs 0 --effects inertia --pairs cold_engine+dpf_regeneration  # a subset
    python benchmarks/bench_diagnose.py --truth map                     # the same on the VECTO 325 kW map engine
    python benchmarks/bench_diagnose.py --truth map --spread            # 90-min trips, a hidden effect each
    python benchmarks/bench_diagnose.py --acceptance --truth map --with-effect power_nonlinearity  # second round
    python benchmarks/bench_diagnose.py --acceptance --truth map --engine benchmarks/engines/325kW_steady.veng  # another engine set
    python benchmarks/bench_diagnose.py --acceptance --truth map --seeds 1 --perturb 1e-13  # the fuel's last bits changed

Trips are simulated diesel trips (fuelid/sim/) decoded by fuelid's recorder (tests/ident/hidden.py), identified with the
paper's orders (plus the --with-effect effects: the diagnosis's second round); the 90-minute trip hides a DPF
regeneration. Times are wall-clock on whatever machine runs it, each diagnosis without and with a worker process
building ahead the models `fuelid identify` would build (workers=0 and 1, ident.diagnosis.builds).

The floor a verified candidate may reach instead of a 25 % drop: on the paper engine the RMS of the simulator's
noise H e (the truth is the model class plus noise); the map engine adds no noise, and what the LTI model cannot
follow there is the engine's own curvature, so its floor is the held-out RMS error of the same model identified
on the same trip (seed, route) with nothing hidden.
"""
import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import NamedTuple

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fuelid.ident import diagnosis as dg  # noqa: E402  (fuelid before numpy: it pins the BLAS kernels, fuelid.blas)
from fuelid.ident import effects as fx  # noqa: E402
from fuelid.ident.identify import FitMemo, identify_model  # noqa: E402
from fuelid.ident.validation import evaluate  # noqa: E402
from fuelid.sim.catalog import ALL_EFFECT_TRIPS  # noqa: E402
from fuelid.sim.effects import GENERIC_EFFECTS  # noqa: E402
from tests.ident import hidden  # noqa: E402

import numpy as np  # noqa: E402

EFFECTS = ["dpf_regeneration", "inertia", "power_nonlinearity", "overrun_cutoff", "cold_engine", "engine_fan",
           "gear_shift", "ambient", "fuel_delay", "hot_intake_air", "auxiliary_load"]
GENERIC_DAYS = 3  # a bus signal fuelid knows no physics for is recommended only when it carries over to other trips
#   (ident.diagnosis.recommendation: one trip, ONE_TRIP_ONLY), so a case with a generic effect is diagnosed, as that
#   advice says, on its route driven on three days, and validated on three other days


PERTURB = 0.0  # --perturb: every trip's fuel samples multiplied by 1 + PERTURB


def simulated(*args, **kwargs):
    """hidden.simulated's (dataset, truth arrays, summary), the dataset's fuel samples [L/h] multiplied by
    1 + PERTURB: with PERTURB = 1e-13 only their last bits change, which no physics can tell apart."""
    ds, arrays, summary = hidden.simulated(*args, **kwargs)
    return (dataclasses.replace(ds, y=ds.y * (1.0 + PERTURB)) if PERTURB else ds), arrays, summary


def best_of(f, n: int = 3) -> float:
    """The shortest wall time [s] of n calls of f (the machine is shared: the minimum is the least disturbed)."""
    times = []
    for _ in range(n):
        t = time.perf_counter()
        f()
        times.append(time.perf_counter() - t)
    return min(times)


def timing(truth: str, engine: str = ""):
    """Wall time of the diagnosis of each trip, the models `fuelid identify` would build made when needed in this
    process (workers=0, the fleet's jobs) and ahead in a worker process (workers=1, `fuelid diagnose`'s default on
    two cores or more: ident.diagnosis.builds), side by side; the same diagnosis either way (checked here)."""
    print("trip     samples  candidates  diagnose [s]  with a worker [s]  ratio  without verification [s]   "
          "(best of 3)")
    for minutes in (15, 30, 60, 90):
        ds, _, _ = simulated("dpf_regeneration", 7, minutes * 60.0, truth=truth, engine=engine)
        model = hidden.identify(ds)
        out = same_either_way(model, ds)
        total, ahead = (best_of(lambda: dg.diagnose(model, ds, workers=w)) for w in (0, 1))
        tests_only = best_of(lambda: dg.diagnose(model, ds, n_verify=0))
        print(f"{minutes:3d} min  {out['test']['samples']:7d}  {out['test']['candidates_tested']:10d}  {total:12.2f}"
              f"  {ahead:17.2f}  {ahead / total:5.2f}  {tests_only:24.2f}   top: {out['candidates'][0]['effect']}",
              flush=True)
    delayed, _, _ = simulated("fuel_delay", 7, 5400.0, truth=truth, engine=engine)  # verified by seed 2's sweep
    delayed_model = hidden.identify(delayed)
    top = same_either_way(delayed_model, delayed)["candidates"][0]
    t, ahead = (best_of(lambda: dg.diagnose(delayed_model, delayed, workers=w)) for w in (0, 1))
    print(f" 90 min with a hidden 0.4 s fuel delay (21 refits of the reference model): {t:.2f} s, with a worker "
          f"{ahead:.2f} s ({ahead / t:.2f})   top: {top['spec']}")
    days, _, _ = simulated("hot_intake_air", 3000, truth=truth, engine=engine, days=GENERIC_DAYS)
    days_model = hidden.identify(days)
    named = [c["effect"] for c in same_either_way(days_model, days)["candidates"] if c.get("recommended")]
    t, ahead = (best_of(lambda: dg.diagnose(days_model, days, workers=w)) for w in (0, 1))
    print(f" {GENERIC_DAYS} days of 20 min with the hot intake air (generic signals checked leave-one-trip-out by PEM): "
          f"{t:.2f} s, with a worker {ahead:.2f} s ({ahead / t:.2f})   recommended: {', '.join(named)}")
    generic = fx.generic_effects(ds)
    all_candidates = list(fx.EFFECTS.values()) + generic
    for k in (10, 25, len(all_candidates)):
        t = best_of(lambda: dg.diagnose(model, ds, candidates=all_candidates[:k], n_verify=0))
        print(f" 90 min, {k:3d} candidates, without verification: {t:.2f} s")
    additive = list(fx.EFFECTS.values()) + [e for e in generic if e.id.split(":")[0] in ("level", "rate", "state")]
    for name, c in (("generic signals additive only (level, rate, state)", additive), ("every form", all_candidates)):
        t = best_of(lambda: dg.diagnose(model, ds, candidates=c))
        print(f" 90 min, {name}: {len(c)} candidates, {t:.2f} s")


def spread(truth: str, engine: str, first_seed: int):
    """Wall time, with a worker (best of 2), of the diagnosis of one 90-min trip per hidden effect whose trip is
    one route driven on one day (EFFECTS, on seed first_seed + k for the k-th) and of a trip with nothing hidden:
    how the timing's one 90-min trip (a DPF regeneration, seed 7) stands among trips that hide other effects and
    make forward selection accept other numbers of them; their median and largest."""
    cases = [None] + [e for e in EFFECTS if len(ALL_EFFECT_TRIPS[e]) == 1 and days_of(e) == 1]
    times = {}
    for k, effect in enumerate(cases):
        ds, _, _ = simulated(effect, first_seed + k, 5400.0, truth=truth, engine=engine)
        model = hidden.identify(ds)
        out = dg.diagnose(model, ds, workers=1)
        times[effect] = best_of(lambda: dg.diagnose(model, ds, workers=1), 2)
        print(f" {effect or 'nothing hidden':20s} seed {first_seed + k:5d}  {len(ds.t):6d} samples  "
              f"{times[effect]:6.2f} s  accepted {sum(1 for c in out.candidates if c.role)}, recommended "
              f"{', '.join(c.effect for c in out.candidates if c.recommended) or '-'}", flush=True)
    t = np.array(list(times.values()))
    worst = max(times, key=times.get)
    print(f"90-min trips with a worker: median {np.median(t):.2f} s, largest {t.max():.2f} s "
          f"({worst or 'nothing hidden'}), of {len(t)}")


def same_either_way(model, ds) -> dict:
    """The diagnosis's JSON, checked to be the same with the builds made ahead in a worker and without."""
    out = dg.diagnose(model, ds).to_json()
    if dg.diagnose(model, ds, workers=1).to_json() != out:
        raise SystemExit("the diagnosis with a worker differs from the one without")
    return out


def first_named(out: dict) -> dict:
    """The diagnosis's answer to "which hidden effect?" (its JSON): the first missing effect named; when none, the
    engine map term (the engine's curvature, e.g. a hidden power_nonlinearity); else the first candidate."""
    named = [r for r in out["candidates"] if r.get("role") == "missing effect"] \
        or [r for r in out["candidates"] if r.get("role") == "engine map"]
    return (named or out["candidates"])[0]


def floor_rmse(effect: str, seed: int, truth: str, arrays: dict, base_effects: tuple, engine: str = "") -> float:
    """The yardstick of a verified candidate [L/h] (module docstring)."""
    if truth != "map":
        return float(np.sqrt(np.mean(arrays["noise"] ** 2)))
    null, _, _ = simulated(None, seed, routes_of=effect, truth=truth, engine=engine, days=days_of(effect))
    return hidden.held_out_rmse(hidden.identify(null, effects=base_effects), null)


PAIRS = [("cold_engine", "dpf_regeneration"), ("engine_fan", "fuel_delay"), ("ambient", "dpf_regeneration"),
         ("hot_intake_air", "auxiliary_load"), ("gear_shift", "dpf_regeneration")]
VALIDATION_SEED_OFFSET = 50  # the validation trip of a case: another day (seed + 50), same route and effects


# The id under which fuelid adds a hidden effect of the simulator (sim.effects): its own for the catalogued ones;
# a generic one's signal in the form its physics takes; the fuel delay at its simulated size
ORACLE_IDS = {"fuel_delay": "fuel_delay=0.4", "hot_intake_air": "scales:AMB.EngAirInletTemp",
              "auxiliary_load": "torque:EEC3.EstEngParasiticLossesPercentTorque"}
HELD_BY_TERM = {"engine_map": {"power_nonlinearity"}}  # hidden effects whose columns the engine's term has already
ORACLE_MIN_DROP = 0.02  # the true effects must lower the validation error by this share [1] for the oracle to ask
#   anything of the recommendation: the diagnosis's own relevance (min_drop_percent 2 %); less is within the
#   reproducibility of one identification's validation error (README)


def days_of(case) -> int:
    """The days a case's route is driven (hidden.simulated): GENERIC_DAYS when it hides a generic effect, else 1."""
    names = case if isinstance(case, tuple) else (case,) if case else ()
    return GENERIC_DAYS if set(names) & set(GENERIC_EFFECTS) else 1


class Validation(NamedTuple):
    """Validation-trip RMS simulation errors [L/h] of one case (`validation`): the model as it is (base), with
    everything recommended (with_), with everything recommended but one ({effect: RMS}: leave one out), and issue
    16's oracle — with the engine's term alone (the map or product term the diagnosis named, else none: engine)
    and with that term and the true hidden effects (oracle); None where not measured."""

    base: float | None = None
    with_: float | None = None
    others: dict = {}
    engine: float | None = None
    oracle: float | None = None

    def oracle_share(self) -> float | None:
        """(engine − with_) / (engine − oracle) [1]: how much of what the true effects would lower the validation
        error beyond the engine's term the recommendation lowers it (issue 16: at least 0.7); None when the true
        effects lower it by less than ORACLE_MIN_DROP of it (nothing to find) or nothing was measured. The model as
        it is stands for the recommendation when nothing was recommended."""
        if None in (self.engine, self.oracle) or self.engine - self.oracle < ORACLE_MIN_DROP * self.engine:
            return None
        return (self.engine - (self.engine if self.with_ is None else self.with_)) / (self.engine - self.oracle)


def validation(case, seed: int, routes_of, truth: str, ds, model, recommended: list, base_effects: tuple,
               engine_term: str | None = None, engine: str = "", days: int = 1) -> Validation:
    """The Validation of a case on another day's trip of it (seed + VALIDATION_SEED_OFFSET; `days` days): each model
    re-identified on the diagnosed data as `fuelid identify --effects-from` does (ident.identify.identify_model,
    one FitMemo for all, so a fit asked for twice is done once). The oracle only for a case with a hidden effect
    (case not None), the base and the rest only when something was recommended."""
    if not recommended and case is None:
        return Validation()
    val, _, _ = simulated(case, seed + VALIDATION_SEED_OFFSET, routes_of=routes_of, truth=truth, engine=engine,
                          days=days)
    as_is = evaluate(model, val)["rmse"]["simulation"]
    memo = FitMemo()

    def rmse(effects):
        m = identify_model(ds, hidden.PAPER, base_effects + tuple(effects), memo=memo)
        return evaluate(m, val)["rmse"]["simulation"]

    term = (engine_term,) if engine_term else ()
    hidden_ids = tuple(ORACLE_IDS.get(e, e) for e in ((case,) if isinstance(case, str) else case or ())
                       if e not in HELD_BY_TERM.get(engine_term, ()))
    with_term = with_truth = None
    if case is not None:
        with_term = rmse(term) if term else as_is
        with_truth = rmse(term + tuple(e for e in hidden_ids if e not in term))
    if not recommended:
        return Validation(engine=with_term, oracle=with_truth)
    others = {e: rmse([o for o in recommended if o != e]) for e in recommended} if len(recommended) > 1 else {}
    return Validation(as_is, rmse(recommended), others, with_term, with_truth)


def acceptance(seeds: int, null_seeds: int, null_pairs: int, first_seed: int, first_null_seed: int,
               truth: str = "diesel_p320", base_effects: tuple = (), pair_seeds: int | None = None,
               effects=EFFECTS, pairs=PAIRS, engine: str = ""):
    """Issue 7's criteria per trip (tests/ident/diagnosis/test_hidden_effects.py checks the same on fewer seeds):
    found — the top candidate is significant and names the hidden effect (its id or an SPN the simulator shows it on);
    verified — besides, the held-out RMS error falls by ≥ 25 % or to within 5 % of the noise floor; all — besides,
    the cycle fuel error falls (RMS over the cycles, 0.1 percentage point tolerance). Then two effects hidden at
    once (PAIRS, issue 16): both named, and the validation error with what was recommended. Then the false-alarm
    rate on trips with nothing hidden: single trips, and sets of trips in the ambient effect's three weathers
    identified together. For every case with a recommendation (issue 16, item 3): the RMS error on another day's
    trip (seed + 50) of the model as it is and with everything recommended added; worse = it rose, or one of the
    effects added raised it (everything recommended but that one does better: "raised by"). For every case with
    hidden effects, issue 16's oracle (`Validation.oracle_share`): the recommendation lowers that error beyond the
    engine's own term (the map term, when named) by at least 70 % of what adding the true effects to the term
    does (ORACLE_IDS). effects, pairs: the single effects and pairs to run (default all); engine: the map truth's
    VECTO engine set (hidden.simulated)."""
    print("effect               seed  top candidate                       named  held-out drop  RMSE/floor  "
          "cycle err %  pass  hidden effect's rank  engine map term  missing effects  validation RMS base -> with  "
          "worse  oracle")
    counts, worse, shares = {}, [], []

    def checked(case, seed, routes_of, ds, model, out, days: int = 1) -> str:
        recommended = dg.confirmed_effects(out["candidates"])
        v = validation(case, seed, routes_of, truth, ds, model, recommended, base_effects, out["engine_map"], engine,
                       days)
        share = v.oracle_share()
        if case is not None:
            shares.append(share)
        oracle = "" if case is None else f"  oracle: engine term {v.engine:.3f} -> true effect {v.oracle:.3f}, " \
            + ("nothing to find" if share is None else f"share {share:.2f}")
        if v.base is None:
            return "     -                  -" + oracle
        raised = [f"{e} {v.others[e]:.3f}->{v.with_:.3f}" for e in recommended if v.others.get(e, np.inf) < v.with_]
        worse.append(v.with_ > v.base or bool(raised))
        return (f"{v.base:6.3f} -> {v.with_:6.3f} ({','.join(recommended)})  "
                f"{'WORSE' if worse[-1] else 'no':>5s}" + (f"  raised by: {'; '.join(raised)}" if raised else "")
                + oracle)

    for effect in (e for e in effects if e not in base_effects):
        for seed in range(first_seed, first_seed + seeds):
            ds, arrays, summary = simulated(effect, seed, truth=truth, engine=engine, days=days_of(effect))
            model = hidden.identify(ds, effects=base_effects)
            out = dg.diagnose(model, ds).to_json()
            top = first_named(out)
            # verified on top of the effects accepted before it (the engine map term) when it was, else on its own
            v = (top.get("conditional") or {}).get("verification") or top["verification"] or {}
            spns = {p for e in summary["effects"] for p in e["spns"]} - {190, 513}
            names = [r["effect"] == effect or bool(spns & set(r["spns"])) for r in out["candidates"]
                     if r.get("role") != "engine map" or r is top]  # its rank among the hidden-effect candidates
            named = top["significant"] and (top["effect"] == effect or bool(spns & set(top["spns"])))
            rank = names.index(True) + 1 if any(names) else "-"
            drop = v.get("rmse_drop_percent")
            cyc = [abs(v.get(f"cycle_fuel_error_percent_{k}", {}).get("rms", np.nan)) for k in ("without", "with")]
            floor = None  # simulated only when the drop alone does not decide (a null trip on the map engine)
            if named and drop is not None and drop < 25:
                # the same model on the same trip with nothing hidden, with the engine map term the diagnosis added
                floor = floor_rmse(effect, seed, truth, arrays, base_effects + ((out["engine_map"],)
                                                                                 if out["engine_map"] else ()), engine)
            verified = named and drop is not None and (drop >= 25 or v["rmse_with"] <= 1.05 * floor)
            ok = verified and cyc[1] <= cyc[0] + 0.1
            ratio = "-" if floor is None else f"{v['rmse_with'] / floor:.2f}"
            counts.setdefault(effect, []).append((named, verified, ok))
            print(f"{effect:20s} {seed:5d}  {top['effect'][:34]:34s}  {'yes' if named else 'no':>5s}  "
                  f"{'-' if drop is None else f'{drop:6.1f} %':>13s}  {ratio:>10s}"
                  f"  {cyc[0]:5.2f}->{cyc[1]:5.2f}  {'yes' if ok else 'no':>4s}  {rank!s:>4}  {out['engine_map'] or '-'}"
                  f"  {','.join(out['missing_effects']) or '-'}  "
                  + checked(effect, seed, None, ds, model, out, days_of(effect)),
                  flush=True)
    for effect, rows in counts.items():
        found, verified, ok = (sum(col) for col in zip(*rows))
        print(f"{effect:20s} found {found}/{len(rows)}, verified {verified}/{len(rows)}, all criteria {ok}/{len(rows)}")
    both = []
    for pair in pairs:
        for seed in range(first_seed, first_seed + (seeds if pair_seeds is None else pair_seeds)):
            ds, _, summary = simulated(pair, seed, truth=truth, engine=engine, days=days_of(pair))
            model = hidden.identify(ds, effects=base_effects)
            out = dg.diagnose(model, ds).to_json()
            found = [r for r in out["candidates"] if r["significant"]]
            spns = {e["name"]: set(e["spns"]) - {190, 513} for e in summary["effects"]}
            named = [any(r["effect"] == e or spns[e] & set(r["spns"]) for r in found) for e in pair]
            both.append(all(named))
            print(f"{'+'.join(pair):36s} {seed:5d}  named: {','.join(r['effect'] for r in found)[:60] or '-':60s}"
                  f"  both {'yes' if all(named) else 'no':>3s}  " + checked(pair, seed, None, ds, model, out,
                                                                             days_of(pair)),
                  flush=True)
    print(f"two effects at once: both named in {sum(both)} of {len(both)}")
    for routes_of, days, what, n in ((None, 1, "trips", null_seeds),
                                     ("ambient", 1, "sets of trips in different weather", null_pairs),
                                     ("hot_intake_air", GENERIC_DAYS, f"sets of {GENERIC_DAYS} days on one route",
                                      null_pairs)):
        alarms = maps = 0
        for seed in range(first_null_seed, first_null_seed + n):
            ds, _, _ = simulated(None, seed, routes_of=routes_of, truth=truth, engine=engine, days=days)
            model = hidden.identify(ds, effects=base_effects)
            out = dg.diagnose(model, ds).to_json()
            top = first_named(out)
            alarm = bool(out["missing_effects"])
            alarms += alarm
            maps += out["engine_map"] is not None
            drop = top["rmse_drop_percent"] or np.nan
            term = next((r for r in out["candidates"] if r.get("role") == "engine map"), None)
            said = "no missing effect" if not alarm else \
                f"ALARM {','.join(out['missing_effects'])} ({drop:.1f} % held-out drop)"
            print(f"null seed {seed} ({what}): {said}; engine map term: "
                  + ("-" if term is None else f"{term['effect']} ({term['rmse_drop_percent']:.1f} %)") + "  "
                  + checked(None, seed, routes_of, ds, model, out, days), flush=True)
        print(f"no hidden effect: a missing effect named in {alarms} of {n} {what} "
              f"({100.0 * alarms / max(n, 1):.0f} % false alarms); the engine map term in {maps} of {n}")
    print(f"recommendations that raise the validation-trip RMS error (all of them, or one given the others): "
          f"{sum(worse)} of {len(worse)} cases with one")
    met = [s for s in shares if s is not None]
    print(f"issue 16's oracle (the recommendation lowers the validation error beyond the engine's term by at least "
          f"70 % of what the true effects would): {sum(s >= 0.7 for s in met)} of {len(met)} cases whose hidden "
          f"effects lower it by at least {100 * ORACLE_MIN_DROP:g} % ({len(shares) - len(met)} where they do not)")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--acceptance", action="store_true", help="run the acceptance table instead of the timing")
    ap.add_argument("--spread", action="store_true",
                    help="time one 90-min trip per hidden effect (from --first-seed) instead of the timing")
    ap.add_argument("--seeds", type=int, default=3, help="seeds per hidden effect (default 3)")
    ap.add_argument("--null-seeds", type=int, default=20, help="trips with nothing hidden (default 20)")
    ap.add_argument("--null-pairs", type=int, default=10,
                    help="sets of trips with nothing hidden, each kind: three weathers (the ambient effect's "
                         "routes), and GENERIC_DAYS days on the hot-intake-air route (default 10)")
    ap.add_argument("--first-seed", type=int, default=3000, help="first seed of the hidden-effect trips (3000)")
    ap.add_argument("--first-null-seed", type=int, default=100, help="first seed of the null trips (100)")
    ap.add_argument("--pair-seeds", type=int, default=None, help="seeds per pair of hidden effects (default --seeds)")
    ap.add_argument("--truth", choices=("diesel_p320", "map"), default="diesel_p320",
                    help="the engine's fuel truth: the paper's model (default) or the VECTO 325 kW map engine")
    ap.add_argument("--engine", default="", metavar="VENG",
                    help="with --truth map: the VECTO engine set (a .veng file or a shipped set's name; default the "
                         "325 kW engine), e.g. benchmarks/engines/325kW_steady.veng, the same engine without its "
                         "transient fuelling")
    ap.add_argument("--with-effect", action="append", default=[], metavar="EFFECT",
                    help="identify the model with this effect before diagnosing (repeatable); it is not hidden")
    ap.add_argument("--effects", default=",".join(EFFECTS), metavar="ID,...",
                    help="the single hidden effects to run (default all; '' for none)")
    ap.add_argument("--pairs", default=",".join("+".join(p) for p in PAIRS), metavar="A+B,...",
                    help="the pairs of hidden effects to run (default all of PAIRS; '' for none)")
    ap.add_argument("--perturb", type=float, default=0.0, metavar="EPS",
                    help="multiply every trip's fuel samples by 1 + EPS (e.g. 1e-13: how much of the table the "
                         "last bits of the data decide)")
    args = ap.parse_args()
    PERTURB = args.perturb
    if args.engine and args.truth != "map":
        ap.error("--engine drives the map truth only (--truth map)")
    print(f"engine truth: {args.truth}" + (f" ({args.engine})" if args.engine else "") + "; model: paper orders"
          + "".join(f" + {e}" for e in args.with_effect))
    if args.acceptance:
        acceptance(args.seeds, args.null_seeds, args.null_pairs, args.first_seed, args.first_null_seed,
                   args.truth, tuple(args.with_effect), args.pair_seeds, [e for e in args.effects.split(",") if e],
                   [tuple(p.split("+")) for p in args.pairs.split(",") if p], args.engine)
    elif args.spread:
        spread(args.truth, args.engine, args.first_seed)
    else:
        timing(args.truth, args.engine)
