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

from typing import Any, NamedTuple, Sequence

import numpy as np

from mewa_bench.design.policies import RandomTaskSpecific
from mewa_bench.design.suites import SHIPPED_SUITES, load_suite
from mewa_bench.game.rules import (initial_state, is_terminal, observation, outcomes, state_from_observation,
                                   step_reward)
from mewa_bench.game.task import Task
from mewa_bench.protocol.agent import Transition

PRIVILEGED = False
NUM_ACTIONS = 4
REWARD_TOLERANCE = 1e-6


class Explanation(NamedTuple):
    """How a task's rules produce an observed step: the mistake type at stake (-1: none), and if one happened."""

    mistake_type: int
    mistaken: bool


def starts_like(task: Task, obs: np.ndarray) -> bool:
    """True if `obs` is the first observation of an episode of `task`."""
    return bool(np.array_equal(observation(task, initial_state(task)), obs))


def explain(task: Task, transition: Transition) -> Explanation | None:
    """How `task`'s rules produce `transition`, or None if they cannot (for any worker)."""
    obs = np.asarray(transition.obs, dtype=np.float32)
    next_obs = np.asarray(transition.next_obs, dtype=np.float32)
    state = state_from_observation(task, obs)
    if is_terminal(task, state) or not np.array_equal(observation(task, state), obs):
        return None
    result = outcomes(task, state, int(transition.action))
    branches = [(result.ok, False)] + ([(result.mistake, True)] if result.mistake is not None else [])
    for reached, mistaken in branches:
        if (np.array_equal(observation(task, reached), next_obs)
                and bool(transition.terminated) == is_terminal(task, reached)
                and abs(step_reward(task, reached) - float(transition.reward)) <= REWARD_TOLERANCE):
            return Explanation(result.mistake_type, mistaken)
    return None


def public_tasks(suites: str) -> list[Task]:
    """The tasks listed in the given suites (comma-separated names or paths), each task once."""
    tasks: dict[tuple, Task] = {}
    for name in suites.split(","):
        for task in load_suite(name.strip()).tasks:
            tasks.setdefault((task.key(), task.average_worker), task)
    return list(tasks.values())


class TaskBelief:
    """The known tasks still consistent with everything observed since `reset()`, in their given order."""

    def __init__(self, tasks: Sequence[Task]) -> None:
        self.tasks = tuple(tasks)
        self.candidates = list(self.tasks)

    def reset(self) -> None:
        """A new pair: every task is possible again."""
        self.candidates = list(self.tasks)

    def start_episode(self, obs: np.ndarray) -> None:
        """Keep the candidates whose episodes start with `obs`."""
        self.candidates = [task for task in self.candidates if starts_like(task, obs)]

    def update(self, transition: Transition) -> Explanation | None:
        """Drop the candidates that cannot produce `transition`; the explanation of the first one left."""
        explained = [(task, explain(task, transition)) for task in self.candidates]
        self.candidates = [task for task, why in explained if why is not None]
        return next((why for _, why in explained if why is not None), None)

    @property
    def task(self) -> Task | None:
        """The task acted for: the first candidate left (None if no known task explains what was seen)."""
        return self.candidates[0] if self.candidates else None


class RandomTaskSpecificAgent:
    """Plays the random task-specific policy for the task it infers."""

    policy = RandomTaskSpecific()

    def __init__(self, suite: str = ",".join(SHIPPED_SUITES), seed: int | str = 0) -> None:
        self.task_belief = TaskBelief(public_tasks(suite))
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)
        self.reset_task()

    def reset_task(self) -> None:
        """A new hidden pair: every known task is possible again."""
        self.task_belief.reset()
        self.episode_starting = True

    def act(self, obs: np.ndarray) -> int:
        """One draw from the policy's action distribution in the candidate task's state."""
        obs = np.asarray(obs, dtype=np.float32)
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
