"""Dataset build from MCAP: from a converted file's message columns, against the record-by-record build and the
column-wise JSON build of the same file, in one run.

    .venv/bin/python benchmarks/bench_dataset.py [--hours 70] [--repeat 1] [--json] [--csv-only]

Data: the shipped 1.5 h trip (replay_logs/diesel_ident_90min.log.gz) converted by `fuelid convert` (every
channel, /can/raw included, and the message columns), and a long recording: that trip's decoded messages
(/j1939 JSON channels and their message columns, no /can/raw) repeated with shifted log times into 1.5 h files
until --hours, built in one call as one truck's files; both made once into benchmarks/.cache/dataset/
(git-ignored; delete it after changing the file format). Also the trip as the logger daemon writes it (frame by
frame, one-second chunks with message indexes, its message columns), read through its columns and its JSON.

Each build runs in a fresh process (imports excluded from the time), which reports its CPU time, wall time
and peak RSS (getrusage ru_maxrss, imports included: about 100 MB). The peer is the record-by-record build
the dataset used before (one Python dict per decoded message: `read_messages` → `build_dataset(records)`),
run on the 1.5 h trip only — at ~380 MB per hour of data it cannot hold a long recording; beside it the
column-wise JSON build, which files without message columns get (the same file, columns ignored), and the
commands' second build of the same file and options, read from the user cache directory (ident.datacache). All
give the same Dataset (checked here by a SHA-256 of its arrays, and bit for bit in tests/ident/).

CSV: `fuelid dataset -o x.csv`'s writer (ident.dataset.save_dataset, pyarrow's CSV writer) on the trip's Dataset,
in MB of CSV written per second of wall time and per CPU second (the best of at least 3, the metadata sidecar
included; on a loaded machine the wall time waits for a core), beside the
row-by-row writer it replaced (one Python string per value; the same content: tests/ident/test_dataset_csv.py).
Limit: ≥ 50 MB/s. `--csv-only` measures only that.
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
CACHE = REPO / "benchmarks" / ".cache" / "dataset"
TRIP = REPO / "replay_logs" / "diesel_ident_90min.log.gz"


def peak_rss_mb() -> float:
    """This process's peak RSS [MB]: VmHWM, which starts afresh at exec (ru_maxrss would carry the parent's)."""
    status = Path("/proc/self/status").read_text()
    return int(next(line.split()[1] for line in status.splitlines() if line.startswith("VmHWM:"))) / 1024


def converted_trip(name: str = TRIP.name.removesuffix(".log.gz")) -> Path:
    """replay_logs/NAME.log.gz converted by `fuelid convert`, made once into CACHE."""
    out = CACHE / f"{name}.mcap"
    if not out.exists():
        CACHE.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(".part.mcap")
        subprocess.run([sys.executable, "-m", "fuelid.cli", "convert", str(TRIP.with_name(f"{name}.log.gz")), "-o",
                        str(tmp), "--json"], check=True, stdout=subprocess.DEVNULL, cwd=REPO)
        tmp.rename(out)
    return out


def daemon_trip() -> Path:
    """The trip as the logger daemon writes it (frame by frame, one-second chunks, message columns), one file."""
    out = CACHE / "diesel_ident_90min.daemon.mcap"
    if not out.exists():
        from fuelid.logger.readers import read_frames
        from fuelid.logger.recorder import Recorder, open_writer

        CACHE.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(".part")
        writer = open_writer(tmp, source="benchmark")
        recorder = Recorder(writer)
        for msg in read_frames(TRIP):
            recorder.on_message_received(msg)
        writer.close()
        tmp.rename(out)
    return out


def long_recording(trip: Path, hours: float) -> list[Path]:
    """The trip's decoded messages (/j1939 JSON channels and their message columns, no /can/raw) in 1.5 h files
    with log times shifted by whole trip lengths, up to `hours`."""
    import foxglove
    import numpy as np
    from foxglove.mcap import MCAPCompression, MCAPWriteOptions

    from fuelid.logger.columns import MEDIA_TYPE, NAME, ColumnWriter, read_block
    from fuelid.logger.mcap_log import read_attachments, read_chunks
    from fuelid.logger.mcap_log import _chunk_messages  # the records of one chunk, as read_messages walks them
    from fuelid.logger.decode import Decoder

    topics = {f"/j1939/{m}" for m in Decoder().message_names()}
    messages = [m for ids, data in read_chunks(trip, topics) for m in _chunk_messages(data, ids)]
    rows = []
    for data in read_attachments(trip, NAME)[1]:
        b = read_block(data)
        rows += [(int(b.seq[i]), int(b.t_ns[i]), int(b.pgn[i]), int(b.sa[i]), 255, None, bytes(b.payload[i, :b.length[i]]))
                 for i in np.argsort(b.seq)]  # da and tp do not enter the dataset
    first, last = messages[0][1], max(m[1] for m in messages)
    length = (last - first) // 10**9 * 10**9 + 60 * 10**9  # a minute's gap between the files
    files = []
    for i in range(int(round(hours * 3600e9 / length))):
        path = CACHE / f"long_columns_{i:03d}.mcap"
        files.append(path)
        if path.exists():
            continue
        context = foxglove.Context()
        writer = foxglove.open_mcap(path.with_suffix(".part"), allow_overwrite=True, context=context,
                                    writer_options=MCAPWriteOptions(compression=MCAPCompression.Zstd, profile="",
                                                                    chunk_size=4 << 20, emit_message_indexes=False,
                                                                    emit_chunk_indexes=False))  # as convert
        channels = {t: foxglove.Channel(t, message_encoding="json", context=context) for t in sorted(topics)}
        for topic, log_time, data in messages:
            channels[topic].log(data, log_time=log_time + i * length)
        columns = ColumnWriter(lambda data, t0: writer.attach(log_time=t0, create_time=t0, name=NAME,
                                                              media_type=MEDIA_TYPE, data=data))
        for _, t, pgn, sa, da, tp, payload in rows:
            columns.add_message(t + i * length, pgn, sa, da, tp, payload)
        columns.flush()
        writer.close()
        path.with_suffix(".part").rename(path)
    return files


MODES = {"records": "record by record (old)", "json": "column-wise JSON", "columns": "message columns (new)",
         "cache": "cached (a command again)"}


def child(mode: str, paths: list[str]) -> None:
    """Build once and print the cost as JSON (runs in its own process)."""
    import hashlib
    import warnings

    from fuelid.ident import dataset
    from fuelid.ident.datacache import cached_dataset
    from fuelid.ident.dataset import build_dataset
    from fuelid.logger.mcap_log import read_messages

    warnings.simplefilter("ignore", UserWarning)
    topics = ["/flowmeter"] + [f"/j1939/{m}" for m in
                               ("EEC1", "EEC2", "EEC3", "LFE1", "CCVS1", "ETC2", "EC1", "VI", "AMB", "ET1", "LFC1",
                                "HRLFC", "ERC1", "FD", "DPFC1", "HOURS")]
    if mode == "json":  # the same file read as if it had no message columns (as files before them read)
        dataset.read_attachments = lambda path, name: None
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    c0, w0 = time.process_time(), time.perf_counter()
    if mode == "records":
        ds = build_dataset([r for p in paths for r in read_messages(p, topics)])
    elif mode == "cache":  # as the commands build: from the cache beside the file (primed by an earlier run)
        ds = cached_dataset(paths, {}, lambda: build_dataset(paths))
    else:
        ds = build_dataset(paths)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    digest = hashlib.sha256()
    for a in (ds.t, ds.u, ds.y, ds.valid, ds.cycle, ds.u0, *ds.extra.values()):
        digest.update(a.tobytes())
    digest.update(json.dumps([list(ds.extra), ds.sources, ds.notes, ds.y0]).encode())
    print(json.dumps({"mode": mode, "cpu_s": cpu, "wall_s": wall, "samples": len(ds),
                      "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "rss_after_imports_mb": rss0, "digest": digest.hexdigest(), "extras": len(ds.extra)}))


def run(mode: str, paths: list[Path]) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", mode, *map(str, paths)], check=True,
                         capture_output=True, text=True, cwd=REPO)
    return json.loads(out.stdout.strip().splitlines()[-1])


def row_writer(ds, path: Path) -> None:
    """The row-by-row CSV writer the dataset used before (the peer): repr(float) per value, NaN empty."""
    import numpy as np

    cols = [ds.t - ds.t[0], ds.valid.astype(float), ds.cycle.astype(float), ds.u[:, 0], ds.u[:, 1], ds.y,
            *ds.extra.values()]
    stamps = np.datetime64("1970-01-01T00:00:00", "ms") + np.round(ds.t * 1e3).astype("timedelta64[ms]")
    with open(path, "w", newline="") as f:
        f.write("header\n")
        for stamp, row in zip([f"{s}Z" for s in stamps.astype(str)], np.column_stack(cols)):
            values = ["" if np.isnan(v) else repr(float(v)) for v in row]
            f.write(",".join([values[0], stamp, *values[1:]]) + "\n")


def csv_speed(trip: Path, repeat: int) -> dict:
    """MB/s of the CSV writer and of the row-by-row writer on the trip's Dataset (best of `repeat`)."""
    import tempfile

    from fuelid.ident.dataset import build_dataset, save_dataset

    ds = build_dataset([trip])
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, write in (("pyarrow", save_dataset), ("rows", row_writer)):
            best, cpu = None, None
            for _ in range(repeat):
                path = Path(tmp) / f"{name}.csv"
                t0, c0 = time.perf_counter(), time.process_time()
                write(ds, path)
                wall, c = time.perf_counter() - t0, time.process_time() - c0
                best, cpu = (wall, c) if best is None else (min(best, wall), min(cpu, c))
            mb = path.stat().st_size / 1e6
            out[name] = {"wall_s": best, "cpu_s": cpu, "mb": mb, "mb_per_s": mb / best, "mb_per_cpu_s": mb / cpu}
    return {**out, "speedup": out["rows"]["wall_s"] / out["pyarrow"]["wall_s"], "samples": len(ds),
            "load_average": os.getloadavg()}


def print_csv(c: dict) -> None:
    print(f"CSV of the trip ({c['samples']} samples): pyarrow writer {c['pyarrow']['mb']:.1f} MB in "
          f"{c['pyarrow']['wall_s']:.2f} s = {c['pyarrow']['mb_per_s']:.0f} MB/s wall, "
          f"{c['pyarrow']['mb_per_cpu_s']:.0f} MB per CPU s (limit 50 MB/s); row-by-row writer "
          f"{c['rows']['mb_per_s']:.1f} MB/s; {c['speedup']:.1f}× faster (load average {c['load_average'][0]:.1f})")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=70.0, help="length of the long recording [h] (0: skip it)")
    ap.add_argument("--repeat", type=int, default=1, help="builds per case; the fastest counts")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--csv-only", action="store_true", help="measure only the CSV writer")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args.child[0], args.child[1:])

    trip = converted_trip()
    if args.csv_only:
        c = csv_speed(trip, max(args.repeat, 3))
        print(json.dumps(c, indent=1)) if args.json else print_csv(c)
        return
    load_before = os.getloadavg()
    best = {}
    run("cache", [trip])  # writes the cache (or finds it)
    for _ in range(args.repeat):  # interleaved, so a burst of other work hits all alike
        for mode in MODES:
            r = run(mode, [trip])
            if mode not in best or r["cpu_s"] < best[mode]["cpu_s"]:
                best[mode] = r
    daemon = daemon_trip()
    from_daemon = {mode: run(mode, [daemon]) for mode in ("columns", "json")}
    old, new = best["records"], best["columns"]
    if len({(r["digest"], r["samples"]) for r in [*best.values(), *from_daemon.values()]}) != 1:
        raise SystemExit("bench_dataset: the builds differ")
    summary = {"trip_mcap_mb": trip.stat().st_size / 1e6, **best,
               "cpu_speedup": old["cpu_s"] / new["cpu_s"], "wall_speedup": old["wall_s"] / new["wall_s"],
               "json_cpu_speedup": best["json"]["cpu_s"] / new["cpu_s"],
               "rss_ratio": old["peak_rss_mb"] / new["peak_rss_mb"], "load_average_before": load_before,
               "daemon_file": {"mcap_mb": daemon.stat().st_size / 1e6, **from_daemon}}
    if args.hours:
        files = long_recording(trip, args.hours)
        long = run("columns", files)
        summary["long"] = {"files": len(files), "hours": len(files) * 1.5,
                           "mcap_mb": sum(f.stat().st_size for f in files) / 1e6, **long}
    summary["csv"] = csv_speed(trip, max(args.repeat, 3))
    summary["load_average_after"] = os.getloadavg()
    if args.json:
        print(json.dumps(summary, indent=1))
        return
    print(f"1.5 h trip ({summary['trip_mcap_mb']:.1f} MB MCAP, {new['samples']} samples), load average "
          f"{load_before[0]:.1f} before, {summary['load_average_after'][0]:.1f} after")
    print(f"{'build':>26} {'CPU s':>7} {'wall s':>7} {'peak RSS MB':>11}")
    for mode, name in MODES.items():
        r = best[mode]
        print(f"{name:>26} {r['cpu_s']:>7.2f} {r['wall_s']:>7.2f} {r['peak_rss_mb']:>11.0f}")
    print(f"speed-up vs record by record {summary['cpu_speedup']:.1f}× CPU, {summary['wall_speedup']:.1f}× wall "
          f"(vs column-wise JSON {summary['json_cpu_speedup']:.1f}× CPU); peak RSS {summary['rss_ratio']:.2f}× "
          f"smaller (imports ≈ {new['rss_after_imports_mb']:.0f} MB); the same Dataset (SHA-256 of its arrays); "
          f"cached {old['cpu_s'] / best['cache']['cpu_s']:.0f}× record by record")
    d = summary["daemon_file"]
    print(f"the daemon's file of the trip ({d['mcap_mb']:.1f} MB): message columns {d['columns']['cpu_s']:.2f} CPU s, "
          f"{d['columns']['peak_rss_mb']:.0f} MB; column-wise JSON {d['json']['cpu_s']:.2f} s, "
          f"{d['json']['peak_rss_mb']:.0f} MB ({d['json']['cpu_s'] / d['columns']['cpu_s']:.1f}×); the same Dataset")
    if args.hours:
        lg = summary["long"]
        print(f"long: {lg['files']} files, {lg['hours']:.1f} h ({lg['mcap_mb']:.0f} MB, /j1939 + columns), "
              f"{lg['samples']} samples: {lg['cpu_s']:.1f} CPU s ({lg['cpu_s'] / lg['hours']:.2f} s per hour of "
              f"data), peak RSS {lg['peak_rss_mb']:.0f} MB")
    print_csv(summary["csv"])


if __name__ == "__main__":
    main()
