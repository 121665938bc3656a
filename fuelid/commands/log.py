"""fuelid log: the in-cab logger daemon (CAN bus + flow meter -> rotated, crash-safe MCAP files)."""
import logging
import signal

from fuelid.ident.live import LiveEstimator, live_estimator
from fuelid.logger.config import LoggerConfig
from fuelid.logger.daemon import Daemon


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
    p.add_argument("--identify", action="store_true", default=None,
                   help="run the online estimator on the logged stream: /ident/prediction, /ident/residual and "
                        "/ident/parameters channels, DIR/model.json snapshots")
    p.add_argument("--model", dest="identify_model", metavar="PRIOR.json",
                   help="--identify: model to start from (e.g. a fleet model); default from scratch")
    p.add_argument("--orders", dest="identify_orders", metavar="paper|SPEC",
                   help="--identify from scratch: model orders as for fuelid identify (default paper)")
    p.add_argument("--method", dest="identify_method", choices=["rpem", "kalman"],
                   help="--identify: recursive prediction error (default) or Kalman random-walk fuel gain "
                        "(needs --model)")
    p.add_argument("--forgetting", dest="identify_forgetting", type=float, metavar="LAMBDA",
                   help="--identify: constant forgetting factor λ in (0, 1] (default 0.9995 from a model, "
                        "growing to 1 from scratch)")
    p.add_argument("--snapshot-s", type=float, metavar="S",
                   help="--identify: write DIR/model.json every S seconds and at shutdown (default 300)")
    p.add_argument("--replay-speed", type=float, metavar="X",
                   help="--identify: the bus carries a replay at X times real time (fuelid replay --speed X); "
                        "default 1")
    p.add_argument("--upload-server", metavar="URL",
                   help="upload every closed file to this fleet server (fuelid serve), queued across restarts")
    p.add_argument("--upload-token-file", metavar="FILE", help="the truck's fleet token (default: $FUELID_TOKEN)")
    p.add_argument("--delete-after-upload", action="store_true", default=None,
                   help="delete a local file once the server has confirmed it (sha256 and size)")
    p.add_argument("-q", "--quiet", action="store_true", help="log warnings only")


def run(args) -> int:
    overrides = {k: getattr(args, k) for k in (
        "interface", "channel", "bitrate", "listen_only", "serial_port", "serial_baudrate", "flow_gain",
        "flow_offset", "output_dir", "rotate_s", "rotate_mb", "min_free_mb", "status_file", "truck", "identify",
        "identify_model", "identify_orders", "identify_method", "identify_forgetting", "snapshot_s", "replay_speed",
        "upload_server", "upload_token_file", "delete_after_upload")}
    config = LoggerConfig.load(args.config, **overrides)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format="%(asctime)s %(levelname)s %(message)s")
    logging.getLogger("can").setLevel(logging.WARNING)  # python-can says "Created a socket" at each reconnect
    daemon = Daemon(config, estimator(config))
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: daemon.stop())
    daemon.run()
    return 0


def estimator(config: LoggerConfig) -> LiveEstimator | None:
    """The online estimator the identify settings ask for (None when off), for the daemon to run."""
    if not config.identify:
        return None
    return live_estimator(model=config.identify_model, orders=config.identify_orders, method=config.identify_method,
                          forgetting=config.identify_forgetting, snapshot_path=config.output_dir / "model.json",
                          snapshot_every_s=config.snapshot_s, speed=config.replay_speed)
