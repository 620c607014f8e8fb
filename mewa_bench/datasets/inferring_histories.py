"""Task-inferring learning histories: posterior sampling over (public task, worker), told neither.

The `learning-histories` learner (`learning_histories`) knows its task and learns only the worker. On a
suite whose tasks look alike at the start (wide-v2's tasks 0 and 4 share their first observation), a
model that copies it copies play it cannot explain from what it sees. This learner knows only what an
agent may know: the rules, the t-optimal family and the suite's public task list (as the reference
agents' `TaskBelief`). It holds

- the public tasks still consistent with every observed step (a deterministic elimination), and
- for each of them, an exact posterior over the worker on that task's 0.05 grid, uniform at first and
  updated after each episode from the Bernoulli(w_x) trials that task's rules see in the episode.

At each episode start, and whenever the task it acts for is ruled out, it samples a (task, grid worker)
pair from the joint posterior (every public task equally likely a priori, every grid worker of a task
equally likely) and plays the t-optimal policy best for that pair, its counters from zero. Its action at
each step is a function of what it has seen and of its own seeded draws: exactly what an in-context
model can learn to copy. Played by `expert_rollout.play_agent`, like the expert tier.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mewa_bench.agents.task_inference import explain, observed_state, starts_like
from mewa_bench.datasets.chain_rollout import Played
from mewa_bench.datasets.expert_rollout import play_agent
from mewa_bench.datasets.learning_histories import learner_model, sample_posterior
from mewa_bench.design.policies import TOptimal, toptimal_family
from mewa_bench.game.task import Task
from mewa_bench.protocol.agent import Transition


class TaskInferringLearner:
    """Posterior sampling over (public task, grid worker); the protocol's agent calls."""

    def __init__(self, tasks: Sequence[Task]) -> None:
        self.tasks = tuple(tasks)
        self.reset_task(0)

    def reset_task(self, seed: int) -> None:
        """A new (task, worker): every public task possible, every posterior uniform, draws from `seed`."""
        self.rng = np.random.default_rng(seed)
        self.candidates = list(range(len(self.tasks)))
        self.mistakes = {c: np.zeros(t.N) for c, t in enumerate(self.tasks)}  # up to the last episode's end
        self.trials = {c: np.zeros(t.N) for c, t in enumerate(self.tasks)}
        self.episode_mistakes = {c: np.zeros(t.N) for c, t in enumerate(self.tasks)}
        self.episode_trials = {c: np.zeros(t.N) for c, t in enumerate(self.tasks)}
        self.acting_for: int | None = None  # the sampled task, None before an episode's first action
        self.policy: TOptimal | None = None
        self.memory: tuple[int, int] = (0, 0)

    def act(self, obs: np.ndarray) -> int:
        """The sampled policy's action in the sampled task's reading of `obs`."""
        if self.acting_for is None:
            self.candidates = [c for c in self.candidates if starts_like(self.tasks[c], obs)]
            self.choose()
        task = self.tasks[self.acting_for]
        choice = self.policy.choices(task, observed_state(task, obs), self.memory)[0]
        self.memory = choice.memory
        return choice.action

    def observe(self, transition: Transition) -> None:
        """Rule out the tasks that cannot produce `transition`; count each survivor's trial and mistake."""
        survivors = []
        for c in self.candidates:
            why = explain(self.tasks[c], transition)
            if why is None:
                continue
            survivors.append(c)
            if why.mistake_type >= 0:
                self.episode_trials[c][why.mistake_type] += 1
                self.episode_mistakes[c][why.mistake_type] += why.mistaken
        if not survivors:
            raise ValueError("no public task explains the observed step: the learner's task is not in its list")
        self.candidates = survivors
        if self.acting_for not in survivors and not (transition.terminated or transition.truncated):
            self.choose()

    def end_episode(self) -> None:
        """Update the worker posteriors with the episode's trials; the next episode samples afresh."""
        for c in self.candidates:
            self.mistakes[c] += self.episode_mistakes[c]
            self.trials[c] += self.episode_trials[c]
        for c in range(len(self.tasks)):
            self.episode_mistakes[c][:] = 0
            self.episode_trials[c][:] = 0
        self.acting_for = None

    def choose(self) -> None:
        """Sample (task, grid worker) from the joint posterior; play that pair's best t-optimal policy."""
        models = [learner_model(self.tasks[c]) for c in self.candidates]
        joint = np.concatenate([self.mistakes[c] @ m.log_w.T + (self.trials[c] - self.mistakes[c]) @ m.log_not_w.T
                                - np.log(len(m.grid)) for c, m in zip(self.candidates, models)])
        pick = int(sample_posterior(joint[None, :], self.rng.random(1))[0])
        ends = np.cumsum([len(m.grid) for m in models])
        k = int(np.searchsorted(ends, pick, side="right"))  # the candidate whose grid holds `pick`
        self.acting_for = self.candidates[k]
        best = models[k].best_policy[pick - (ends[k - 1] if k else 0)]
        self.policy = toptimal_family(self.tasks[self.acting_for].N)[int(best)]
        self.memory = self.policy.initial_memory()


def play_inferring_histories(tasks: tuple[Task, ...], task_idx: np.ndarray, workers: np.ndarray, keys: np.ndarray,
                             seeds: np.ndarray) -> Played:
    """Histories of len(keys[m]) episodes on (tasks[task_idx[m]], workers[m]), the learner seeded `seeds[m]`."""
    return play_agent(TaskInferringLearner(tasks), tasks, task_idx, workers, keys, seeds)
