"""The fleet server's HTTP API (FastAPI; OpenAPI description at /openapi.json; no /docs page, which would load
Swagger UI from another origin).

All endpoints are under /api/v1 and take `Authorization: Bearer <token>` (fleet.auth). Missing or unknown
token → 401; a role not allowed → 403. Every reply under /api/ and /openapi.json carries `Cache-Control:
no-store`. Request bodies run under fleet.limits' deadlines. Upload protocol: fuelid/logger/upload.py and
docs/reference/fleet-api.md.
"""
from __future__ import annotations

import hashlib
import logging
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Callable, Literal

from fastapi import Depends, FastAPI, HTTPException, Path as PathParam, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, Field
from starlette.requests import ClientDisconnect

from fuelid.errors import InputError
from fuelid.fleet import auth, console, db
from fuelid.fleet.limits import BodyDeadline, Timeouts
from fuelid.fleet.refits import RefitManager, dask_runner_factory
from fuelid.fleet.storage import FILE_MODE, HEX64, BlobStore, UploadRefused, inspect_mcap, make_dir, open_owned
from fuelid import __version__

log = logging.getLogger("fuelid.fleet")
MiB = 1 << 20
FILE_NAME_PATTERN = r"^[^/\\\x00-\x1f]+$"  # a name, not a path: no folder separators, no control characters


@dataclass
class Settings:
    """Server configuration: `data_dir` (blobs, job scratch, the SQLite database unless `database_url`),
    upload size limit [bytes], Dask scheduler address (None: a LocalCluster of `workers` processes), and
    the debounce after new data before a truck's refit [s] (None: no refits on new data), and how much of a
    truck's newest recorded time a refit uses [s]. Partial uploads are bounded per uploader (the truck a
    token uploads for, or "admin"): at most `max_partial_uploads` files and `max_partial_bytes` (their bytes
    held plus the declared size of the one growing; default twice the upload limit), and deleted
    `partial_expiry_s` [s] after their last byte arrived. `timeouts`: the client deadlines (fleet.limits; the
    app applies the body deadlines); `file_mode`: the mode of every file the server creates in `data_dir`
    (folders, `data_dir` included, get storage.dir_mode of it)."""

    data_dir: Path
    database_url: str | None = None
    max_upload_bytes: int = 1024 * MiB
    scheduler: str | None = None
    workers: int | None = None
    refit_after_s: float | None = 600.0
    refit_window_s: float = 24 * 3600.0
    max_partial_uploads: int = 8
    max_partial_bytes: int | None = None
    partial_expiry_s: float = 7 * 24 * 3600.0
    console_settings: console.ConsoleSettings = field(default_factory=console.ConsoleSettings)  # reference points, drift threshold
    timeouts: Timeouts = field(default_factory=Timeouts)
    file_mode: int = FILE_MODE


# --- response models (the OpenAPI description, checked by the schemathesis tests) ---

class Health(BaseModel):
    status: str
    version: str


class TokenIn(BaseModel):
    role: Literal["admin", "engineer", "truck"]
    truck: str | None = Field(None, pattern=auth.TRUCK_PATTERN, description="required for role truck only")
    name: str = Field("", max_length=auth.NAME_MAX, description="who or what holds the token: printable text")


class TokenInfo(BaseModel):
    id: int
    role: str
    truck: str | None
    name: str
    created_unix_s: float
    revoked_unix_s: float | None = None


class NewToken(BaseModel):
    id: int
    token: str = Field(description="the secret; shown only in this reply")
    role: str
    truck: str | None
    name: str


class UploadState(BaseModel):
    sha256: str
    size_bytes: int
    offset: int = Field(description="bytes of the file the server holds; the next PUT starts here")
    stored: bool
    status: str
    truck: str | None = None


class FileInfo(BaseModel):
    sha256: str
    truck: str
    size_bytes: int
    start_ns: int | None = Field(description="first message log time [ns since the epoch]")
    end_ns: int | None = Field(description="last message log time [ns since the epoch]")
    messages: int
    uploaded_unix_s: float
    name: str | None = Field(None, description="the file's name on the uploader (null for files uploaded before "
                                               "names were kept)")


class StoredFile(FileInfo):
    status: str
    offset: int
    stored: bool


class TruckInfo(BaseModel):
    truck: str
    files: int
    size_bytes: int
    start_ns: int | None
    end_ns: int | None
    latest_model_version: int | None


class ModelInfo(BaseModel):
    truck: str
    version: int
    job_id: int | None
    created_unix_s: float
    model_sha256: str
    diagnosis_sha256: str
    report_sha256: str | None
    metrics: dict
    n_samples: int | None
    duration_s: float | None = Field(description="data the model was identified on [s]")
    top_effect: str | None


class JobInfo(BaseModel):
    id: int
    truck: str
    reason: str
    status: str
    created_unix_s: float
    started_unix_s: float | None
    finished_unix_s: float | None
    error: str | None
    model_version: int | None


class Detail(BaseModel):
    detail: str = Field(description="what went wrong, one line")


ERRORS = {400: {"model": Detail, "description": "unparsable request"},
          401: {"model": Detail, "description": "missing or unknown token"},
          403: {"model": Detail, "description": "the token's role may not do this"},
          422: {"model": Detail, "description": "invalid parameters or body"}}
NOT_FOUND = {404: {"model": Detail, "description": "no such truck, version or job"}}
Truck = Annotated[str, PathParam(pattern=auth.TRUCK_PATTERN, description="truck id (VIN or fleet number)")]
Sha256 = Annotated[str, PathParam(pattern=HEX64, description="sha256 of the whole file, lower-case hex")]


def create_app(settings: Settings, runner_factory: Callable[[], object] | None = None) -> FastAPI:
    """The ASGI app. `runner_factory` makes the job runner (default: fleet.jobs.JobRunner on Dask)."""
    data_dir = make_dir(Path(settings.data_dir), settings.file_mode)
    engine = db.open_database(data_dir, settings.database_url, settings.file_mode)
    store = BlobStore(data_dir, settings.file_mode)
    swept = store.sweep(db.registered_hashes(engine))
    expired = store.expire_partials(settings.partial_expiry_s)
    interrupted = db.fail_interrupted_jobs(engine)
    if swept or expired or interrupted:
        log.warning("startup: removed %d unregistered blobs and %d expired partial uploads, marked %d interrupted "
                    "jobs failed", swept, expired, interrupted)
    max_partial_bytes = settings.max_partial_bytes or 2 * settings.max_upload_bytes
    refits = RefitManager(engine, store, data_dir / "jobs",
                          runner_factory or dask_runner_factory(settings.scheduler, settings.workers),
                          settings.refit_after_s, settings.refit_window_s)
    receiving: set[Path] = set()  # the partial uploads a request is appending to now (one request each)

    @asynccontextmanager
    async def lifespan(_app):
        yield
        await run_in_threadpool(refits.close)  # stops the Dask cluster with the server

    app = FastAPI(title="fuelid fleet", version=__version__, lifespan=lifespan, docs_url=None, redoc_url=None,
                  description="Truck MCAP uploads, per-truck fuel-model registry and identification jobs.")
    app.state.engine, app.state.store, app.state.refits = engine, store, refits

    @app.exception_handler(RequestValidationError)
    async def one_line_validation_error(_request, exc: RequestValidationError):
        # Every error body is {"detail": "<one line>"}, which the clients print as it is.
        parts = [f"{'.'.join(str(x) for x in e.get('loc', ()))}: {e.get('msg')}" for e in exc.errors()]
        return JSONResponse({"detail": "; ".join(parts) or "invalid request"}, status_code=422)
    bearer = HTTPBearer(auto_error=False, description="fuelid token (`fuelid token create`)")

    def principal(creds: HTTPAuthorizationCredentials | None = Depends(bearer)) -> auth.Principal:
        who = auth.authenticate(engine, creds.credentials) if creds else None
        if who is None:
            raise HTTPException(401, "missing or unknown token", headers={"WWW-Authenticate": "Bearer"})
        return who

    def role(*allowed: str):
        def check(who: auth.Principal = Depends(principal)) -> auth.Principal:
            if who.role not in allowed:
                token = f"{'an' if who.role[0] in 'aeiou' else 'a'} {who.role} token"
                raise HTTPException(403, f"{token} may not do this (needs {' or '.join(allowed)})")
            return who
        return check

    admin, reader, uploader = role("admin"), role("admin", "engineer"), role("admin", "truck")
    console.mount(app, engine, store, settings.console_settings, reader, ERRORS)  # the engineer's page at / and its API

    @app.middleware("http")
    async def api_headers(request, call_next):
        response = await call_next(request)
        if request.url.path.startswith("/api/") or request.url.path == "/openapi.json":
            response.headers["Cache-Control"] = "no-store"  # tokens, and data that is not the cache's to keep
            response.headers["X-Content-Type-Options"] = "nosniff"
        return response

    def known_truck(truck: str) -> None:
        if not db.truck_exists(engine, truck):
            raise HTTPException(404, f"no truck {truck}")

    @app.get("/api/v1/health", response_model=Health, tags=["service"])
    def health():
        """Liveness, no token needed."""
        return {"status": "ok", "version": __version__}

    # --- tokens ---

    @app.post("/api/v1/tokens", response_model=NewToken, status_code=201, responses=ERRORS, tags=["tokens"])
    def create_token(body: TokenIn, _=Depends(admin)):
        """Create a token (admin). The secret is in this reply only."""
        try:
            return auth.create_token(engine, body.role, body.truck, body.name)
        except InputError as exc:
            raise HTTPException(422, str(exc)) from None

    @app.get("/api/v1/tokens", response_model=list[TokenInfo], responses=ERRORS, tags=["tokens"])
    def list_tokens(_=Depends(admin)):
        return auth.list_tokens(engine)

    @app.delete("/api/v1/tokens/{token_id}", response_model=TokenInfo,
                responses={**ERRORS, **NOT_FOUND, 409: {"model": Detail, "description": "revoking itself"}},
                tags=["tokens"])
    def revoke_token(token_id: Annotated[int, PathParam(ge=1, le=2**31 - 1)], who=Depends(admin)):
        if token_id == who.token_id:  # an admin locking itself out would leave no way back but the database
            raise HTTPException(409, "a token cannot revoke itself; use another admin token")
        if not auth.revoke_token(engine, token_id):
            raise HTTPException(404, f"no live token {token_id}")
        return next(t for t in auth.list_tokens(engine) if t["id"] == token_id)

    # --- uploads ---

    def claimed_truck(who: auth.Principal, truck: str | None) -> str | None:
        if who.role == "truck":
            if truck not in (None, who.truck):
                raise HTTPException(403, f"this token uploads for truck {who.truck} only, not {truck}")
            return who.truck
        return truck

    def stored_reply(row: dict, truck: str | None, status: str) -> dict:
        if truck is not None and row["truck"] != truck:
            raise HTTPException(403, f"this file is stored for another truck, not {truck}")  # never say which
        return {**row, "status": status, "offset": row["size_bytes"], "stored": True}

    def check_size(size: int) -> None:
        if size == 0:
            raise HTTPException(422, "an empty file (0 bytes) is not an MCAP recording: nothing to store")
        if size > settings.max_upload_bytes:
            raise HTTPException(413, f"file of {size} B exceeds the server's limit of "
                                     f"{settings.max_upload_bytes} B")

    def check_partial_quota(part: Path, uploader: str, size: int) -> None:
        """Refuse (429: retry later) a PUT that would take the uploader past its partial-upload bounds."""
        store.expire_partials(settings.partial_expiry_s, keep=set(receiving))
        others = [p for p in store.partials(uploader) if p != part]
        held = sum(p.stat().st_size for p in others if p.exists())
        if not part.exists() and len(others) >= settings.max_partial_uploads:
            raise HTTPException(429, f"{len(others)} partial uploads held for this uploader (limit "
                                     f"{settings.max_partial_uploads}): finish them, or retry after they expire")
        if held + size > max_partial_bytes:
            raise HTTPException(429, f"partial uploads of this uploader would hold {held + size} B (limit "
                                     f"{max_partial_bytes} B): finish them, or retry after they expire")

    upload_errors = {**ERRORS, 413: {"model": Detail, "description": "file larger than the server accepts"}}

    @app.get("/api/v1/uploads/{sha256}", response_model=UploadState, responses=upload_errors, tags=["uploads"])
    def upload_state(sha256: Sha256, size: Annotated[int, Query(ge=0, le=2**62)],
                     truck: Annotated[str | None, Query(pattern=auth.TRUCK_PATTERN)] = None,
                     who=Depends(uploader)):
        """How much of a file the server holds: `offset` bytes of a partial upload, or `stored`."""
        truck = claimed_truck(who, truck)
        check_size(size)
        row = db.get_file(engine, sha256)
        if row is not None:
            return stored_reply(row, truck, "already stored")
        part = store.partial(sha256, truck or "admin")
        offset = part.stat().st_size if part.exists() else 0
        return {"sha256": sha256, "size_bytes": size, "offset": offset, "stored": False, "status": "partial",
                "truck": truck}

    @app.put("/api/v1/uploads/{sha256}", response_model=StoredFile, status_code=201, tags=["uploads"],
             openapi_extra={"requestBody": {"required": True, "content": {"application/octet-stream": {
                 "schema": {"type": "string", "format": "binary"}}}}},
             responses={**upload_errors,
                        200: {"model": StoredFile, "description": "already stored (nothing changed)"},
                        202: {"model": UploadState, "description": "bytes appended; send the rest from `offset`"},
                        409: {"model": UploadState, "description": "`offset` is not where the upload stands"},
                        429: {"model": Detail, "description": "the uploader holds too many or too large partial "
                                                              "uploads; retry later"},
                        422: {"model": Detail, "description": "invalid parameters, not a complete MCAP file, "
                                                              "or hash mismatch"}})
    async def upload(request: Request, sha256: Sha256, size: Annotated[int, Query(ge=0, le=2**62)],
                     offset: Annotated[int, Query(ge=0, le=2**62)] = 0,
                     truck: Annotated[str | None, Query(pattern=auth.TRUCK_PATTERN)] = None,
                     name: Annotated[str | None, Query(max_length=255, pattern=FILE_NAME_PATTERN,
                                                       description="the file's own name (no folder)")] = None,
                     who=Depends(uploader)):
        """Append the body at byte `offset` of the file `sha256` of `size` bytes. When the last byte arrives
        the file is checked (sha256, complete MCAP, its truck) and stored: 201; or refused with nothing kept."""
        truck = claimed_truck(who, truck)
        check_size(size)
        part = store.partial(sha256, truck or "admin")
        if stored := await already_stored(part, sha256, truck, holding=False):
            return stored
        if part in receiving:  # the same upload is still arriving on another connection
            return _state(409, sha256, size, _held(part), truck, "another request is uploading this file; retry "
                                                                 "later")
        receiving.add(part)
        try:
            return await receive_and_store(request, part, sha256, size, offset, truck, name)
        finally:
            receiving.discard(part)

    async def already_stored(part: Path, sha256: str, truck: str | None, holding: bool) -> JSONResponse | None:
        """The 200 reply when `sha256` is stored, else None. The uploader's partial upload of it is dropped, unless
        another request is appending to it (`holding`: the caller is that request)."""
        row = await run_in_threadpool(db.get_file, engine, sha256)
        if row is None:
            return None
        if holding or part not in receiving:
            part.unlink(missing_ok=True)
        return JSONResponse(stored_reply(row, truck, "already stored"), status_code=200)

    async def receive_and_store(request: Request, part: Path, sha256: str, size: int, offset: int,
                                truck: str | None, name: str | None):
        """The upload, its partial file reserved for this request: append the body, and store the file when
        complete. Every way out is a documented reply: 200 stored meanwhile, 201, 202 partial, 409 offset, or a
        refusal keeping nothing."""
        await run_in_threadpool(check_partial_quota, part, truck or "admin", size)
        held = _held(part)
        if offset != held:
            return _state(409, sha256, size, held, truck, f"offset {offset} but the server holds {held} B")
        try:
            held = await _receive(request, part, size - held, store.file_mode)
        except ClientDisconnect:  # what arrived stays for the resume
            return _state(202, sha256, size, _held(part), truck, "partial")
        except UploadRefused as exc:
            raise HTTPException(exc.status, str(exc)) from None
        if stored := await already_stored(part, sha256, truck, holding=True):  # another uploader stored it
            return stored
        if held < size:
            return _state(202, sha256, size, held, truck, "partial")
        try:
            row = await run_in_threadpool(_store_upload, engine, store, part, sha256, truck, name, set(receiving))
        except UploadRefused as exc:
            if stored := await already_stored(part, sha256, truck, holding=True):
                return stored
            if exc.status == 409:
                return _state(409, sha256, size, _held(part), truck, str(exc))
            raise HTTPException(exc.status, str(exc)) from None
        refits.data_arrived(row["truck"])
        return {**row, "status": "stored", "offset": size, "stored": True}

    # --- the registry ---

    @app.get("/api/v1/trucks", response_model=list[TruckInfo], responses=ERRORS, tags=["registry"])
    def trucks(_=Depends(reader)):
        """Every truck: files, bytes, message time range [ns], latest model version."""
        return db.list_trucks(engine)

    @app.get("/api/v1/trucks/{truck}/files", response_model=list[FileInfo], responses={**ERRORS, **NOT_FOUND},
             tags=["registry"])
    def truck_files(truck: Truck, _=Depends(reader)):
        known_truck(truck)
        return db.list_files(engine, truck)

    @app.get("/api/v1/trucks/{truck}/models", response_model=list[ModelInfo], responses={**ERRORS, **NOT_FOUND},
             tags=["registry"])
    def truck_models(truck: Truck, _=Depends(reader)):
        """Model versions of a truck with their validation metrics."""
        known_truck(truck)
        return db.list_models(engine, truck)

    artifacts = {"model.json": ("model_sha256", "application/json"),
                 "diagnosis.json": ("diagnosis_sha256", "application/json"),
                 "report.html": ("report_sha256", "text/html")}

    @app.get("/api/v1/trucks/{truck}/models/{version}/{artifact}", tags=["registry"],
             responses={**ERRORS, **NOT_FOUND, 200: {"content": {"application/json": {}, "text/html": {}},
                                                     "description": "the file"}})
    def model_artifact(truck: Truck, version: Annotated[str, PathParam(pattern=r"^(latest|[1-9][0-9]{0,8})$")],
                       artifact: Literal["model.json", "diagnosis.json", "report.html"], _=Depends(reader)):
        """A model version's model.json, diagnosis.json or report.html (`latest` or a version number)."""
        model = db.get_model(engine, truck, None if version == "latest" else int(version))
        if model is None:
            raise HTTPException(404, f"truck {truck} has no model version {version}")
        column, media = artifacts[artifact]
        if model[column] is None:
            raise HTTPException(404, f"model version {model['version']} of {truck} has no {artifact}")
        return FileResponse(store.path(model[column]), media_type=media,
                            headers={"X-Model-Version": str(model["version"])})

    # --- jobs ---

    @app.post("/api/v1/trucks/{truck}/refit", response_model=JobInfo, status_code=202,
              responses={**ERRORS, **NOT_FOUND}, tags=["jobs"])
    def refit_truck(truck: Truck, _=Depends(reader)):
        """Identify the truck's model again on all its files (a job; poll /api/v1/jobs/{id})."""
        known_truck(truck)
        return refits.request(truck, "request")

    @app.post("/api/v1/refit", response_model=list[JobInfo], status_code=202, responses=ERRORS, tags=["jobs"])
    def refit_fleet(_=Depends(reader)):
        """A job for every truck with files."""
        return [refits.request(t["truck"], "fleet") for t in db.list_trucks(engine) if t["files"]]

    @app.get("/api/v1/jobs", response_model=list[JobInfo], responses=ERRORS, tags=["jobs"])
    def jobs(truck: Annotated[str | None, Query(pattern=auth.TRUCK_PATTERN)] = None,
             active: bool = False, _=Depends(reader)):
        """Recent jobs (newest first), optionally of one truck or only queued/running ones."""
        return db.list_jobs(engine, truck=truck, active_only=active)

    @app.get("/api/v1/jobs/{job_id}", response_model=JobInfo, responses={**ERRORS, **NOT_FOUND}, tags=["jobs"])
    def job(job_id: Annotated[int, PathParam(ge=1, le=2**31 - 1)], _=Depends(reader)):
        row = db.get_job(engine, job_id)
        if row is None:
            raise HTTPException(404, f"no job {job_id}")
        return row

    # outermost (added last): the deadlines apply to uvicorn's own receive
    app.add_middleware(BodyDeadline, idle_s=settings.timeouts.body_idle_s, total_s=settings.timeouts.request_s)
    return app


def _held(part: Path) -> int:
    """Bytes of a partial upload the server holds (0: none)."""
    try:
        return part.stat().st_size
    except FileNotFoundError:
        return 0


def _state(status: int, sha256: str, size: int, offset: int, truck: str | None, detail: str) -> JSONResponse:
    return JSONResponse({"sha256": sha256, "size_bytes": size, "offset": offset, "stored": False,
                         "status": "partial", "truck": truck, "detail": detail}, status_code=status)


async def _receive(request: Request, part: Path, room: int, file_mode: int) -> int:
    """Append the request body to `part`, created (with `file_mode`) at the body's first byte; return the bytes
    `part` holds. A body running past `room` bytes is refused (413), a write failing (disk full) refused as 503
    (retry later), and then the request's bytes are dropped: `part` is as before, or gone when it was empty.
    A client disconnecting (ClientDisconnect) keeps what arrived."""
    start, written, f = _held(part), 0, None
    try:
        async for chunk in request.stream():
            written += len(chunk)
            if written > room:
                raise UploadRefused(413, f"body runs {written - room}+ B past the declared size")
            if chunk:
                f = f or open_owned(part, file_mode)
                f.write(chunk)
                f.flush()
    except (UploadRefused, OSError) as exc:
        if f is not None:
            f.truncate(start)
            f.close()
            f = None
            if start == 0:
                part.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise UploadRefused(503, f"the server cannot store the upload now ({exc.strerror}); retry later") \
                from None
        raise
    finally:
        if f is not None:
            f.close()
    return start + written


def _store_upload(engine, store: BlobStore, part: Path, sha256: str, truck: str | None, name: str | None,
                  receiving: set[Path]) -> dict:
    """Check the complete partial upload and store it; on any refusal the partial file is deleted. Other
    uploaders' partial uploads of the same file go too, but those in `receiving` (their request drops them when
    it ends). A partial upload gone meanwhile (expired, or the same file stored) is a 409 refusal."""
    if not part.exists():
        raise UploadRefused(409, "the partial upload is gone (expired or stored meanwhile); start again at 0")
    try:
        h = hashlib.sha256()
        with open(part, "rb") as f:
            while block := f.read(MiB):
                h.update(block)
        if h.hexdigest() != sha256:
            raise UploadRefused(422, f"content hash {h.hexdigest()} differs from the declared {sha256}; "
                                     "upload again from offset 0")
        info = inspect_mcap(part)
        if not auth.valid_truck(info.truck):
            raise UploadRefused(422, f"the file's truck id {info.truck!r} is not a valid truck id")
        if truck is not None and info.truck != truck:
            raise UploadRefused(403, f"the file is from truck {info.truck}, not {truck}")
        size = part.stat().st_size
        store.commit(part, sha256)
        for other in store.incoming.glob(f"{sha256}-*.part"):  # the same file half-sent by another uploader
            if other not in receiving:
                other.unlink(missing_ok=True)
    except BaseException:
        part.unlink(missing_ok=True)
        raise
    db.add_file(engine, sha256=sha256, truck=info.truck, size_bytes=size, start_ns=info.start_ns,
                end_ns=info.end_ns, messages=info.messages, name=name)
    return db.get_file(engine, sha256)
