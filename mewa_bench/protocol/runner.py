"""The evaluation runner (SPEC section 6): every (pair, seed) unit of a suite, 10 episodes each.

For each unit the agent gets `reset_task()`, then plays the pair's episodes; its state carries
across those episodes and is reset between units. Env seeds are derived from (suite hash, pair,
seed, episode). Results are written after every unit (atomically), so an interrupted or failed run
keeps what it finished and `resume=True` continues it.
"""

from __future__ import annotations

import hashlib
import os
import platform
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from mewa_bench.design.references import summarise
from mewa_bench.design.suites import Suite, load_suite
from mewa_bench.envs.mewa_env import DEFAULT_IMAGE_SIZE, ENV_VERSION, MewaEnv
from mewa_bench.protocol.agent import Transition, agent_sha256
from mewa_bench.protocol.isolation import (DEFAULT_MEMORY_LIMIT, DEFAULT_TIME_LIMIT, AgentError, AgentRunner,
                                           make_agent_runner)
from mewa_bench.protocol.results import (PROTOCOL_VERSION, SCHEMA_VERSION, ResultsError, read_results, unit_key,
                                         write_results)
from mewa_bench.protocol.scoring import BOOTSTRAP_SAMPLES, BOOTSTRAP_SEED, CONFIDENCE, score_run
from mewa_bench.protocol.trajectory import BackgroundSinks, EpisodeRecord, RunInfo, StepRecord, TrajectorySink, UnitRecord

EPISODES_PER_PAIR = 10
DEFAULT_SEEDS = (0, 1, 2)


class EvaluationError(RuntimeError):
    """The agent failed during a run; says where (agent file, pair, seed, episode, step)."""

    def __init__(self, message: str, kind: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class EvalConfig:
    """What to evaluate and how."""

    agent_path: Path
    suite: str = "narrow-v1"
    seeds: tuple[int, ...] = DEFAULT_SEEDS
    episodes: int = EPISODES_PER_PAIR
    out: Path | None = None
    name: str | None = None
    agent_args: dict[str, str] = field(default_factory=dict)
    checkpoint: str | None = None
    isolated: bool = True
    time_limit: float | None = DEFAULT_TIME_LIMIT
    memory_limit: int | None = DEFAULT_MEMORY_LIMIT
    privileged: bool = False
    jobs: int = 1
    resume: bool = False
    overwrite: bool = False  # replace an existing results file (it is replaced when the first unit is written)
    pairs: tuple[int, ...] | None = None  # a subset of pairs, for quick checks (the run is then partial)
    collect_trajectories: bool = False  # set by `evaluate` when sinks are attached
    mode: str = "vector"  # or "sapien": agents observe {"state": float32[18], "image": uint8[H, W, 3]}
    image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE


def agent_name(path: Path) -> str:
    """`submissions/foo/agent.py` -> "foo"; `my_agent.py` -> "my_agent"."""
    return path.parent.name if path.stem == "agent" else path.stem


def default_results_path(config: EvalConfig, suite: Suite) -> Path:
    """`results/<agent>-<suite>.json` in the working directory (`...-partial.json` for a --pairs run)."""
    partial = "-partial" if config.pairs is not None else ""
    return Path("results") / f"{config.name or agent_name(config.agent_path)}-{suite.name}{partial}.json"


def env_seed(suite_hash: str, pair: int, seed: int, episode: int) -> int:
    """Deterministic env seed of one episode, independent of run order and parallelism."""
    digest = hashlib.sha256(f"{suite_hash}/{pair}/{seed}/{episode}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def hidden_pair(suite: Suite, pair: int) -> dict[str, Any]:
    """What a privileged agent is told at reset_task: the pair's task and worker."""
    p = suite.pairs[pair]
    return {"task": suite.tasks[p.task_index].to_dict(), "worker": list(p.worker.w)}


def step_record(step: int, obs: Any, action: int, reward: float, next_obs: Any, terminated: bool,
                truncated: bool, info: dict[str, Any]) -> StepRecord:
    """A step for the sinks: state vectors, plus the image of `next_obs` in sapien mode."""
    if isinstance(obs, dict):
        return StepRecord(step, obs["state"], action, reward, next_obs["state"], terminated, truncated,
                          info["progress"], info["events"], next_obs["image"])
    return StepRecord(step, obs, action, reward, next_obs, terminated, truncated, info["progress"], info["events"])


def play_unit(runner: AgentRunner, env: MewaEnv, suite: Suite, pair: int, seed: int, episodes: int,
              privileged: bool, agent_file: str, collect: bool = False) -> tuple[dict[str, Any], UnitRecord | None]:
    """One (pair, seed) unit: reset_task, then `episodes` episodes; the unit's record and, if `collect`, its steps."""
    p = suite.pairs[pair]
    task, worker = suite.tasks[p.task_index], p.worker.w
    where = f"agent {agent_file}, pair {pair}, seed {seed}"
    try:
        runner.reset_task(hidden_pair(suite, pair) if privileged else None)
    except AgentError as e:
        raise EvaluationError(f"{where}, before episode 1 (reset_task): {e}", e.kind) from None
    best = p.max_expected
    seeds, returns, normalised, lengths, played = [], [], [], [], []
    for k in range(episodes):
        s = env_seed(suite.sha256, pair, seed, k)
        obs, _ = env.reset(seed=s, options={"task": task, "worker": worker})
        first_image = obs["image"] if collect and isinstance(obs, dict) else None
        transition, step, done, steps = None, 0, False, []
        while not done:
            try:
                action = runner.step(transition, obs)
            except AgentError as e:
                raise EvaluationError(f"{where}, episode {k + 1}, step {step}: {e}", e.kind) from None
            next_obs, reward, terminated, truncated, info = env.step(action)
            transition = Transition(obs, action, float(reward), next_obs, terminated, truncated)
            if collect:
                steps.append(step_record(step, obs, action, float(reward), next_obs, terminated, truncated, info))
            obs, step, done = next_obs, step + 1, terminated or truncated
        try:
            runner.end_episode(transition)
        except AgentError as e:
            raise EvaluationError(f"{where}, episode {k + 1}, end_episode after step {step}: {e}", e.kind) from None
        seeds.append(s)
        returns.append(info["episode_return"])
        normalised.append(info["normalised_return"])
        lengths.append(step)
        if collect:
            played.append(EpisodeRecord(k, s, tuple(steps), info["episode_return"], info["normalised_return"],
                                        info["normalised_return"] / best, first_image))
    unit = {"pair": pair, "seed": seed, "task": p.task_index, "env_seeds": seeds, "returns": returns,
            "normalised_returns": normalised, "lengths": lengths, "scores": [v / best for v in normalised]}
    record = UnitRecord(pair, seed, p.task_index, task.to_dict(), worker, tuple(played)) if collect else None
    return unit, record


class _UnitPlayer:
    """Plays units with one agent runner (created on first use) and one env."""

    def __init__(self, config: EvalConfig, suite: Suite) -> None:
        self.config, self.suite = config, suite
        self.env = MewaEnv(task=suite.tasks[0], worker=suite.pairs[0].worker.w, mode=config.mode,
                           image_size=config.image_size)
        self.runner: AgentRunner | None = None

    def play(self, pair: int, seed: int) -> tuple[dict[str, Any], float, UnitRecord | None]:
        c = self.config
        if self.runner is None:
            try:
                self.runner = make_agent_runner(c.agent_path, self.env.observation_space, self.env.action_space,
                                                c.agent_args, c.checkpoint, isolated=c.isolated,
                                                time_limit=c.time_limit, memory_limit=c.memory_limit)
            except AgentError as e:
                raise EvaluationError(f"agent {c.agent_path}: {e}", e.kind) from None
        start = time.perf_counter()
        try:
            unit, record = play_unit(self.runner, self.env, self.suite, pair, seed, c.episodes, c.privileged,
                                     str(c.agent_path), collect=c.collect_trajectories)
        except EvaluationError:
            self.close()
            raise
        return unit, time.perf_counter() - start, record

    def close(self) -> None:
        if self.runner is not None:
            self.runner.close()
            self.runner = None


_WORKER_PLAYER: _UnitPlayer | None = None


def _worker_play(config: EvalConfig, pair: int, seed: int) -> tuple[dict[str, Any], float, UnitRecord | None]:
    """Entry point of a --jobs worker process: reuse one player per process."""
    global _WORKER_PLAYER
    if _WORKER_PLAYER is None:
        _WORKER_PLAYER = _UnitPlayer(config, load_suite(config.suite))
    return _WORKER_PLAYER.play(pair, seed)


def machine_info() -> dict[str, Any]:
    """Where the run happened."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"platform": platform.platform(), "python": platform.python_version(), "cpus": cpus,
            "processor": platform.machine()}


def new_results(config: EvalConfig, suite: Suite) -> dict[str, Any]:
    """The header of a results file, before any unit."""
    from mewa_bench import __version__

    return {
        "schema_version": SCHEMA_VERSION, "protocol_version": PROTOCOL_VERSION, "complete": False,
        "agent": {"name": config.name or agent_name(config.agent_path), "file": str(config.agent_path),
                  "sha256": agent_sha256(config.agent_path), "privileged": config.privileged,
                  "agent_args": dict(sorted(config.agent_args.items())), "checkpoint": config.checkpoint},
        "suite": {"name": suite.name, "version": suite.content["version"], "sha256": suite.sha256},
        "env": {"id": suite.content["env_id"], "version": ENV_VERSION, "mode": config.mode,
                **({"image_size": list(config.image_size)} if config.mode == "sapien" else {})},
        "package_version": __version__, "seeds": list(config.seeds), "episodes_per_pair": config.episodes,
        "pairs": list(config.pairs) if config.pairs is not None else None,
        "isolation": {"isolated": config.isolated, "time_limit": config.time_limit, "memory_limit": config.memory_limit},
        "units": [],
        "timing": {"started": datetime.now(timezone.utc).isoformat(timespec="seconds"), "units": {}},
        "machine": machine_info(),
    }


def _resume_from(path: Path, fresh: dict[str, Any]) -> dict[str, Any]:
    """Continue an earlier run of the same agent, suite and settings."""
    old = read_results(path)
    before, now = old.get("agent", {}), fresh["agent"]
    if before.get("sha256") != now["sha256"]:
        raise ResultsError(f"{path}: cannot resume: the agent file changed since this run started (sha256 "
                           f"{str(before.get('sha256'))[:12]}… then, {now['sha256'][:12]}… now); results of two "
                           f"different agents cannot be mixed: start a new run (--out FILE, or --overwrite)")
    for key in ("agent", "suite", "seeds", "episodes_per_pair", "pairs", "env"):
        if old.get(key) != fresh.get(key):
            raise ResultsError(f"{path}: cannot resume: {key} differs from this run "
                               f"({old.get(key)!r} in the file, {fresh.get(key)!r} now)")
    return old


def finish(results: dict[str, Any], suite: Suite) -> dict[str, Any]:
    """Add scores and baselines to a results dict whose units are all done.

    A partial run (--pairs) is compared with the references over its own pairs, never the whole suite's.
    """
    units = results["units"] = sorted(results["units"], key=unit_key)
    normalised = np.array([u["normalised_returns"] for u in units])
    best = np.array([suite.pairs[u["pair"]].max_expected for u in units])
    partial = results.get("pairs") is not None
    if partial:
        played = [suite.pairs[i].data for i in results["pairs"]]
        baselines = {**summarise(played), "pairs": list(results["pairs"])}
    else:
        baselines = {"score": suite.summary["score"], "skill": suite.summary["skill"],
                     "non_adaptive_gap": suite.summary["non_adaptive_gap"]}
    scores = score_run(normalised, best, baselines["score"]["random_task_specific"])
    results["scores"] = {**scores.to_dict(), "bootstrap": {"seed": BOOTSTRAP_SEED, "samples": BOOTSTRAP_SAMPLES,
                                                           "confidence": CONFIDENCE, "unit": "(pair, seed)"}}
    results["baselines"] = baselines
    results["complete"] = not partial
    return results


Progress = Callable[[int, int], None]


def run_info(config: EvalConfig, suite: Suite, results: dict[str, Any]) -> RunInfo:
    """What sinks record about the run."""
    return RunInfo(agent=results["agent"]["name"], agent_sha256=results["agent"]["sha256"], suite=suite.name,
                   suite_sha256=suite.sha256, seeds=tuple(config.seeds), episodes_per_pair=config.episodes,
                   env_id=results["env"]["id"], env_version=results["env"]["version"],
                   package_version=results["package_version"], mode=results["env"]["mode"],
                   extra={"privileged": config.privileged})


def evaluate(config: EvalConfig, progress: Progress = lambda done, total: None,
             sinks: Sequence[TrajectorySink] = ()) -> tuple[dict[str, Any], Path]:
    """Run (or resume) an evaluation; returns the final results and where they were written.

    Each sink (MCAP / Rerun log, dataset recorder) gets every unit played in this call as soon as it
    finishes, and is closed at the end, also when the run fails or is interrupted.
    """
    if sinks and not config.collect_trajectories:
        config = replace(config, collect_trajectories=True)
    if not config.agent_path.exists():
        raise EvaluationError(f"agent file {config.agent_path} does not exist", "load")
    for what, values in (("seeds", config.seeds), ("pairs", config.pairs or ())):
        if len(set(values)) != len(values):
            raise ValueError(f"{what} {list(values)} repeat a value: every (pair, seed) unit is played once")
    if not config.seeds:
        raise ValueError("at least one seed is needed")
    suite = load_suite(config.suite)
    out = config.out or default_results_path(config, suite)
    results = new_results(config, suite)
    if config.resume and out.exists():
        results = _resume_from(out, results)
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

    def record(unit: dict[str, Any], seconds: float, trajectory: UnitRecord | None) -> None:
        results["units"].append(unit)
        results["timing"]["units"][f"{unit['pair']}/{unit['seed']}"] = round(seconds, 4)
        write_results(out, results)  # after every unit: nothing finished is ever lost
        writers.add_unit(trajectory)
        progress(len(results["units"]), total)

    writers = BackgroundSinks(sinks)
    writers.start(run_info(config, suite, results))
    try:
        if config.jobs <= 1 or len(todo) <= 1:
            player = _UnitPlayer(config, suite)
            try:
                for pair, seed in todo:
                    record(*player.play(pair, seed))
            finally:
                player.close()
        else:
            with ProcessPoolExecutor(max_workers=config.jobs, mp_context=get_context("spawn")) as pool:
                futures = [pool.submit(_worker_play, config, pair, seed) for pair, seed in todo]
                try:
                    for future in as_completed(futures):
                        record(*future.result())
                except BaseException:
                    for f in futures:
                        f.cancel()
                    raise
    finally:
        writers.close()
    finish(results, suite)
    timing = results["timing"]
    timing["finished"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
    timing["wall_time"] = round(timing.get("wall_time", 0.0) + time.perf_counter() - start, 3)
    write_results(out, results)
    return results, out
