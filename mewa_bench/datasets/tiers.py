"""The behaviour tiers of the training datasets: who plays, for how many episodes per worker, and the exact
expected return of each episode's behaviour where one is defined.

- `random`: uniform over the 4 palette actions (SPEC section 4's random baseline).
- `random-task-specific`: knows the game, ignores the worker (SPEC section 4).
- `expert`: a shipped adaptive reference agent (default bayes-explorer, the stronger one: it wins
  most of the v2 suites' gaps; bayes-adaptive with `expert_agent`) playing the protocol's 10 episodes per worker, told
  neither task nor worker.
  Its behaviour changes with what it has seen, so no exact expected return is stored.
- `learning-histories`: posterior sampling over the t-optimal family (`learning_histories`), one
  history of `history_episodes` episodes per worker, in learning order. The learner is told its task
  (only the worker is hidden from it).
- `task-inferring-histories`: the same kind of learner told neither task nor worker
  (`inferring_histories`): posterior sampling over (public task, worker). Its behaviour changes within an
  episode when the task it acts for is ruled out, so no exact expected return is stored. On a wide generator's
  task structures it knows every renaming of every structure (`generator_histories`), as a new task requires.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mewa_bench.datasets.chain_rollout import Played, play_chain
from mewa_bench.design.policies import RANDOM, RANDOM_TASK_SPECIFIC, policy_from_name, toptimal_family
from mewa_bench.design.replay import replay_chain
from mewa_bench.game.task import Task

if TYPE_CHECKING:
    from mewa_bench.datasets.expert_rollout import MapTasks

TIERS = ("random", "random-task-specific", "expert", "learning-histories", "task-inferring-histories")
HISTORY_TIERS = ("learning-histories", "task-inferring-histories")
PROTOCOL_EPISODES = 10
REPO = Path(__file__).resolve().parents[2]
EXPERT_AGENTS = ("bayes-adaptive", "bayes-explorer")
ADAPTIVE = -1  # behaviour_policy of a frame played by an adaptive agent (no fixed policy)


@dataclass(frozen=True)
class TierRun:
    """What a tier played for a group of meta-episodes of one task."""

    played: Played  # episode-major: meta-episode, then episode
    policy: np.ndarray  # int64 [E]: index into `tier_policies` of each episode's behaviour, ADAPTIVE if none


def reference_policies(n: int) -> tuple[str, ...]:
    """The policies whose exact values every dataset stores: the t-optimal family, then the two random baselines."""
    return (*(p.name for p in toptimal_family(n)), RANDOM_TASK_SPECIFIC, RANDOM)


def expected_of_episodes(tier: str, policy: np.ndarray, meta: np.ndarray, values: np.ndarray) -> np.ndarray | None:
    """Exact expected normalised return of each episode's behaviour, from `values` [reference policies, M]
    (None for the expert tier, whose behaviour adapts)."""
    if tier == "random":
        return values[-1][meta]
    if tier == "random-task-specific":
        return values[-2][meta]
    if tier == "learning-histories":
        return values[policy, meta]
    return None


def episodes_per_worker(tier: str, history_episodes: int) -> int:
    """Episodes of one meta-episode in a tier."""
    return history_episodes if tier in HISTORY_TIERS else PROTOCOL_EPISODES


def tier_policies(tier: str, n: int) -> tuple[str, ...]:
    """Names of the fixed policies a tier's episodes may play (what `behaviour_policy` indexes)."""
    if tier == "random":
        return (RANDOM,)
    if tier == "random-task-specific":
        return (RANDOM_TASK_SPECIFIC,)
    if tier == "learning-histories":
        return tuple(p.name for p in toptimal_family(n))
    return ()


def expert_path(agent: str) -> Path:
    """The agent file of an expert agent name."""
    if agent not in EXPERT_AGENTS:
        raise ValueError(f"unknown expert agent {agent!r}; expected one of {', '.join(EXPERT_AGENTS)}")
    return REPO / "submissions" / agent / "agent.py"


def behaviour_source(tier: str, expert_agent: str, every_renaming: bool = False) -> Path:
    """The file that defines a tier's behaviour (its sha256 identifies the behaviour); `every_renaming`: the
    task-inferring learner knows every renaming of its tasks (a generator's task structures)."""
    here = Path(__file__).resolve().parents[1]
    if tier == "expert":
        return expert_path(expert_agent)
    if tier == "learning-histories":
        return here / "datasets" / "learning_histories.py"
    if tier == "task-inferring-histories":
        return here / "datasets" / ("generator_histories.py" if every_renaming else "inferring_histories.py")
    return here / "design" / "policies.py"


def file_sha256(path: Path) -> str:
    """sha256 of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def play_tier(tier: str, suite: str, tasks: tuple[Task, ...], task_index: int, workers: np.ndarray,
              keys: np.ndarray, rng: np.random.Generator, agent_seeds: np.ndarray, expert_agent: str = "bayes-explorer",
              jobs: int = 1, map_tasks: MapTasks | None = None, every_renaming: bool = False) -> TierRun:
    """Play a tier on meta-episodes of task `tasks[task_index]`: one worker per row of `workers` [M, 4], the
    luck keys of its episodes in the row of `keys` [M, H]; `every_renaming`: the task-inferring learner knows every
    renaming of `tasks`, not only `tasks`."""
    task = tasks[task_index]
    n_meta, n_ep = keys.shape
    if tier in ("random", "random-task-specific"):
        policy = policy_from_name(tier_policies(tier, task.N)[0])
        chain = replay_chain(task, (policy,))
        played = play_chain(task, chain, np.full(n_meta * n_ep, chain.roots[0]), np.repeat(workers, n_ep, axis=0),
                            keys.reshape(-1))
        return TierRun(played, np.zeros(n_meta * n_ep, dtype=np.int64))
    if tier == "learning-histories":
        from mewa_bench.datasets.learning_histories import play_histories

        played, chosen = play_histories(task, workers, keys, rng)
        return TierRun(played, chosen.reshape(-1))
    if tier == "task-inferring-histories":
        from mewa_bench.datasets.expert_rollout import play_in_chunks
        from mewa_bench.datasets.generator_histories import play_generator_histories
        from mewa_bench.datasets.pool_models import play_pool_histories

        play = play_generator_histories if every_renaming else play_pool_histories
        played = play_in_chunks(play, (tasks,), np.full(n_meta, task_index), workers, keys,
                                agent_seeds, jobs, map_tasks)
        return TierRun(played, np.full(n_meta * n_ep, ADAPTIVE, dtype=np.int64))
    if tier == "expert":
        from mewa_bench.datasets.expert_rollout import play_expert_parallel

        played = play_expert_parallel(expert_path(expert_agent), suite, tasks, np.full(n_meta, task_index), workers,
                                      keys, agent_seeds, jobs, map_tasks)
        return TierRun(played, np.full(n_meta * n_ep, ADAPTIVE, dtype=np.int64))
    raise ValueError(f"unknown tier {tier!r}; expected one of {', '.join(TIERS)}")
