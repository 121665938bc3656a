"""The diagnosis loop: compare a model with measurements, see where it fails, learn which physical effect is
missing (ident.effects), and verify it by refitting.

Which effect is missing — a score (Lagrange-multiplier) test per candidate
-------------------------------------------------------------------------
The model M gives prediction errors ε(t) = D/C (A ỹ − Σ_i B_i/F_i ũ_i). If an effect with regressors x(t)
(N × k, ident.effects) were missing, y would contain Σ_l β_l x(t − l) and ε would contain its prewhitened image

    ψ_x(t) = D(q)/C(q) [x(t), x(t−1), …]          (the gradient −∂ε/∂β at β = 0, same filter as ε).

The score test asks whether ε is correlated with ψ_x beyond what the fitted parameters θ already absorb:
with Z = [Ψ_θ, D/C·1] (the PEM gradient −∂ε/∂θ at θ̂, pem.prediction_errors, and an offset) and
M_Z = I − Z Z⁺, the score is s = (M_Z ψ_x)ᵀ ε and

    LM = sᵀ Ω̂⁻¹ s  ~  χ²(k_eff)  under "no such effect",

with Ω̂ the Newey–West (Bartlett kernel, L = ⌊4 (N/100)^{2/9}⌋ lags) long-run covariance of the terms
g_t = (M_Z ψ_x)(t) ε(t). For white, homoskedastic ε this is N R² of the regression of ε on [Z, ψ_x] (the
textbook LM statistic); the robust form keeps the level when ε is not quite white or its variance changes with
load (Wooldridge 1990). k_eff is the rank of M_Z ψ_x (directions fully explained by the model are not testable).
p = P(χ²(k_eff) ≥ LM) by scipy.stats.chi2.

Many candidates: Holm's step-down correction. The user's requirement is that on data with no missing effect
*no* candidate is flagged in ≥ 95 % of trips: that is the family-wise error rate, which Holm controls at α
under any dependence between the tests (bus signals are strongly dependent: coolant and oil temperature,
torque-like signals); Benjamini–Hochberg controls the false-discovery proportion instead, which is the same
only under the global null, and needs positive dependence. Holm is six lines here, so statsmodels (a heavy
dependency for one function) is not used.

Verification: the candidates with the smallest p-values (default 3, significant or not) are each added to the
model (ident.effects.apply_effects) and refitted by PEM on one half of the data, the model without it likewise,
and the simulation RMSE of both is measured on the other half; then the halves swap (two-fold cross-validation
in time). The halves are interleaved blocks of 5 minutes, so an effect that happens once (a cold start, one
regeneration) is in both. rmse_drop_percent = 100 (1 − RMSE_with / RMSE_without) over both held-out halves.
Significant candidates are listed first, the verified ones by their error drop; an effect only a refit can
confirm is flagged when its drop is not positive.

Known limit: the score test is taken at the model fitted without the effect. A slow effect (a regeneration, a
cold start) is partly absorbed by that fit's noise model as low-frequency noise (D gets a root near 1), which
lowers the test's power for it; its verified error drop still shows it.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.linalg import qr, svd
from scipy.signal import lfilter
from scipy.stats import chi2

from ident import effects as fx
from ident.pem import pem, prediction_errors
from ident.polymodel import PolyModel, input_responses, predict, simulate
from ident.validation import autocorr_test, crosscorr_test, evaluate

CONTEXT_EFFECTS = ("gear_shift", "overrun_cutoff", "idle_fuelling", "dpf_regeneration", "cold_engine", "pto",
                   "retarder", "engine_fan")


# ---- the statistics (plain arrays) ------------------------------------------------------------------------

@dataclass(frozen=True)
class ScoreTest:
    """LM statistic, its degrees of freedom k_eff, p-value (and log p, which does not underflow), and β̂ the
    coefficients of the candidate columns in the least-squares regression of ε on [Z, ψ_x]."""

    statistic: float
    df: int
    p_value: float
    log_p: float
    coef: np.ndarray


def newey_west(g: np.ndarray, lags: int) -> np.ndarray:
    """Long-run covariance Σ_{|l|≤L} (1 − |l|/(L+1)) Γ_l of the rows of g (N × k), Γ_l = Σ_t g_t g_{t−l}ᵀ."""
    omega = g.T @ g
    for lag in range(1, lags + 1):
        gamma = g[lag:].T @ g[:-lag]
        omega += (1.0 - lag / (lags + 1.0)) * (gamma + gamma.T)
    return omega


def score_test(eps, X, Z=None, hac_lags: int | None = None, rank_tol: float = 1e-4) -> ScoreTest:
    """Score (LM) test that ε (N) does not depend on the columns of X (N × k) beyond the nuisance columns Z
    (N × p): LM = sᵀ Ω̂⁻¹ s ~ χ²(k_eff), module docstring. Columns of X whose part orthogonal to Z has less
    than rank_tol of their norm are not testable (k_eff counts the rest); k_eff = 0 gives LM = 0, p = 1."""
    eps = np.asarray(eps, float)
    X = np.asarray(X, float).reshape(eps.size, -1)
    if Z is not None and Z.size:
        Q = qr(Z, mode="economic", check_finite=False)[0]
        Xt, et = X - Q @ (Q.T @ X), eps - Q @ (Q.T @ eps)
    else:
        Xt, et = X - X.mean(axis=0), eps - eps.mean()
    coef = np.linalg.lstsq(Xt, et, rcond=None)[0] if Xt.size else np.zeros(0)
    norms = np.linalg.norm(X, axis=0)
    norms[norms == 0] = 1.0
    U, sig, Vt = svd(Xt / norms, full_matrices=False, check_finite=False)
    keep = sig > rank_tol
    k = int(keep.sum())
    if k == 0:
        return ScoreTest(0.0, 0, 1.0, 0.0, coef)
    W = U[:, keep]  # orthonormal basis of the testable directions
    g = W * et[:, None]
    L = int(4 * (eps.size / 100.0) ** (2 / 9)) if hac_lags is None else hac_lags
    s = g.sum(axis=0)
    lm = float(s @ np.linalg.solve(newey_west(g, L), s))
    return ScoreTest(lm, k, float(chi2.sf(lm, k)), float(chi2.logsf(lm, k)), coef)


def holm(p_values, alpha: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Holm's step-down adjusted p-values p̃_(i) = max_{j≤i} min(1, (m − j + 1) p_(j)) (sorted order) and the
    rejections p̃ < alpha; controls the family-wise error rate at alpha under any dependence."""
    p = np.asarray(p_values, float)
    m = p.size
    order = np.argsort(p)
    adj = np.empty(m)
    adj[order] = np.minimum(1.0, np.maximum.accumulate((m - np.arange(m)) * p[order]))
    return adj, adj < alpha


def lagged(x: np.ndarray, lags) -> np.ndarray:
    """Columns x_j(t − l) for each column j and lag l ≥ 0 (zero before the start): N × (k·len(lags))."""
    x = np.asarray(x, float).reshape(len(x), -1)
    out = np.zeros((x.shape[0], x.shape[1] * len(lags)))
    for i, lag in enumerate(lags):
        out[lag:, i * x.shape[1]:(i + 1) * x.shape[1]] = x[: x.shape[0] - lag]
    return out


def settle_samples(model: PolyModel, fraction: float = 0.01, cap: int = 400) -> int:
    """Samples until the slowest pole of 1/A, 1/F_i, 1/C (the filters started from zero state) decays to
    `fraction`, plus the structure's n_start; at most cap + n_start."""
    radii = [np.abs(np.roots(p)).max() for p in [model.A, model.C, *model.F] if p.size > 1]
    r = min(max(radii, default=0.0), 0.9999)
    n = 0 if r <= 0 else math.ceil(math.log(fraction) / math.log(r))
    return model.structure.n_start + min(n, cap)


# ---- running the model over a dataset --------------------------------------------------------------------

@dataclass
class Run:
    """A model run over the valid segments of a dataset: u, y the model's inputs and (shifted) fuel; ysim, ypred
    (1-step), eps (prediction errors, NaN during each segment's first `warm` samples) — all N long, NaN
    outside the segments used; segs the slices used; Z, e the stacked nuisance gradient and ε after warm-up."""

    u: np.ndarray
    y: np.ndarray
    ysim: np.ndarray
    ypred: np.ndarray
    eps: np.ndarray
    segs: list
    warm: int
    Z: np.ndarray
    e: np.ndarray


def run_model(model: PolyModel, ds) -> Run:
    """Simulate, predict and compute ε and the PEM gradient of `model` on every valid segment of ds long
    enough to leave 50 samples after the model's settling time."""
    u, y = fx.model_data(model, ds)
    warm = settle_samples(model)
    n = len(y)
    ysim, ypred, eps = (np.full(n, np.nan) for _ in range(3))
    segs, Zs, es = [], [], []
    s = model.structure
    for seg in ds.segments():
        ok = np.isfinite(y[seg]) & np.isfinite(u[seg]).all(axis=1)
        if seg.stop - seg.start < warm + 50 or not ok.all():
            continue
        us, ys = u[seg], y[seg]
        ysim[seg] = simulate(model, us)
        ypred[seg] = predict(model, us, ys, 1)
        e, psi = prediction_errors(model.theta, s, us - np.asarray(model.u0), ys - model.y0, jacobian=True)
        offset = lfilter(model.D, model.C, np.ones(len(ys)))
        eps[seg.start + warm: seg.stop] = e[warm:]
        Zs.append(np.column_stack([psi, offset])[warm:])
        es.append(e[warm:])
        segs.append(seg)
    if not segs:
        raise ValueError(f"no valid segment of the data is longer than the model's settling time ({warm} samples)")
    return Run(u, y, ysim, ypred, eps, segs, warm, np.vstack(Zs), np.concatenate(es))


def candidate_columns(model: PolyModel, ds, run: Run, effect: fx.Effect):
    """(Regressors on the dataset grid, their prewhitened lagged image ψ_x stacked over the run's segments after
    warm-up, the lagged unfiltered columns likewise); None when the effect's signals are not logged."""
    if effect.form == "shift":
        reg = fx.Regressors(fx.rate(run.ysim, ds.t)[:, None], ("d/dt simulated fuel",), (f"{ds.output_unit}/s",))
    else:
        reg = effect.build(ds)
    if reg is None:
        return None
    psi, raw = [], []
    for seg in run.segs:
        x = lagged(np.nan_to_num(reg.x[seg]), effect.lags)
        psi.append(lfilter(model.D, model.C, x, axis=0)[run.warm:])
        raw.append(x[run.warm:])
    return reg, np.vstack(psi), np.vstack(raw)


# ---- where it fails (the compare section is ident.validation.evaluate) --------------------------------------------------------------------------

def context_flags(ds) -> dict[str, np.ndarray]:
    """Per sample, whether each driving context (gear shift, overrun, idle, DPF regeneration, cold engine, PTO,
    retarder, fan) holds, from the bus signals that are logged."""
    flags = {}
    for eid in CONTEXT_EFFECTS:
        reg = fx.EFFECTS[eid].build(ds)
        if reg is not None:
            flags[fx.EFFECTS[eid].name] = reg.x[:, 0] > 1e-3
    return flags


def worst_segments(ds, run: Run, window_s: float = 30.0, n: int = 5, share: float = 0.2) -> list[dict]:
    """The n non-overlapping windows of window_s [s] with the largest RMS simulation error, each with its bias,
    mean speed and torque, and the contexts that cover at least `share` of it."""
    err = run.ysim - run.y
    ok = np.isfinite(err)
    w = max(int(round(window_s / ds.Ts)), 1)
    kernel = np.ones(w)
    cnt = np.convolve(ok, kernel, "same")
    ms = np.convolve(np.where(ok, err**2, 0.0), kernel, "same") / np.maximum(cnt, 1)
    ms[cnt < 0.8 * w] = -1.0
    flags = context_flags(ds)
    out = []
    for _ in range(n):
        c = int(np.argmax(ms))
        if ms[c] < 0:
            break
        sl = slice(max(c - w // 2, 0), c + w - w // 2)
        m = ok[sl]
        ctx = [name for name, f in flags.items() if f[sl][m].mean() >= share]
        out.append({
            "t_start_s": float(ds.t[sl.start]), "t_end_s": float(ds.t[min(sl.stop, len(ds.t)) - 1]),
            "rmse": float(np.sqrt(ms[c])), "bias": float(np.mean(err[sl][m])),
            "speed_rpm": float(np.mean(ds.u[sl, 0][m])), "torque": float(np.mean(ds.u[sl, 1][m])),
            "context": ctx or ["steady driving"],
        })
        ms[max(c - w, 0): c + w] = -1.0
    return out


def error_map(ds, run: Run, bins: int = 8, min_count: int = 20) -> dict:
    """Simulation error (model − measured) over the speed × torque plane: equal-width bins over the valid
    range; per cell the sample count, mean error (bias) and RMS error [output unit], null under min_count."""
    err = run.ysim - run.y
    ok = np.isfinite(err)
    n, T = ds.u[ok, 0], ds.u[ok, 1]
    e_n = np.linspace(n.min(), n.max() + 1e-9, bins + 1)
    e_T = np.linspace(T.min(), T.max() + 1e-9, bins + 1)
    cnt = np.histogram2d(n, T, [e_n, e_T])[0]
    s1 = np.histogram2d(n, T, [e_n, e_T], weights=err[ok])[0]
    s2 = np.histogram2d(n, T, [e_n, e_T], weights=err[ok] ** 2)[0]
    good = cnt >= min_count
    mean = np.where(good, s1 / np.maximum(cnt, 1), np.nan)
    rms = np.where(good, np.sqrt(s2 / np.maximum(cnt, 1)), np.nan)
    nul = lambda a: [[None if not np.isfinite(v) else float(v) for v in row] for row in a]  # noqa: E731
    return {"speed_edges_rpm": e_n.tolist(), "torque_edges": e_T.tolist(), "torque_unit": ds.input_units[1],
            "count": cnt.astype(int).tolist(), "mean_error": nul(mean), "rms_error": nul(rms)}


def where_it_fails(model: PolyModel, ds, run: Run, max_lag: int = 25) -> dict:
    """Residual whiteness and input cross-correlation (paper eqs. 18–19, 99 % bounds), the worst segments with
    their context, and the error map."""
    auto = autocorr_test(run.eps, max_lag)
    cross = crosscorr_test(run.eps, np.where(np.isfinite(run.eps)[:, None], run.u, np.nan), max_lag)
    test = lambda c: {"passed": c.passed, "bound": c.bound, "lags": c.lags.tolist(), "r": c.r.tolist(),  # noqa: E731
                      "outside_lags": c.outside().tolist()}
    return {
        "whiteness": {"autocorr_pass": auto.passed, "autocorr": test(auto),
                      "crosscorr_pass": {name: c.passed for name, c in zip(model.input_names, cross)},
                      "crosscorr": {name: test(c) for name, c in zip(model.input_names, cross)}},
        "worst_segments": worst_segments(ds, run),
        "error_map": error_map(ds, run),
    }


# ---- explanation ---------------------------------------------------------------------------------------

def _signals_text(effect: fx.Effect) -> str:
    spn = {s: p for s, p in zip(effect.signals, effect.spns)} if len(effect.spns) == len(effect.signals) else {}
    parts = [f"{s} (SPN {spn[s]})" if s in spn else s for s in effect.signals]
    if not spn and effect.spns:
        parts = [f"{', '.join(effect.signals)} (SPN {', '.join(map(str, effect.spns))})"]
    return ", ".join(parts)


def static_gain(model: PolyModel, i: int) -> float:
    """Steady-state gain B_i(1) / (A(1) F_i(1)) of input i [output unit per input unit]."""
    return float(model.B[i].sum() / (model.A.sum() * model.F[i].sum()))


def explain(effect: fx.Effect, reg: fx.Regressors, contribution: np.ndarray, gains: np.ndarray, torque_gain: float,
            ds, run: Run) -> tuple[str, dict]:
    """One sentence an engineer acts on, and the size of the effect (JSON-ready), from its estimated fuel
    contribution [output unit] on the grid and its steady-state gain per regressor column [output unit per
    column unit] (for the shift: −τ [s]); torque_gain the model's torque gain [output unit per torque unit]."""
    unit = ds.output_unit
    ok = np.isfinite(contribution) & np.isfinite(run.y)
    c = np.where(ok, contribution, 0.0)
    rms = float(np.sqrt(np.mean(c[ok] ** 2))) if ok.any() else 0.0
    size = {"rms_contribution": rms}
    act = f"add effect {effect.id}"
    sig = _signals_text(effect)
    if effect.form == "shift":
        tau = -float(gains[0])
        size["delay_s"] = tau
        way = "lags" if tau > 0 else "leads"
        return f"the fuel signal {way} speed and torque by about {abs(tau):.2f} s beyond what the model's dynamics " \
               f"absorb; {act}", size
    if effect.id == "inertia" and ds.input_units[1] == "Nm" and torque_gain:
        J_bus = float(np.nanmedian(ds.extra["EC1.EngMomentOfInertia"])) if reg.units[0] == "Nm" else None
        J = float(gains[0]) / torque_gain * (J_bus or 1.0)
        size["inertia_kgm2"] = J
        bus = f" (EC1 SPN 1794 reports {J_bus:.2f} kg·m²)" if J_bus else ""
        return f"fuel follows the crankshaft's acceleration torque J dω/dt with J ≈ {J:.2f} kg·m²{bus}: the " \
               f"reported torque is net of it; {act}", size
    if effect.form == "regime":
        on = (reg.x[:, 0] > 0.5) & ok
        if on.any():
            extra = float(c[on].mean())
            base = float(np.mean(run.y[on])) - extra
            size.update(mean_change_when_on=extra, share_on=float(on.sum() / ok.sum()))
            pct = ""
            if base > 0.1 * abs(extra):
                size["percent_change_when_on"] = 100 * extra / base
                pct = f" ({100 * extra / base:+.0f} %)"
            word = "higher" if extra > 0 else "lower"
            return f"fuel is {abs(extra):.2f} {unit}{pct} {word} than the model whenever {effect.name} is on " \
                   f"({sig}); {act}", size
    if reg.x.shape[1] == 1:
        size["gain_per_unit"] = float(gains[0])
        return f"fuel changes by {gains[0]:+.3g} {unit} per {reg.units[0] or 'unit'} of {reg.names[0]} ({sig}) " \
               f"beyond what speed and torque explain (RMS {rms:.2f} {unit}); {act}", size
    return f"{effect.name} ({sig}) explains {rms:.2f} {unit} RMS of the fuel beyond speed and torque; {act}", size


# ---- verification by refitting -----------------------------------------------------------------------

def blocks(ds, run: Run, block_s: float = 300.0) -> list[np.ndarray]:
    """Two interleaved halves of the run's samples (after warm-up): alternate blocks of block_s [s] within each
    segment, [even blocks, odd blocks] as index arrays. Interleaving (rather than first half / second half)
    keeps an effect that happens once — a cold start, one regeneration — in both halves."""
    w = max(int(round(block_s / ds.Ts)), 1)
    halves = [[], []]
    for seg in run.segs:
        idx = np.arange(seg.start + run.warm, seg.stop)
        for h in range(2):
            halves[h].append(idx[((idx - idx[0]) // w) % 2 == h])
    return [np.concatenate(h) for h in halves]


@dataclass
class Fold:
    """A PEM fit on one half and its squared simulation errors [output unit²] on the other (held-out) half."""

    model: PolyModel
    sq: np.ndarray


def fit_and_test(u, y, fit_idx, test_idx, run: Run, structure, model: PolyModel, init: PolyModel,
                 max_iter: int = 50) -> Fold:
    """PEM on the samples fit_idx (concatenated; the few samples after each block boundary see the previous
    block's filter state, the same for every model compared), then the fitted model simulated over every
    segment of the run and its squared error kept on test_idx."""
    u0 = tuple(model.u0) + (0.0,) * (structure.n_inputs - len(model.u0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = pem(u[fit_idx], y[fit_idx], structure, model.Ts, init=init, u0=u0, y0=model.y0, max_iter=max_iter)
    ysim = np.full(len(y), np.nan)
    for seg in run.segs:
        ysim[seg] = simulate(m, u[seg])
    e = ysim[test_idx] - y[test_idx]
    return Fold(m, e[np.isfinite(e)] ** 2)


def _extended_init(model: PolyModel, orders) -> PolyModel:
    """model with one more input per entry of orders (nb, nf, nk): B = 0, F = 1 (PEM's starting point)."""
    k = len(orders)
    return PolyModel(A=model.A, B=list(model.B) + [np.zeros(o[2] + o[0]) for o in orders],
                     F=list(model.F) + [np.r_[1.0, np.zeros(o[1])] for o in orders], C=model.C, D=model.D,
                     Ts=model.Ts, nk=tuple(model.nk) + tuple(o[2] for o in orders),
                     u0=tuple(model.u0) + (0.0,) * k, y0=model.y0)


def baseline_folds(model: PolyModel, ds, run: Run) -> list[Fold]:
    """The model refitted on each half and tested on the other (the reference of every verification)."""
    halves = blocks(ds, run)
    return [fit_and_test(run.u, run.y, halves[a], halves[1 - a], run, model.structure, model, model) for a in (0, 1)]


def verify(model: PolyModel, ds, run: Run, effect_id: str, parameters: dict | None = None,
           base: list[Fold] | None = None) -> dict:
    """Refit with the effect on each interleaved half, test on the other (module docstring): held-out simulation
    RMSE [output unit] with and without, and the drop [%]. With a fuel shift each model is scored against the
    fuel it models (the shifted one)."""
    new = fx.apply_effects(fx.at_operating_point(ds, model), [effect_id], parameters)
    shifted = "fuel_delay" in new.parameters
    u_new = np.hstack([run.u, new.u])
    y_new = new.y if shifted else run.y
    s_new = new.extend(model.structure)
    init = _extended_init(model, new.orders)
    halves = blocks(ds, run)
    base = base or baseline_folds(model, ds, run)
    folds = [fit_and_test(u_new, y_new, halves[a], halves[1 - a], run, s_new, model, init) for a in (0, 1)]
    k = new.u.shape[1]
    m_in = len(model.B)
    contribution = np.mean([input_responses(f.model, u_new)[:, m_in:].sum(axis=1) for f in folds], axis=0)
    gains = np.mean([[static_gain(f.model, m_in + j) for j in range(k)] for f in folds], axis=0)
    torque_gain = float(np.mean([static_gain(f.model, 1) for f in folds]))
    r_base = float(np.sqrt(np.mean(np.concatenate([f.sq for f in base]))))
    r_new = float(np.sqrt(np.mean(np.concatenate([f.sq for f in folds]))))
    return {"rmse_without": r_base, "rmse_with": r_new, "rmse_drop_percent": 100.0 * (1.0 - r_new / r_base),
            "parameters": new.parameters, "_contribution": contribution, "_gains": gains, "_torque_gain": torque_gain}


# ---- the diagnosis ---------------------------------------------------------------------------------------

def rank_candidates(model: PolyModel, ds, run: Run, candidates=None, alpha: float = 0.05) -> list[dict]:
    """Score-test every candidate effect not already in the model; Holm-corrected; sorted by p-value (log p)."""
    if candidates is None:
        candidates = list(fx.EFFECTS.values()) + fx.generic_effects(ds)
    included = {fx.parse_effect(e)[0] for e in model.effects}
    dsm = fx.at_operating_point(ds, model)
    rows, untestable = [], []
    for effect in candidates:
        if effect.id in included:
            continue
        cols = candidate_columns(model, dsm, run, effect)
        if cols is None:
            untestable.append({"effect": effect.id, "name": effect.name, "form": effect.form,
                               "signals": list(effect.signals), "spns": list(effect.spns), "testable": False,
                               "statistic": None, "df": 0, "p_value": None, "significant": False,
                               "explanation": "not testable: its bus signals are not in the data"})
            continue
        reg, psi, raw = cols
        res = score_test(run.e, psi, run.Z)
        contribution = np.full(len(ds.t), np.nan)
        c = raw @ res.coef
        contribution[np.concatenate([np.arange(s.start + run.warm, s.stop) for s in run.segs])] = \
            c if effect.form == "regime" else c - c.mean()  # the model's offset absorbs a level's mean
        gains = res.coef.reshape(len(effect.lags), -1).sum(axis=0)
        text, size = explain(effect, reg, contribution, gains, static_gain(model, 1), dsm, run)
        rows.append({"effect": effect.id, "name": effect.name, "form": effect.form, "signals": list(effect.signals),
                     "spns": list(effect.spns), "statistic": res.statistic, "df": res.df, "p_value": res.p_value,
                     "log10_p": res.log_p / math.log(10), "testable": res.df > 0, "size": size,
                     "explanation": text, "physics": effect.physics, "_reg": reg, "_effect": effect})
    adj, sig = holm([r["p_value"] for r in rows], alpha) if rows else (np.zeros(0), np.zeros(0, bool))
    for r, a, s in zip(rows, adj, sig):
        r["p_holm"] = float(a)
        # p-values below ~1e-300 underflow; compare log p with Holm's log(alpha/m) bound in that case
        r["significant"] = bool(s or (r["df"] > 0 and r["log10_p"] < math.log10(alpha / len(rows))))
    rows.sort(key=lambda r: (r["log10_p"], -r["statistic"]))
    return rows + untestable


def diagnose(model: PolyModel, ds, alpha: float = 0.05, n_verify: int = 3, candidates=None) -> dict:
    """The whole diagnosis of `model` on dataset ds (module docstring); JSON-ready. The n_verify candidates with
    the smallest score p-values (significant or not) are refitted; significant ones are listed first, those
    verified by the largest held-out error drop first."""
    run = run_model(model, ds)
    rows = rank_candidates(model, ds, run, candidates, alpha)
    testable = [r for r in rows if r["testable"]]
    base = baseline_folds(model, ds, run) if n_verify and testable else None
    for r in rows:
        r.update(rmse_drop_percent=None, verification=None)
    for r in testable[:n_verify]:
        try:
            params = {"fuel_delay": r["size"]["delay_s"]} if r["form"] == "shift" else None
            v = verify(model, ds, run, r["effect"], params, base)
            contribution, gains, g_T = (v.pop(k) for k in ("_contribution", "_gains", "_torque_gain"))
            if v["rmse_drop_percent"] > 0 and r["form"] != "shift":  # the refit measures the size better
                r["explanation"], r["size"] = explain(r["_effect"], r["_reg"], contribution, gains, g_T,
                                                      fx.at_operating_point(ds, model), run)
            r.update(rmse_drop_percent=v["rmse_drop_percent"], verification=v)
        except (ValueError, np.linalg.LinAlgError) as exc:
            r["verification"] = {"error": str(exc)}
    for r in testable:
        drop = r["rmse_drop_percent"]
        if r["significant"] and drop is not None and drop <= 0:
            r["explanation"] += " — but refitting with it did not lower the held-out error: treat it with care"
    key = lambda r: (not r["significant"], -(r["rmse_drop_percent"] if r["rmse_drop_percent"] is not None  # noqa: E731
                                             and r["significant"] else -np.inf), r.get("log10_p", 0.0))
    rows.sort(key=key)
    for r in rows:
        r.pop("_reg", None), r.pop("_effect", None)
    best = rows[0] if rows and rows[0]["significant"] else None
    if best:
        drop = f" (held-out RMS error {-best['rmse_drop_percent']:+.0f} % when added)" \
            if best["rmse_drop_percent"] is not None else ""
        verdict = f"Missing effect: {best['explanation']}{drop}."
    else:
        verdict = f"No significant candidate: none of the {len(testable)} candidate effects explains the residual " \
                  f"(Holm-corrected, family-wise α = {alpha:g}); the model is not missing any effect the bus reveals."
    return {
        "model": {"effects": list(model.effects), "inputs": list(model.input_names), "Ts": model.Ts},
        "data": ds.summary() if hasattr(ds, "summary") else {},
        "compare": {**evaluate(model, ds), "unit": ds.output_unit},
        "where_it_fails": where_it_fails(model, ds, run),
        "test": {"method": "score (LM) test on the prediction errors, Newey-West robust, chi2(k); Holm step-down "
                           "over all candidates; verified by two-fold interleaved refits",
                 "alpha": alpha, "candidates_tested": len(testable), "samples": int(run.e.size)},
        "candidates": rows,
        "verdict": verdict,
    }
