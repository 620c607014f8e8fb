"""The batched envs in Gymnasium's three autoreset modes, per-lane seeds, and against SyncVectorEnv."""

from __future__ import annotations

import hashlib
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import mewa_bench  # noqa: F401 - registers the env ids
from mewa_bench.envs import MetaEpisodeVectorEnv, MewaEnv, MewaVectorEnv

# sha256 of 3000 NEXT_STEP steps (observations, rewards, flags and infos) of 16 lanes, computed from the
# code before the autoreset modes existed: the default mode must keep these bytes.
NEXT_STEP_DIGESTS = {
    ("mewa/MEWA-v0", ()): "a95b44781470ad77bd0db0dbebdc414dd99f8a63525017049b060f098a9a6404",
    ("mewa/MEWA-Meta-v0", (("episodes", 3),)): "4f75da280020ccbdf9aa9d5225237bea2e27503e7d45db99c3c084b40380613b",
}


def feed(h: Any, value: Any) -> None:
    """Hash a step's output: dicts by sorted key, everything else as a numpy array (dtype and bytes)."""
    if isinstance(value, dict):
        for key in sorted(value):
            h.update(key.encode())
            feed(h, value[key])
    else:
        a = np.asarray(value)
        h.update(a.dtype.str.encode())
        h.update(a.tobytes())


def run_digest(env_id: str, steps: int = 3000, **kwargs: Any) -> str:
    """sha256 over a seeded random-action run of 16 lanes."""
    env = gym.make_vec(env_id, num_envs=16, **kwargs)
    h = hashlib.sha256()
    obs, info = env.reset(seed=7)
    feed(h, obs)
    feed(h, info)
    rng = np.random.default_rng(11)
    for _ in range(steps):
        for part in env.step(rng.integers(0, 4, size=16)):
            feed(h, part)
    return h.hexdigest()


def test_next_step_keeps_its_bytes() -> None:
    for (env_id, kwargs), expected in NEXT_STEP_DIGESTS.items():
        assert run_digest(env_id, **dict(kwargs)) == expected, env_id


MODES = (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED)
IDS = (("mewa/MEWA-v0", {}), ("mewa/MEWA-Meta-v0", {"episodes": 3}))


def entries(infos: dict[str, Any], n: int, prefix: str = "") -> dict[tuple[str, int], tuple[Any, bool]]:
    """Vector infos as {(key, lane): (value, masked)}: a lane has a key where its `_` mask is True, or
    everywhere if there is no mask (`masked` False); nested dicts (final_info) under 'final_info/...'."""
    out: dict[tuple[str, int], tuple[Any, bool]] = {}
    for key, value in infos.items():
        if key.startswith("_"):
            continue
        mask = infos.get("_" + key)
        if isinstance(value, dict):
            for (sub, lane), v in entries(value, n, prefix + key + "/").items():
                if mask is None or mask[lane]:
                    out[sub, lane] = v
            continue
        for lane in range(n):
            if mask is None or mask[lane]:
                v = value[lane]
                out[prefix + key, lane] = (np.asarray(v).tolist() if v is not None else None, mask is not None)
    return out


def assert_same_infos(sync: dict[str, Any], ours: dict[str, Any], n: int, where: str) -> None:
    """Every entry of SyncVectorEnv's infos is in ours with the same value; ours has no masked entry more."""
    a, b = entries(sync, n), entries(ours, n)
    for key, (value, _) in a.items():
        assert key in b, f"{where}: {key} missing"
        assert b[key][0] == value, f"{where}: {key} {b[key][0]} != {value}"
    extra = [key for key, (_, masked) in b.items() if masked and key not in a]
    assert not extra, f"{where}: entries SyncVectorEnv does not give: {extra}"


def play_both(env_id: str, kwargs: dict[str, Any], mode: AutoresetMode, steps: int, n: int = 6) -> None:
    """Our batched env and SyncVectorEnv over the scalar env, per-lane seeds, the same actions: equal steps."""
    ours = gym.make_vec(env_id, num_envs=n, autoreset_mode=mode, **kwargs)
    sync = gym.make_vec(env_id, num_envs=n, vectorization_mode="sync", vector_kwargs={"autoreset_mode": mode},
                        **kwargs)
    assert ours.autoreset_mode == mode and ours.metadata["autoreset_mode"] == mode
    seeds = [100 + 7 * i for i in range(n)]
    (o1, i1), (o2, i2) = sync.reset(seed=seeds), ours.reset(seed=seeds)
    np.testing.assert_array_equal(o1, o2)
    assert_same_infos(i1, i2, n, "reset")
    rng = np.random.default_rng(5)
    ends = 0
    for t in range(steps):
        actions = rng.integers(0, 4, size=n)
        out1, out2 = sync.step(actions), ours.step(actions)
        for k in range(4):
            np.testing.assert_array_equal(out1[k], out2[k], err_msg=f"{env_id} {mode} step {t} part {k}")
        assert_same_infos(out1[4], out2[4], n, f"{env_id} {mode} step {t}")
        done = out1[2] | out1[3]
        ends += int(done.sum())
        if mode == AutoresetMode.DISABLED and done.any():
            (o1, i1), (o2, i2) = (env.reset(options={"reset_mask": done.copy()}) for env in (sync, ours))
            np.testing.assert_array_equal(o1, o2)
            assert_same_infos(i1, i2, n, f"masked reset after step {t}")
    assert ends >= 3 * n  # several episodes ended in every lane on average


@pytest.mark.parametrize("mode", MODES, ids=lambda m: m.name)
@pytest.mark.parametrize("env_id,kwargs", IDS, ids=[i for i, _ in IDS])
def test_per_lane_seeds_play_what_sync_vector_env_plays(env_id: str, kwargs: dict[str, Any],
                                                        mode: AutoresetMode) -> None:
    play_both(env_id, kwargs, mode, steps=400 if env_id == "mewa/MEWA-v0" else 800)


def episodes_played(env_id: str, kwargs: dict[str, Any], mode: AutoresetMode, seed: Any, steps: int,
                    n: int = 8) -> list[list[list[tuple]]]:
    """Per lane, its finished episodes as [(first obs), (action, obs, reward, terminated, truncated), ...];
    each lane's actions come from its own generator, drawn only when the lane acts."""
    env = gym.make_vec(env_id, num_envs=n, autoreset_mode=mode, **kwargs)
    obs, _ = env.reset(seed=seed)
    lane_rngs = [np.random.default_rng(1000 + i) for i in range(n)]
    current: list[list[tuple]] = [[(obs[i].tobytes(),)] for i in range(n)]
    finished: list[list[list[tuple]]] = [[] for _ in range(n)]
    starting = np.zeros(n, dtype=bool)  # NEXT_STEP: the lane's next step is its reset step
    for _ in range(steps):
        actions = np.array([0 if starting[i] else lane_rngs[i].integers(0, 4) for i in range(n)])
        obs, reward, term, trunc, info = env.step(actions)
        done = term | trunc
        for i in range(n):
            if starting[i]:
                current[i] = [(obs[i].tobytes(),)]
                continue
            last = info["final_obs"][i] if mode == AutoresetMode.SAME_STEP and done[i] else obs[i]
            current[i].append((int(actions[i]), last.tobytes(), float(reward[i]), bool(term[i]), bool(trunc[i])))
            if done[i]:
                finished[i].append(current[i])
                current[i] = [(obs[i].tobytes(),)] if mode == AutoresetMode.SAME_STEP else []
        if mode == AutoresetMode.DISABLED and done.any():
            obs, _ = env.reset(options={"reset_mask": done})
            for i in np.flatnonzero(done):
                current[i] = [(obs[i].tobytes(),)]
        starting = done if mode == AutoresetMode.NEXT_STEP else np.zeros(n, dtype=bool)
    return finished


@pytest.mark.parametrize("env_id,kwargs", IDS, ids=[i for i, _ in IDS])
@pytest.mark.parametrize("seed", [3, [5, 6, 7, 8, 9, 10, 11, 12]], ids=["int seed", "seed list"])
def test_the_modes_play_the_same_episodes(env_id: str, kwargs: dict[str, Any], seed: Any) -> None:
    """With a seed list, all three modes; with one int seed (one generator shared by the lanes, drawn
    in the order episodes start), SAME_STEP and DISABLED, whose episodes start on the same steps."""
    played = {mode: episodes_played(env_id, kwargs, mode, seed, steps=600) for mode in MODES}
    reference = played[AutoresetMode.NEXT_STEP if isinstance(seed, list) else AutoresetMode.SAME_STEP]
    for mode in (AutoresetMode.SAME_STEP, AutoresetMode.DISABLED):
        for lane, episodes in enumerate(played[mode]):
            k = min(len(episodes), len(reference[lane]))
            assert k >= 3, (mode, lane, k)
            assert episodes[:k] == reference[lane][:k], (mode, lane)


def test_int_and_list_seeds_draw_differently_and_a_lane_seed_is_its_own() -> None:
    """A seed list is per lane: lane i with seed s plays the same episodes wherever s sits in the list."""
    a = episodes_played("mewa/MEWA-v0", {}, AutoresetMode.NEXT_STEP, [1, 2, 3, 4, 5, 6, 7, 8], steps=300)
    b = episodes_played("mewa/MEWA-v0", {}, AutoresetMode.NEXT_STEP, [9, 2, 9, 9, 9, 9, 9, 9], steps=300)
    c = episodes_played("mewa/MEWA-v0", {}, AutoresetMode.NEXT_STEP, 1, steps=300)
    assert a[1] == b[1] and a[0] != b[0]
    assert a[0] != c[0]
    # One int seed: NEXT_STEP's extra reset steps change the order in which the lanes' episodes start,
    # hence which pairs and luck they draw from the shared generator.
    same = episodes_played("mewa/MEWA-v0", {}, AutoresetMode.SAME_STEP, 1, steps=300)
    assert any(c[i][:len(c[i])] != same[i][:len(c[i])] for i in range(8))


def test_the_mode_is_per_env_and_bad_modes_are_named() -> None:
    same = gym.make_vec("mewa/MEWA-Meta-v0", num_envs=2, autoreset_mode="SameStep")
    default = gym.make_vec("mewa/MEWA-Meta-v0", num_envs=2)
    assert same.autoreset_mode == AutoresetMode.SAME_STEP == same.metadata["autoreset_mode"]
    assert default.autoreset_mode == AutoresetMode.NEXT_STEP == default.metadata["autoreset_mode"]
    assert MewaVectorEnv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    with pytest.raises(ValueError, match="autoreset_mode 'Sometimes' is not one of NEXT_STEP"):
        MewaVectorEnv(2, autoreset_mode="Sometimes")


def test_bad_resets_and_steps_say_what_is_wrong() -> None:
    env = MewaVectorEnv(3, autoreset_mode=AutoresetMode.DISABLED)
    with pytest.raises(RuntimeError, match="never started"):
        env.step(np.zeros(3, dtype=np.int64))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"one per sub-env: 3, got 2"):
        env.reset(seed=[1, 2])
    with pytest.raises(ValueError, match="seed of sub-env 1 must be a non-negative int"):
        env.reset(seed=[1, 2.5, 3])
    with pytest.raises(ValueError, match=r"bool numpy array of shape \(3,\), got int64 \(3,\)"):
        env.reset(options={"reset_mask": np.array([1, 0, 0])})
    with pytest.raises(ValueError, match="resets no sub-env"):
        env.reset(options={"reset_mask": np.zeros(3, dtype=bool)})
    with pytest.raises(ValueError, match="cannot be combined with 'task'"):
        env.reset(options={"reset_mask": np.ones(3, dtype=bool), "task": env.tasks[0]})
    rng = np.random.default_rng(0)
    done = np.zeros(3, dtype=bool)
    while not done.any():
        _, _, term, trunc, _ = env.step(rng.integers(0, 4, size=3))
        done = term | trunc
    with pytest.raises(RuntimeError, match=r"sub-env\(s\) \[\d.*reset_mask"):
        env.step(rng.integers(0, 4, size=3))
    obs, info = env.reset(options={"reset_mask": done})
    assert (info["progress"][done] == 0).all()
    env.step(rng.integers(0, 4, size=3))  # every lane runs again


def test_a_masked_reset_leaves_the_other_lanes_alone() -> None:
    env = MetaEpisodeVectorEnv(4, episodes=2, autoreset_mode=AutoresetMode.DISABLED)
    env.reset(seed=[1, 2, 3, 4])
    for _ in range(5):
        obs, _, _, _, info = env.step(np.array([0, 1, 2, 3]))
    state = (env.workers, env.luck_keys, env.episode_in_trial)
    mask = np.array([False, True, False, False])
    again, info = env.reset(seed=[None, 9, None, None], options={"reset_mask": mask})
    np.testing.assert_array_equal(again[~mask], obs[~mask])
    assert not again[1, 18:].any()  # no previous action, reward or new-episode flag
    for before, after in zip(state, (env.workers, env.luck_keys, env.episode_in_trial)):
        np.testing.assert_array_equal(before[~mask], after[~mask])
    fresh = MetaEpisodeVectorEnv(4, episodes=2)
    first, _ = fresh.reset(seed=[5, 9, 5, 5])
    np.testing.assert_array_equal(again[1], first[1])  # lane 1 reseeded with 9: its first meta-episode
    assert env.luck_keys[1] == fresh.luck_keys[1]


def test_events_are_opt_in_so_every_info_entry_is_numeric() -> None:
    sync = gym.make_vec("mewa/MEWA-v0", num_envs=4, vectorization_mode="sync")
    sync.reset(seed=[0, 1, 2, 3])
    rng = np.random.default_rng(0)
    for _ in range(200):
        *_, info = sync.step(rng.integers(0, 4, size=4))
        assert all(np.asarray(v).dtype != object for v in info.values()), sorted(info)
    env = MewaEnv(events=True)
    env.reset(seed=0)
    kinds = set()
    for _ in range(300):
        _, _, term, trunc, info = env.step(int(rng.integers(0, 4)))
        kinds |= {e.kind for e in info["events"]}
        if term or trunc:
            env.reset()
    assert {"mistake", "structure_completed", "subgoal_reached"} <= kinds
    assert "events" not in MewaEnv().reset(seed=0)[1]
