"""The game's colour symmetry: renaming the palette's colours maps a task, its states, observations and actions
onto another task's, step for step.

Nothing in the rules (SPEC section 2) depends on which palette colour is which: a task's `colors` and `order`
name colours, and a mistake's type counts open structures, not their colours. So for a permutation `p` of the
palette (colour c is renamed p[c]), the task with colours p[colors] and order p[order] (the same K, M, rewards,
worker blocks and worker distribution) faced with action p[a] in the renamed state moves exactly as the original
does with a, and its observation is the original's with the per-colour entries moved. Each wide task is one of
24 renamings of its structure (N, K, M, worker blocks); learners that see histories under random renamings
meet every renaming of the structures they are trained on.
"""

from __future__ import annotations

import numpy as np

from mewa_bench.game.palette import (NUM_COLORS, OBS_AGENT_BLOCKS, OBS_COMPLETED, OBS_MISTAKE_FLAGS, OBS_SIZE,
                                      OBS_STRUCTURE_BLOCKS)
from mewa_bench.game.task import Task

__all__ = ["observation_gather", "relabelled_task", "renamings"]


def _checked(p: np.ndarray | list[int] | tuple[int, ...]) -> np.ndarray:
    p = np.asarray(p, dtype=np.int64)
    if sorted(p.tolist()) != list(range(NUM_COLORS)):
        raise ValueError(f"a renaming of the palette must be a permutation of 0..{NUM_COLORS - 1}, got {p.tolist()}")
    return p


def observation_gather(p: np.ndarray | list[int] | tuple[int, ...]) -> np.ndarray:
    """Indices g with renamed_obs = obs[..., g] when colour c is renamed p[c] (int64[OBS_SIZE])."""
    p = _checked(p)
    gather = np.arange(OBS_SIZE)
    for group in (OBS_AGENT_BLOCKS, OBS_STRUCTURE_BLOCKS, OBS_MISTAKE_FLAGS, OBS_COMPLETED):
        slots = np.arange(OBS_SIZE)[group]  # slot of colour c: slots[c]
        gather[slots[p]] = slots
    return gather


def relabelled_task(task: Task, p: np.ndarray | list[int] | tuple[int, ...]) -> Task:
    """`task` with colour c renamed p[c]: the same game under other colour names."""
    p = _checked(p)
    fields = task.to_dict()
    fields["colors"] = sorted(int(p[c]) for c in task.colors)
    fields["order"] = [int(p[c]) for c in task.order]
    return Task.from_dict(fields)


def renamings(rng: np.random.Generator, count: int) -> np.ndarray:
    """`count` renamings of the palette drawn uniformly with `rng` (int64[count, NUM_COLORS])."""
    return np.argsort(rng.random((count, NUM_COLORS)), axis=1)
