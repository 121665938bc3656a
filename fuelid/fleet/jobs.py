"""Per-truck identification jobs and fleet-wide refits on Dask.

`identify_truck` is one job: the truck's MCAP files → dataset (ident.dataset) → the model `fuelid identify` builds by
default, through its own code path (ident.fuellag.identify_lag_chosen: the fuel binned one report period earlier
when that simulates held-out blocks better, and ident.modelchoice's engine model, the engine's map under the paper's
Box-Jenkins dynamics, when it simulates held-out blocks better, else the paper's linear model) → diagnosis
(ident.diagnosis.diagnose) → model.json, diagnosis.json and report.html (ident.report) in out_dir. It is a plain module
function of plain arguments, so Dask pickles it by reference and any worker with fuelid installed runs it.

Bounded memory: what the dataset's build, the identification (the engine model's map step holds a few N × 81
arrays), the diagnosis, its verification and the report hold grows with the samples they see, so they see bounded
samples of the truck's data: whole files, evenly spaced in time, at most IDENTIFY_HOURS of recorded time by their
summaries (`files_sample`), are read; whole drive cycles (ident.dataset's, 30 min) of those, evenly spaced, at most
IDENTIFY_HOURS of them for the model (`cycles_sample`) and DIAGNOSIS_HOURS of those for the diagnosis. A
truck-week costs a job what IDENTIFY_HOURS of files cost, whatever the hours.

Held-out evidence: the model is fitted on the truck's data (its sample: all of it, the newest file included, whenever
the data fit in IDENTIFY_HOURS) and the diagnosis runs on (a sample of) the same data, because its score tests are by
construction tests at the fitted model; what needs unseen data is measured by refits: diagnose holds candidate effects to PEM refits scored on the blocks (or trips)
each fold leaves out of the fit, and scores the model itself the same way (the diagnosis's `held_out`),
reported as metrics["held_out"] next to the in-sample metrics.

`JobRunner` runs jobs on a Dask LocalCluster of worker processes (the default: one single-threaded worker per
core) or on an existing cluster through its scheduler address. Each job limits BLAS/OpenMP to one thread, so
n workers on n cores never oversubscribe (pem's narrow N × 41 problems are slower with more BLAS threads), and
each worker imports the identification stack once when it starts, not per job. The MCAP paths must be
readable by the workers (same host, or storage shared with the cluster).
"""
from __future__ import annotations

import dataclasses
import importlib
import json
import os
import resource
import time
import uuid
import warnings
from pathlib import Path

import numpy as np
from mcap.reader import SeekingReader
from threadpoolctl import threadpool_limits

from fuelid.errors import FuelidError
from fuelid.fleet import effectlist
from fuelid.ident.dataset import Dataset, build_dataset
from fuelid.ident.diagnosis import diagnose, effects_to_add
from fuelid.ident.identify import MIN_SEGMENT_S
from fuelid.ident.fuellag import identify_lag_chosen
from fuelid.ident.modelchoice import ModelKind, identify_chosen
from fuelid.ident.modelfile import load_model, save_model
from fuelid.ident.polymodel import Structure, parse_orders
from fuelid.ident.report import write_report
from fuelid.ident.steady import data_reference
from fuelid.ident.validation import evaluate
from fuelid.output import json_safe


IDENTIFY_HOURS = 12.0  # the most data the models of one job are identified on [h]
DIAGNOSIS_HOURS = 6.0  # the most data the diagnosis and the report of one job see [h]


def evenly_spaced(seconds: np.ndarray, hours: float) -> np.ndarray:
    """Indices of k of the items lasting `seconds` [s] (in time order) at evenly spaced positions, the newest
    always among them, k the most whose total stays within `hours` [h] (at least one); all of them when they fit."""
    n, budget_s = len(seconds), 3600.0 * hours
    if seconds.sum() <= budget_s:
        return np.arange(n)

    def pick(k):
        return np.unique(np.linspace(n - 1, 0, k).round().astype(int))

    k = max(int(budget_s // max(float(np.median(seconds)), 1e-3)), 1)
    while k > 1 and seconds[pick(k)].sum() > budget_s:
        k -= 1
    return pick(k)


def cycles_sample(ds: Dataset, hours: float) -> Dataset:
    """ds itself when its drive cycles last at most `hours` [h] in all; else a Dataset of the samples of whole
    drive cycles (ds.cycle ≥ 0) chosen by `evenly_spaced`, the rest of the fields as ds's."""
    ids, counts = np.unique(ds.cycle[ds.cycle >= 0], return_counts=True)
    chosen = evenly_spaced(counts * ds.Ts, hours)
    if len(chosen) == len(ids):
        return ds
    rows = np.flatnonzero(np.isin(ds.cycle, ids[chosen]))
    return dataclasses.replace(ds, t=ds.t[rows], u=ds.u[rows], y=ds.y[rows], valid=ds.valid[rows],
                               cycle=ds.cycle[rows], extra={name: x[rows] for name, x in ds.extra.items()},
                               notes=list(ds.notes))


def recorded_span(path: str) -> tuple[int, float] | None:
    """(first message's time [ns], time its messages span [s]) of an MCAP file by its summary's statistics; None
    when it has none (a file cut before its footer, or not an MCAP file): only reading it tells."""
    try:
        with open(path, "rb") as f:
            summary = SeekingReader(f).get_summary()
    except Exception:  # noqa: BLE001 - mcap, struct and I/O errors alike: the dataset's build reports them
        return None
    stats = summary.statistics if summary is not None else None
    if stats is None or not stats.message_count:
        return None
    return stats.message_start_time, (stats.message_end_time - stats.message_start_time) / 1e9


def files_sample(paths: list[str], hours: float) -> list[int]:
    """Indices of the MCAP files a job reads: all of them when they record at most `hours` [h] in all, else
    whole files at evenly spaced positions in time (`evenly_spaced`: the newest always), by the time their
    summaries say they span. All of them when any file's span is unknown."""
    spans = [recorded_span(p) for p in paths]
    if any(s is None for s in spans):
        return list(range(len(paths)))
    order = sorted(range(len(paths)), key=lambda i: spans[i][0])
    chosen = evenly_spaced(np.array([spans[i][1] for i in order]), hours)
    return sorted(order[i] for i in chosen)


class JobError(FuelidError):
    """A truck's data cannot give a model (no files, no fuel signal, too little valid data...): one line why."""


def job_dataset(paths: list[str], fuel_lag_s: float) -> Dataset:
    """The truck's dataset, the fuel binned fuel_lag_s [s] earlier (its warnings kept in ds.notes), at most
    IDENTIFY_HOURS of its whole drive cycles (the rest let go here)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return cycles_sample(build_dataset(paths, fuel_lag_s=fuel_lag_s), IDENTIFY_HOURS)


def readable(previous_model: str | None):
    """The truck's previous model, or None when there is none or this fuelid cannot read it (a model file of an
    older format): it only warm-starts the refit and gives the previous model's metrics."""
    try:
        return load_model(previous_model) if previous_model else None
    except FuelidError:
        return None


def _write_json(path: Path, obj) -> None:
    """obj as strict JSON (NaN → null) through a temporary file renamed over path: no reader sees half a file."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(json_safe(obj), indent=1, allow_nan=False) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def _report(out: Path, model, diagnosis, ds, truck: str, files: list[str], after=()) -> tuple[str | None, str | None]:
    """(report.html path, None) by ident.report.write_report, or (None, why) when the report fails: the model
    and diagnosis are the job's product, the report only shows them. after: (label, model) refitted with effects."""
    path = out / "report.html"
    try:
        write_report(path, model, ds, diagnosis=diagnosis, after=after, truck=truck, files=files)
    except Exception as exc:  # noqa: BLE001 - a broken report must not lose the model
        return None, f"report.html not written: {_one_line(exc)}"
    return str(path), None


def identify_truck(truck: str, mcap_paths: list[str], out_dir: str, *, orders: str = "paper",
                   previous_model: str | None = None, names: list[str] | None = None) -> dict:
    """Identify and diagnose one truck's fuel model from its MCAP files, and identify it again with the effects
    the diagnosis confirmed (as `fuelid identify --effects-from` would); write out_dir/model.json (with those
    effects), out_dir/diagnosis.json (of the model without them) and out_dir/report.html (both models).

    orders: 'paper' or a SPEC as `fuelid identify --orders`. previous_model: the truck's current model.json;
    PEM starts from it when it has the same structure (a refit then needs fewer iterations) and its metrics on
    the same data (when binned with its Ts and fuel lag) are returned as previous_metrics (is the new version
    better?). names: the files' names as
    uploaded, for the model, the diagnosis and the report (default: the paths).
    Returns (JSON-ready) {"truck", "model_path", "diagnosis_path", "report_path" (None when the report failed: see warnings),
    "metrics": {"fit_percent": {simulation, prediction} [%], "rmse": {simulation, prediction} [unit],
    "cycle_fuel_error_percent": {cycle id: E, mean, rms} [%], "unit", "held_out": {"rmse_simulation" [unit],
    "cycle_fuel_error_percent": {mean, rms} [%]} or None},
    "effects_added" (the confirmed effects the stored model includes), "without_effects" (the metrics of the
    model without them, the one diagnosed; None when nothing was added), "previous_metrics" (same keys but
    held_out, or None), "n_samples" (identification samples, Ts = 0.3 s),
    "duration_s" (valid data [s]), "wall_s" and "cpu_s" (this job's wall and CPU time [s]), "phases_s" (wall time
    [s] of dataset, identify, diagnose with the held-out refits, identify with effects, write of the files and
    report), "peak_rss_mb" (the worker process's peak resident memory [MB] after each phase: its peak so far, earlier
    jobs on the worker included), "top_effect"
    (the first hidden effect the diagnosis recommends, never the engine's own map: fleet.effectlist; or None), "warnings"}. Raises JobError for unusable data, with a
    one-line message.
    """
    t_start, cpu_start = time.perf_counter(), time.process_time()
    paths = [str(p) for p in mcap_paths]
    names = list(names) if names else paths
    if not paths:
        raise JobError(f"{truck}: no recordings to identify on")
    missing = [p for p in paths if not os.path.isfile(p)]
    if missing:
        raise JobError(f"{truck}: no such recording {missing[0]}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model_path, diagnosis_path = out / "model.json", out / "diagnosis.json"
    phases, peaks = {}, {}

    def lap(name):  # wall time [s] and the process's peak memory [MB] after each phase, for the fleet-scaling sketch
        phases[name] = time.perf_counter() - t_start - sum(phases.values())
        peaks[name] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: kB

    with threadpool_limits(1):  # one BLAS/OpenMP thread: the cluster runs one job per core
        try:
            structure = Structure(**parse_orders(orders))
            read, n_files = files_sample(paths, IDENTIFY_HOURS), len(paths)
            paths, names = [paths[i] for i in read], [names[i] for i in read]
            built = {0.0: job_dataset(paths, 0.0)}  # handed over once: the lag choice holds one dataset at a time
            lap("dataset")
            previous = readable(previous_model)
            # the model `fuelid identify` builds: the fuel lag and the engine model when they simulate held-out
            # blocks better
            model, ds = identify_lag_chosen(lambda lag: built.pop(lag) if lag in built else job_dataset(paths, lag),
                                            structure, min_segment_s=MIN_SEGMENT_S, files=names, init=previous)
            lap("identify")
            sample = cycles_sample(ds, DIAGNOSIS_HOURS)
            found = diagnose(model, sample)
            lap("diagnose")
            diagnosis = found.to_json()
            effects = effects_to_add(diagnosis)
            # the kind chosen, or the engine model when the diagnosis advises the map (a linear model's diagnosis)
            kind = ModelKind.ENGINE if "engine_map" in effects else ModelKind(model.info["model_choice"]["chosen"])
            stored = identify_chosen(ds, structure, effects, kind=kind, min_segment_s=MIN_SEGMENT_S, files=names,
                                     init=previous, base=model) if effects else model
            stored.info["fuel_lag_choice"] = model.info["fuel_lag_choice"]  # the effects' data are binned so too
            lap("identify with effects")
        except FuelidError as exc:
            raise JobError(f"{truck}: {' '.join(str(exc).split())}") from None
        previous_metrics = None
        if previous is not None and abs(previous.Ts - ds.Ts) < 1e-9 and abs(previous.fuel_lag_s - ds.fuel_lag_s) < 1e-9:
            try:
                previous_metrics = evaluate(previous, ds)
            except FuelidError:  # another fuel unit or effects whose signals this data lacks: not comparable
                pass
        stored.info["steady_reference"] = data_reference(stored, ds)  # the signals the point decides (ident.steady)
        save_model(stored, model_path)
        diagnosis["data"]["files"] = names
        if len(names) < n_files:
            diagnosis["data"]["files_sample"] = (f"{len(names)} of {n_files} files, evenly spaced in time "
                                                 f"(at most {IDENTIFY_HOURS:g} h)")
        if sample is not ds:
            diagnosis["data"]["sample"] = (f"{len(np.unique(sample.cycle))} of {len(np.unique(ds.cycle[ds.cycle >= 0]))} "
                                           f"drive cycles, evenly spaced (at most {DIAGNOSIS_HOURS:g} h)")
        diagnosis["model"]["file"] = "the model without the effects it names" if effects else str(model_path)
        _write_json(diagnosis_path, diagnosis)
        after = [(f"with {', '.join(effects)}", stored)] if effects else []
        report_path, report_error = _report(out, model, found, sample, truck, names, after)
        lap("write")

    def metrics(m):
        return {"fit_percent": m["fit_percent"], "rmse": m["rmse"],
                "cycle_fuel_error_percent": m["cycle_fuel_error_percent"], "unit": ds.output_unit}

    recommended = effectlist.missing(diagnosis["candidates"])
    return json_safe({
        "truck": truck,
        "model_path": str(model_path),
        "diagnosis_path": str(diagnosis_path),
        "report_path": report_path,
        "metrics": {**metrics(stored.validation), "held_out": diagnosis["held_out"] and {
            "rmse_simulation": diagnosis["held_out"]["rmse"],
            "cycle_fuel_error_percent": diagnosis["held_out"]["cycle_fuel_error_percent"]}},
        "effects_added": effects,
        "without_effects": metrics(model.validation) if effects else None,
        "previous_metrics": previous_metrics and metrics(previous_metrics),
        "n_samples": stored.training["identification_samples"],
        "duration_s": stored.training["valid_duration_s"],
        "wall_s": time.perf_counter() - t_start,
        "cpu_s": time.process_time() - cpu_start,
        "phases_s": phases,
        "peak_rss_mb": peaks,
        "top_effect": recommended[0] if recommended else None,
        "warnings": ds.notes + list(stored.info.get("warnings", [])) + ([report_error] if report_error else []),
    })


def _warm_up() -> None:
    """Import the identification stack once per worker process (a second or more with plotly), so no job pays
    for it. Nothing on this path is numba-compiled (only the online RPEM is)."""
    for name in ("fuelid.ident.dataset", "fuelid.ident.identify", "fuelid.ident.diagnosis", "fuelid.ident.modelfile", "fuelid.ident.report"):
        importlib.import_module(name)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if isinstance(exc, FuelidError) else f"{type(exc).__name__}: {text}".rstrip(": ")


class JobRunner:
    """Identification jobs on Dask: a LocalCluster of `n_workers` processes (default one per core) with
    `threads_per_worker` threads each when scheduler is None, else the cluster at `scheduler` ("tcp://host:8786").
    A context manager; close() shuts down a LocalCluster it started (never a remote cluster)."""

    def __init__(self, scheduler: str | None = None, n_workers: int | None = None, threads_per_worker: int = 1):
        from distributed import Client, LocalCluster  # the optional [fleet] extra, slow to import

        self._cluster = None
        if scheduler is None:
            # no dashboard: several runners (tests, a server and a CLI refit) must not fight over port 8787
            self._cluster = LocalCluster(n_workers=n_workers, threads_per_worker=threads_per_worker,
                                         processes=True, dashboard_address=None)
            self.client = Client(self._cluster)
        else:
            try:
                self.client = Client(scheduler, timeout="10s")
            except OSError as exc:
                raise FuelidError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        self.client.run(_warm_up)

    def submit(self, truck: str, mcap_paths: list[str], out_dir: str, **kw):
        """A distributed.Future of identify_truck(truck, mcap_paths, out_dir, **kw). Bigger trucks get a
        higher priority: started first, the longest jobs do not end up alone at the end of a refit."""
        paths = [str(p) for p in mcap_paths]
        size = sum(os.path.getsize(p) for p in paths if os.path.isfile(p))
        return self.client.submit(identify_truck, truck, paths, str(out_dir), **kw, pure=False,
                                  key=f"identify-{truck}-{uuid.uuid4().hex[:8]}", priority=size >> 20)

    def refit_all(self, tasks: list[dict]) -> list[dict]:
        """Run identify_truck(**task) for every task on the cluster; results in the order of tasks, a failed
        truck as {"truck", "error": one line} (its exception is not raised)."""
        futures = [self.submit(**task) for task in tasks]
        results = []
        for task, future in zip(tasks, futures):
            try:
                results.append(future.result())
            except Exception as exc:  # JobError, a worker killed, a bug: reported per truck, the refit goes on
                results.append({"truck": task["truck"], "error": _one_line(exc)})
        return results

    def close(self) -> None:
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()

    def __enter__(self) -> JobRunner:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
