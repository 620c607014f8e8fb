"""Suites: the list, each suite file as shipped, and its hashes. Hidden suites are never served."""

from __future__ import annotations

import hashlib
from functools import lru_cache
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse

from mewa_bench.design.suites import ALL_SUITES, load_suite, shipped_path
from mewa_bench.service.errors import ApiError, not_found
from mewa_bench.service.routes.context import settings_of
from mewa_bench.service.settings import HIDDEN_SUFFIX

router = APIRouter(prefix="/api/suites", tags=["suites"])


@lru_cache(maxsize=None)
def suite_summary(name: str) -> dict[str, Any]:
    """What the list says about a public suite (its content hash is what results files carry)."""
    suite = load_suite(name)
    path = shipped_path(name)
    return {"name": name, "version": suite.content["version"], "sha256": suite.sha256,
            "file_sha256": hashlib.sha256(path.read_bytes()).hexdigest(), "size": path.stat().st_size,
            "pairs": len(suite.pairs), "tasks": len(suite.tasks), "url": f"/api/suites/{name}"}


def _public(name: str) -> str:
    """A public suite name, or a 404 (saying so for a hidden one)."""
    if name.endswith(HIDDEN_SUFFIX):
        raise ApiError(404, "hidden_suite", f"suite {name!r} is a hidden test suite: the server never serves it")
    if name not in ALL_SUITES:
        raise not_found(f"suite {name!r} (public suites: {', '.join(ALL_SUITES)})")
    return name


@router.get("", summary="The public suites")
def list_suites(request: Request) -> list[dict[str, Any]]:
    """Every public suite with its content hash, file hash, size and the seeds its boards rank with."""
    settings = settings_of(request)
    return [{**suite_summary(name), "seeds": len(settings.seeds_for(name))} for name in ALL_SUITES]


@router.get("/{name}", summary="Download a suite file", response_class=FileResponse)
def download_suite(name: str) -> FileResponse:
    """The suite file exactly as shipped (`mewa-bench suites verify` checks it)."""
    name = _public(name)
    info = suite_summary(name)
    return FileResponse(shipped_path(name), media_type="application/json", filename=f"{name}.json",
                        headers={"X-Suite-SHA256": info["sha256"], "X-Content-SHA256": info["file_sha256"]})


@router.get("/{name}/sha256", summary="A suite's hashes")
def suite_hash(name: str) -> dict[str, str]:
    """`sha256`: the suite's content hash (results files must carry it); `file_sha256`: of the file's bytes."""
    info = suite_summary(_public(name))
    return {"name": name, "sha256": info["sha256"], "file_sha256": info["file_sha256"]}
