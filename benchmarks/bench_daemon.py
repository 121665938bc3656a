"""Logger daemon CPU use and frames lost at FMS load (~200 frames/s) and at a saturated 500 kbit/s bus
(~3,600 frames/s), against python-can's own logger (`python -m can.logger`: a Notifier + can.Logger
writing candump -L) on the same bus and traffic.

    .venv/bin/python benchmarks/bench_daemon.py [--seconds 10] [--json]

Bus: python-can's `virtual` interface, in one process. Why not vcan: this machine's kernel has no CAN, and
in the VM (tests/logger/vcan.py) the CPU is emulated, so CPU figures there say nothing about real hardware.
Why not `udp_multicast` across processes: it needs msgpack and multicast routing, and would mostly measure
its own UDP and msgpack decoding. In one process each side's CPU is read per thread from
/proc/self/task/<tid>/stat: the receiver's notifier thread plus, for fuelid, the daemon's main loop
(flushes, rotation checks, status file); the sender thread's CPU is excluded.
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
from logger.config import LoggerConfig  # noqa: E402
from logger.daemon import Daemon  # noqa: E402
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


def run_fuelid(rate: float, seconds: float, out: Path) -> dict:
    config = LoggerConfig(interface="virtual", channel="bench-fuelid", output_dir=out)
    daemon = Daemon(config)
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
    return {"sent": sent, "logged": received, "lost": sent - received, "cpu_s": cpu, "cpu_pct_of_core": 100 * cpu / seconds}


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
    for load, rate in LOADS.items():
        with tempfile.TemporaryDirectory() as d:
            results[load] = {"frames_per_s": rate,
                             "fuelid_log": run_fuelid(rate, args.seconds, Path(d) / "fuelid"),
                             "can_logger": run_can_logger(rate, args.seconds, Path(d))}
        r = results[load]
        r["cpu_ratio_fuelid_over_can_logger"] = r["fuelid_log"]["cpu_s"] / max(r["can_logger"]["cpu_s"], 1e-9)
    if args.json:
        print(json.dumps(results, indent=2))
        return 0
    print(f"{'load':<16}{'frames/s':>9}  {'fuelid log: CPU % core, lost':<30}{'can.logger: CPU % core, lost':<30}{'ratio':>6}")
    for load, r in results.items():
        f, c = r["fuelid_log"], r["can_logger"]
        print(f"{load:<16}{r['frames_per_s']:>9}  {f['cpu_pct_of_core']:>6.1f} %, {f['lost']:>3} of {f['sent']:<13}"
              f"{c['cpu_pct_of_core']:>6.1f} %, {c['lost']:>3} of {c['sent']:<13}{r['cpu_ratio_fuelid_over_can_logger']:>6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
