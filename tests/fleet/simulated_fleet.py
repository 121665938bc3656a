"""A fleet of simulated trucks written straight into a server's registry: model versions whose coefficients
drift by a known amount (no identification run), for the console's API, browser test and benchmark.

Each truck's engine maps speed [rpm] and torque [N·m] about idle (600 rpm, 0 N·m, y0 = 2 L/h) to fuel [L/h]
through a Box-Jenkins model; the truck's efficiency factor scales every B_i, so its steady-state fuel above idle
grows by exactly that factor. Version v of a drifting truck has the factor 1 + drift · (v − 1)/(versions − 1).
"""
from __future__ import annotations

import hashlib
import json
import time

import numpy as np
import sqlalchemy as sa

from fuelid.fleet import db
from fuelid.fleet.storage import BlobStore
from fuelid.ident.enginemap import fit_map
from fuelid.ident.hammerstein import MAP_COLUMN, RISE_COLUMN, RISE_MAP_COLUMN
from fuelid.ident.modelfile import to_dict
from fuelid.ident.polymodel import PolyModel


def engine_model(factor: float = 1.0, effects=()) -> PolyModel:
    """The fleet's engine with its B scaled by `factor`; covariance giving σ_S ≈ 0.1 % of the steady fuel."""
    m = PolyModel(A=[1.0], B=[[0, factor * 0.004, factor * 0.002], [factor * 0.012, factor * 0.006]],
                  F=[[1, -0.5], [1, -0.3]], C=[1, 0.2], D=[1, -0.7], Ts=0.3, nk=(1, 0),
                  input_names=("EEC1.EngSpeed", "EngTorque"), input_units=("rpm", "Nm"),
                  output_name="LFE1.EngFuelRate", output_unit="L/h", u0=(600.0, 0.0), y0=2.0,
                  effects=tuple(effects), info={"noise_variance": 0.04})
    n = m.structure.n_params
    m.covariance = 1e-10 * np.eye(n)
    return m


def _fitted_map() -> dict:
    """An engine map (ident.enginemap) of a curved fuel surface [L/h] over 600–1900 rpm × 0–2400 N·m about idle:
    the model's plane plus 0.5 ñT̃ + 0.3 ñ² + 0.8 T̃² (ñ, T̃ in krpm and kNm)."""
    rng = np.random.default_rng(7)
    n, T = rng.uniform(600, 1900, 4000), rng.uniform(0, 2400, 4000)
    dn, dT = (n - 600.0) / 1000.0, T / 1000.0
    fuel = 2.0 + 6.0 * dn + 18.0 * dT + 0.5 * dn * dT + 0.3 * dn ** 2 + 0.8 * dT ** 2
    return fit_map(n, T, fuel, (600.0, 0.0), 2.0, ("rpm", "Nm", "L/h")).to_dict()


MAP = _fitted_map()


def mapped_model(factor: float = 1.0) -> PolyModel:
    """engine_model with the engine map: its three engine_map columns (the map beyond its plane, of static gain
    `factor`, and the torque rise's two, which are zero at rest) and the fitted map the model carries."""
    base = engine_model(factor)
    gains = [1.0, 0.0, 0.0]
    m = PolyModel(A=base.A, B=base.B + [[factor * g] for g in gains], F=base.F + [[1.0]] * 3, C=base.C, D=base.D,
                  Ts=base.Ts, nk=base.nk + (0,) * 3, input_names=base.input_names + (MAP_COLUMN, RISE_COLUMN, RISE_MAP_COLUMN),
                  input_units=base.input_units + ("L/h", "kNm/s", "kNm/s"), output_name=base.output_name,
                  output_unit=base.output_unit, u0=base.u0 + (0.0,) * 3, y0=base.y0, effects=("engine_map",),
                  info={**base.info, "effect_parameters": {"engine_map": MAP}})
    m.covariance = 1e-10 * np.eye(m.structure.n_params)
    return m


def store_version(store: BlobStore, truck: str, model: PolyModel, top_effect=None, recommended=()) -> dict:
    """model.json, a diagnosis (its candidates: `recommended` with recommended true) and a small report (an inline script writes the truck's name into it) in the blob
    store: the sha256 columns of a models row."""
    sha = {}
    for name, text in [("model", json.dumps(to_dict(model))),
                       ("diagnosis", json.dumps({"truck": truck, "top_effect": top_effect, "candidates": [
                           {"id": e, "effect": e, "recommended": True} for e in recommended]})),
                       ("report", "<!doctype html><html><head><title>report</title></head><body><h1 id='t'></h1>"
                                  f"<script>document.getElementById('t').textContent = {json.dumps(truck)} + "
                                  "' fuel model report';</script></body></html>")]:
        tmp = store.incoming / f"{name}-{truck}.tmp"
        tmp.write_text(text, encoding="utf-8")
        sha[name] = store.put_file(tmp)
        tmp.unlink()
    return {"model_sha256": sha["model"], "diagnosis_sha256": sha["diagnosis"], "report_sha256": sha["report"]}


METRICS = {"fit_percent": {"simulation": 92.0, "prediction": 99.0}, "rmse": {"simulation": 0.8, "prediction": 0.2},
           "cycle_fuel_error_percent": {"mean": 0.3, "rms": 1.1}, "unit": "L/h"}


def add_truck(engine: sa.Engine, truck: str, hours: float = 10.0, files: int = 2) -> None:
    """The truck and `files` files of `hours` recorded time in all (rows only: the console reads no MCAP)."""
    t0 = 1_700_000_000 * 10**9
    with engine.begin() as conn:
        db.insert_ignore(conn, db.trucks, truck=truck, created_unix_s=time.time())
        for k in range(files):
            start = t0 + int(k * hours / files * 3.6e12)
            db.insert_ignore(conn, db.files, sha256=hashlib.sha256(f"{truck}-{k}".encode()).hexdigest(), truck=truck,
                             size_bytes=1_000_000, start_ns=start, end_ns=start + int(hours / files * 3.6e12),
                             messages=100_000, uploaded_unix_s=time.time())


def simulated_fleet(engine: sa.Engine, store: BlobStore, trucks: int = 6, versions: int = 3,
                    drifting: dict[str, float] | None = None, new_effect: str | None = None,
                    distinct_middle: bool = True, mapped: str | None = None) -> list[str]:
    """`trucks` trucks FLEET-000… (plus the names in `drifting`: truck → final relative drift, e.g. 0.08), each
    with `versions` model versions a day apart; trucks not drifting stay within ±0.2 %. `new_effect` names a
    truck whose latest diagnosis names fan_on for the first time (and recommends it). `mapped` names a truck whose
    models carry the engine map (`mapped_model`) and whose latest diagnosis recommends engine_map and names it
    first, for the first time, as the diagnosis names the engine's own map: a property of the engine, not an effect. distinct_middle False gives the versions
    between the first and the latest the first one's files (the fleet view reads only those two; a benchmark's
    setup then writes far fewer files). Returns the truck names."""
    rng = np.random.default_rng(7)
    drifting = drifting or {}
    names = [f"FLEET-{i:03d}" for i in range(trucks)] + list(drifting) + ([mapped] if mapped else [])
    now = time.time()
    for name in names:
        add_truck(engine, name)
        base = 1.0 + 0.03 * rng.standard_normal()  # trucks differ; each compares with its own first model
        rows = []
        for v in range(versions):
            change = drifting.get(name, 0.002 * rng.standard_normal()) * (v / max(versions - 1, 1))
            effect = "fan_on" if name == new_effect and v == versions - 1 else "engine_map" if name == mapped and v == versions - 1 else None
            if distinct_middle or v in (0, versions - 1):
                model = (mapped_model if name == mapped else engine_model)(base * (1.0 + change))
                files = store_version(store, name, model, effect, [effect] if effect else [])
            rows.append({"truck": name, "version": v + 1, "job_id": None,
                         "created_unix_s": now - 86400.0 * (versions - 1 - v), **files, "metrics": METRICS,
                         "n_samples": 12000, "duration_s": 3600.0, "top_effect": effect})
        with engine.begin() as conn:
            conn.execute(db.models.insert(), rows)
    return names
