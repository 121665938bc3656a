"""Logger daemon CPU use and frames lost at FMS load (~200 frames/s) and at a saturated 500 kbit/s bus
(~3,600 frames/s), against python-can's own logger (`python -m can.logger`: a Notifier + can.Logger
writing candump -L) on the same bus and traffic; and the daemon with online identification on
(`fuelid log --identify --model M`: the paper's diesel model, 41 parameters, RPEM on every 0.3 s bin; its
first 10 s are the estimator's warm-up, so runs of --seconds 10 measure no updates), and the online estimator
alone (CPU per decoded record and per bin, without bus or files).

    .venv/bin/python benchmarks/bench_daemon.py [--seconds 10] [--json]

Bus: python-can's `virtual` interface, in one process. Why not vcan: this machine's kernel has no CAN, and
in the VM (tests/logger/vcan.py) the CPU is emulated, so CPU figures there say nothing about real hardware.
Why not `udp_multicast` across processes: it needs msgpack and multicast routing, and would mostly measure
its own UDP and msgpack decoding. In one process each side's CPU is read per thread from
/proc/self/task/<tid>/stat: the receiver's notifier thread plus, for fuelid, the daemon's main loop
(flushes, rotation checks, status file); the sender thread's CPU is excluded. The daemon rotates its file
every third of a run, so closing files (summary, message-column attachments) is counted; it runs again
without message columns (what it wrote before them), for their cost.
"""
import argparse
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import can

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from fuelid.commands.log import estimator  # noqa: E402
from fuelid.logger.config import LoggerConfig  # noqa: E402
from fuelid.logger import daemon as daemon_module  # noqa: E402
from fuelid.logger.daemon import Daemon  # noqa: E402
from tests.logger import traffic  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")
LOADS = {"fms": 200, "saturated_500k": 3600}


def thread_cpu_s(tids) -> float:
    total = 0
    for tid in tids:
        fields = Path(f"/proc/self/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
        total += int(fields[11]) + int(fields[12])  # utime, stime
    return total / TICK


def send(channel: str, rate: float, seconds: float) -> int:
    """Send the FMS traffic mix at `rate` frames/s on an absolute schedule; returns frames sent."""
    mix = traffic.frames(5.0)
    bus = can.Bus(interface="virtual", channel=channel)
    n = int(rate * seconds)
    start = time.monotonic()
    for k in range(n):
        wait = start + k / rate - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        m = mix[k % len(mix)]
        bus.send(can.Message(arbitration_id=m.arbitration_id, data=m.data, is_extended_id=True))
    bus.shutdown()
    return n


def native_ids(*threads) -> list[int]:
    return [t.native_id for t in threads if t is not None]


def without_columns(open_writer):
    """`open_writer` whose writers write no message columns (the daemon before them)."""
    def opened(*args, **kwargs):
        writer = open_writer(*args, **kwargs)
        writer.columns = None
        return writer
    return opened


def run_fuelid(rate: float, seconds: float, out: Path, model: Path | None = None, columns: bool = True) -> dict:
    """The daemon on the virtual bus, a new file every third of the run; with `model`, online identification
    from it (--identify --model); `columns` False: without message columns."""
    config = LoggerConfig(interface="virtual", channel="bench-fuelid", output_dir=out, identify=model is not None,
                          identify_model=model, rotate_s=seconds / 3)
    if not columns:
        daemon_module.open_writer, opener = without_columns(daemon_module.open_writer), daemon_module.open_writer
    daemon = Daemon(config, estimator(config))  # as `fuelid log` wires it
    main = threading.Thread(target=daemon.run)
    main.start()
    while daemon.bus is None or daemon.bus.state != "up":
        time.sleep(0.01)
    rx_thread = daemon.bus._notifier._readers[0]
    tids = native_ids(main, rx_thread)
    cpu0 = thread_cpu_s(tids)
    sent = send("bench-fuelid", rate, seconds)
    time.sleep(0.5)  # let the receiver drain
    cpu = thread_cpu_s(tids) - cpu0
    received = daemon.sink.recorder.stats.frames
    daemon.stop()
    main.join()
    if not columns:
        daemon_module.open_writer = opener
    result = {"sent": sent, "logged": received, "lost": sent - received, "cpu_s": cpu,
              "cpu_pct_of_core": 100 * cpu / seconds}
    if model is not None:
        status = daemon.status()["identify"]
        result.update(identify_samples=status["samples"], identify_updates=status["updates"],
                      identify_rejected=status["rejected_steps"], identify_errors=status["errors"])
    return result


def estimator_cost(model: Path, seconds: float = 600.0) -> dict:
    """The online estimator alone (ident.live, no bus, no files): µs of CPU per decoded record and per 0.3 s
    bin over `seconds` of FMS-rate EEC1 (20 ms) and LFE1 (100 ms) records from a driving-like signal."""
    import math

    from fuelid.ident.live import LiveEstimator
    from fuelid.ident.modelfile import load_model

    live = LiveEstimator.from_model(load_model(model))
    live.prepare()
    records = []
    for k in range(int(seconds / 0.02)):
        t = 1000.0 + 0.02 * k
        records.append(("/j1939/EEC1", t, {"sa": 0, "EngSpeed": 1200.0 + 500.0 * math.sin(t / 7.0),
                                            "ActualEngPercentTorque": 40.0 + 30.0 * math.sin(t / 3.0)}))
        if k % 5 == 0:
            records.append(("/j1939/LFE1", t + 0.001, {"sa": 0, "EngFuelRate": 20.0 + 10.0 * math.sin(t / 3.0)}))
    cpu = time.process_time()
    for rec in records:
        live.feed(*rec)
    cpu = time.process_time() - cpu
    bins = live.est.report()["samples"]
    return {"records": len(records), "bins": bins, "updates": live.est.report()["updates"],
            "us_per_record": 1e6 * cpu / len(records), "us_per_bin": 1e6 * cpu / bins}


def paper_model(path: Path) -> Path:
    """The paper's diesel model with its noise model stabilised (tests/ident/online_data.py), torque in % (the
    traffic mix sends no EC1 reference torque), as model.json."""
    import dataclasses

    from fuelid.ident.modelfile import save_model
    from tests.ident.online_data import diesel_truth

    model = diesel_truth()
    save_model(dataclasses.replace(model, input_units=("rpm", "%"), output_unit="L/h", u0=(600.0, 0.0)), path)
    return path


def run_can_logger(rate: float, seconds: float, out: Path) -> dict:
    # What `python -m can.logger -i virtual -c CH -f out.log` runs: a Notifier feeding can.Logger.
    bus = can.Bus(interface="virtual", channel="bench-canlogger")
    logger = can.Logger(str(out / "can.log"))
    notifier = can.Notifier(bus, [logger], timeout=1.0)
    tids = native_ids(notifier._readers[0])
    cpu0 = thread_cpu_s(tids)
    sent = send("bench-canlogger", rate, seconds)
    time.sleep(0.5)
    cpu = thread_cpu_s(tids) - cpu0
    notifier.stop()
    logger.stop()
    bus.shutdown()
    logged = sum(1 for line in open(out / "can.log") if line.strip())
    return {"sent": sent, "logged": logged, "lost": sent - logged, "cpu_s": cpu, "cpu_pct_of_core": 100 * cpu / seconds}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0, help="length of each run [s]")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    results = {}
    with tempfile.TemporaryDirectory() as d:
        results["estimator_alone"] = estimator_cost(paper_model(Path(d) / "prior.json"))
    for load, rate in LOADS.items():
        with tempfile.TemporaryDirectory() as d:
            model = paper_model(Path(d) / "prior.json")
            results[load] = {"frames_per_s": rate,
                             "fuelid_log": run_fuelid(rate, args.seconds, Path(d) / "fuelid"),
                             "fuelid_log_without_columns": run_fuelid(rate, args.seconds, Path(d) / "nocolumns",
                                                                      columns=False),
                             "fuelid_log_identify": run_fuelid(rate, args.seconds, Path(d) / "identify", model),
                             "can_logger": run_can_logger(rate, args.seconds, Path(d))}
        r = results[load]
        r["cpu_ratio_fuelid_over_can_logger"] = r["fuelid_log"]["cpu_s"] / max(r["can_logger"]["cpu_s"], 1e-9)
    if args.json:
        print(json.dumps(results, indent=2))
        return 0
    print(f"{'load':<16}{'frames/s':>9}  {'fuelid log: CPU % core, lost':<30}{'no columns: CPU %, lost':<26}"
          f"{'--identify: CPU %, lost, bins':<36}{'can.logger: CPU % core, lost':<30}{'ratio':>6}")
    for load, r in results.items():
        if load == "estimator_alone":
            continue
        f, n, i, c = r["fuelid_log"], r["fuelid_log_without_columns"], r["fuelid_log_identify"], r["can_logger"]
        print(f"{load:<16}{r['frames_per_s']:>9}  {f['cpu_pct_of_core']:>6.1f} %, {f['lost']:>3} of {f['sent']:<13}"
              f"{n['cpu_pct_of_core']:>6.1f} %, {n['lost']:>3} lost{'':<11}"
              f"{i['cpu_pct_of_core']:>6.1f} %, {i['lost']:>3} lost, {i['identify_samples']:>5} bins{'':<6}"
              f"{c['cpu_pct_of_core']:>6.1f} %, {c['lost']:>3} of {c['sent']:<13}{r['cpu_ratio_fuelid_over_can_logger']:>6.2f}")
    e = results["estimator_alone"]
    print(f"online estimator alone (paper orders): {e['us_per_record']:.1f} µs CPU per decoded record, "
          f"{e['us_per_bin']:.0f} µs per 0.3 s bin ({e['updates']} updates in {e['bins']} bins): "
          f"{0.3e6 / e['us_per_bin']:,.0f}x real time")
    return 0


if __name__ == "__main__":
    sys.exit(main())
