"""Uploading closed MCAP files to the fleet server: the HTTP protocol client and the daemon's upload queue.

Protocol (docs/reference/fleet-api.md): files are addressed by their sha256. `GET /api/v1/uploads/{sha256}?size=N` tells
how many bytes of that file the server already holds (`offset`) or that it is `stored`; each
`PUT /api/v1/uploads/{sha256}?size=N&offset=K` appends the body at byte K and answers 202 with the new offset,
201 once the whole file arrived and passed the server's checks (hash, MCAP, truck), or 200 when the file was
already stored. An upload cut at any byte (network gone, server killed) resumes from the server's offset, and
repeating a request is harmless, so every failure is simply retried: at once after a 409 naming another offset
(resend from there), after a jittered exponential backoff when the server is busy (5xx, 408, 429, or a 409 at
the same offset: another request is uploading the file), never by resending a chunk in a tight loop. The
server's 200/201 reply names the sha256 and size it stored; only a reply matching the local file counts as
confirmation, and only then may the queue delete the local file.

Standard library only (urllib), so the in-cab install needs nothing more; `logger` never imports `fleet`.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import random
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from email.message import Message
from pathlib import Path
from typing import Callable

from fuelid.errors import FuelidError
from fuelid.logger.durable import write_atomic

log = logging.getLogger("fuelid.upload")

API = "/api/v1"
CHUNK_BYTES = 8 << 20  # bytes per PUT: a cut costs at most this much resending, and memory stays bounded
JOURNAL = "upload-queue.json"
JOURNAL_RETRY_S = 1.0  # a journal write that failed is tried again this often [s]
CURED_BY_A_NEW_TOKEN = (401, 403)  # refusals tried again when the token changes (unknown token, wrong role/truck)


class UploadError(FuelidError):
    """An upload or API request that failed; `status` is the HTTP status, None when the server was not reached."""

    def __init__(self, message: str, status: int | None = None, body: dict | None = None):
        super().__init__(message)
        self.status = status
        self.body = body or {}


class Unavailable(UploadError):
    """Worth retrying later: no network, connection refused or cut, timeout, 5xx, 408, 429, and a 409 saying
    another request is uploading the file."""


class Rejected(UploadError):
    """The server refused this request for good (401, 403, 413, 422, ...), or the file cannot be sent at all (an
    empty file; status None): retrying will not help."""


def _error(status: int | None, url: str, detail: str, body: dict | None = None) -> UploadError:
    retry = status is None or status >= 500 or status in (408, 429)
    where = urllib.parse.urlsplit(url).path
    text = f"{detail} ({where})" if status is None else f"HTTP {status}: {detail} ({where})"
    return (Unavailable if retry else Rejected)(text, status, body)


def request(method: str, url: str, token: str | None, *, data: bytes | None = None,
            content_type: str = "application/octet-stream", timeout_s: float = 60.0) -> tuple[int, bytes, Message]:
    """One HTTP request with a bearer token → (status, body bytes, headers (case-insensitive)) for 2xx replies.

    Anything else raises Unavailable (retryable) or Rejected (the server's `detail` message in one line)."""
    headers = {"Accept": "application/json"}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    if data is not None:
        headers["Content-Type"] = content_type
    req = urllib.request.Request(url, data=data, method=method, headers=headers)
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as resp:
            return resp.status, resp.read(), resp.headers
    except urllib.error.HTTPError as exc:
        raw = exc.read()
        try:  # the fleet server's errors are {"detail": "one line", ...}; a proxy's may be anything
            body = json.loads(raw)
            body = body if isinstance(body, dict) else {"detail": body}
        except ValueError:
            body = {"detail": raw.decode(errors="replace").strip() or exc.reason}
        raise _error(exc.code, url, " ".join(str(body.get("detail")).split()), body) from None
    except (urllib.error.URLError, OSError) as exc:  # refused, reset, unreachable, timeout
        reason = getattr(exc, "reason", exc)
        raise _error(None, url, f"cannot reach server: {reason}") from None


def request_json(method: str, url: str, token: str | None, payload=None, *, timeout_s: float = 60.0):
    """`request` with a JSON body (when payload is not None) and a JSON reply."""
    data = None if payload is None else json.dumps(payload).encode()
    _, body, _ = request(method, url, token, data=data, content_type="application/json", timeout_s=timeout_s)
    return json.loads(body) if body else None


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


def upload_file(path: str | Path, server_url: str, token: str, *, truck: str | None = None,
                chunk_bytes: int = CHUNK_BYTES, timeout_s: float = 60.0, sha256: str | None = None,
                cancel: threading.Event | None = None) -> dict:
    """Upload one file, resuming from whatever the server already holds; return the server's confirmation
    (`status` "stored" or "already stored", `sha256`, `size_bytes`, `truck`, ...).

    One attempt: a network failure raises Unavailable and the next call resumes where this one stopped.
    `truck` (optional) asks the server to check the file is that truck's; `cancel` stops between chunks."""
    path = Path(path)
    size = path.stat().st_size
    if size == 0:
        raise Rejected(f"{path}: an empty file (0 bytes) is not an MCAP recording; nothing to upload")
    digest = sha256 or file_sha256(path)
    base = f"{server_url.rstrip('/')}{API}/uploads/{digest}"
    query = {"size": size, "name": path.name, **({"truck": truck} if truck else {})}
    state = request_json("GET", f"{base}?{urllib.parse.urlencode(query)}", token, timeout_s=timeout_s)
    offset = state.get("offset", 0)
    reply = state if state.get("stored") else None
    with open(path, "rb") as f:
        while reply is None:
            if cancel is not None and cancel.is_set():
                raise Unavailable("upload stopped", None)
            f.seek(offset)
            data = f.read(chunk_bytes)
            url = f"{base}?{urllib.parse.urlencode({**query, 'offset': offset})}"
            try:
                status, body, _ = request("PUT", url, token, data=data, timeout_s=timeout_s)
            except UploadError as exc:
                if exc.status != 409:
                    raise
                held = int(exc.body.get("offset", 0))
                if held == offset:  # another request is uploading this file: back off (the caller retries)
                    raise Unavailable(str(exc), 409, exc.body) from None
                offset = held  # the server holds a different offset (an earlier try went on): resend from there
                continue
            answer = json.loads(body)
            if status == 202:
                offset = int(answer["offset"])
            else:
                reply = answer
    if reply.get("sha256") != digest or reply.get("size_bytes") != size:
        raise Rejected(f"server confirmed {reply.get('sha256')} ({reply.get('size_bytes')} B), "
                       f"not {digest} ({size} B): {path}")
    return {**reply, "path": str(path)}


class Backoff:
    """Exponential backoff: delays initial_s, 2·initial_s, ... capped at max_s [s], each ±10 % jitter so a
    fleet that lost the network together (or trucks refused together with 429) does not come back in step."""

    def __init__(self, initial_s: float = 1.0, max_s: float = 300.0):
        self.initial_s, self.max_s = initial_s, max_s
        self.reset()

    def reset(self) -> None:
        self._next_s = self.initial_s

    def next(self) -> float:
        delay = self._next_s
        self._next_s = min(self.max_s, self._next_s * 2)
        return delay * random.uniform(0.9, 1.1)


def upload_with_retry(path: str | Path, server_url: str, token: str, *, deadline_s: float = 60.0,
                      backoff: Backoff | None = None, **kw) -> dict:
    """upload_file, retried with backoff on Unavailable (unreachable, 5xx, 408, 429, the file busy with another
    request: 409 at the same offset) until `deadline_s` [s] have passed (`fuelid upload`)."""
    backoff = backoff or Backoff(0.5, 10.0)
    end = time.monotonic() + deadline_s
    digest = kw.pop("sha256", None) or file_sha256(path)
    while True:
        try:
            return upload_file(path, server_url, token, sha256=digest, **kw)
        except Unavailable:
            delay = backoff.next()
            if time.monotonic() + delay > end:
                raise
            time.sleep(delay)



class UploadQueue:
    """Uploads closed MCAP files in the background, in the order queued, whenever the server can be reached.

    The queue is a journal `spool_dir/upload-queue.json` (pending paths, and those the server refused for
    good with its reason) rewritten atomically on every change, so a restart or power cut loses nothing: the
    next UploadQueue on the same spool_dir carries on, and the server's offset makes a cut upload resume.
    A journal that cannot be written (disk full) is retried every JOURNAL_RETRY_S while uploads go on
    (`journal_error` in the status); a damaged one found at start is set aside and the queue rebuilt from
    the `*.mcap` files in spool_dir, so the logger always starts.
    Unreachable server, timeouts and 5xx → wait and retry with exponential backoff (`initial_backoff_s` up to
    `max_backoff_s` [s]); a refusal of the file (403/413/422 ...) moves it to `rejected` and goes on with the
    next. A refusal that a change can cure is tried again after the change: a 401 (unknown token) holds the
    whole queue until `token` (a string, or a function re-read every `token_check_s` [s], e.g. of the token
    file) gives another token, and then files refused with 401/403 are queued again; `retry(paths)` queues
    refused files again on the caller's word (e.g. relabelled with the VIN). `prepare(path)`, when given, runs
    in the upload thread just before each attempt (relabelling happens there, never under an upload).
    With `delete_after_upload` a file is deleted only after the server confirmed its sha256 and size.
    """

    def __init__(self, spool_dir: str | Path, server_url: str, token: str | Callable[[], str], truck: str | None, *,
                 delete_after_upload: bool = False, initial_backoff_s: float = 1.0, max_backoff_s: float = 300.0,
                 timeout_s: float = 60.0, chunk_bytes: int = CHUNK_BYTES, token_check_s: float = 5.0,
                 prepare: Callable[[str], None] | None = None, start: bool = True):
        self.spool_dir = Path(spool_dir)
        self.spool_dir.mkdir(parents=True, exist_ok=True)
        self.server_url, self.truck = server_url, truck
        self._token_source = token if callable(token) else (lambda: token)
        self.token_check_s, self.prepare = token_check_s, prepare
        self._token: str | None = None  # the token of the last attempt
        self._refused_token: str | None = None  # the token the server answered 401 to
        self._again: set[str] = set()  # files to queue again even if the attempt in flight is refused
        self.delete_after_upload = delete_after_upload
        self.timeout_s, self.chunk_bytes = timeout_s, chunk_bytes
        self._backoff = Backoff(initial_backoff_s, max_backoff_s)
        self._journal = self.spool_dir / JOURNAL
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.uploaded = 0
        self.last_error: str | None = None
        self.journal_error: str | None = None  # why the journal on disk is behind the queue, None when it is not
        self.journal_set_aside: str | None = None  # where a damaged journal found at start was moved
        self.pending, self.rejected = self._load()
        self._thread = threading.Thread(target=self._run, name="fuelid-upload", daemon=True)
        if start:
            self.start()

    def start(self) -> None:
        self._thread.start()

    def _load(self) -> tuple[list[str], list[dict]]:
        try:
            state = json.loads(self._journal.read_bytes())
            pending, rejected = state.get("pending", []), state.get("rejected", [])
            if not (all(isinstance(p, str) for p in pending) and all(isinstance(r, dict) for r in rejected)):
                raise ValueError("pending must be paths, rejected must be records")
            return list(pending) + self._closed_since_journal(set(pending) | {r.get("path") for r in rejected}), \
                list(rejected)
        except FileNotFoundError:
            return [], []
        except (OSError, ValueError, AttributeError, TypeError) as exc:
            return self._rebuild(exc), []

    def _closed_since_journal(self, listed: set[str]) -> list[str]:
        """Files in spool_dir written after the journal's last write and not in it: closed while the journal
        could not be written (every change rewrites it, so normally there are none)."""
        since = self._journal.stat().st_mtime
        later = [str(p.resolve()) for p in sorted(self.spool_dir.glob("*.mcap")) if p.stat().st_mtime > since]
        return [p for p in later if p not in listed]

    def _rebuild(self, exc: Exception) -> list[str]:
        """Set a damaged journal aside and queue every closed file in the folder again: logging comes first, and
        a file the server already holds costs one request ("already stored"); refusals are forgotten (tried again)."""
        aside = self._journal.with_name(f"{JOURNAL}.damaged-{time.time():.0f}")
        try:
            os.replace(self._journal, aside)
        except OSError as move_exc:  # unreadable and immovable: the next write replaces it
            aside = Path(f"{self._journal} (not moved: {move_exc.strerror})")
        self.journal_set_aside = str(aside)
        pending = [str(p.resolve()) for p in sorted(self.spool_dir.glob("*.mcap"))]
        log.error("upload: damaged journal %s (%s) set aside as %s; queued the %d files in %s again",
                  self._journal, exc, aside.name, len(pending), self.spool_dir)
        self.pending, self.rejected = pending, []
        self._save()
        return pending

    def _save(self) -> None:
        """Write the journal; on failure (disk full, I/O error) keep going and try again from the upload thread."""
        state = {"version": 1, "truck": self.truck, "pending": self.pending, "rejected": self.rejected}
        try:
            write_atomic(self._journal, json.dumps(state, indent=1).encode())
        except OSError as exc:
            if self.journal_error is None:
                log.error("upload: cannot write the journal %s: %s (retrying; the queue goes on in memory)",
                          self._journal, exc)
            self.journal_error = f"cannot write {self._journal.name}: {exc}"
            self._wake.set()
            return
        if self.journal_error is not None:
            log.info("upload: journal %s written again", self._journal)
            self.journal_error = None

    def enqueue(self, path: str | Path) -> None:
        """Queue a closed file (an absolute path is kept); queuing a path twice uploads it once."""
        path = str(Path(path).resolve())
        with self._lock:
            if path not in self.pending:
                self.pending.append(path)
                self._save()
        self._wake.set()

    def status(self) -> dict:
        """Counts for a status file: queued, uploaded since start, refused, and the last error."""
        with self._lock:
            return {"queued": len(self.pending), "uploaded": self.uploaded, "rejected": len(self.rejected),
                    "last_error": self.last_error, "journal_error": self.journal_error,
                    "journal_set_aside": self.journal_set_aside}

    def retry(self, paths) -> None:
        """Queue refused files again (the cause of their refusal changed); one being uploaded now is queued
        again even if this attempt is refused."""
        paths = {str(Path(p).resolve()) for p in paths}
        with self._lock:
            self._again |= paths & set(self.pending)
            self._requeue(lambda r: r["path"] in paths)
        self._wake.set()

    def _requeue(self, which: Callable[[dict], bool]) -> None:
        # Called with the lock held.
        back = [r for r in self.rejected if which(r)]
        if back:
            self.rejected = [r for r in self.rejected if not which(r)]
            self.pending += [r["path"] for r in back if r["path"] not in self.pending]
            log.info("upload: %d refused files queued again", len(back))
            self._save()

    def _done(self, path: str, refusal: Rejected | str | None = None) -> None:
        with self._lock:
            self.pending.remove(path)
            if path in self._again:  # its refusal's cause changed during the attempt
                self._again.discard(path)
                if refusal is not None:
                    self.pending.append(path)
                    refusal = None
            if refusal is not None:
                self.rejected.append({"path": path, "error": str(refusal), "at_unix_s": time.time(),
                                      "status": getattr(refusal, "status", None)})
            self._save()

    def _current_token(self) -> str | None:
        """The token to use now, or None while there is none or only the one the server refused."""
        try:
            token = self._token_source()
        except FuelidError as exc:  # the token file is missing or empty: wait for it
            self.last_error = str(exc)
            return None
        if token == self._refused_token:
            return None
        if self._token is not None and token != self._token:
            log.info("upload: the token changed; files it refused are queued again")
            with self._lock:
                self._requeue(lambda r: r.get("status") in CURED_BY_A_NEW_TOKEN)
        self._token, self._refused_token = token, None
        return token

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._step()
            except Exception as exc:  # nothing may end the thread while files wait: say it, wait, go on
                log.exception("upload: unexpected error")
                self.last_error = f"{type(exc).__name__}: {exc}"
                self._stop.wait(self._backoff.next())

    def _step(self) -> None:
        """Upload the first queued file (one attempt), or wait for one; retry a journal write that failed."""
        with self._lock:
            if self.journal_error is not None:
                self._save()
            path = self.pending[0] if self.pending else None
        token = self._current_token()
        if path is None or token is None:  # nothing to send, or no usable token: look again later
            self._wake.wait(JOURNAL_RETRY_S if self.journal_error is not None else self.token_check_s)
            self._wake.clear()
            return
        if not os.path.exists(path):
            log.warning("upload: %s vanished before upload; dropped from the queue", path)
            self._done(path, "file missing")
            return
        try:
            if self.prepare is not None:
                self.prepare(path)
            reply = upload_file(path, self.server_url, token, truck=self.truck,
                                chunk_bytes=self.chunk_bytes, timeout_s=self.timeout_s, cancel=self._stop)
        except Rejected as exc:
            self.last_error = str(exc)
            if exc.status == 401:  # the token, not the file: hold the queue until there is another one
                self._refused_token = token
                self.last_error += "; waiting for a new token"
                log.error("upload: server refused the token: %s; waiting for a new token", exc)
                return
            log.error("upload: server refused %s: %s", path, exc)
            self._done(path, exc)
            return
        except (Unavailable, OSError) as exc:
            self.last_error = str(exc)
            self._stop.wait(self._backoff.next())
            return
        self._backoff.reset()
        self.last_error = None
        if self.delete_after_upload:  # upload_file returned only on a confirmation matching the file
            os.remove(path)
        self.uploaded += 1
        log.info("upload: %s %s (%s)", path, reply["status"], reply["sha256"][:12])
        self._done(path)

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop after the chunk in flight; what is still queued stays in the journal for the next start."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    def __enter__(self) -> UploadQueue:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
