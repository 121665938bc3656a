"""Static baselines the dynamic model is judged against.

1. The steady-state engine map of paper 000, Section V.A: data points from segments of ≥ 3 s at essentially
   constant vehicle speed, interpolated over (engine speed, torque). "Essentially constant" is defined here
   as max − min of the (0.3 s-averaged) wheel-based vehicle speed ≤ 1 km/h over the window; each
   non-overlapping such window of one segment gives one point (window means of speed, torque and fuel).
   Interpolation: scipy's LinearNDInterpolator (piecewise linear on a Delaunay triangulation of the points,
   axes rescaled to the unit square) inside their convex hull, NearestNDInterpolator outside it.

2. The static locally weighted regression (LWR) models of paper 001, calibrated and evaluated on the
   resampled data:
     VB   fuel = f(vehicle speed v [km/h], acceleration dv/dt [m/s²])   (no wheel torque on the FMS bus)
     EB   fuel = f(engine speed n [rpm], engine torque T [Nm])
     EB*  fuel = f(n, T + J1 dω/dt),  ω = 2π n / 60 [rad/s], J1 [kg·m²]  (paper 001, eq. 2)
   with the fuel-shift sensitivity sweep (fuel advanced/delayed within ±1 s) and the J1 sweep, run in the
   paper's order by `seed2_baselines` (shift first, then J1 for EB* at that shift). Inputs outside the
   calibration range are clamped to it (`static_model`), as a lookup table holds its edge.

LWR is written here (`lwr`) because the libraries at hand do not have it in two dimensions: statsmodels'
lowess is 1-D only and scikit-learn has no local linear regression. It reproduces MATLAB's 2-D 'lowess'
surface fit (Curve Fitting Toolbox, used by paper 001): at each query point a linear model fitted by
weighted least squares to the `span` nearest points, tricube weights w = (1 − (d/d_max)³)³ of the
distance d relative to the farthest of them, after scaling each input by its standard deviation.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator, RegularGridInterpolator
from scipy.spatial import QhullError, cKDTree

from fuelid.errors import InputError, FuelidError
from fuelid.ident.dataset import VEHICLE_SPEED, Dataset


def _segment_ids(ds: Dataset) -> np.ndarray:
    """Per sample the index of its segment, −1 when invalid."""
    seg = np.full(len(ds), -1)
    for i, s in enumerate(ds.segments()):
        seg[s] = i
    return seg


def _vehicle_speed(ds: Dataset) -> np.ndarray:
    if VEHICLE_SPEED not in ds.extra:
        raise FuelidError(f"no vehicle speed ({VEHICLE_SPEED}) in the data")
    return ds.extra[VEHICLE_SPEED]


def steady_points(ds: Dataset, min_duration_s: float = 3.0, speed_tol_kmh: float = 1.0):
    """Steady-state points: (X (n×2) [rpm, torque unit of ds], fuel (n) [output unit of ds]).

    One point per non-overlapping window of ceil(min_duration_s / Ts) samples [s] inside one segment
    where the vehicle speed varies by at most speed_tol_kmh [km/h]; windows are taken greedily in time.
    """
    L = int(np.ceil(min_duration_s / ds.Ts))
    if len(ds) < L:
        return np.empty((0, 2)), np.empty(0)
    v, seg = _vehicle_speed(ds), _segment_ids(ds)
    vw, sw = sliding_window_view(v, L), sliding_window_view(seg, L)
    ok = (sw.min(axis=1) == sw.max(axis=1)) & (sw[:, 0] >= 0) & np.isfinite(vw).all(axis=1)
    ok &= np.where(ok, np.ptp(np.nan_to_num(vw), axis=1), np.inf) <= speed_tol_kmh
    starts, nxt = [], 0
    for i in np.flatnonzero(ok):
        if i >= nxt:
            starts.append(i)
            nxt = i + L
    idx = np.asarray(starts, dtype=int)[:, None] + np.arange(L)
    return ds.u[idx].mean(axis=1), ds.y[idx].mean(axis=1)


@dataclass
class EngineMap:
    """Steady-state fuel map: points X (n×2) [rpm, Nm] and fuel (n) [fuel unit]; call it with u (N×2)."""
    X: np.ndarray
    fuel: np.ndarray

    def __post_init__(self):
        if len(self.X) == 0:
            raise FuelidError("no steady-state segments for the engine map (vehicle speed never constant ≥ 3 s)")
        self._nearest = NearestNDInterpolator(self.X, self.fuel, rescale=True)
        try:
            self._linear = LinearNDInterpolator(self.X, self.fuel, rescale=True)
        except (QhullError, ValueError):  # fewer than 3 points or all on a line
            self._linear = None

    def __call__(self, u) -> np.ndarray:
        u = np.asarray(u, float)
        out = np.full(len(u), np.nan)
        ok = np.isfinite(u).all(axis=1)
        if ok.any():
            lin = self._linear(u[ok]) if self._linear is not None else np.full(ok.sum(), np.nan)
            out[ok] = np.where(np.isnan(lin), self._nearest(u[ok]), lin)
        return out


def engine_map(ds: Dataset, min_duration_s: float = 3.0, speed_tol_kmh: float = 1.0) -> EngineMap:
    """The paper-000 baseline map built from the steady-state points of ds (see steady_points)."""
    return EngineMap(*steady_points(ds, min_duration_s, speed_tol_kmh))


def lwr(X, y, Xq, span: float = 0.05, grid: int | None = None) -> np.ndarray:
    """Locally weighted linear regression (2-D lowess) of y on X, evaluated at Xq.

    X (n×p), y (n), Xq (m×p) in any units (each column is scaled by its standard deviation over X);
    span: the neighbourhood, a fraction of n when < 1 (MATLAB's convention), else a number of points.
    Rows with a non-finite value are left out of the fit; queries with one give NaN.
    grid: when given (p = 2), the local fits are made only at the grid × grid nodes spanning the finite
    queries and Xq is interpolated bilinearly between them — for many queries (each local fit costs one
    span-point neighbourhood: 900 points for span 0.05 of the 1.5 h trip); on that trip grid = 60 differs from
    the exact evaluation by 0.44 L/h RMS, the level of the fit's own noise (fuel std 20 L/h).
    """
    X, y, Xq = np.atleast_2d(np.asarray(X, float)), np.asarray(y, float), np.atleast_2d(np.asarray(Xq, float))
    q = np.isfinite(Xq).all(axis=1)
    if grid is not None and q.any():
        lo, hi = Xq[q].min(axis=0), Xq[q].max(axis=0)
        axes = [np.linspace(a, b if b > a else a + 1.0, grid) for a, b in zip(lo, hi)]
        nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(axes))
        surface = lwr(X, y, nodes, span).reshape((grid,) * len(axes))
        out = np.full(len(Xq), np.nan)
        out[q] = RegularGridInterpolator(axes, surface)(Xq[q])
        return out
    fit = np.isfinite(X).all(axis=1) & np.isfinite(y)
    X, y = X[fit], y[fit]
    p = X.shape[1]
    k = int(np.ceil(span * len(X))) if span < 1 else int(span)
    k = min(max(k, p + 2), len(X))
    if len(X) < p + 1:
        raise InputError(f"LWR needs at least {p + 1} finite points, got {len(X)}")
    scale = X.std(axis=0)
    scale[scale == 0] = 1.0
    tree = cKDTree(X / scale)
    out = np.full(len(Xq), np.nan)
    q = np.flatnonzero(q)
    for chunk in np.array_split(q, max(1, len(q) // 2000)):
        if not len(chunk):
            continue
        d, j = tree.query(Xq[chunk] / scale, k=k)
        d, j = d.reshape(len(chunk), k), j.reshape(len(chunk), k)
        dmax = d[:, -1:] * (1 + 1e-9) + 1e-12
        w = (1 - (d / dmax) ** 3) ** 3
        Z = np.concatenate([np.ones((len(chunk), k, 1)), (X[j] - Xq[chunk, None, :]) / scale], axis=2)
        Zw = Z * w[..., None]
        A = Zw.transpose(0, 2, 1) @ Z + 1e-9 * np.eye(p + 1)
        b = np.einsum("mki,mk->mi", Zw, y[j])
        out[chunk] = np.linalg.solve(A, b[..., None])[:, 0, 0]
    return out


STATIC_KINDS = ("VB", "EB", "EB*")


def static_inputs(ds: Dataset, kind: str, J1: float = 0.0) -> np.ndarray:
    """The regressors (N×2) of a paper-001 static model: 'VB' [km/h, m/s²], 'EB' [rpm, Nm] or
    'EB*' [rpm, Nm] with torque T + J1 dω/dt, J1 [kg·m²]. Derivatives are central differences on the
    grid, NaN next to an invalid sample."""
    if kind == "VB":
        v = _vehicle_speed(ds)
        return np.column_stack([v, np.gradient(v / 3.6, ds.Ts)])
    if kind == "EB":
        return ds.u
    if kind == "EB*":
        if ds.input_units[1] != "Nm":
            raise FuelidError("EB* needs the torque in Nm (EC1 reference torque missing)")
        dw = np.gradient(ds.u[:, 0] * 2 * np.pi / 60, ds.Ts)
        return np.column_stack([ds.u[:, 0], ds.u[:, 1] + J1 * dw])
    raise ValueError(f"static model kind must be one of {STATIC_KINDS}, got {kind!r}")


def _shift(ds: Dataset, x: np.ndarray, shift_s: float) -> np.ndarray:
    """x (N) shifted in time within each segment of ds: x_s(t) = x(t − shift_s), shift_s [s] rounded to whole
    samples; NaN where t − shift_s leaves the segment."""
    n = int(round(shift_s / ds.Ts))
    seg = _segment_ids(ds)
    idx = np.arange(len(ds)) - n
    ok = (idx >= 0) & (idx < len(ds))
    out = np.full(len(ds), np.nan)
    src = idx[ok]
    same = (seg[ok] >= 0) & (seg[src] == seg[ok])
    out[np.flatnonzero(ok)[same]] = x[src[same]]
    return out


def shifted_output(ds: Dataset, shift_s: float) -> np.ndarray:
    """Fuel shifted in time within each segment: y_s(t) = y(t − shift_s) (`_shift`); negative = fuel
    advanced (paper 001's 0.4 s advance is shift_s = −0.4)."""
    return _shift(ds, ds.y, shift_s)


def static_model(train: Dataset, test: Dataset, kind: str = "EB", J1: float = 0.0, shift_s: float = 0.0,
                 span: float = 0.05, grid: int | None = None, rows=None) -> np.ndarray:
    """Fuel predicted on `test` [output unit] by the LWR model `kind` calibrated on `train` with the fuel
    shifted by shift_s [s] (so it predicts the shifted fuel y(t − shift_s)); NaN on test's invalid samples
    and, when rows (indices) is given, everywhere else. span, grid: as in `lwr`.

    Inputs outside the range of the calibration data are clamped to it, input by input, as a lookup table
    holds its edge values: a local linear fit extrapolates without bound (VB calibrated on the 1.5 h trip,
    whose top speed is 85 km/h, gave −120 % cycle fuel on a motorway cycle driven at 87–89 km/h)."""
    keep = test.valid.copy()
    if rows is not None:
        keep &= np.isin(np.arange(len(test)), rows)
    X = static_inputs(train, kind, J1)[train.valid]
    if not len(X):
        raise InputError(f"{kind}: no valid calibration sample")
    Xq = np.clip(static_inputs(test, kind, J1)[keep], np.nanmin(X, axis=0), np.nanmax(X, axis=0))
    out = np.full(len(test), np.nan)
    out[keep] = lwr(X, shifted_output(train, shift_s)[train.valid], Xq, span, grid)
    return out


def outside_share(train: Dataset, test: Dataset, kind: str, J1: float = 0.0) -> float:
    """Share of test's valid samples with an input of `kind` outside the calibration range of train (where
    `static_model` clamps)."""
    X, Xq = static_inputs(train, kind, J1)[train.valid], static_inputs(test, kind, J1)[test.valid]
    with np.errstate(invalid="ignore"):
        out = (Xq < np.nanmin(X, axis=0)) | (Xq > np.nanmax(X, axis=0))
    return float(out.any(axis=1).mean()) if len(Xq) else float("nan")


def _spread(ds: Dataset, max_points: int | None) -> np.ndarray | None:
    """At most max_points valid sample indices evenly spread over ds (None: all)."""
    valid = np.flatnonzero(ds.valid)
    if max_points is None or len(valid) <= max_points:
        return None
    return valid[np.linspace(0, len(valid) - 1, max_points).astype(int)]


def _scores(y, yhat) -> tuple[float, float]:
    ok = np.isfinite(y) & np.isfinite(yhat)
    res = y[ok] - yhat[ok]
    return float(np.sqrt(np.mean(res ** 2))), float(1 - res @ res / np.sum((y[ok] - y[ok].mean()) ** 2))


def _best(sweep: dict, key: str) -> dict:
    """sweep with 'best_<key>' (the value of least RMSE) and 'best_at_edge' (it is the first or last value)."""
    i = int(np.nanargmin(sweep["rmse"]))
    return {**sweep, f"best_{key}": sweep[key][i], "best_at_edge": i in (0, len(sweep[key]) - 1)}


def fuel_shift_sweep(ds: Dataset, kind: str = "EB", shifts_s=None, J1: float = 0.0, span: float = 0.05,
                     max_points: int | None = None) -> dict:
    """Paper 001's fuel-shift sensitivity: for each shift [s] (default every sample within ±1 s) calibrate
    and evaluate `kind` on ds with the shifted fuel; returns {'shift_s', 'rmse' [output unit], 'r2'} lists
    and 'best_shift_s', the shift of least RMSE ('best_at_edge': it is the first or last tried). max_points:
    score on at most this many valid samples, evenly spread (every shift on the same ones; the calibration
    always uses all)."""
    if shifts_s is None:
        n = int(np.floor(1.0 / ds.Ts + 1e-9))
        shifts_s = np.arange(-n, n + 1) * ds.Ts
    rows = _spread(ds, max_points)
    out = {"shift_s": [], "rmse": [], "r2": []}
    for s in shifts_s:
        ys = shifted_output(ds, s)
        r, r2 = _scores(ys, static_model(ds, ds, kind, J1, s, span, rows=rows))
        out["shift_s"].append(float(s)), out["rmse"].append(r), out["r2"].append(r2)
    return _best(out, "shift_s")


def inertia_sweep(ds: Dataset, J1_values=None, shift_s: float = 0.0, span: float = 0.05,
                  max_points: int | None = None) -> dict:
    """Paper 001's J1 sweep for EB*: calibrate and evaluate on ds for each J1 [kg·m²] (default −5…5 in 0.25
    steps: the sign is left to the data, since the bus torque of a truck engine already contains the
    inertial part); returns {'J1', 'rmse' [output unit], 'r2'} lists and 'best_J1', the J1 [kg·m²] of least
    RMSE ('best_at_edge' as in `fuel_shift_sweep`). max_points: as in `fuel_shift_sweep`."""
    J1_values = np.arange(-5.0, 5.0 + 1e-9, 0.25) if J1_values is None else J1_values
    ys = shifted_output(ds, shift_s)
    rows = _spread(ds, max_points)
    out = {"J1": [], "rmse": [], "r2": []}
    for J in J1_values:
        r, r2 = _scores(ys, static_model(ds, ds, "EB*", J, shift_s, span, rows=rows))
        out["J1"].append(float(J)), out["rmse"].append(r), out["r2"].append(r2)
    return _best(out, "J1")


def seed2_baselines(train: Dataset, test: Dataset, kinds=STATIC_KINDS, *, span: float = 0.05, grid: int | None = 60,
                    J1_values=np.arange(-4.0, 4.0 + 1e-9, 0.5), sweep_points: int | None = 1000) -> dict:
    """Paper 001's procedure: the fuel-shift sweep (EB, J1 = 0) on `train` picks the shift τ [s]; for EB* the
    J1 sweep at τ picks J1 [kg·m²]; each model of `kinds` is then calibrated on train with the fuel shifted
    by τ and predicts test's measured fuel as ŷ(t) = f(x(t + τ)) (the model maps inputs to the fuel τ later).

    Returns {'predictions': {kind: ŷ (N) [output unit]}, 'outside': {kind: `outside_share`}, 'fuel_shift':
    sweep, 'J1': sweep or None, 'errors': {kind: message}} (a kind whose signals are missing, e.g. VB without
    vehicle speed, is an error, not a prediction). The sweeps score on sweep_points evenly spread samples;
    grid: as in `lwr`, for the predictions.
    """
    shift = fuel_shift_sweep(train, "EB", span=span, max_points=sweep_points)
    tau = shift["best_shift_s"]
    inertia = inertia_sweep(train, J1_values, tau, span, sweep_points) if "EB*" in kinds else None
    out = {"predictions": {}, "outside": {}, "fuel_shift": shift, "J1": inertia, "errors": {}}
    for kind in kinds:
        J1 = inertia["best_J1"] if kind == "EB*" else 0.0
        try:
            f = static_model(train, test, kind, J1, tau, span, grid)
        except FuelidError as exc:
            out["errors"][kind] = str(exc)
            continue
        out["predictions"][kind] = _shift(test, f, -tau)
        out["outside"][kind] = outside_share(train, test, kind, J1)
    return out
