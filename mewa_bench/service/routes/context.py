"""What every route needs from the app: its settings, database sessions, and the submitter behind a token."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Iterator

from fastapi import Path, Request

from mewa_bench.service.errors import ApiError
from mewa_bench.service.settings import Settings

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

    from mewa_bench.service.models import Token

MAX_ID = 2**63 - 1  # the largest id a database row can have
SubmissionId = Annotated[int, Path(ge=1, le=MAX_ID, description="A submission's id.")]
TOKEN_HINT = "tokens are made by the server's admin: mewa-bench serve token create NAME"


def settings_of(request: Request) -> Settings:
    """The app's settings."""
    return request.app.state.settings


def session(request: Request) -> Iterator[Session]:
    """A database session for one request (a FastAPI dependency)."""
    with request.app.state.sessions() as s:
        yield s


def submitter(request: Request) -> Token:
    """The live token in `Authorization: Bearer <token>`, or a 401 saying what is missing."""
    from mewa_bench.service.tokens import find_token

    header = request.headers.get("authorization")
    if not header:
        raise ApiError(401, "missing_token", f"this endpoint needs an API token: send 'Authorization: Bearer <token>' "
                                             f"({TOKEN_HINT})", headers={"WWW-Authenticate": "Bearer"})
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        raise ApiError(401, "missing_token", "the Authorization header must be 'Bearer <token>'",
                       headers={"WWW-Authenticate": "Bearer"})
    with request.app.state.sessions() as s:
        row = find_token(s, token.strip())
    if row is None:
        raise ApiError(401, "invalid_token", f"unknown or revoked API token ({TOKEN_HINT})",
                       headers={"WWW-Authenticate": "Bearer"})
    return row
