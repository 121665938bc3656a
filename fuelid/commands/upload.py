"""fuelid upload: send MCAP files to the fleet server (resumable, by sha256; fuelid/logger/upload.py)."""
import os
import sys

from fuelid.errors import FuelidError
from fuelid.logger.upload import UploadError, upload_with_retry
from fuelid.output import print_json


def add_server_arguments(p, token_help: str = "API token (default: $FUELID_TOKEN)") -> None:
    """--server and --token, defaulting to $FUELID_SERVER and $FUELID_TOKEN (shared by the fleet clients)."""
    p.add_argument("--server", default=os.environ.get("FUELID_SERVER"), metavar="URL",
                   help="fleet server, e.g. http://fleet:8000 (default: $FUELID_SERVER)")
    p.add_argument("--token", default=os.environ.get("FUELID_TOKEN"), metavar="TOKEN", help=token_help)


def server_and_token(args) -> tuple[str, str]:
    if not args.server:
        raise FuelidError("no server: give --server URL or set FUELID_SERVER")
    if not args.token:
        raise FuelidError("no token: give --token TOKEN or set FUELID_TOKEN")
    return args.server, args.token


def add_arguments(p):
    p.add_argument("files", nargs="+", metavar="FILE.mcap", help="closed (complete) MCAP recordings")
    add_server_arguments(p, "a truck token (or admin) (default: $FUELID_TOKEN)")
    p.add_argument("--truck", metavar="ID", help="refuse unless the file is this truck's (the server checks)")
    p.add_argument("--retry-s", type=float, default=120.0, metavar="S",
                   help="keep retrying an unreachable or busy server, a file another request is uploading, or a "
                        "cut upload for this long [s], with jittered exponential backoff up to 10 s (default 120)")
    p.add_argument("--json", action="store_true", help="print one result per file as JSON")


def run(args) -> int:
    server, token = server_and_token(args)
    results, failed = [], 0
    for path in args.files:
        try:
            reply = upload_with_retry(path, server, token, truck=args.truck, deadline_s=args.retry_s)
            results.append(reply)
            if not args.json:
                print(f"{path}: {reply['status']} for truck {reply['truck']} "
                      f"({reply['size_bytes']} B, sha256 {reply['sha256'][:12]})")
        except (UploadError, OSError) as exc:
            failed += 1
            results.append({"path": path, "error": str(exc)})
            print(f"fuelid upload: error: {path}: {exc}", file=sys.stderr)
    if args.json:
        print_json(results)
    return 1 if failed else 0
