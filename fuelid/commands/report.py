"""fuelid report: the diagnosis of a model on recordings as one self-contained HTML file (ident.report)."""
import json
from pathlib import Path

import numpy as np

from fuelid.commands.dataset import add_dataset_arguments, build_for_models
from fuelid.commands.diagnose import PRELOAD, add_jobs_argument, add_settings_arguments, diagnosed, settings_from
from fuelid.errors import FuelidError
from fuelid.ident.modelfile import load_model
from fuelid.ident.report import write_report
from fuelid.logger.mcap_log import read_metadata
from fuelid.parallel import jobs
from fuelid.paths import readable_file
from fuelid.sim.vecto import read_engine


def add_arguments(p):
    p.add_argument("inputs", nargs="+", metavar="FILE",
                   help="MODEL.json, then optional AFTER.json models (refitted with effects added), then the MCAP "
                        "recordings: model files end in .json, anything else is a recording")
    p.add_argument("-o", "--output", required=True, metavar="REPORT.html", help="HTML file to write")
    p.add_argument("--title", metavar="T", help="page title (default: 'fuelid diagnosis report — TRUCK')")
    add_settings_arguments(p)
    p.add_argument("--diagnosis", metavar="DIAGNOSIS.json",
                   help="use this saved `fuelid diagnose --json` result of MODEL on the same recordings instead of "
                        "diagnosing again")
    p.add_argument("--max-points", type=int, default=6000, metavar="N",
                   help="points per curve before min/max decimation (default 6000)")
    add_dataset_arguments(p)
    add_jobs_argument(p)


def truck_name(paths) -> str | None:
    """The truck named in the recordings' fuelid MCAP metadata (VIN when seen), several joined by ', '."""
    names = []
    for p in paths:
        try:
            name = read_metadata(p).get("fuelid", {}).get("truck")
        except Exception:  # noqa: BLE001 — a file without readable metadata just names no truck
            name = None
        if name and name not in names:
            names.append(name)
    return ", ".join(names) or None


def saved_diagnosis(path: str, model_path: str, data_paths: list[str]) -> dict:
    """A saved `fuelid diagnose --json` result, checked to be of this model on these recordings."""
    try:
        diagnosis = json.loads(Path(path).read_text())
        of = (diagnosis["model"].get("file"), diagnosis["data"].get("files"))
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise FuelidError(f"--diagnosis {path}: not a `fuelid diagnose --json` result ({exc})") from exc
    if of != (model_path, data_paths):
        raise FuelidError(f"--diagnosis {path}: it diagnosed {of[0]} on {', '.join(of[1] or [])}, "
                          f"not {model_path} on {', '.join(data_paths)}")
    return diagnosis


def truth_beside(path: str) -> dict | None:
    """The simulator's truth file (`fuelid simulate`'s X.truth.json) of recording `path`: X.truth.json beside it for
    X.mcap, X.log.gz or X.log; None when there is none or it is unreadable."""
    p = Path(path)
    stem = p.name
    for suffix in (".mcap", ".log.gz", ".log"):
        if stem.endswith(suffix):
            stem = stem[: -len(suffix)]
            break
    try:
        return json.loads((p.parent / f"{stem}.truth.json").read_text())
    except (OSError, ValueError):
        return None


def true_engine_map(data_paths, torque_unit: str):
    """The true steady-state fuel map (n [rpm], T [torque_unit]) → fuel [L/h] of the VECTO engine the simulator ran
    the recordings with (the engine its truth file names, the same in all), over the torque the bus reports (the
    indicated torque; the map is charted over the flywheel torque, indicated minus friction, friction = minus the
    motoring torque; the reference torque the largest full-load torque: sim.mapfuel); None when they are not
    simulated with one."""
    truths = [truth_beside(p) for p in data_paths]
    engines = {(t.get("config") or {}).get("engine") for t in truths if t and t.get("fuel_truth", {}).get("name") == "map"}
    if len(engines) != 1 or None in engines or None in truths:
        return None
    engine = read_engine(engines.pop())
    scale = engine.max_torque_nm / 100.0 if torque_unit == "%" else 1.0
    return lambda n, T: engine.fuel_g_h(n, np.asarray(T) * scale + engine.motoring(n)) / (1000.0 * engine.fuel_density_kg_l)


def run(args) -> int:
    model_paths = [p for p in args.inputs if p.endswith(".json")]
    data_paths = [p for p in args.inputs if not p.endswith(".json")]
    if not model_paths or not data_paths:
        raise FuelidError("give a model file (.json), optionally AFTER models (.json), and recordings (.mcap)")
    if args.diagnosis:
        readable_file(args.diagnosis)
    if args.max_points < 100:
        raise FuelidError(f"--max-points must be at least 100, got {args.max_points}")
    model, *after = [load_model(p) for p in model_paths]
    ds = build_for_models(args, data_paths, list(zip(model_paths, [model, *after])))
    if args.diagnosis:
        diagnosis = saved_diagnosis(args.diagnosis, model_paths[0], data_paths)
        verdict = diagnosis["verdict"]
    else:
        with jobs(args.jobs, PRELOAD):
            diagnosis = diagnosed(model, ds, settings_from(args))
        verdict = diagnosis.verdict
    out = write_report(args.output, model, ds, diagnosis=diagnosis, label=Path(model_paths[0]).name,
                       after=[(Path(p).name, m) for p, m in zip(model_paths[1:], after)],
                       title=args.title, truck=truck_name(data_paths), files=data_paths,
                       max_points=args.max_points, true_map=true_engine_map(data_paths, model.input_units[1]))
    print(f"{out}: {out.stat().st_size / 1e6:.1f} MB; {verdict}")
    return 0
