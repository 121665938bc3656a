"""Fuel truth: the seed paper's Box-Jenkins engine models, run on the simulator's true engine inputs.

    y(k) = Gw(q) W(k) + GT(q) T(k) + H(q) e(k),   Gw = q^-nk Bw/Fw,  GT = BT/FT,  H = C/D,   Ts = 0.3 s

Source of the coefficients: seed paper 000 (Madhusudhanan et al., "Engine fuel consumption modelling using
prediction error identification and on-road data"), Appendix, eqs. (21)-(32): Scania P320 diesel and Scania
P340 gas. They are embedded below (`PAPER_MODELS`) so the simulator runs without ../shared; a test checks them
against ../shared/design/paper_models.json whenever that file is present.

Units that make the printed gains plausible (checked against engine physics: 100 % of 1600 Nm at 1200 rpm is
201 kW, at 200 g/kWh 48 L/h diesel; the model gives 0.48 L/h/% x 93 % + 1.1 + 2.5 = 48 L/h):
  W  engine speed minus the 600 rpm idle operating point [rpm]
  T  actual engine torque (SPN 513, indicated) minus its idle value [% of the reference torque, SPN 544]
  y  fuel rate minus the idle fuel rate [L/h diesel, kg/h gas]
DC gains: Gw 0.0019 L/h per rpm, GT 0.48 L/h per % (diesel); 0.0031 kg/h per rpm, 0.37 kg/h per % (gas).

The printed diesel noise denominator D has a complex root pair at |z| = 1.033 (unstable, most likely from
rounding the coefficients to 4 digits). `stable_polynomial` reflects every root outside the unit circle to
1/conj(z); this keeps the noise spectrum's shape up to a constant factor, which the chosen noise level absorbs.
The same is applied to C so that H is minimum phase, i.e. the unique noise model a prediction-error method
can identify. The simulated H is recorded in the truth file with a note saying so.
"""
from dataclasses import dataclass

import numpy as np
from scipy import signal

TS_S = 0.3
"""Sampling interval of the paper's models [s]."""

PAPER_MODELS = {
    "diesel_p320": {
        "source": "seed paper 000, Appendix eqs. (21)-(26), Scania P320 diesel",
        "Gw": {"nk": 3, "B": [0, 0, 0, 0.001171, -0.001928, 0.001929, -0.001095],
               "F": [1, -2.042, 2.415, -1.78, 0.551, -0.1025]},
        "GT": {"nk": 0, "B": [0.08494, 0.05512, -0.03854, -0.06077, -0.03114],
               "F": [1, -0.5971, -0.5782, -0.2039, 0.3611, 0.03823]},
        "H": {"C": [1, -3.455, 4.74, -3.948, 3.758, -3.864, 2.36, -0.6951, 0.2516, -0.2643, 0.1683, -0.04875],
              "D": [1, -4.547, 8.628, -9.613, 8.999, -9.039, 7.537, -4.104, 1.584, -0.6304, 0.213, -0.02728]},
    },
    "gas_p340": {
        "source": "seed paper 000, Appendix eqs. (27)-(32), Scania P340 compressed gas",
        "Gw": {"nk": 3, "B": [0, 0, 0, 0.001887, -0.001204, 0.001189, -0.0003614],
               "F": [1, -1.591, 0.9563, 0.5942, -0.9717, 0.5044]},
        "GT": {"nk": 0, "B": [0.05099, 0.04245, -0.01672, 0.006218, 0.02182],
               "F": [1, -1.038, -0.02435, 0.8159, -0.6473, 0.1803]},
        "H": {"C": [1, -0.1898, -0.3046, -0.3604, -0.3639, 0.1212, 0.4104, -0.5819, 0.2884, 0.05158, 0.06619],
              "D": [1, -1.379, 0.1144, 0.1047, -0.06714, 0.442, 0.1539, -1.087, 1.1, -0.3445, -0.0315]},
    },
}
"""The appendix models as printed (polynomials in z^-1, leading coefficient first, B with nk leading zeros)."""

PAPER_JSON_KEYS = {"diesel_p320": "diesel_scania_p320", "gas_p340": "gas_scania_p340"}
"""Name of each model in ../shared/design/paper_models.json."""


@dataclass(frozen=True)
class FuelTruth:
    """One selectable fuel truth: a BJ model plus the operating point it is linearised around.

    `noise_std` is the standard deviation of the coloured noise H e [fuel unit], chosen so that the
    noise-free model explains about the paper's fit (91 % diesel, 85 % gas) on a mixed trip.
    """

    name: str
    fuel: str                 # "diesel" or "gas"
    fuel_unit: str            # "L/h" or "kg/h"
    idle_speed_rpm: float     # operating point of W
    idle_torque_pct: float    # operating point of T (indicated torque at idle)
    idle_fuel: float          # operating point of y [fuel unit]
    noise_std: float          # std of H e [fuel unit]
    fuel_density_kg_l: float  # to turn kg into L where needed

    @property
    def model(self) -> dict:
        return PAPER_MODELS[self.name]


TRUTHS = {
    "diesel_p320": FuelTruth("diesel_p320", "diesel", "L/h", 600.0, 7.0, 2.5, 1.8, 0.835),
    "gas_p340": FuelTruth("gas_p340", "gas", "kg/h", 600.0, 7.0, 2.8, 2.4, 1.0),
}


def stable_polynomial(coefficients) -> np.ndarray:
    """The monic polynomial in z^-1 whose roots are those of `coefficients`, each root z with |z| > 1
    replaced by 1/conj(z) (its mirror in the unit circle)."""
    roots = np.roots(coefficients)
    outside = np.abs(roots) > 1.0
    roots[outside] = 1.0 / np.conj(roots[outside])
    return np.real(np.poly(roots))


def noise_polynomials(truth: FuelTruth) -> tuple[np.ndarray, np.ndarray]:
    """(C, D) of the simulated noise model: the printed ones with roots reflected into the unit circle."""
    h = truth.model["H"]
    return stable_polynomial(h["C"]), stable_polynomial(h["D"])


def noise_gain(c: np.ndarray, d: np.ndarray, n: int = 20000) -> float:
    """sqrt(sum h_k^2), the std of H e for unit-variance white e, from the first n impulse-response taps."""
    impulse = np.zeros(n)
    impulse[0] = 1.0
    return float(np.sqrt(np.sum(signal.lfilter(c, d, impulse) ** 2)))


def deterministic_fuel(truth: FuelTruth, speed_rpm: np.ndarray, torque_pct: np.ndarray) -> np.ndarray:
    """Noise-free model output at Ts [fuel unit]:

        y0 = y_idle + Gw (n - n_idle) + GT (T - T_idle)

    speed_rpm, torque_pct: true engine speed [rpm] and indicated torque [%] at Ts (sim.trip: their bin means). The
    filters start at rest in the idle operating point, as the trips do.
    """
    m = truth.model
    w = speed_rpm - truth.idle_speed_rpm
    t = torque_pct - truth.idle_torque_pct
    return (truth.idle_fuel + signal.lfilter(m["Gw"]["B"], m["Gw"]["F"], w)
            + signal.lfilter(m["GT"]["B"], m["GT"]["F"], t))


def fuel_noise(truth: FuelTruth, n: int, rng: np.random.Generator, std: float | None = None) -> np.ndarray:
    """Coloured noise v = H e at Ts [fuel unit], std `std` (default `truth.noise_std`), H the truth's noise model;
    the filter is run over a 2000-sample lead-in first so that v starts stationary."""
    c, d = noise_polynomials(truth)
    sigma_e = (truth.noise_std if std is None else std) / noise_gain(c, d)
    lead = 2000
    e = rng.normal(0.0, sigma_e, n + lead)
    return signal.lfilter(c, d, e)[lead:]


def describe(truth: FuelTruth, std: float | None = None) -> dict:
    """The truth-file entry of a fuel truth: coefficients as printed and as simulated, units and notes; `std`: the
    noise std simulated (default `truth.noise_std`)."""
    m = truth.model
    c, d = noise_polynomials(truth)
    std = truth.noise_std if std is None else std
    return {
        "name": truth.name,
        "source": m["source"],
        "structure": "Box-Jenkins: y = Gw W + GT T + H e; Gw = q^-nk Bw/Fw, GT = q^-nk BT/FT, H = C/D",
        "ts_s": TS_S,
        "inputs": {
            "W": {"signal": "EEC1.EngSpeed", "spn": 190, "unit": "rpm",
                  "operating_point": truth.idle_speed_rpm},
            "T": {"signal": "EEC1.ActualEngPercentTorque", "spn": 513, "unit": "%",
                  "operating_point": truth.idle_torque_pct,
                  "note": "true indicated torque; the bus reports it unless an effect hides part of it"},
        },
        "output": {"unit": truth.fuel_unit, "operating_point": truth.idle_fuel,
                   "signal": "LFE1.EngFuelRate (SPN 183)" if truth.fuel == "diesel"
                   else "flow meter (0-10 V serial capture)"},
        "Gw": m["Gw"],
        "GT": m["GT"],
        "H_printed": m["H"],
        "H_simulated": {"C": c.tolist(), "D": d.tolist(),
                        "note": "printed C and D with every root outside the unit circle reflected to "
                                "1/conj(z) (the printed diesel D has a root pair at |z| = 1.033)"},
        "noise_std": std,
        "noise_e_std": std / noise_gain(c, d),
        "units_note": "torque in % of the reference torque, fuel in L/h (diesel) or kg/h (gas), speed with "
                      "the 600 rpm idle operating point subtracted: the only units that make the printed "
                      "gains physically plausible",
    }
