"""ASGI middleware every answer passes: security headers on every page, and a bound on uploads read at once.

Security headers: a content security policy (the pages load nothing from elsewhere and run no
script), no framing, no MIME sniffing, no referrer. The upload gate answers a 503 JSON error with
Retry-After when `limit` submissions are already being received: it reads the refused request's
body and drops it as it comes (nothing is kept, so a burst of large uploads cannot pile up in the
API process; a client that is still sending would otherwise see its connection reset, not the 503).
"""

from __future__ import annotations

import json
import threading
from typing import Any, Callable

SECURITY_HEADERS = (
    (b"content-security-policy", b"default-src 'none'; img-src 'self'; style-src 'unsafe-inline'; "
                                 b"base-uri 'none'; form-action 'none'; frame-ancestors 'none'"),
    (b"x-frame-options", b"DENY"),
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"no-referrer"),
)
INTERNAL_ERROR = json.dumps({"error": "internal", "detail": "the server failed to answer this request"}).encode()
RETRY_SECONDS = 1
DRAIN_LIMIT = 256 << 20  # past this many bytes of a refused body, the connection is closed instead


class SecurityHeaders:
    """Adds SECURITY_HEADERS to every HTTP answer (replacing any of the same name)."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: dict, receive: Callable, send: Callable) -> None:
        """Pass the request on; add the headers to the answer's start."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        names = {name for name, _ in SECURITY_HEADERS}
        started = False

        async def with_headers(message: dict) -> None:
            """The answer's start with the headers."""
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                kept = [(k, v) for k, v in message.get("headers", []) if k.lower() not in names]
                message = {**message, "headers": kept + list(SECURITY_HEADERS)}
            await send(message)

        try:
            await self.app(scope, receive, with_headers)
        except Exception:
            # An unexpected error is answered by the framework's outermost layer, past this one: answer its JSON
            # 500 here, with the headers, and let the error go on to be logged (the layer sees the answer started).
            if not started:
                await with_headers({"type": "http.response.start", "status": 500,
                                    "headers": [(b"content-type", b"application/json")]})
                await send({"type": "http.response.body", "body": INTERNAL_ERROR})
            raise


class UploadGate:
    """At most `limit` requests on `paths` at once; the next ones get a 503 with Retry-After."""

    def __init__(self, app: Any, paths: frozenset[str], limit: int,
                 count: Callable[[str, int], None] = lambda reason, status: None) -> None:
        self.app, self.paths, self.limit, self.count = app, paths, limit, count
        self.in_flight = 0
        self._lock = threading.Lock()

    async def __call__(self, scope: dict, receive: Callable, send: Callable) -> None:
        """Pass the request on if there is room, else answer 503."""
        if scope["type"] != "http" or scope["path"] not in self.paths:
            await self.app(scope, receive, send)
            return
        with self._lock:
            admitted = self.in_flight < self.limit
            if admitted:
                self.in_flight += 1
        if not admitted:
            self.count("busy", 503)
            drained = await _drain(receive)
            await _busy(send, self.limit, close=not drained)
            return
        try:
            await self.app(scope, receive, send)
        finally:
            with self._lock:
                self.in_flight -= 1


async def _drain(receive: Callable) -> bool:
    """Read a request's body and drop it; False if the client went away or it passed DRAIN_LIMIT."""
    seen = 0
    while True:
        message = await receive()
        if message["type"] != "http.request":
            return False
        seen += len(message.get("body", b""))
        if seen > DRAIN_LIMIT:
            return False
        if not message.get("more_body", False):
            return True


async def _busy(send: Callable, limit: int, close: bool) -> None:
    """The 503 JSON answer."""
    body = json.dumps({"error": "busy", "detail": f"the server is receiving {limit} submissions already, its limit; "
                                                  f"retry in {RETRY_SECONDS} s"}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
               (b"retry-after", str(RETRY_SECONDS).encode())] + ([(b"connection", b"close")] if close else [])
    await send({"type": "http.response.start", "status": 503, "headers": headers})
    await send({"type": "http.response.body", "body": body})
