"""An agent file that plays a named policy of the task design, for recording datasets.

`mewa-bench record --policy NAME` runs this file (privileged: it is told the pair's task, and for
`max-expected` the worker) with agent args `policy` and `seed`. Policies: `random`,
`random-task-specific`, `toptimal(rho1=..,rho2=..,q=..)` and `max-expected` (the best t-optimal
policy for the worker: the max-expected baseline). It is a data generator, never a ranked agent.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

PRIVILEGED = True
MAX_EXPECTED = "max-expected"
AGENT_FILE = Path(__file__)


class PolicyPlayer:
    """Plays one policy; the task (and worker) arrive with reset_task(hidden)."""

    def __init__(self, policy: str, seed: int) -> None:
        from mewa_bench.design.policies import policy_from_name

        if policy != MAX_EXPECTED:
            policy_from_name(policy)  # fail at construction on an unknown name
        self.policy_name = policy
        self.rng = np.random.default_rng(seed)
        self.player: Any = None

    def reset_task(self, hidden: dict | None = None) -> None:
        """Set up the policy for the pair's task (and worker, for max-expected)."""
        from mewa_bench.design.exact import best_toptimal
        from mewa_bench.design.policies import PolicyAgent
        from mewa_bench.game.task import Task

        if hidden is None:
            raise ValueError("the policy agent must be run privileged (it is told the task)")
        task = Task.from_dict(hidden["task"])
        name = self.policy_name
        if name == MAX_EXPECTED:
            name = best_toptimal(task, hidden["worker"])[0].name
        self.player = PolicyAgent(name, task, self.rng)

    def act(self, observation: np.ndarray) -> int:
        """The policy's action for the observed state."""
        from mewa_bench.protocol.agent import state_vector

        return self.player.act_observation(state_vector(observation))

    def end_episode(self) -> None:
        """Policies restart their counters at every episode."""
        self.player.reset()


def check_policy_name(policy: str) -> None:
    """Raise ValueError, naming the choices, unless `policy` is a baseline this agent can play."""
    from mewa_bench.design.policies import policy_from_name

    if policy == MAX_EXPECTED:
        return
    try:
        policy_from_name(policy)
    except ValueError:
        raise ValueError(f"unknown policy {policy!r}: expected random, random-task-specific, {MAX_EXPECTED}, "
                         "toptimal(rho1=R1,rho2=R2,q=Q), or an agent .py file") from None


def make_agent(observation_space: Any, action_space: Any, policy: str = "random", seed: str = "0") -> PolicyPlayer:
    """Agent args: policy (name), seed."""
    return PolicyPlayer(policy, int(seed))
