"""API tokens: one per submitter, created by the admin command, stored only as a sha256.

A token is 256 random bits (`secrets`), so a plain sha256 is a safe way to store it: there is no
dictionary to try. The token itself is shown once, when it is made.
"""

from __future__ import annotations

import hashlib
import re
import secrets
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

    from mewa_bench.service.models import Token

PREFIX = "mewa_"
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@-]{0,99}$")


class TokenError(ValueError):
    """A token command that cannot be done (a taken name, an unknown one)."""


@dataclass(frozen=True)
class TokenInfo:
    """What `token list` shows about a token (never the token itself)."""

    name: str
    created: float
    revoked: bool
    rate_per_minute: int | None
    daily_results: int | None
    daily_agents: int | None


def hash_token(token: str) -> str:
    """The stored form of a token."""
    return hashlib.sha256(token.encode()).hexdigest()


def create_token(session: Session, name: str, rate_per_minute: int | None = None, daily_results: int | None = None,
                 daily_agents: int | None = None) -> str:
    """Make a token for submitter `name`; returns the token (the database keeps only its hash)."""
    from sqlalchemy import select

    from mewa_bench.service.models import Token

    if not NAME_RE.match(name):
        raise TokenError(f"token name {name!r}: use 1-100 letters, digits, '.', '_', '@' or '-'")
    for what, value in (("rate limit", rate_per_minute), ("daily results quota", daily_results),
                        ("daily agents quota", daily_agents)):
        if value is not None and value < 0:
            raise TokenError(f"{what} must be >= 0, got {value}")
    if session.scalar(select(Token.id).where(Token.name == name)) is not None:
        raise TokenError(f"a token named {name!r} exists already (revoke it first, or choose another name)")
    token = PREFIX + secrets.token_urlsafe(32)
    session.add(Token(name=name, token_hash=hash_token(token), created=time.time(), revoked=False,
                      rate_per_minute=rate_per_minute, daily_results=daily_results, daily_agents=daily_agents))
    session.flush()
    return token


def revoke_token(session: Session, name: str) -> None:
    """Revoke the token named `name` (its submissions stay)."""
    from sqlalchemy import select

    from mewa_bench.service.models import Token

    token = session.scalar(select(Token).where(Token.name == name))
    if token is None:
        raise TokenError(f"no token named {name!r}")
    token.revoked = True


def list_tokens(session: Session) -> list[TokenInfo]:
    """Every token, by name."""
    from sqlalchemy import select

    from mewa_bench.service.models import Token

    return [TokenInfo(t.name, t.created, t.revoked, t.rate_per_minute, t.daily_results, t.daily_agents)
            for t in session.scalars(select(Token).order_by(Token.name))]


def find_token(session: Session, token: str) -> Token | None:
    """The live token row of a presented token, or None."""
    from sqlalchemy import select

    from mewa_bench.service.models import Token

    row = session.scalar(select(Token).where(Token.token_hash == hash_token(token)))
    return None if row is None or row.revoked else row
