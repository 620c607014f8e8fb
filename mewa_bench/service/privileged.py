"""Privileged agents the server knows, so that a results file cannot pass one off as an ordinary agent.

A results upload says itself whether its run was privileged (told the hidden pair); the server
cannot watch a run it did not play, so such rows are labelled self-reported. What it can check, it
checks: an upload that claims not to be privileged is refused when its agent file's sha256 is that
of an agent known to be privileged: the shipped reference agents whose results are privileged, and
every agent the server itself ranked as privileged.
"""

from __future__ import annotations

import functools
import re
from pathlib import Path
from typing import TYPE_CHECKING

from mewa_bench.service.errors import unprocessable

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

SHIPPED = Path(__file__).resolve().parents[2] / "submissions"  # the checkout's reference submissions, if present
_HEAD_BYTES = 4096  # a results file's agent block comes first
_AGENT_BLOCK = re.compile(r'"agent":\s*\{(?P<body>(?:[^{}]|\{[^{}]*\})*)\}')  # agent_args: one level inside


@functools.lru_cache(maxsize=1)
def shipped_privileged(root: Path = SHIPPED) -> frozenset[str]:
    """The agent sha256s of the shipped submissions whose results are privileged."""
    found = set()
    for results in sorted(root.glob("*/results-*.json")) if root.is_dir() else []:
        with open(results, "rb") as f:
            head = f.read(_HEAD_BYTES).decode("utf-8", "replace")
        block = _AGENT_BLOCK.search(head)
        if block and re.search(r'"privileged":\s*true', block["body"]):
            digest = re.search(r'"sha256":\s*"([0-9a-f]{64})"', block["body"])
            if digest:
                found.add(digest.group(1))
    return frozenset(found)


def known_privileged(session: Session) -> set[str]:
    """Every agent sha256 known to be privileged: the shipped ones and those of privileged board entries."""
    from sqlalchemy import select

    from mewa_bench.service.models import BoardEntry

    return set(shipped_privileged()) | set(session.scalars(select(BoardEntry.agent_sha256)
                                                           .where(BoardEntry.privileged.is_(True)).distinct()))


def refuse_unprivileged_claim(known: set[str] | frozenset[str], agent_sha256: object, privileged: bool) -> None:
    """A 422 if a results file claims that the run of a `known` privileged agent was not privileged."""
    if not privileged and isinstance(agent_sha256, str) and agent_sha256 in known:
        raise unprocessable("privileged_agent", f"results file: agent.sha256 {agent_sha256} is a privileged agent's "
                                                f"(it is told the hidden pair), but the file says agent.privileged is "
                                                f"not true; a privileged run is never ranked as an ordinary one")
