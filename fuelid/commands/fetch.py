"""fuelid fetch: a truck's model (model.json), and optionally its report and diagnosis, from the fleet server."""
from pathlib import Path

from fuelid.commands.upload import add_server_arguments, server_and_token
from fuelid.fleet.client import FleetClient
from fuelid.output import print_json
from fuelid.paths import writable_file


def add_arguments(p):
    p.add_argument("truck", metavar="TRUCK", help="truck id (VIN or fleet number)")
    p.add_argument("--version", type=int, metavar="V", help="model version (default: the latest)")
    p.add_argument("-o", "--output", default="model.json", metavar="MODEL.json",
                   help="where to write the model (default model.json)")
    p.add_argument("--report", metavar="REPORT.html", help="also write the version's HTML report")
    p.add_argument("--diagnosis", metavar="DIAGNOSIS.json", help="also write the version's diagnosis")
    add_server_arguments(p, "an engineer or admin token (default: $FUELID_TOKEN)")
    p.add_argument("--json", action="store_true", help="print what was written as JSON")


def run(args) -> int:
    client = FleetClient(*server_and_token(args))
    wanted = [("model.json", args.output), ("report.html", args.report), ("diagnosis.json", args.diagnosis)]
    for _, target in wanted:
        if target:
            writable_file(target)
    client = FleetClient(*server_and_token(args))
    version, written = args.version, {}
    for name, target in wanted:
        if target:
            # The first download fixes the version, so the report matches the model even if a job just ended.
            body, version = client.artifact(args.truck, version, name)
            Path(target).write_bytes(body)
            written[name] = target
    if args.json:
        print_json({"truck": args.truck, "version": version, "written": written})
    else:
        print(f"{args.truck} model version {version}: " + ", ".join(written.values()))
    return 0
