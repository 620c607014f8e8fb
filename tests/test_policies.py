"""Baseline policies: the t-optimal family against the authors' traces, and the random baselines."""

from __future__ import annotations

import numpy as np
import pytest

from mewa_bench.design.policies import (CRITICAL_1, CRITICAL_2, NOT_CRITICAL, PolicyAgent, RandomTaskSpecific,
                                        TOptimal, UniformRandom, critical_kind, policy_from_name, policy_names,
                                        toptimal_family)
from mewa_bench.game import Task, observation, transition_table
from mewa_bench.game.rules import AGENT, DONE, PROGRESS, STRUCT, initial_state


def _state(task: Task, structures: dict[int, int], completed: tuple[int, ...] = (),
           agent: dict[int, int] | None = None) -> tuple[int, ...]:
    """A hand-made game state: structure sizes, completed colours (a prefix of the order), agent blocks."""
    s = list(initial_state(task))
    for c, n in structures.items():
        s[STRUCT + c] = n
        s[AGENT + c] -= n
    for c in completed:
        s[DONE + c] = 1
        s[AGENT + c] -= task.M
    for c, n in (agent or {}).items():
        s[AGENT + c] = n
    s[PROGRESS] = len(completed)
    assert tuple(task.order[: len(completed)]) == tuple(completed)
    return tuple(s)


def _replay(task: Task, agent: PolicyAgent, worker: list[int], n_steps: int) -> list[int]:
    """Actions of `agent` for n_steps through the table, with a deterministic worker (w in {0, 1})."""
    table = transition_table(task)
    agent.reset()
    s, actions = 0, []
    for _ in range(n_steps):
        a = agent.act(table.states[s])
        actions.append(a)
        x = table.mistake_type[s, a]
        s = table.next_mistake[s, a] if x >= 0 and worker[x] == 1 else table.next_ok[s, a]
        if table.terminal[s]:
            break
    return actions


def test_family_sizes_and_trace_order(traces: list[dict]) -> None:
    assert len(toptimal_family(4)) == 19 and len(toptimal_family(3)) == 11 and len(toptimal_family(2)) == 5
    in_traces = list(dict.fromkeys(t["kind"] for t in traces if t["kind"].startswith("toptimal")))
    assert in_traces == list(policy_names(4, baselines=False))
    assert policy_names(3)[-2:] == ("random-task-specific", "random")


def test_names_round_trip_and_reject_outsiders() -> None:
    for name in policy_names(4):
        assert policy_from_name(name).name == name
    assert policy_from_name("toptimal(rho1=2, rho2=1, q=1)") == TOptimal(2, 1, 1)
    for bad in ("toptimal(rho1=1,rho2=2,q=0)", "toptimal(rho1=0,rho2=0,q=1)", "greedy", "toptimal(rho1=1,rho2=0,q=2)"):
        with pytest.raises(ValueError):
            policy_from_name(bad)


def test_every_toptimal_trace_is_reproduced(traces: list[dict]) -> None:
    checked = 0
    for trace in traces:
        if not trace["kind"].startswith("toptimal"):
            continue
        task = Task.from_dict(trace["task"])
        actions = _replay(task, PolicyAgent(trace["kind"], task), trace["worker"], len(trace["steps"]))
        assert actions == trace["actions"], (trace["kind"], trace["worker"])
        checked += 1
    assert checked == 114


def test_agent_acts_the_same_on_observations(canonical_task: Task) -> None:
    table = transition_table(canonical_task)
    by_state, by_obs = PolicyAgent(TOptimal(3, 2, 1), canonical_task), PolicyAgent(TOptimal(3, 2, 1), canonical_task)
    for s in range(0, table.n_states, 7):
        if table.terminal[s]:
            continue
        by_state.reset()
        by_obs.reset()
        state = table.states[s]
        assert by_state.act(state) == by_obs.act_observation(observation(canonical_task, state))


def test_critical_states(canonical_task: Task) -> None:
    task = canonical_task  # order (3, 1, 2, 0)
    assert critical_kind(task, _state(task, {})) == NOT_CRITICAL
    assert critical_kind(task, _state(task, {3: 1})) == CRITICAL_1
    assert critical_kind(task, _state(task, {3: 2})) == NOT_CRITICAL
    assert critical_kind(task, _state(task, {3: 2, 2: 1})) == CRITICAL_2
    assert critical_kind(task, _state(task, {3: 2, 2: 2})) == NOT_CRITICAL
    # Leftover structures of completed colours never make a critical state 2.
    assert critical_kind(task, _state(task, {1: 2, 3: 1}, completed=(3,), agent={3: 1})) == NOT_CRITICAL


def test_safe_action_preference(canonical_task: Task) -> None:
    task = canonical_task
    # Later sub-goals in sub-goal order: 1 before 2 before 0.
    assert TOptimal(3, 0, 0).choices(task, _state(task, {3: 1}), (0, 0))[0].action == 1
    assert TOptimal(3, 0, 0).choices(task, _state(task, {3: 1, 1: 1}), (1, 0))[0].action == 2
    # Counter exhausted: risky.
    assert TOptimal(1, 0, 1).choices(task, _state(task, {3: 1}), (1, 0))[0].action == 3
    # Deadline 0 (last): no later colour; q = 1 uses leftovers of completed colours in sub-goal order.
    last = _state(task, {0: 1}, completed=(3, 1, 2))
    assert TOptimal(1, 0, 0).choices(task, last, (0, 0))[0].action == 0
    assert TOptimal(1, 0, 1).choices(task, last, (0, 0))[0].action == 3
    no_leftover = _state(task, {0: 1}, completed=(3, 1, 2), agent={3: 0})
    assert TOptimal(1, 0, 1).choices(task, no_leftover, (0, 0))[0].action == 1


def test_counters_run_across_a_completed_deadline(canonical_task: Task) -> None:
    policy = TOptimal(2, 1, 0)
    task = canonical_task
    c2 = _state(task, {3: 2, 1: 1, 2: 1})
    first = policy.choices(task, c2, (0, 0))[0]
    assert first.action == 1 and first.memory == (0, 1)  # postpone, counting the run
    # The deadline completed and the next one is critical 2 at once: the run goes on, so complete.
    after = _state(task, {1: 2, 2: 1}, completed=(3,))
    assert policy.choices(task, after, (0, 1))[0].action == 1
    assert policy.choices(task, after, (0, 0))[0].action == 2


def test_random_task_specific_distribution(canonical_task: Task) -> None:
    task, policy = canonical_task, RandomTaskSpecific()
    dist = {c.action: c.prob for c in policy.choices(task, _state(task, {3: 1}), ())}
    assert dist == {1: 0.5, 3: 0.5}
    last = _state(task, {0: 1}, completed=(3, 1, 2))
    assert {c.action: c.prob for c in policy.choices(task, last, ())} == {3: 0.25, 0: 0.75}
    assert {c.action: c.prob for c in policy.choices(task, _state(task, {3: 2, 2: 1}), ())} == {2: 0.5, 3: 0.5}
    assert {c.action: c.prob for c in policy.choices(task, _state(task, {}), ())} == {3: 1.0}


def test_random_agents_sample_their_distribution(canonical_task: Task) -> None:
    with pytest.raises(ValueError):
        PolicyAgent("random", canonical_task)
    rng = np.random.default_rng(7)
    agent = PolicyAgent("random-task-specific", canonical_task, rng)
    last = _state(canonical_task, {0: 1}, completed=(3, 1, 2))
    picks = np.array([agent.act(last) for _ in range(8000)])
    assert abs((picks == 3).mean() - 0.25) < 4 * np.sqrt(0.25 * 0.75 / 8000)
    n3 = Task(colors=(0, 2, 3), order=(2, 0, 3), K=4, M=4, rewards=(-1.0, -0.5, -0.2), worker_blocks=(3, 5, 0))
    uniform = PolicyAgent(UniformRandom(), n3, rng)
    counts = np.bincount([uniform.act(initial_state(n3)) for _ in range(8000)], minlength=4)
    assert np.all(np.abs(counts / 8000 - 0.25) < 4 * np.sqrt(0.25 * 0.75 / 8000))
