"""The engine's static fuel map f(n, T): a smooth surface over engine speed n [rpm] × torque T [the model's torque
unit, N·m or %], in the fuel unit [L/h or kg/h] — the nonlinear block of the engine model (ident.hammerstein).

The surface is a tensor-product cubic B-spline (P-spline, Eilers & Marx 1996),

    s(n, T) = Σ_i Σ_j c_ij B_i(n) C_j(T),

on equally spaced knots over the data's operating region [n_lo, n_hi] × [T_lo, T_hi] (`SEGMENTS` intervals per axis,
the knots extended three intervals beyond each end, so the basis reproduces every plane exactly), with the
second-difference penalty

    λ (‖Δ²_n c‖² + ‖Δ²_T c‖²)          (Δ² along the speed index i, resp. the torque index j)

which leaves a plane (indeed any a + b n + c T + d n T) unpenalised and bends the rest towards one where the data are
thin. λ is chosen by blocked cross-validation (`cv_smoothing`: the samples cut into blocks of BLOCK consecutive
samples, the blocks dealt into CV_FOLDS folds, each fold predicted by the unconstrained penalised fit to the others;
blocks rather than samples because the errors are correlated in time, where leave-one-out and its GCV shortcut
choose too little smoothing; Arlot & Celisse 2010), then the coefficients are fitted by penalised least
squares under the constraints (`penalised_fit`, scipy.optimize.lsq_linear):

- monotone in torque: c_i,j+1 ≥ c_i,j (more torque never takes less fuel; every combustion engine's map is so, and a
  B-spline with non-decreasing coefficients is non-decreasing);
- no negative fuel: each speed row's value at the lowest torque, v_i = (c_i,0 + 4 c_i,1 + c_i,2)/6 ≥ 0 (the torque
  basis at T_lo, `_axis` at u = 0). With the above, s(n, T) ≥ s(n, T_lo) = Σ_i B_i(n) v_i ≥ 0. Bounding c_i,0 itself
  instead would be wrong at the edge: c_i,0 is about the row's value one knot interval below T_lo (the Greville
  abscissa), so a row whose fuel at T_lo is less than its rise over one interval (low fuel at low torque next to its
  slope, as on an engine's map) needs a negative c_i,0, and c_i,0 ≥ 0 bends the surface up along the lowest interval.

Both are bounds on z = (v_i, c_i,j − c_i,j−1), c = M z (`monotone_transform`).

Outside the region (`basis`): speed is clamped to [n_lo, n_hi]; torque below T_lo is clamped to T_lo, above T_hi the
surface continues linearly along torque with its slope at T_hi (non-negative, so still monotone); at or below zero
torque (`CUT_TORQUE`: motoring, the injection cut) the fuel is 0.

The model's input is the map's part beyond a plane, m(n, T) = s(n, T) − (p_0 + p_n (n − n0) + p_T (T − T0))
(`beyond_plane`): p_0 the model's fuel at its operating point (n0, T0) (the data's idle fuel y0). A static fit
(`fit_map`) takes p_n, p_T the slopes of the least-squares plane of s over its data, so m has no speed- or
torque-linear component there; the engine model (ident.hammerstein) sets them to its speed and torque paths' static
gains, so that the model's steady state is s itself. A plane's coefficients on the basis are exact
(`EngineMap.plane_coefficients`, `greville`), so moving the plane between s and the paths leaves m a spline.

The validity region is the data's coverage: sample counts on a COVERAGE_BINS × COVERAGE_BINS grid over the knot box
(`covered`: at least COVERAGE_MIN samples in the cell).

The coefficients' covariance (`coefficient_covariance`) is the sandwich of the penalised least-squares estimate,
robust to errors correlated in time: with A = ΦᵀΦ + λ'P (the penalised Gram matrix), r = y − Φ ĉ and the samples
cut into consecutive blocks b of BLOCK samples,

    Cov(ĉ) = A⁻¹ (Σ_b Φ_bᵀ r_b r_bᵀ Φ_b) A⁻¹

(the cluster-robust estimator of Liang & Zeger 1986 with blocks as clusters; for the penalised fit's frequentist
covariance, Wood, *Generalized Additive Models*, 2017, §6.9). It ignores the bounds (where a bound holds, the true
spread is smaller) and the smoothing bias; a steady state s(p) = φ(p)ᵀ ĉ has the variance φ(p)ᵀ Cov(ĉ) φ(p)
(ident.steady).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cholesky, solve, solve_triangular
from scipy.optimize import lsq_linear

from fuelid.blas import in_one_blas_thread, one_blas_thread
from fuelid.errors import InputError

DEGREE = 3  # cubic
SEGMENTS = 6  # knot intervals per axis: 9 × 9 coefficients
CUT_TORQUE = 0.0  # at or below this torque [model unit] the injection is cut: no fuel
COVERAGE_BINS = 12
COVERAGE_MIN = 10  # samples in a coverage cell for it to count as covered
SMOOTHING_GRID = np.logspace(-6, 3, 19)  # λ tried by `cv_smoothing`, relative to tr(ΦᵀΦ)/tr(P)
MIN_SAMPLES = 200
BLOCK = 100  # samples (30 s at 0.3 s, longer than the errors' memory) per block of `cv_smoothing`, the covariance
CV_FOLDS = 5


def knots(lo: float, hi: float, segments: int = SEGMENTS) -> np.ndarray:
    """Equally spaced knots with `segments` intervals over [lo, hi], extended DEGREE intervals beyond each end."""
    if not hi > lo:
        hi = lo + 1.0
    h = (hi - lo) / segments
    return lo + h * np.arange(-DEGREE, segments + DEGREE + 1)


def _position(t: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(j, u, h) of x on equally spaced knots t (spacing h): x, clamped into the base interval [t[DEGREE],
    t[-DEGREE-1]] (NaN taken as its lower end), lies in its j-th interval [t[3 + j], t[4 + j]] at u ∈ [0, 1]."""
    k = len(t) - DEGREE - 1
    lo, hi, h = t[DEGREE], t[-DEGREE - 1], (t[-1] - t[0]) / (len(t) - 1)
    pos = (np.clip(np.where(np.isnan(x), lo, x), lo, hi) - lo) / h
    j = np.minimum(pos.astype(int), k - DEGREE - 1)
    return j, pos - j, h


def _axis(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """B-spline basis values (N × K) at x, clamped into the knots' base interval (`_position`).

    On equally spaced knots (`knots`, spacing h) the cubic B-splines non-zero on the j-th interval of the base are
    B_j … B_j+3, at the position u in it (de Boor 1978)

        B_j = v³/6,  B_j+1 = (3u²(u − 2) + 4)/6,  B_j+2 = (3v²(v − 2) + 4)/6,  B_j+3 = u³/6,   v = 1 − u."""
    x = np.asarray(x, float).ravel()
    j, u, _ = _position(t, x)
    v = 1.0 - u
    out = np.zeros((x.size, len(t) - DEGREE - 1))
    rows = np.arange(x.size)
    out[rows, j] = v * v * v / 6.0
    out[rows, j + 1] = (3.0 * u * u * (u - 2.0) + 4.0) / 6.0
    out[rows, j + 2] = (3.0 * v * v * (v - 2.0) + 4.0) / 6.0
    out[rows, j + 3] = u * u * u / 6.0
    return out


def _axis_slope(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """d/dx of each B-spline basis function (N × K) at x, clamped into the base interval as in `_axis`: its
    polynomials differentiated, dB_j/dx = −v²/(2h), dB_j+1/dx = u(3u − 4)/(2h), dB_j+2/dx = −v(3v − 4)/(2h),
    dB_j+3/dx = u²/(2h)."""
    x = np.asarray(x, float).ravel()
    j, u, h = _position(t, x)
    v = 1.0 - u
    out = np.zeros((x.size, len(t) - DEGREE - 1))
    rows = np.arange(x.size)
    for k, d in enumerate((-v * v, u * (3.0 * u - 4.0), -v * (3.0 * v - 4.0), u * u)):
        out[rows, j + k] = d / (2.0 * h)
    return out


def greville(t: np.ndarray) -> np.ndarray:
    """The Greville abscissae ξ_i = (t_i+1 + t_i+2 + t_i+3)/3 of the cubic B-splines on knots t (K): Σ_i ξ_i B_i(x) = x,
    so a line a + b x has the coefficients a + b ξ_i (de Boor 1978)."""
    k = len(t) - DEGREE - 1
    return (t[1: k + 1] + t[2: k + 2] + t[3: k + 3]) / 3.0


def second_differences(k: int) -> np.ndarray:
    """Δ² (k − 2 × k)."""
    return np.diff(np.eye(k), n=2, axis=0)


def penalty(kn: int, kt: int) -> np.ndarray:
    """R with ‖R c‖² = ‖Δ²_n C‖² + ‖Δ²_T C‖² for c = C.ravel() (C kn × kt, speed index first)."""
    return np.vstack([np.kron(second_differences(kn), np.eye(kt)), np.kron(np.eye(kn), second_differences(kt))])


def monotone_transform(kn: int, kt: int) -> np.ndarray:
    """M with c = M z, z = (v_i, c_i,j − c_i,j−1) per speed index i, v_i = (c_i,0 + 4 c_i,1 + c_i,2)/6 the row's value
    at the lowest torque: z ≥ 0 ⇔ non-negative and monotone in torque (module docstring). Per row, c_i,0 =
    v_i − (5 d_1 + d_2)/6 (d_j = c_i,j − c_i,j−1) and c_i,j = c_i,0 + d_1 + … + d_j."""
    edge = np.eye(kt)
    edge[0, 1:3] = (-5.0 / 6.0, -1.0 / 6.0)
    return np.kron(np.eye(kn), np.tril(np.ones((kt, kt))) @ edge)


@dataclass
class EngineMap:
    """A fitted static fuel map (module docstring). speed_knots [rpm], torque_knots [torque unit] the knot vectors,
    coef (kn × kt) [fuel unit]; plane (p_0 [fuel unit], p_n [fuel unit/rpm], p_T [fuel unit/torque unit]) about the
    operating point (n0 [rpm], T0 [torque unit]); fuel_scale [fuel unit] a typical fuel level (the transient columns'
    scale); smoothing λ [1] relative to tr(ΦᵀΦ)/tr(RᵀR); coverage (COVERAGE_BINS × COVERAGE_BINS) sample counts over
    the knot box, speed first."""

    speed_knots: np.ndarray
    torque_knots: np.ndarray
    coef: np.ndarray
    plane: tuple[float, float, float]
    operating_point: tuple[float, float]
    fuel_scale: float
    smoothing: float
    coverage: np.ndarray
    speed_unit: str = "rpm"
    torque_unit: str = "%"
    fuel_unit: str = "L/h"
    covariance: np.ndarray | None = None

    def __post_init__(self):
        self.speed_knots = np.asarray(self.speed_knots, float)
        self.torque_knots = np.asarray(self.torque_knots, float)
        self.coef = np.asarray(self.coef, float).reshape(len(self.speed_knots) - DEGREE - 1,
                                                         len(self.torque_knots) - DEGREE - 1)
        self.coverage = np.asarray(self.coverage, float)
        self.plane = tuple(float(v) for v in self.plane)
        self.operating_point = tuple(float(v) for v in self.operating_point)
        if self.covariance is not None:
            self.covariance = np.asarray(self.covariance, float).reshape(self.coef.size, self.coef.size)

    @property
    def speed_range(self) -> tuple[float, float]:
        """[n_lo, n_hi] [rpm], the knot box along speed."""
        return float(self.speed_knots[DEGREE]), float(self.speed_knots[-DEGREE - 1])

    @property
    def torque_range(self) -> tuple[float, float]:
        """[T_lo, T_hi] [torque unit], the knot box along torque."""
        return float(self.torque_knots[DEGREE]), float(self.torque_knots[-DEGREE - 1])

    def _axes(self, n, T) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(B_i(n) N × kn, C_j(T) N × kt, fuelled N): the axes' basis values with the extrapolation of the module
        docstring (speed clamped, torque clamped below T_lo, linear above T_hi) and whether T > CUT_TORQUE."""
        n, T = np.broadcast_arrays(np.asarray(n, float).ravel(), np.asarray(T, float).ravel())
        bn = _axis(self.speed_knots, n)
        bt = _axis(self.torque_knots, T)
        t_hi = self.torque_range[1]
        above = T > t_hi
        if above.any():
            bt[above] += (T[above] - t_hi)[:, None] * _axis_slope(self.torque_knots, t_hi)
        return bn, bt, T > CUT_TORQUE  # NaN torque: not fuelled

    def basis(self, n, T) -> np.ndarray:
        """Φ (N × kn·kt): s(n, T) = Φ c (c = coef.ravel(), speed index first), rows at T ≤ CUT_TORQUE zero."""
        bn, bt, fuelled = self._axes(n, T)
        phi = (bn[:, :, None] * bt[:, None, :]).reshape(len(bn), -1)
        phi[~fuelled] = 0.0
        return phi

    def __call__(self, n, T) -> np.ndarray:
        """s(n, T) [fuel unit] at speeds n [rpm] and torques T [torque unit] (arrays of one shape; 0 where T is
        NaN)."""
        shape = np.broadcast(np.asarray(n), np.asarray(T)).shape
        bn, bt, fuelled = self._axes(n, T)
        return np.where(fuelled, ((bn @ self.coef) * bt).sum(axis=1), 0.0).reshape(shape)

    def torque_slope(self, n, T) -> np.ndarray:
        """∂s/∂T (n, T) [fuel unit per torque unit], the fuel the engine burns for one more unit of torque at (n, T):
        0 where the injection is cut (T ≤ CUT_TORQUE, or NaN) and below the knot box (the map is flat there), the
        slope at T_hi above it (the map's linear extrapolation)."""
        shape = np.broadcast(np.asarray(n), np.asarray(T)).shape
        n, T = np.broadcast_arrays(np.asarray(n, float).ravel(), np.asarray(T, float).ravel())
        (t_lo, t_hi), bn = self.torque_range, _axis(self.speed_knots, n)
        slope = ((bn @ self.coef) * _axis_slope(self.torque_knots, T)).sum(axis=1)
        return np.where((T > CUT_TORQUE) & (T >= t_lo), slope, 0.0).reshape(shape)

    def plane_at(self, n, T) -> np.ndarray:
        """p_0 + p_n (n − n0) + p_T (T − T0) [fuel unit]."""
        p0, pn, pT = self.plane
        n0, T0 = self.operating_point
        return p0 + pn * (np.asarray(n, float) - n0) + pT * (np.asarray(T, float) - T0)

    def beyond_plane(self, n, T, s: np.ndarray | None = None) -> np.ndarray:
        """m(n, T) = s(n, T) − plane [fuel unit]: the model's map input (s: the map's values there, when known)."""
        return (self(n, T) if s is None else s) - self.plane_at(n, T)

    def covered(self, n, T) -> np.ndarray:
        """Whether (n, T) lies in a coverage cell with at least COVERAGE_MIN identification samples."""
        n, T = np.asarray(n, float), np.asarray(T, float)
        i, j = self._cells(n, T)
        inside = (i >= 0) & (i < COVERAGE_BINS) & (j >= 0) & (j < COVERAGE_BINS)
        out = np.zeros(np.broadcast(n, T).shape, bool)
        out[inside] = self.coverage[i[inside], j[inside]] >= COVERAGE_MIN
        return out

    def _cells(self, n, T):
        (n_lo, n_hi), (t_lo, t_hi) = self.speed_range, self.torque_range
        i = np.floor((n - n_lo) / (n_hi - n_lo) * COVERAGE_BINS)
        j = np.floor((T - t_lo) / (t_hi - t_lo) * COVERAGE_BINS)
        i = np.where(n == n_hi, COVERAGE_BINS - 1, i)
        j = np.where(T == t_hi, COVERAGE_BINS - 1, j)
        i, j = np.broadcast_arrays(np.nan_to_num(i, nan=-1).astype(int), np.nan_to_num(j, nan=-1).astype(int))
        return i, j

    def plane_coefficients(self, a: float, b_n: float, b_T: float) -> np.ndarray:
        """The coefficients (kn × kt) of the plane a + b_n (n − n0) + b_T (T − T0) [fuel unit] on this map's basis
        (`greville`): exact over the knot box."""
        n0, T0 = self.operating_point
        return a + b_n * (greville(self.speed_knots)[:, None] - n0) + b_T * (greville(self.torque_knots)[None, :] - T0)

    def with_coefficients(self, coef, plane, smoothing: float | None = None,
                          covariance: np.ndarray | None = None) -> EngineMap:
        """This map with other coefficients (kn·kt), plane, and smoothing λ and covariance [fuel unit²] (kn·kt ×
        kn·kt) when given (else this map's λ, and no covariance)."""
        return EngineMap(self.speed_knots, self.torque_knots, np.asarray(coef, float), plane, self.operating_point,
                         self.fuel_scale, self.smoothing if smoothing is None else smoothing, self.coverage,
                         self.speed_unit, self.torque_unit, self.fuel_unit, covariance)

    def to_dict(self) -> dict:
        """JSON-ready: the knots, coefficients (speed index first), plane, coverage and units."""
        return {"kind": "tensor-product cubic B-spline (P-spline)", "degree": DEGREE,
                "units": {"speed": self.speed_unit, "torque": self.torque_unit, "fuel": self.fuel_unit},
                "speed_knots": self.speed_knots.tolist(), "torque_knots": self.torque_knots.tolist(),
                "coefficients": self.coef.tolist(),
                "plane": {"p0": self.plane[0], "per_speed": self.plane[1], "per_torque": self.plane[2]},
                "operating_point": {"speed": self.operating_point[0], "torque": self.operating_point[1]},
                "fuel_scale": self.fuel_scale, "smoothing": self.smoothing,
                "cut_torque": CUT_TORQUE,
                "coverage": {"bins": COVERAGE_BINS, "min_samples": COVERAGE_MIN, "counts": self.coverage.tolist()},
                **({} if self.covariance is None else {"covariance": self.covariance.tolist()})}

    @classmethod
    def from_dict(cls, d: dict) -> EngineMap:
        """The map of a `to_dict` content; InputError when it is not one."""
        try:
            return cls(d["speed_knots"], d["torque_knots"], d["coefficients"],
                       (d["plane"]["p0"], d["plane"]["per_speed"], d["plane"]["per_torque"]),
                       (d["operating_point"]["speed"], d["operating_point"]["torque"]), float(d["fuel_scale"]),
                       float(d["smoothing"]), d["coverage"]["counts"], d["units"]["speed"], d["units"]["torque"],
                       d["units"]["fuel"], d.get("covariance"))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"malformed engine map: {exc}") from None


def plane_slopes(phi: np.ndarray, n: np.ndarray, T: np.ndarray, op) -> np.ndarray:
    """Π (2 × K): the slopes (p_n, p_T) of the least-squares plane a + p_n (n − n0) + p_T (T − T0) of Σ_k c_k φ_k
    over the samples (n, T) are Π c (op = (n0, T0))."""
    P = np.column_stack([np.ones_like(n), (n - op[0]) / 1000.0, (T - op[1]) / 1000.0])  # columns of order one
    with one_blas_thread():
        return 1e-3 * solve(P.T @ P, P.T @ phi, assume_a="pos")[1:]


def fold_grams(phi: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(G_f, g_f, yy_f) = (Φ_fᵀΦ_f, Φ_fᵀy_f, y_fᵀy_f) per fold f of CV_FOLDS: the samples (rows in time order) cut into
    consecutive blocks of BLOCK samples, block b in fold b mod CV_FOLDS."""
    fold = np.arange(len(y)) // BLOCK % CV_FOLDS
    parts = [(phi[fold == f], y[fold == f]) for f in range(CV_FOLDS)]
    return (np.stack([p.T @ p for p, _ in parts]), np.stack([p.T @ v for p, v in parts]),
            np.array([v @ v for _, v in parts]))


def cv_smoothing(G: np.ndarray, g: np.ndarray, yy: np.ndarray, P: np.ndarray) -> float:
    """λ [relative to tr(ΦᵀΦ)/tr(RᵀR)] of SMOOTHING_GRID minimising the blocked cross-validation error

        CV(λ) = Σ_f ‖y_f − Φ_f c_λ^(−f)‖²,   c_λ^(−f) = (G − G_f + λ' P)⁻¹ (g − g_f),

    of the unconstrained fit without fold f, from the folds' Gram matrices (`fold_grams`: G_f, g_f, yy_f stacked;
    G = Σ_f G_f, g = Σ_f g_f) and P = RᵀR; ‖y_f − Φ_f c‖² = yy_f − 2 cᵀg_f + cᵀG_f c."""
    Gall, gall = G.sum(axis=0), g.sum(axis=0)
    scale = np.trace(Gall) / np.trace(P)
    ridge = 1e-10 * np.trace(Gall) * np.eye(len(Gall))
    scores = []
    for lam in SMOOTHING_GRID:
        score = 0.0
        for Gf, gf, yyf in zip(G, g, yy):
            c = solve(Gall - Gf + lam * scale * P + ridge, gall - gf, assume_a="pos")
            score += yyf - 2 * c @ gf + c @ Gf @ c
        scores.append(score)
    return float(SMOOTHING_GRID[int(np.argmin(scores))])


@in_one_blas_thread  # N × K products: BLAS threads cost more than they save (fuelid.blas)
def penalised_fit(phi: np.ndarray, y: np.ndarray, kn: int, kt: int, smoothing: float | None = None,
                  monotone: bool = True) -> tuple[np.ndarray, float, np.ndarray]:
    """c = argmin ‖y − Φ c‖² + λ' ‖R c‖² (R: `penalty`, λ' = λ tr(ΦᵀΦ)/tr(RᵀR), λ by `cv_smoothing` when not given),
    monotone: under z = M⁻¹ c ≥ 0 (non-negative, monotone in torque; `monotone_transform`); Φ's rows in time order.

    The criterion is c'(G + λ'P)c − 2c'g + yᵀy (G = ΦᵀΦ, g = Φᵀy, P = RᵀR): with the Cholesky factor
    G + λ'P = L Lᵀ it is ‖Lᵀ c − L⁻¹ g‖² + const, a K × K bounded least-squares problem for scipy.optimize.lsq_linear
    (K = kn·kt; the penalty keeps G + λ'P well conditioned: its null space, the bilinear surfaces, is determined
    by any data not on one line). Returns (c, λ, A), A = G + λ'P the penalised Gram matrix
    (`penalised_gram`, for `coefficient_covariance`)."""
    G, g = phi.T @ phi, phi.T @ y
    lam = cv_smoothing(*fold_grams(phi, y), penalty_gram(kn, kt)) if smoothing is None else smoothing
    A = penalised_gram(G, lam, kn, kt)
    L = cholesky(A, lower=True)
    b = solve_triangular(L, g, lower=True)
    if not monotone:
        return solve_triangular(L.T, b, lower=False), lam, A
    M = monotone_transform(kn, kt)
    z = lsq_linear(L.T @ M, b, bounds=(0.0, np.inf), method="bvls").x
    return M @ z, lam, A


def penalty_gram(kn: int, kt: int) -> np.ndarray:
    """P = RᵀR of the second-difference penalty (`penalty`)."""
    R = penalty(kn, kt)
    return R.T @ R


def penalised_gram(G: np.ndarray, smoothing: float, kn: int, kt: int) -> np.ndarray:
    """A = G + λ' P (+ a ridge of 1e-10 tr G), λ' = λ tr(G)/tr(P): the Gram matrix of the penalised fit."""
    P = penalty_gram(kn, kt)
    return G + smoothing * np.trace(G) / np.trace(P) * P + 1e-10 * np.trace(G) * np.eye(len(G))


def coefficient_covariance(phi: np.ndarray, r: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Cov(ĉ) = A⁻¹ (Σ_b Φ_bᵀ r_b r_bᵀ Φ_b) A⁻¹ [fuel unit²] (module docstring) from the design Φ (N × K, rows in
    time order), the residuals r (N) and the penalised Gram matrix A (`penalised_gram`)."""
    blocks = np.arange(len(r)) // BLOCK
    scores = np.zeros((blocks[-1] + 1 if len(r) else 0, phi.shape[1]))
    np.add.at(scores, blocks, phi * r[:, None])
    Ainv_S = solve(A, scores.T, assume_a="pos")  # A⁻¹ Φ_bᵀ r_b, one column per block
    return Ainv_S @ Ainv_S.T


def fit_map(n, T, y, op, y0: float, units=("rpm", "%", "L/h"), smoothing: float | None = None) -> EngineMap:
    """The static map of fuel y [fuel unit] over speed n [rpm] and torque T [torque unit] (finite samples of the
    three arrays): knots over their range (torque from max(min T, CUT_TORQUE)), coefficients by `penalised_fit`
    (non-negative, monotone in torque; λ by `cv_smoothing` when not given), the plane through (op = (n0, T0), y0)
    with the slopes of the least-squares plane over these samples, their coverage, the coefficients' covariance
    (`coefficient_covariance`, the samples in the order given). InputError with fewer than MIN_SAMPLES samples above
    the cut torque."""
    n, T, y = (np.asarray(a, float).ravel() for a in (n, T, y))
    ok = np.isfinite(n) & np.isfinite(T) & np.isfinite(y)
    n, T, y = n[ok], T[ok], y[ok]
    fuelled = T > CUT_TORQUE
    if fuelled.sum() < MIN_SAMPLES:
        raise InputError(f"too little data for an engine map: {int(fuelled.sum())} samples with torque above "
                         f"{CUT_TORQUE:g} {units[1]}, at least {MIN_SAMPLES} needed")
    tn, tt = knots(n.min(), n.max()), knots(max(T[fuelled].min(), CUT_TORQUE), T.max())
    shell = EngineMap(tn, tt, np.zeros((len(tn) - DEGREE - 1) * (len(tt) - DEGREE - 1)), (0, 0, 0), op, 1.0, 0.0,
                      np.zeros((COVERAGE_BINS, COVERAGE_BINS)), *units)
    phi = shell.basis(n, T)
    kn, kt = shell.coef.shape
    c, lam, A = penalised_fit(phi[fuelled], y[fuelled], kn, kt, smoothing)
    with one_blas_thread():
        cov = coefficient_covariance(phi[fuelled], y[fuelled] - phi[fuelled] @ c, A)
    counts = np.histogram2d(n, T, bins=COVERAGE_BINS, range=[shell.speed_range, shell.torque_range])[0]
    plane = (y0, *(plane_slopes(phi, n, T, op) @ c))
    return EngineMap(tn, tt, c, plane, op, float(np.percentile(y, 95)) or 1.0, lam, counts, *units, cov)
