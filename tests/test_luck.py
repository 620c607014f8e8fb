"""Coupled worker luck (protocol v2): the draws, the envs that use them, and replays on the same keys."""

from __future__ import annotations

import hashlib
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from scipy import stats

from conftest import DATA, REPO
from mewa_bench.design.exact import expected_returns
from mewa_bench.design.policies import PolicyAgent, policy_names
from mewa_bench.design.replay import replay_returns
from mewa_bench.envs.mewa_env import MewaEnv
from mewa_bench.game import luck
from mewa_bench.game.task import Task


def test_uniforms_are_uniform_and_independent_of_each_other() -> None:
    keys = np.random.default_rng(1).integers(0, luck.KEY_BOUND, size=20000, dtype=np.uint64)
    u = luck.uniforms(keys, 2, 3)
    assert ((u >= 0) & (u < 1)).all()
    assert stats.kstest(u, "uniform").pvalue > 1e-3
    v = luck.uniforms(keys, 2, 4)  # the next draw of the same colour, and another colour's draw
    w = luck.uniforms(keys, 1, 3)
    assert abs(stats.pearsonr(u, v)[0]) < 0.03 and abs(stats.pearsonr(u, w)[0]) < 0.03
    assert np.array_equal(u, luck.uniforms(keys, 2, 3))  # a pure function of (key, colour, j)


def test_episode_table_is_the_elementwise_uniforms() -> None:
    table = luck.episode_table(12345, 100)
    assert len(table) == 4 and len(table[0]) == luck.draws_per_color(100) == 50
    assert table[3][7] == luck.uniforms(12345, 3, 7)[0]


@pytest.mark.parametrize("bad", [-1, 2**63, 1.5, "3", True])
def test_bad_luck_keys_are_rejected(canonical_task: Task, bad: object) -> None:
    env = MewaEnv(task=canonical_task, worker=(0.5, 0.4, 0.3, 0.2))
    with pytest.raises(ValueError, match="luck_key"):
        env.reset(options={"luck_key": bad})


def _play(env: MewaEnv, actions: list[int], **options: object) -> list[tuple]:
    obs, _ = env.reset(options=options or None)
    out = [tuple(obs)]
    for a in actions:
        obs, r, term, trunc, info = env.step(a)
        out.append((tuple(obs), r, term, trunc, info["events"]))
        if term or trunc:
            break
    return out


def test_the_key_fixes_the_luck_and_the_draws_follow_the_rule(canonical_task: Task) -> None:
    worker = (0.5, 0.5, 0.5, 0.5)
    env = MewaEnv(task=canonical_task, worker=worker, events=True)
    actions = [int(a) for a in np.random.default_rng(3).integers(0, 4, size=100)]
    assert _play(env, actions, luck_key=77) == _play(env, actions, luck_key=77)
    # the rule, re-derived here: the j-th second block of colour c is a mistake iff u(key, c, j) < w[x]
    env.reset(options={"luck_key": 77})
    seen = {c: 0 for c in range(4)}
    structures = [0, 0, 0, 0]
    for a in actions:
        before = env.unwrapped._fast.states[env.unwrapped._s]
        structures = list(before[4:8])
        obs, _, term, trunc, info = env.step(a)
        if before[a] > 0 and structures[a] == 1:  # this block is structure a's second
            x = sum(1 for c in range(4) if structures[c] >= 1 or c == a) - 1
            expected = luck.uniforms(77, a, seen[a])[0] < worker[x]
            seen[a] += 1
            assert any(e.kind == "mistake" for e in info["events"]) == expected
        if term or trunc:
            break
    assert sum(seen.values()) > 5


def test_batched_and_scalar_envs_play_the_same_episodes_for_the_same_keys(canonical_task: Task) -> None:
    n, worker = 64, (0.55, 0.45, 0.3, 0.2)
    vec = gym.make_vec("mewa/MEWA-v0", num_envs=n, vectorization_mode="vector_entry_point",
                       task=canonical_task, worker=worker)
    obs, _ = vec.reset(seed=5)
    keys = vec.unwrapped.luck_keys
    rng = np.random.default_rng(0)
    steps: list[list] = [[tuple(o)] for o in obs]
    actions: list[list[int]] = [[] for _ in range(n)]
    done = np.zeros(n, dtype=bool)
    while not done.all():
        a = rng.integers(0, 4, size=n)
        obs, r, term, trunc, _ = vec.step(a)
        for i in np.flatnonzero(~done):
            actions[i].append(int(a[i]))
            steps[i].append((tuple(obs[i]), float(r[i]), bool(term[i]), bool(trunc[i])))
        done |= term | trunc
    env = MewaEnv(task=canonical_task, worker=worker, events=True)
    for i in range(n):
        scalar = _play(env, actions[i], luck_key=int(keys[i]))
        assert [scalar[0]] + [s[:4] for s in scalar[1:]] == steps[i], f"sub-env {i}"


def test_replays_equal_env_episodes_for_every_deterministic_policy(canonical_task: Task) -> None:
    worker = (0.6, 0.35, 0.3, 0.1)
    names = policy_names(4, baselines=False)
    keys = [int(k) for k in np.random.default_rng(9).integers(0, luck.KEY_BOUND, size=6, dtype=np.uint64)]
    replayed = replay_returns(canonical_task, names, worker, keys)
    env = MewaEnv(task=canonical_task, worker=worker)
    for p, name in enumerate(names):
        agent = PolicyAgent(name, canonical_task)
        for i, key in enumerate(keys):
            obs, _ = env.reset(options={"luck_key": key})
            agent.reset()
            total, done = 0.0, False
            while not done:
                obs, r, term, trunc, _ = env.step(agent.act_observation(obs))
                total, done = total + r, term or trunc
            assert total == pytest.approx(replayed[i, p], abs=1e-12), (name, key)


@pytest.mark.parametrize("worker", [(0.9, 0.6, 0.3, 0.1), (0.1, 0.2, 0.7, 0.9), (1.0, 1.0, 0.0, 0.0)])
def test_monte_carlo_over_keys_matches_the_exact_engine(canonical_task: Task, worker: tuple) -> None:
    """Coupled luck leaves every policy's distribution alone: sampled means match exact values."""
    names = policy_names(4)  # the t-optimal family and both random baselines
    keys = np.random.default_rng(11).integers(0, luck.KEY_BOUND, size=3000, dtype=np.uint64)
    sampled = replay_returns(canonical_task, names, worker, keys)
    exact = expected_returns(canonical_task, names, [worker], normalised=False)[:, 0]
    se = sampled.std(axis=0) / np.sqrt(len(keys))
    assert np.all(np.abs(sampled.mean(axis=0) - exact) <= 4.5 * se + 1e-9), np.abs(sampled.mean(0) - exact) / se


def test_env_monte_carlo_matches_the_exact_engine(canonical_task: Task) -> None:
    """The same check through MewaEnv seeded resets (the keys drawn by the env itself)."""
    worker = (0.7, 0.5, 0.3, 0.2)
    env = MewaEnv(task=canonical_task, worker=worker)
    agent = PolicyAgent("toptimal(rho1=2,rho2=1,q=1)", canonical_task)
    env.reset(seed=0)
    returns = []
    for _ in range(3000):
        obs, _ = env.reset()
        agent.reset()
        total, done = 0.0, False
        while not done:
            obs, r, term, trunc, _ = env.step(agent.act_observation(obs))
            total, done = total + r, term or trunc
        returns.append(total)
    exact = expected_returns(canonical_task, ["toptimal(rho1=2,rho2=1,q=1)"], [worker], normalised=False)[0, 0]
    assert abs(np.mean(returns) - exact) <= 4 * np.std(returns) / np.sqrt(len(returns))


def test_float_and_bool_actions_are_rejected_like_the_runner_does(canonical_task: Task) -> None:
    env = MewaEnv(task=canonical_task, worker=(0.5, 0.4, 0.3, 0.2))
    env.reset(seed=0)
    for bad in (2.0, True, np.float32(1.0), 4, -1):
        with pytest.raises(ValueError, match="invalid action"):
            env.step(bad)
    env.step(np.int64(3))
    env.step(np.array(1))


def test_shipped_reference_traces_are_the_shared_ones() -> None:
    shared = REPO.parent / "shared" / "reference" / "traces-canonical.json"
    if not shared.exists():
        pytest.skip("no shared/ beside the checkout: the shipped copy is the reference")
    digest = lambda p: hashlib.sha256(Path(p).read_bytes()).hexdigest()  # noqa: E731
    assert digest(DATA / "traces-canonical.json") == digest(shared)


def test_the_scalar_draw_is_the_vectorised_one() -> None:
    rng = np.random.default_rng(4)
    keys = rng.integers(0, luck.KEY_BOUND, size=500, dtype=np.uint64)
    colours, j = rng.integers(0, 4, size=500), rng.integers(0, 50, size=500)
    vectorised = luck.uniforms(keys, colours, j)
    assert [luck.uniform(int(k), int(c), int(i)) for k, c, i in zip(keys, colours, j)] == vectorised.tolist()
