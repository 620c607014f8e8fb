"""Per-lane seeding of the batched envs: lane i draws its pairs and luck keys as a `MewaEnv` would.

`reset(seed=[s_0, ..., s_n-1])` on a batched env gives each lane its own generator, seeded as
`MewaEnv.reset(seed=s_i)` seeds the scalar env's, and draws from it in the scalar env's order (pairs
SCALAR_PAIR_BATCH at a time, then one luck key per episode). So lane i plays the episodes that
Gymnasium's `SyncVectorEnv` over `MewaEnv` plays in its sub-env i for the same seeds and actions.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from gymnasium.utils import seeding

from mewa_bench.envs.pairs import SCALAR_PAIR_BATCH, PairSource
from mewa_bench.game import luck
from mewa_bench.game.palette import NUM_COLORS


def lane_seeds(seed: Any, num_envs: int) -> list[int | None] | None:
    """A per-lane seed list as a list of ints or None, or None if `seed` is not a sequence; ValueError if bad."""
    if seed is None or isinstance(seed, (int, np.integer)):
        return None
    if isinstance(seed, (str, bytes, bool)) or not isinstance(seed, (Sequence, np.ndarray)):
        raise ValueError(f"seed must be an int, a list of {num_envs} ints (or None) or None, got {seed!r}")
    seeds = list(seed)
    if len(seeds) != num_envs:
        raise ValueError(f"a list of seeds needs one per sub-env: {num_envs}, got {len(seeds)}")
    for i, s in enumerate(seeds):
        if s is not None and (isinstance(s, (bool, np.bool_)) or not isinstance(s, (int, np.integer)) or s < 0):
            raise ValueError(f"seed of sub-env {i} must be a non-negative int or None, got {s!r}")
    return [None if s is None else int(s) for s in seeds]


class LaneGenerators:
    """One generator and one queue of sampled pairs per lane."""

    def __init__(self, num_envs: int) -> None:
        self.rngs: list[np.random.Generator | None] = [None] * num_envs
        self.pending: list[list[tuple[int, list[float]]]] = [[] for _ in range(num_envs)]

    def seed(self, seeds: Sequence[int | None], rows: np.ndarray) -> None:
        """Seed the lanes in `rows` whose seed is not None (their queued pairs are dropped, as in `MewaEnv`)."""
        for i in rows.tolist():
            if seeds[i] is not None:
                self.rngs[i] = seeding.np_random(seeds[i])[0]
                self.pending[i].clear()

    def clear_pending(self) -> None:
        """Forget the queued pairs (the pair source changed)."""
        for queue in self.pending:
            queue.clear()

    def _rng(self, i: int) -> np.random.Generator:
        if self.rngs[i] is None:  # never seeded: an unseeded generator, as a scalar env would get
            self.rngs[i] = seeding.np_random()[0]
        return self.rngs[i]

    def draw(self, source: PairSource, rows: np.ndarray, new_pairs: bool,
             task_idx: np.ndarray, workers: np.ndarray) -> np.ndarray:
        """For each lane in `rows`: a new pair written into `task_idx`/`workers` (if `new_pairs`), then
        a luck key; returns the keys, uint64 [len(rows)]."""
        keys = np.zeros(len(rows), dtype=np.uint64)
        for k, i in enumerate(rows.tolist()):
            rng = self._rng(i)
            if new_pairs:
                if not self.pending[i]:
                    tasks, ws = source.sample(rng, SCALAR_PAIR_BATCH)
                    self.pending[i].extend(reversed(list(zip(tasks.tolist(), ws.tolist()))))
                t, w = self.pending[i].pop()
                n = source.tasks[t].N
                task_idx[i] = t
                workers[i, :NUM_COLORS] = 0.0
                workers[i, :n] = w[:n]
            keys[k] = int(rng.integers(0, luck.KEY_BOUND))
        return keys
