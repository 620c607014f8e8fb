"""random: the paper's random baseline as an agent, uniform over the 4 palette actions.

It knows nothing and learns nothing. Its actions come from its own `numpy.random.Generator` (never
the global RNG), seeded once from the agent arg `seed` (default 0) when the agent is built, so the
units of a run draw different actions and a sequential run is reproducible (with `--jobs`, which
units share a process varies, so use the default `--jobs 1` to reproduce a results file).

Run it: `mewa-bench evaluate submissions/random/agent.py --suite narrow-v1`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

PRIVILEGED = False
NUM_ACTIONS = 4


class RandomAgent:
    """Picks each action with probability 1/4, whatever it observes."""

    def __init__(self, seed: int | str = 0) -> None:
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)

    def reset_task(self) -> None:
        """Nothing to forget (the random stream goes on, so units do not replay the same actions)."""

    def act(self, obs: np.ndarray) -> int:
        """A uniformly random palette colour."""
        return int(self.rng.integers(NUM_ACTIONS))

    def observe(self, transition: Any) -> None:
        """Nothing to learn."""

    def end_episode(self) -> None:
        """Nothing to adapt."""


def make_agent(observation_space: Any, action_space: Any, seed: int | str = 0) -> RandomAgent:
    """Build the agent; agent arg: seed."""
    if getattr(action_space, "n", NUM_ACTIONS) != NUM_ACTIONS:
        raise ValueError(f"expected the MEWA action space Discrete({NUM_ACTIONS}), got {action_space}")
    return RandomAgent(seed)
