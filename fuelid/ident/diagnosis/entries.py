"""How an effect enters the model, for the diagnosis: each entry kind (ident.effects.Effect.enters) says how its
regressors become the test's columns, how it is tested and verified, and how its size is said. A new kind is one
class here and its name in ENTRIES.

    additive     y + Σ_l β_l x(t − l): the effect's columns at its lags (an input, a nonlinearity, a regime)
    scales_fuel  y (1 + m x): the columns x and x·ŷ (ŷ the model's simulated fuel: the gradient at m = 0, with
                 the model's dynamics); its direction is judged on x·ŷ
    torque       a torque T + κ x the fuel burns for and the bus does not report: the fuel the model's torque
                 path makes of it, B_T/(A F_T) x (the gradient at κ = 0, one column)
    shift        the fuel signal's delay y(t − τ): tested and verified on seed 2's reference model
                 (ident.diagnosis.delay), not on the model itself
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fuelid.blas import one_blas_thread
from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.candidate import Candidate, Evidence
from fuelid.ident.diagnosis.delay import reference_fit, shift_test, verify_shift
from fuelid.ident.diagnosis.explanation import contribution_on_grid, explain, signals_text, static_gain
from fuelid.ident.diagnosis.run import Run
from fuelid.ident.diagnosis.statistics import lagged, level_test, score_test
from fuelid.ident.diagnosis.verification import (MIN_IDENTIFIABILITY, Baseline, identifiability, leave_one_trip_out,
                                                 slow_drifts, verify)
from fuelid.ident.filters import lfilter
from fuelid.ident.modeldata import at_operating_point
from fuelid.ident.polymodel import PolyModel


@dataclass
class TestColumns:
    """An effect's columns in the model's two tests (ident.diagnosis.statistics, 1–2), stacked over the run's
    segments after their first run.warm samples: psi its prewhitened lagged image ψ_x = D/C x (test 1), w = A x
    (test 2, in the domain of w), raw the lagged columns x in the fuel domain; reg its regressors on the dataset
    grid."""

    reg: fx.Regressors
    psi: np.ndarray
    w: np.ndarray
    raw: np.ndarray


class Additive:
    """y + Σ_l β_l x(t − l), tested on the model itself by both tests (ident.diagnosis.statistics, 1–2) and
    verified by its linearised refit (ident.diagnosis.verification); a regressor in the model's torque unit is
    verified with its image through the torque path beside it."""

    retested = True  # re-tested given the effects accepted before it (ident.diagnosis.selection, 5)
    drop_in_verdict = True  # the verdict quotes the model's held-out RMS error drop
    also_through_torque = True

    def regressors(self, reg: fx.Regressors, run: Run, ds) -> fx.Regressors:
        """The regressors the test uses, from the effect's own (on the dataset grid)."""
        return reg

    def path(self, model: PolyModel, x: np.ndarray) -> np.ndarray:
        """The lagged columns x of one segment in the fuel domain."""
        return x

    def columns(self, model: PolyModel, ds, run: Run, effect: fx.Effect) -> TestColumns | None:
        """The effect's columns in both tests (TestColumns); None when its signals are not logged."""
        reg = effect.build(ds)
        if reg is None:
            return None
        reg = self.regressors(reg, run, ds)
        psi, raw = [], []
        for seg in run.segs:
            x = self.path(model, lagged(np.nan_to_num(reg.x[seg]), effect.lags))
            psi.append(lfilter(model.D, model.C, x, axis=0)[run.warm:])
            raw.append(x[run.warm:])
        raw = np.vstack(raw)
        return TestColumns(reg, np.vstack(psi), lfilter(model.A, [1.0], raw, axis=0), raw)

    def test(self, model: PolyModel, ds, run: Run, effect: fx.Effect, cols: TestColumns | None,
             projected: tuple[np.ndarray, np.ndarray] | None) -> Evidence | None:
        """Both tests on the model itself of the effect's columns `cols` (`columns`), `projected` their nuisance-free
        parts (`projected_columns`); None when its signals are not logged."""
        if cols is None:
            return None
        with one_blas_thread():
            pred = score_test(run.e, cols.psi, run.Q, eps_projected=run.e_projected, X_projected=projected[0])
            level, left = level_test(run.r, cols.w, run.lens, run.QG, X_projected=projected[1])
        return Evidence(cols.reg, cols.raw, cols.w, {"prediction_error": pred, "simulation_error": level}, left,
                        pred.coef)

    def direction_regressor(self, c: Candidate, run: Run) -> np.ndarray:
        """The regressor the refit's change of the fuel must covary with in the effect's direction (Effect.sign):
        its first column x (for a regime: the mean change on minus off)."""
        return c.x[:, 0]

    def refit_columns(self, c: Candidate, model: PolyModel, ds, run: Run) -> tuple[np.ndarray, np.ndarray]:
        """The columns a refit adds for the candidate, stacked like run.r: (in the w domain, in the fuel domain);
        a regressor in the model's torque unit also through the model's torque path."""
        if self.through_torque(c, ds):
            return tuple(np.column_stack(p) for p in zip((c.w, c.x), torque_path_columns(model, run, c.reg.x[:, 0])))
        return c.w, c.x

    def through_torque(self, c: Candidate, ds) -> bool:
        return self.also_through_torque and c.definition.form == "input" and c.reg.units == (ds.input_units[1],)

    def verify(self, c: Candidate, model: PolyModel, ds, run: Run, base: Baseline) -> dict:
        """verify() the candidate against the model as it is (`base`, its Baseline on run); its explanation re-made
        from the refit's β."""
        X, Xy = self.refit_columns(c, model, ds, run)
        c.X = X  # for the refits on top of it
        X = np.ascontiguousarray(X)  # the refit's products' last bits depend on the layout: one for every entry kind
        v, beta, change = verify(base, X, ds)
        # does the fuel rise or fall with the effect? The covariance of the change adding it makes to the held-out
        # fuel (its own part and the model's re-fitted gains and offset together) with its direction regressor
        x0 = self.direction_regressor(c, run)
        v["direction"] = int(np.sign((change - change.mean()) @ (x0 - x0.mean())))
        v["identifiability"] = identifiability(run, *self.varying_column(c, run), self.confounders(c, ds, run))
        v["identifiable"] = bool(v["identifiability"] >= MIN_IDENTIFIABILITY)
        if len(base.groups) > 1:  # the refit fitted on the other trips, scored on each one
            without, with_ = base.trips, leave_one_trip_out(model, run, X, base.folds)
            n = np.array([g.size for g in base.groups])
            pooled = [np.sqrt(n @ np.square(e) / n.sum()) for e in (without.rmse, with_.rmse)]
            v["trips"] = {"rmse_without": without.rmse, "rmse_with": with_.rmse,
                          "rmse_drop_percent": [100.0 * (1.0 - b / a) for a, b in zip(without.rmse, with_.rmse)],
                          "pooled_rmse_drop_percent": float(100.0 * (1.0 - pooled[1] / pooled[0])),
                          "determined": with_.determined}
        if v["rmse_drop_percent"] > 0:  # the held-out-checked refit measures it better
            effect = c.definition
            gains = beta[:c.x.shape[1]].reshape(len(effect.lags), -1).sum(axis=0)
            if self.through_torque(c, ds):
                gains = gains + beta[-1] * static_gain(model, 1)
            c.explanation, c.size = explain(self, effect, c.reg, contribution_on_grid(effect.form, Xy, beta, run),
                                            gains, [model], at_operating_point(ds, model), run)
        return v

    def varying_column(self, c: Candidate, run: Run) -> tuple[np.ndarray, np.ndarray]:
        """(the part of the decisive column its signal's variation makes, the decisive column) in the fuel domain,
        stacked like run.r: whether the effect is identifiable (verification.identifiability). For x, x itself."""
        return c.x[:, 0], c.x[:, 0]

    def confounders(self, c: Candidate, ds, run: Run) -> np.ndarray | None:
        """What else its decisive column could be, beyond an offset and the initial states (verification.
        identifiability): for a bus signal whose physics is not known (Effect.zero False), a slow drift over each
        trip of what it adds to (`carrier`)."""
        return None if c.definition.zero else slow_drifts(ds, run, self.carrier(run))

    def carrier(self, run: Run) -> np.ndarray:
        """What the effect's column multiplies, stacked like run.r: 1 for an additive effect."""
        return np.ones(run.r.size)

    def relevance(self, v: dict) -> float:
        """The held-out RMS error drop [%] that decides a verification."""
        return v["rmse_drop_percent"]

    def why_not_admitted(self, v: dict, min_drop_percent: float) -> str | None:
        """Why the kind does not admit a verification v that is relevant and points the physics' way (a clause for
        the explanation), None when it does: every one but some of a fuel delay's (Shift)."""
        return None

    def sentence(self, effect, reg, gains, size: dict, sig: str, act: str) -> str | None:
        """The kind's own explanation (ident.diagnosis.explanation.explain), None for the common ones."""
        return None


class ScalesFuel(Additive):
    """y (1 + m x): a regeneration's post-injection, enrichment when cold or in thin air, no injection at all on
    overrun. Tested on x and x·ŷ; its direction and identifiability judged on x·ŷ."""

    def regressors(self, reg, run, ds):
        x = reg.x[:, 0]
        return fx.Regressors(np.column_stack([x, x * run.ysim]), (reg.names[0], f"{reg.names[0]} x model fuel"),
                             (reg.units[0], f"{reg.units[0]}.{ds.output_unit}"))

    def varying_column(self, c, run):
        # x·ŷ with x constant is the model's own fuel scaled: what identifies m is (x − x̄)·ŷ. A raw bus signal's
        # origin is arbitrary (0 °C), so its x̄·ŷ says nothing of how well m is determined: measured against its own
        # (x − x̄)·ŷ (Effect.zero)
        x, fuel = c.x[:, 0], run.ysim[run.index]
        varying = (x - x.mean()) * fuel
        return varying, x * fuel if c.definition.zero else varying

    def carrier(self, run):
        return run.ysim[run.index]  # a slowly drifting gain

    def direction_regressor(self, c, run):
        # x·ŷ: air density is nearly constant within a trip, and a trip's fuel level is not told apart from its
        # estimated initial state
        return c.x[:, 0] * run.ysim[run.index]

    def sentence(self, effect, reg, gains, size, sig, act):
        if effect.form == "regime":  # said as a regime's change while on (explain)
            return None
        # m is x·ŷ's coefficient, not read from x's own: x can be nearly constant over a trip, where a trip's fuel
        # level is not told apart from its initial state
        m = float(gains[1])
        step, per = (0.1, "10 %") if reg.units[0] == "1" else (10.0, f"10 {reg.units[0]}")
        size["relative_change_per_unit"] = m
        return f"fuel is {100 * abs(m) * step:.1f} % {'higher' if m > 0 else 'lower'} per {per} of {reg.names[0]} " \
               f"({sig}), in proportion to the fuel itself; {act}"


class Torque(Additive):
    """A torque T + κ x the engine delivers and the bus does not report (in the model's torque unit per unit of
    κ): tested as the fuel the model's torque path makes of it, B_T/(A F_T) x."""

    also_through_torque = False  # it is through the torque path already

    def path(self, model, x):
        return lfilter(model.B[1], np.convolve(model.A, model.F[1]), x, axis=0)

    def sentence(self, effect, reg, gains, size, sig, act):
        size["torque_scale"] = float(gains[0])
        per = reg.units[0].split("/")[-1] if "/" in reg.units[0] else ""
        return f"fuel burns for a torque the bus does not report: {reg.names[0]} × {gains[0]:.3g} {per} ({sig}); " \
               f"{act}"


class Shift(Additive):
    """The fuel signal's delay y(t − τ), tested and verified on seed 2's reference model (ident.diagnosis.delay);
    a property of the signal path, so not re-tested given fuelling effects."""

    retested = False
    drop_in_verdict = False  # the explanation says what the delay does to the model itself

    def columns(self, model, ds, run, effect):
        return None  # tested on its own reference model

    def test(self, model, ds, run, effect, cols, projected):
        ref = reference_fit(ds, run)
        test, left, x = shift_test(ds, run, ref)
        grid = np.full(len(ds.t), np.nan)
        grid[run.index] = x[:, 0]
        reg = fx.Regressors(grid[:, None], ("d/dt reference model's fuel",), (f"{ds.output_unit}/s",))
        return Evidence(reg, x, lfilter(model.A, [1.0], x, axis=0), {"reference_model_shift": test}, left, test.coef,
                        ref)

    def verify(self, c, model, ds, run, base):
        v = verify_shift(c.ref, model, ds, run, base.scores)
        tau = v["reference"]["delay_s"]
        # y(t − τ) ≈ (1 − τ/Ts) y(t) + (τ/Ts) y(t − Ts) for τ < Ts: the model's own taps hold such a delay
        v["sample_period_s"], v["within_one_sample"] = ds.Ts, bool(abs(tau) < ds.Ts)
        c.spec = f"{c.effect}={tau:.2f}"
        c.size = {"delay_s": tau}
        own = v["rmse_drop_percent"]
        c.explanation = (
            f"the fuel signal {'lags' if tau > 0 else 'leads'} speed and torque by {abs(tau):.2f} s "
            f"({signals_text(c.definition)}): seed 2's low-order model, whose dynamics cannot absorb a delay, fits "
            f"{v['reference']['rmse_drop_percent']:.1f} % better on held-out data with it; "
            + (f"this model's own dynamics absorb it (held-out RMS error {-own:+.1f} % with it)" if own < 2.0 else
               f"this model's held-out RMS error falls {own:.1f} % with it") + f"; add effect {c.spec}")
        return v

    def relevance(self, v):
        return v["reference"]["rmse_drop_percent"]  # the reference model's (verify_shift)

    def why_not_admitted(self, v, min_drop_percent):
        # at least one sample long (a shorter one the model's own taps hold, delay.py), and not making the model
        # itself worse beyond the relevance bar: the model absorbs a true delay, a spurious one (the reference's
        # misfit on a curved engine) it does not
        if v["within_one_sample"]:
            return f" — but it is shorter than one sample period ({v['sample_period_s']:g} s), which the model's " \
                   "own input taps interpolate: not a missing effect"
        if v["rmse_drop_percent"] < -min_drop_percent:
            return f" — but advancing the fuel by it changes this model's own held-out RMS error by " \
                   f"{-v['rmse_drop_percent']:+.0f} %: what the reference model gains is not a delay of the fuel " \
                   "signal: not confirmed"
        return None

    def sentence(self, effect, reg, gains, size, sig, act):
        tau = -float(gains[0])
        size["delay_s"] = tau
        way = "lags" if tau > 0 else "leads"
        return f"the fuel signal {way} speed and torque by about {abs(tau):.2f} s ({sig}; first-order estimate on " \
               f"seed 2's low-order model); {act}"


ENTRIES = {"additive": Additive(), "scales_fuel": ScalesFuel(), "torque": Torque(), "shift": Shift()}


def projected_columns(run: Run, columns: list[TestColumns | None]) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """Each candidate's test columns (`Additive.columns`; None: none) with the nuisance columns projected out:
    (M_Z ψ_x by run.Q, M_G w by run.QG). All of them in one product with each basis, which reads the basis
    (N × 60–95) once instead of once per candidate."""
    have = [c for c in columns if c is not None]
    if not have:
        return [None] * len(columns)
    with one_blas_thread():
        parts = [np.split(basis.project_out(np.column_stack([getattr(c, name) for c in have])),
                          np.cumsum([getattr(c, name).shape[1] for c in have])[:-1], axis=1)
                 for basis, name in ((run.Q, "psi"), (run.QG, "w"))]
    projected = iter(zip(*parts))
    return [None if c is None else next(projected) for c in columns]


def torque_path_columns(model: PolyModel, run: Run, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A torque-like regressor x (N, the model's torque unit) through the model's torque path, stacked like run.r:
    (B_T/F_T x, the column of the w domain; B_T/(A F_T) x, its fuel [output unit]) — ∂w/∂κ and ∂ŷ/∂κ when the
    torque the fuel burns for is T + κ x (ident.diagnosis.verification)."""
    x = np.nan_to_num(x)
    B, F = model.B[1], model.F[1]
    cols = [(lfilter(B, F, x[s])[run.warm:], lfilter(B, np.convolve(model.A, F), x[s])[run.warm:]) for s in run.segs]
    return np.concatenate([c[0] for c in cols]), np.concatenate([c[1] for c in cols])
