"""Limits per token and per request: a sliding-window rate limit, daily quotas, and upload sizes.

The rate limit counts a token's submissions in the API process (one process serves the API); the
quotas count its stored submissions in the database, inside the transaction that adds a new one,
so concurrent uploads cannot overshoot them. The body-size middleware refuses an upload larger
than its endpoint allows before reading it (Content-Length) or as soon as it passes the limit
(chunked bodies), so an oversized upload never reaches the disk.
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from typing import Any, Callable

from mewa_bench.service.errors import ApiError

WINDOW = 60.0  # seconds of the rate limit
DAY = 86400.0


class RateLimiter:
    """At most `limit` events per token in any WINDOW seconds."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._events: dict[int, deque[float]] = {}
        self._lock = threading.Lock()
        self._clock = clock

    def check(self, token_id: int, limit: int) -> None:
        """Count one event for the token, or raise a 429 ApiError with the time to wait."""
        now = self._clock()
        with self._lock:
            events = self._events.setdefault(token_id, deque())
            while events and events[0] <= now - WINDOW:
                events.popleft()
            if len(events) >= limit:
                wait = max(1, int(events[0] + WINDOW - now + 0.999))
                raise ApiError(429, "rate_limited", f"rate limit of {limit} submissions per minute reached for this "
                                                    f"token; retry in {wait} s", headers={"Retry-After": str(wait)})
            events.append(now)


def quota_error(kind: str, limit: int, oldest: float, now: float) -> ApiError:
    """The 429 of a full daily quota; `oldest` is when the oldest counted submission was made."""
    wait = max(1, int(oldest + DAY - now + 0.999))
    return ApiError(429, "quota_exceeded", f"daily quota of {limit} {kind} submissions reached for this token; the "
                                           f"next one is possible in {wait} s", headers={"Retry-After": str(wait)})


class BodySizeLimit:
    """ASGI middleware: a 413 JSON error for request bodies above the limit of their path."""

    def __init__(self, app: Any, limit_of: Callable[[str], int | None],
                 count: Callable[[str, int], None] = lambda reason, status: None) -> None:
        self.app, self.limit_of, self.count = app, limit_of, count

    async def __call__(self, scope: dict, receive: Callable, send: Callable) -> None:
        """Pass the request on, counting its body against the limit of its path."""
        limit = self.limit_of(scope["path"]) if scope["type"] == "http" else None
        if limit is None:
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            self.count("too_large", 413)
            await _too_large(send, int(declared), limit)
            return
        seen = 0
        exceeded = False

        async def counted_receive() -> dict:
            """The next body chunk; past the limit, a disconnect."""
            nonlocal seen, exceeded
            if exceeded:
                return {"type": "http.disconnect"}
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    exceeded = True  # the app sees a client that went away; its answer is replaced below
                    return {"type": "http.disconnect"}
            return message

        async def filtered_send(message: dict) -> None:
            """The app's answer, dropped once the body was over the limit."""
            if not exceeded:
                await send(message)

        try:
            await self.app(scope, counted_receive, filtered_send)
        except Exception:
            if not exceeded:
                raise
        if exceeded:
            self.count("too_large", 413)
            await _too_large(send, seen, limit)


def too_large_detail(size: int, limit: int) -> str:
    """The message of a 413."""
    return f"the upload is larger than this endpoint's limit of {limit:,} bytes (at least {size:,} bytes were sent)"


async def _too_large(send: Callable, size: int, limit: int) -> None:
    """Send the 413 JSON answer."""
    body = json.dumps({"error": "too_large", "detail": too_large_detail(size, limit)}).encode()
    await send({"type": "http.response.start", "status": 413,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})
