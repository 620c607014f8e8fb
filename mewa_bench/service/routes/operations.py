"""What an operator watches: liveness, readiness and Prometheus metrics (`metrics`)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response

router = APIRouter(tags=["service"])
RETRY_SECONDS = 5


@router.get("/api/live", summary="Does the process answer")
def live() -> dict[str, str]:
    """Always `{"status": "live"}` while the API process serves (needs neither the database nor the disk)."""
    return {"status": "live"}


@router.get("/api/ready", summary="Can the service take submissions", response_model=None,
            responses={503: {"description": "Not ready: `checks` says what is not"}})
def ready(request: Request) -> Any:
    """The database answers, the data dir's disk has more than its reserve free, this server's workers run."""
    from mewa_bench.service.readiness import readiness

    state = request.app.state
    body = readiness(state.engine, state.storage, state.workers())
    headers = None if body["ready"] else {"Retry-After": str(RETRY_SECONDS)}
    return JSONResponse(body, status_code=200 if body["ready"] else 503, headers=headers)


@router.get("/metrics", include_in_schema=False, response_model=None)
def prometheus(request: Request) -> Any:
    """Prometheus metrics (text exposition format, or OpenMetrics if the scraper asks for it)."""
    data, content_type = request.app.state.metrics.render(request.headers.get("accept"))
    return Response(data, media_type=content_type)
