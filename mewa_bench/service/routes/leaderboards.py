"""Leaderboards as JSON: every board (public suites and hidden suites), and each one's ranked rows.

The HTML pages of the same boards are `service.web`'s.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, Request

from mewa_bench.service import boards
from mewa_bench.service.errors import not_found
from mewa_bench.service.routes.context import session, settings_of

router = APIRouter(tags=["leaderboards"])


@router.get("/api/leaderboards", summary="Every board")
def list_boards(request: Request, db=Depends(session)) -> list[dict[str, Any]]:
    """Public and hidden boards with their number of entries and best mean score."""
    return boards.boards_index(db, settings_of(request))


@router.get("/api/leaderboards/{name}", summary="One board")
def get_board(name: str, request: Request, db=Depends(session)) -> dict[str, Any]:
    """Ranked rows (agents, privileged agents unranked, the suite's reference lines) with adaptation curves."""
    content = boards.board(db, settings_of(request), name)
    if content is None:
        raise not_found(f"leaderboard {name!r}")
    return content
