"""random-task-specific: the paper's random task-specific baseline policy as an agent.

The policy knows the game but ignores the worker: in critical state 1 it allows leftover blocks
with probability 1/2, then takes a safe action (if one exists) or the risky one with probability
1/2 each; in critical state 2 it postpones or completes with probability 1/2 each; otherwise it
hands the current sub-goal's colour (`mewa_bench.design.policies.RandomTaskSpecific`).

It is not told the task. It knows the public task lists of the shipped suites (agent arg `suite`:
comma-separated suite names or paths, default all shipped suites) and infers its task from
observations exactly as the bayes-adaptive agent does: the candidates are the known tasks whose
first observation matches, and every step drops those whose rules cannot produce the observed
transition; it acts for the first candidate left. On narrow-v1 that is the right task from the
first step, so the agent plays exactly the baseline policy; on tasks that share their first
observation with another it may act for the wrong one until a completed structure tells them apart.
Its coin flips come from its own generator, seeded once from the agent arg `seed` when it is built
(the stream goes on across units, so units do not replay the same coin flips).

Run it: `mewa-bench evaluate submissions/random-task-specific/agent.py --suite narrow-v1`.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from mewa_bench.design.policies import RandomTaskSpecific
from mewa_bench.design.suites import SHIPPED_SUITES
from mewa_bench.game.rules import state_from_observation
from mewa_bench.protocol.agent import Transition, state_vector
from mewa_bench.agents.task_inference import TaskBelief, public_tasks

PRIVILEGED = False
NUM_ACTIONS = 4


class RandomTaskSpecificAgent:
    """Plays the random task-specific policy for the task it infers."""

    policy = RandomTaskSpecific()

    def __init__(self, suite: str = ",".join(SHIPPED_SUITES), seed: int | str = 0) -> None:
        self.task_belief = TaskBelief(public_tasks(suite))
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)
        self.reset_task()

    def reset_task(self, seed: int | None = None) -> None:
        """A new hidden pair: every known task is possible again; coin flips reseeded from the unit's seed."""
        if seed is not None:
            self.rng = np.random.default_rng([self.seed, seed])
        self.task_belief.reset()
        self.episode_starting = True

    def act(self, obs: np.ndarray) -> int:
        """One draw from the policy's action distribution in the candidate task's state."""
        obs = state_vector(obs)  # the 18 floats, also in sapien mode
        if self.episode_starting:
            self.task_belief.start_episode(obs)
            self.episode_starting = False
        task = self.task_belief.task
        if task is None:  # an unknown task: play uniformly at random
            return int(self.rng.integers(NUM_ACTIONS))
        options = self.policy.choices(task, state_from_observation(task, obs), ())
        return int(options[0].action if len(options) == 1 else self.draw(options))

    def draw(self, options: Sequence[Any]) -> int:
        """The action of one option drawn with the options' probabilities."""
        u = self.rng.random()
        for option in options:
            u -= option.prob
            if u < 0:
                return option.action
        return options[-1].action

    def observe(self, transition: Transition) -> None:
        """Drop the task candidates the step rules out."""
        self.task_belief.update(transition)
        if transition.terminated or transition.truncated:
            self.episode_starting = True

    def end_episode(self) -> None:
        """The next act() starts an episode (of the same pair)."""
        self.episode_starting = True


def make_agent(observation_space: Any, action_space: Any, **kwargs: Any) -> RandomTaskSpecificAgent:
    """Build the agent; agent args: suite, seed."""
    if getattr(action_space, "n", NUM_ACTIONS) != NUM_ACTIONS:
        raise ValueError(f"expected the MEWA action space Discrete({NUM_ACTIONS}), got {action_space}")
    return RandomTaskSpecificAgent(**kwargs)
