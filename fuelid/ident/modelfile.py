"""model.json: the versioned, human-readable file of an identified PolyModel (docs: ARCHITECTURE.md).

    {"format": "fuelid-model", "version": 3,
     "structure": {"kind": "bj", "na": 0, "nc": 11, "nd": 11},
     "Ts_s": 0.3,
     "inputs": [{"name", "unit", "u0", "nb", "nf", "nk", "B": [...], "F": [...]}, ...],
     "output": {"name", "unit", "y0"},
     "A": [1.0], "C": [...], "D": [...],                 polynomials in q⁻¹, leading coefficient first
     "effects": [...], "parameters": {"names": [...], "std_errors": [...] | null, "covariance": [[...]] | null},
     "training": {...}, "validation": {...}, "info": {...}}

B arrays carry the nk leading zeros. Floats are written with Python's shortest round-trip repr, so
load_model(save_model(m)) gives back every coefficient bit for bit.

An engine model (ident.hammerstein) lists the effect "engine_map" first in "effects"; its map travels in
info.effect_parameters.engine_map (ident.enginemap.EngineMap.to_dict: knots, coefficients, plane, coverage counts,
units), from which ident.modeldata.model_data rebuilds its input columns on any dataset. info.model_choice records
which model `fuelid identify` kept and why (ident.modelchoice.ModelChoice.to_json), info.joint the loss V over the
joint identification's rounds.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from fuelid.errors import FuelidError
from fuelid.ident.polymodel import PolyModel, parameter_names
from fuelid.output import json_safe

FORMAT = "fuelid-model"
VERSION = 3  # 2: on an engine model an effect that scales the fuel has the column x·m; 3: a torque, x·∂m/∂T
PAPER_MODELS = Path(__file__).resolve().parents[3] / "shared" / "design" / "paper_models.json"


def _plain(x):
    """JSON-ready copy: numpy arrays and scalars to lists and Python numbers."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_plain(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x


def to_dict(model: PolyModel) -> dict:
    """The model.json content of `model`: its figures that could not be computed (NaN or inf: a cycle fuel error
    without a complete drive cycle, say) as null, as every `--json` prints them."""
    s = model.structure
    cov = model.covariance
    return _plain({
        "format": FORMAT,
        "version": VERSION,
        "structure": {"kind": s.kind, "na": s.na, "nc": s.nc, "nd": s.nd},
        "Ts_s": model.Ts,
        "inputs": [{"name": name, "unit": unit, "u0": u0, "nb": nb, "nf": nf, "nk": nk, "B": B, "F": F}
                   for name, unit, u0, nb, nf, nk, B, F in zip(model.input_names, model.input_units, model.u0,
                                                               s.nb, s.nf, s.nk, model.B, model.F)],
        "output": {"name": model.output_name, "unit": model.output_unit, "y0": model.y0},
        "A": model.A, "C": model.C, "D": model.D,
        "effects": list(model.effects),
        "parameters": {"names": parameter_names(s),
                       "std_errors": None if cov is None else model.std_errors,
                       "covariance": cov},
        "training": json_safe(model.training),
        "validation": json_safe(model.validation),
        "info": json_safe(model.info),
    })


def _is_torque(effect: str, definitions: dict | None = None) -> bool:
    """Whether the effect "ID" or "ID=VALUE" enters as a torque the bus does not report (a generic torque: form, a
    built-in or plug-in effect, or one the engineer defined, its table among `definitions`)."""
    from fuelid.ident import effects as fx  # SciPy and cantools: only for an older file's engine model

    eid = fx.parse_effect(effect)[0]
    if eid in (definitions or {}):
        return definitions[eid].get("enters") == "torque"
    known = {**{e.id: e for e in fx.plugin_effects()}, **fx.EFFECTS}
    return eid.startswith("torque:") or (eid in known and known[eid].enters == "torque")


def from_dict(d: dict) -> PolyModel:
    """The PolyModel of a model.json content; FuelidError when it is not one."""
    try:
        if d.get("format") != FORMAT:
            raise ValueError(f"not a {FORMAT} file")
        if d.get("version") not in (1, 2, VERSION):
            raise ValueError(f"unsupported version {d.get('version')!r} (this fuelid reads 1 to {VERSION})")
        if d["version"] == 1 and "engine_map" in d.get("effects", []) and len(d["effects"]) > 1:
            raise ValueError("version 1: an engine model with effects, written by an older fuelid whose effects "
                             "that scale the fuel had one input column fewer; identify it again")
        effects, definitions = d.get("effects", []), (d.get("info") or {}).get("effect_definitions")
        if d["version"] == 2 and "engine_map" in effects and any(_is_torque(e, definitions) for e in effects):
            raise ValueError("version 2: an engine model with a torque the bus does not report, written by an older "
                             "fuelid that gave it one input column fewer; identify it again")
        inputs = d["inputs"]
        cov = d["parameters"]["covariance"]
        model = PolyModel(
            A=d["A"], B=[i["B"] for i in inputs], F=[i["F"] for i in inputs], C=d["C"], D=d["D"],
            Ts=float(d["Ts_s"]), nk=[i["nk"] for i in inputs],
            input_names=[i["name"] for i in inputs], input_units=[i["unit"] for i in inputs],
            output_name=d["output"]["name"], output_unit=d["output"]["unit"],
            u0=[i["u0"] for i in inputs], y0=d["output"]["y0"],
            covariance=None if cov is None else np.array(cov, float),
            info=d.get("info", {}), effects=d.get("effects", []),
            training=d.get("training", {}), validation=d.get("validation", {}),
        )
        s = model.structure
        if [(i["nb"], i["nf"]) for i in inputs] != list(zip(s.nb, s.nf)):
            raise ValueError("orders nb/nf disagree with the polynomial lengths")
        if cov is not None and model.covariance.shape != (s.n_params, s.n_params):
            raise ValueError(f"covariance is not {s.n_params} × {s.n_params}")
        return model
    except FuelidError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        detail = f"missing field {exc}" if isinstance(exc, KeyError) else str(exc)
        raise FuelidError(f"malformed model: {detail}") from None


def save_model(model: PolyModel, path) -> None:
    """Write model.json atomically (a temporary file renamed over `path`); into `path` itself when it exists and
    is not a regular file (`-o /dev/null`, a pipe): renaming over a device would replace it."""
    text = json.dumps(to_dict(model), indent=1, allow_nan=False) + "\n"
    path = Path(path)
    if path.exists() and not path.is_file():
        path.write_text(text, encoding="utf-8")
        return
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def load_model(path) -> PolyModel:
    """Read a model.json; FuelidError with one line when it is missing, unreadable or malformed."""
    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise FuelidError(f"cannot read model {path}: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FuelidError(f"model {path} is not valid JSON: {exc}") from None
    if not isinstance(d, dict):
        raise FuelidError(f"model {path}: malformed model: not a JSON object")
    try:
        return from_dict(d)
    except FuelidError as exc:
        raise FuelidError(f"model {path}: {exc}") from None


def load_paper_model(name: str, path=None) -> PolyModel:
    """An appendix model of the seed paper from paper_models.json ('diesel_scania_p320', 'gas_scania_p340').

    path defaults to shared/design/paper_models.json beside the repository. Inputs engine speed [rpm] and
    torque [%] as deviations from idle (the paper does not print its idle values, so u0 = 0, y0 = 0); output
    fuel flow in L/h (diesel) or kg/h (gas), as the file's note explains.
    """
    path = Path(path) if path is not None else PAPER_MODELS
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        m = doc[name]
        Gw, GT, H = m["Gw"], m["GT"], m["H"]
        return PolyModel(
            A=[1.0], B=[Gw["B"], GT["B"]], F=[Gw["F"], GT["F"]], C=H["C"], D=H["D"], Ts=float(doc["ts_s"]),
            nk=[Gw["nk"], GT["nk"]], input_names=("engine_speed", "engine_torque"), input_units=("rpm", "%"),
            output_name="fuel_flow", output_unit="L/h" if "diesel" in name else "kg/h",
            info={"source": doc.get("source", str(path)), "reported": m.get("reported", {})},
        )
    except OSError as exc:
        raise FuelidError(f"cannot read paper models {path}: {exc.strerror or exc}") from None
    except KeyError as exc:
        raise FuelidError(f"paper models {path}: no {exc} (have: {', '.join(k for k in doc if isinstance(doc[k], dict))})") from None
    except (ValueError, TypeError) as exc:
        raise FuelidError(f"paper models {path}: malformed: {exc}") from None
