"""random: the paper's random baseline as an agent, uniform over the 4 palette actions.

It knows nothing and learns nothing. Its actions come from its own `numpy.random.Generator` (never
the global RNG), reseeded at every `reset_task(seed=...)` from the agent arg `seed` (default 0) and
the unit's seed that the evaluation protocol passes, so every (pair, seed) unit draws its own
actions and a results file is reproduced exactly whatever `--jobs`, lanes or `--resume` did.

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

    def reset_task(self, seed: int | None = None) -> None:
        """A new unit: its own random stream (the stream just goes on when no unit seed is given)."""
        if seed is not None:
            self.rng = np.random.default_rng([self.seed, seed])

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
