"""The shipped reference agents (`submissions/*/agent.py`) against the suites' exact baselines.

Each agent is loaded as the evaluator loads it and driven through `MewaEnv` by a local loop with
the protocol's calls: reset_task (with the hidden pair for the privileged oracle), then episodes,
observe after every step and end_episode at the end. Sampled means are compared with the exact
baselines within 3 standard errors.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import pytest
from scipy.stats import chi2

from mewa_bench.design.suites import Pair, Suite, load_suite
from mewa_bench.envs.mewa_env import MewaEnv
from mewa_bench.game.task import Task
from mewa_bench.protocol.agent import Transition, load_agent

SUBMISSIONS = Path(__file__).resolve().parents[1] / "submissions"
EPISODES = 10  # per pair, as in the protocol
UNITS = 3  # (pair, seed) units per pair for the baseline checks
TOLERANCE = 1e-9  # below this, returns are equal up to floating-point rounding


@pytest.fixture(scope="module")
def narrow() -> Suite:
    return load_suite("narrow-v1")


@pytest.fixture(scope="module")
def wide() -> Suite:
    return load_suite("wide-v1")


@pytest.fixture(scope="module")
def env(narrow: Suite) -> MewaEnv:
    return MewaEnv(task=narrow.tasks[0], worker=narrow.pairs[0].worker.w)


def load(name: str, env: MewaEnv, **agent_args: str) -> Any:
    """Load `submissions/<name>/agent.py` as the evaluator does."""
    return load_agent(SUBMISSIONS / name / "agent.py", env.observation_space, env.action_space, agent_args)


def hidden(task: Task, worker: Sequence[float]) -> dict[str, Any]:
    """What a privileged agent is told at reset_task."""
    return {"task": task.to_dict(), "worker": list(worker)}


def play_episode(agent: Any, env: MewaEnv, seed: int | None,
                 options: dict[str, Any] | None = None) -> tuple[float, list[int]]:
    """One episode of the protocol loop: its normalised return and the actions taken."""
    obs, _ = env.reset(seed=seed, options=options)
    actions, done = [], False
    while not done:
        action = agent.act(obs)
        next_obs, reward, terminated, truncated, info = env.step(action)
        agent.observe(Transition(obs, action, float(reward), next_obs, terminated, truncated))
        obs, done = next_obs, terminated or truncated
        actions.append(action)
    agent.end_episode()
    return info["normalised_return"], actions


def play_pair(agent: Any, env: MewaEnv, task: Task, worker: Sequence[float], seed: int,
              episodes: int = EPISODES, privileged: bool = False) -> tuple[list[float], list[int]]:
    """reset_task, then `episodes` episodes of one pair: normalised returns and all actions."""
    if privileged:
        agent.reset_task(hidden(task, worker))
    else:
        agent.reset_task()
    returns, actions = [], []
    for k in range(episodes):
        value, taken = play_episode(agent, env, seed * 1000 + k, {"task": task, "worker": list(worker)})
        returns.append(value)
        actions.extend(taken)
    return returns, actions


def pair_returns(agent_for_unit: Callable[[int], Any], env: MewaEnv, suite: Suite, pairs: Sequence[Pair],
                 units: int = UNITS, privileged: bool = False) -> dict[int, np.ndarray]:
    """Normalised returns per pair index: `units` runs of 10 episodes, unit u played by `agent_for_unit(u)`."""
    out = {}
    for pair in pairs:
        task = suite.tasks[pair.task_index]
        runs = []
        for u in range(units):
            unit = 100 * pair.index + u
            runs.append(play_pair(agent_for_unit(unit), env, task, pair.worker.w, unit, privileged=privileged)[0])
        out[pair.index] = np.concatenate(runs)
    return out


def seeded(name: str, env: MewaEnv) -> Callable[[int], Any]:
    """A fresh agent per unit, seeded by the unit, so that the units are independent draws."""
    return lambda unit: load(name, env, seed=str(unit))


def shared(agent: Any) -> Callable[[int], Any]:
    """The same (deterministic) agent for every unit."""
    return lambda unit: agent


def deviation_in_se(returns: dict[int, np.ndarray], expected: dict[int, float]) -> float:
    """(mean over pairs of sampled mean - exact value) / its standard error."""
    diffs = np.array([returns[p].mean() - expected[p] for p in returns])
    variances = np.array([returns[p].var(ddof=1) / len(returns[p]) for p in returns])
    se = np.sqrt(variances.sum()) / len(diffs)
    if se > TOLERANCE:
        return float(diffs.mean() / se)
    return 0.0 if abs(diffs.mean()) < TOLERANCE else float(np.inf)


def pair_z_scores(returns: dict[int, np.ndarray], expected: dict[int, float]) -> np.ndarray:
    """Per pair: (sampled mean - exact value) / standard error; a pair whose returns never vary must match exactly."""
    z = []
    for p, values in returns.items():
        diff, se = values.mean() - expected[p], values.std(ddof=1) / np.sqrt(len(values))
        z.append(diff / se if se > TOLERANCE else (0.0 if abs(diff) < TOLERANCE else np.inf))
    return np.array(z)


def assert_matches(returns: dict[int, np.ndarray], expected: dict[int, float]) -> None:
    """The suite mean within 3 SE of the exact one, and no pair off (chi-square test at the 0.1% level)."""
    assert abs(deviation_in_se(returns, expected)) <= 3.0
    z = pair_z_scores(returns, expected)
    assert (z ** 2).sum() <= chi2.ppf(0.999, df=len(z)), np.round(z, 2)


def baseline(suite: Suite, name: str) -> dict[int, float]:
    """An exact baseline of every pair, by pair index."""
    return {p.index: float(p.data["baselines"][name]) for p in suite.pairs}


# -- random ---------------------------------------------------------------------------------------

def test_random_matches_exact_random_baseline(narrow: Suite, env: MewaEnv) -> None:
    returns = pair_returns(seeded("random", env), env, narrow, narrow.pairs)
    assert_matches(returns, baseline(narrow, "random"))
    # the check has power: the same returns are far from the random task-specific baseline
    assert abs(deviation_in_se(returns, baseline(narrow, "random_task_specific"))) > 10.0


def test_random_is_deterministic_given_its_seed(narrow: Suite, env: MewaEnv) -> None:
    task, worker = narrow.tasks[0], narrow.pairs[5].worker.w
    first = play_pair(load("random", env, seed="7"), env, task, worker, seed=1, episodes=2)
    again = play_pair(load("random", env, seed="7"), env, task, worker, seed=1, episodes=2)
    other = play_pair(load("random", env, seed="8"), env, task, worker, seed=1, episodes=2)
    assert first == again
    assert first[1] != other[1]


def test_random_never_touches_the_global_rng(narrow: Suite, env: MewaEnv) -> None:
    np.random.seed(0)
    expected = np.random.random()
    np.random.seed(0)
    agent = load("random", env)
    agent.reset_task()
    for _ in range(50):
        agent.act(np.zeros(18, dtype=np.float32))
    assert np.random.random() == expected


def test_a_deterministic_agent_unit_does_not_depend_on_the_units_before_it(narrow: Suite, env: MewaEnv) -> None:
    task, first, second = narrow.tasks[0], narrow.pairs[2].worker.w, narrow.pairs[7].worker.w
    agent = load("bayes-adaptive", env)
    play_pair(agent, env, task, first, seed=5, episodes=2)
    after_another_unit = play_pair(agent, env, task, second, seed=6, episodes=2)
    assert play_pair(load("bayes-adaptive", env), env, task, second, seed=6, episodes=2) == after_another_unit


@pytest.mark.parametrize("name", ["random", "random-task-specific"])
def test_random_agents_continue_their_stream_and_reproduce_from_their_seed(narrow: Suite, env: MewaEnv,
                                                                           name: str) -> None:
    task, worker = narrow.tasks[0], narrow.pairs[7].worker.w
    agent = load(name, env)
    one = play_pair(agent, env, task, worker, seed=6, episodes=2)
    two = play_pair(agent, env, task, worker, seed=6, episodes=2)
    assert one != two  # same pair and env seeds, but the coin flips go on: units are not replays
    again = load(name, env)
    assert [play_pair(again, env, task, worker, seed=6, episodes=2) for _ in range(2)] == [one, two]


# -- random task-specific -------------------------------------------------------------------------

def test_random_task_specific_matches_exact_baseline(narrow: Suite, env: MewaEnv) -> None:
    returns = pair_returns(seeded("random-task-specific", env), env, narrow, narrow.pairs)
    assert_matches(returns, baseline(narrow, "random_task_specific"))
    assert abs(deviation_in_se(returns, baseline(narrow, "random"))) > 10.0


def test_random_task_specific_is_deterministic_given_its_seed(narrow: Suite, env: MewaEnv) -> None:
    task, worker = narrow.tasks[0], narrow.pairs[7].worker.w
    first = play_pair(load("random-task-specific", env, seed="3"), env, task, worker, seed=2, episodes=3)
    again = play_pair(load("random-task-specific", env, seed="3"), env, task, worker, seed=2, episodes=3)
    assert first == again


# -- oracle ---------------------------------------------------------------------------------------

def test_oracle_picks_the_max_expected_policy(narrow: Suite, env: MewaEnv) -> None:
    agent = load("oracle-t-optimal", env)
    for pair in narrow.pairs:
        agent.reset_task(hidden(narrow.tasks[pair.task_index], pair.worker.w))
        assert agent.expected_return == pytest.approx(pair.max_expected, abs=1e-9)


def test_oracle_matches_max_expected(narrow: Suite, env: MewaEnv) -> None:
    returns = pair_returns(shared(load("oracle-t-optimal", env)), env, narrow, narrow.pairs, privileged=True)
    assert_matches(returns, baseline(narrow, "max_expected"))
    assert deviation_in_se(returns, baseline(narrow, "random_task_specific")) > 8.0  # ~9.5 SE with these seeds


def test_oracle_refuses_to_run_unprivileged(env: MewaEnv) -> None:
    agent = load("oracle-t-optimal", env)
    with pytest.raises(ValueError, match="privileged"):
        agent.reset_task()


@pytest.mark.parametrize("name, privileged", [("random", False), ("random-task-specific", False),
                                              ("bayes-adaptive", False), ("oracle-t-optimal", True)])
def test_only_the_oracle_is_privileged(env: MewaEnv, name: str, privileged: bool) -> None:
    agent = load(name, env)
    if privileged:  # it refuses to run without being told the pair, and plays once told
        with pytest.raises(ValueError, match="privileged"):
            agent.reset_task()
        task, worker = load_suite("narrow-v1").tasks[0], load_suite("narrow-v1").pairs[0].worker.w
        agent.reset_task(hidden(task, worker))
    else:  # it plays without being told anything
        agent.reset_task()
    _, actions = play_episode(agent, env, seed=0)
    assert len(actions) > 0


# -- bayes-adaptive -------------------------------------------------------------------------------

def test_bayes_adaptive_infers_every_wide_task(wide: Suite) -> None:
    env = MewaEnv(task=wide.tasks[0])  # no worker given: a meta-train worker per reset
    agent = load("bayes-adaptive", env)  # knows the tasks of every shipped suite by default
    candidates_at_start = []
    for i, task in enumerate(wide.tasks):
        agent.reset_task()
        for episode in range(3):
            options = {"task": task} if episode == 0 else {"keep_pair": True}
            obs, _ = env.reset(seed=10 + i if episode == 0 else None, options=options)
            done, first_step = False, episode == 0
            while not done:
                action = agent.act(obs)
                if first_step:  # act() has checked the first observation against the known tasks
                    candidates_at_start.append(len(agent.task_belief.candidates))
                    first_step = False
                next_obs, reward, terminated, truncated, _ = env.step(action)
                agent.observe(Transition(obs, action, float(reward), next_obs, terminated, truncated))
                obs, done = next_obs, terminated or truncated
                assert task in agent.task_belief.candidates, f"wide task {i} was ruled out"
            agent.end_episode()
        assert agent.task_belief.candidates == [task], f"wide task {i} not identified after 3 episodes"
    assert max(candidates_at_start) > 1  # some tasks share their first observation: inference had work to do


def test_bayes_adaptive_posterior_moves_towards_the_worker(narrow: Suite, env: MewaEnv) -> None:
    agent = load("bayes-adaptive", env)
    task = narrow.tasks[0]
    for index in (0, 6, 10, 12):
        worker = np.array(narrow.pairs[index].worker.w)
        agent.reset_task()
        prior_distance = np.abs(agent.posterior_mean() - worker).sum()
        distances = []
        for k in range(EPISODES):
            play_episode(agent, env, 600 + 10 * index + k, {"task": task, "worker": list(worker)})
            distances.append(np.abs(agent.posterior_mean() - worker).sum())
        assert distances[-1] < prior_distance - 0.2, (index, prior_distance, distances)
        assert distances[-1] <= distances[0] + 0.05, (index, distances)


def test_bayes_adaptive_beats_random_task_specific(narrow: Suite, env: MewaEnv) -> None:
    agent = load("bayes-adaptive", env)
    pairs = [narrow.pairs[i] for i in (0, 1, 5, 7)]
    returns = pair_returns(shared(agent), env, narrow, pairs, units=2)
    rts = {index: value for index, value in baseline(narrow, "random_task_specific").items() if index in returns}
    assert deviation_in_se(returns, rts) > 3.0


def test_bayes_adaptive_is_deterministic(narrow: Suite, env: MewaEnv) -> None:
    task, worker = narrow.tasks[0], narrow.pairs[3].worker.w
    first = play_pair(load("bayes-adaptive", env, seed="1"), env, task, worker, seed=4, episodes=3)
    again = play_pair(load("bayes-adaptive", env, seed="1"), env, task, worker, seed=4, episodes=3)
    assert first == again


@pytest.mark.parametrize("name", ["random-task-specific", "bayes-adaptive"])
def test_an_unknown_task_falls_back_to_random_play(small_task: Task, name: str) -> None:
    env = MewaEnv(task=small_task, worker=(0.5, 0.3, 0.1))  # a task no shipped suite lists
    agent = load(name, env)
    agent.reset_task()
    _, actions = play_episode(agent, env, seed=0)
    assert agent.task_belief.candidates == []
    assert len(set(actions)) > 1
    other = load(name, env, seed="1")
    other.reset_task()
    assert play_episode(other, env, seed=0)[1] != actions  # random play: another agent seed, other actions
