"""Task-inferring learning histories over a wide generator's whole range: posterior sampling over (task, worker),
where the task is any the generator can draw.

`inferring_histories.TaskInferringLearner` knows a list of tasks. Given a generator's task structures
(`generated_tasks.task_structures`: colours 0..N-1 completed in that order) as its list, it would know each task's
sub-goal order from its colours, which a new task never tells: its histories under renamed colours show a learner
that hands the right colour first without having seen why. This learner knows every renaming of every structure
(24 x 168 tasks on the wide suites: what the generator draws, each equally likely given the first observation,
which shows N, the colours and K), so it finds the order, M and the worker blocks by playing.

It plays as `TaskInferringLearner` does: it keeps the tasks consistent with every observed step; at each episode
start, and whenever the task it acts for is ruled out, it samples (task, grid worker) from the joint posterior
(every task equally likely a priori, every grid worker of a task equally likely) and plays that pair's best
t-optimal policy. Two facts keep it fast:

- the rules do not care which colour is which (`game.relabel`): a renamed task's step is its structure's step
  with the colours named back, so one structure's table and learner model serve its 24 renamings;
- a mistake trial (a structure reaching 2 blocks), its type and its outcome are all in the observation, so every
  task still consistent has counted the same trials: one count, and one worker posterior per structure.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

from mewa_bench.agents.task_inference import explain, observed_state
from mewa_bench.datasets.chain_rollout import Played
from mewa_bench.datasets.expert_rollout import play_agent
from mewa_bench.datasets.learning_histories import sample_posterior
from mewa_bench.datasets.pool_models import every_model
from mewa_bench.design.policies import TOptimal, toptimal_family
from mewa_bench.game.palette import NUM_COLORS
from mewa_bench.game.relabel import observation_gather, relabelled_task
from mewa_bench.game.rules import initial_state, observation
from mewa_bench.game.task import Task
from mewa_bench.protocol.agent import Transition, state_vector

RENAMINGS = np.array(list(itertools.permutations(range(NUM_COLORS))), dtype=np.int64)  # [24, 4]: colour c -> p[c]
_BACK = np.argsort(RENAMINGS, axis=1)  # the inverse renamings
_GATHER_BACK = np.stack([observation_gather(q) for q in _BACK])  # [24, 18]: an observation with its colours named back


def _log_sum_exp(x: np.ndarray) -> float:
    """log(sum(exp(x))) without overflow."""
    top = float(x.max())
    return top + float(np.log(np.exp(x - top).sum()))


class GeneratorInferringLearner:
    """Posterior sampling over (any renaming of any of `structures`, grid worker); the protocol's agent calls.

    A candidate is a pair (s, r): structure `structures[s]` with colour c renamed `RENAMINGS[r][c]`."""

    def __init__(self, structures: Sequence[Task]) -> None:
        self.structures = tuple(structures)
        starts = np.stack([observation(t, initial_state(t)) for t in self.structures])  # [S, 18]
        # first observation of candidate (s, r), renamed: starts[s] with colour c's entries moved to RENAMINGS[r][c]
        self.starts = np.stack([starts[:, observation_gather(p)] for p in RENAMINGS])  # [24, S, 18]
        self.reset_task(0)

    def reset_task(self, seed: int) -> None:
        """A new (task, worker): every task possible, the worker posteriors uniform, draws from `seed`."""
        self.rng = np.random.default_rng(seed)
        self.cand_s = np.tile(np.arange(len(self.structures)), len(RENAMINGS))
        self.cand_r = np.repeat(np.arange(len(RENAMINGS)), len(self.structures))
        self.mistakes = np.zeros(NUM_COLORS)  # by mistake type, up to the last episode's end
        self.trials = np.zeros(NUM_COLORS)
        self.episode_mistakes = np.zeros(NUM_COLORS)
        self.episode_trials = np.zeros(NUM_COLORS)
        self.acting_for: tuple[int, int] | None = None  # (s, r) sampled, None before an episode's first action
        self.policy: TOptimal | None = None
        self.memory: tuple[int, int] = (0, 0)

    def candidates(self) -> list[Task]:
        """The tasks still consistent with what was observed, renamed (for inspection and tests)."""
        return [relabelled_task(self.structures[s], RENAMINGS[r]) for s, r in zip(self.cand_s, self.cand_r)]

    def act(self, obs: np.ndarray) -> int:
        """The sampled policy's action in the sampled task's reading of `obs`."""
        if self.acting_for is None:
            obs = state_vector(obs)
            keep = np.all(self.starts[self.cand_r, self.cand_s] == obs, axis=1)
            self._keep(keep, "an episode's first observation")
            self.choose()
        s, r = self.acting_for
        task = self.structures[s]
        choice = self.policy.choices(task, observed_state(task, state_vector(obs)[_GATHER_BACK[r]]), self.memory)[0]
        self.memory = choice.memory
        return int(RENAMINGS[r][choice.action])

    def observe(self, transition: Transition) -> None:
        """Rule out the tasks that cannot produce `transition`; count its trial and mistake once."""
        keep = np.zeros(len(self.cand_s), dtype=bool)
        why = None
        for r in np.unique(self.cand_r):
            named_back = _named_back(transition, int(r))
            for i in np.flatnonzero(self.cand_r == r):
                explained = explain(self.structures[self.cand_s[i]], named_back)
                if explained is not None:
                    keep[i], why = True, explained
        self._keep(keep, "the observed step")
        if why.mistake_type >= 0:
            self.episode_trials[why.mistake_type] += 1
            self.episode_mistakes[why.mistake_type] += why.mistaken
        if not self._still_acting() and not (transition.terminated or transition.truncated):
            self.choose()

    def end_episode(self) -> None:
        """Add the episode's trials to the worker posterior; the next episode samples afresh."""
        self.mistakes += self.episode_mistakes
        self.trials += self.episode_trials
        self.episode_mistakes[:] = 0
        self.episode_trials[:] = 0
        self.acting_for = None

    def choose(self) -> None:
        """Sample (task, grid worker) from the joint posterior; play that pair's best t-optimal policy."""
        u = self.rng.random(2)
        joint = self.structure_posteriors()
        weight = {s: _log_sum_exp(j) for s, j in joint.items()}
        pick = int(sample_posterior(np.array([[weight[s] for s in self.cand_s]]), u[:1])[0])
        s, r = int(self.cand_s[pick]), int(self.cand_r[pick])
        worker = int(sample_posterior(joint[s][None, :], u[1:])[0])
        self.acting_for = (s, r)
        self.policy = toptimal_family(self.structures[s].N)[int(every_model(self.structures[s]).best_policy[worker])]
        self.memory = self.policy.initial_memory()

    def structure_posteriors(self) -> dict[int, np.ndarray]:
        """The unnormalised log posterior of (candidate structure, grid worker), the same for each renaming."""
        out = {}
        for s in np.unique(self.cand_s).tolist():
            model = every_model(self.structures[s])
            n = self.structures[s].N
            out[s] = (self.mistakes[:n] @ model.log_w.T + (self.trials[:n] - self.mistakes[:n]) @ model.log_not_w.T
                      - np.log(len(model.grid)))
        return out

    def candidate_log_weights(self) -> np.ndarray:
        """The unnormalised log posterior of each candidate task (in `candidates()` order)."""
        weight = {s: _log_sum_exp(j) for s, j in self.structure_posteriors().items()}
        return np.array([weight[s] for s in self.cand_s.tolist()])

    def _keep(self, keep: np.ndarray, what: str) -> None:
        """Keep the candidates marked in `keep`; none left is an error (the task is outside the generator)."""
        if not keep.any():
            raise ValueError(f"no renaming of the learner's task structures explains {what}: the task is not one the "
                             "generator draws")
        self.cand_s, self.cand_r = self.cand_s[keep], self.cand_r[keep]

    def _still_acting(self) -> bool:
        """True if the task acted for is still a candidate."""
        if self.acting_for is None:
            return False
        s, r = self.acting_for
        return bool(np.any((self.cand_s == s) & (self.cand_r == r)))


def _named_back(transition: Transition, r: int) -> Transition:
    """`transition` as it reads with renaming `RENAMINGS[r]` undone."""
    gather, action = _GATHER_BACK[r], int(transition.action)
    return transition._replace(obs=state_vector(transition.obs)[gather],
                               action=int(_BACK[r][action]) if 0 <= action < NUM_COLORS else action,
                               next_obs=state_vector(transition.next_obs)[gather])


def play_generator_histories(structures: tuple[Task, ...], task_idx: np.ndarray, workers: np.ndarray,
                             keys: np.ndarray, seeds: np.ndarray) -> Played:
    """Histories of len(keys[m]) episodes on (structures[task_idx[m]], workers[m]), the learner seeded `seeds[m]`
    and knowing every renaming of `structures`."""
    return play_agent(GeneratorInferringLearner(structures), structures, task_idx, workers, keys, seeds)
