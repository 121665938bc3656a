"""fuelid status: what the running logger daemon reports in its status file."""
import time

from fuelid.errors import FuelidError
from fuelid.logger.config import LoggerConfig
from fuelid.logger.daemon import read_status
from fuelid.output import print_json

STALE_S = 5.0  # a status older than this means the daemon is not running (it rewrites it every second)


def add_arguments(p):
    p.add_argument("--status-file", metavar="FILE", help="the daemon's status file (default: from --config, else ./fuelid-logs/status.json)")
    p.add_argument("--config", metavar="FILE.toml", help="the daemon's settings file, to find its status file")
    p.add_argument("--json", action="store_true", help="print the status as JSON")


def run(args) -> int:
    path = LoggerConfig.load(args.config, status_file=args.status_file).status_file
    try:
        s = read_status(path)
    except FileNotFoundError:
        raise FuelidError(f"no status file {path}: is `fuelid log` running with this output directory?") from None
    except (OSError, ValueError, KeyError) as exc:
        raise FuelidError(f"unreadable status file {path}: {exc}") from None
    running = s["state"] == "running" and s["age_s"] <= STALE_S
    if args.json:
        print_json({**s, "running": running})
        return 0 if running else 1
    state = "running" if running else ("stopped" if s["state"] == "stopped" else f"not running (status {s['age_s']:.0f} s old)")
    bus = s["bus"]
    lines = [
        f"fuelid log: {state}, pid {s['pid']}, up {_duration(s['uptime_s'])}",
        f"bus:        {bus['interface']} {bus['channel']} {bus['state']}, {bus['connects']} connect(s)"
        + (f", last error: {bus['last_error']}" if bus["last_error"] else ""),
        f"frames:     {s['frames']} ({s['frames_per_s']:.0f}/s), drops {s['drops']}, decode errors {s['decode_errors']}, error frames {s['error_frames']}",
        f"file:       {s['file'] or '(not writing)'}; {s['files_closed']} closed",
    ]
    serial = s["serial"]
    lines.append("serial:     none" if serial is None else
                 f"serial:     {serial['port']} {serial['state']}, {serial['lines']} lines, {serial['invalid']} invalid, {serial['disconnects']} disconnects")
    lines.append(f"truck:      {s['truck']}" + ("" if s["vin"] else " (no VIN seen)"))
    ident = s.get("identify")
    if ident:
        fit = ident.get("fit_simulation_pct")
        lines.append(f"identify:   {ident['state']}, {ident.get('updates', 0)} updates, {ident['errors']} errors"
                     + ("" if fit is None else f", running fit {fit:.1f} %") + f"; snapshot {ident['snapshot']}")
    upload = s.get("upload")
    if upload:
        lines.append(f"upload:     {upload['queued']} queued, {upload['uploaded']} uploaded, {upload['rejected']} refused"
                     + (f"; last error: {upload['last_error']}" if upload["last_error"] else ""))
        if upload.get("journal_error"):
            lines.append(f"  now: upload journal: {upload['journal_error']}")
        if upload.get("journal_set_aside"):
            lines.append(f"  damaged upload journal set aside: {upload['journal_set_aside']}")
    if s["faults"]:
        lines.append("faults:     " + ", ".join(f"{k} {v}" for k, v in s["faults"].items())
                     + "".join(f"\n  now: {k}: {v}" for k, v in s["faults_active"].items()))
    print("\n".join(lines))
    return 0 if running else 1


def _duration(seconds: float) -> str:
    return time.strftime("%H:%M:%S", time.gmtime(seconds)) if seconds < 86400 else f"{seconds / 86400:.1f} d"
