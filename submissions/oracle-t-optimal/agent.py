"""oracle-t-optimal: the privileged upper reference, the best t-optimal policy for the known worker.

PRIVILEGED: the evaluator tells it the hidden pair, `reset_task({"task": Task.to_dict(), "worker":
[w_0, ...]})`, which only privileged runs do (`mewa-bench evaluate ... --privileged`); its results
are marked privileged and never ranked. It computes the exact expected return of every t-optimal
policy for that worker (`mewa_bench.design.exact.best_toptimal`) and plays the best one in every
episode: its expected score is the max-expected baseline, 1.0 by definition. It learns nothing.

Run it: `mewa-bench evaluate submissions/oracle-t-optimal/agent.py --suite narrow-v1 --privileged`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mewa_bench.design.exact import best_toptimal
from mewa_bench.design.policies import TOptimal
from mewa_bench.game.rules import state_from_observation
from mewa_bench.game.task import Task
from mewa_bench.protocol.agent import Transition, state_vector

PRIVILEGED = True
NUM_ACTIONS = 4


class OracleTOptimalAgent:
    """Plays the max-expected t-optimal policy of the pair it is told."""

    def __init__(self) -> None:
        self.task: Task | None = None
        self.policy: TOptimal | None = None
        self.expected_return = float("nan")
        self.memory: Any = None

    def reset_task(self, hidden: dict | None = None) -> None:
        """Learn the hidden pair and pick its best policy; a run that is not privileged is an error."""
        if hidden is None:
            raise ValueError("oracle-t-optimal is a privileged reference agent: it must be told the hidden pair "
                             "(run it with `mewa-bench evaluate ... --privileged`)")
        self.task = Task.from_dict(hidden["task"])
        worker = np.asarray(hidden["worker"], dtype=np.float64)
        self.policy, self.expected_return = best_toptimal(self.task, worker)
        self.memory = self.policy.initial_memory()

    def act(self, obs: np.ndarray) -> int:
        """The policy's action in the observed state."""
        if self.task is None or self.policy is None:
            raise RuntimeError("act() before reset_task(hidden): oracle-t-optimal must be told the pair first")
        state = state_from_observation(self.task, state_vector(obs))
        choice = self.policy.choices(self.task, state, self.memory)[0]
        self.memory = choice.memory
        return int(choice.action)

    def observe(self, transition: Transition) -> None:
        """Restart the policy's counters once the episode is over."""
        if transition.terminated or transition.truncated:
            self.end_episode()

    def end_episode(self) -> None:
        """The next episode starts with fresh counters."""
        if self.policy is not None:
            self.memory = self.policy.initial_memory()


def make_agent(observation_space: Any, action_space: Any) -> OracleTOptimalAgent:
    """Build the agent (it takes no agent args)."""
    if getattr(action_space, "n", NUM_ACTIONS) != NUM_ACTIONS:
        raise ValueError(f"expected the MEWA action space Discrete({NUM_ACTIONS}), got {action_space}")
    return OracleTOptimalAgent()
