"""How long the fleet server waits for a client, and how many connections it holds: the guards that keep a slow,
stalled or hostile connection from holding a worker, an upload lock or a file descriptor for long.

A request passes three deadlines, each closing the connection when it runs out:

- headers: a new connection (or the next request on a kept-alive one, from its first byte) must deliver its
  request line and headers within `header_s` [s], in at most MAX_HEADER_BYTES (more: 431). uvicorn has
  neither bound with httptools (its keep-alive timer stops at the first byte and never runs before the first
  request; h11's incomplete-event limit is h11's only), so `guarded_protocol` adds them to uvicorn's HTTP
  protocol; uvicorn's own `timeout_keep_alive` (`keep_alive_s`) still closes a kept-alive connection that stays
  silent between requests.
- body: once the headers are in, each read of the body must bring bytes within `body_idle_s` [s], and the
  whole body must be in within `request_s` [s] of the headers (`BodyDeadline`, ASGI middleware). At either
  deadline the application sees the client as disconnected (an upload keeps what arrived and releases its
  lock) and the client gets `408 {"detail": ...}` with `Connection: close`.
- connections: at most `max_connections` are open at once (default three quarters of the process's open-file
  limit, so accepting never runs out of descriptors); a connection past it closes the one that has waited
  longest for a request's headers (a slowloris, or an idle kept-alive connection), or itself when every other
  connection is inside a request. A flood of half-sent requests thus cannot lock out `GET /api/v1/health`.
  (uvicorn's `limit_concurrency` answers 503 only once a request's headers are in, so it does not bound these.)
"""
from __future__ import annotations

import asyncio
import json
import resource
from collections import OrderedDict
from dataclasses import dataclass

MAX_HEADER_BYTES = 64 * 1024  # a request line and headers (nginx's default allows 1 kB + 4 × 8 kB)


@dataclass(frozen=True)
class Timeouts:
    """Client deadlines [s] and the connection bound (None: three quarters of the open-file limit)."""

    header_s: float = 10.0
    body_idle_s: float = 30.0
    request_s: float = 600.0
    keep_alive_s: float = 75.0
    max_connections: int | None = None

    def connections(self) -> int:
        """The connection bound in force."""
        if self.max_connections is not None:
            return self.max_connections
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        return max(16, (soft if soft != resource.RLIM_INFINITY else 4096) * 3 // 4)


def guarded_protocol(header_s: float, max_connections: int) -> type[asyncio.Protocol]:
    """uvicorn's HTTP protocol class (httptools, else h11) with the header deadline and the connection bound."""
    from uvicorn.protocols.http.auto import AutoHTTPProtocol

    waiting: OrderedDict[asyncio.Protocol, None] = OrderedDict()  # connections between requests, longest first

    class Guarded(AutoHTTPProtocol):
        _header_timer: asyncio.TimerHandle | None = None
        _header_bytes = 0  # received since the request began, while its headers are incomplete

        def _between_requests(self) -> bool:
            return self.cycle is None or self.cycle.response_complete

        def _arm(self) -> None:
            if self._header_timer is None:
                self._header_timer = self.loop.call_later(header_s, self._header_deadline)

        def _disarm(self) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def _header_deadline(self) -> None:
            self._header_timer = None
            if self._between_requests() and not self.transport.is_closing():
                self.transport.close()

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            waiting[self] = None
            self._arm()
            if len(self.connections) > max_connections:
                oldest = next(iter(waiting))  # self when every other connection is inside a request
                waiting.pop(oldest)
                oldest.transport.close()

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            if not self._between_requests():  # the headers are in: the body deadlines take over
                self._disarm()
                waiting.pop(self, None)
                self._header_bytes = 0
            elif not self.transport.is_closing():
                self._arm()  # the first byte of the next request on a kept-alive connection
                self._header_bytes += len(data)
                if self._header_bytes > MAX_HEADER_BYTES:
                    self.transport.write(b"HTTP/1.1 431 Request Header Fields Too Large\r\nContent-Length: 0\r\n"
                                         b"Connection: close\r\n\r\n")
                    self.transport.close()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if self._between_requests() and not self.transport.is_closing():
                waiting[self] = None  # kept alive: uvicorn's keep-alive timer runs until the next byte

        def connection_lost(self, exc) -> None:
            self._disarm()
            waiting.pop(self, None)
            super().connection_lost(exc)

    return Guarded


class BodyDeadline:
    """ASGI middleware: a request body that stalls `idle_s` [s] or is not complete `total_s` [s] after the
    headers ends as a disconnect for the application and a 408 with `Connection: close` for the client."""

    def __init__(self, app, idle_s: float, total_s: float):
        self.app, self.idle_s, self.total_s = app, idle_s, total_s

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        loop = asyncio.get_running_loop()
        end = loop.time() + self.total_s
        body_done, expired, responded, answered = False, None, False, False  # answered: the 408 went out

        async def timed_receive():
            nonlocal body_done, expired, answered
            if expired is not None:
                return {"type": "http.disconnect"}
            if body_done:
                return await receive()
            wait_s = min(self.idle_s, end - loop.time())
            try:
                message = await asyncio.wait_for(receive(), max(wait_s, 0.0))
            except TimeoutError:
                expired = (f"no byte of the request body for {self.idle_s:g} s" if wait_s == self.idle_s else
                           f"the request body was not complete within {self.total_s:g} s")
                if not responded:
                    answered = True
                    await send({"type": "http.response.start", "status": 408, "headers": [
                        (b"content-type", b"application/json"), (b"connection", b"close"),
                        (b"cache-control", b"no-store")]})
                    await send({"type": "http.response.body", "body": json.dumps({"detail": expired}).encode()})
                return {"type": "http.disconnect"}
            body_done = message["type"] != "http.request" or not message.get("more_body", False)
            return message

        async def guarded_send(message):
            nonlocal responded
            if answered:
                return  # the client got its 408
            responded = True
            await send(message)

        await self.app(scope, timed_receive, guarded_send)


def run_server(app, host: str, port: int, timeouts: Timeouts, log_level: str = "info") -> None:
    """Serve `app` under uvicorn with `timeouts`' header deadline, keep-alive and connection bound (the body
    deadlines are the app's BodyDeadline middleware)."""
    import uvicorn

    protocol = guarded_protocol(timeouts.header_s, timeouts.connections())
    uvicorn.run(app, host=host, port=port, log_level=log_level, http=protocol,
                timeout_keep_alive=timeouts.keep_alive_s)
