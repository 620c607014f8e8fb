"""The expert tier's behaviour: a shipped adaptive reference agent playing the 10-episode protocol per worker.

The agent (default `submissions/bayes-explorer/agent.py`) is loaded from its file and played the way
the evaluation runner plays it (reset_task, then act / observe per step and end_episode per
episode), on `MewaEnv` with the training luck keys. It is told neither the task nor the worker. Each
meta-episode is independent of the others (the agent is reset with its own seed), so chunks of them
can run in parallel processes with the same result.
"""

from __future__ import annotations

import hashlib
import importlib.util
import sys
from concurrent.futures import ProcessPoolExecutor
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mewa_bench.datasets.chain_rollout import Played
from mewa_bench.game.rules import state_from_observation
from mewa_bench.game.table import transition_table
from mewa_bench.game.task import Task

REPO = Path(__file__).resolve().parents[2]
EXPERT_AGENT = REPO / "submissions" / "bayes-explorer" / "agent.py"


MapTasks = Callable[[Callable[..., Any], list[tuple]], list]  # a function over argument tuples, results in order


def agent_sha256(path: Path) -> str:
    """sha256 of an agent file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def load_agent_module(path: Path) -> Any:
    """Import an agent file as a module (it must define `make_agent`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"expert agent {path} not found (the expert tier needs a checkout with submissions/)")
    name = f"_mewa_expert_{path.parent.name.replace('-', '_')}"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    sys.modules[name] = module  # dataclasses look their module up while the file runs
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


def play_expert(path: Path, suite: str, tasks: tuple[Task, ...], task_idx: np.ndarray, workers: np.ndarray,
                keys: np.ndarray, seeds: np.ndarray) -> Played:
    """Meta-episode m: the agent file's agent reset with seed `seeds[m]`, then len(keys[m]) episodes on (task, worker)."""
    from gymnasium import spaces

    from mewa_bench.game.palette import NUM_COLORS, OBS_SIZE

    module = load_agent_module(path)
    agent = module.make_agent(spaces.Box(0.0, 255.0, (OBS_SIZE,), np.float32), spaces.Discrete(NUM_COLORS),
                              suite=suite, seed=0)
    return play_agent(agent, tasks, task_idx, workers, keys, seeds)


def play_agent(agent: Any, tasks: tuple[Task, ...], task_idx: np.ndarray, workers: np.ndarray, keys: np.ndarray,
               seeds: np.ndarray) -> Played:
    """Meta-episode m: `agent` (the protocol's reset_task / act / observe / end_episode) reset with seed `seeds[m]`,
    then len(keys[m]) episodes on (tasks[task_idx[m]], workers[m]) with those luck keys."""
    from mewa_bench.envs.mewa_env import MewaEnv
    from mewa_bench.game.palette import NUM_COLORS
    from mewa_bench.protocol.agent import Transition

    env = MewaEnv(task=tasks[int(task_idx[0])], worker=workers[0][: tasks[int(task_idx[0])].N])
    rows: list[tuple] = []
    lengths: list[int] = []
    returns: list[float] = []
    for m in range(len(keys)):
        task = tasks[int(task_idx[m])]
        table = transition_table(task)
        agent.reset_task(seed=int(seeds[m]))
        for e, key in enumerate(keys[m]):
            obs, _ = env.reset(options={"task": task, "worker": list(workers[m][: task.N]), "luck_key": int(key)})
            count, total = 0, 0.0
            done = False
            while not done:
                action = int(agent.act(obs))
                nxt, reward, terminated, truncated, _ = env.step(action)
                state = table.index[state_from_observation(task, obs)]
                rows.append((len(lengths), count, state, action, table.index[state_from_observation(task, nxt)],
                             float(reward), bool(terminated), bool(terminated or truncated)))
                agent.observe(Transition(obs, action, float(reward), nxt, bool(terminated), bool(truncated)))
                obs, count, total, done = nxt, count + 1, total + float(reward), terminated or truncated
            agent.end_episode()
            lengths.append(count)
            returns.append(total)
    cols = list(zip(*rows))
    ints = [np.array(c, dtype=np.int64) for c in cols[:5]]
    return Played(ints[0], ints[1], ints[2], ints[3], ints[4], np.array(cols[5]), np.array(cols[6], dtype=bool),
                  np.array(cols[7], dtype=bool), np.zeros((len(lengths), NUM_COLORS)),
                  np.zeros((len(lengths), NUM_COLORS)), np.array(lengths, dtype=np.int64), np.array(returns))


def play_expert_parallel(path: Path, suite: str, tasks: tuple[Task, ...], task_idx: np.ndarray, workers: np.ndarray,
                         keys: np.ndarray, seeds: np.ndarray, jobs: int = 1, map_tasks: MapTasks | None = None) -> Played:
    """`play_expert` over `jobs` x 4 chunks of meta-episodes (see `play_in_chunks`)."""
    return play_in_chunks(play_expert, (path, suite, tasks), task_idx, workers, keys, seeds, jobs, map_tasks)


def play_in_chunks(play: Callable[..., Played], head: tuple, task_idx: np.ndarray, workers: np.ndarray,
                   keys: np.ndarray, seeds: np.ndarray, jobs: int = 1, map_tasks: MapTasks | None = None) -> Played:
    """`play(*head, task_idx, workers, keys, seeds)` over `jobs` x 4 chunks of meta-episodes, in `jobs` processes or as
    `map_tasks` (the same frames for any `jobs` and either way: each meta-episode depends only on its worker, luck
    keys and seed)."""
    from mewa_bench.datasets.chain_rollout import concat_played

    if map_tasks is None and (jobs <= 1 or len(keys) < 2):
        return play(*head, task_idx, workers, keys, seeds)
    chunks = np.array_split(np.arange(len(keys)), min(jobs * 4, len(keys)))
    args = [(*head, task_idx[c], workers[c], keys[c], seeds[c]) for c in chunks]
    parts = map_tasks(play, args) if map_tasks is not None else list(shared_pool(jobs).map(play, *zip(*args)))
    return concat_played(parts)


_POOLS: dict[int, ProcessPoolExecutor] = {}


def shared_pool(jobs: int) -> ProcessPoolExecutor:
    """A process pool kept for the life of the process (its processes keep the agent and its task models
    loaded from one round of meta-episodes to the next); shut down at exit."""
    import atexit
    import multiprocessing

    if jobs not in _POOLS:
        _POOLS[jobs] = ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"))
        atexit.register(_POOLS[jobs].shutdown)
    return _POOLS[jobs]
