"""The one-step rules and the transition table against the authors' reference traces."""

from __future__ import annotations

import numpy as np

from mewa_bench.game import Task, normalised_return, observation, outcomes, return_bounds, transition_table
from mewa_bench.game.rules import initial_state, state_from_observation


def replay_rules(trace: dict) -> None:
    """Replay a trace with `rules.outcomes` directly (w in {0, 1}: no randomness)."""
    task = Task.from_dict(trace["task"])
    w = trace["worker"]
    state = initial_state(task)
    for i, step in enumerate(trace["steps"]):
        out = outcomes(task, state, step["action"])
        state = out.mistake if out.mistake_type >= 0 and w[out.mistake_type] == 1 else out.ok
        where = f"{trace['kind']} worker {w} step {i}"
        np.testing.assert_array_equal(observation(task, state), np.float32(step["obs"]), err_msg=where)
        assert state[-1] == step["progress"], where


def test_rules_replay_every_reference_trace(traces: list[dict]) -> None:
    assert len(traces) == 132
    for trace in traces:
        replay_rules(trace)


def spec_step(task: Task, obs: np.ndarray, action: int, mistake: bool) -> tuple[np.ndarray, int, list[tuple]]:
    """SPEC section 2's step written out on the 18 observation floats, independently of `game.rules`.

    Returns the next observation, the mistake type x the step risks (-1: none) and the events as
    (kind, colour, value) in the order they happen; `mistake` decides rule 3's coin.
    """
    o = [int(v) for v in obs]
    agent, struct, flag, done = o[0:4], o[4:12:2], o[5:12:2], o[12:16]
    left, placed = o[16], o[17]
    progress = 0
    while progress < task.N and done[task.order[progress]]:
        progress += 1
    events, x = [], -1
    if action in task.colors and agent[action] > 0:  # rule 1 otherwise: nothing changes
        agent[action] -= 1  # rule 2
        struct[action] += 1
        if struct[action] == 2:  # rule 3
            x = sum(1 for c in range(4) if struct[c] >= 1) - 1
            if mistake:
                flag[action] = 1
                events.append(("mistake", action, x))
        if struct[action] == task.M:  # rule 4
            returned = flag[action] == 1
            struct[action], flag[action] = 0, 0
            if returned:
                agent[action] += task.M
                events.append(("structure_returned", action, task.M))
            else:
                done[action] = 1
                events.append(("structure_completed", action, 0))
                while progress < task.N and done[task.order[progress]]:
                    events.append(("subgoal_reached", task.order[progress], progress))
                    left, placed = left - task.worker_blocks[progress], placed + task.worker_blocks[progress]
                    progress += 1
    pairs = [v for c in range(4) for v in (struct[c], flag[c])]
    return np.float32(agent + pairs + done + [left, placed]), x, events


def test_table_agrees_with_an_independent_step_on_every_state(canonical_task: Task, small_task: Task) -> None:
    for task in (canonical_task, small_task):
        tab = transition_table(task)
        for s, state in enumerate(tab.states):
            np.testing.assert_array_equal(tab.obs[s], observation(task, state))
            assert state_from_observation(task, tab.obs[s]) == state
            if tab.terminal[s]:
                continue
            for a in range(4):
                ok_obs, x, ok_events = spec_step(task, tab.obs[s], a, mistake=False)
                np.testing.assert_array_equal(tab.obs[tab.next_ok[s, a]], ok_obs, err_msg=f"state {s} action {a}")
                assert tab.mistake_type[s, a] == x
                assert [tuple(e) for e in tab.event_sets[tab.events_ok[s, a]]] == ok_events
                out = outcomes(task, state, a)
                if x >= 0:
                    bad_obs, _, bad_events = spec_step(task, tab.obs[s], a, mistake=True)
                    np.testing.assert_array_equal(tab.obs[tab.next_mistake[s, a]], bad_obs)
                    assert [tuple(e) for e in tab.event_sets[tab.events_mistake[s, a]]] == bad_events
                    assert [tuple(e) for e in out.mistake_events] == bad_events
                else:
                    assert out.mistake is None and out.mistake_events == ()


def test_canonical_state_space_size(canonical_task: Task) -> None:
    # SPEC section 11: "about 4,000 reachable states for the canonical task".
    assert 3500 < transition_table(canonical_task).n_states < 4500


def test_unavailable_colour_is_a_no_op(small_task: Task) -> None:
    state = initial_state(small_task)
    out = outcomes(small_task, state, 1)  # blue is not in the task
    assert out.ok == state and out.mistake is None
    s = list(state)
    s[0] = 0  # no orange block left
    out = outcomes(small_task, tuple(s), 0)
    assert out.ok == tuple(s)


def test_mistake_type_counts_open_structures(canonical_task: Task) -> None:
    state = initial_state(canonical_task)
    for a in (0, 1, 2):  # open three structures with one block each
        state = outcomes(canonical_task, state, a).ok
    out = outcomes(canonical_task, state, 1)  # blue reaches 2 blocks with 3 structures open
    assert out.mistake_type == 2
    assert [e.kind for e in out.mistake_events] == ["mistake"]


def test_mistaken_structure_returns_blocks(canonical_task: Task) -> None:
    state = initial_state(canonical_task)
    state = outcomes(canonical_task, state, 3).ok
    state = outcomes(canonical_task, state, 3).mistake  # flagged
    out = outcomes(canonical_task, state, 3)
    assert out.ok[3] == canonical_task.K  # all red blocks back with the agent
    assert out.ok[4 + 3] == 0 and out.ok[8 + 3] == 0 and out.ok[12 + 3] == 0
    assert [e.kind for e in out.ok_events] == ["structure_returned"]


def test_normalised_return_bounds(canonical_task: Task) -> None:
    r_min, r_max = return_bounds(canonical_task)
    assert normalised_return(canonical_task, r_min) == 0.0
    assert normalised_return(canonical_task, r_max) == 1.0
    # The mistake-free episode in sub-goal order earns exactly R_max.
    tab = transition_table(canonical_task)
    s, total = 0, 0.0
    for c in canonical_task.order:
        for _ in range(canonical_task.M):
            s = tab.next_ok[s, c]
            total += tab.reward[s]
    assert tab.terminal[s]
    assert abs(total - r_max) < 1e-12
