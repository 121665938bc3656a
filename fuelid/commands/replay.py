"""fuelid replay: play recorded CAN traffic onto a python-can bus (and a flow-meter capture onto a pty)."""
import signal
import sys
import threading

import can

from fuelid.errors import FuelidError
from fuelid.logger.replay import PtyMeter, replay
from fuelid.output import print_json


def add_arguments(p):
    p.add_argument("inputs", nargs="*", metavar="FILE", help="CAN recordings, played one after another")
    p.add_argument("--interface", default="socketcan", help="python-can interface (default socketcan)")
    p.add_argument("--channel", default="vcan0", help="python-can channel (default vcan0)")
    p.add_argument("--bitrate", type=int, help="bitrate [bit/s] for interfaces that set it")
    p.add_argument("--speed", type=float, default=1.0, metavar="X", help="play X times faster than recorded (default 1)")
    p.add_argument("--loop", action="store_true", help="start again at the end, until interrupted")
    p.add_argument("--flowmeter", metavar="CAPTURE", help="flow-meter capture (.flow) to play onto a pseudo-terminal")
    p.add_argument("--pty", action="store_true", help="with --flowmeter: play it onto a pseudo-terminal (the default) and print its path")
    p.add_argument("--pty-link", metavar="LINK", help="with --flowmeter: also make LINK a symlink to the pty, a stable name for the daemon")
    p.add_argument("--json", action="store_true", help="print the timing report as JSON")


def run(args) -> int:
    if not args.inputs and not args.flowmeter:
        raise FuelidError("nothing to replay: give CAN recordings and/or --flowmeter CAPTURE")
    if (args.pty or args.pty_link) and not args.flowmeter:
        raise FuelidError("--pty needs --flowmeter CAPTURE")

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    bus = meter = None
    try:
        if args.inputs:
            options = {"bitrate": args.bitrate} if args.bitrate else {}
            try:
                bus = can.Bus(interface=args.interface, channel=args.channel, **options)
            except (can.CanError, OSError, ValueError, ImportError) as exc:
                raise FuelidError(f"cannot open {args.interface} bus {args.channel}: {exc}") from None
        if args.flowmeter:
            meter = PtyMeter(args.pty_link)
            # The daemon (or a test) reads this line to find the meter.
            print(f"flow meter on {meter.path}" + (f" ({meter.link})" if meter.link else ""), file=sys.stderr, flush=True)
        try:
            stats = replay(args.inputs, bus, capture=args.flowmeter, meter=meter, speed=args.speed, loop=args.loop,
                           should_stop=stop.is_set)
        except KeyboardInterrupt:
            return 130
    finally:
        if bus is not None:
            bus.shutdown()
        if meter is not None:
            meter.close()

    report = stats.to_dict()
    if args.json:
        print_json(report)
    else:
        print(f"sent {stats.frames} frames" + (f" and {stats.flow_lines} flow-meter lines" if args.flowmeter else "")
              + f" in {stats.duration_s:.2f} s ({stats.passes} pass{'es' if stats.passes != 1 else ''})")
        print(f"lateness: max {stats.lateness.max_s * 1e3:.2f} ms, mean {stats.lateness.mean_s * 1e3:.3f} ms, "
              f"at the end {stats.lateness.last_s * 1e3:.2f} ms")
        for key in ("skipped_error_frames", "send_errors", "flow_lines_dropped"):
            if report[key]:
                print(f"{key.replace('_', ' ')}: {report[key]}")
    return 0
