"""Ranking the candidates and naming the missing effect: the tests of every candidate, Holm, verification of
the likeliest, and the sequential conditional check.

5. Sequential conditional check. Bus signals are dependent (a cab temperature follows the level shift a real
   effect leaves in the error). The confirmed candidates are taken in the order of their held-out drop
   (`_priority`; a generic bus signal's discounted by GENERIC_WEIGHT); each after the first is re-tested by the
   simulation-error test with the accepted candidates' columns among the nuisance columns and must still reject
   (Bonferroni over the candidates) and explain min_effect_percent, and, added on top of them, still lower the
   held-out RMS error by min_drop_percent, else it is "explained by" the first (`accept_sequentially`).

A candidate is `significant` — a missing effect the diagnosis names — when the Holm-corrected test rejects
AND it explains at least min_effect_percent (default 1 %) of the simulation error AND, when verified, the
linearised refit lowers the held-out RMS error by at least min_drop_percent (default 2 %) the way its physics
says AND (after the first) it survives the conditional check. The conjunction can only remove rejections, so
the family-wise false-alarm rate stays ≤ α. Significant candidates are listed first, in the order accepted;
then the rest by p-value. Measured on 20-minute simulated trips (benchmarks/bench_diagnose.py --acceptance):
1 of 70 data sets with nothing hidden (50 trips, 20 pairs of trips) names an effect; README gives the table per
hidden effect.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.signal import lfilter

from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.delay import reference_fit, shift_test, verify_shift
from fuelid.ident.diagnosis.explanation import explain, signals_text, static_gain
from fuelid.ident.diagnosis.failures import where_it_fails
from fuelid.ident.diagnosis.run import Run, candidate_columns, run_gradients
from fuelid.ident.diagnosis.statistics import holm, level_test, nuisance_basis, one_blas_thread, score_test
from fuelid.ident.diagnosis.verification import held_out, held_out_scores, verify
from fuelid.ident.modeldata import at_operating_point
from fuelid.ident.modelrun import run_model
from fuelid.ident.polymodel import PolyModel
from fuelid.ident.validation import metrics

GENERIC_WEIGHT = 0.8  # a generic bus signal must explain 25 % more than a named effect to be accepted first


def rank_candidates(model: PolyModel, ds, run: Run, candidates=None, alpha: float = 0.05) -> list[dict]:
    """Both tests of every candidate effect not already in the model (ident.diagnosis.statistics, 1–3); Holm-corrected;
    sorted by p-value (log p)."""
    if candidates is None:
        candidates = list(fx.EFFECTS.values()) + fx.generic_effects(ds)
    included = {fx.parse_effect(e)[0] for e in model.effects}
    dsm = at_operating_point(ds, model)
    rows, untestable = [], []
    for effect in candidates:
        if effect.id in included:
            continue
        found = _candidate_tests(model, dsm, run, effect)
        if found is None:
            untestable.append({"effect": effect.id, "name": effect.name, "form": effect.form,
                               "signals": list(effect.signals), "spns": list(effect.spns), "testable": False,
                               "statistic": None, "df": 0, "p_value": None, "significant": False,
                               "test_significant": False, "estimated_drop_percent": None,
                               "explanation": "not testable: its bus signals are not in the data"})
            continue
        reg, raw, tests, left, coef, ref = found
        log_p = min(0.0, math.log(len(tests)) + min(t.log_p for t in tests.values()))  # Bonferroni over its tests
        df = max(t.df for t in tests.values())
        gains = coef.reshape(len(effect.lags), -1).sum(axis=0)
        text, size = explain(effect, reg, contribution_on_grid(effect.form, raw, coef, run), gains, [model], dsm, run)
        rows.append({"effect": effect.id, "spec": effect.id, "name": effect.name, "form": effect.form,
                     "signals": list(effect.signals), "spns": list(effect.spns),
                     "statistic": max(t.statistic for t in tests.values()), "df": df, "p_value": math.exp(log_p),
                     "log10_p": log_p / math.log(10), "testable": df > 0,
                     "tests": {name: {"statistic": t.statistic, "df": t.df, "p_value": t.p_value}
                               for name, t in tests.items()},
                     "estimated_drop_percent": 100.0 * (1.0 - left), "size": size,
                     "explanation": text, "physics": effect.physics, "_reg": reg, "_effect": effect, "_x": raw,
                     "_raw": lfilter(model.A, [1.0], raw, axis=0), "_ref": ref})
    adj, sig = holm([r["p_value"] for r in rows], alpha) if rows else (np.zeros(0), np.zeros(0, bool))
    for r, a, s in zip(rows, adj, sig):
        r["p_holm"] = float(a)
        # p-values below ~1e-300 underflow; compare log p with Holm's log(alpha/m) bound in that case
        r["test_significant"] = bool(r["testable"] and (s or r["log10_p"] < math.log10(alpha / len(rows))))
        r["significant"] = False  # until verified (diagnose)
    rows.sort(key=lambda r: (r["log10_p"], -r["statistic"]))
    return rows + untestable


def _candidate_tests(model: PolyModel, ds, run: Run, effect: fx.Effect):
    """(Regressors, their lagged columns stacked like run.r, {name: ScoreTest}, the fraction of the simulation
    error left after fitting them, the coefficients the explanation starts from, the Reference model of a
    fuel-signal delay or None); None when the effect's signals are not logged. A delay is tested on seed 2's
    low-order model (shift_test), every other effect by both tests on the model itself."""
    if effect.form == "shift":
        ref = reference_fit(ds, run)
        test, left, x = shift_test(ds, run, ref)
        grid = np.full(len(ds.t), np.nan)
        grid[run.index] = x[:, 0]
        reg = fx.Regressors(grid[:, None], ("d/dt reference model's fuel",), (f"{ds.output_unit}/s",))
        return reg, x, {"reference_model_shift": test}, left, test.coef, ref
    cols = candidate_columns(model, ds, run, effect)
    if cols is None:
        return None
    reg, psi, raw = cols
    with one_blas_thread():
        pred = score_test(run.e, psi, run.Q)
        level, left = level_test(run.r, lfilter(model.A, [1.0], raw, axis=0), run.lens, run.QG)  # w has A x
    return reg, raw, {"prediction_error": pred, "simulation_error": level}, left, pred.coef, None


def contribution_on_grid(form: str, columns: np.ndarray, coef: np.ndarray, run: Run) -> np.ndarray:
    """The fuel contribution X β [output unit] of an effect's columns X (stacked like run.r) on the dataset grid:
    NaN outside the run, a level's mean removed (the model's offset absorbs it), a regime's kept."""
    contribution = np.full(len(run.y), np.nan)
    c = columns @ coef
    contribution[run.index] = c if form == "regime" else c - c.mean()
    return contribution


def torque_path_columns(model: PolyModel, run: Run, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A torque-like regressor x (N, the model's torque unit) through the model's torque path, stacked like run.r:
    (B_T/F_T x, the column of the w domain; B_T/(A F_T) x, its fuel [output unit]) — ∂w/∂κ and ∂ŷ/∂κ when the
    torque the fuel burns for is T + κ x (ident.diagnosis.verification, 4)."""
    x = np.nan_to_num(x)
    B, F = model.B[1], model.F[1]
    cols = [(lfilter(B, F, x[s])[run.warm:], lfilter(B, np.convolve(model.A, F), x[s])[run.warm:]) for s in run.segs]
    return np.concatenate([c[0] for c in cols]), np.concatenate([c[1] for c in cols])


def _verify_row(r: dict, model: PolyModel, ds, run: Run, base: dict, base_ysim: np.ndarray) -> dict:
    """verify() the candidate of row r against the model as it is (with its torque-path column when its regressor
    is a torque); its explanation re-made from the refit's β. A delay: `verify_shift`."""
    effect, X, Xy = r["_effect"], r["_raw"], r["_x"]
    if effect.form == "shift":
        v = verify_shift(r["_ref"], model, ds, run, base)
        tau = v["reference"]["delay_s"]
        r["spec"] = f"{effect.id}={tau:.2f}"
        r["size"] = {"delay_s": tau}
        own = v["rmse_drop_percent"]
        r["explanation"] = (
            f"the fuel signal {'lags' if tau > 0 else 'leads'} speed and torque by {abs(tau):.2f} s "
            f"({signals_text(effect)}): seed 2's low-order model, whose dynamics cannot absorb a delay, fits "
            f"{v['reference']['rmse_drop_percent']:.1f} % better on held-out data with it; "
            + (f"this model's own dynamics absorb it (held-out RMS error {-own:+.1f} % with it)" if own < 2.0 else
               f"this model's held-out RMS error falls {own:.1f} % with it") + f"; add effect {r['spec']}")
        return v
    through_torque = effect.form == "input" and r["_reg"].units == (ds.input_units[1],) and not effect.torque
    if through_torque:
        X, Xy = (np.column_stack(c) for c in zip((X, Xy), torque_path_columns(model, run, r["_reg"].x[:, 0])))
    v = verify(run, X, model, ds, base, base_ysim)
    r["_X"] = X  # for the conditional check on top of the candidates accepted before it
    beta, change = v.pop("_beta"), v.pop("_change")
    # does the fuel rise or fall with the effect? The covariance of the change adding it makes to the held-out
    # fuel (its own part and the model's re-fitted gains and offset together) with its first column x (for a
    # regime: the mean change on minus off), or with x·ŷ when it scales the fuel (Effect.scales_fuel)
    x0 = r["_x"][:, 0] * (run.ysim[run.index] if effect.scales_fuel else 1.0)
    v["direction"] = int(np.sign((change - change.mean()) @ (x0 - x0.mean())))
    if v["rmse_drop_percent"] > 0:  # the held-out-checked refit measures it better
        n_lagged = r["_x"].shape[1]
        gains = beta[:n_lagged].reshape(len(effect.lags), -1).sum(axis=0)
        if through_torque:
            gains = gains + beta[-1] * static_gain(model, 1)
        r["explanation"], r["size"] = explain(effect, r["_reg"], contribution_on_grid(effect.form, Xy, beta, run),
                                              gains, [model], at_operating_point(ds, model), run)
    return v


def _relevance(v: dict) -> float:
    """The held-out RMS error drop [%] that decides a verification: the model's own, or for a delay the
    reference model's (verify_shift)."""
    return v["reference"]["rmse_drop_percent"] if "reference" in v else v["rmse_drop_percent"]


def _confirmed(r: dict, min_drop_percent: float) -> bool:
    """Whether row r's verification confirms it: the held-out RMS error falls by at least min_drop_percent
    (`_relevance`), and the fuel moves the way the effect's physics says (Effect.sign: fuel cut on overrun falls,
    a regeneration adds fuel, the fuel signal lags). A candidate the refit cannot score stays as the tests found
    it."""
    v = r["verification"]
    if "error" in v:
        return True
    return _relevance(v) >= min_drop_percent and r["_effect"].sign * v["direction"] >= 0


def _priority(r: dict) -> float:
    """Order of acceptance: the held-out RMS error drop when verified, else the estimated drop; a generic bus
    signal's discounted by GENERIC_WEIGHT (a named physical effect is preferred to a bus signal that explains no
    more than it)."""
    v = r["verification"]
    drop = r["estimated_drop_percent"] if v is None or "error" in v else _relevance(v)
    return drop * (1.0 if r["effect"] in fx.EFFECTS else GENERIC_WEIGHT)


def accept_sequentially(rows: list[dict], run: Run, model: PolyModel, ds, alpha: float, min_effect_percent: float,
                        min_drop_percent: float, m: int) -> list[dict]:
    """The candidates named as missing, in order (module docstring, 5): rows (in order of preference), each after
    the first re-tested conditional on those accepted before it and accepted when (a) the simulation-error test
    with their columns among the nuisance columns still rejects at alpha/m (Bonferroni over the m candidates
    tested) and still explains min_effect_percent, and (b) when verified, adding it on top of them still lowers
    the held-out RMS error by min_drop_percent. The others get `explained_by`."""
    accepted, QG, resid = [], run.QG, run.r
    X_accepted, rmse_accepted = np.zeros((run.r.size, 0)), None  # verified columns accepted so far, their score
    for r in rows:
        if r["form"] == "shift":  # the signal path, tested on its own reference model: not explained by fuelling
            accepted.append(r)
            continue
        if accepted:
            with one_blas_thread():
                test, left = level_test(resid, r["_raw"], run.lens, QG)
            r["conditional"] = {"given": [a["effect"] for a in accepted], "p_value": test.p_value,
                                "estimated_drop_percent": 100.0 * (1.0 - left), "rmse_drop_percent": None}
            explained = test.log_p >= math.log(alpha / m) or 100.0 * (1.0 - left) < min_effect_percent
            if not explained and "_X" in r:
                if rmse_accepted is None:
                    rmse_accepted = held_out_scores(held_out(model, run, X_accepted), ds)["rmse"]
                rmse = held_out_scores(held_out(model, run, np.column_stack([X_accepted, r["_X"]])), ds)["rmse"]
                drop = 100.0 * (1.0 - rmse / rmse_accepted)
                r["conditional"]["rmse_drop_percent"] = drop
                explained = drop < min_drop_percent
            if explained:
                r["explained_by"] = accepted[0]["effect"]
                continue
        accepted.append(r)
        if "_X" in r:
            X_accepted, rmse_accepted = np.column_stack([X_accepted, r["_X"]]), None
        with one_blas_thread():
            QG = nuisance_basis(np.column_stack([QG, r["_raw"]]))
        resid = run.r - QG @ (QG.T @ run.r)
    return accepted


def diagnose(model: PolyModel, ds, alpha: float = 0.05, n_verify: int = 10, min_effect_percent: float = 1.0,
             candidates=None, min_drop_percent: float = 2.0) -> dict:
    """The whole diagnosis of `model` on dataset ds (ident.diagnosis and its modules); JSON-ready.

    Returns {model, data, compare (ident.validation.evaluate), held_out (held_out_scores of the model as it is,
    linearised refit without each block: rmse [output unit], cycle_fuel_error_percent; None when it cannot be
    scored), where_it_fails, test, candidates, verdict}.
    Each candidate (best first) has: effect (id for `fuelid identify --effect`), name, form, signals (DBC
    names), spns, statistic (the larger LM of its two tests), df, p_value (Bonferroni over the two tests),
    p_holm, test_significant (Holm at alpha), estimated_drop_percent (share of the simulation error its
    least-squares fit explains), conditional (its re-test given the effects accepted before it), explained_by,
    rmse_drop_percent (held-out RMS simulation error drop with it, linearised refit, None unless verified),
    verification (held-out RMSE and cycle fuel errors without/with, direction), significant (a missing effect:
    when verified, a held-out drop ≥ min_drop_percent in the direction of its physics, then accepted by
    `accept_sequentially`), size, explanation, physics, tests. At most n_verify of the candidates that pass the
    tests and explain min_effect_percent are verified, by estimated drop."""
    mrun = run_model(model, ds)
    run = run_gradients(mrun)
    rows = rank_candidates(model, ds, run, candidates, alpha)
    for r in rows:
        r.update(rmse_drop_percent=None, verification=None, conditional=None, explained_by=None)
    testable = [r for r in rows if r["testable"]]
    try:  # the model as it is, scored on each block left out: the reference every verification is measured against
        base_ysim = held_out(model, run, np.zeros((run.r.size, 0)))["ysim"]
        base = held_out_scores({"y": run.y, "ysim": base_ysim}, ds)
    except (ValueError, np.linalg.LinAlgError):
        base = base_ysim = None
    eligible = sorted((r for r in testable
                       if r["test_significant"] and r["estimated_drop_percent"] >= min_effect_percent),
                      key=lambda r: -_priority(r))
    if eligible and n_verify and base is None:
        raise ValueError("the model cannot be scored on held-out blocks of these data")
    for r in eligible[:n_verify]:
        try:
            r["verification"] = v = _verify_row(r, model, ds, run, base, base_ysim)
            r["rmse_drop_percent"] = v["rmse_drop_percent"]
        except (ValueError, np.linalg.LinAlgError) as exc:
            r["verification"] = {"error": str(exc)}
    confirmed, unconfirmed = [], []
    for r in eligible:
        (confirmed if r["verification"] is None or _confirmed(r, min_drop_percent) else unconfirmed).append(r)
    confirmed.sort(key=lambda r: (r["verification"] is None, -_priority(r)))  # verified ones first
    accepted = accept_sequentially(confirmed, run, model, ds, alpha, min_effect_percent, min_drop_percent,
                                   max(len(testable), 1))
    for r in accepted:
        r["significant"] = True
    for r in unconfirmed:
        v = r["verification"]
        if _relevance(v) < min_drop_percent:
            r["explanation"] += f" — but adding it changes the held-out RMS error by {-_relevance(v):+.1f} " \
                                f"% (a fall of {min_drop_percent:g} % is needed): not confirmed"
        else:
            r["explanation"] += " — but the refit moves the fuel the other way than this effect would: not " \
                                "confirmed"
    for r in rows:
        if r["explained_by"]:
            r["explanation"] += f" — explained by {r['explained_by']} (not significant given it)"
        elif r["test_significant"] and not r["significant"] and r["estimated_drop_percent"] < min_effect_percent:
            r["explanation"] += f" — statistically detectable, but it explains only " \
                                f"{r['estimated_drop_percent']:.1f} % of the simulation error (< {min_effect_percent:g} %)"
    order = {id(r): k for k, r in enumerate(accepted)}
    rows.sort(key=lambda r: (not r["significant"], order.get(id(r), 0), r.get("log10_p", 0.0)))
    for r in rows:
        for key in ("_reg", "_effect", "_x", "_raw", "_X", "_ref"):
            r.pop(key, None)
    testable = [r for r in rows if r["testable"]]
    best = rows[0] if rows and rows[0]["significant"] else None
    if best:
        drop = "" if best["rmse_drop_percent"] is None or best["form"] == "shift" else \
            f" (held-out RMS error {-best['rmse_drop_percent']:+.0f} % when added)"
        verdict = f"Missing effect: {best['explanation']}{drop}."
    else:
        verdict = f"No significant candidate: none of the {len(testable)} candidate effects explains the residual " \
                  f"(Holm-corrected, family-wise α = {alpha:g}, at least {min_effect_percent:g} % of the " \
                  f"simulation error, and a held-out RMS error drop of at least {min_drop_percent:g} %); the model " \
                  "is not missing any effect the bus reveals."
    return {
        "model": {"effects": list(model.effects), "inputs": list(model.input_names), "Ts": model.Ts},
        "data": ds.summary() if hasattr(ds, "summary") else {},
        "compare": {**metrics(mrun, ds), "unit": ds.output_unit},
        "held_out": base,
        "where_it_fails": where_it_fails(model, ds, run),
        "test": {"method": "score (LM) tests on the prediction errors and, GLS-whitened under the alternative, on "
                           "the simulation errors; Newey-West robust, chi2(k); Bonferroni over the two, Holm "
                           "step-down over all candidates; relevance, sequential conditional re-tests, and "
                           "a linearised refit scored leaving out one 60-s block at a time",
                 "alpha": alpha, "min_effect_percent": min_effect_percent, "min_drop_percent": min_drop_percent,
                 "candidates_tested": len(testable),
                 "samples": int(run.e.size)},
        "candidates": rows,
        "verdict": verdict,
    }
