"""fuelid log: the in-cab logger daemon (CAN bus + flow meter -> rotated, crash-safe MCAP files)."""
import logging
import signal

HELP = "log a CAN bus (and the flow meter) to rotated MCAP files until stopped; the in-cab daemon"


def add_arguments(p):
    p.add_argument("--config", metavar="FILE.toml", help="settings file (command-line options override it)")
    p.add_argument("--interface", help="python-can interface (default socketcan; e.g. virtual, pcan, kvaser)")
    p.add_argument("--channel", help="python-can channel (default can0)")
    p.add_argument("--bitrate", type=int, help="bitrate [bit/s]; for socketcan set with `ip link` (needs CAP_NET_ADMIN)")
    p.add_argument("--listen-only", action="store_true", default=None, help="never acknowledge or send on the bus, where the interface allows")
    p.add_argument("--serial", dest="serial_port", metavar="PORT", help="flow meter's serial port (a device, or a pyserial URL)")
    p.add_argument("--baudrate", dest="serial_baudrate", type=int, help="flow meter's baud rate (default 9600)")
    p.add_argument("--flow-gain", type=float, metavar="KG_H_PER_V", help="meter calibration gain [kg/h per V] (default 12.5)")
    p.add_argument("--flow-offset", type=float, metavar="KG_H", help="meter calibration offset [kg/h] (default 0)")
    p.add_argument("--output-dir", metavar="DIR", help="where the MCAP files go (default ./fuelid-logs)")
    p.add_argument("--rotate-s", type=float, metavar="S", help="start a new file after S seconds (default 3600)")
    p.add_argument("--rotate-mb", type=float, metavar="MB", help="... or once a file reaches MB megabytes (default 256)")
    p.add_argument("--min-free-mb", type=float, metavar="MB", help="stop writing below MB free, resume above twice that (default 32)")
    p.add_argument("--status-file", metavar="FILE", help="status JSON, replaced every second (default DIR/status.json)")
    p.add_argument("--truck", help="truck name until a VIN is seen on the bus")
    p.add_argument("-q", "--quiet", action="store_true", help="log warnings only")


def run(args) -> int:
    from logger.config import LoggerConfig
    from logger.daemon import Daemon

    overrides = {k: getattr(args, k) for k in (
        "interface", "channel", "bitrate", "listen_only", "serial_port", "serial_baudrate", "flow_gain",
        "flow_offset", "output_dir", "rotate_s", "rotate_mb", "min_free_mb", "status_file", "truck")}
    config = LoggerConfig.load(args.config, **overrides)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format="%(asctime)s %(levelname)s %(message)s")
    logging.getLogger("can").setLevel(logging.WARNING)  # python-can says "Created a socket" at each reconnect
    daemon = Daemon(config)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: daemon.stop())
    daemon.run()
    return 0
