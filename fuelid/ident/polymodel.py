"""MISO polynomial models in the shift operator q (Ljung, *System Identification*, 2nd ed., ch. 4).

The general structure, one output y and m inputs u_i, sampled every Ts seconds::

    A(q) y(t) = Σ_i  B_i(q)/F_i(q) · u_i(t)  +  C(q)/D(q) · e(t),        e white, variance λ

    A(q)   = 1 + a_1 q⁻¹ + … + a_na q⁻ⁿᵃ
    B_i(q) = q⁻ⁿᵏⁱ (b_i,0 + b_i,1 q⁻¹ + … + b_i,nb_i−1 q⁻⁽ⁿᵇⁱ⁻¹⁾)     (nk_i ≥ 0 leading zeros)
    F_i(q) = 1 + f_i,1 q⁻¹ + … + f_i,nf_i q⁻ⁿᶠⁱ
    C(q)   = 1 + c_1 q⁻¹ + … + c_nc q⁻ⁿᶜ,   D(q) = 1 + d_1 q⁻¹ + … + d_nd q⁻ⁿᵈ

Every polynomial is a numpy array of coefficients of q⁰, q⁻¹, … (leading coefficient first), exactly the
convention of scipy.signal.lfilter and of the paper's appendix (eqs. 21–32); B_i carries its nk_i leading
zeros. Named special cases: ARX (na, nb, nk), ARMAX (+ nc), OE (nb, nf, nk), BJ (nb, nf, nk, nc, nd).

Signals are in the units of the data; the model works on deviations from its operating point (u0, y0):
`simulate`, `predict` and `residuals` subtract u0 from the inputs and y0 from the output, and add y0 back to
outputs. All filters start from zero initial state (the data are deviations from a rest point).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from fuelid.errors import FuelidError
from fuelid.ident.filters import lfilter


@dataclass(frozen=True)
class Structure:
    """Orders and delays of a MISO polynomial model: per input nb_i, nf_i, nk_i; shared na, nc, nd."""

    nb: tuple[int, ...]
    nf: tuple[int, ...]
    nk: tuple[int, ...]
    nc: int = 0
    nd: int = 0
    na: int = 0

    def __post_init__(self):
        for name in ("nb", "nf", "nk"):
            object.__setattr__(self, name, tuple(int(v) for v in np.atleast_1d(getattr(self, name))))
        if not len(self.nb) == len(self.nf) == len(self.nk):
            raise ValueError(f"nb, nf, nk need one entry per input, got {self.nb}, {self.nf}, {self.nk}")
        if min(self.nb + self.nf + self.nk + (self.nc, self.nd, self.na)) < 0:
            raise ValueError("orders and delays must be non-negative")

    @classmethod
    def arx(cls, na, nb, nk):
        """A(q) y = Σ B_i(q) u_i + e."""
        nb = tuple(np.atleast_1d(nb))
        return cls(nb=nb, nf=(0,) * len(nb), nk=nk, na=na)

    @classmethod
    def armax(cls, na, nb, nc, nk):
        """A(q) y = Σ B_i(q) u_i + C(q) e."""
        nb = tuple(np.atleast_1d(nb))
        return cls(nb=nb, nf=(0,) * len(nb), nk=nk, nc=nc, na=na)

    @classmethod
    def oe(cls, nb, nf, nk):
        """y = Σ B_i(q)/F_i(q) u_i + e."""
        return cls(nb=nb, nf=nf, nk=nk)

    @classmethod
    def bj(cls, nb, nf, nk, nc, nd):
        """y = Σ B_i(q)/F_i(q) u_i + C(q)/D(q) e  (the paper's eq. 17)."""
        return cls(nb=nb, nf=nf, nk=nk, nc=nc, nd=nd)

    @property
    def n_inputs(self) -> int:
        return len(self.nb)

    @property
    def n_params(self) -> int:
        return self.na + sum(self.nb) + sum(self.nf) + self.nc + self.nd

    @property
    def kind(self) -> str:
        """'arx', 'armax', 'oe', 'bj' when the structure is one of the named cases, else 'poly'."""
        no_f = not any(self.nf)
        if no_f and self.nd == 0 and self.na > 0:
            return "armax" if self.nc else "arx"
        if self.na == 0 and all(self.nf):
            return "bj" if (self.nc or self.nd) else "oe"
        return "poly"

    @property
    def n_start(self) -> int:
        """Samples whose predictor depends on unknown initial state: max(na, nk_i + nb_i − 1, nf_i, nc, nd)."""
        lags = [self.na, self.nc, self.nd] + [k + b - 1 for k, b in zip(self.nk, self.nb)] + list(self.nf)
        return max(lags)


# The paper's Box-Jenkins orders (eq. 17): G_w nb=4 nf=5 nk=3, G_T nb=5 nf=5 nk=0, C and D of order 11.
PAPER_ORDERS = dict(nb=(4, 5), nf=(5, 5), nk=(3, 0), nc=11, nd=11)


def parse_orders(spec: str) -> dict:
    """'paper' or 'nb=4,5;nf=5,5;nk=3,0;nc=11;nd=11[;na=0]' → Structure keyword arguments (FuelidError if not)."""
    if spec == "paper":
        return dict(PAPER_ORDERS)
    if spec == "auto":
        raise FuelidError("--orders auto is an offline search (fuelid identify); here give paper or a SPEC")
    out = {}
    try:
        for part in filter(None, (p.strip() for p in spec.replace(" ", ";").split(";"))):
            key, value = (x.strip() for x in part.split("=", 1))
            if key in ("nb", "nf", "nk"):
                out[key] = tuple(int(v) for v in value.split(","))
            elif key in ("nc", "nd", "na"):
                out[key] = int(value)
            else:
                raise ValueError(f"unknown order {key!r}")
        if "nb" not in out:
            raise ValueError("nb is required")
        m = len(out["nb"])
        out.setdefault("nf", (0,) * m)
        out.setdefault("nk", (1,) * m)
        if not len(out["nf"]) == len(out["nk"]) == m == 2:
            raise ValueError("nb, nf and nk need one value per input (engine speed, torque)")
    except ValueError as exc:  # int() and unpacking say what is wrong; the message names the option
        raise FuelidError(f"--orders {spec!r}: {exc}") from exc
    return out


def parameter_names(s: Structure) -> list[str]:
    """Names of θ's entries in order: a…, then per input b…, then per input f…, then c…, d…

    θ = [a_1…a_na, b_1,0…b_1,nb1−1, …, b_m,…, f_1,1…f_1,nf1, …, f_m,…, c_1…c_nc, d_1…d_nd]; B coefficients are
    named by their lag (b1_3 multiplies u_1(t−3)).
    """
    names = [f"a{j}" for j in range(1, s.na + 1)]
    names += [f"b{i + 1}_{s.nk[i] + j}" for i in range(s.n_inputs) for j in range(s.nb[i])]
    names += [f"f{i + 1}_{j}" for i in range(s.n_inputs) for j in range(1, s.nf[i] + 1)]
    names += [f"c{j}" for j in range(1, s.nc + 1)] + [f"d{j}" for j in range(1, s.nd + 1)]
    return names


@dataclass
class PolyModel:
    """A(q) y = Σ B_i/F_i u_i + C/D e with metadata; see the module docstring for the conventions.

    Ts [s]; nk per input; u0 [input units] and y0 [output unit] the operating point; covariance the
    parameter covariance P of θ (order of `parameter_names`), None when unknown; info estimator facts
    (iterations, loss V, λ, warnings, wall time); effects the physical effects included (ids); training a
    summary of the identification data; validation the metrics measured on it.
    """

    A: np.ndarray
    B: list[np.ndarray]
    F: list[np.ndarray]
    C: np.ndarray
    D: np.ndarray
    Ts: float
    nk: tuple[int, ...]
    input_names: tuple[str, ...] = ()
    input_units: tuple[str, ...] = ()
    output_name: str = "y"
    output_unit: str = ""
    u0: tuple[float, ...] = ()
    y0: float = 0.0
    covariance: np.ndarray | None = None
    info: dict = field(default_factory=dict)
    effects: tuple[str, ...] = ()
    training: dict = field(default_factory=dict)
    validation: dict = field(default_factory=dict)

    def __post_init__(self):
        self.A, self.C, self.D = (np.asarray(p, float) for p in (self.A, self.C, self.D))
        self.B = [np.asarray(b, float) for b in self.B]
        self.F = [np.asarray(f, float) for f in self.F]
        m = len(self.B)
        self.nk = tuple(int(k) for k in self.nk)
        if len(self.F) != m or len(self.nk) != m:
            raise ValueError("B, F and nk need one entry per input")
        for poly, name in [(self.A, "A"), (self.C, "C"), (self.D, "D")] + [(f, "F") for f in self.F]:
            if poly.ndim != 1 or poly.size == 0 or poly[0] != 1.0:
                raise ValueError(f"{name} must be monic (leading coefficient 1)")
        for b, k in zip(self.B, self.nk):
            if b.ndim != 1 or b.size < k or np.any(b[:k] != 0):
                raise ValueError("each B_i must start with its nk_i zero coefficients")
        self.input_names = tuple(self.input_names) or tuple(f"u{i + 1}" for i in range(m))
        self.input_units = tuple(self.input_units) or ("",) * m
        self.u0 = tuple(float(v) for v in self.u0) or (0.0,) * m
        self.y0 = float(self.y0)
        self.effects = tuple(self.effects)
        if self.covariance is not None:
            self.covariance = np.asarray(self.covariance, float)

    @property
    def fuel_lag_s(self) -> float:
        """The fuel signal's reporting lag [s] its data were binned with (training.fuel_lag_s; 0 without it)."""
        return float(self.training.get("fuel_lag_s", 0.0))

    @property
    def structure(self) -> Structure:
        return Structure(
            nb=tuple(b.size - k for b, k in zip(self.B, self.nk)),
            nf=tuple(f.size - 1 for f in self.F),
            nk=self.nk,
            nc=self.C.size - 1,
            nd=self.D.size - 1,
            na=self.A.size - 1,
        )

    @property
    def theta(self) -> np.ndarray:
        """θ in the order of `parameter_names`."""
        return Polynomials(self.A, self.B, self.F, self.C, self.D).theta(self.nk)

    @property
    def std_errors(self) -> np.ndarray | None:
        """Standard errors √diag(P) of θ, None without a covariance."""
        return None if self.covariance is None else np.sqrt(np.diag(self.covariance))


class Polynomials(NamedTuple):
    """The polynomials of a parameter vector θ: A, B_i (with their nk_i leading zeros), F_i, C, D."""

    A: np.ndarray
    B: list[np.ndarray]
    F: list[np.ndarray]
    C: np.ndarray
    D: np.ndarray

    def theta(self, nk) -> np.ndarray:
        """θ in the order of `parameter_names` (nk the input delays: the leading zeros of each B_i)."""
        return np.concatenate([self.A[1:]] + [b[k:] for b, k in zip(self.B, nk)] + [f[1:] for f in self.F]
                              + [self.C[1:], self.D[1:]])


def polynomials(theta: np.ndarray, s: Structure) -> Polynomials:
    """The polynomials of structure s with parameter vector θ (order of `parameter_names`), without the checks
    and metadata of a PolyModel (the PEM evaluates them for every trial step): views into one array, gathered
    from [1, 0, θ] in one step (`_layout`)."""
    theta = np.asarray(theta, float)
    if theta.size != s.n_params:
        raise ValueError(f"θ has {theta.size} entries, structure {s} needs {s.n_params}")
    source, spans = _layout(s)
    full = np.concatenate(([1.0, 0.0], theta))[source]
    p = [full[a:b] for a, b in spans]
    m = s.n_inputs
    return Polynomials(A=p[0], B=p[1 : 1 + m], F=p[1 + m : 1 + 2 * m], C=p[-2], D=p[-1])


@functools.lru_cache(maxsize=None)
def _layout(s: Structure) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Where each coefficient of A, B_1…B_m, F_1…F_m, C, D, laid end to end, comes from in [1, 0, θ] (the leading
    1 of A, F_i, C, D; the nk_i leading zeros of B_i; θ's entries in order), and each polynomial's (start, stop)
    in that layout."""
    source, spans, k = [], [], 2
    for lead, n, count in ([(0, 1, s.na)] + [(1, nk, nb) for nb, nk in zip(s.nb, s.nk)] + [(0, 1, nf) for nf in s.nf]
                           + [(0, 1, s.nc), (0, 1, s.nd)]):
        spans.append((len(source), len(source) + n + count))
        source += [lead] * n + list(range(k, k + count))
        k += count
    return np.array(source, dtype=np.intp), spans


def from_theta(theta: np.ndarray, s: Structure, Ts: float, **meta) -> PolyModel:
    """The PolyModel of structure s with parameter vector θ (order of `parameter_names`)."""
    return PolyModel(**polynomials(theta, s)._asdict(), Ts=Ts, nk=s.nk, **meta)


def as_inputs(u, m: int | None = None) -> np.ndarray:
    """Inputs as an (N, m) float array; a 1-D u is one input."""
    u = np.asarray(u, float)
    u = u[:, None] if u.ndim == 1 else u
    if u.ndim != 2 or (m is not None and u.shape[1] != m):
        raise ValueError(f"u must be (N, {m or 'm'}), got shape {np.shape(u)}")
    return u


def input_responses(model: PolyModel, u) -> np.ndarray:
    """x_i(t) = B_i(q)/F_i(q) (u_i(t) − u0_i), one column per input, zero initial state."""
    du = as_inputs(u, len(model.B)) - np.asarray(model.u0)
    x = np.empty_like(du)
    for i, (b, f) in enumerate(zip(model.B, model.F)):
        x[:, i] = lfilter(b, f, du[:, i])
    return x


def simulate(model: PolyModel, u) -> np.ndarray:
    """Noise-free output (e = 0): y_s(t) = y0 + 1/A(q) · Σ_i B_i(q)/F_i(q) (u_i(t) − u0_i)."""
    return model.y0 + lfilter([1.0], model.A, input_responses(model, u).sum(axis=1))


def residuals(model: PolyModel, u, y) -> np.ndarray:
    """One-step prediction errors ε(t) = D(q)/C(q) · [A(q) ỹ(t) − Σ_i B_i(q)/F_i(q) ũ_i(t)],  ỹ = y − y0, ũ = u − u0.

    This is H⁻¹(q)(y − G(q)u) with G_i = B_i/(A F_i), H = C/(A D) (Ljung eq. 3.19, paper eq. 4).
    """
    w = lfilter(model.A, [1.0], np.asarray(y, float) - model.y0) - input_responses(model, u).sum(axis=1)
    return lfilter(model.D, model.C, w)


def predict(model: PolyModel, u, y, k: int | float = 1) -> np.ndarray:
    """k-step-ahead prediction ŷ(t | t−k);  k = math.inf gives the simulation.

    ŷ(t|t−k) = W_k(q) G(q) u(t) + (1 − W_k(q)) y(t),  W_k = H̄_k H⁻¹  (Ljung eq. 3.31), where
    H̄_k(q) = Σ_{j<k} h_j q⁻ʲ is the first k terms of the impulse response of H = C/(A D). Since
    H⁻¹(y − G u) = ε, this is ŷ(t|t−k) = y(t) − H̄_k(q) ε(t): the output minus the part of the noise not yet
    known k samples earlier.
    """
    if k == math.inf:
        return simulate(model, u)
    if k < 1 or k != int(k):
        raise ValueError(f"prediction horizon must be a positive integer or math.inf, got {k}")
    impulse = np.zeros(int(k))
    impulse[0] = 1.0
    h_k = lfilter(model.C, np.convolve(model.A, model.D), impulse)
    return np.asarray(y, float) - lfilter(h_k, [1.0], residuals(model, u, y))
