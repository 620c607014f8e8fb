"""The app factory: a FastAPI app over one service instance's settings and database.

Building the app applies the schema migrations (a no-op when they are applied). The OpenAPI
description is at /openapi.json (and readable at /docs, a page built from it, offline). Every error
is JSON `{"error": code, "detail": message}`, including FastAPI's own request validation errors and
an unexpected failure (a 500 naming no internals). Every answer carries the security headers
(`guards.SecurityHeaders`); submissions are received at most `limits.uploads_in_flight` at once.

Faults have answers of their own: a database outage is a 503 with Retry-After (`outages`), a full
disk a 507 (`storage`). For operators: `/api/live` (the process answers), `/api/ready` (the database
answers, the disk has more than its reserve free, the workers run; else 503 naming what is not) and
`/metrics` (Prometheus, `metrics`); every error answer is counted there by its reason.
"""

from __future__ import annotations

import json
from typing import Any

from mewa_bench.extras import require
from mewa_bench.service.settings import Settings

MULTIPART_SLACK = 64 * 1024  # form boundaries and fields around the uploaded files
DESCRIPTION = """The MEWA meta-RL benchmark as a service: suites, leaderboards (public and hidden test suites),
datasets, and submissions of results files (re-scored from their episodes) or agents (evaluated in a sandbox).
Submitting needs an API token: `Authorization: Bearer <token>`."""


def body_limits(settings: Settings):
    """The largest request body per path (the parts are checked one by one in the routes)."""
    limits = settings.limits

    def limit_of(path: str) -> int | None:
        """The body limit of a path."""
        if path == "/api/submissions/results":
            return limits.results_bytes + MULTIPART_SLACK
        if path == "/api/submissions/agent":
            return limits.agent_bytes + limits.checkpoint_bytes + MULTIPART_SLACK
        return MULTIPART_SLACK

    return limit_of


def create_app(settings: Settings) -> Any:
    """The ASGI app (FastAPI) of a service instance."""
    require("fastapi", "service", "mewa-bench serve")
    require("sqlalchemy", "service", "mewa-bench serve")
    from fastapi import FastAPI, Request
    from fastapi.exceptions import RequestValidationError
    from fastapi.responses import HTMLResponse, JSONResponse, Response
    from sqlalchemy.exc import SQLAlchemyError
    from starlette.exceptions import HTTPException

    from mewa_bench import __version__
    from mewa_bench.leaderboard.validate import SuiteCache
    from mewa_bench.service.db import make_engine, migrate, schema_revision, session_factory
    from mewa_bench.service.errors import ApiError
    from mewa_bench.service.jobs import queue_counts
    from mewa_bench.service.guards import INTERNAL_ERROR, SecurityHeaders, UploadGate
    from mewa_bench.service.limits import BodySizeLimit, RateLimiter
    from mewa_bench.service.metrics import Metrics
    from mewa_bench.service.outages import database_unavailable, is_outage
    from mewa_bench.service.storage import StorageGuard, is_disk_full
    from mewa_bench.service.web.docs_page import docs_html
    from mewa_bench.service.routes import datasets, leaderboards, operations, submissions, suites
    from mewa_bench.service import web  # the pages; included first, so its / and /leaderboards/<board> win

    make_data_dir(settings)
    engine = make_engine(settings.database_url)
    migrate(engine)
    app = FastAPI(title="MEWA benchmark service", version=__version__, description=DESCRIPTION, docs_url=None,
                  redoc_url=None)
    app.state.settings = settings
    app.state.engine = engine
    app.state.sessions = session_factory(engine)
    app.state.rate = RateLimiter()
    app.state.suites = SuiteCache()
    app.state.storage = storage = StorageGuard(settings.data_dir, settings.reserve_bytes)
    app.state.workers = lambda: (0, 0)  # (alive, expected): `server.run_server` sets its pool's
    app.state.metrics = metrics = Metrics(app.state.sessions, storage, lambda: app.state.workers())

    def answer(error: ApiError) -> JSONResponse:
        """An ApiError as its JSON answer, counted by its reason."""
        metrics.rejected(error.code, error.status)
        return JSONResponse(error.body(), status_code=error.status, headers=error.headers)

    @app.exception_handler(ApiError)
    async def api_error(request: Request, error: ApiError) -> JSONResponse:
        """An ApiError as its JSON answer."""
        return answer(error)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, error: RequestValidationError) -> JSONResponse:
        """A request FastAPI could not parse (a missing form field...) as a 400 naming the fields."""
        problems = "; ".join(f"{'.'.join(str(p) for p in e.get('loc', ()))}: {e.get('msg')}" for e in error.errors())
        return answer(ApiError(400, "invalid_request", f"malformed request: {problems}"))

    @app.exception_handler(HTTPException)
    async def http_error(request: Request, error: HTTPException) -> JSONResponse:
        """Starlette's own errors (unknown path, wrong method) in the same JSON form."""
        code = {404: "not_found", 405: "method_not_allowed"}.get(error.status_code, "http_error")
        return answer(ApiError(error.status_code, code, str(error.detail), getattr(error, "headers", None)))

    def fault(request: Request, error: Exception) -> JSONResponse:
        """A full disk (507), a database outage (503), else the JSON 500 of anything unexpected."""
        if is_disk_full(error):
            return answer(storage.refused())
        if is_outage(error):
            return answer(database_unavailable())
        import logging

        logging.getLogger("mewa_bench.service").error("%s %s failed", request.method, request.url.path,
                                                      exc_info=error)
        metrics.rejected("internal", 500)
        return JSONResponse(json.loads(INTERNAL_ERROR), status_code=500)

    app.add_exception_handler(SQLAlchemyError, fault)
    app.add_exception_handler(OSError, fault)

    @app.exception_handler(Exception)
    async def unexpected(request: Request, error: Exception) -> Response:
        """Anything else: a JSON 500 that names no internals (the server's log has the traceback)."""
        import logging

        metrics.rejected("internal", 500)
        logging.getLogger("mewa_bench.service").exception("%s %s failed", request.method, request.url.path)
        return Response(INTERNAL_ERROR, status_code=500, media_type="application/json")

    @app.get("/docs", include_in_schema=False)
    def docs() -> HTMLResponse:
        """The API reference page."""
        return HTMLResponse(docs_html(app.openapi()))

    @app.get("/api/health", tags=["service"], summary="Is the service up")
    def health() -> dict[str, Any]:
        """The database, its schema revision and the job queue."""
        with app.state.sessions() as s:
            counts = queue_counts(s)
        from mewa_bench.service.cgroups import cgroup_support

        return {"status": "ok", "version": __version__, "database": engine.dialect.name,
                "schema": schema_revision(engine), "jobs": counts, "sandbox_limits": cgroup_support().describe(),
                "uploads_ranked": settings.rank_uploads}

    for module in (web, suites, leaderboards, datasets, submissions, operations):
        app.include_router(module.router)
    app.add_middleware(BodySizeLimit, limit_of=body_limits(settings), count=metrics.rejected)
    app.add_middleware(UploadGate, paths=frozenset({"/api/submissions/results", "/api/submissions/agent"}),
                       limit=settings.limits.uploads_in_flight, count=metrics.rejected)
    app.add_middleware(SecurityHeaders)  # added last: the outermost, so every answer has the headers
    return app


def make_data_dir(settings: Settings) -> None:
    """The data dir at 0700 and the SQLite database file at 0600, made so or tightened to it when they exist
    (every command that opens the data dir calls this, so none leaves it readable by other users)."""
    import os

    settings.data_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
    os.chmod(settings.data_dir, 0o700)  # whatever the umask, and an existing dir too
    if settings.db_url is None:
        database = settings.data_dir / "service.db"
        if not database.exists():
            os.close(os.open(database, os.O_CREAT | os.O_WRONLY, 0o600))
        os.chmod(database, 0o600)
