"""Exact engine and known-worker optimum: against traces, Monte Carlo and plain references."""

from __future__ import annotations

from collections import defaultdict
from functools import lru_cache

import numpy as np
import pytest

from mewa_bench.design.exact import expected_returns, plan_for
from mewa_bench.design.optimum import known_worker_optimum, optimal_actions, plan_returns
from mewa_bench.design.policies import Policy, PolicyAgent, policy_from_name, policy_names
from mewa_bench.game import Task, normalised_return, transition_table

CANONICAL = Task(colors=(0, 1, 2, 3), order=(3, 1, 2, 0), K=5, M=3, rewards=(-0.4, -0.3, -0.2, -0.1),
                 worker_blocks=(2, 2, 4, 0), name="canonical")
N3 = Task(colors=(0, 2, 3), order=(2, 0, 3), K=4, M=3, rewards=(-1.0, -0.45, -0.2), worker_blocks=(3, 5, 0), name="n3")
M5 = Task(colors=(0, 1, 2, 3), order=(1, 3, 0, 2), K=5, M=5, rewards=(-0.9, -0.6, -0.5, -0.15),
          worker_blocks=(1, 3, 4, 0), name="m5k5")
M2 = Task(colors=(1, 2, 3), order=(3, 1, 2), K=4, M=2, rewards=(-0.5, -0.3, -0.1), worker_blocks=(4, 4, 0), T=40)


def _worker(task: Task, *values: float) -> np.ndarray:
    return np.array(values[: task.N], dtype=np.float64)


def _monte_carlo(task: Task, policy: str, worker: np.ndarray, episodes: int, seed: int) -> np.ndarray:
    """Normalised returns of episodes played by a PolicyAgent through the transition table."""
    table = transition_table(task)
    rng = np.random.default_rng(seed)
    agent = PolicyAgent(policy, task, rng)
    out = np.empty(episodes)
    for e in range(episodes):
        agent.reset()
        s, total = 0, 0.0
        for _ in range(task.T):
            a = agent.act(table.states[s])
            x = table.mistake_type[s, a]
            s = table.next_mistake[s, a] if x >= 0 and rng.random() < worker[x] else table.next_ok[s, a]
            total += table.reward[s]
            if table.terminal[s]:
                break
        out[e] = normalised_return(task, total)
    return out


def _forward(task: Task, policy: Policy, worker: np.ndarray) -> float:
    """Reference: propagate the distribution over (state, memory) step by step, no reductions."""
    table = transition_table(task)
    dist: dict[tuple, float] = {(0, policy.initial_memory()): 1.0}
    total = 0.0
    for _ in range(task.T):
        following: dict[tuple, float] = defaultdict(float)
        for (s, memory), p in dist.items():
            for prob, a, next_memory in policy.choices(task, table.states[s], memory):
                x = table.mistake_type[s, a]
                outs = ((table.next_ok[s, a], 1.0),) if x < 0 else (
                    (table.next_ok[s, a], 1.0 - worker[x]), (table.next_mistake[s, a], worker[x]))
                for s2, q in outs:
                    total += p * prob * q * table.reward[s2]
                    if not table.terminal[s2]:
                        following[(s2, next_memory)] += p * prob * q
        dist = following
    return normalised_return(task, total)


def test_deterministic_workers_match_trace_returns(traces: list[dict]) -> None:
    task = Task.from_dict(traces[0]["task"])
    names = list(policy_names(4, baselines=False))
    workers = sorted({tuple(t["worker"]) for t in traces})
    values = expected_returns(task, names, np.array(workers, dtype=np.float64))
    assert values.shape == (19, len(workers))
    checked = 0
    for trace in traces:
        if trace["kind"] in names:
            expected = normalised_return(task, sum(step["reward"] for step in trace["steps"]))
            got = values[names.index(trace["kind"]), workers.index(tuple(trace["worker"]))]
            assert got == pytest.approx(expected, abs=1e-12), (trace["kind"], trace["worker"])
            checked += 1
    assert checked == 114


@pytest.mark.parametrize("task", [CANONICAL, N3, M5, M2], ids=lambda t: t.name or "m2")
def test_engine_equals_forward_reference(task: Task) -> None:
    workers = np.array([[0.83, 0.61, 0.27, 0.09], [0.35, 0.35, 0.2, 0.0], [1.0, 0.5, 0.5, 0.5]])[:, : task.N]
    names = policy_names(task.N)
    values = expected_returns(task, names, workers)
    for p, name in enumerate(names):
        for w in range(len(workers)) if name != "random" else (0,):
            reference = _forward(task, policy_from_name(name), workers[w])
            assert values[p, w] == pytest.approx(reference, abs=1e-12), (name, w)


CASES = [
    (CANONICAL, "toptimal(rho1=0,rho2=0,q=0)", (0.55, 0.3, 0.15, 0.05)),
    (CANONICAL, "toptimal(rho1=2,rho2=1,q=0)", (0.72, 0.41, 0.33, 0.08)),
    (CANONICAL, "toptimal(rho1=3,rho2=2,q=1)", (0.95, 0.6, 0.6, 0.25)),
    (CANONICAL, "toptimal(rho1=1,rho2=1,q=1)", (0.4, 0.4, 0.05, 0.05)),
    (CANONICAL, "random-task-specific", (0.65, 0.45, 0.25, 0.1)),
    (CANONICAL, "random", (0.3, 0.2, 0.1, 0.0)),
    (N3, "toptimal(rho1=2,rho2=1,q=1)", (0.7, 0.4, 0.2)),
    (N3, "toptimal(rho1=1,rho2=0,q=0)", (0.5, 0.35, 0.123)),
    (N3, "random-task-specific", (0.9, 0.5, 0.3)),
    (N3, "random", (0.6, 0.3, 0.1)),
    (M5, "toptimal(rho1=3,rho2=3,q=1)", (0.45, 0.3, 0.2, 0.1)),
    (M5, "toptimal(rho1=2,rho2=0,q=0)", (0.25, 0.2, 0.15, 0.05)),
    (M5, "random-task-specific", (0.3, 0.15, 0.1, 0.05)),
]


@pytest.mark.parametrize("task, policy, worker", CASES, ids=[f"{t.name}-{p}" for t, p, _ in CASES])
def test_exact_agrees_with_monte_carlo(task: Task, policy: str, worker: tuple[float, ...]) -> None:
    w = np.array(worker)
    exact = expected_returns(task, [policy], w)[0, 0]
    sample = _monte_carlo(task, policy, w, episodes=1500, seed=1000 + CASES.index((task, policy, worker)))
    standard_error = sample.std(ddof=1) / np.sqrt(len(sample))
    assert abs(sample.mean() - exact) <= 3 * standard_error + 1e-12, (sample.mean(), exact, standard_error)


def test_reward_independent_plan_is_reused_with_other_rewards() -> None:
    other = CANONICAL.with_rewards((-1.0, -0.7, -0.33, -0.02))
    assert plan_for(other, policy_names(4)) is plan_for(CANONICAL, policy_names(4))
    w = np.array([0.6, 0.4, 0.3, 0.1])
    for name in ("toptimal(rho1=3,rho2=1,q=1)", "random-task-specific"):
        reference = _forward(other, policy_from_name(name), w)
        assert expected_returns(other, [name], w)[0, 0] == pytest.approx(reference, abs=1e-12)


def test_shapes_bounds_and_raw_scale() -> None:
    rng = np.random.default_rng(3)
    workers = rng.random((37, 4))
    values = expected_returns(CANONICAL, None, workers, chunk=16)
    assert values.shape == (19, 37) and np.all(values >= -1e-12) and np.all(values <= 1 + 1e-12)
    single = expected_returns(CANONICAL, None, workers[5])
    np.testing.assert_array_equal(single[:, 0], values[:, 5])  # no dependence on the batching, to the bit
    raw = expected_returns(CANONICAL, None, workers[:3], normalised=False)
    assert np.all(raw < 0) and np.all(raw >= CANONICAL.T * CANONICAL.rewards[0] - 1e-9)
    with pytest.raises(ValueError):
        expected_returns(CANONICAL, None, workers[:, :3])
    with pytest.raises(ValueError):
        expected_returns(CANONICAL, None, workers + 1.0)


@pytest.mark.parametrize("task", [CANONICAL, N3, M5], ids=lambda t: t.name)
def test_optimum_dominates_every_policy(task: Task) -> None:
    rng = np.random.default_rng(11)
    workers = np.vstack([np.sort(rng.random((12, task.N)), axis=1)[:, ::-1], rng.random((4, task.N)),
                         np.zeros(task.N), np.ones(task.N)])
    best = known_worker_optimum(task, workers)
    policies = expected_returns(task, policy_names(task.N), workers)
    assert np.all(best >= policies.max(axis=0) - 1e-12)
    assert best[-2] == pytest.approx(1.0, abs=1e-12)  # w = 0: the perfect episode
    assert best[-1] == pytest.approx(0.0, abs=1e-12)  # w = 1: nothing is ever completed


def test_optimum_beats_the_family_somewhere() -> None:
    workers = np.array([[0.8, 0.55, 0.35, 0.15], [0.6, 0.5, 0.4, 0.3], [0.9, 0.7, 0.5, 0.3], [0.5, 0.2, 0.1, 0.0]])
    gap = known_worker_optimum(CANONICAL, workers) - expected_returns(CANONICAL, None, workers).max(axis=0)
    assert gap.max() > 1e-3


def test_optimum_equals_plain_recursion_on_a_short_horizon() -> None:
    task = Task(colors=(0, 2, 3), order=(2, 0, 3), K=4, M=3, rewards=(-1.0, -0.45, -0.2), worker_blocks=(3, 5, 0), T=14)
    table = transition_table(task)
    w = np.array([0.7, 0.35, 0.1])

    @lru_cache(maxsize=None)
    def value(s: int, t: int) -> float:
        if t == 0 or table.terminal[s]:
            return 0.0
        best = -np.inf
        for a in range(4):
            x = table.mistake_type[s, a]
            ok, bad = int(table.next_ok[s, a]), int(table.next_mistake[s, a])
            q_ok = table.reward[ok] + value(ok, t - 1)
            q = q_ok if x < 0 else (1 - w[x]) * q_ok + w[x] * (table.reward[bad] + value(bad, t - 1))
            best = max(best, q)
        return best

    assert known_worker_optimum(task, w, normalised=False)[0] == pytest.approx(value(0, task.T), abs=1e-12)


def test_optimal_actions_achieve_the_optimum_exactly_and_by_monte_carlo() -> None:
    """Following optimal_actions (by steps left and state) earns the known-worker optimum."""
    task = Task(colors=(0, 2, 3), order=(2, 0, 3), K=4, M=3, rewards=(-1.0, -0.45, -0.2), worker_blocks=(3, 5, 0), T=14)
    table = transition_table(task)
    w = np.array([0.7, 0.35, 0.1])
    plan = optimal_actions(task, w)

    @lru_cache(maxsize=None)
    def value(s: int, t: int) -> float:  # the plan's own value, a fixed action per (state, steps left)
        if t == 0 or table.terminal[s]:
            return 0.0
        a = int(plan[t, s])
        x = table.mistake_type[s, a]
        ok, bad = int(table.next_ok[s, a]), int(table.next_mistake[s, a])
        q_ok = table.reward[ok] + value(ok, t - 1)
        return q_ok if x < 0 else (1 - w[x]) * q_ok + w[x] * (table.reward[bad] + value(bad, t - 1))

    assert value(0, task.T) == pytest.approx(known_worker_optimum(task, w, normalised=False)[0], abs=1e-12)

    worker = np.array([0.9, 0.6, 0.3, 0.2])  # the canonical task, full horizon: sampled episodes
    plan, table, rng = optimal_actions(CANONICAL, worker), transition_table(CANONICAL), np.random.default_rng(5)
    returns = np.zeros(4000)
    for e in range(len(returns)):
        s = 0
        for left in range(CANONICAL.T, 0, -1):
            a = plan[left, s]
            x = table.mistake_type[s, a]
            s = table.next_mistake[s, a] if x >= 0 and rng.random() < worker[x] else table.next_ok[s, a]
            returns[e] += table.reward[s]
            if table.terminal[s]:
                break
    exact = known_worker_optimum(CANONICAL, worker, normalised=False)[0]
    assert abs(returns.mean() - exact) < 4 * returns.std() / np.sqrt(len(returns))
    best_family = expected_returns(CANONICAL, None, worker[None, :], normalised=False).max()
    assert exact > best_family + 1e-3  # a worker where the step-level plan beats every t-optimal policy


def test_plan_returns_value_a_plan_for_other_workers_by_plain_recursion() -> None:
    """plan_returns: a plan made for one worker, followed by others, against the plain recursion."""
    task = Task(colors=(0, 2, 3), order=(2, 0, 3), K=4, M=3, rewards=(-1.0, -0.45, -0.2), worker_blocks=(3, 5, 0), T=14)
    table = transition_table(task)
    plan = optimal_actions(task, [0.7, 0.35, 0.1])
    workers = np.array([[0.7, 0.35, 0.1], [0.2, 0.9, 0.5], [1.0, 0.0, 1.0]])

    def recursion(w: np.ndarray) -> float:
        @lru_cache(maxsize=None)
        def value(s: int, t: int) -> float:
            if t == 0 or table.terminal[s]:
                return 0.0
            a = int(plan[t, s])
            x = table.mistake_type[s, a]
            ok, bad = int(table.next_ok[s, a]), int(table.next_mistake[s, a])
            q_ok = table.reward[ok] + value(ok, t - 1)
            return q_ok if x < 0 else (1 - w[x]) * q_ok + w[x] * (table.reward[bad] + value(bad, t - 1))
        return value(0, task.T)

    raw = plan_returns(task, plan, workers, normalised=False, chunk=2)
    assert raw == pytest.approx([recursion(w) for w in workers], abs=1e-12)
    assert raw[0] == pytest.approx(known_worker_optimum(task, workers[:1], normalised=False)[0], abs=1e-12)
    assert raw[1] < known_worker_optimum(task, workers[1:2], normalised=False)[0] - 1e-6  # made for another worker
    with pytest.raises(ValueError, match="steps left, states"):
        plan_returns(task, plan[:-1], workers)
