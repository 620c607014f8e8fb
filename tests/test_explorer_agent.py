"""The bayes-explorer reference agent: public knowledge only, deterministic, a sound posterior, adapts on v2."""

from __future__ import annotations

import importlib.util
import inspect
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from mewa_bench.design.suites import load_suite
from mewa_bench.envs.mewa_env import MewaEnv
from mewa_bench.protocol.agent import Transition
from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.runner import evaluate

AGENT_PATH = Path(__file__).resolve().parents[1] / "submissions" / "bayes-explorer" / "agent.py"


def load_module() -> ModuleType:
    """The agent file as a module."""
    spec = importlib.util.spec_from_file_location("_bayes_explorer_under_test", AGENT_PATH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the file runs
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def explorer() -> ModuleType:
    """The agent module, loaded once for the file."""
    return load_module()


@pytest.fixture(scope="module")
def canonical_v2(explorer: ModuleType):
    """The canonical task's model, with both worker families in its prior (listed by narrow-v1 and narrow-v2)."""
    agent = explorer.BayesExplorerAgent()
    task = load_suite("narrow-v2").tasks[0]
    return agent, agent.model(task)


def play_actions(agent, suite: str, pair: int, unit_seed: int, episodes: int) -> list[int]:
    """The agent's actions over `episodes` episodes of one pair (env seeds fixed per episode)."""
    s = load_suite(suite)
    task = s.tasks[s.pairs[pair].task_index]
    env = MewaEnv(task=task, worker=s.pairs[pair].worker.w)
    agent.reset_task(seed=unit_seed)
    actions = []
    for episode in range(episodes):
        obs, _ = env.reset(seed=100 + episode)
        done = False
        while not done:
            action = agent.act(obs)
            next_obs, reward, terminated, truncated, _ = env.step(action)
            agent.observe(Transition(obs, action, reward, next_obs, terminated, truncated))
            actions.append(action)
            obs, done = next_obs, terminated or truncated
        agent.end_episode()
    return actions


def test_the_agent_is_not_privileged(explorer: ModuleType) -> None:
    """It declares itself unprivileged and its reset_task cannot take the hidden pair."""
    assert explorer.PRIVILEGED is False
    parameters = inspect.signature(explorer.BayesExplorerAgent.reset_task).parameters
    assert list(parameters) == ["self", "seed"]


def test_play_is_deterministic_given_the_seeds(explorer: ModuleType) -> None:
    """Two agents with the same agent seed and unit seed act identically on the same episodes."""
    first = play_actions(explorer.BayesExplorerAgent(seed=3), "narrow-v2", 2, unit_seed=11, episodes=3)
    second = play_actions(explorer.BayesExplorerAgent(seed=3), "narrow-v2", 2, unit_seed=11, episodes=3)
    assert first == second


def test_posterior_mean_approaches_the_observed_rate(canonical_v2) -> None:
    """After 300 trials of type 3 with 210 mistakes, the posterior mean of w_3 is near 0.7."""
    _, model = canonical_v2
    mistakes, successes = np.array([0.0, 0.0, 0.0, 210.0]), np.array([0.0, 0.0, 0.0, 90.0])
    post = np.exp(model.log_posterior(mistakes, successes) - model.log_posterior(mistakes, successes).max())
    mean = (post / post.sum()) @ model.grid
    assert abs(mean[3] - 0.7) < 0.03


def test_prior_is_a_distribution_over_both_families(explorer: ModuleType, canonical_v2) -> None:
    """The prior sums to 1 and gives each strict family (paper, overloaded) a sizeable share."""
    _, model = canonical_v2
    prior = explorer.posterior_of(model.log_prior)
    steps = np.diff(model.grid, axis=1)
    paper = (steps <= 0).all(axis=1) & (steps < 0).any(axis=1)
    overloaded = (steps >= 0).all(axis=1) & (steps > 0).any(axis=1)
    assert abs(prior.sum() - 1.0) < 1e-9
    assert prior[paper].sum() > 0.4 and prior[overloaded].sum() > 0.15


def test_v1_only_rules_keep_the_paper_family(explorer: ModuleType) -> None:
    """A task whose rules only v1 lists gets a grid of non-increasing workers only."""
    agent = explorer.BayesExplorerAgent()
    v2_keys = {t.key() for name in ("narrow-v2", "wide-v2") for t in load_suite(name).tasks}
    task = next(t for t in load_suite("wide-v1").tasks if t.key() not in v2_keys)
    grid = agent.model(task).grid
    assert (np.diff(grid, axis=1) <= 0).all()


def test_greedy_evidence_makes_greedy_building_the_choice(explorer: ModuleType, canonical_v2) -> None:
    """Perfect work with one structure open and failures with two: rho1 = 0, now and under exploration."""
    agent, model = canonical_v2
    mistakes, successes = np.array([0.0, 8.0, 0.0, 0.0]), np.array([12.0, 0.0, 0.0, 0.0])
    log_post = model.log_posterior(mistakes, successes)
    for remaining in (1, 5, 10):
        choice = explorer.choose(model, log_post, remaining, agent.settings, np.random.default_rng(0))
        assert model.policies[choice].rho1 == 0


def test_paper_evidence_makes_parallel_building_the_choice(explorer: ModuleType, canonical_v2) -> None:
    """Failures with one or two structures open and perfect work with four: a policy that opens all four."""
    agent, model = canonical_v2
    mistakes, successes = np.array([6.0, 6.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 12.0])
    choice = explorer.choose(model, model.log_posterior(mistakes, successes), 1, agent.settings,
                             np.random.default_rng(0))
    assert model.policies[choice].rho1 == 3


def test_short_evaluation_adapts_on_an_overloaded_worker(tmp_path: Path) -> None:
    """On narrow-v2 pair 7, w = (0, 1, 1, 1), the prior's choice builds in parallel; episode 10 beats episode 1."""
    config = EvalConfig(agent_path=AGENT_PATH, suite="narrow-v2", pairs=(7,), seeds=(0, 1, 2), isolated=False,
                        out=tmp_path / "r.json")
    results, _ = evaluate(config)
    scores = np.array([unit["scores"] for unit in results["units"]])
    assert scores.shape == (3, 10)
    assert scores[:, -1].mean() > scores[:, 0].mean() + 0.2
    assert scores[:, -1].mean() > 0.95


def test_step_plan_follows_the_known_worker_optimum_of_a_planning_worker(explorer: ModuleType) -> None:
    """With much evidence on every mistake type, a later episode follows a step-level plan when one beats
    the t-optimal family under the posterior: its actions are the known-worker optimum of the planning
    worker of the chosen quantile, which sits within a level of the truth, and the 0.9 planning worker
    is at or above the posterior mean for every type (pessimism); the episode-1 choice stays t-optimal."""
    from mewa_bench.design.exact import structural_task
    from mewa_bench.design.optimum import optimal_actions
    from mewa_bench.game.rules import state_from_observation
    from mewa_bench.game.table import transition_table

    suite = load_suite("wide-v1")
    pair = suite.pairs[1]
    task, worker = suite.tasks[pair.task_index], np.array(pair.worker.w)  # (1, 1, 0, 0)
    agent = explorer.BayesExplorerAgent(suite="wide-v1")
    env = MewaEnv(task=task, worker=worker)
    obs, _ = env.reset(seed=3)
    agent.act(obs)
    assert not agent.planned_episode  # the first episode never follows the plan (plan_from = 1)

    agent.reset_task(seed=0)
    agent.mistakes = np.round(40 * worker)
    agent.successes = 40 - agent.mistakes
    agent.episodes_done = 1
    action = agent.act(obs)
    rounding = agent.settings.plan_quantum / 2
    assert np.all(agent.planning_worker(task, 0.9) >= agent.posterior_mean() - rounding)
    assert agent.planned_episode  # this worker is one where a plan pays
    planning = agent.planning_worker(task, agent.episode_quantile)
    assert np.all(np.abs(planning - worker) <= 0.1)
    support, weight = agent.likely_workers(task)
    assert agent.plan_scores(task, agent.episode_quantile, support) @ weight > (agent.model(task).values[:, support] @ weight).max()
    state = transition_table(structural_task(task)).index[state_from_observation(task, obs)]
    assert action == optimal_actions(task, planning)[task.T, state]


def test_the_plan_is_played_only_when_it_wins_under_the_posterior(explorer: ModuleType) -> None:
    """After one episode of w_3 mistakes (19 of 20) the planning worker is (1, 1, 0.95, 0.95); its plan beats
    the t-optimal family there by 0.018 but scores 0 when w_2 = 1 (as on narrow-v1's (1, 1, 1, 0.95) pair):
    the posterior check keeps the t-optimal policy; without the check the episode follows the plan."""
    from mewa_bench.design.optimum import optimal_actions, plan_returns

    task = load_suite("narrow-v1").tasks[0]
    obs, _ = MewaEnv(task=task, worker=[1.0, 1.0, 1.0, 0.95]).reset(seed=3)

    def after_one_episode(**knobs: str) -> object:
        agent = explorer.BayesExplorerAgent(suite="narrow-v1", **knobs)
        agent.reset_task(seed=0)
        agent.mistakes, agent.successes = np.array([0.0, 0, 0, 19]), np.array([0.0, 0, 0, 1])
        agent.episodes_done = 1
        agent.act(obs)
        return agent

    checked, unchecked = after_one_episode(plan_quantiles="0.9"), after_one_episode(plan_quantiles="0.9", plan_check="0")
    assert tuple(checked.planning_worker(task, 0.9)) == (1.0, 1.0, 0.95, 0.95)
    assert checked.step_plan(task, 0.9)[1] >= checked.settings.plan_margin
    assert unchecked.planned_episode and not checked.planned_episode
    assert plan_returns(task, optimal_actions(task, [1.0, 1.0, 0.95, 0.95]), [[1.0, 1.0, 1.0, 0.95]])[0] == 0.0
    model = checked.model(task)
    support = np.array([int(np.flatnonzero((model.grid == w).all(axis=1))[0])
                        for w in ([1.0, 1.0, 1.0, 0.95], [1.0, 1.0, 0.95, 0.95])])
    expected = plan_returns(task, optimal_actions(task, [1.0, 1.0, 0.95, 0.95]), model.grid[support]) / model.denominator[support]
    assert checked.plan_scores(task, 0.9, support) == pytest.approx(expected, abs=1e-12)
    assert checked.plan_scores(task, 0.9, support)[1] > model.values[:, support[1]].max()  # the plan's own worker: it wins
