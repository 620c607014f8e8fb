"""bayes-adaptive: a reference MEWA agent that infers the task and the worker as it plays.

It is told neither the task nor the worker. What it knows is public: the tasks listed in the
shipped suite files (agent arg `suite`: comma-separated suite names or paths, default all shipped
suites) with their average workers, that workers are non-increasing (w_0 >= w_1 >= ...), and the
t-optimal policy family.

- Task: the candidates are the known tasks whose first observation matches the one seen (the
  colours in play, K, the worker's blocks). After every step it drops the candidates whose rules
  cannot produce the observed transition (next observation, reward, termination): this reveals M
  and the sub-goal order as structures complete. It acts for the first candidate left.
- Worker: each time a structure gets its second block with x + 1 structures open, it sees whether a
  mistake of type x happened. Its posterior over the worker lives on a grid of non-increasing
  workers (step `grid_step`); the prior is a product of Betas centred on the task's public average
  worker with `prior_strength` pseudo-observations per type, restricted to the grid.
- Policy: the t-optimal policy with the highest posterior expected return. The exact expected
  return of every policy at every grid worker is computed once per task (`mewa_bench.design.exact`,
  about 0.6 s for N = 4), so each decision is one weighted average. It decides at every episode
  start and, unless `adapt_within_episode=false`, again after every mistake observation.
- Cache: the posterior depends only on the evidence counts (mistakes and successes per mistake
  type), so each task model remembers the policy it chose for every count vector seen so far (one
  small entry each, kept for the life of the process and shared by its agents): a repeated decision
  is a dictionary look-up with the same result. Task inference and the state of an observation are
  look-ups in the task's transition table (`mewa_bench.agents.task_inference`).

`reset_task(seed=...)` forgets the task candidates and the evidence. The agent is deterministic;
`seed` (with the unit's seed from the protocol) only drives the uniform-random fallback used if no
known task explains what it sees. Task models (with their cached decisions) are shared by all the
agents of a process (the evaluation runner plays several side by side).

Run it: `mewa-bench evaluate submissions/bayes-adaptive/agent.py --suite narrow-v1`.
"""

from __future__ import annotations

import itertools
import sys
import types
from typing import Any, Sequence

import numpy as np
from scipy.stats import beta as beta_distribution

from mewa_bench.design.exact import expected_returns
from mewa_bench.design.policies import TOptimal, toptimal_family
from mewa_bench.design.suites import SHIPPED_SUITES
from mewa_bench.game.task import Task
from mewa_bench.protocol.agent import Transition, state_vector
from mewa_bench.agents.task_inference import TaskBelief, observed_state, public_tasks

PRIVILEGED = False
NUM_ACTIONS = 4
TINY = 1e-300  # stands in for 0 under log, so that 0 observations x log(0) = 0, not nan


class Evidence:
    """Mistake observations of one pair: per mistake type x, how many mistakes and how many not."""

    def __init__(self) -> None:
        self.mistakes = np.zeros(NUM_ACTIONS)
        self.successes = np.zeros(NUM_ACTIONS)

    def record(self, mistake_type: int, mistaken: bool) -> None:
        """A structure got its second block with `mistake_type + 1` structures open."""
        (self.mistakes if mistaken else self.successes)[mistake_type] += 1

    def counts(self, n: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """The counts of mistake types 0..n-1, hashable: (mistakes, successes)."""
        return tuple(self.mistakes[:n].tolist()), tuple(self.successes[:n].tolist())


def non_increasing_grid(n: int, step: float) -> np.ndarray:
    """All workers [G, n] with components on the grid 0, step, ..., 1 and w_0 >= w_1 >= ..."""
    count = int(round(1.0 / step))
    if count < 1 or abs(count * step - 1.0) > 1e-9:
        raise ValueError(f"grid_step must divide 1 (e.g. 0.05 or 0.1), got {step!r}")
    levels = range(count, -1, -1)
    rows = list(itertools.combinations_with_replacement(levels, n))  # each tuple is non-increasing
    return np.array(rows, dtype=np.float64) / count


def log_prior(grid: np.ndarray, prior_mean: Sequence[float], strength: float, step: float) -> np.ndarray:
    """Log prior weight of each grid worker: Beta(strength * mean, strength * (1 - mean)) mass of its cell."""
    mean = np.clip(np.asarray(prior_mean, dtype=np.float64), 1e-3, 1.0 - 1e-3)
    a, b = strength * mean, strength * (1.0 - mean)
    low, high = np.clip(grid - step / 2, 0.0, 1.0), np.clip(grid + step / 2, 0.0, 1.0)
    mass = beta_distribution.cdf(high, a, b) - beta_distribution.cdf(low, a, b)
    return np.log(np.maximum(mass, TINY)).sum(axis=1)


class TaskModel:
    """For one task: the worker grid, its prior, each t-optimal policy's exact return per grid worker, its decisions."""

    def __init__(self, task: Task, step: float, prior_strength: float) -> None:
        average = task.average_worker if task.average_worker is not None else (0.5,) * task.N
        self.policies = toptimal_family(task.N)
        self.grid = non_increasing_grid(task.N, step)
        self.log_prior = log_prior(self.grid, average, prior_strength, step)
        self.log_w = np.log(np.maximum(self.grid, TINY))
        self.log_not_w = np.log(np.maximum(1.0 - self.grid, TINY))
        self.values = expected_returns(task, self.policies, self.grid)  # [P, G]
        self.decisions: dict[tuple, TOptimal] = {}  # evidence counts -> best policy

    def posterior(self, evidence: Evidence) -> np.ndarray:
        """Posterior probability of each grid worker."""
        n = self.grid.shape[1]
        log_weight = self.log_prior + self.log_w @ evidence.mistakes[:n] + self.log_not_w @ evidence.successes[:n]
        weight = np.exp(log_weight - log_weight.max())
        return weight / weight.sum()

    def posterior_mean(self, evidence: Evidence) -> np.ndarray:
        """Posterior mean worker [N]."""
        return self.posterior(evidence) @ self.grid

    def best_policy(self, evidence: Evidence) -> TOptimal:
        """The policy with the highest posterior expected return, computed once per evidence counts."""
        key = evidence.counts(self.grid.shape[1])  # all that `posterior` reads from the evidence
        best = self.decisions.get(key)
        if best is None:
            best = self.decisions[key] = self.compute_best_policy(evidence)
        return best

    def compute_best_policy(self, evidence: Evidence) -> TOptimal:
        """The policy with the highest posterior expected return (the first one on ties)."""
        return self.policies[int(np.argmax(self.values @ self.posterior(evidence)))]


def as_flag(value: bool | str) -> bool:
    """An agent arg read as a boolean ("true"/"false", "1"/"0", "yes"/"no")."""
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text not in ("true", "false", "1", "0", "yes", "no"):
        raise ValueError(f"expected true or false, got {value!r}")
    return text in ("true", "1", "yes")


class BayesAdaptiveAgent:
    """Infers the task from observations and the worker from its mistakes; plays the Bayes-best t-optimal policy."""

    def __init__(self, suite: str = ",".join(SHIPPED_SUITES), seed: int | str = 0, grid_step: float | str = 0.05,
                 prior_strength: float | str = 2.0, adapt_within_episode: bool | str = True) -> None:
        self.task_belief = TaskBelief(public_tasks(suite))
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)  # only for tasks no public suite lists
        self.grid_step = float(grid_step)
        non_increasing_grid(2, self.grid_step)  # fail early on a bad step
        self.prior_strength = float(prior_strength)
        if self.prior_strength <= 0:
            raise ValueError(f"prior_strength must be positive, got {prior_strength!r}")
        self.adapt_within_episode = as_flag(adapt_within_episode)
        self.models: dict[tuple, TaskModel] = {}  # built once per task, on first use
        self.reset_task()

    def reset_task(self, seed: int | None = None) -> None:
        """A new hidden pair: forget the task candidates and the worker evidence."""
        if seed is not None:
            self.rng = np.random.default_rng([self.seed, seed])
        self.task_belief.reset()
        self.evidence = Evidence()
        self.policy: TOptimal | None = None
        self.memory: Any = None
        self.episode_starting = True

    def act(self, obs: np.ndarray) -> int:
        """The chosen policy's action for the candidate task's state."""
        obs = state_vector(obs)  # the 18 floats, also in sapien mode
        if self.episode_starting:
            self.start_episode(obs)
        task = self.task_belief.task
        if task is None or self.policy is None:  # an unknown task: nothing to infer from
            return int(self.rng.integers(NUM_ACTIONS))
        choice = self.policy.choices(task, observed_state(task, obs), self.memory)[0]
        self.memory = choice.memory
        return int(choice.action)

    def observe(self, transition: Transition) -> None:
        """Narrow the task candidates, record mistake evidence, and re-plan when something changed."""
        acted_for = self.task_belief.task
        why = self.task_belief.update(transition)
        observed = why is not None and why.mistake_type >= 0
        if observed:
            self.evidence.record(why.mistake_type, why.mistaken)
        if transition.terminated or transition.truncated:
            self.episode_starting = True
        elif self.task_belief.task is not acted_for:
            self.choose_policy(reset_memory=True)
        elif observed and self.adapt_within_episode:
            self.choose_policy(reset_memory=False)

    def end_episode(self) -> None:
        """The next act() starts an episode (of the same pair)."""
        self.episode_starting = True

    def start_episode(self, obs: np.ndarray) -> None:
        """Check the first observation against the candidates and choose the episode's policy."""
        self.task_belief.start_episode(obs)
        self.episode_starting = False
        self.choose_policy(reset_memory=True)

    def choose_policy(self, reset_memory: bool) -> None:
        """Switch to the best policy under the current beliefs, keeping run counters within its limits."""
        task = self.task_belief.task
        if task is None:
            self.policy = None
            return
        best = self.model(task).best_policy(self.evidence)
        if reset_memory or self.policy is None:
            self.memory = best.initial_memory()
        elif best != self.policy:
            run1, run2 = self.memory
            self.memory = (min(run1, best.rho1), min(run2, best.rho2))
        self.policy = best

    def model(self, task: Task) -> TaskModel:
        """The task's grid model (about 0.6 s to build for N = 4, once per task)."""
        key = (task.key(), task.average_worker)
        if key not in self.models:  # shared by the agents of one process (the runner's lanes): built once
            shared, settings = _shared_models(), (key, self.grid_step, self.prior_strength)
            if settings not in shared:
                shared[settings] = TaskModel(task, self.grid_step, self.prior_strength)
            self.models[key] = shared[settings]
        return self.models[key]

    def posterior_mean(self) -> np.ndarray | None:
        """The posterior mean worker for the current candidate task (None if no candidate is left)."""
        task = self.task_belief.task
        return None if task is None else self.model(task).posterior_mean(self.evidence)


def make_agent(observation_space: Any, action_space: Any, **kwargs: Any) -> BayesAdaptiveAgent:
    """Build the agent; agent args: suite, seed, grid_step, prior_strength, adapt_within_episode."""
    if getattr(action_space, "n", NUM_ACTIONS) != NUM_ACTIONS:
        raise ValueError(f"expected the MEWA action space Discrete({NUM_ACTIONS}), got {action_space}")
    return BayesAdaptiveAgent(**kwargs)


def _shared_models() -> dict:
    """One process-wide cache of task models (this file may be imported once per agent object)."""
    holder = sys.modules.get(_CACHE_MODULE)
    if holder is None:
        holder = sys.modules[_CACHE_MODULE] = types.ModuleType(_CACHE_MODULE)
        holder.models = {}  # type: ignore[attr-defined]
    return holder.models  # type: ignore[attr-defined]


_CACHE_MODULE = "_mewa_bayes_adaptive_models"
