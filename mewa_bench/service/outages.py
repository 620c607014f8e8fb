"""Database outages: how they are recognised, what the API answers during one, and how workers wait one out.

An outage is an error of the connection, not of a statement: the server refused or dropped the
connection, the pool timed out, SQLite's lock was busy past its timeout. The API answers a request
that needs the database with a 503 JSON error and `Retry-After` (never a generic 500). A worker
retries its database calls with a growing pause (0.5 s doubling to 5 s), logging the outage once
when it starts and once when it ends; nothing it does in an outage counts against an agent.
"""

from __future__ import annotations

import logging
import time
from typing import Callable, TypeVar

from mewa_bench.service.errors import ApiError

log = logging.getLogger("mewa_bench.service")
RETRY_AFTER = 5  # seconds a client is told to wait during an outage
FIRST_PAUSE, LONGEST_PAUSE = 0.5, 5.0
T = TypeVar("T")


def is_outage(error: BaseException) -> bool:
    """Whether an error is the database being unreachable (not a failed statement, not a full disk)."""
    from sqlalchemy import exc

    from mewa_bench.service.storage import is_disk_full

    if isinstance(error, exc.DBAPIError) and error.connection_invalidated:
        return True
    if isinstance(error, (exc.OperationalError, exc.InterfaceError, exc.TimeoutError)):
        return not is_disk_full(error)
    return False


def database_unavailable() -> ApiError:
    """The 503 answer of a request that needed the database during an outage."""
    return ApiError(503, "database_unavailable", f"the server's database cannot be reached right now; nothing was "
                                                 f"changed by this request, retry in {RETRY_AFTER} s",
                    headers={"Retry-After": str(RETRY_AFTER)})


def until_reachable(action: Callable[[], T], what: str, gone: Callable[[], bool] = lambda: False) -> T:
    """`action()`, called again after each outage error until it succeeds (or `gone()` says to stop retrying, then
    the error is raised); any other error is raised at once."""
    pause, since = FIRST_PAUSE, None
    while True:
        try:
            result = action()
        except Exception as e:
            if not is_outage(e) or gone():
                raise
            if since is None:
                since = time.monotonic()
                log.warning("%s: the database is unreachable (%s); retrying until it is back", what,
                            str(e).splitlines()[0][:200])
            time.sleep(pause)
            pause = min(LONGEST_PAUSE, pause * 2)
            continue
        if since is not None:
            log.warning("%s: the database is reachable again after %.1f s", what, time.monotonic() - since)
        return result
