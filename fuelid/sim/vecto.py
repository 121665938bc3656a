"""VECTO engine sets: the .veng engine file, its .vmap fuel map and its .vfld full-load curve.

VECTO (the European Commission's truck CO2 certification simulator) describes an engine by three files:

    .veng  JSON, {"Header": {"FileVersion": n}, "Body": {"IdlingSpeed" [rpm], "Inertia" [kg m²],
           "Displacement" [cm³], "FullLoadCurve": "x.vfld", "RatedPower" [W], "RatedSpeed" [rpm],
           "MaxTorque" [N m], ...}}; file names relative to it. The fuel is named in one of two ways:
             FileVersion <= 4: Body "FuelMap": "x.vmap", "FuelType" (a name or its number in FUEL_TYPES,
                               absent: diesel), "WHTC-Urban"/"WHTC-Rural"/"WHTC-Motorway" [-]
             FileVersion 5:    Body "Fuels": [{"FuelMap", "FuelType", "WHTC-Urban", ...}, ...], one entry per
                               fuel (two for a dual-fuel engine; the first is the primary fuel and the one read)
           RatedPower or RatedSpeed absent or 0: taken from the full-load curve (its largest power T ω); the
           largest torque is always the curve's (a declared MaxTorque is not used). A WHTC factor that is absent
           or 0 (engineering-mode files leave the declaration factors at 0) is "WHTC-Engineering" when that is
           given and not 0, else 1 (no correction). FileVersion 1 and 2 (VECTO 2) name the curve in
           "FullLoadCurves": [{"Path": "x.vfld", "Gears": "0 - 99"}, ...], the first the engine's, and hold no
           WHTC factors VECTO reads (1 here), as VECTO reads them. A comma before a closing } or ] is accepted,
           as VECTO's JSON reader (Json.NET) accepts it; VECTO's own generic dual-fuel engine file has one.
    .vmap  CSV, one header line: engine speed [rpm], flywheel torque [N m], fuel consumption [g/h]; the grid need
           not be rectangular (the full-load line cuts it at high torque). When the header names all three
           ("engine speed", "torque", "fuel consumption", units in brackets aside) the columns are found by name,
           else they are the first three; further columns (a waste-heat-recovery engine's "whr power electrical
           [W]", "whr power mechanical [W]") are not read.
    .vfld  CSV, one header line: engine speed [rpm], full-load torque [N m], motoring torque [N m] (<= 0),
           optionally a PT1 time constant of the torque build-up [s]

`read_engine` reads a set (a .veng path or a shipped set's short name, `SHIPPED`) into a `VectoEngine`; any
malformed or incomplete file raises a FuelidError naming the file and the field, in one line. Files may start
with a byte-order mark and use CR LF, as VECTO writes them. The steady-state map is interpolated linearly on a
Delaunay triangulation of its (speed, torque) points, as VECTO does; a query is first clamped to the speed range
and to [motoring, full load], and a point still outside the map's convex hull takes the value of the nearest map
point.
"""
import json
import math
import re
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path

import numpy as np
from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
from scipy.spatial import QhullError

from fuelid.errors import FuelidError

SHIPPED = {"vecto_325kW": "vecto_325kW_12.7l/Engine_325kW_12.7l.veng"}
"""Short name -> engine file of the sets shipped in fuelid/sim/engines/ (each with its SOURCES.md)."""

REQUIRED_VENG = ("IdlingSpeed", "Inertia")
WHTC_FIELDS = ("WHTC-Urban", "WHTC-Rural", "WHTC-Motorway")
"""Transient correction factors of declaration mode; VECTO's engineering-mode files may omit them or leave them 0."""
WHTC_ENGINEERING = "WHTC-Engineering"
"""The one correction factor of engineering mode, used where a declaration factor is not given."""
FUEL_TYPES = ("DieselCI", "EthanolCI", "PetrolPI", "EthanolPI", "LPGPI", "NGPI", "NGCI")
"""VECTO's fuel types, in the order of their numbers (a FuelType given as a number indexes this)."""
LIQUID_DENSITY_KG_L = {"DieselCI": 0.835, "EthanolCI": 0.820, "PetrolPI": 0.748, "EthanolPI": 0.786,
                       "LPGPI": 0.560}
"""Density of each liquid fuel [kg/L] (diesel B7, ED95, E10, E85 and liquefied petroleum gas), to turn the map's g/h
into the L/h of LFE1 (SPN 183). The natural-gas types have no liquid volume: the map truth refuses them."""


@dataclass(frozen=True, eq=False)
class VectoEngine:
    """One engine set. Arrays: map points (rpm, N m, g/h) and the full-load curve over its speeds [rpm]."""

    name: str
    path: str                       # the .veng file
    idle_speed_rpm: float
    inertia_kgm2: float
    displacement_cm3: float | None
    whtc: dict                      # {"urban": f, "rural": f, "motorway": f}, dimensionless
    fuel_type: str                  # one of FUEL_TYPES (the primary fuel of a dual-fuel engine)
    fuels: tuple                    # every fuel type the file lists, primary first
    file_version: int | None        # Header.FileVersion, None when absent
    rated_power_kw: float           # declared, or the full-load curve's largest power
    rated_speed_rpm: float          # declared, or the speed of the full-load curve's largest power
    map_rpm: np.ndarray
    map_nm: np.ndarray
    map_g_h: np.ndarray
    fld_rpm: np.ndarray
    full_load_nm: np.ndarray
    motoring_nm: np.ndarray          # <= 0
    pt1_s: np.ndarray | None         # torque build-up time constant per fld speed [s], None if not given
    _linear: LinearNDInterpolator = field(repr=False, default=None)
    _nearest: NearestNDInterpolator = field(repr=False, default=None)

    @property
    def fuel_density_kg_l(self) -> float:
        """Density of the (primary) fuel [kg/L]; FuelidError for a gaseous fuel (no L/h to report)."""
        if self.fuel_type not in LIQUID_DENSITY_KG_L:
            raise FuelidError(f"{self.path}: fuel type {self.fuel_type} is a gas; the map truth reports L/h "
                              f"(LFE1) and needs a liquid fuel ({', '.join(LIQUID_DENSITY_KG_L)})")
        return LIQUID_DENSITY_KG_L[self.fuel_type]

    @property
    def max_torque_nm(self) -> float:
        """Largest full-load torque [N m] (the J1939 reference torque, SPN 544)."""
        return float(self.full_load_nm.max())

    def full_load(self, speed_rpm):
        """Full-load flywheel torque [N m] at engine speed [rpm], linear in the curve, its end values held."""
        return np.interp(speed_rpm, self.fld_rpm, self.full_load_nm)

    def motoring(self, speed_rpm):
        """Motoring (drag) flywheel torque [N m] at engine speed [rpm], <= 0."""
        return np.interp(speed_rpm, self.fld_rpm, self.motoring_nm)

    def pt1(self, speed_rpm):
        """PT1 time constant of the torque build-up [s] at engine speed [rpm]; 0 where the curve gives none."""
        if self.pt1_s is None:
            return np.zeros_like(np.asarray(speed_rpm, float))
        return np.interp(speed_rpm, self.fld_rpm, self.pt1_s)

    def fuel_g_h(self, speed_rpm, torque_nm):
        """Steady-state fuel consumption [g/h] at engine speed [rpm] and flywheel torque [N m]:

            FC = map(clip(n), clip(T, T_mot(n), T_full(n)))   for T > T_mot(n),   0 at or below motoring

        `map` is linear on the Delaunay triangulation of the map points (nearest point outside their hull)."""
        n = np.clip(np.asarray(speed_rpm, float), self.fld_rpm[0], self.fld_rpm[-1])
        torque = np.asarray(torque_nm, float)
        mot = self.motoring(n)
        t = np.clip(torque, mot, self.full_load(n))
        f = self._linear(n, t)
        outside = np.isnan(f)
        if np.any(outside):
            f = np.where(outside, self._nearest(n, t), f)
        return np.where(torque <= mot, 0.0, np.maximum(f, 0.0))


def engine_file(name_or_path) -> Path:
    """The .veng file of a shipped set's short name, or the given path."""
    if str(name_or_path) in SHIPPED:
        return Path(str(files("fuelid.sim") / "engines" / SHIPPED[str(name_or_path)]))
    return Path(name_or_path)


def read_engine(name_or_path) -> VectoEngine:
    """The engine set named by a short name (`SHIPPED`) or a .veng path; FuelidError if it is not a valid set."""
    path = engine_file(name_or_path)
    if not path.is_file():
        known = ", ".join(SHIPPED)
        raise FuelidError(f"{path}: no such engine file (give a VECTO .veng file or one of: {known})")
    try:
        doc = _json(path.read_text(encoding="utf-8-sig"))  # VECTO's own files often start with a BOM
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FuelidError(f"{path}: not a VECTO engine file (JSON): {exc}") from None
    body = doc.get("Body") if isinstance(doc, dict) else None
    if not isinstance(body, dict):
        raise FuelidError(f"{path}: no \"Body\" object (not a VECTO engine file)")
    missing = [k for k in REQUIRED_VENG if k not in body]
    if missing:
        raise FuelidError(f"{path}: field {missing[0]!r} missing")
    version = _file_version(path, doc)
    fuel_doc, fuels = _fuels(path, body)
    idle = _number(path, body, "IdlingSpeed", 200.0, 1500.0)
    inertia = _number(path, body, "Inertia", 0.1, 50.0)
    displacement = _number(path, body, "Displacement", 100.0, 100000.0) if "Displacement" in body else None
    whtc = _whtc(path, fuel_doc, version)
    fld_rpm, full, motoring, pt1 = _read_full_load(_full_load_path(path, body, version))
    map_path = _beside(path, fuel_doc, "FuelMap")
    map_rpm, map_nm, map_g_h = _read_map(map_path)
    if fld_rpm[0] > idle:
        raise FuelidError(f"{path}: IdlingSpeed {idle:g} rpm is below the full-load curve's first speed "
                          f"{fld_rpm[0]:g} rpm")
    power_w = full * fld_rpm * math.pi / 30.0  # P = T ω [W]
    declared_w = _number(path, body, "RatedPower", 0.0, 2e6) if "RatedPower" in body else 0.0
    declared_rpm = _number(path, body, "RatedSpeed", 0.0, 10000.0) if "RatedSpeed" in body else 0.0
    points = np.column_stack([map_rpm, map_nm])
    try:
        linear = LinearNDInterpolator(points, map_g_h, rescale=True)
    except QhullError:
        raise FuelidError(f"{map_path}: the map's (speed, torque) points span no area (all on one line?)") from None
    return VectoEngine(name=str(body.get("ModelName") or path.stem), path=str(path), idle_speed_rpm=idle,
                       inertia_kgm2=inertia, displacement_cm3=displacement, whtc=whtc, fuel_type=fuels[0],
                       fuels=fuels, file_version=version,
                       rated_power_kw=(declared_w or float(power_w.max())) / 1000.0,
                       rated_speed_rpm=declared_rpm or float(fld_rpm[np.argmax(power_w)]), map_rpm=map_rpm,
                       map_nm=map_nm, map_g_h=map_g_h, fld_rpm=fld_rpm, full_load_nm=full, motoring_nm=motoring,
                       pt1_s=pt1, _linear=linear, _nearest=NearestNDInterpolator(points, map_g_h, rescale=True))


def describe(engine: VectoEngine) -> dict:
    """The truth-file entry of an engine set (scalars only, no curves)."""
    dual = (f"dual-fuel engine ({', '.join(engine.fuels)}): the map truth burns the primary fuel "
            f"{engine.fuel_type} only, on its own map" if len(engine.fuels) > 1 else None)
    return {"name": engine.name, "file": Path(engine.path).name, "file_version": engine.file_version,
            "fuel_type": engine.fuel_type, "fuels": list(engine.fuels), **({"fuels_note": dual} if dual else {}),
            "rated_power_kw": round(engine.rated_power_kw, 3), "rated_speed_rpm": engine.rated_speed_rpm,
            "idle_speed_rpm": engine.idle_speed_rpm,
            "inertia_kgm2": engine.inertia_kgm2, "displacement_cm3": engine.displacement_cm3,
            "max_torque_nm": engine.max_torque_nm, "whtc": engine.whtc, "map_points": int(len(engine.map_rpm)),
            "speed_range_rpm": [float(engine.fld_rpm[0]), float(engine.fld_rpm[-1])],
            "pt1": engine.pt1_s is not None}


_TRAILING_COMMA = re.compile(r'("(?:[^"\\]|\\.)*")|,(\s*[}\]])')
"""A JSON string (kept as it is) or a comma before a closing bracket (dropped)."""


def _json(text: str):
    """The JSON document of text; a comma before } or ] (outside strings) is accepted, as Json.NET accepts it."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        try:
            return json.loads(_TRAILING_COMMA.sub(lambda m: m.group(1) or m.group(2), text))
        except json.JSONDecodeError:
            raise exc from None


def _whtc(path: Path, fuel_doc: dict, version: int | None) -> dict:
    """The WHTC correction factors {"urban", "rural", "motorway"} (module docstring): each declaration factor, else
    WHTC-Engineering, else 1; a factor given and not 0 must lie in 0.8..1.5. FileVersion 1–2: 1 (VECTO reads the
    factors from FileVersion 3 on)."""
    def given(key: str) -> float | None:
        if version is not None and version < 3:
            return None
        if key not in fuel_doc or _number(path, fuel_doc, key, 0.0, 1.5) == 0.0:
            return None
        return _number(path, fuel_doc, key, 0.8, 1.5)

    engineering = given(WHTC_ENGINEERING)
    return {k.split("-")[1].lower(): given(k) or engineering or 1.0 for k in WHTC_FIELDS}


def _file_version(path: Path, doc: dict) -> int | None:
    header = doc.get("Header")
    value = header.get("FileVersion") if isinstance(header, dict) else None
    if value is None:
        return None
    try:
        return int(value)
    except (TypeError, ValueError):
        raise FuelidError(f"{path}: Header field 'FileVersion' is not a number: {value!r}") from None


def _fuel_type(path: Path, value) -> str:
    """A FuelType given as a name (any case) or as its number in FUEL_TYPES."""
    names = {n.lower(): n for n in FUEL_TYPES}
    if isinstance(value, str) and value.strip().lower() in names:
        return names[value.strip().lower()]
    if isinstance(value, (int, str)) and not isinstance(value, bool) and str(value).strip().isdigit():
        k = int(str(value).strip())
        if k < len(FUEL_TYPES):
            return FUEL_TYPES[k]
    raise FuelidError(f"{path}: field 'FuelType' = {value!r} is not a VECTO fuel type "
                      f"({', '.join(FUEL_TYPES)}, or their numbers 0-{len(FUEL_TYPES) - 1})")


def _fuels(path: Path, body: dict) -> tuple[dict, tuple]:
    """(the object that holds the primary fuel's FuelMap, FuelType and WHTC factors, every fuel type listed):
    Body itself (FileVersion <= 4) or Body.Fuels[0] (FileVersion 5)."""
    if "Fuels" not in body:
        if "FuelMap" not in body:
            raise FuelidError(f"{path}: field 'FuelMap' missing (or 'Fuels', as FileVersion 5 names the maps)")
        return body, (_fuel_type(path, body.get("FuelType", "DieselCI")),)
    fuels = body["Fuels"]
    if not isinstance(fuels, list) or not fuels or not all(isinstance(f, dict) for f in fuels):
        raise FuelidError(f"{path}: field 'Fuels' must be a list of fuel objects, got {fuels!r:.60}")
    for k, f in enumerate(fuels):
        for key in ("FuelMap", "FuelType"):
            if key not in f:
                raise FuelidError(f"{path}: field 'Fuels[{k}].{key}' missing")
    return fuels[0], tuple(_fuel_type(path, f["FuelType"]) for f in fuels)


def _number(path: Path, body: dict, key: str, low: float, high: float) -> float:
    value = body[key]
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise FuelidError(f"{path}: field {key!r} is not a number: {value!r}") from None
    if not (math.isfinite(x) and low <= x <= high):
        raise FuelidError(f"{path}: field {key!r} = {x:g} is outside {low:g}..{high:g}")
    return x


def _full_load_path(path: Path, body: dict, version: int | None) -> Path:
    """The .vfld file: Body.FullLoadCurve, or in FileVersion 1–2 the Path of Body.FullLoadCurves' first entry (its
    gears 0 – 99: the engine's own curve; later entries limit single gears), as VECTO reads them."""
    if version is not None and version < 3 and "FullLoadCurve" not in body:
        curves = body.get("FullLoadCurves")
        if not isinstance(curves, list) or not curves or not isinstance(curves[0], dict) or "Path" not in curves[0]:
            raise FuelidError(f"{path}: field 'FullLoadCurves' must list objects with a 'Path' (FileVersion "
                              f"{version}), got {curves!r:.60}")
        return _beside(path, curves[0], "Path")
    if "FullLoadCurve" not in body:
        raise FuelidError(f"{path}: field 'FullLoadCurve' missing")
    return _beside(path, body, "FullLoadCurve")


def _beside(path: Path, body: dict, key: str) -> Path:
    name = body[key]
    if not isinstance(name, str) or not name.strip():
        raise FuelidError(f"{path}: field {key!r} must name a file, got {name!r}")
    target = path.parent / name.strip()
    if not target.is_file():
        raise FuelidError(f"{path}: field {key!r} names {target}, which does not exist")
    return target


def _read_table(path: Path, columns: tuple, optional: float = 0) -> tuple[list[str], np.ndarray]:
    """(the header's column names, lower case and without their units in brackets; the rows as floats) of a VECTO
    CSV file (one header line, '#' comments); `columns` name the required columns, `optional` more may follow."""
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except UnicodeDecodeError as exc:
        raise FuelidError(f"{path}: not a text file: {exc}") from None
    rows, width = [], None
    body = [(i + 1, s) for i, s in enumerate(lines) if s.strip() and not s.lstrip().startswith("#")]
    if not body:
        raise FuelidError(f"{path}: empty (expected a header line and rows of {', '.join(columns)})")
    for number, line in body[1:]:  # the first line is the header
        cells = [c.strip() for c in line.split("#")[0].split(",")]
        if width is None:
            width = len(cells)
        if not len(columns) <= len(cells) <= len(columns) + optional or len(cells) != width:
            raise FuelidError(f"{path}: line {number}: expected {len(columns)} columns "
                              f"({', '.join(columns)}), got {len(cells)}")
        try:
            row = [float(c) for c in cells]
        except ValueError:
            raise FuelidError(f"{path}: line {number}: not a number in {line.strip()!r}") from None
        if not all(math.isfinite(x) for x in row):
            raise FuelidError(f"{path}: line {number}: not a finite number in {line.strip()!r}")
        rows.append(row)
    if len(rows) < 2:
        raise FuelidError(f"{path}: fewer than two rows of {', '.join(columns)}")
    header = [re.sub(r"\[.*?\]", "", c).strip().lower() for c in body[0][1].split("#")[0].split(",")]
    return header, np.array(rows)


def _read_full_load(path: Path):
    cols = ("engine speed [rpm]", "full load torque [Nm]", "motoring torque [Nm]")
    _, a = _read_table(path, cols, optional=1)
    rpm, full, motoring = a[:, 0], a[:, 1], a[:, 2]
    if np.any(np.diff(rpm) <= 0):
        k = int(np.argmax(np.diff(rpm) <= 0)) + 1
        raise FuelidError(f"{path}: {cols[0]} must increase, {rpm[k]:g} follows {rpm[k - 1]:g}")
    if np.any(full < 0):
        raise FuelidError(f"{path}: {cols[1]} is negative at {rpm[np.argmax(full < 0)]:g} rpm")
    if np.any(motoring > 0):
        raise FuelidError(f"{path}: {cols[2]} must be <= 0, is {motoring.max():g} at {rpm[np.argmax(motoring)]:g} rpm")
    pt1 = a[:, 3] if a.shape[1] > 3 else None
    if pt1 is not None and np.any(pt1 < 0):
        raise FuelidError(f"{path}: PT1 time constant [s] is negative at {rpm[np.argmax(pt1 < 0)]:g} rpm")
    return rpm, full, motoring, pt1


def _read_map(path: Path):
    cols = ("engine speed [rpm]", "torque [Nm]", "fuel consumption [g/h]")
    header, a = _read_table(path, cols, optional=math.inf)
    names = [c.split(" [")[0] for c in cols]
    by_name = set(names) <= set(header) and len(header) == a.shape[1]  # a header that names the rows' columns
    a = a[:, [header.index(c) for c in names] if by_name else [0, 1, 2]]
    if len(a) < 3:
        raise FuelidError(f"{path}: fewer than three map points")
    if np.any(a[:, 2] < 0):
        raise FuelidError(f"{path}: {cols[2]} is negative at {a[np.argmax(a[:, 2] < 0), 0]:g} rpm")
    if np.any(a[:, 0] <= 0):
        raise FuelidError(f"{path}: {cols[0]} must be positive")
    _, first = np.unique(a[:, :2], axis=0, return_index=True)
    if len(first) != len(a):
        dup = a[np.setdiff1d(np.arange(len(a)), first)[0]]
        raise FuelidError(f"{path}: the point {dup[0]:g} rpm, {dup[1]:g} Nm appears twice")
    return a[:, 0], a[:, 1], a[:, 2]
