"""What the MCAP and Rerun logs share: readable event texts, their severity, a run's identity."""

from __future__ import annotations

import hashlib
import json
from typing import Any

from mewa_bench.game.palette import COLOR_NAMES
from mewa_bench.game.rules import Event
from mewa_bench.protocol.trajectory import RunInfo

# Events that set the team back are warnings; progress is information.
WARNING_KINDS = frozenset({"mistake", "structure_returned"})


def color_name(color: int) -> str:
    """Palette name of a colour index, or the index itself if it is out of the palette."""
    return COLOR_NAMES[color] if 0 <= color < len(COLOR_NAMES) else f"colour {color}"


def event_text(event: Event) -> str:
    """What happened, in words: "mistake on blue (type 2)"."""
    color = color_name(event.color)
    if event.kind == "mistake":
        return f"mistake on {color} (type {event.value})"
    if event.kind == "structure_completed":
        return f"{color} structure completed"
    if event.kind == "structure_returned":
        return f"{color} structure returned to the agent ({event.value} blocks)"
    if event.kind == "subgoal_reached":
        return f"sub-goal {event.value} ({color}) reached"
    return f"{event.kind} on {color} ({event.value})"


def event_message(pair: int, seed: int, episode: int, step: int, event: Event) -> str:
    """An event with where it happened: "pair 3 seed 0 ep 2 step 5: mistake on blue (type 2)"."""
    return f"pair {pair} seed {seed} ep {episode} step {step}: {event_text(event)}"


def is_warning(event: Event) -> bool:
    """Whether an event is logged as a warning (mistakes, returned structures) rather than info."""
    return event.kind in WARNING_KINDS


def run_metadata(run: RunInfo) -> dict[str, str]:
    """The run's description as string key/values (MCAP metadata, Rerun properties)."""
    meta = {
        "agent": run.agent, "agent_sha256": run.agent_sha256, "suite": run.suite, "suite_sha256": run.suite_sha256,
        "seeds": ",".join(str(s) for s in run.seeds), "episodes_per_pair": str(run.episodes_per_pair),
        "env_id": run.env_id, "env_version": run.env_version, "package_version": run.package_version,
        "mode": run.mode, "protocol_version": str(run.protocol_version),
    }
    for key, value in sorted(run.extra.items()):
        meta.setdefault(key, value if isinstance(value, str) else json.dumps(value, sort_keys=True))
    return meta


def run_digest(run: RunInfo) -> str:
    """A hex digest that identifies the run's settings (same agent, suite, seeds and mode give the same)."""
    key: dict[str, Any] = run_metadata(run)
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()
