"""One sentence an engineer acts on, and the size of the effect, from a candidate's estimated fuel
contribution [output unit] and gains."""
from __future__ import annotations

import numpy as np

from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.run import Run
from fuelid.ident.filters import lfilter
from fuelid.ident.polymodel import PolyModel


def contribution_on_grid(form: str, columns: np.ndarray, coef: np.ndarray, run: Run) -> np.ndarray:
    """The fuel contribution X β [output unit] of an effect's columns X (stacked like run.r) on the dataset grid:
    NaN outside the run, a level's mean removed (the model's offset absorbs it), a regime's kept."""
    contribution = np.full(len(run.y), np.nan)
    c = columns @ coef
    contribution[run.index] = c if form == "regime" else c - c.mean()
    return contribution


def signals_text(effect: fx.Effect) -> str:
    spn = {s: p for s, p in zip(effect.signals, effect.spns)} if len(effect.spns) == len(effect.signals) else {}
    parts = [f"{s} (SPN {spn[s]})" if s in spn else s for s in effect.signals]
    if not spn and effect.spns:
        parts = [f"{', '.join(effect.signals)} (SPN {', '.join(map(str, effect.spns))})"]
    return ", ".join(parts)


def static_gain(model: PolyModel, i: int) -> float:
    """Steady-state gain B_i(1) / (A(1) F_i(1)) of input i [output unit per input unit]."""
    return float(model.B[i].sum() / (model.A.sum() * model.F[i].sum()))


def torque_response(models, x: np.ndarray) -> np.ndarray:
    """The fuel [output unit] the models' torque path B_2/F_2 (mean over models) makes of x (N) [torque unit]."""
    x = np.nan_to_num(np.asarray(x, float))
    return np.mean([lfilter(m.B[1], m.F[1], x) for m in models], axis=0)


def explain(entry, effect: fx.Effect, reg: fx.Regressors, contribution: np.ndarray, gains: np.ndarray,
            torque_models, ds, run: Run) -> tuple[str, dict]:
    """`sentence`, or for an effect the engineer defined with an explanation template, the template filled in
    (ident.effectfile) and what to do."""
    text, size = sentence(entry, effect, reg, contribution, gains, torque_models, ds, run)
    if effect.template is None:
        return text, size
    measure = next((size[k] for k in ("mean_change_when_on", "relative_change_per_unit", "torque_scale",
                                      "gain_per_unit") if k in size), float("nan"))
    percent = size.get("percent_change_when_on", 100.0 * size.get("relative_change_per_unit", float("nan")))
    filled = effect.template.format(signals=signals_text(effect), size=measure, percent=percent,
                                    rms=size["rms_contribution"], unit=ds.output_unit, x_unit=reg.units[0])
    return f"{filled}; add effect {effect.id} (defined in {effect.source})", size


def sentence(entry, effect: fx.Effect, reg: fx.Regressors, contribution: np.ndarray, gains: np.ndarray,
             torque_models, ds, run: Run) -> tuple[str, dict]:
    """One sentence an engineer acts on, and the size of the effect (JSON-ready), from its estimated fuel contribution
    [output unit] on the grid and its steady-state gain per regressor column [output unit per column unit] (for the
    shift: −τ [s]); entry the effect's entry kind (ident.diagnosis.entries), whose own sentence, if it has one, is
    said unless the effect is the inertia or a regime that was on; torque_models the fitted models whose torque path
    gives the inertia J: the contribution of J_bus dω/dt [Nm] is J/J_bus times what the torque path makes of it, so
    J = J_bus ⟨c, c_T⟩ / ⟨c_T, c_T⟩ (least squares over the samples, c_T = torque_response)."""
    unit = ds.output_unit
    ok = np.isfinite(contribution) & np.isfinite(run.y)
    c = np.where(ok, contribution, 0.0)
    rms = float(np.sqrt(np.mean(c[ok] ** 2))) if ok.any() else 0.0
    size = {"rms_contribution": rms}
    act = f"add effect {effect.id}"
    sig = signals_text(effect)
    if effect.id == "inertia" and ds.input_units[1] == "Nm" and reg.units[0] == "Nm":
        J_bus = float(np.nanmedian(ds.extra["EC1.EngMomentOfInertia"]))
        c_T = torque_response(torque_models, reg.x[:, 0])[ok]
        c_T, c_ok = c_T - c_T.mean(), c[ok] - c[ok].mean()
        J = J_bus * float(c_ok @ c_T / max(c_T @ c_T, 1e-300))
        size["inertia_kgm2"] = J
        bus = f" (EC1 SPN 1794 reports {J_bus:.2f} kg·m²)"
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
            if effect.id.startswith("state:"):  # indicators of a bus signal's values, against its most frequent one
                others = [f"{name}: {float(c[(x > 0.5) & ok].mean()):+.2f} {unit}"
                          for name, x in zip(reg.names[1:], reg.x[:, 1:].T) if ((x > 0.5) & ok).any()]
                return f"fuel is {abs(extra):.2f} {unit}{pct} {word} whenever {reg.names[0]}" \
                       + (f" ({'; '.join(others)})" if others else "") \
                       + f", relative to the signal's most frequent value ({sig}); {act}", size
            return f"fuel is {abs(extra):.2f} {unit}{pct} {word} than the model whenever {effect.name} is on " \
                   f"({sig}); {act}", size
    text = entry.sentence(effect, reg, gains, size, sig, act)
    if text is not None:
        return text, size
    if reg.x.shape[1] == 1:
        size["gain_per_unit"] = float(gains[0])
        return f"fuel changes by {gains[0]:+.3g} {unit} per {reg.units[0] or 'unit'} of {reg.names[0]} ({sig}) " \
               f"beyond what speed and torque explain (RMS {rms:.2f} {unit}); {act}", size
    return f"{effect.name} ({sig}) explains {rms:.2f} {unit} RMS of the fuel beyond speed and torque; {act}", size


def as_evidence(c) -> str:
    """The sentence of a tested candidate that was not confirmed: evidence, never advice. Its size and its "add
    effect" are left out (a size is trusted only for a confirmed effect, whose coefficient the held-out refit
    checked); why it was not confirmed stays."""
    reasons = c.explanation.split(" — ", 1)[1] if " — " in c.explanation else ""
    p = f"Holm p = {c.p_holm:.2g}" if c.p_holm is not None else "not tested"
    verdict = f"significant in its own test ({p}) but not confirmed" if c.test_significant else f"not significant ({p})"
    named = c.name if all(s in c.name for s in c.definition.signals) else f"{c.name} ({signals_text(c.definition)})"
    return (f"{verdict}: {named} is evidence, not advice"
            + (f" — {reasons}" if reasons else ""))
