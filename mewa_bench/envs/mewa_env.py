"""The MEWA Gymnasium environment (vector observations)."""

from __future__ import annotations

import importlib.util
from typing import Any, NamedTuple, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from mewa_bench.envs.pairs import SCALAR_PAIR_BATCH, PairSource, as_task
from mewa_bench.game import luck
from mewa_bench.game.normalise import return_bounds
from mewa_bench.game.palette import (COLOR_NAMES, NUM_COLORS, OBS_AGENT_BLOCKS, OBS_COMPLETED, OBS_MISTAKE_FLAGS,
                                      OBS_SIZE, OBS_STRUCTURE_BLOCKS, OBS_WORKER_LEFT, OBS_WORKER_PLACED)
from mewa_bench.game.table import transition_table
from mewa_bench.game.task import Task, Worker

ENV_VERSION = "v0"
RENDER_MODES = ("ansi", "rgb_array")  # rgb_array: the SAPIEN picture, with the sapien extra
OBSERVATION_MODES = ("vector", "sapien")
DEFAULT_IMAGE_SIZE = (128, 128)  # (height, width)


class MewaEnv(gym.Env):
    """
    ## Description
    MEWA ("Meta-learning for Worker Adapting", Stoican, Cangelosi & Weisswange, IEEE SSCI 2023).
    The agent hands coloured blocks, one per step, to a simulated worker that builds one structure
    per colour. Structures must be completed in a hidden sub-goal order. When a structure gets its
    second block the worker may make a mistake, with a probability `w[x]` that depends on how many
    structures are open at once (`x + 1`); a mistaken structure is handed back when it reaches `M`
    blocks. The worker's mistake probabilities are hidden and differ from one task variation to the
    next, so a good agent must adapt to the worker it faces.

    ## Action Space
    `Discrete(4)`: the palette colour of the block to hand over,
    `0 orange, 1 blue, 2 green, 3 red`. A colour the task does not use, or of which the agent has no
    block left, is a no-op that still costs the step's reward.

    ## Observation Space
    `Box(0, 255, (18,), float32)`:
    - `[0:4]` blocks the agent holds, per palette colour;
    - `[4:12]` per colour: blocks in the worker's open structure, and its mistake flag (0/1);
    - `[12:16]` completed flag per colour;
    - `[16]` worker blocks not yet placed, `[17]` worker blocks placed.

    With `mode="sapien"`: `Dict(state=<the Box above>, image=Box(0, 255, (H, W, 3), uint8))`.

    ## Rewards
    While sub-goal `i` is the current one, every step gives `task.rewards[i]` (negative, increasing
    with `i`); the step that completes the last sub-goal gives 0.

    ## Starting State
    `K` blocks of each colour the task uses; no structures; no worker blocks placed.

    ## Episode End
    - Termination: every sub-goal has been completed.
    - Truncation: `task.T` (= 100) steps without termination.

    ## Worker luck
    Each episode draws a luck key (an int in [0, 2**63)) from the env's generator; the j-th time
    the structure of colour c gets its second block, the mistake happens if `u(key, c, j) < w[x]`
    (`mewa_bench.game.luck`). Each draw is an independent Bernoulli(w[x]), as the rules say; the key
    only makes luck reproducible and shareable: two policies played with the same key meet the
    same luck where their paths allow (`reset(options={"luck_key": k})`, `env.luck_key`).

    ## Information
    `info["progress"]` (sub-goals reached), at the end of an episode `info["episode_return"]` and
    `info["normalised_return"]` (SPEC section 2: 0 = worst, 1 = perfect), and with `events=True`
    `info["events"]` (a tuple of `Event`s: `mistake`, `structure_completed`, `structure_returned`,
    `subgoal_reached`). Events are off by default so that every info entry is a number, which
    generic readers (vector envs' info stacking, TorchRL) can batch.

    ## Arguments
    ```python
    gymnasium.make("mewa/MEWA-v0")                          # narrow-v1 task, meta-train workers
    gymnasium.make("mewa/MEWA-v0", task=task, worker=(0.6, 0.4, 0.2, 0.1))   # one fixed pair
    gymnasium.make("mewa/MEWA-v0", tasks=suite.tasks)       # a task and a worker sampled per reset
    ```
    - `task`: a `Task` (or its JSON dict). With `worker`, the pair is fixed; without, a meta-train
      worker is sampled from the task's distribution at every reset.
    - `tasks`: several tasks; each reset samples one uniformly, then a meta-train worker.
    - `include_centre`: also sample meta-train workers from the centre band (see `distributions`).
    - `events=True`: report each step's game events in `info["events"]` (logs use them).
    - `mode="sapien"`: observations become `{"state": float32[18], "image": uint8[H, W, 3]}`, the
      scene rendered headless by SAPIEN (`image_size=(H, W)`, default 128 x 128); same rules.
      `render_mode="rgb_array"` returns that image, `render_mode="ansi"` a text picture.
    - `reset(options={"task": ..., "worker": ...})` switches to that pair (for this and later resets);
      `reset(options={"keep_pair": True})` plays the current pair again (see `MetaEpisode`);
      `reset(options={"luck_key": k})` plays this episode with luck key `k` (combines with the others).

    ## Version History
    - v0: the rules of SPEC section 2, reproducing the authors' reference traces exactly. Since
      protocol 2 mistakes are drawn from a per-episode luck key (same game, same distributions; a
      given seed gives other episodes than the protocol-1 code did).
    """

    metadata: dict[str, Any] = {"render_modes": list(RENDER_MODES), "render_fps": 4}

    def __init__(self, task: Task | dict | None = None, worker: Sequence[float] | None = None,
                 tasks: Sequence[Task | dict] | None = None, include_centre: bool = False,
                 render_mode: str | None = None, mode: str = "vector",
                 image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE, events: bool = False) -> None:
        self.metadata = {**MewaEnv.metadata, "render_modes": available_render_modes()}
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise ValueError(f"render_mode {render_mode!r} is not one of {list(RENDER_MODES)}")
        if mode not in OBSERVATION_MODES:
            raise ValueError(f"mode {mode!r} is not one of {', '.join(OBSERVATION_MODES)}")
        self.render_mode, self.mode, self.events = render_mode, mode, bool(events)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self._renderer: Any = None
        self.action_space = spaces.Discrete(NUM_COLORS)
        state_space = spaces.Box(0.0, 255.0, shape=(OBS_SIZE,), dtype=np.float32)
        if mode == "sapien":
            height, width = self.image_size
            self.observation_space = spaces.Dict({
                "state": state_space, "image": spaces.Box(0, 255, shape=(height, width, 3), dtype=np.uint8)})
            self._image()  # fail now, with the install hint, if no render device is usable
        else:
            self.observation_space = state_space
        if render_mode == "rgb_array" and render_mode not in self.metadata["render_modes"]:
            self._image()  # sapien is missing: fail now, naming the extra
        self._source = PairSource.build(task, worker, tasks, include_centre)
        self._set_pair(self._source.tasks[0], self._source.worker or Worker((0.0,) * self._source.tasks[0].N))
        self._t = 0
        self._done = True
        self._pending: list[tuple[int, list[float]]] = []

    # -- the current pair -------------------------------------------------------------------------
    @property
    def tasks(self) -> tuple[Task, ...]:
        """The tasks this env draws from (one when the pair is fixed)."""
        return self._source.tasks

    @property
    def task(self) -> Task:
        """The task being played (hidden from agents under the evaluation protocol)."""
        return self._task

    @property
    def worker(self) -> Worker:
        """The worker of the current episode (hidden from agents under the evaluation protocol)."""
        return self._worker

    def _set_pair(self, task: Task, worker: Worker) -> None:
        worker.check_fits(task)
        if getattr(self, "_task", None) is None or task.key() != self._task.key():
            self._fast = _fast_table(task)
            self._r_min, r_max = return_bounds(task)
            self._r_span = r_max - self._r_min
        self._task, self._worker = task, worker
        self._w = list(worker.w)

    # -- Gymnasium API ----------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start an episode.

        `options` may fix a new pair, {"task": Task|dict, "worker": [w_0, ...]}, for this and later
        resets, or ask to replay the current pair once more, {"keep_pair": True}.
        """
        super().reset(seed=seed)
        if seed is not None:
            self._pending.clear()
        options = dict(options or {})
        unknown = set(options) - {"task", "worker", "keep_pair", "luck_key"}
        if unknown:
            raise ValueError(f"unknown reset option(s) {sorted(unknown)}; expected 'task', 'worker', 'keep_pair' "
                             "or 'luck_key'")
        key = luck.check_key(options.pop("luck_key")) if "luck_key" in options else None
        if options.get("keep_pair"):
            if len(options) > 1:
                raise ValueError("reset option 'keep_pair' cannot be combined with 'task' or 'worker'")
            return self._start(key)
        if "task" in options or "worker" in options:
            task = as_task(options["task"]) if "task" in options else self._task
            if "worker" not in options and (task.average_worker is None or task.sigma is None):
                raise ValueError("reset option 'task' without 'worker' needs a task with a worker distribution")
            worker = Worker.of(options["worker"]) if "worker" in options else None
            self._source = PairSource((task,), worker, self._source.include_centre)
            self._source.check()
            self._pending.clear()
        if not self._pending:  # sampling pairs in batches makes resets ~50x cheaper
            task_idx, workers = self._source.sample(self.np_random, SCALAR_PAIR_BATCH)
            self._pending.extend(reversed(list(zip(task_idx.tolist(), workers.tolist()))))
        i, w = self._pending.pop()
        task = self._source.tasks[i]
        self._set_pair(task, Worker(tuple(w[: task.N])))
        return self._start(key)

    @property
    def luck_key(self) -> int:
        """The current episode's luck key (hidden from agents under the evaluation protocol)."""
        return self._luck_key

    def _start(self, key: int | None = None) -> tuple[np.ndarray, dict]:
        if key is None:
            key = int(self.np_random.integers(0, luck.KEY_BOUND))
        self._luck_key = key
        self._draws = [0] * NUM_COLORS
        self._s = 0
        self._t = 0
        self._return = 0.0
        self._done = False
        return self._observe(0), ({"progress": 0, "events": ()} if self.events else {"progress": 0})

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Hand over one block of colour `action`."""
        if self._done:
            raise RuntimeError("step() called on a finished episode (or before reset()); call reset() first")
        a = action if type(action) is int and 0 <= action < NUM_COLORS else as_action(action)
        f = self._fast
        s = self._s
        x = f.mistake_type[s][a]
        mistake = False
        if x >= 0:  # the structure gets its second block: the j-th draw of colour a decides
            j = self._draws[a]
            self._draws[a] = j + 1
            mistake = luck.uniform(self._luck_key, a, j) < self._w[x]
        if mistake:
            s, events = f.next_mistake[s][a], f.events_mistake[s][a]
        else:
            s, events = f.next_ok[s][a], f.events_ok[s][a]
        self._s = s
        self._t += 1
        reward = f.reward[s]
        self._return += reward
        terminated = f.terminal[s]
        truncated = self._t >= self._task.T and not terminated
        info: dict[str, Any] = {"progress": f.progress[s]}
        if self.events:
            info["events"] = f.event_sets[events]
        if terminated or truncated:
            self._done = True
            info["episode_return"] = self._return
            info["normalised_return"] = (self._return - self._r_min) / self._r_span
        return self._observe(s), reward, terminated, truncated, info

    def _observe(self, s: int) -> np.ndarray | dict[str, np.ndarray]:
        obs = self._fast.obs[s].copy()
        if self.mode == "vector":
            return obs
        return {"state": obs, "image": self._image(s)}

    def _image(self, s: int | None = None) -> np.ndarray:
        """The SAPIEN picture of state index `s` (or just build the renderer); sapien is imported here only."""
        if self._renderer is None:
            from mewa_bench.render.scene import SceneRenderer

            height, width = self.image_size
            self._renderer = SceneRenderer(width=width, height=height)
        if s is None:
            return np.empty(0, dtype=np.uint8)
        return self._renderer.render(self._task, self._fast.states[s])

    def render(self) -> str | np.ndarray | None:
        """Text picture (render_mode="ansi") or SAPIEN image (render_mode="rgb_array") of the current state."""
        if self.render_mode == "ansi":
            return render_text(self._task, self._fast.obs[self._s], self._t)
        if self.render_mode == "rgb_array":
            return self._image(getattr(self, "_s", 0))
        return None


def available_render_modes() -> list[str]:
    """The render modes this install supports: "ansi", and "rgb_array" if sapien can be imported."""
    return list(RENDER_MODES) if importlib.util.find_spec("sapien") is not None else ["ansi"]


def as_action(action: Any) -> int:
    """An action as an int in 0..3; floats (even 2.0), bools and out-of-range values are errors."""
    if isinstance(action, np.ndarray) and action.ndim == 0:
        action = action[()]
    if isinstance(action, (bool, np.bool_)) or not isinstance(action, (int, np.integer)) \
            or not 0 <= action < NUM_COLORS:
        raise ValueError(f"invalid action {action!r}: expected an int in 0..{NUM_COLORS - 1}")
    return int(action)


class _FastTable(NamedTuple):
    """A transition table as nested Python lists: indexing them is several times faster than numpy's."""

    next_ok: list[list[int]]
    next_mistake: list[list[int]]
    mistake_type: list[list[int]]
    events_ok: list[list[int]]
    events_mistake: list[list[int]]
    event_sets: tuple
    obs: np.ndarray
    reward: list[float]
    terminal: list[bool]
    progress: list[int]
    states: tuple


_FAST: dict[tuple, _FastTable] = {}


def _fast_table(task: Task) -> _FastTable:
    key = task.key()
    if key not in _FAST:
        t = transition_table(task)
        _FAST[key] = _FastTable(t.next_ok.tolist(), t.next_mistake.tolist(), t.mistake_type.tolist(),
                                t.events_ok.tolist(), t.events_mistake.tolist(), t.event_sets, t.obs,
                                t.reward.tolist(), t.terminal.tolist(), t.progress.tolist(), t.states)
    return _FAST[key]


def render_text(task: Task, obs: np.ndarray, t: int) -> str:
    """A few lines describing an observation, for humans."""
    lines = [f"step {t}/{task.T}  order: {' > '.join(COLOR_NAMES[c] for c in task.order)}"]
    agent, blocks, flags, completed = (obs[OBS_AGENT_BLOCKS], obs[OBS_STRUCTURE_BLOCKS], obs[OBS_MISTAKE_FLAGS],
                                       obs[OBS_COMPLETED])
    for c in task.colors:
        flag = " (mistake)" if flags[c] else ""
        done = " done" if completed[c] else ""
        lines.append(f"  {COLOR_NAMES[c]:<6} agent {int(agent[c])}  structure {int(blocks[c])}{flag}{done}")
    lines.append(f"  worker blocks: {int(obs[OBS_WORKER_PLACED])} placed, {int(obs[OBS_WORKER_LEFT])} to place")
    return "\n".join(lines)
