"""fuelid trucks: the fleet server's trucks (files, time range, latest model), or one truck's files and models."""
import datetime

from fuelid.commands.upload import add_server_arguments, server_and_token
from fuelid.fleet.client import FleetClient
from fuelid.output import print_json


def add_arguments(p):
    p.add_argument("truck", nargs="?", metavar="TRUCK", help="show this truck's files and model versions")
    add_server_arguments(p, "an engineer or admin token (default: $FUELID_TOKEN)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def _utc(ns) -> str:
    if ns is None:
        return "-"
    return datetime.datetime.fromtimestamp(ns / 1e9, datetime.timezone.utc).strftime("%Y-%m-%d %H:%M")


def run(args) -> int:
    client = FleetClient(*server_and_token(args))
    if args.truck is None:
        rows = client.trucks()
        if args.json:
            print_json(rows)
            return 0
        print(f"{'truck':<20} {'files':>6} {'MB':>9} {'first (UTC)':>17} {'last (UTC)':>17} {'model':>6}")
        for t in rows:
            print(f"{t['truck']:<20} {t['files']:>6} {t['size_bytes'] / 1e6:>9.1f} {_utc(t['start_ns']):>17} "
                  f"{_utc(t['end_ns']):>17} {t['latest_model_version'] or '-':>6}")
        return 0
    result = {"truck": args.truck, "files": client.files(args.truck), "models": client.models(args.truck)}
    if args.json:
        print_json(result)
        return 0
    print(f"{args.truck}: {len(result['files'])} files")
    for f in result["files"]:
        print(f"  {f['sha256'][:12]} {f['size_bytes']:>11} B  {_utc(f['start_ns'])} - {_utc(f['end_ns'])}")
    print(f"model versions: {len(result['models'])}")
    for m in result["models"]:
        fit = (m["metrics"].get("fit_percent") or {}).get("simulation")
        fit_s = "-" if fit is None else f"{fit:.1f} %"
        print(f"  v{m['version']}: fit (simulation) {fit_s}, {m['n_samples']} samples, top effect "
              f"{m['top_effect'] or '-'}")
    return 0
