"""A PolyModel for the tools engineers already use: a MATLAB script rebuilding it as an `idpoly`, or a .mat file.

MATLAB's System Identification Toolbox writes the same model as fuelid (Ljung's general form)::

    A(q) y(t) = Σ_i B_i(q)/F_i(q) u_i(t) + C(q)/D(q) e(t)

    sys = idpoly(A, B, C, D, F, NoiseVariance, Ts)

with every polynomial a row vector of coefficients of q⁰, q⁻¹, … (MATLAB's default `Variable` 'z^-1'), and for
several inputs B and F cell arrays of one row per input. An input delay of nk samples is nk leading zeros in
B_i, exactly as in fuelid's B arrays, so the script writes B as it is and leaves `InputDelay` at 0 (setting
both would delay twice). idpoly has no operating point: the script defines u0 and y0 and says how to use them,
y = y0 + sim(sys, u − u0). The parameter covariance is written as the matrix `P` with `theta_names` in
fuelid's order (a, b per input, f per input, c, d), not set on the idpoly: setcov expects the toolbox's own
parameter order and free/fixed bookkeeping.

An engine model (ident.hammerstein) adds its Hammerstein block, as MATLAB's `idnlhw` users know one: the static
nonlinearity in front of the linear model. Its map s(n, T) [fuel unit] is written twice: as the tensor-product
B-spline (knot vectors `map_speed_knots`, `map_torque_knots`, coefficients `map_coefficients`, for the Curve Fitting
Toolbox's `spmak`/`fnval`), and as its values `map_fuel` on a MAP_GRID × MAP_GRID grid (`map_speed`, `map_torque`)
for a `griddedInterpolant` (clamped outside the grid; fuelid continues linearly above the torque range), with
the data's coverage on that grid (`map_covered`), the plane (`map_plane`) and the cut torque; the script defines
`engine_inputs(n, T)`, the map's three input columns (the map beyond its plane, the torque rise r and r·s/f_scale)
that follow engine speed and torque in u.

Numbers are written with Python's shortest round-trip repr, which MATLAB reads back to the same double.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fuelid.ident.enginemap import CUT_TORQUE
from fuelid.ident.hammerstein import engine_map_of
from fuelid.ident.polymodel import PolyModel, parameter_names

MAP_GRID = 25  # grid points per axis of the engine map's values


def noise_variance(model: PolyModel) -> float | None:
    """λ, the variance of e [output unit²] the estimator recorded, None when unknown."""
    lam = model.info.get("noise_variance")
    return None if lam is None else float(lam)


def _num(x: float) -> str:
    return repr(float(x))


def _row(values) -> str:
    return "[" + " ".join(_num(v) for v in np.asarray(values, float).ravel()) + "]"


def _printable(s: str) -> str:
    """s without control characters (a newline would end a MATLAB comment or literal)."""
    return "".join(c for c in str(s) if c.isprintable())


def _text(s: str) -> str:
    """A MATLAB char literal: quotes doubled, control characters (never in a sane name) dropped."""
    return "'" + _printable(s).replace("'", "''") + "'"


def _cell(items) -> str:
    return "{" + ", ".join(items) + "}"


def matlab_script(model: PolyModel, source: str = "") -> str:
    """The text of a MATLAB script that builds `sys`, the idpoly of `model`, plus u0, y0, P and theta_names."""
    s = model.structure
    lam = noise_variance(model)
    lines = [
        f"% fuelid fuel model as a System Identification Toolbox idpoly{f' (from {_printable(source)})' if source else ''}.",
        "% A y = sum_i B_i/F_i u_i + C/D e; polynomials in q^-1, leading coefficient first; the nk leading",
        "% zeros of each B are its input delay in samples (InputDelay stays 0).",
        "% The model works on deviations from the operating point: y = y0 + sim(sys, u - u0).",
        f"Ts = {_num(model.Ts)};  % sampling interval [s]",
        f"fuel_lag_s = {_num(model.fuel_lag_s)};  % the fuel's samples were binned at their log time minus this [s]",
        f"A = {_row(model.A)};",
        "B = " + _cell(_row(b) for b in model.B) + ";",
        f"C = {_row(model.C)};",
        f"D = {_row(model.D)};",
        "F = " + _cell(_row(f) for f in model.F) + ";",
        "nk = [" + " ".join(map(str, model.nk)) + "];  % input delays [samples], already in B",
        f"NoiseVariance = {_num(lam if lam is not None else 1.0)};  % variance of e [({_printable(model.output_unit)})^2]"
        + ("" if lam is not None else " (not recorded: idpoly's default 1)"),
        f"u0 = {_row(model.u0)};  % input operating point [" + ", ".join(map(_printable, model.input_units)) + "]",
        f"y0 = {_num(model.y0)};  % output operating point [{_printable(model.output_unit)}]",
        "sys = idpoly(A, B, C, D, F, NoiseVariance, Ts, ...",
        f"    'InputName', {_cell(map(_text, model.input_names))}, 'InputUnit', {_cell(map(_text, model.input_units))}, ...",
        f"    'OutputName', {_cell([_text(model.output_name)])}, 'OutputUnit', {_cell([_text(model.output_unit)])}, ...",
        "    'TimeUnit', 'seconds');",
        "theta_names = " + _cell(map(_text, parameter_names(s))) + ";  % fuelid's parameter order",
    ]
    if model.covariance is not None:
        rows = ";\n    ".join(" ".join(_num(v) for v in r) for r in model.covariance)
        lines.append(f"P = [{rows}];  % covariance of theta (order of theta_names)")
    else:
        lines.append("P = [];  % covariance not known")
    return "\n".join(lines + _hammerstein_lines(model)) + "\n"


def map_grid(model: PolyModel) -> dict | None:
    """The engine map's values on a MAP_GRID × MAP_GRID grid over its knot box (speed first), its coverage there and
    its spline; None for a model without an engine map."""
    emap = engine_map_of(model)
    if emap is None:
        return None
    n = np.linspace(*emap.speed_range, MAP_GRID)
    T = np.linspace(*emap.torque_range, MAP_GRID)
    gn, gt = np.meshgrid(n, T, indexing="ij")
    return {"map_speed": n, "map_torque": T, "map_fuel": emap(gn, gt), "map_covered": emap.covered(gn, gt),
            "map_speed_knots": emap.speed_knots, "map_torque_knots": emap.torque_knots,
            "map_coefficients": emap.coef, "map_plane": np.asarray(emap.plane), "map_operating_point":
            np.asarray(emap.operating_point), "map_fuel_scale": emap.fuel_scale, "map_cut_torque": CUT_TORQUE}


def _matrix(a) -> str:
    return "[" + ";\n    ".join(" ".join(_num(v) for v in r) for r in np.atleast_2d(np.asarray(a, float))) + "]"


def _hammerstein_lines(model: PolyModel) -> list[str]:
    """The engine map block of the script (module docstring), [] for a model without one."""
    g = map_grid(model)
    if g is None:
        return []
    emap = engine_map_of(model)
    units = f"[{_printable(emap.speed_unit)}] x [{_printable(emap.torque_unit)}] -> [{_printable(emap.fuel_unit)}]"
    scale = 1000.0 if emap.torque_unit == "Nm" else 100.0
    return [
        "% --- Hammerstein block (idnlhw's input nonlinearity): the engine's static fuel map s(n, T), " + units,
        "% as a tensor-product cubic B-spline (Curve Fitting Toolbox: sp = spmak({map_speed_knots, map_torque_knots},"
        " map_coefficients))",
        f"map_speed_knots = {_row(g['map_speed_knots'])};",
        f"map_torque_knots = {_row(g['map_torque_knots'])};",
        f"map_coefficients = {_matrix(g['map_coefficients'])};",
        "% and its values on a grid (speed along rows), with the identification data's coverage there",
        f"map_speed = {_row(g['map_speed'])};",
        f"map_torque = {_row(g['map_torque'])};",
        f"map_fuel = {_matrix(g['map_fuel'])};",
        f"map_covered = logical({_matrix(g['map_covered'])});",
        f"map_plane = {_row(g['map_plane'])};  % [p0 pn pT]: the plane the model's speed and torque paths carry",
        f"map_operating_point = {_row(g['map_operating_point'])};  % [n0 T0] of the plane",
        f"map_fuel_scale = {_num(g['map_fuel_scale'])};  % the transient column's scale [{_printable(emap.fuel_unit)}]",
        f"map_cut_torque = {_num(g['map_cut_torque'])};  % at or below this torque the fuel is cut: s = 0",
        "map = griddedInterpolant({map_speed, map_torque}, map_fuel, 'spline', 'nearest');",
        "map_s = @(n, T) (T > map_cut_torque) .* max(map(n, T), 0);",
        "% the engine map's input columns, u = [n, T, engine_inputs(n, T), ...] (column vectors, Ts apart):",
        "engine_inputs = @(n, T) [map_s(n, T) - (map_plane(1) + map_plane(2) * (n - map_operating_point(1)) "
        "+ map_plane(3) * (T - map_operating_point(2))), ...",
        f"    max(gradient(T, Ts), 0) / {_num(scale)}, max(gradient(T, Ts), 0) / {_num(scale)} .* map_s(n, T) "
        "/ map_fuel_scale];",
    ]


def _cell_array(arrays) -> np.ndarray:
    """A 1-D object array (savemat writes a cell array), also when the arrays have equal lengths."""
    out = np.empty(len(arrays), dtype=object)
    for i, a in enumerate(arrays):
        out[i] = np.asarray(a, float)
    return out


def mat_variables(model: PolyModel) -> dict:
    """The variables of the .mat export: the same names as the MATLAB script, B and F as 1×m cell arrays."""
    lam = noise_variance(model)
    return {
        "Ts": model.Ts, "fuel_lag_s": model.fuel_lag_s, "A": model.A, "B": _cell_array(model.B), "C": model.C, "D": model.D, "F": _cell_array(model.F),
        "nk": np.asarray(model.nk, float), "NoiseVariance": np.nan if lam is None else lam,
        "u0": np.asarray(model.u0, float), "y0": model.y0,
        "InputName": np.array(model.input_names, dtype=object), "InputUnit": np.array(model.input_units, dtype=object),
        "OutputName": model.output_name, "OutputUnit": model.output_unit,
        "theta": model.theta, "theta_names": np.array(parameter_names(model.structure), dtype=object),
        "P": np.zeros((0, 0)) if model.covariance is None else model.covariance,
        **(map_grid(model) or {}),
    }


def write_matlab(model: PolyModel, path, source: str = "") -> None:
    Path(path).write_text(matlab_script(model, source), encoding="utf-8")


def write_mat(model: PolyModel, path) -> None:
    from scipy.io import savemat  # SciPy's io only here: reading and writing models needs none of it

    savemat(path, mat_variables(model), do_compression=True, oned_as="row")
