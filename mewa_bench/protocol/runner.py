"""The evaluation runner (SPEC section 6): every (pair, seed) unit of a suite, 10 episodes each.

For each unit the agent gets `reset_task()`, then plays the pair's episodes; its state carries
across those episodes and is reset between units. Env seeds are derived from (suite hash, pair,
seed, episode) (`protocol.config`). Results are written as units finish (atomically, `protocol.results`),
so an interrupted or failed run keeps what it finished and `resume=True` continues it.

Here: the unit loop (`unit_calls`: one unit as a sequence of agent calls), the lanes that play
units side by side on one agent process (`_LanePlayer`), and the dispatch over --jobs processes
(`evaluate`).
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from concurrent.futures import ProcessPoolExecutor, as_completed
from datetime import datetime, timezone
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Callable, Generator, NamedTuple, Sequence

import numpy as np

from mewa_bench.design.suites import Suite, load_suite
from mewa_bench.envs.mewa_env import MewaEnv
from mewa_bench.protocol.agent import Transition
from mewa_bench.protocol.config import EvalConfig, default_results_path, default_seeds, env_seed, hidden_pair, unit_seed
from mewa_bench.protocol.isolation import END_EPISODE, RESET_TASK, STEP, AgentError, AgentRunner, make_agent_runner
from mewa_bench.protocol.results import ResultsError, finish, new_results, resume_from, unit_key, write_results
from mewa_bench.protocol.scoring import episode_score
from mewa_bench.protocol.trajectory import BackgroundSinks, EpisodeRecord, RunInfo, StepRecord, TrajectorySink, UnitRecord

WRITE_INTERVAL = 1.0  # least seconds between writes of the results file during a run
WRITE_SHARE = 0.1  # and at most this share of the run's time spent writing it (a big run's file takes a while)


class EvaluationError(RuntimeError):
    """The agent failed during a run; says where (agent file, pair, seed, episode, step)."""

    def __init__(self, kind: str, message: str) -> None:  # the order of AgentError's
        super().__init__(message)
        self.kind = kind


class AgentCall(NamedTuple):
    """What a unit asks of its agent next: a call of `isolation` (RESET_TASK, STEP, END_EPISODE), and when."""

    operation: int
    args: tuple
    episode: int  # -1: before the first episode
    step: int  # for END_EPISODE: the episode's last step


def describe(call: AgentCall, agent_file: Path, pair: int, seed: int) -> str:
    """Where a call happened, for error messages (episodes and steps count from 0, as in logs and datasets)."""
    where = f"agent {agent_file}, pair {pair}, seed {seed}"
    if call.operation == RESET_TASK:
        return f"{where}, before episode 0 (reset_task)"
    if call.operation == END_EPISODE:
        return f"{where}, episode {call.episode}, end_episode after step {call.step}"
    return f"{where}, episode {call.episode}, step {call.step}"


UnitResult = tuple[dict[str, Any], UnitRecord | None]


def unit_calls(env: MewaEnv, suite: Suite, pair: int, seed: int, config: EvalConfig, collect: bool = False
               ) -> Generator[AgentCall, int | None, UnitResult]:
    """One (pair, seed) unit as a sequence of agent calls: reset_task, then `episodes` episodes.

    Send each call's reply (the action for a step, None otherwise); the generator returns the
    unit's record and, if `collect` (sinks are attached), its steps. Episodes and steps count from 0,
    as in logs and datasets.
    """
    p = suite.pairs[pair]
    task, worker = suite.tasks[p.task_index], p.worker.w
    hidden = hidden_pair(suite, pair) if config.privileged else None
    yield AgentCall(RESET_TASK, (hidden, unit_seed(suite.sha256, pair, seed)), -1, -1)
    seeds, returns, normalised, lengths, played = [], [], [], [], []
    for k in range(config.episodes):
        s = env_seed(suite.sha256, pair, seed, k)
        obs, _ = env.reset(seed=s, options={"task": task, "worker": worker, "luck_key": s})  # luck key = env seed
        first_image = obs["image"] if collect and isinstance(obs, dict) else None
        transition, step, done, steps = None, 0, False, []
        while not done:
            action = yield AgentCall(STEP, (transition, obs), k, step)
            next_obs, reward, terminated, truncated, info = env.step(action)
            transition = Transition(obs, action, float(reward), next_obs, terminated, truncated)
            if collect:
                steps.append(StepRecord(step, transition, info["progress"], info["events"]))
            obs, step, done = next_obs, step + 1, terminated or truncated
        yield AgentCall(END_EPISODE, (transition,), k, step - 1)
        seeds.append(s)
        returns.append(info["episode_return"])
        normalised.append(info["normalised_return"])
        lengths.append(step)
        if collect:
            played.append(EpisodeRecord(k, s, tuple(steps), info["episode_return"], info["normalised_return"],
                                        float(episode_score(info["normalised_return"], p.max_expected)), first_image))
    unit = {"pair": pair, "seed": seed, "task": p.task_index, "env_seeds": seeds, "returns": returns,
            "normalised_returns": normalised, "lengths": lengths,
            "scores": [float(v) for v in episode_score(np.array(normalised), p.max_expected)]}
    record = UnitRecord(pair, seed, p.task_index, task.to_dict(), worker, tuple(played)) if collect else None
    return unit, record


OnUnit = Callable[[dict[str, Any], float, UnitRecord | None], None]


class _LanePlayer:
    """Plays units on an agent runner with `config.lanes` lanes (created on first use), one env per lane.

    All lanes advance together, one batched agent call per round, so crossing the process boundary
    costs one round trip per round, not per step; a lane whose unit ends takes the next unit not yet
    begun, so the lanes stay full until the units run out (a lane's unit does not depend on its lane).
    """

    def __init__(self, config: EvalConfig, suite: Suite, collect: bool) -> None:
        self.config, self.suite, self.collect = config, suite, collect
        self.envs: list[MewaEnv] = []
        self.runner: AgentRunner | None = None

    def play(self, units: Sequence[tuple[int, int]], on_unit: OnUnit) -> None:
        """Play (pair, seed) units; `on_unit(unit, seconds, record)` as each one finishes."""
        c = self.config
        if not units:
            return
        if self.runner is None:
            n_lanes = min(c.lanes, len(units))  # a short run needs no more agents than units
            self.envs = [MewaEnv(task=self.suite.tasks[0], worker=self.suite.pairs[0].worker.w, mode=c.mode,
                                 image_size=c.image_size, events=self.collect) for _ in range(n_lanes)]
            env = self.envs[0]
            try:
                self.runner = make_agent_runner(c.agent_path, env.observation_space, env.action_space, c.agent_args,
                                                c.checkpoint, isolated=c.isolated, time_limit=c.time_limit,
                                                memory_limit=c.memory_limit, lanes=n_lanes, launcher=c.launcher)
            except AgentError as e:
                raise EvaluationError(e.kind, f"agent {c.agent_path}: {e}") from None
        n_lanes = len(self.envs)
        waiting = deque(units)
        active: dict[int, tuple[Generator, AgentCall, float, int, int]] = {}

        def start(lane: int) -> None:
            if waiting:
                pair, seed = waiting.popleft()
                calls = unit_calls(self.envs[lane], self.suite, pair, seed, c, self.collect)
                active[lane] = (calls, next(calls), time.perf_counter(), pair, seed)

        for lane in range(n_lanes):
            start(lane)
        while active:
            lanes = sorted(active)
            try:
                replies = self.runner.batch([(lane, active[lane][1].operation, active[lane][1].args) for lane in lanes])
            except AgentError as e:
                self.close()
                if e.index is not None and e.index < len(lanes):
                    _, failed, _, pair, seed = active[lanes[e.index]]
                    where = describe(failed, c.agent_path, pair, seed)
                else:  # the whole batch failed (the process died, ran out of memory): where its lanes were
                    _, first, _, pair, seed = active[lanes[0]]
                    where = describe(first, c.agent_path, pair, seed)
                    if len(lanes) > 1:
                        where = f"{where} (the first of a batch of {len(lanes)} lanes)"
                raise EvaluationError(e.kind, f"{where}: {e}") from None
            for lane, reply in zip(lanes, replies):
                calls, _, started, pair, seed = active[lane]
                try:
                    active[lane] = (calls, calls.send(reply), started, pair, seed)
                except StopIteration as done:
                    del active[lane]
                    on_unit(*done.value[:1], time.perf_counter() - started, done.value[1])
                    start(lane)

    def close(self) -> None:
        if self.runner is not None:
            self.runner.close()
            self.runner = None


_WORKER_PLAYER: _LanePlayer | None = None


def _worker_play(units: list[tuple[int, int]], config: EvalConfig, collect: bool
                 ) -> list[tuple[dict[str, Any], float, UnitRecord | None]]:
    """Entry point of a --jobs worker process or a Ray task: play a batch of units, reusing one player
    per process while the run's settings stay the same (a Ray worker may serve several runs)."""
    global _WORKER_PLAYER
    if _WORKER_PLAYER is not None and (_WORKER_PLAYER.config, _WORKER_PLAYER.collect) != (config, collect):
        _WORKER_PLAYER.close()
        _WORKER_PLAYER = None
    if _WORKER_PLAYER is None:
        _WORKER_PLAYER = _LanePlayer(config, load_suite(config.suite), collect)
    finished: list[tuple[dict[str, Any], float, UnitRecord | None]] = []
    _WORKER_PLAYER.play(units, lambda unit, seconds, record: finished.append((unit, seconds, record)))
    return finished


Progress = Callable[[int, int], None]


def _play_on_ray(config: EvalConfig, todo: list[tuple[int, int]], collect: bool, record: OnUnit) -> None:
    """The units as Ray tasks of `config.lanes` units each (`protocol.ray_backend`)."""
    from mewa_bench.protocol import ray_backend

    with ray_backend.session(config.ray, num_cpus=config.jobs if config.jobs > 1 else None):
        batches = [todo[i:i + config.lanes] for i in range(0, len(todo), config.lanes)]
        ray_backend.play_batches(config, batches, collect, _worker_play, record, EvaluationError)


def run_info(config: EvalConfig, suite: Suite, results: dict[str, Any]) -> RunInfo:
    """What sinks record about the run."""
    return RunInfo(agent=results["agent"]["name"], agent_sha256=results["agent"]["sha256"], suite=suite.name,
                   suite_sha256=suite.sha256, seeds=tuple(config.seeds), episodes_per_pair=config.episodes,
                   env_id=results["env"]["id"], env_version=results["env"]["version"],
                   package_version=results["package_version"], mode=results["env"]["mode"],
                   extra={"privileged": config.privileged, **_given("agent_args", results["agent"].get("agent_args")),
                          **_given("checkpoint", results["agent"].get("checkpoint"))})


def _given(key: str, value: Any) -> dict[str, Any]:
    """{key: value} when the value was given (not empty), else nothing: a run's records name only what was set."""
    return {key: value} if value else {}


def evaluate(config: EvalConfig, progress: Progress = lambda done, total: None,
             sinks: Sequence[TrajectorySink] = ()) -> tuple[dict[str, Any], Path]:
    """Run (or resume) an evaluation; returns the final results and where they were written.

    Each sink (MCAP / Rerun log, dataset recorder) gets every unit played in this call as soon as it
    finishes, and is closed at the end, also when the run fails or is interrupted.
    """
    if not config.agent_path.exists():
        raise EvaluationError("load", f"agent file {config.agent_path} does not exist")
    suite = load_suite(config.suite)
    if config.seeds is None:
        config = dataclasses.replace(config, seeds=default_seeds(suite.name))
    for what, values in (("seeds", config.seeds), ("pairs", config.pairs or ())):
        if len(set(values)) != len(values):
            raise ValueError(f"{what} {list(values)} repeat a value: every (pair, seed) unit is played once")
    if not config.seeds:
        raise ValueError("at least one seed is needed")
    if config.lanes < 1:
        raise ValueError(f"lanes must be >= 1, got {config.lanes}")
    out = config.out or default_results_path(config, suite)
    results = new_results(config, suite)
    if config.resume and out.exists():
        results = resume_from(out, results)
    elif out.exists() and not config.overwrite:
        raise ResultsError(f"{out} already exists: pass --resume to continue that run, --overwrite to replace it, "
                           f"or --out for another file")
    pairs = config.pairs if config.pairs is not None else tuple(range(len(suite.pairs)))
    bad = [p for p in pairs if not 0 <= p < len(suite.pairs)]
    if bad:
        raise ValueError(f"pair(s) {bad} not in {suite.name} (pairs 0..{len(suite.pairs) - 1})")
    done = {unit_key(u) for u in results["units"]}
    todo = [(p, s) for p in pairs for s in config.seeds if (p, s) not in done]
    total = len(pairs) * len(config.seeds)
    progress(total - len(todo), total)
    start = time.perf_counter()

    last_write = [time.perf_counter(), 0, WRITE_INTERVAL]  # when the file was last written, with how many units, gap

    def save() -> None:
        began = time.perf_counter()
        write_results(out, results)
        now = time.perf_counter()
        last_write[:] = [now, len(results["units"]), max(WRITE_INTERVAL, (now - began) * (1 / WRITE_SHARE - 1))]

    def record(unit: dict[str, Any], seconds: float, trajectory: UnitRecord | None) -> None:
        results["units"].append(unit)
        results["timing"]["units"][f"{unit['pair']}/{unit['seed']}"] = round(seconds, 4)
        if time.perf_counter() - last_write[0] >= last_write[2]:
            save()  # spaced while running (WRITE_INTERVAL, WRITE_SHARE), and whatever happens at the end
        writers.add_unit(trajectory)
        progress(len(results["units"]), total)

    writers = BackgroundSinks(sinks)
    try:
        if todo:  # a finished run resumed plays nothing: no empty log files
            writers.start(run_info(config, suite, results))
        if config.ray is not None and todo:
            _play_on_ray(config, todo, bool(sinks), record)
        elif config.jobs <= 1 or len(todo) <= config.lanes:
            player = _LanePlayer(config, suite, collect=bool(sinks))
            try:
                player.play(todo, record)
            finally:
                player.close()
        else:
            batches = [todo[i:i + config.lanes] for i in range(0, len(todo), config.lanes)]
            with ProcessPoolExecutor(max_workers=config.jobs, mp_context=get_context("spawn")) as pool:
                futures = [pool.submit(_worker_play, batch, config, bool(sinks)) for batch in batches]
                try:
                    for future in as_completed(futures):
                        for finished in future.result():
                            record(*finished)
                except BaseException:
                    for f in futures:
                        f.cancel()
                    raise
    finally:
        if len(results["units"]) != last_write[1]:
            save()  # nothing finished is ever lost, also when the run fails or is interrupted
        writers.close()
    finish(results, suite)
    timing = results["timing"]
    timing["finished"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
    timing["wall_time"] = round(timing.get("wall_time", 0.0) + time.perf_counter() - start, 3)
    write_results(out, results)
    return results, out
