"""Effects the engineer defines: a small TOML file that describes a physical effect fuelid's catalogue
(ident.effects) lacks, in the catalogue's own terms, so `fuelid diagnose --effects-file F` tests it beside the
built-in ones and `fuelid identify --effects-file F --effect ID` adds it. docs/reference/formats.md gives the format,
docs/effects-example.toml an example.

    [[effect]]
    id = "hot_intake_air"                 # [a-z][a-z0-9_]*, not a built-in id
    name = "hot intake air"
    enters = "scales_fuel"                # additive | scales_fuel | torque | shift
    unit = "K"                            # the unit of x
    x = { excess = "AMB.EngAirInletTemp", above = 30.0 }
    explanation = "fuel is {percent:.1f} % higher per K of intake air above 30 °C ({signals})"
    physics = "..."                       # optional; sign = +1 | -1 | 0, orders = [nb, nf, nk] optional

The transform x is a tree of a few operators over bus signals (DBC names MESSAGE.Signal, checked against
fuelid/dbc/fms.dbc); a bare string is the signal's value:

    "MSG.Sig" or {signal = "MSG.Sig"}   the value, held across the bus's short gaps
    {state = X, on = [v, …]}            1 where X is one of the values, else 0 (an on/off state)
    {state = X, between = [lo, hi]}     1 where lo ≤ X ≤ hi, else 0
    {deficit = X, below = r}            max(r − X, 0)   (a deficit below a reference)
    {excess = X, above = r}             max(X − r, 0)   (an excess above a level)
    {rate = X}                          dX/dt [unit of X per s]
    {product = [X, Y, …]}               X · Y · …

How it enters decides the columns a refit adds (as for the built-in effects): an on/off state that scales the
fuel is a regime, I, I·ñ, I·T̃ (ident.effects.regime: the built-in DPF regeneration exactly); a continuous x that
scales the fuel, x, x·ñ, x·T̃ (the first-order terms of y (1 + m x)); additive and torque, x alone; a shift has
no x (the fuel signal's delay, tested like fuel_delay). The explanation template is Python format syntax over
{signals} (DBC names and SPNs), {size} (the effect's size: fuel change while on [fuel unit] for a state, relative
fuel change per unit of x when it scales the fuel, torque per unit of x for a torque, fuel per unit of x when
additive), {percent} (for a state the % change while on, for scales_fuel 100 × size; else NaN), {rms} (RMS
fuel contribution), {unit} (the fuel unit) and {x_unit}.

A model identified with such an effect carries its definition (model.info["effect_definitions"]), so compare,
diagnose and report rebuild its inputs without the file.
"""
from __future__ import annotations

import functools
import math
import re
import string
import tomllib
from dataclasses import dataclass
from pathlib import Path

import cantools
import numpy as np

from fuelid.dbc import FMS_DBC
from fuelid.errors import InputError
from fuelid.ident import effects as fx

ENTERS = ("additive", "scales_fuel", "torque", "shift")
FIELDS = {"id", "name", "enters", "unit", "x", "explanation", "physics", "sign", "orders"}
TEMPLATE_FIELDS = {"signals": "SIG (SPN 1)", "size": 1.0, "percent": 1.0, "rms": 1.0, "unit": "L/h",
                   "x_unit": "1"}
ID_PATTERN = re.compile(r"[a-z][a-z0-9_]*\Z")
# operator -> its parameters (name, kind): "value" a number, "values" a list of numbers, "pair" [lo, hi]
OPERATORS = {"signal": (), "state": (), "deficit": (("below", "value"),), "excess": (("above", "value"),),
             "rate": (), "product": ()}
STATE_CHOICES = (("on", "values"), ("between", "pair"))


@functools.lru_cache(maxsize=1)
def dbc_signals() -> frozenset[str]:
    """Every signal of fuelid/dbc/fms.dbc as MESSAGE.Signal."""
    db = cantools.database.load_file(str(FMS_DBC))
    return frozenset(f"{m.name}.{s.name}" for m in db.messages for s in m.signals)


class _Bad(Exception):
    """A field of one effect is wrong: (field path, message)."""


# ---- the transform tree ----------------------------------------------------------------------------------

def _number(v, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _Bad(where, f"must be a number, not {v!r}")
    return float(v)


def _node(tree, where: str):
    """The transform tree checked: ("signal", name) | (op, child(ren), params)."""
    if isinstance(tree, str):
        if tree not in dbc_signals():
            raise _Bad(where, f"{tree!r} is not a signal of the DBC ({FMS_DBC.name}); write MESSAGE.Signal")
        return ("signal", tree, {})
    if not isinstance(tree, dict):
        raise _Bad(where, f"must be a signal name or a table with one of {', '.join(OPERATORS)}")
    ops = [k for k in tree if k in OPERATORS]
    if len(ops) != 1:
        raise _Bad(where, f"needs exactly one of {', '.join(OPERATORS)}, has {', '.join(tree) or 'none'}")
    op = ops[0]
    allowed = dict(OPERATORS[op]) | (dict(STATE_CHOICES) if op == "state" else {})
    for k in tree:
        if k != op and k not in allowed:
            raise _Bad(f"{where}.{k}", f"unknown parameter of {op} (it takes {', '.join(allowed) or 'none'})")
    params = {}
    for name, kind in OPERATORS[op]:
        if name not in tree:
            raise _Bad(f"{where}.{name}", f"missing ({op} needs it)")
        params[name] = _number(tree[name], f"{where}.{name}")
    if op == "state":
        given = [k for k, _ in STATE_CHOICES if k in tree]
        if len(given) != 1:
            raise _Bad(where, "a state needs exactly one of on = [values] or between = [lo, hi]")
        key, value = given[0], tree[given[0]]
        if not isinstance(value, list) or not value or (key == "between" and len(value) != 2):
            raise _Bad(f"{where}.{key}", "must be a list of numbers" + (" [lo, hi]" if key == "between" else ""))
        params[key] = tuple(_number(v, f"{where}.{key}") for v in value)
    if op == "signal":
        if not isinstance(tree[op], str):
            raise _Bad(f"{where}.signal", f"must be a signal name MESSAGE.Signal, not {tree[op]!r}")
        return _node(tree[op], f"{where}.signal")
    if op == "product":
        items = tree[op]
        if not isinstance(items, list) or len(items) < 2:
            raise _Bad(f"{where}.product", "must be a list of at least two transforms")
        return ("product", [_node(t, f"{where}.product[{k}]") for k, t in enumerate(items)], {})
    return (op, _node(tree[op], f"{where}.{op}"), params)


def _signals(node) -> list[str]:
    op, child, _ = node
    if op == "signal":
        return [child]
    kids = child if op == "product" else [child]
    return [s for k in kids for s in _signals(k)]


def _bus_value(ds, name: str) -> np.ndarray | None:
    """A bus signal on the dataset grid, held across gaps: from ds.extra, or the model's own inputs (engine
    speed [rpm], torque [% of reference torque])."""
    if name in ds.extra:
        x = ds.extra[name]
        return fx.held(x) if np.isfinite(x[ds.valid]).any() else None
    if name == "EEC1.EngSpeed":
        return ds.u[:, 0]
    if name == "EEC1.ActualEngPercentTorque":
        ref = fx.reference_torque(ds)
        return ds.u[:, 1] * 100.0 / ref if ds.input_units[1] == "Nm" and ref else ds.u[:, 1]
    return None


def evaluate(node, ds) -> np.ndarray | None:
    """The transform's values on the dataset grid; None when a signal it needs is not in the data."""
    op, child, p = node
    if op == "signal":
        return _bus_value(ds, child)
    if op == "product":
        parts = [evaluate(k, ds) for k in child]
        return None if any(v is None for v in parts) else functools.reduce(np.multiply, parts)
    x = evaluate(child, ds)
    if x is None:
        return None
    if op == "state":
        on = np.isin(x, p["on"]) if "on" in p else (x >= p["between"][0]) & (x <= p["between"][1])
        return on.astype(float)
    if op == "deficit":
        return np.maximum(p["below"] - x, 0.0)
    if op == "excess":
        return np.maximum(x - p["above"], 0.0)
    return fx.rate(x, ds.t)  # rate


@dataclass(frozen=True)
class _Build:
    """Effect.build for a transform: the columns its way of entering adds (module docstring). A class rather than a
    closure, so that the effect pickles: the diagnosis builds candidates in worker processes (fuelid.parallel)."""

    node: tuple
    label: str
    unit: str
    enters: str

    def __call__(self, ds):
        x = evaluate(self.node, ds)
        if x is None:
            return None
        if self.node[0] == "state" and self.enters == "scales_fuel":
            return fx.regime(ds, x, self.label)
        if self.enters == "scales_fuel":
            return fx.scaling(ds, x, self.label, self.unit)
        return fx.Regressors(x[:, None], (self.label,), (self.unit,))


# ---- one effect ------------------------------------------------------------------------------------------

def _text(table: dict, key: str, required: bool = True) -> str | None:
    v = table.get(key)
    if v is None and not required:
        return None
    if not isinstance(v, str) or not v.strip():
        raise _Bad(key, "missing" if v is None else f"must be a non-empty string, not {v!r}")
    if "\n" in v and key != "physics":
        raise _Bad(key, "must be one line")
    return v.strip()


def effect_from_table(table: dict, source: str = "") -> fx.Effect:
    """The Effect a definition table describes (module docstring); InputError naming the effect and the field."""
    eid = table.get("id") if isinstance(table, dict) else None
    who = f"effect {eid!r}" if isinstance(eid, str) else "effect"
    try:
        if not isinstance(table, dict):
            raise _Bad("effect", "must be a table")
        for k in table:
            if k not in FIELDS:
                raise _Bad(k, f"unknown field (known: {', '.join(sorted(FIELDS))})")
        eid = _text(table, "id")
        if not ID_PATTERN.match(eid):
            raise _Bad("id", f"{eid!r} must be lower-case letters, digits and _ (starting with a letter)")
        if eid in fx.EFFECTS or eid in fx.ALIASES:
            raise _Bad("id", f"{eid!r} is a built-in effect; choose another id")
        name = _text(table, "name")
        enters = _text(table, "enters")
        if enters not in ENTERS:
            raise _Bad("enters", f"{enters!r} is not one of {', '.join(ENTERS)}")
        sign = table.get("sign", 0 if enters != "shift" else 1)
        if sign not in (-1, 0, 1) or isinstance(sign, bool):
            raise _Bad("sign", f"must be +1 (more fuel as x grows), -1 (less) or 0 (either), not {sign!r}")
        orders = table.get("orders", [1, 1, 0])
        if (not isinstance(orders, list) or len(orders) != 3
                or not all(isinstance(o, int) and not isinstance(o, bool) and o >= 0 for o in orders)
                or orders[0] < 1):
            raise _Bad("orders", f"must be [nb ≥ 1, nf ≥ 0, nk ≥ 0] (integers), not {orders!r}")
        physics = _text(table, "physics", required=False) or name
        template = _text(table, "explanation", required=False)
        if template is not None:
            fields = ", ".join("{" + f + "}" for f in TEMPLATE_FIELDS)
            try:
                unknown = {f for _, f, _, _ in string.Formatter().parse(template) if f is not None} \
                    - set(TEMPLATE_FIELDS)
                if unknown:
                    raise _Bad("explanation", f"unknown field {{{sorted(unknown)[0]}}}; fields: {fields}")
                template.format(**TEMPLATE_FIELDS)
            except (ValueError, KeyError, IndexError) as exc:
                raise _Bad("explanation", f"not a valid template ({exc}); fields: {fields}") from None
        if enters == "shift":
            for k in ("x", "unit"):
                if k in table:
                    raise _Bad(k, "a shift (the fuel signal's delay) has no transform and no unit")
            return fx.Effect(eid, name, physics, ("LFE1.EngFuelRate",), (fx.spn_of("LFE1.EngFuelRate"),), "shift",
                             None, orders=(0, 0, 0), lags=(0,), sign=sign, enters="shift", template=template,
                             source=source, definition=dict(table))
        unit = table.get("unit")
        if not isinstance(unit, str):
            raise _Bad("unit", "missing (the unit of x, e.g. \"K\", \"1\" for a state)" if unit is None else
                       f"must be a string, not {unit!r}")
        if "x" not in table:
            raise _Bad("x", "missing (the transform of bus signals)")
        node = _node(table["x"], "x")
    except _Bad as bad:
        where, message = bad.args
        raise InputError(f"{source + ': ' if source else ''}{who}: {where}: {message}") from None
    signals = tuple(dict.fromkeys(_signals(node)))
    spns = tuple(p for p in map(fx.spn_of, signals) if p is not None)
    form = "regime" if node[0] == "state" else "input"
    lags = (0,) if enters in ("scales_fuel", "torque") or form == "regime" else (0, 1, 2)
    return fx.Effect(eid, name, physics, signals, spns, form, _Build(node, name, unit, enters),
                     orders=tuple(orders), lags=lags, sign=sign, enters=enters, template=template, source=source,
                     definition=dict(table))


def read_effects_file(path) -> list[fx.Effect]:
    """The effects of a TOML effect file ([[effect]] tables); InputError in one line naming the file, the
    effect and the field."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not TOML ({exc})") from None
    extra = set(doc) - {"effect"}
    if extra:
        raise InputError(f"{path}: unknown top-level field {sorted(extra)[0]!r} (an effect file holds [[effect]] "
                         "tables)")
    tables = doc.get("effect")
    if not isinstance(tables, list) or not tables:
        raise InputError(f"{path}: no [[effect]] table")
    out = [effect_from_table(t, str(path)) for t in tables]
    seen = set()
    for e in out:
        if e.id in seen:
            raise InputError(f"{path}: effect {e.id!r}: id: defined twice")
        seen.add(e.id)
    return out


def defined_effects(paths=()) -> list[fx.Effect]:
    """The effects of the files `paths` and of installed plug-ins (ident.effects.plugin_effects); an id defined
    twice is an InputError."""
    out = list(fx.plugin_effects())
    for p in paths or ():
        out += read_effects_file(p)
    ids = [e.id for e in out]
    twice = sorted({i for i in ids if ids.count(i) > 1})
    if twice:
        sources = [e.source for e in out if e.id == twice[0]]
        raise InputError(f"effect {twice[0]!r} is defined twice ({', '.join(sources)})")
    return out


def effects_of_model(model) -> list[fx.Effect]:
    """The engineer-defined effects a model carries (model.info["effect_definitions"], as `identify_model`
    stores them)."""
    return [effect_from_table(t, f"model effect {eid}")
            for eid, t in (model.info.get("effect_definitions") or {}).items()]
