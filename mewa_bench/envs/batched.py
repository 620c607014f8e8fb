"""Batched MEWA: many (task, worker) pairs stepped at once with numpy, as a Gymnasium vector env."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from mewa_bench.envs.lanes import LaneGenerators, lane_seeds
from mewa_bench.envs.pairs import PairSource
from mewa_bench.game import luck
from mewa_bench.game.normalise import return_bounds
from mewa_bench.game.palette import NUM_COLORS, OBS_SIZE
from mewa_bench.game.table import transition_table
from mewa_bench.game.task import Task, Worker

PAIR_BATCH = 1024  # meta-train pairs sampled per call of the sampler


class StackedTables:
    """The transition tables of several tasks concatenated into one state space (offset per task)."""

    def __init__(self, tasks: Sequence[Task]) -> None:
        tables = [transition_table(t) for t in tasks]
        sizes = [t.n_states for t in tables]
        self.start = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)  # initial state per task
        shift = np.repeat(self.start, sizes)[:, None]
        self.next_ok = (np.concatenate([t.next_ok for t in tables]) + shift).ravel()
        self.next_mistake = (np.concatenate([t.next_mistake for t in tables]) + shift).ravel()
        # Mistake type -1 (no mistake possible) points at column NUM_COLORS of the padded workers (= 0).
        mtype = np.concatenate([t.mistake_type for t in tables]).astype(np.int64)
        self.mistake_column = np.where(mtype < 0, NUM_COLORS, mtype).ravel()
        self.obs = np.concatenate([t.obs for t in tables])
        self.reward = np.concatenate([t.reward for t in tables])
        self.terminal = np.concatenate([t.terminal for t in tables])
        self.progress = np.concatenate([t.progress for t in tables])
        bounds = np.array([return_bounds(t) for t in tasks])
        self.r_min, self.r_span = bounds[:, 0], bounds[:, 1] - bounds[:, 0]
        self.horizon = np.array([t.T for t in tasks], dtype=np.int64)


def as_autoreset_mode(mode: AutoresetMode | str) -> AutoresetMode:
    """An `AutoresetMode` from itself or its value ("NextStep", "SameStep", "Disabled")."""
    try:
        return AutoresetMode(mode)
    except ValueError:
        names = ", ".join(f"{m.name} ({m.value!r})" for m in AutoresetMode)
        raise ValueError(f"autoreset_mode {mode!r} is not one of {names}") from None


def same_step_infos(infos: dict[str, Any], done: np.ndarray, fresh: dict[str, np.ndarray]) -> dict[str, Any]:
    """SAME_STEP infos as Gymnasium's `SyncVectorEnv` builds them: the `done` lanes' step infos go to
    `final_info` (masked); at top level those lanes show the new episode's entries (`fresh`, arrays
    over all lanes) and no others. Entries without a `_` mask hold for every lane."""
    final: dict[str, Any] = {}
    top: dict[str, Any] = {}
    for key, value in infos.items():
        if key.startswith("_"):
            continue
        mask = infos.get("_" + key, np.ones_like(done))
        zeros = np.zeros_like(value)
        if (mask & done).any():
            final[key], final["_" + key] = np.where(done, value, zeros), mask & done
        if key in fresh:
            top[key] = np.where(done, fresh[key], value)
            if "_" + key in infos:
                top["_" + key] = mask | done
            continue
        keep = mask & ~done
        if keep.any():
            top[key], top["_" + key] = np.where(keep, value, zeros), keep
    top.update(final_info=final, _final_info=done.copy())
    return top


class MewaVectorEnv(VectorEnv):
    """`num_envs` MEWA games stepped together; same rules and arguments as `MewaEnv`.

    Each sub-env plays its own (task, worker) pair: the fixed pair, or a task and a meta-train
    worker sampled at each of its resets (`workers=[...]`: one of these, drawn uniformly).

    Autoreset (`autoreset_mode=`, also through `gym.make_vec(..., autoreset_mode=...)`; the
    `autoreset_mode` attribute and `metadata["autoreset_mode"]` say which), as Gymnasium 1.x defines:
    - `NEXT_STEP` (default): a sub-env resets itself on the step *after* its episode ended; that step
      ignores the action and returns the first observation of the new episode with reward 0.
    - `SAME_STEP`: the step that ends an episode returns the first observation of the next one;
      the last observation is in `infos["final_obs"]` (an object array, None elsewhere) and that
      step's infos in `infos["final_info"]`, masked by `_final_obs` / `_final_info`.
    - `DISABLED`: nothing resets by itself; `reset(options={"reset_mask": mask})` resets the lanes
      where the bool mask is True (stepping a lane whose episode ended is an error).

    Seeds: `reset(seed=s)` (an int) seeds one generator that all sub-envs draw from, in bulk, in the
    order their episodes start (the fast default). `reset(seed=[s_0, ..., s_n-1])` seeds each lane
    on its own (None keeps that lane's generator): lane i then plays the episodes `MewaEnv` plays
    after `reset(seed=s_i)`, i.e. what Gymnasium's `SyncVectorEnv` over `MewaEnv` gives for that
    seed list. Which modes play the same episodes (pairs, luck, observations, rewards) for the same
    seed and per-lane actions (tested): with a seed list, all three; with an int seed, SAME_STEP and
    DISABLED when the ended lanes are reset after every step (NEXT_STEP's extra reset steps change
    the order in which the lanes' episodes start, hence what each draws from the shared generator).

    `infos` hold `progress` [num_envs] and, on steps where some episode ends, `episode_return` and
    `normalised_return` with their `_`-prefixed masks (all numeric arrays). `env.workers` and
    `env.task_indices` give each sub-env's current pair, `env.luck_keys` each episode's luck key
    (mistakes are drawn as in `MewaEnv`: the same key and actions give the same episode).
    """

    metadata: dict[str, Any] = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 1, task: Task | dict | None = None, worker: Sequence[float] | None = None,
                 tasks: Sequence[Task | dict] | None = None, include_centre: bool = False,
                 render_mode: str | None = None, workers: Sequence[Sequence[float]] | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if render_mode is not None:
            raise ValueError("the batched env does not render; use MewaEnv for render modes")
        self.autoreset_mode = as_autoreset_mode(autoreset_mode)
        self.metadata = {**type(self).metadata, "autoreset_mode": self.autoreset_mode}
        self.num_envs = num_envs
        self.render_mode = None
        self._source = PairSource.build(task, worker, tasks, include_centre, workers)
        self._stack = StackedTables(self._source.tasks)
        self.single_action_space = spaces.Discrete(NUM_COLORS)
        self.single_observation_space = spaces.Box(0.0, 255.0, shape=(OBS_SIZE,), dtype=np.float32)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self._rows = np.arange(num_envs)
        self._state = np.zeros(num_envs, dtype=np.int64)
        self._task_idx = np.zeros(num_envs, dtype=np.int64)
        self._workers = np.zeros((num_envs, NUM_COLORS + 1))  # + a zero column for "no mistake possible"
        self._t = np.zeros(num_envs, dtype=np.int64)
        self._return = np.zeros(num_envs)
        self._needs_reset = np.ones(num_envs, dtype=bool)
        self._keys = np.zeros(num_envs, dtype=np.uint64)
        self._draws = np.zeros((num_envs, NUM_COLORS), dtype=np.int64)  # second blocks so far, per colour
        self._pairs: tuple[np.ndarray, np.ndarray] | None = None  # sampled pairs not handed out yet
        self._pairs_used = 0
        self._lanes: LaneGenerators | None = None  # per-lane generators after reset(seed=[...])

    @property
    def tasks(self) -> tuple[Task, ...]:
        """The tasks the sub-envs draw from (index = `task_indices`)."""
        return self._source.tasks

    @property
    def task_indices(self) -> np.ndarray:
        """Index into `tasks` of each sub-env's current task."""
        return self._task_idx.copy()

    @property
    def workers(self) -> np.ndarray:
        """Each sub-env's current worker, float64 [num_envs, 4] (unused components 0)."""
        return self._workers[:, :NUM_COLORS].copy()

    @property
    def luck_keys(self) -> np.ndarray:
        """Each sub-env's current luck key, uint64 [num_envs] (see `MewaEnv`'s "Worker luck")."""
        return self._keys.copy()

    def _next_pairs(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The next n pairs from the source, sampled PAIR_BATCH at a time (a few episodes end per step,
        and the sampler's cost is mostly per call)."""
        if self._pairs is None or len(self._pairs[0]) - self._pairs_used < n:
            task_idx, workers = self._source.sample(self.np_random, max(n, PAIR_BATCH))
            if self._pairs is not None:  # keep the order: what is left first, then the new draws
                task_idx = np.concatenate([self._pairs[0][self._pairs_used:], task_idx])
                workers = np.concatenate([self._pairs[1][self._pairs_used:], workers])
            self._pairs, self._pairs_used = (task_idx, workers), 0
        start, self._pairs_used = self._pairs_used, self._pairs_used + n
        return self._pairs[0][start:self._pairs_used], self._pairs[1][start:self._pairs_used]

    def _start_episodes(self, rows: np.ndarray, new_pairs: bool = True) -> None:
        """Start an episode in `rows`: on a new pair from the source, or on the pair they hold."""
        if self._lanes is not None:
            keys = self._lanes.draw(self._source, rows, new_pairs, self._task_idx, self._workers)
        else:
            if new_pairs:
                task_idx, workers = self._next_pairs(len(rows))
                self._task_idx[rows] = task_idx
                self._workers[rows, :NUM_COLORS] = workers
            keys = self.np_random.integers(0, luck.KEY_BOUND, size=len(rows), dtype=np.uint64)
        self._state[rows] = self._stack.start[self._task_idx[rows]]
        self._keys[rows] = keys
        self._draws[rows] = 0
        self._t[rows] = 0
        self._return[rows] = 0.0
        self._needs_reset[rows] = False

    def reset(self, *, seed: int | Sequence[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every sub-env, or those where `options["reset_mask"]` is True (the others keep playing).

        `seed`: an int (one generator for all sub-envs) or a list with a seed (or None) per sub-env;
        see the class docstring. `options={"task": ..., "worker": ...}` fixes one pair for all of them.
        """
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        unknown = set(options) - {"task", "worker"}
        if unknown:
            raise ValueError(f"unknown reset option(s) {sorted(unknown)}; expected 'task', 'worker' or 'reset_mask'")
        seeds = lane_seeds(seed, self.num_envs)
        if mask is not None:
            if options:
                raise ValueError("reset option 'reset_mask' cannot be combined with 'task' or 'worker' "
                                 "(a new pair source applies to all sub-envs)")
            rows = np.flatnonzero(self._check_mask(mask))
            self._seed(seed, seeds, rows)
            return self._begin(rows)
        self._seed(seed, seeds, self._rows)
        self._pairs = None  # a seed (or new options) starts the pair sequence afresh
        if options:
            task = options.get("task", self._source.tasks[0] if len(self._source.tasks) == 1 else None)
            if task is None:
                raise ValueError("reset option 'worker' needs a 'task' when the env has several tasks")
            worker = Worker.of(options["worker"]) if "worker" in options else None
            self._source = PairSource.build(task, worker, None, self._source.include_centre)
            self._stack = StackedTables(self._source.tasks)
            if self._lanes is not None:
                self._lanes.clear_pending()
        self._start_episodes(self._rows)
        return self._stack.obs[self._state], {"progress": np.zeros(self.num_envs, dtype=np.int8)}

    def _seed(self, seed: Any, seeds: list[int | None] | None, rows: np.ndarray) -> None:
        """Apply a reset's seed: an int reseeds the shared generator, a list the lanes in `rows`."""
        if seeds is not None:
            if self._lanes is None:
                self._lanes = LaneGenerators(self.num_envs)
            self._lanes.seed(seeds, rows)
        elif seed is not None:
            super().reset(seed=int(seed))
            self._lanes = None
            self._pairs = None

    def _check_mask(self, mask: Any) -> np.ndarray:
        """`options["reset_mask"]` as Gymnasium defines it: a bool array [num_envs] with a True somewhere."""
        if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_ or mask.shape != (self.num_envs,):
            got = f"{mask.dtype} {mask.shape}" if isinstance(mask, np.ndarray) else type(mask).__name__
            raise ValueError(f"reset option 'reset_mask' must be a bool numpy array of shape ({self.num_envs},), "
                             f"got {got}")
        if not mask.any():
            raise ValueError("reset option 'reset_mask' resets no sub-env (no True value)")
        return mask

    def _begin(self, rows: np.ndarray, current: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start new episodes in `rows` (a masked reset, a same-step autoreset): every sub-env's
        observation and infos afterwards (`current`: the observations of the others, if not the state's)."""
        self._start_episodes(rows)
        return self._stack.obs[self._state], {"progress": self._stack.progress[self._state]}

    def _check_actions(self, actions: np.ndarray) -> np.ndarray:
        """The actions as an int array [num_envs] of colours 0..3, or a ValueError naming the bad sub-envs."""
        a = np.asarray(actions)
        if a.shape != (self.num_envs,) or a.dtype.kind not in "iu":
            raise ValueError(f"actions must be an int array of shape ({self.num_envs},), got {a.dtype} {a.shape}")
        if a.size and (a.min() < 0 or a.max() >= NUM_COLORS):
            bad = np.flatnonzero((a < 0) | (a >= NUM_COLORS))
            raise ValueError(f"invalid action(s) at sub-env(s) {bad[:5].tolist()}: expected 0..{NUM_COLORS - 1}")
        return a

    def _advance(self, a: np.ndarray, moving: np.ndarray) -> np.ndarray:
        """Next state of every sub-env under actions `a` (the rules' table; mistakes drawn from each
        episode's luck key). Only the `moving` sub-envs use up luck draws."""
        st = self._stack
        flat = self._state * NUM_COLORS + a
        column = st.mistake_column[flat]
        mistake = np.zeros(self.num_envs, dtype=bool)
        draw = np.flatnonzero((column < NUM_COLORS) & moving)  # second blocks: the luck decides
        if draw.size:
            colour = a[draw]
            j = self._draws[draw, colour]
            self._draws[draw, colour] = j + 1
            u = luck.uniforms(self._keys[draw], colour, j)
            mistake[draw] = u < self._workers[draw, column[draw]]
        return np.where(mistake, st.next_mistake[flat], st.next_ok[flat])

    def _move(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Apply one step to every sub-env: the action where an episode runs, an autoreset (new pair,
        reward 0, action ignored) where one ended on the previous step. Returns (reward, resetting)."""
        a = self._check_actions(actions)
        resetting = self._needs_reset.copy()
        if self.autoreset_mode != AutoresetMode.NEXT_STEP and resetting.any():
            bad = np.flatnonzero(resetting)[:5].tolist()
            what = ("reset them with reset(options={'reset_mask': mask})" if self.autoreset_mode == AutoresetMode.DISABLED
                    else "call reset() first")
            raise RuntimeError(f"step() on sub-env(s) {bad} whose episode ended or never started: {what}")
        nxt = self._advance(a, ~resetting)
        if resetting.any():
            rows = np.flatnonzero(resetting)
            self._start_episodes(rows)
            nxt[rows] = self._state[rows]
            self._t[rows] = -1  # the reset step itself does not count
        self._state = nxt
        self._t += 1
        reward = self._stack.reward[nxt]
        reward[resetting] = 0.0
        self._return += reward
        return reward, resetting

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every sub-env with its action (int array [num_envs] of colours 0..3)."""
        reward, resetting = self._move(actions)
        terminated, truncated, infos = self._episode_ends(resetting)
        obs, infos = self._autoreset(terminated | truncated, self._stack.obs[self._state], infos)
        return obs, reward, terminated, truncated, infos

    def _autoreset(self, done: np.ndarray, obs: np.ndarray, infos: dict[str, Any]) -> tuple[np.ndarray, dict[str, Any]]:
        """After a step: in SAME_STEP, restart the lanes whose episode is `done` at once (their last
        observation and infos go to `final_obs`/`final_info`); else mark them for a reset."""
        if self.autoreset_mode != AutoresetMode.SAME_STEP or not done.any():
            self._needs_reset = done
            return obs, infos
        final_obs = np.full(self.num_envs, None, dtype=object)
        for i in np.flatnonzero(done).tolist():
            final_obs[i] = obs[i].copy()
        obs, fresh = self._begin(np.flatnonzero(done), obs)
        infos = same_step_infos(infos, done, fresh)
        infos.update(final_obs=final_obs, _final_obs=done.copy())
        return obs, infos

    def _episode_ends(self, resetting: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        """After `_move`: which episodes terminated or were truncated, and the infos (progress; the
        returns of the episodes that ended, with their `_` masks)."""
        st, nxt = self._stack, self._state
        terminated = st.terminal[nxt] & ~resetting
        truncated = (self._t >= st.horizon[self._task_idx]) & ~terminated
        done = terminated | truncated
        infos: dict[str, Any] = {"progress": st.progress[nxt]}
        if done.any():
            ti = self._task_idx
            infos["episode_return"] = np.where(done, self._return, 0.0)
            infos["normalised_return"] = np.where(done, (self._return - st.r_min[ti]) / st.r_span[ti], 0.0)
            for key in ("episode_return", "normalised_return"):
                infos["_" + key] = done
        return terminated, truncated, infos
