"""fuelid convert: recorded CAN logs (and a flow-meter capture) to MCAP, through the daemon's own decode path."""
import math
from pathlib import Path

import numpy as np

from fuelid.errors import FuelidError
from fuelid.logger.flowmeter import Calibration, capture_readings
from fuelid.logger.frame_block import FrameBlock
from fuelid.logger.readers import one_timeline, open_frames
from fuelid.logger.recorder import Recorder, open_writer
from fuelid.output import print_json
from fuelid.progress import progress


def add_arguments(p):
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="CAN recordings, played in the order given")
    p.add_argument("-o", "--output", required=True, metavar="OUT.mcap", help="MCAP file to write")
    p.add_argument("--flowmeter", metavar="CAPTURE", help="flow-meter capture (.flow or .flow.gz) to merge by time")
    p.add_argument("--flow-gain", type=float, default=12.5, metavar="KG_H_PER_V", help="meter calibration gain [kg/h per V] (default 12.5: 0-10 V = 0-125 kg/h)")
    p.add_argument("--flow-offset", type=float, default=0.0, metavar="KG_H", help="meter calibration offset [kg/h] (default 0)")
    p.add_argument("--truck", default="unknown", help="truck name until a VIN is seen on the bus")
    p.add_argument("--keep-damaged", action="store_true",
                   help="keep the output when an input is damaged (its frames up to the damage); without it a "
                        "damaged input is an error and no output is left")
    p.add_argument("--raw-only", action="store_true",
                   help="keep the output when no J1939 message is decoded (its frames in /can/raw only, e.g. an "
                        "11-bit OBD log); without it that is an error and no output is left")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args) -> int:
    inputs = [Path(p) for p in args.inputs]
    for path in inputs + ([Path(args.flowmeter)] if args.flowmeter else []):
        if not path.is_file():
            raise FuelidError(f"no such file: {path}")
    output = Path(args.output)
    if output.resolve() in {p.resolve() for p in inputs}:
        raise FuelidError(f"output {output} would overwrite an input")

    sources = [open_frames(p) for p in inputs]
    warnings: list[str] = []
    writer = open_writer(output, truck=args.truck, source=" ".join(str(p) for p in inputs), live=False)
    recorder = Recorder(writer)
    readings = ()
    if args.flowmeter:
        calibration = Calibration(gain_kg_h_per_v=args.flow_gain, offset_kg_h=args.flow_offset)
        readings = capture_readings(args.flowmeter, calibration)
    try:
        _record(recorder, progress(one_timeline(sources, warnings, blocks=True), desc="convert", unit="part"), readings)
        recorder.reassembler.expire(math.inf)  # transport sessions still open at the end of the input time out
    finally:
        writer.close()

    damaged = [s for s in sources if s.status == "damaged"]
    no_j1939 = not recorder.stats.decoded
    kept = (args.keep_damaged or not damaged) and (args.raw_only or not no_j1939)
    if not kept:  # nothing silently wrong: frames of a damaged input are not left behind as a good log
        output.unlink()
    summary = conversion_summary(recorder, sources, output, warnings, kept)
    if args.json:
        print_json(summary)
    else:
        print(format_summary(summary))
    if damaged and not args.keep_damaged:
        s = damaged[0]
        raise FuelidError(f"{s.path} is damaged at {s.position or 'an unknown place'} ({s.error}); no output "
                          "written: --keep-damaged keeps the frames that could be read")
    if no_j1939 and not args.raw_only:
        stats = recorder.stats
        raise FuelidError(f"no J1939/FMS message fuelid decodes in {stats.frames} frames ({stats.standard_frames} with 11-bit "
                          "identifiers, as OBD-II and other non-J1939 buses use): not a truck's FMS/J1939 recording; "
                          "no output written: --raw-only keeps the frames in /can/raw")
    return 0


def _record(recorder: Recorder, items, readings) -> None:
    """The frames (FrameBlocks and single frames, in order) and the meter readings into `recorder`, merged by
    time as heapq.merge orders them: a reading goes just before the first frame later than it."""
    readings = iter(readings)
    head = next(readings, None)
    for item in items:
        if isinstance(item, FrameBlock):
            before, row = [], 0
            while head is not None and (later := np.flatnonzero(item.t[row:] > head.t)).size:
                row += int(later[0])
                before.append((row, head))
                head = next(readings, None)
            recorder.on_block(item, before)
        else:
            while head is not None and head.t < item.timestamp:
                recorder.on_flow_reading(head)
                head = next(readings, None)
            recorder.on_message_received(item)
    while head is not None:
        recorder.on_flow_reading(head)
        head = next(readings, None)


def conversion_summary(recorder, sources, output: Path, warnings: list[str], kept: bool = True) -> dict:
    """What was read and decoded, as plain JSON-able data: per input its status (complete, truncated or
    damaged), where it ended (`position`, ``line N``/``byte N``) and why (`error`)."""
    stats = recorder.stats
    messages = {}
    for (name, sa), count in sorted(stats.decoded.items()):
        messages.setdefault(name, {})[f"0x{sa:02X}"] = count
    invalid = {}
    for (name, signal, status), count in sorted(stats.invalid.items()):
        invalid.setdefault(f"{name}.{signal}", {})[status] = count
    signals = sorted({f"{name}.{s}" for name in messages for s in recorder.decoder.signal_names(name)})
    return {
        "output": str(output) if kept else None,
        "output_bytes": output.stat().st_size if kept else 0,
        "truck": recorder.vin or "unknown",
        "inputs": [{"path": str(s.path), "format": s.format, "status": s.status, "position": s.position,
                    "error": s.error, "frames": s.frames, "skipped_lines": s.skipped} for s in sources],
        "warnings": warnings,
        "frames": stats.frames,
        "error_frames": stats.error_frames,
        "remote_frames": stats.remote_frames,
        "standard_frames": stats.standard_frames,
        "decoder": recorder.decoder.counters(),
        "transport_protocol": recorder.reassembler.counters(),
        "messages": messages,
        "signals": signals,
        "invalid_values": invalid,
        "flowmeter_readings": dict(stats.flow_readings),
    }


def format_summary(s: dict) -> str:
    if s["output"]:
        lines = [f"wrote {s['output']} ({s['output_bytes'] / 1e6:.2f} MB), truck {s['truck']}"]
    else:
        lines = ["wrote nothing (see the error below)"]
    for i in s["inputs"]:
        outcome = i["status"] if i["status"] == "complete" else f"{i['status']} at {i['position']} ({i['error']})"
        lines.append(f"  read {i['path']} [{i['format']}]: {outcome}, {i['frames']} frames, "
                     f"{i['skipped_lines']} malformed lines skipped")
    lines += [f"warning: {w}" for w in s["warnings"]]
    lines.append(f"frames: {s['frames']} ({s['error_frames']} error, {s['remote_frames']} remote, {s['standard_frames']} 11-bit)")
    lines.append("decoder: " + ", ".join(f"{k} {v}" for k, v in s["decoder"].items()))
    lines.append("transport protocol: " + ", ".join(f"{k} {v}" for k, v in s["transport_protocol"].items()))
    lines.append("messages (per source address):")
    for name, by_sa in s["messages"].items():
        lines.append(f"  {name:<6} " + "  ".join(f"SA {sa}: {n}" for sa, n in by_sa.items()))
    lines.append(f"signals decoded: {len(s['signals'])}")
    if s["invalid_values"]:
        lines.append("null values (not available / error / reserved / missing):")
        for sig, by_status in s["invalid_values"].items():
            lines.append(f"  {sig:<45} " + ", ".join(f"{k} {v}" for k, v in by_status.items()))
    if s["flowmeter_readings"]:
        lines.append("flow meter: " + ", ".join(f"{k} {v}" for k, v in s["flowmeter_readings"].items()))
    return "\n".join(lines)
