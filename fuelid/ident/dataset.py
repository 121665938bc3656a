"""Identification data from logged J1939/FMS records: paper 000, Section III (preprocessing).

`build_dataset` turns decoded MCAP records (`/j1939/<MESSAGE>` and `/flowmeter`, see docs/formats.md) into a
`Dataset` on a regular grid of Ts seconds (paper: 0.3 s):

inputs   u[:, 0] engine speed [rpm]   = EEC1.EngSpeed (SPN 190)
         u[:, 1] engine torque [Nm]   = EEC1.ActualEngPercentTorque (SPN 513) [%] × EC1.EngReferenceTorque
                                        (SPN 544) [Nm] / 100; [%] (with a warning) when EC1 never arrived
output   y       fuel flow            = /flowmeter flow_kg_h [kg/h] or LFE1.EngFuelRate (SPN 183) [L/h]

Source addresses. Per signal, the values of the preferred source address of its message are used
(logger.j1939.DEFAULT_SOURCE_PREFERENCE: the engine 0x00, the transmission 0x03 for ETC2); only when that
address never sends a valid value of the signal are the values of the other address that sent the most
valid values used. A null (not available / error) is no sample at all, so it never replaces a valid value.

Resampling (no interpolation). The log time is cut into bins [kTs, (k+1)Ts) (multiples of Ts on the log
clock, computed in integer ns so that a sample on a boundary always opens the next bin):
- averaged (mean of the valid samples in the bin): engine speed, torque, fuel flow, vehicle speed — the
  fast, continuous signals the models use (EEC1 comes every 10–50 ms, LFE1/CCVS1/the meter every ~100 ms);
- held (the last valid sample before the bin's end): every other signal ("extras", named MESSAGE.Signal),
  which is exact for states and enumerations (gear, switches) and right for slow broadcasts;
- a bin without a sample of an averaged signal holds the previous value if it is at most `max_gap_s` old at
  the bin's end; after a longer gap the samples are NaN and invalid. Extras hold up to
  max(max_gap_s, 3 × their median period) and never decide validity.
A sample is valid when speed, torque and fuel are all finite; maximal runs of valid samples are the
segments (identification runs per segment). Stretches with no data for longer than max_gap_s are not
filled with empty rows: the grid keeps one invalid row there and jumps, so `t` is increasing but not
uniform across such breaks (rotated files and several days of logs stay small).

Operating point (paper: idle, 600 rpm). Idle samples are valid samples with |speed − idle_rpm| ≤
idle_tol_rpm and, when CCVS1 is logged, vehicle speed < 2 km/h, in runs lasting at least idle_min_s
(3 s: a settled idle, not a pass through 600 rpm); u0 = (mean speed, mean torque) and y0 =
mean fuel over them. The torque operating point is the torque the engine reports at idle (friction and
accessories, a few % of the reference torque). idle_rpm defaults to EC1.EngSpeedAtIdlePoint1 when logged,
else 600 rpm. `u`, `y` are kept absolute; `du`, `dy` are the deviations the paper identifies on (PolyModel
subtracts its u0, y0 itself).

Drive cycles (for eq. 20 / Table I). Each segment is cut into consecutive windows of `cycle_s` seconds
(default 1800 s, the paper's 30-minute cycles); a remainder shorter than cycle_s joins the window before
it, and a segment shorter than cycle_s is one cycle. Segments shorter than `min_cycle_s` belong to no
cycle (id −1). Engine-off stops split segments (no traffic), so a cycle never spans a stop.
"""
from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.io import loadmat, savemat

from fuelid.errors import FuelidError
from fuelid.logger.decode import Decoder, signal_units
from fuelid.logger.j1939 import DEFAULT_SOURCE_PREFERENCE, preferred_source
from fuelid.logger.mcap_log import MAGIC, read_messages
from fuelid.progress import progress

SPEED = "EEC1.EngSpeed"
TORQUE_PCT = "EEC1.ActualEngPercentTorque"
REF_TORQUE = "EC1.EngReferenceTorque"
IDLE_SPEED = "EC1.EngSpeedAtIdlePoint1"
VEHICLE_SPEED = "CCVS1.WheelBasedVehicleSpeed"
FUEL_SIGNALS = {"flowmeter": ("flowmeter.flow_kg_h", "kg/h"), "lfe1": ("LFE1.EngFuelRate", "L/h")}
AVERAGED = {SPEED, TORQUE_PCT, VEHICLE_SPEED, *(name for name, _ in FUEL_SIGNALS.values())}
NOT_SIGNALS = {"t", "pgn", "sa", "da", "invalid", "tp", "device_t", "raw", "status"}
NUMBER_OR_NULL = {int, float, type(None)}


@dataclass
class Dataset:
    """Resampled identification data; see the module docstring for how each field is made.

    Ts [s]; t [s] bin start times on the log clock (N); u (N×2) [rpm, Nm or %]; y (N) [output_unit];
    u0 (2) and y0 the idle operating point in the same units; valid (N) bool; cycle (N) int drive-cycle id
    (−1 = none); extra MESSAGE.Signal → (N) array in the DBC unit; sources signal → source address used;
    notes the warnings raised while building.
    """
    Ts: float
    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    input_names: tuple[str, str]
    input_units: tuple[str, str]
    output_name: str
    output_unit: str
    u0: np.ndarray
    y0: float
    valid: np.ndarray
    cycle: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    sources: dict[str, int | None] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def du(self) -> np.ndarray:
        """Inputs minus the operating point (N×2)."""
        return self.u - self.u0

    @property
    def dy(self) -> np.ndarray:
        """Output minus the operating point (N)."""
        return self.y - self.y0

    def segments(self, min_s: float = 0.0) -> list[slice]:
        """Maximal runs of valid, consecutive samples at least min_s [s] long, as slices."""
        v = self.valid
        jump = np.r_[True, np.abs(np.diff(self.t) - self.Ts) > 0.01 * self.Ts]
        start = v & (jump | ~np.r_[False, v[:-1]])
        last = v & np.r_[start[1:] | ~v[1:], True]
        return [slice(int(a), int(b) + 1) for a, b in zip(np.flatnonzero(start), np.flatnonzero(last))
                if (b + 1 - a) * self.Ts >= min_s]

    def summary(self) -> dict:
        """A JSON-ready description (sizes, units, operating point, sources, warnings)."""
        segs = self.segments()
        return {
            "Ts": self.Ts,
            "samples": len(self),
            "valid_samples": int(self.valid.sum()),
            "valid_duration_s": float(self.valid.sum() * self.Ts),
            "segments": len(segs),
            "cycles": sorted(int(c) for c in np.unique(self.cycle[self.cycle >= 0])),
            "inputs": [{"name": n, "unit": u} for n, u in zip(self.input_names, self.input_units)],
            "output": {"name": self.output_name, "unit": self.output_unit},
            "operating_point": {"u0": [float(v) for v in self.u0], "y0": float(self.y0)},
            "sources": self.sources,
            "extra_signals": sorted(self.extra),
            "warnings": list(self.notes),
        }


def _records(sources, damaged=None):
    """Chain (topic, log_time_ns, record) from MCAP paths (read with a progress bar on a terminal) and/or
    record iterables; a bare list of records works too. A damaged chunk of a file raises FuelidError, or,
    when a `damaged` list is given, is skipped and appended to it."""
    if isinstance(sources, (str, Path)):
        sources = [sources]
    spans = {}  # path -> (first, last) log time [ns]: files are parts of one timeline and must not overlap
    for src in sources:
        if isinstance(src, (str, Path)):
            p = Path(src)
            if not p.is_file():
                raise FuelidError(f"{p}: no such file")
            topics = ["/flowmeter"] + [f"/j1939/{m}" for m in Decoder().message_names()]  # not /can/raw
            first = last = None
            for record in progress(read_messages(p, topics, damaged=damaged), desc=p.name, unit="msg"):
                t = record[1]
                if first is None:
                    first = last = t
                elif t < first:  # comparisons, not min()/max(): this runs once per message
                    first = t
                elif t > last:
                    last = t
                yield record
            for other, (a, b) in spans.items():
                if first is not None and a is not None and first <= b and a <= last:
                    raise FuelidError(f"{p} and {other} overlap in time: they are not parts of one recording; "
                                      "give them to separate runs")
            spans[p] = (first, last)
        elif isinstance(src, tuple) and len(src) == 3 and isinstance(src[0], str):
            yield src
        else:
            yield from src


def _collect(records) -> dict[str, dict]:
    """signal name → source address → (log times [ns] int64 array, values float array) of the valid
    (numeric) samples; signals and addresses in the order their first valid sample arrived.

    Records are grouped by topic and source address, then each signal becomes one column of its group:
    JSON null (not available) is NaN in a float array and dropped, booleans and strings are no samples. (A
    per-value dict walk here was the slowest step after reading the file.)"""
    by_topic: dict[str, tuple[list, list, list]] = {}
    for n, (topic, log_ns, rec) in enumerate(records):  # once per message: as little work as possible
        group = by_topic.get(topic)
        if group is None:
            group = by_topic[topic] = ([], [], [])
        group[0].append(n)
        group[1].append(log_ns)
        group[2].append(rec)
    found = []  # (arrival of the first valid sample, its key position in the record, name, sa, times, values)
    for topic, (order, times, recs) in by_topic.items():
        if topic == "/flowmeter":
            msg, sas = "flowmeter", [None] * len(recs)
        elif topic.startswith("/j1939/"):
            msg, sas = topic[7:], [r.get("sa") for r in recs]
        else:
            continue
        for sa in dict.fromkeys(sas):
            idx = [i for i, a in enumerate(sas) if a == sa]
            group, group_times = [recs[i] for i in idx], np.asarray(times, np.int64)[idx]
            for name in set().union(*group) - NOT_SIGNALS:
                col = [r.get(name) for r in group]
                if set(map(type, col)) <= NUMBER_OR_NULL:  # the usual case: numpy makes None NaN
                    values = np.array(col, dtype=float)
                else:
                    values = np.array([v if type(v) in (int, float) else np.nan for v in col], dtype=float)
                keep = ~np.isnan(values)  # JSON has no NaN: NaN here is exactly "no sample"
                if keep.any():
                    first = idx[int(np.argmax(keep))]
                    found.append((order[first], list(recs[first]).index(name), f"{msg}.{name}", sa,
                                  group_times[keep], values[keep]))
    sig: dict[str, dict] = {}
    for _, _, name, sa, ts, vs in sorted(found, key=lambda f: f[:2]):
        sig.setdefault(name, {})[sa] = (ts, vs)
    return sig


def _cut_files(sources) -> str:
    """'; PATH is truncated: N s readable' for each MCAP source cut before its footer (the reason a signal may be
    missing), else ''."""
    paths = [Path(s) for s in ([sources] if isinstance(sources, (str, Path)) else sources) if isinstance(s, (str, Path))]
    notes = []
    for p in paths:
        with open(p, "rb") as f:
            f.seek(max(p.stat().st_size - len(MAGIC), 0))
            if f.read() == MAGIC:
                continue
        times = [t for _, t, _ in read_messages(p, damaged=[])]
        readable = (max(times) - min(times)) / 1e9 if times else 0.0
        notes.append(f"{p} is truncated (cut before its end): {readable:.0f} s readable")
    return "; " + "; ".join(notes) + " (`fuelid recover` rewrites what is left)" if notes else ""


def _choose(sig: dict, preference: dict) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], dict]:
    """Per signal the samples of one source address (preferred, else the one with most samples), time-sorted."""
    chosen, used = {}, {}
    for name, by_sa in sig.items():
        msg = name.split(".", 1)[0]
        pref = None if msg == "flowmeter" else preferred_source(msg, preference)
        sa = pref if pref in by_sa else max(by_sa, key=lambda a: len(by_sa[a][0]))
        ts, vs = by_sa[sa]
        order = np.argsort(ts, kind="stable")
        chosen[name], used[name] = (ts[order], vs[order]), sa
    return chosen, used


def _resample(ts, vs, k_rows, t0, Ts, hold, mean):
    """One signal on the grid rows k_rows (bin numbers): bin mean (or last sample) with a hold of at most
    `hold`; times ts, t0, Ts, hold in integer ns, so a sample on a bin boundary always opens the bin."""
    bin_end = t0 + (k_rows + 1) * Ts
    j = np.searchsorted(ts, bin_end, side="left") - 1  # last sample before each bin's end
    out = np.full(len(k_rows), np.nan)
    fresh = (j >= 0) & (bin_end - ts[np.maximum(j, 0)] <= hold)
    out[fresh] = vs[j[fresh]]
    if mean:
        row = np.searchsorted(k_rows, (ts - t0) // Ts)
        n = np.bincount(row, minlength=len(k_rows))
        s = np.bincount(row, weights=vs, minlength=len(k_rows))
        out[n > 0] = s[n > 0] / n[n > 0]
    return out


def _lasting(mask: np.ndarray, n: int) -> np.ndarray:
    """mask restricted to its runs of at least n consecutive True samples."""
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    out = np.zeros_like(mask)
    for a, b in zip(edges[::2], edges[1::2]):
        out[a:b] = b - a >= n
    return out


def _cycles(ds_valid_segments: list[slice], n: int, Ts: float, cycle_s: float, min_cycle_s: float) -> np.ndarray:
    cycle = np.full(n, -1, dtype=np.int64)
    cid = 0
    per = max(int(round(cycle_s / Ts)), 1)
    for seg in ds_valid_segments:
        length = seg.stop - seg.start
        if length * Ts < min_cycle_s:
            continue
        windows = max(length // per, 1)
        for w in range(windows):
            a = seg.start + w * per
            b = seg.stop if w == windows - 1 else a + per
            cycle[a:b] = cid
            cid += 1
    return cycle


def build_dataset(
    sources,
    Ts: float = 0.3,
    source_preference: dict[str, int] = DEFAULT_SOURCE_PREFERENCE,
    fuel: str = "auto",
    max_gap_s: float = 1.0,
    idle_rpm: float | None = None,
    idle_tol_rpm: float = 50.0,
    idle_min_s: float = 3.0,
    cycle_s: float = 1800.0,
    min_cycle_s: float = 60.0,
    skip_damaged: bool = False,
) -> Dataset:
    """Build a Dataset from MCAP paths and/or iterables of (topic, log_time_ns, record) records.

    Ts [s] grid step; fuel 'auto' (the flow meter when it has valid readings, else LFE1), 'flowmeter'
    [kg/h] or 'lfe1' [L/h]; max_gap_s [s] the longest stretch a model signal is held; idle_rpm,
    idle_tol_rpm [rpm], idle_min_s [s] the operating point; cycle_s, min_cycle_s [s] the drive cycles.
    A file's damaged chunk (failing its CRC) raises FuelidError naming the bytes; with skip_damaged it is
    left out (a gap in the data) and noted. Raises FuelidError when engine speed, torque or the fuel
    signal is missing. Method: module docstring.
    """
    if Ts <= 0:
        raise FuelidError(f"sampling interval must be positive, got {Ts} s")
    if fuel not in ("auto", *FUEL_SIGNALS):
        raise FuelidError(f"fuel must be auto, flowmeter or lfe1, got {fuel!r}")
    damaged = [] if skip_damaged else None
    chosen, used = _choose(_collect(_records(sources, damaged)), source_preference)
    if fuel == "auto":
        fuel = "flowmeter" if FUEL_SIGNALS["flowmeter"][0] in chosen else "lfe1"
    fuel_name, fuel_unit = FUEL_SIGNALS[fuel]
    for name, what in [(SPEED, "engine speed"), (TORQUE_PCT, "engine torque")]:
        if name not in chosen:
            raise FuelidError(f"no {what} ({name}) in the data" + _cut_files(sources))
    if fuel_name not in chosen:
        raise FuelidError(
            f"no fuel flow ({fuel_name}) in the data" + (_cut_files(sources) or (
                "" if fuel == "flowmeter" and FUEL_SIGNALS["lfe1"][0] in chosen
                else ": a gas truck's engine may not send its fuel rate (LFE1); convert its recording with the flow "
                     "meter's capture beside it, `fuelid convert LOG --flowmeter CAPTURE.flow`")))

    ts_ns = int(round(Ts * 1e9))
    t0 = min(int(ts[0]) for ts, _ in chosen.values()) // ts_ns * ts_ns  # bins start at multiples of Ts
    occupied = np.unique(np.concatenate([(ts - t0) // ts_ns for ts, _ in chosen.values()]))
    span = int(np.ceil(max_gap_s / Ts)) + 2  # hold bins + one invalid row after a gap
    k_rows = np.unique((occupied[:, None] + np.arange(span)).ravel())
    k_rows = k_rows[k_rows <= occupied[-1]]  # nothing held past the end of the data

    def grid(name, hold_s=max_gap_s):
        ts, vs = chosen[name]
        return _resample(ts, vs, k_rows, t0, ts_ns, int(hold_s * 1e9), name in AVERAGED)

    notes = [f"skipped {d}" for d in damaged or ()]
    for note in notes:
        warnings.warn(note, stacklevel=2)
    speed, pct, y = grid(SPEED), grid(TORQUE_PCT), grid(fuel_name)
    if REF_TORQUE in chosen:
        torque, torque_unit = pct * np.median(chosen[REF_TORQUE][1]) / 100.0, "Nm"
    else:
        torque, torque_unit = pct, "%"
        notes.append("EC1 (engine reference torque) never arrived: torque kept in % of reference torque")
        warnings.warn(notes[-1], stacklevel=2)
    u = np.column_stack([speed, torque])
    valid = np.isfinite(u).all(axis=1) & np.isfinite(y)

    extra = {}
    for name, (ts, vs) in chosen.items():
        if name in (SPEED, TORQUE_PCT, fuel_name):
            continue
        period = float(np.median(np.diff(ts))) * 1e-9 if len(ts) > 1 else 0.0
        extra[name] = grid(name, max(max_gap_s, 3 * period))

    if idle_rpm is None:
        idle_rpm = float(np.median(chosen[IDLE_SPEED][1])) if IDLE_SPEED in chosen else 600.0
    idle = valid & (np.abs(speed - idle_rpm) <= idle_tol_rpm)
    if VEHICLE_SPEED in extra:
        idle &= extra[VEHICLE_SPEED] < 2.0
    idle = _lasting(idle, int(np.ceil(idle_min_s / Ts)))
    if idle.any():
        u0, y0 = u[idle].mean(axis=0), float(y[idle].mean())
    else:
        u0, y0 = np.array([idle_rpm, 0.0]), 0.0
        notes.append(f"no idle samples near {idle_rpm:g} rpm: operating point set to ({idle_rpm:g} rpm, 0, 0)")
        warnings.warn(notes[-1], stacklevel=2)

    ds = Dataset(
        Ts=float(Ts), t=(t0 + k_rows * ts_ns) * 1e-9, u=u, y=y,
        input_names=(SPEED, "EngTorque"), input_units=("rpm", torque_unit),
        output_name=fuel_name, output_unit=fuel_unit, u0=u0, y0=y0, valid=valid,
        cycle=np.full(len(k_rows), -1, dtype=np.int64), extra=extra, sources=used, notes=notes,
    )
    ds.cycle = _cycles(ds.segments(), len(ds), Ts, cycle_s, min_cycle_s)
    return ds


# ---- export / import ---------------------------------------------------------------------------------

def _meta(ds: Dataset) -> dict:
    return {
        "format": "fuelid dataset v1", "Ts": ds.Ts,
        "input_names": list(ds.input_names), "input_units": list(ds.input_units),
        "output_name": ds.output_name, "output_unit": ds.output_unit,
        "u0": [float(v) for v in ds.u0], "y0": ds.y0, "sources": ds.sources, "notes": ds.notes,
        "extra": list(ds.extra),
    }


def _columns(ds: Dataset) -> dict[str, np.ndarray]:
    cols = {"t": ds.t, "valid": ds.valid.astype(float), "cycle": ds.cycle.astype(float),
            ds.input_names[0]: ds.u[:, 0], ds.input_names[1]: ds.u[:, 1], ds.output_name: ds.y}
    cols.update(ds.extra)
    return cols


def csv_sidecar(path) -> Path:
    """The metadata file beside a dataset CSV, named as CSV on the Web (W3C CSVW) names it: DATA.csv-metadata.json."""
    path = Path(path)
    return path.with_name(path.name + "-metadata.json")


def _csv_units(ds: Dataset) -> dict[str, str]:
    """Column name → unit of every column the CSV writes (time_utc, valid and cycle have none)."""
    units = {"time_s": "s", ds.input_names[0]: ds.input_units[0], ds.input_names[1]: ds.input_units[1],
             ds.output_name: ds.output_unit}
    dbc = signal_units()
    units.update({name: dbc[name] for name in ds.extra if name in dbc})
    return units


def _write_csv(ds: Dataset, path: Path) -> None:
    """A plain CSV a spreadsheet opens (one header row, 'name [unit]'; time as seconds since the first sample
    and as ISO 8601 UTC), and its CSVW metadata sidecar with the units, the start time and fuelid's metadata."""
    cols = _columns(ds)
    t0 = float(ds.t[0]) if len(ds.t) else 0.0
    units = _csv_units(ds)
    cols = {"time_s": ds.t - t0, **{k: v for k, v in cols.items() if k != "t"}}
    stamps = (np.datetime64("1970-01-01T00:00:00", "ms") + np.round(ds.t * 1e3).astype("timedelta64[ms]"))
    iso = [f"{s}Z" for s in stamps.astype(str)]
    names = list(cols)
    header = ["time_s [s]", "time_utc"] + [f"{n} [{units[n]}]" if n in units else n for n in names[1:]]
    with open(path, "w", newline="") as f:
        f.write(",".join(header) + "\n")
        data = np.column_stack(list(cols.values()))
        for stamp, row in zip(iso, data):
            values = ["" if np.isnan(v) else repr(float(v)) for v in row]
            f.write(",".join([values[0], stamp, *values[1:]]) + "\n")
    columns = [{"name": "time_s", "titles": header[0], "datatype": "number", "schema:unitText": "s",
                "dc:description": "time since the first sample"},
               {"name": "time_utc", "titles": "time_utc", "datatype": "dateTime",
                "dc:description": "bin start time, UTC (the log clock)"}]
    columns += [{"name": n, "titles": title, "datatype": "number", **({"schema:unitText": units[n]} if n in units else {})}
                for n, title in zip(names[1:], header[2:])]
    sidecar = {"@context": "http://www.w3.org/ns/csvw", "url": path.name,
               "tableSchema": {"columns": columns}, "fuelid": {**_meta(ds), "t0": t0}}
    csv_sidecar(path).write_text(json.dumps(sidecar, indent=1) + "\n")


def _read_csv(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The metadata and the columns (t on the log clock) of a CSV written by _write_csv."""
    sidecar = csv_sidecar(path)
    try:
        meta = json.loads(sidecar.read_text())["fuelid"]
    except FileNotFoundError:
        raise FuelidError(f"{path}: its metadata file {sidecar.name} is missing beside it") from None
    except (ValueError, KeyError, TypeError) as e:
        raise FuelidError(f"{sidecar}: not a fuelid dataset metadata file ({e})") from None
    with open(path) as f:
        titles = f.readline().rstrip("\n").split(",")
    names = [title.split(" [", 1)[0] for title in titles]
    data = np.genfromtxt(path, delimiter=",", skip_header=1, ndmin=2,
                         usecols=[i for i, n in enumerate(names) if n != "time_utc"])
    cols = dict(zip([n for n in names if n != "time_utc"], data.T))
    cols["t"] = float(meta["t0"]) + cols.pop("time_s")
    return meta, cols


def save_dataset(ds: Dataset, path) -> Path:
    """Write ds to .csv (a header row of 'name [unit]', then one row per sample, NaN empty; time as time_s
    since the first sample and time_utc in ISO 8601; the metadata in the CSVW sidecar DATA.csv-metadata.json)
    or .mat (scipy.io.savemat: Ts, t, u, y, u0, y0, valid, cycle, names, units and a struct `extra` whose
    field names are the signal names with '.' → '_')."""
    path = Path(path)
    if path.suffix == ".csv":
        _write_csv(ds, path)
    elif path.suffix == ".mat":
        meta = _meta(ds)
        savemat(path, {
            "Ts": ds.Ts, "t": ds.t, "u": ds.u, "y": ds.y, "u0": ds.u0, "y0": ds.y0,
            "valid": ds.valid, "cycle": ds.cycle,
            "input_names": np.array(ds.input_names, dtype=object),
            "input_units": np.array(ds.input_units, dtype=object),
            "output_name": ds.output_name, "output_unit": ds.output_unit,
            "meta_json": json.dumps(meta),
            "extra": {k.replace(".", "_"): v for k, v in ds.extra.items()},
        }, oned_as="column")
    else:
        raise FuelidError(f"{path}: output must end in .csv or .mat")
    return path


def load_dataset(path) -> Dataset:
    """Read back a file written by save_dataset (.csv with its sidecar, or .mat)."""
    path = Path(path)
    if path.suffix == ".csv":
        meta, cols = _read_csv(path)
    elif path.suffix == ".mat":
        m = loadmat(path, squeeze_me=True, chars_as_strings=True)
        meta = json.loads(str(m["meta_json"]))
        ex = m["extra"]
        extra_mat = {n: np.atleast_1d(ex[n].item()).astype(float) for n in (ex.dtype.names or ())}
        cols = {"t": np.atleast_1d(m["t"]), "valid": np.atleast_1d(m["valid"]), "cycle": np.atleast_1d(m["cycle"]),
                meta["input_names"][0]: np.atleast_2d(m["u"])[:, 0], meta["input_names"][1]: np.atleast_2d(m["u"])[:, 1],
                meta["output_name"]: np.atleast_1d(m["y"])}
        cols.update({k: extra_mat[k.replace(".", "_")] for k in meta["extra"]})
    else:
        raise FuelidError(f"{path}: dataset files end in .csv or .mat")
    fixed = {"t", "valid", "cycle", *meta["input_names"], meta["output_name"]}
    return Dataset(
        Ts=float(meta["Ts"]), t=np.asarray(cols["t"], float),
        u=np.column_stack([cols[n] for n in meta["input_names"]]).astype(float),
        y=np.asarray(cols[meta["output_name"]], float),
        input_names=tuple(meta["input_names"]), input_units=tuple(meta["input_units"]),
        output_name=meta["output_name"], output_unit=meta["output_unit"],
        u0=np.asarray(meta["u0"], float), y0=float(meta["y0"]),
        valid=np.asarray(cols["valid"]).astype(bool), cycle=np.asarray(cols["cycle"]).astype(np.int64),
        extra={k: np.asarray(v, float) for k, v in cols.items() if k not in fixed},
        sources=meta["sources"], notes=meta["notes"],
    )
