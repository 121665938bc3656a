"""fuelid serve: the fleet server (uploads, model registry, identification jobs on Dask) under uvicorn."""
from pathlib import Path

from fuelid.errors import FuelidError
from fuelid.fleet.drift import parse_points


def octal(text: str) -> int:
    return int(text, 8)


def add_arguments(p):
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only; 0.0.0.0: every "
                        "interface, behind a TLS proxy)")
    p.add_argument("--port", type=int, default=8000, help="TCP port to listen on (default 8000)")
    p.add_argument("--data-dir", default="fleet-data", metavar="DIR",
                   help="stored files, job scratch and (unless --database-url) the SQLite database "
                        "(default ./fleet-data)")
    p.add_argument("--database-url", metavar="URL",
                   help="e.g. postgresql+psycopg://user:pass@host/fuelid (default: SQLite in --data-dir)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="Dask scheduler for identification jobs, e.g. tcp://10.0.0.5:8786 (default: a local "
                        "cluster started on the first job; with a remote cluster --data-dir must be shared)")
    p.add_argument("--workers", type=int, metavar="N", help="local cluster worker processes (default: Dask's)")
    p.add_argument("--max-upload-mb", type=float, default=1024.0, metavar="MB",
                   help="largest file accepted [MiB] (default 1024); larger → 413")
    p.add_argument("--max-partial-uploads", type=int, default=8, metavar="N",
                   help="partial (unfinished) uploads one truck may hold (default 8); more → 429")
    p.add_argument("--max-partial-mb", type=float, metavar="MB",
                   help="bytes one truck's partial uploads may hold [MiB] (default twice --max-upload-mb)")
    p.add_argument("--partial-expiry-h", type=float, default=168.0, metavar="H",
                   help="delete a partial upload H hours after its last byte arrived (default 168: a week)")
    p.add_argument("--refit-after", type=float, default=600.0, metavar="S",
                   help="identify a truck again S seconds after its last new file (default 600)")
    p.add_argument("--refit-window-h", type=float, default=24.0, metavar="H",
                   help="a refit uses the truck's newest H hours of recorded data (default 24)")
    p.add_argument("--reference-points", default="1000x600Nm,1200x1200Nm,1400x1800Nm", metavar="POINTS",
                   help="the console's default operating points for fuel-efficiency drift: RPMxTORQUE with Nm or "
                        "%% (the models' torque unit), comma separated (default 1000x600Nm,1200x1200Nm,1400x1800Nm)")
    p.add_argument("--drift-threshold", type=float, default=5.0, metavar="PCT",
                   help="flag a truck whose steady-state fuel moved more than PCT %% (and 2σ) since its first model "
                        "(default 5)")
    p.add_argument("--header-timeout", type=float, default=10.0, metavar="S",
                   help="close a connection whose request line and headers are not all in S seconds after it "
                        "opened (or after the next request's first byte) (default 10)")
    p.add_argument("--body-idle-timeout", type=float, default=30.0, metavar="S",
                   help="answer 408 and close when a request body brings no byte for S seconds; a stalled upload "
                        "keeps what arrived and frees the file for the resume (default 30)")
    p.add_argument("--request-timeout", type=float, default=600.0, metavar="S",
                   help="answer 408 and close when a request body is not complete S seconds after its headers "
                        "(default 600: an 8 MiB upload chunk at 14 kB/s)")
    p.add_argument("--keep-alive", type=float, default=75.0, metavar="S",
                   help="close a kept-alive connection silent for S seconds between requests (default 75: longer "
                        "than a reverse proxy's upstream keep-alive, nginx's 60 s, so the proxy closes first)")
    p.add_argument("--max-connections", type=int, metavar="N",
                   help="open connections at most; one more closes the one waiting longest for a request "
                        "(default: three quarters of the open-file limit, `ulimit -n`)")
    p.add_argument("--file-mode", type=octal, default=0o600, metavar="OCTAL",
                   help="mode of the files the server creates in --data-dir; folders get the matching x bits "
                        "(default 600: files 0600, folders 0700, owner only; 640 lets the group read)")
    p.add_argument("--no-auto-refit", action="store_true", help="identify only when asked (refit)")
    p.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"],
                   help="server log level (default info)")


def run(args) -> int:
    # the optional [fleet] extra (uvicorn, FastAPI): imported here so the rest of the CLI works without it
    from fuelid.fleet.app import MiB, Settings, create_app
    from fuelid.fleet.console import ConsoleSettings
    from fuelid.fleet.limits import Timeouts, run_server

    if min(args.max_upload_mb, args.refit_window_h, args.max_partial_uploads, args.partial_expiry_h,
           args.max_partial_mb or 1, args.drift_threshold, args.header_timeout, args.body_idle_timeout,
           args.request_timeout, args.keep_alive, args.max_connections or 1) <= 0:
        raise FuelidError("--max-upload-mb, --refit-window-h, the partial-upload limits, --drift-threshold, the "
                          "timeouts and --max-connections must be positive")
    if not 0 <= args.file_mode <= 0o777 or not args.file_mode & 0o600 == 0o600:
        raise FuelidError(f"--file-mode {args.file_mode:o}: give permission bits (at most 777) that let the owner "
                          "read and write, e.g. 600 or 640")
    timeouts = Timeouts(header_s=args.header_timeout, body_idle_s=args.body_idle_timeout,
                        request_s=args.request_timeout, keep_alive_s=args.keep_alive,
                        max_connections=args.max_connections)
    try:
        console = ConsoleSettings(parse_points(args.reference_points), args.drift_threshold)
    except ValueError as exc:
        raise FuelidError(f"--reference-points: {exc}") from None
    settings = Settings(data_dir=Path(args.data_dir), database_url=args.database_url,
                        max_upload_bytes=int(args.max_upload_mb * MiB), scheduler=args.scheduler,
                        workers=args.workers, refit_after_s=None if args.no_auto_refit else args.refit_after,
                        refit_window_s=args.refit_window_h * 3600.0, max_partial_uploads=args.max_partial_uploads,
                        max_partial_bytes=int(args.max_partial_mb * MiB) if args.max_partial_mb else None,
                        partial_expiry_s=args.partial_expiry_h * 3600.0, console_settings=console,
                        timeouts=timeouts, file_mode=args.file_mode)
    try:
        app = create_app(settings)
    except Exception as exc:  # unreachable database, bad URL, unwritable data dir
        raise FuelidError(f"cannot start: {' '.join(str(exc).split())[:300]}") from exc
    run_server(app, args.host, args.port, timeouts, args.log_level)
    return 0
