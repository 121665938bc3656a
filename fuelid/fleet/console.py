"""The fleet engineer's console: the API behind the page (fleet summary with drift, truck history, alerts,
report links) and the page itself (static files in fuelid/fleet/static, served at `/`).

Drift (fleet.drift) needs each model version's model.json; they are content-addressed, so each is parsed once
and kept by its sha256 (a model file never changes under its hash). The page's files carry a content security
policy allowing scripts, styles and requests from the server's own origin only, no inline script. A report
(plotly inline, written by ident.report) is opened through a short-lived link (`POST .../report-link`), never
with the token in a URL, and served sandboxed (an opaque origin: its scripts cannot read the console's storage).
"""
from __future__ import annotations

import json
import math
import secrets
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Callable

import sqlalchemy as sa
from fastapi import APIRouter, Depends, FastAPI, HTTPException, Path as PathParam, Query
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field
from pydantic_core import to_json

from fuelid.fleet import auth, db
from fuelid.fleet.effectlist import ENGINE_PROPERTIES, in_model, missing
from fuelid.fleet.drift import DEFAULT_POINTS, Drift, ReferencePoint, SteadyFuel, drift, fleet_median, \
    parse_points, steady_fuel, versus_median
from fuelid.fleet.storage import BlobStore
from fuelid.errors import FuelidError
from fuelid.ident.modelfile import load_model
from fuelid.ident.polymodel import PolyModel

STATIC = Path(__file__).with_name("static")
CONSOLE_CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; connect-src 'self'; "
               "base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
# The report inlines plotly.js and its data: inline scripts, no network, and a sandbox with an opaque origin.
REPORT_CSP = ("default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; "
              "img-src data: blob:; font-src data:; base-uri 'none'; form-action 'none'; "
              "sandbox allow-scripts allow-downloads allow-popups")
REPORT_LINK_S = 120.0
MAX_VIEWS = 8  # choices of reference points and threshold whose fleet view is kept


@dataclass(frozen=True)
class ConsoleSettings:
    """The fleet-wide default reference points and the drift threshold [%] (fleet.drift)."""

    points: tuple[ReferencePoint, ...] = DEFAULT_POINTS
    threshold_percent: float = 5.0


# --- response models ---

class DriftInfo(BaseModel):
    steady_fuel: float | None = Field(None, description="mean steady-state fuel over the reference points [unit]")
    steady_fuel_std: float | None = Field(None, description="its standard error from the covariance [unit]")
    per_point: list[float] | None = Field(None, description="steady-state fuel at each reference point [unit]")
    drift_percent: float | None = Field(None, description="100 (S / S of the first version − 1) [%]")
    drift_std_percent: float | None = Field(None, description="standard error of drift_percent [%]")
    drift_alert: bool = False
    note: str | None = Field(None, description="why steady fuel or drift is missing")
    steady_reference: dict[str, str] | None = Field(
        None, description="the reference condition of the steady state: bus signal -> what it was held at "
                          "(speed and torque are the points')")


class Alert(BaseModel):
    truck: str
    kind: str = Field(description="drift | new effect")
    version: int
    message: str
    drift_percent: float | None = None
    drift_std_percent: float | None = None


class TruckSummary(DriftInfo):
    truck: str
    files: int
    data_hours: float = Field(description="recorded time of the truck's files [h]")
    last_upload_unix_s: float | None
    start_ns: int | None
    end_ns: int | None
    versions: int
    latest_version: int | None
    latest_created_unix_s: float | None
    fit_percent: float | None = Field(description="latest version's simulation fit [%]")
    cycle_fuel_error_percent: float | None = Field(description="latest version's RMS cycle fuel error [%]")
    unit: str | None = Field(description="fuel unit of the model (L/h or kg/h)")
    top_effect: str | None = Field(description="the hidden effect the latest diagnosis recommended first (never "
                                               "the engine's own map)")
    effects: list[str] = Field(description="effects the latest model includes (\"in the model\")")
    missing_effects: list[str] = Field(description="hidden effects the latest diagnosis recommends that the model "
                                                   "lacks (\"missing\"); the engine's map is never one")
    vs_fleet_percent: float | None = Field(description="100 (S / fleet median S − 1) [%]")
    alerts: list[Alert]


class FleetSummary(BaseModel):
    points: list[str] = Field(description="reference points used, RPMxTORQUE<Nm|%>")
    threshold_percent: float
    fleet_median_steady_fuel: float | None
    trucks: list[TruckSummary]


class VersionInfo(DriftInfo):
    version: int
    created_unix_s: float
    job_id: int | None
    fit_percent: float | None
    rmse: float | None
    cycle_fuel_error_percent: float | None
    unit: str | None
    top_effect: str | None
    effects: list[str]
    missing_effects: list[str]
    duration_s: float | None
    has_report: bool


class FileSpan(BaseModel):
    sha256: str
    size_bytes: int
    start_ns: int | None
    end_ns: int | None
    messages: int
    uploaded_unix_s: float


class JobBrief(BaseModel):
    id: int
    reason: str
    status: str
    created_unix_s: float
    finished_unix_s: float | None
    error: str | None
    model_version: int | None


class TruckHistory(BaseModel):
    truck: str
    points: list[str]
    threshold_percent: float
    versions: list[VersionInfo]
    files: list[FileSpan]
    jobs: list[JobBrief]


class ReportLink(BaseModel):
    url: str = Field(description="same-origin path of the report, valid without a token until expires_unix_s")
    expires_unix_s: float


# --- drift of stored model versions ---

class ModelCache:
    """Parsed model.json files and their steady fuel at given points, by sha256 (content-addressed: never
    stale). Bounded: each table is emptied when full, so a long-running server's memory stays flat."""

    def __init__(self, store: BlobStore, max_models: int = 4096, max_steady: int = 65536):
        self.store, self.max_models, self.max_steady = store, max_models, max_steady
        self._models: dict[str, PolyModel | str] = {}
        self._steady: dict[tuple, dict[str, SteadyFuel | str]] = {}  # points -> sha256 -> steady fuel
        self._candidates: dict[str, list[dict]] = {}  # diagnosis sha256 -> its candidates

    def model(self, sha256: str) -> PolyModel | str:
        """The model, or why it cannot be read (one line)."""
        if sha256 not in self._models:
            if len(self._models) >= self.max_models:
                self._models.clear()
            try:
                self._models[sha256] = load_model(self.store.path(sha256))
            except FuelidError as exc:
                self._models[sha256] = str(exc).split(": ", 1)[-1]
        return self._models[sha256]

    def steady_at(self, points: tuple[ReferencePoint, ...]) -> Callable[[str], SteadyFuel | str]:
        """A function of a model's sha256 giving fleet.drift.steady_fuel at `points`, or why there is none."""
        if points not in self._steady and len(self._steady) >= 16:
            self._steady.clear()
        table = self._steady.setdefault(points, {})

        def steady(sha256: str) -> SteadyFuel | str:
            if sha256 not in table:
                if len(table) >= self.max_steady:
                    table.clear()
                model = self.model(sha256)
                try:
                    table[sha256] = model if isinstance(model, str) else steady_fuel(model, points)
                except ValueError as exc:
                    table[sha256] = str(exc)
            return table[sha256]

        return steady

    def effects(self, sha256: str) -> list[str]:
        """The ids of the effects the model includes, each once."""
        model = self.model(sha256)
        return [] if isinstance(model, str) else in_model(model.effects)

    def missing(self, model_sha256: str, diagnosis_sha256: str | None) -> list[str]:
        """The hidden effects the diagnosis recommends that the model lacks (fleet.effectlist.missing); none
        when the diagnosis cannot be read."""
        if diagnosis_sha256 is None:
            return []
        if diagnosis_sha256 not in self._candidates:
            if len(self._candidates) >= self.max_models:
                self._candidates.clear()
            try:
                doc = json.loads(self.store.path(diagnosis_sha256).read_text(encoding="utf-8"))
                found = doc.get("candidates") if isinstance(doc, dict) else None
            except (OSError, UnicodeDecodeError, json.JSONDecodeError):  # a missing or damaged diagnosis names nothing
                found = None
            self._candidates[diagnosis_sha256] = [c for c in found or [] if isinstance(c, dict)]
        return missing(self._candidates[diagnosis_sha256], self.effects(model_sha256))


def _drift_fields(current: SteadyFuel | str, first: SteadyFuel | str | None, threshold: float) -> dict:
    if isinstance(current, str):
        return {"note": current}
    out = {"steady_fuel": current.mean, "steady_fuel_std": current.std_error, "per_point": list(current.per_point),
           "steady_reference": current.reference}
    if first is None or isinstance(first, str):
        return {**out, "note": None if first is None else f"first version: {first}"}
    try:
        d: Drift = drift(current, first, threshold)
    except ValueError as exc:
        return {**out, "note": str(exc)}
    return {**out, "drift_percent": d.percent, "drift_std_percent": d.std_error_percent, "drift_alert": d.alert}


def _number(x) -> float | None:
    return float(x) if isinstance(x, (int, float)) and math.isfinite(x) else None


def _metrics(m: dict) -> dict:
    """fit [%], RMSE [unit], RMS cycle fuel error [%] and unit of a version's metrics (jobs.identify_truck)."""
    def pick(v, key):
        return _number(v.get(key)) if isinstance(v, dict) else _number(v)

    return {"fit_percent": pick(m.get("fit_percent"), "simulation"), "rmse": pick(m.get("rmse"), "simulation"),
            "cycle_fuel_error_percent": pick(m.get("cycle_fuel_error_percent"), "rms"),
            "unit": m.get("unit") if isinstance(m.get("unit"), str) else None}


def _alerts(truck: str, latest: dict, fields: dict, new_effect: bool) -> list[Alert]:
    alerts = []
    if fields.get("drift_alert"):
        sd = fields["drift_std_percent"]
        alerts.append(Alert(truck=truck, kind="drift", version=latest["version"],
                            drift_percent=fields["drift_percent"], drift_std_percent=sd,
                            message=f"steady-state fuel {fields['drift_percent']:+.1f} %"
                                    + (f" ± {sd:.1f} %" if sd is not None else " (uncertainty unknown)")
                                    + " since the first model"))
    if new_effect and latest["top_effect"] not in ENGINE_PROPERTIES:
        alerts.append(Alert(truck=truck, kind="new effect", version=latest["version"],
                            message=f"the diagnosis names a new effect: {latest['top_effect']}"))
    return alerts


def _fleet_query(named_trucks: bool = False) -> sa.Select:
    """One row per truck: everything its fleet row is computed from. Its files' count, recorded time,
    last upload and time range; its number of versions; the latest version's id, number, creation time, model,
    named effect and metrics (as JSON text: compared as is, parsed only for a row computed again); the first
    version's model; and whether an earlier version named the latest one's effect. With `named_trucks`, only
    the trucks in the list parameter `trucks` (and only their files and versions are read)."""
    f, m = db.files, db.models
    trucks = sa.bindparam("trucks", expanding=True)

    def only(q: sa.Select, column) -> sa.Select:
        return q.where(column.in_(trucks)) if named_trucks else q

    files = only(sa.select(f.c.truck, sa.func.count().label("files"),
                           sa.func.coalesce(sa.func.sum(f.c.end_ns - f.c.start_ns), 0).label("recorded_ns"),
                           sa.func.max(f.c.uploaded_unix_s).label("last_upload"),
                           sa.func.min(f.c.start_ns).label("start_ns"), sa.func.max(f.c.end_ns).label("end_ns")),
                 f.c.truck).group_by(f.c.truck).subquery()
    span = only(sa.select(m.c.truck, sa.func.min(m.c.version).label("first"),
                          sa.func.max(m.c.version).label("latest"), sa.func.count().label("versions")),
                m.c.truck).group_by(m.c.truck).subquery()
    latest, first, earlier = m.alias("latest"), m.alias("first"), m.alias("earlier")
    # looked for only when the latest version names an effect (most do not: a search per truck saved)
    named_before = sa.case((latest.c.top_effect.is_(None), sa.false()), else_=sa.exists().where(
        earlier.c.truck == latest.c.truck, earlier.c.top_effect == latest.c.top_effect,
        earlier.c.version < latest.c.version))
    t = db.trucks.c.truck
    columns = (t, files.c.files, files.c.recorded_ns, files.c.last_upload, files.c.start_ns, files.c.end_ns,
               span.c.versions, latest.c.id.label("latest_id"), latest.c.version.label("latest_version"),
               latest.c.created_unix_s.label("latest_created_unix_s"), latest.c.model_sha256.label("latest_sha256"),
               latest.c.diagnosis_sha256.label("latest_diagnosis_sha256"),
               latest.c.top_effect, sa.cast(latest.c.metrics, sa.Text).label("metrics"),
               first.c.model_sha256.label("first_sha256"), named_before.label("named_before"))
    joined = (db.trucks.outerjoin(files, files.c.truck == t).outerjoin(span, span.c.truck == t)
              .outerjoin(latest, (latest.c.truck == t) & (latest.c.version == span.c.latest))
              .outerjoin(first, (first.c.truck == t) & (first.c.version == span.c.first)))
    return only(sa.select(*columns).select_from(joined), t)


FLEET_QUERY, FLEET_QUERY_OF = _fleet_query(), _fleet_query(named_trucks=True)
MAX_NAMED = 500  # more changed trucks than this: all are read (bounded IN lists)
# Whether the registry changed since a view was computed (rows are inserted or deleted, never updated): counts
# and newest of trucks (created), files (uploaded) and model versions (id).
FINGERPRINT = sa.select(*(sa.select(agg).scalar_subquery() for agg in (
    sa.func.count(db.trucks.c.truck), sa.func.max(db.trucks.c.created_unix_s), sa.func.count(db.files.c.sha256),
    sa.func.max(db.files.c.uploaded_unix_s), sa.func.count(db.models.c.id), sa.func.max(db.models.c.id))))
# the trucks of rows newer than a fingerprint's: trucks created, files uploaded, versions added
NEW_ROWS = (sa.select(db.trucks.c.truck).where(db.trucks.c.created_unix_s > sa.bindparam("after")),
            sa.select(db.files.c.truck).where(db.files.c.uploaded_unix_s > sa.bindparam("after")),
            sa.select(db.models.c.truck).where(db.models.c.id > sa.bindparam("after")))


def trucks_added_to(conn, before: tuple, now: tuple) -> set[str] | None:
    """The trucks that are new or were given files or model versions since the registry's FINGERPRINT was
    `before`, when those new rows account for every change of the counts up to `now`; None when they do not
    — a truck, file or version deleted, a row committed after one with a newer time or id — and every truck
    must be read."""
    trucks: set[str] = set()
    for query, count0, newest0, count1 in zip(NEW_ROWS, before[::2], before[1::2], now[::2]):
        names = conn.execute(query, {"after": newest0 or 0}).scalars().all()
        if count1 != count0 + len(names):
            return None
        trucks.update(names)
    return trucks


def truck_summary(r, cache: ModelCache, points, threshold: float) -> TruckSummary:
    """The fleet row of one truck from its row `r` of FLEET_QUERY (a mapping): files, data hours, last upload,
    latest version with metrics, effects, drift and alerts; vs_fleet_percent is left to the fleet median."""
    hours = float(r["recorded_ns"] or 0) / 3.6e12  # float: PostgreSQL sums bigints as numeric (Decimal)
    row = {"truck": r["truck"], "files": r["files"] or 0, "data_hours": hours, "last_upload_unix_s": r["last_upload"],
           "start_ns": r["start_ns"], "end_ns": r["end_ns"], "versions": r["versions"] or 0, "latest_version": None,
           "latest_created_unix_s": None, "fit_percent": None, "cycle_fuel_error_percent": None, "unit": None,
           "top_effect": None, "effects": [], "missing_effects": [], "vs_fleet_percent": None, "alerts": [], "note": "no model yet"}
    if r["latest_id"] is not None:
        steady = cache.steady_at(points)
        current = steady(r["latest_sha256"])
        reference = steady(r["first_sha256"]) if r["versions"] > 1 else None
        fields = _drift_fields(current, reference, threshold)
        latest = {"version": r["latest_version"], "top_effect": r["top_effect"]}
        new = r["top_effect"] is not None and not r["named_before"]
        metrics = _metrics(json.loads(r["metrics"] or "{}"))
        row.update(fields, latest_version=r["latest_version"], latest_created_unix_s=r["latest_created_unix_s"],
                   fit_percent=metrics["fit_percent"], cycle_fuel_error_percent=metrics["cycle_fuel_error_percent"],
                   unit=metrics["unit"] or (current.unit if isinstance(current, SteadyFuel) else None),
                   top_effect=r["top_effect"], effects=cache.effects(r["latest_sha256"]),
                   missing_effects=cache.missing(r["latest_sha256"], r["latest_diagnosis_sha256"]),
                   alerts=_alerts(r["truck"], latest, fields, new))
    return TruckSummary.model_validate(row)


@dataclass(frozen=True)
class KeptRow:
    """A truck's row of a fleet view: the FLEET_QUERY row it was computed from, its steady fuel S [unit] (for
    the fleet median), its alerts, and its TruckSummary as JSON without vs_fleet_percent (which moves with the
    median, so it is written into each response)."""

    inputs: tuple
    steady_fuel: float | None
    alerts: list[Alert]
    json: bytes

    @classmethod
    def of(cls, inputs: tuple, summary: TruckSummary) -> "KeptRow":
        return cls(inputs, summary.steady_fuel, summary.alerts,
                   summary.model_dump_json(exclude={"vs_fleet_percent"}).encode())


class FleetView:
    """The fleet summary at one choice of reference points and threshold, brought up to date by what changed:
    each truck's row is kept with the FLEET_QUERY row it was computed from (its inputs) and computed again only
    when those differ — a new, deleted or replaced version, new files, another first model. When the registry
    only gained trucks, files or versions, only their trucks are read (trucks_added_to), so a new model version costs
    one truck's read and row, the fleet median, and the response joined from the rows' JSON. A truck gone
    from the registry is gone from the view: memory is one KeptRow per truck and the last response."""

    def __init__(self, points: tuple[ReferencePoint, ...], threshold: float):
        self.points, self.threshold = points, threshold
        self.fingerprint: tuple | None = None
        self.rows: dict[str, KeptRow] = {}
        self.body = b""  # the FleetSummary as JSON, served as is
        self.alerts: list[Alert] = []

    def refresh(self, conn, cache: ModelCache, fingerprint: tuple) -> None:
        """Bring the view up to the registry whose FINGERPRINT is `fingerprint`."""
        added = None if self.fingerprint is None else trucks_added_to(conn, self.fingerprint, fingerprint)
        if added is None or len(added) > MAX_NAMED:
            result, rows = conn.execute(FLEET_QUERY), {}
        else:  # the other trucks' rows stand as they are
            result, rows = conn.execute(FLEET_QUERY_OF, {"trucks": sorted(added)}), dict(self.rows)
        for r in result:
            inputs, kept = tuple(r), self.rows.get(r.truck)
            rows[r.truck] = kept if kept is not None and kept.inputs == inputs else KeptRow.of(
                inputs, truck_summary(r._mapping, cache, self.points, self.threshold))
        rows = dict(sorted(rows.items()))  # by name, in Python: the same order on every database
        median = fleet_median([k.steady_fuel for k in rows.values() if k.steady_fuel is not None])
        head = FleetSummary.model_construct(points=[str(p) for p in self.points], threshold_percent=self.threshold,
                                            fleet_median_steady_fuel=median, trucks=[]).model_dump_json().encode()
        assert head.endswith(b'"trucks":[]}')
        trucks = b",".join(b'{"vs_fleet_percent":' + to_json(
            None if k.steady_fuel is None else versus_median(k.steady_fuel, median)) + b"," + k.json[1:]
            for k in rows.values())
        self.body = head[:-2] + trucks + b"]}"
        self.rows, self.alerts, self.fingerprint = rows, [a for k in rows.values() for a in k.alerts], fingerprint


def truck_history(engine: sa.Engine, cache: ModelCache, truck: str, points, threshold: float) -> dict:
    rows = db.list_models(engine, truck)
    steady = cache.steady_at(points)
    first = steady(rows[0]["model_sha256"]) if rows else None
    versions = []
    for i, r in enumerate(rows):
        current = first if i == 0 else steady(r["model_sha256"])
        fields = _drift_fields(current, None if i == 0 else first, threshold)
        versions.append({**fields, **_metrics(r["metrics"] or {}), "version": r["version"],
                         "created_unix_s": r["created_unix_s"], "job_id": r["job_id"], "top_effect": r["top_effect"],
                         "effects": cache.effects(r["model_sha256"]),
                         "missing_effects": cache.missing(r["model_sha256"], r["diagnosis_sha256"]), "duration_s": r["duration_s"],
                         "has_report": r["report_sha256"] is not None})
    return {"truck": truck, "points": [str(p) for p in points], "threshold_percent": threshold, "versions": versions,
            "files": db.list_files(engine, truck), "jobs": db.list_jobs(engine, truck=truck, limit=20)}


# --- the router and the page ---

Points = Annotated[str | None, Query(max_length=400, description="reference points RPMxTORQUE<Nm|%>, comma "
                                                                   "separated (default: the server's)")]
Threshold = Annotated[float | None, Query(gt=0, le=1000, description="drift alert threshold [%] (default: the "
                                                                      "server's)")]


def router(engine: sa.Engine, store: BlobStore, settings: ConsoleSettings, reader: Callable,
           errors: dict) -> APIRouter:
    """The console's API under /api/v1 (engineer or admin tokens: `reader`) and the report links; `errors` the
    app's documented error replies (400, 401, 403, 422 with their one-line body model)."""
    api = APIRouter()
    cache = ModelCache(store)
    links: dict[str, tuple[str, float]] = {}  # ticket -> (report sha256, expiry [Unix s])
    not_found = {404: {"model": errors[422]["model"], "description": "no such truck, version, report or link"}}

    def chosen(points: str | None, threshold: float | None):
        try:
            return (parse_points(points) if points else settings.points,
                    threshold if threshold is not None else settings.threshold_percent)
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None

    views: OrderedDict[tuple, FleetView] = OrderedDict()  # (points, threshold) -> view, least recently used first
    views_lock = threading.Lock()  # one refresh at a time: a concurrent request waits for its result

    def view(points: str | None, threshold: float | None) -> FleetView:
        """The fleet view at these points and threshold, refreshed only when the registry changed: rows are
        inserted or deleted, never updated, so the counts and newest ids of trucks, files and model versions
        tell whether anything did."""
        key = chosen(points, threshold)
        with views_lock:
            v = views.pop(key, None) or FleetView(*key)
            views[key] = v
            if len(views) > MAX_VIEWS:
                views.popitem(last=False)
            with engine.connect() as conn:
                fingerprint = tuple(conn.execute(FINGERPRINT).one())
                if fingerprint != v.fingerprint:
                    v.refresh(conn, cache, fingerprint)
            return v

    @api.get("/api/v1/fleet", response_model=FleetSummary, responses=errors, tags=["console"])
    def fleet(points: Points = None, threshold: Threshold = None, _=Depends(reader)):
        """Every truck with data hours, last upload, latest version's fit and cycle error, effects, steady-state
        fuel at the reference points, drift since its first model (± standard error), against the fleet median,
        and alerts."""
        return Response(view(points, threshold).body, media_type="application/json")

    @api.get("/api/v1/alerts", response_model=list[Alert], responses=errors, tags=["console"])
    def alerts(points: Points = None, threshold: Threshold = None, _=Depends(reader)):
        """Trucks whose steady-state fuel drifted beyond the threshold and 2σ, or whose diagnosis names a new
        effect."""
        return view(points, threshold).alerts

    @api.get("/api/v1/trucks/{truck}/history", response_model=TruckHistory,
             responses={**errors, **not_found}, tags=["console"])
    def history(truck: Annotated[str, PathParam(pattern=auth.TRUCK_PATTERN)], points: Points = None,
                threshold: Threshold = None, _=Depends(reader)):
        """Model versions over time (metrics, effects, drift with uncertainty), files with their time ranges,
        recent jobs."""
        if not db.truck_exists(engine, truck):
            raise HTTPException(404, f"no truck {truck}")
        pts, thr = chosen(points, threshold)
        return truck_history(engine, cache, truck, pts, thr)

    @api.post("/api/v1/trucks/{truck}/models/{version}/report-link", response_model=ReportLink,
              responses={**errors, **not_found}, tags=["console"])
    def report_link(truck: Annotated[str, PathParam(pattern=auth.TRUCK_PATTERN)],
                    version: Annotated[int, PathParam(ge=1, le=2**31 - 1)], _=Depends(reader)):
        """A link to the version's report.html that works without a token for a short while (a browser tab
        cannot send the Authorization header)."""
        model = db.get_model(engine, truck, version)
        if model is None or model["report_sha256"] is None:
            raise HTTPException(404, f"truck {truck} has no report for version {version}")
        now = time.time()
        for k in [k for k, (_, exp) in links.items() if exp < now]:
            del links[k]
        ticket = secrets.token_urlsafe(24)
        links[ticket] = (model["report_sha256"], now + REPORT_LINK_S)
        return {"url": f"/reports/{ticket}", "expires_unix_s": now + REPORT_LINK_S}

    @api.get("/reports/{ticket}", tags=["console"],
             responses={200: {"content": {"text/html": {}}, "description": "the report"}, **not_found,
                        422: errors[422]})
    def report(ticket: Annotated[str, PathParam(pattern=r"^[A-Za-z0-9_-]{32}$")]):
        """The report of a link from report-link, sandboxed."""
        sha, expires = links.get(ticket, ("", 0.0))
        if expires < time.time():
            raise HTTPException(404, "unknown or expired report link")
        return FileResponse(store.path(sha), media_type="text/html",
                            headers={"Content-Security-Policy": REPORT_CSP, "Cache-Control": "no-store",
                                     "Referrer-Policy": "no-referrer", "X-Content-Type-Options": "nosniff"})

    return api


def mount(app: FastAPI, engine: sa.Engine, store: BlobStore, settings: ConsoleSettings, reader: Callable,
          errors: dict) -> None:
    """Add the console's API, its page at `/` and its files at /static, with their security headers."""
    app.include_router(router(engine, store, settings, reader, errors))

    @app.get("/", include_in_schema=False)
    def page():
        return FileResponse(STATIC / "index.html", media_type="text/html")

    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.middleware("http")
    async def console_headers(request, call_next):
        response = await call_next(request)
        if request.url.path == "/" or request.url.path.startswith("/static/"):
            response.headers["Content-Security-Policy"] = CONSOLE_CSP
            response.headers["X-Content-Type-Options"] = "nosniff"
            response.headers["Referrer-Policy"] = "no-referrer"
            response.headers["Cache-Control"] = "no-cache"
        return response
