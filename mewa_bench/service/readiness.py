"""Readiness: whether a service instance can take submissions now, and if not, which check fails."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sqlalchemy.engine import Engine

    from mewa_bench.service.storage import StorageGuard

OK = "ok"


def readiness(engine: Engine, storage: StorageGuard, workers: tuple[int, int]) -> dict[str, Any]:
    """`{"ready": bool, "checks": {database, disk, workers}}`, each check "ok" or what is wrong."""
    from sqlalchemy import text

    from mewa_bench.service.outages import is_outage

    checks: dict[str, str] = {}
    try:
        with engine.connect() as connection:
            connection.execute(text("SELECT 1"))
        checks["database"] = OK
    except Exception as e:
        if not is_outage(e):
            raise
        checks["database"] = f"unreachable: {str(e).splitlines()[0][:200]}"
    free = storage.free()
    checks["disk"] = OK if free >= storage.reserve else (f"{free:,} bytes free on the data dir's disk, below the "
                                                         f"reserve of {storage.reserve:,}: uploads get 507")
    alive, expected = workers
    checks["workers"] = OK if alive >= expected else f"{alive} of {expected} worker processes running"
    return {"ready": all(v == OK for v in checks.values()), "checks": checks,
            "free_bytes": free, "reserve_bytes": storage.reserve, "workers_alive": alive, "workers_expected": expected}
