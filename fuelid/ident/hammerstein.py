"""The engine model: the engine's static fuel map (ident.enginemap) as a Hammerstein block under the paper's
Box-Jenkins dynamics, identified jointly by prediction-error minimisation.

    y(t) = y0 + Σ_i B_i/F_i ũ_i(t) + B_m/F_m x_map(t) + C/D e(t),
    x_map(t) = m(n(t), T(t)) = s(n, T) − (y0 + g_n ñ + g_T T̃),   s(n, T) = Σ_k c_k φ_k(n, T)

u = [speed, torque, x_map, torque rise r, r·s/f_scale, other effects' inputs…] (ident.effects' `engine_map`); s the
map, (g_n, g_T) = (G_n(1), G_T(1)) the static gains of the speed and torque paths (`path_gains`; the map's `plane`
(y0, g_n, g_T) after `joint_fit`), so m is the map beyond the plane those paths carry at rest; B_m/F_m of unit
static gain G_m(1) = 1. With m ≡ 0 it is the paper's linear model; its steady state is the map itself
(`steady_state_map`)

    f(n, T) = y0 + G_n(1) ñ + G_T(1) T̃ + G_m(1) m(n, T) = s(n, T).

Joint identification (`joint_fit`): block-coordinate descent (for Hammerstein systems Narendra & Gallman 1966,
Bai 1998) of PEM's criterion V = ½ Σ ε², ε = D/C (ỹ − Σ_i G_i ũ_i) (Ljung 1999, ch. 7), the map's block in the
output-error sense:

(a) the map starts from its static penalised fit to the time-aligned fuel (ident.effects.static_engine_map), m
    beyond its least-squares plane over the data; the dynamics from two starts, each continued by PEM (b) and the
    one `keep` picks kept: the given model (the linear model's dynamics with the map's path fitted beside them) and
    the static map alone (`static_start`: the whole map through B_m = 1, every other path at zero, the given noise
    model), from which PEM adds only the dynamics the data ask for beside the map; from the linear model's
    dynamics alone it can stop where the paths' slow poles hold part of the map, with a larger V and a simulation
    worse than the map's own (docs/explanation/engine-model.md, "What limits the accuracy");
(b) with the map fixed, PEM of every transfer function and the noise model (ident.pem.pem, warm-started);
(c) with the dynamics fixed, the simulation error is affine in the map's coefficients c — x_map = φ c − ℓ with
    ℓ = y0 + g_n ñ + g_T T̃ the paths' plane at the current gains, and the transient column r·s/f_scale = r φ c/f_scale:

        y − ŷ_s = w − Z c,   w = ỹ − Σ_{i ∉ map} G_i ũ_i + G_m ℓ,   Z = G_m φ + G_rs (r φ / f_scale),

    so the whole map, its plane included, is the penalised least-squares solution on the filtered basis columns Z
    (ident.enginemap.penalised_fit: the P-spline penalty, λ by cross-validation on this problem, monotone and
    non-negative):
    the fuel's steady level and slopes are fitted on the simulation error, where the speed and torque paths' static
    gains from (b) are only as good as PEM's slow poles let them be. Then rescaled to G_m(1) = 1: B_m and the
    transient column's B divided by the gain g, c replaced by g c − (g − 1) c_ℓ (c_ℓ the plane ℓ's coefficients,
    exact on the basis: x_map becomes g x_map, the same map path), the transient column's path the same up to its
    share of (g − 1) ℓ r / f_scale. The map is a static property: fitted through the noise model D/C instead (the same V
    as (b)), whose high-order D has roots near the unit circle, its level and slow errors weigh next to nothing;

(b)–(c) repeated while V or the simulation error falls by more than JOINT_TOL of itself (the two steps lower two
criteria), at most JOINT_ROUNDS rounds; of the start and the rounds' models the one identify's own rule keeps
(ident.identify.kept_fit: the lowest V unless another simulates the data grossly better) is kept, and renormalised so
that its map is its steady state (`as_steady_state`: step (b) last moved the gains). A map whose transfer function's
static gain fell to about zero or below (MIN_MAP_GAIN: the data put no weight on the map beyond the plane, as on an
engine whose fuel is a plane in speed and torque), where the rescaling is undefined, ends the rounds. The parameter
covariance is the last PEM's (the dynamics given the map); the map's coefficients carry none.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from fuelid.blas import one_blas_thread
from fuelid.ident.effects import MAP_COLUMNS
from fuelid.ident.enginemap import EngineMap, coefficient_covariance, penalised_fit
from fuelid.ident.filters import lfilter
from fuelid.ident.modeldata import model_data
from fuelid.ident.pem import pem
from fuelid.ident.polymodel import PolyModel, input_responses, residuals, simulate

MAP_EFFECT = "engine_map"
MAP_COLUMN, RISE_COLUMN, RISE_MAP_COLUMN = (f"{MAP_EFFECT}: {name}" for name in MAP_COLUMNS)
JOINT_ROUNDS = 4
JOINT_MAX_ITER = 30  # PEM iterations in each round's step (b), warm-started from the round before
FINAL_MAX_ITER = 100  # the kept round's step (b) continued to this limit when it stopped at JOINT_MAX_ITER
JOINT_TOL = 1e-3  # a round is worth another while it lowers V or the simulation error by more than this share
RENORMALISED_TOL = 0.01  # [1] `as_steady_state` is kept when it raises the simulation error by at most this share
MIN_MAP_GAIN = 0.05  # [1] a map block whose static gain fell below this carries next to nothing of the map


def engine_map_of(model: PolyModel) -> EngineMap | None:
    """The model's engine map (model.info["effect_parameters"]["engine_map"]), None for a model without one."""
    if MAP_EFFECT not in model.effects:
        return None
    return EngineMap.from_dict(model.info["effect_parameters"][MAP_EFFECT])


def static_gain(b: np.ndarray, f: np.ndarray) -> float:
    """G(1) = B(1)/F(1) of one transfer function."""
    return float(np.sum(b) / np.sum(f))


def path_gains(model: PolyModel) -> tuple[float, float]:
    """(G_n(1), G_T(1)): the static gains of the speed and torque paths, of 1/A · B_i/F_i [fuel unit/rpm, fuel
    unit/torque unit]."""
    a1 = float(np.sum(model.A))
    return tuple(static_gain(b, f) / a1 for b, f in zip(model.B[:2], model.F[:2]))


def as_steady_state(model: PolyModel) -> PolyModel:
    """The engine model with its map s renormalised to its steady state: with the map block's static gain
    g = G_m(1) and the paths' gains (g_n, g_T) (`path_gains`), the plane p = (p_0, p_n, p_T),

        s' = g s + (1 − g) p_0 + (g_n − g p_n) ñ + (g_T − g p_T) T̃,   plane' = (p_0, g_n, g_T),   B_m' = B_m / g,

    (the plane's coefficients exact on the B-spline basis: EngineMap.plane_coefficients) so that
    m' = s' − plane' = g m: the map's path is unchanged and f(n, T) = y0 + g_n ñ + g_T T̃ + G_m'(1) m' = s'
    over the knot box (speed is clamped outside it). The transient column r·s/f_scale takes s' (its B divided by g
    too): unchanged up to r times the plane's change (the transient fuelling's share of it). The coefficients'
    covariance becomes g² times its own (the plane's part is the paths', whose uncertainty θ's covariance carries).
    The model unchanged
    when G_m(1) is not above MIN_MAP_GAIN (no map to speak of)."""
    emap = engine_map_of(model)
    names = model.input_names
    j, jr = names.index(MAP_COLUMN), names.index(RISE_MAP_COLUMN)
    g = static_gain(model.B[j], model.F[j]) / float(np.sum(model.A))
    if not (np.isfinite(g) and g > MIN_MAP_GAIN):
        return model
    g_n, g_T = path_gains(model)
    p0, p_n, p_T = emap.plane
    c = g * emap.coef + emap.plane_coefficients((1.0 - g) * p0, g_n - g * p_n, g_T - g * p_T)
    fitted = emap.with_coefficients(c, (p0, g_n, g_T), covariance=None if emap.covariance is None
                                    else g ** 2 * emap.covariance)
    B = list(model.B)
    B[j], B[jr] = B[j] / g, B[jr] / g
    params = {**model.info["effect_parameters"], MAP_EFFECT: fitted.to_dict()}
    return dataclasses.replace(model, B=B, covariance=_scaled_b(model, (j, jr), 1.0 / g),
                               info={**model.info, "effect_parameters": params})


def _scaled_b(model: PolyModel, inputs, factor: float) -> np.ndarray | None:
    """The parameter covariance with the B coefficients of `inputs` multiplied by `factor` (D P D, D diagonal)."""
    if model.covariance is None:
        return None
    s = model.structure
    d = np.ones(s.n_params)
    start = s.na + np.cumsum((0, *s.nb))
    for i in inputs:
        d[start[i]: start[i] + s.nb[i]] = factor
    return model.covariance * np.outer(d, d)


def steady_state_map(model: PolyModel, n, T) -> np.ndarray:
    """The model's steady-state fuel [output unit] at speeds n [rpm] and torques T [torque unit] with every other
    input at its operating point: f(n, T) = y0 + G_n(1)(n − n0) + G_T(1)(T − T0) + G_m(1) m(n, T) (after
    `joint_fit` G_m(1) = 1 and the map's plane is (y0, G_n(1), G_T(1)), so f is the map s over its knot box:
    `as_steady_state`); for a model without an engine map, the plane y0 + G_n(1)(n − n0) + G_T(1)(T − T0). The transient
    columns are 0 in steady state; the static gains are of 1/A · B_i/F_i."""
    n, T = np.asarray(n, float), np.asarray(T, float)
    a1 = float(np.sum(model.A))
    gains = [static_gain(b, f) / a1 for b, f in zip(model.B, model.F)]
    f = model.y0 + gains[0] * (n - model.u0[0]) + gains[1] * (T - model.u0[1])
    emap = engine_map_of(model)
    if emap is not None:
        f = f + gains[model.input_names.index(MAP_COLUMN)] * emap.beyond_plane(n, T)
    return f


def map_summary(model: PolyModel) -> dict | None:
    """The engine map a model carries, in figures (JSON-ready): its region (speed [rpm] and torque [torque unit]
    ranges), the share of its coverage cells with data, the range of its fuel [fuel unit] over the covered cells'
    centres and of the model's steady state there (`steady_state_map`), and its units; None without one."""
    emap = engine_map_of(model)
    if emap is None:
        return None
    k = emap.coverage.shape[0]
    (n_lo, n_hi), (t_lo, t_hi) = emap.speed_range, emap.torque_range
    gn, gt = np.meshgrid(n_lo + (np.arange(k) + 0.5) * (n_hi - n_lo) / k, t_lo + (np.arange(k) + 0.5) * (t_hi - t_lo) / k,
                         indexing="ij")
    covered = emap.covered(gn, gt)
    s, f = emap(gn[covered], gt[covered]), steady_state_map(model, gn[covered], gt[covered])
    return {"speed_range": [n_lo, n_hi], "torque_range": [t_lo, t_hi], "covered_share": float(covered.mean()),
            "map_range": [float(s.min()), float(s.max())], "steady_state_range": [float(f.min()), float(f.max())],
            "units": {"speed": emap.speed_unit, "torque": emap.torque_unit, "fuel": emap.fuel_unit}}


def loss(model: PolyModel, u: np.ndarray, y: np.ndarray, segments) -> float:
    """PEM's criterion V = ½ Σ_s Σ_{t ≥ n_start} ε_s(t)² over the slices `segments` of u, y, each from zero state."""
    n0 = model.structure.n_start
    return float(sum(0.5 * np.sum(residuals(model, u[s], y[s])[n0:] ** 2) for s in segments))


def refit_map(model: PolyModel, ds, segments) -> PolyModel | None:
    """Step (c) of the module docstring: the model with its map's coefficients by penalised least squares on the
    simulation error given its dynamics, on the slices `segments` of dataset ds, rescaled to G_m(1) = 1, the map's
    plane the paths' static gains (y0, G_n(1), G_T(1)), with the coefficients' covariance (ident.enginemap.
    coefficient_covariance of the filtered basis Z and the simulation error left); None when
    the map's transfer function has no positive static gain G_m(1) > MIN_MAP_GAIN (the data give the map's input no
    weight: nothing to refit)."""
    emap = engine_map_of(model)
    names = model.input_names
    j, jr = names.index(MAP_COLUMN), names.index(RISE_MAP_COLUMN)
    gain = static_gain(model.B[j], model.F[j])
    if not (np.isfinite(gain) and gain > MIN_MAP_GAIN):
        return None
    u, y = model_data(model, ds)
    n, T = np.nan_to_num(ds.u[:, 0]), np.nan_to_num(ds.u[:, 1])
    phi = emap.basis(n, T)
    p0, (g_n, g_T) = emap.plane[0], path_gains(model)
    paths = emap.with_coefficients(np.zeros(emap.coef.size), (p0, g_n, g_T)).plane_at(n, T)  # y0 + g_n ñ + g_T T̃
    rise_phi = u[:, names.index(RISE_COLUMN)][:, None] * phi / emap.fuel_scale
    others = [i for i in range(len(model.B)) if i not in (j, jr)]
    sub = dataclasses.replace(model, B=[model.B[i] for i in others], F=[model.F[i] for i in others],
                              nk=[model.nk[i] for i in others], u0=[model.u0[i] for i in others],
                              input_names=[names[i] for i in others], input_units=[model.input_units[i] for i in others],
                              covariance=None)
    n0 = model.structure.n_start
    w_all, z_all = [], []
    with one_blas_thread():
        for s in segments:
            rest = lfilter(model.A, [1.0], y[s] - model.y0) - input_responses(sub, u[s][:, others]).sum(axis=1) \
                + lfilter(model.B[j], model.F[j], paths[s])
            w_all.append(rest[n0:])
            through = lfilter(model.B[j], model.F[j], phi[s], axis=0) \
                + lfilter(model.B[jr], model.F[jr], rise_phi[s], axis=0)
            z_all.append(through[n0:])
        w, Z = np.concatenate(w_all), np.vstack(z_all)
        kn, kt = emap.coef.shape
        c, lam, A = penalised_fit(Z, w, kn, kt)
        cov = coefficient_covariance(Z, w - Z @ c, A)
    # x_map = φ c − (y0 + g_n ñ + g_T T̃) times the gain: the plane's coefficients (exact on the basis) scaled alike
    c = gain * c - (gain - 1.0) * emap.plane_coefficients(p0, g_n, g_T).ravel()
    B = list(model.B)
    B[j], B[jr] = B[j] / gain, B[jr] / gain
    fitted = emap.with_coefficients(c, (p0, g_n, g_T), lam, gain ** 2 * cov)
    params = {**model.info["effect_parameters"], MAP_EFFECT: fitted.to_dict()}
    return dataclasses.replace(model, B=B, covariance=None, info={**model.info, "effect_parameters": params})


def _fitted(fit, u, y, start: PolyModel, Ts: float, segments, max_iter: int) -> PolyModel:
    """PEM (fit) of start's structure on u, y from `start`, with start's names, units, effects and info."""
    fitted = fit(u, y, start.structure, Ts, segments=segments, u0=start.u0, y0=start.y0, init=start,
                 max_iter=max_iter)
    return dataclasses.replace(fitted, input_names=start.input_names, input_units=start.input_units,
                               output_name=start.output_name, output_unit=start.output_unit, effects=start.effects,
                               training=start.training, info={**start.info, **fitted.info})


def simulation_error(model: PolyModel, u: np.ndarray, y: np.ndarray, segments) -> float:
    """RMS simulation error [output unit] over the slices `segments` of u, y, each from zero state, the first n_start
    samples left out."""
    n0 = model.structure.n_start
    err = np.concatenate([(y[s] - simulate(model, u[s]))[n0:] for s in segments])
    return float(np.sqrt(np.mean(err ** 2)))


def static_start(model: PolyModel) -> PolyModel:
    """The engine model `model` started from its static map alone: the map's column carries the whole map (its plane
    (y0, 0, 0), so x_map = s − y0) through B_m = 1, F_m = 1; every other input's path at zero (B = 0, F = 1: the
    speed and torque paths, the transient columns, other effects); the noise model as given. Its simulation is
    y = s(n, T)."""
    emap = engine_map_of(model)
    j = model.input_names.index(MAP_COLUMN)
    B = [np.zeros_like(b) for b in model.B]
    F = [np.r_[1.0, np.zeros(f.size - 1)] for f in model.F]
    B[j][model.nk[j]] = 1.0
    flat = emap.with_coefficients(emap.coef, (emap.plane[0], 0.0, 0.0))
    params = {**model.info["effect_parameters"], MAP_EFFECT: flat.to_dict()}
    return dataclasses.replace(model, B=B, F=F, covariance=None, info={**model.info, "effect_parameters": params})


def joint_fit(model: PolyModel, ds, segments, *, keep, fit=pem, rounds: int = JOINT_ROUNDS, tol: float = JOINT_TOL,
              max_iter: int = JOINT_MAX_ITER, from_static: bool = True) -> PolyModel:
    """The engine model `model` (with the engine_map effect, its dynamics fitted by PEM with its map fixed) refined by
    the block-coordinate descent of the module docstring on the slices `segments` of dataset ds; fit: `pem` or a
    FitMemo's; rounds, tol: at most that many rounds, while V or the simulation error falls by more than tol of
    itself (the rounds alternate two criteria: step (b) lowers V, step (c) the simulation error); max_iter: step
    (b)'s PEM iterations; from_static: also start from the static map (`static_start`, step (a)), False when the
    model is to be continued from where it is (a truck's previous model: another start could move it to another
    minimum, a drift the data do not show). Of the start and the rounds' models the one
    `keep(models, simulation errors)` picks is kept
    (ident.identify.kept_fit: the lowest V unless another simulates the data grossly better — a round can lower V
    while the noise model takes up a drift the simulation then shows), its step (b) continued to FINAL_MAX_ITER when
    it stopped at its limit (its convergence is PEM's own), then renormalised so that its map is its steady state
    (`as_steady_state`) unless that raises its simulation error by more than RENORMALISED_TOL (the transient
    column's share of a large plane change, or speeds beyond the knot box, where the renormalisation is not exact;
    its steady state is then the paths' gains and its map, `steady_state_map`). info["joint"] records V (`loss`) and
    the simulation error (`simulation_error`) of the start and each round, the round kept, why the rounds stopped and
    what the steady state is, and info["joint"]["starts"] V and the simulation error each start reached."""
    u, y = model_data(model, ds)
    V, sim = loss(model, u, y, segments), simulation_error(model, u, y, segments)
    model.info["loss_V"] = V
    starts = {"given": (V, sim)}
    first = None  # the PEM start of the model the rounds start from, when PEM fitted it here
    if from_static:
        start = static_start(model)
        u_s, y_s = model_data(start, ds)
        static = _fitted(fit, u_s, y_s, start, ds.Ts, segments, max_iter)
        V_s, sim_s = loss(static, u_s, y_s, segments), simulation_error(static, u_s, y_s, segments)
        static.info["loss_V"] = V_s
        starts["static map"] = (V_s, sim_s)
        if keep([model, static], [sim, sim_s]) == 1:
            model, u, y, V, sim, first = static, u_s, y_s, V_s, sim_s, start
    tried, history, sims, stop = [(model, u, y, first)], [V], [sim], "rounds"
    for _ in range(rounds):
        start = refit_map(model, ds, segments)
        if start is None:
            stop = "map gain not positive"
            break
        u, y = model_data(start, ds)
        cand = _fitted(fit, u, y, start, ds.Ts, segments, max_iter)
        V_new, sim_new = loss(cand, u, y, segments), simulation_error(cand, u, y, segments)
        cand.info["loss_V"] = V_new
        tried.append((cand, u, y, start))
        history.append(V_new)
        sims.append(sim_new)
        if not (V - V_new > tol * V or sim - sim_new > tol * sim):
            stop = "converged" if V_new < V else "a round raised V"
            break
        model, V, sim = cand, V_new, sim_new
    k = keep([m for m, *_ in tried], sims)
    model, u, y, start = tried[k]
    if start is not None and model.info["stop_reason"] == "max_iterations":  # the kept step (b) to its own end
        model = _fitted(fit, u, y, start, ds.Ts, segments, FINAL_MAX_ITER)
    renormalised = as_steady_state(model)
    before, after = simulation_error(model, u, y, segments), simulation_error(renormalised, *model_data(renormalised, ds),
                                                                             segments)
    steady = "its map"
    if after <= (1.0 + RENORMALISED_TOL) * before:
        model = renormalised
    else:  # the transient column's share of the plane, or speeds beyond the knot box, would change the simulation
        steady = (f"the paths' gains and its map (renormalised, the simulation error would rise from {before:.3g} "
                  f"to {after:.3g} {model.output_unit})")
    model.info["joint"] = {"starts": {name: {"loss_V": v, "simulation_rmse": e} for name, (v, e) in starts.items()},
                           "loss_V": history, "simulation_rmse": sims, "kept_round": k, "stop": stop,
                           "tolerance": tol, "steady_state": steady}
    return model
