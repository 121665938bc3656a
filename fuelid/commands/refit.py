"""fuelid refit: ask the fleet server to identify a truck's model again, or every truck's (Dask jobs)."""
import sys
import time

from fuelid.commands.upload import add_server_arguments, server_and_token
from fuelid.fleet.client import FleetClient
from fuelid.output import print_json


def add_arguments(p):
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("truck", nargs="?", metavar="TRUCK", help="truck id")
    which.add_argument("--all", action="store_true", help="every truck with files")
    p.add_argument("--wait", type=float, default=0.0, metavar="S",
                   help="wait up to S seconds for the jobs to finish (default: return at once); "
                        "exit 1 if one failed or is still running then")
    add_server_arguments(p, "an engineer or admin token (default: $FUELID_TOKEN)")
    p.add_argument("--json", action="store_true", help="print the jobs as JSON")


def run(args) -> int:
    client = FleetClient(*server_and_token(args))
    jobs = client.refit(None if args.all else args.truck)
    jobs = jobs if isinstance(jobs, list) else [jobs]
    end = time.monotonic() + args.wait
    while time.monotonic() < end and any(j["status"] in ("queued", "running") for j in jobs):
        time.sleep(min(2.0, max(0.1, end - time.monotonic())))
        jobs = [client.job(j["id"]) for j in jobs]
    if args.json:
        print_json(jobs)
    else:
        for j in jobs:
            outcome = {"done": f"model version {j['model_version']}", "failed": j["error"],
                       "unchanged": f"(no new data since model version {j['model_version']})"}.get(j["status"], "")
            print(f"job {j['id']} {j['truck']}: {j['status']} {outcome}".rstrip())
    unfinished = [j for j in jobs if j["status"] in ("queued", "running")]
    if args.wait > 0 and unfinished:
        print(f"error: {len(unfinished)} of {len(jobs)} jobs still {unfinished[0]['status']} after waiting "
              f"{args.wait:g} s (see `fuelid trucks` for their progress)", file=sys.stderr)
        return 1
    return 1 if any(j["status"] == "failed" for j in jobs) else 0
