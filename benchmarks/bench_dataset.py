"""Dataset build from MCAP: the column-wise, bin-by-bin build against the record-by-record one, in one run.

    .venv/bin/python benchmarks/bench_dataset.py [--hours 70] [--repeat 1] [--json]

Data: the shipped 1.5 h trip (replay_logs/diesel_ident_90min.log.gz) converted by `fuelid convert` (every
channel, /can/raw included), and a long recording: that trip's decoded messages (/j1939 only) repeated with
shifted log times into 1.5 h files until --hours, built in one call as one truck's files; both made once
into benchmarks/.cache/dataset/ (git-ignored).

Each build runs in a fresh process (imports excluded from the time), which reports its CPU time, wall time
and peak RSS (getrusage ru_maxrss, imports included: about 100 MB). The peer is the record-by-record build
the dataset used before (one Python dict per decoded message: `read_messages` → `build_dataset(records)`),
run on the 1.5 h trip only — at ~380 MB per hour of data it cannot hold a long recording. Both give the
same Dataset (checked here, and bit for bit in tests/ident/test_dataset_mcap.py).
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


def converted_trip() -> Path:
    out = CACHE / "diesel_ident_90min.mcap"
    if not out.exists():
        CACHE.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(".part.mcap")
        subprocess.run([sys.executable, "-m", "fuelid.cli", "convert", str(TRIP), "-o", str(tmp), "--json"],
                       check=True, stdout=subprocess.DEVNULL, cwd=REPO)
        tmp.rename(out)
    return out


def long_recording(trip: Path, hours: float) -> list[Path]:
    """The trip's /j1939 messages in 1.5 h files with log times shifted by whole trip lengths, up to `hours`."""
    import foxglove
    from foxglove.mcap import MCAPCompression, MCAPWriteOptions

    from fuelid.logger.mcap_log import read_chunks
    from fuelid.logger.mcap_log import _chunk_messages  # the records of one chunk, as read_messages walks them

    topics = {f"/j1939/{m}" for m in ("EEC1", "EEC2", "EEC3", "LFE1", "CCVS1", "ETC2", "EC1", "AMB", "ET1",
                                     "LFC1", "HRLFC", "ERC1", "FD", "DPFC1", "HOURS")}
    messages = [m for ids, data in read_chunks(trip, topics) for m in _chunk_messages(data, ids)]
    first, last = messages[0][1], max(m[1] for m in messages)
    length = (last - first) // 10**9 * 10**9 + 60 * 10**9  # a minute's gap between the files
    files = []
    for i in range(int(round(hours * 3600e9 / length))):
        path = CACHE / f"long_{i:03d}.mcap"
        files.append(path)
        if path.exists():
            continue
        context = foxglove.Context()
        writer = foxglove.open_mcap(path.with_suffix(".part"), allow_overwrite=True, context=context,
                                    writer_options=MCAPWriteOptions(compression=MCAPCompression.Zstd, profile=""))
        channels = {t: foxglove.Channel(t, message_encoding="json", context=context) for t in sorted(topics)}
        for topic, log_time, data in messages:
            channels[topic].log(data, log_time=log_time + i * length)
        writer.close()
        path.with_suffix(".part").rename(path)
    return files


def child(mode: str, paths: list[str]) -> None:
    """Build once and print the cost as JSON (runs in its own process)."""
    import warnings

    import numpy as np

    from fuelid.ident.dataset import build_dataset
    from fuelid.logger.mcap_log import read_messages

    warnings.simplefilter("ignore", UserWarning)
    topics = ["/flowmeter"] + [f"/j1939/{m}" for m in
                               ("EEC1", "EEC2", "EEC3", "LFE1", "CCVS1", "ETC2", "EC1", "VI", "AMB", "ET1", "LFC1",
                                "HRLFC", "ERC1", "FD", "DPFC1", "HOURS")]
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    c0, w0 = time.process_time(), time.perf_counter()
    if mode == "columns":
        ds = build_dataset(paths)
    else:
        ds = build_dataset([r for p in paths for r in read_messages(p, topics)])
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    digest = float(np.nansum(ds.u) + np.nansum(ds.y) + sum(np.nansum(v) for v in ds.extra.values()))
    print(json.dumps({"mode": mode, "cpu_s": cpu, "wall_s": wall, "samples": len(ds),
                      "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "rss_after_imports_mb": rss0, "digest": digest, "extras": len(ds.extra)}))


def run(mode: str, paths: list[Path]) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", mode, *map(str, paths)], check=True,
                         capture_output=True, text=True, cwd=REPO)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=70.0, help="length of the long recording [h] (0: skip it)")
    ap.add_argument("--repeat", type=int, default=1, help="builds per case; the fastest counts")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args.child[0], args.child[1:])

    trip = converted_trip()
    load_before = os.getloadavg()
    best = {}
    for _ in range(args.repeat):  # interleaved, so a burst of other work hits both alike
        for mode in ("records", "columns"):
            r = run(mode, [trip])
            if mode not in best or r["cpu_s"] < best[mode]["cpu_s"]:
                best[mode] = r
    old, new = best["records"], best["columns"]
    if old["digest"] != new["digest"] or old["samples"] != new["samples"]:
        raise SystemExit("bench_dataset: the two builds differ")
    summary = {"trip_mcap_mb": trip.stat().st_size / 1e6, "records": old, "columns": new,
               "cpu_speedup": old["cpu_s"] / new["cpu_s"], "wall_speedup": old["wall_s"] / new["wall_s"],
               "rss_ratio": old["peak_rss_mb"] / new["peak_rss_mb"], "load_average_before": load_before}
    if args.hours:
        files = long_recording(trip, args.hours)
        long = run("columns", files)
        summary["long"] = {"files": len(files), "hours": len(files) * 1.5,
                           "mcap_mb": sum(f.stat().st_size for f in files) / 1e6, **long}
    summary["load_average_after"] = os.getloadavg()
    if args.json:
        print(json.dumps(summary, indent=1))
        return
    print(f"1.5 h trip ({summary['trip_mcap_mb']:.0f} MB MCAP, {new['samples']} samples), load average "
          f"{load_before[0]:.1f} before, {summary['load_average_after'][0]:.1f} after")
    print(f"{'build':>22} {'CPU s':>7} {'wall s':>7} {'peak RSS MB':>11}")
    for name, r in (("record by record", old), ("column-wise, binned", new)):
        print(f"{name:>22} {r['cpu_s']:>7.2f} {r['wall_s']:>7.2f} {r['peak_rss_mb']:>11.0f}")
    print(f"speed-up {summary['cpu_speedup']:.2f}× CPU, {summary['wall_speedup']:.2f}× wall; peak RSS "
          f"{summary['rss_ratio']:.2f}× smaller (imports ≈ {new['rss_after_imports_mb']:.0f} MB)")
    if args.hours:
        lg = summary["long"]
        print(f"long: {lg['files']} files, {lg['hours']:.1f} h ({lg['mcap_mb']:.0f} MB, /j1939 only), "
              f"{lg['samples']} samples: {lg['cpu_s']:.1f} CPU s ({lg['cpu_s'] / lg['hours']:.2f} s per hour of "
              f"data), peak RSS {lg['peak_rss_mb']:.0f} MB")


if __name__ == "__main__":
    main()
