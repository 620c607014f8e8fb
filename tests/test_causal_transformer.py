"""The transformer baselines' shared model and lane cache: lanes stepped in any subsets and at any lengths, read
whole or in groups of similar length, give each lane the logits of the full pass over its own sequence."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from mewa_bench.agents.causal_transformer import TOKEN, LaneCache, make_transformer  # noqa: E402


@pytest.mark.parametrize("heads, kv_heads", [(2, 0), (4, 2), (4, 1)])
def test_lanes_at_different_lengths_in_any_subsets_get_their_full_passs_logits(heads: int, kv_heads: int) -> None:
    """Every lane's logits are those of the full pass over its own sequence, with a key/value head per query head or
    shared by several."""
    torch.manual_seed(0)
    model = make_transformer(d_model=16, heads=heads, layers=2, context=64, kv_heads=kv_heads).double().eval()
    rng = np.random.default_rng(0)
    lanes = 40
    lengths = rng.integers(1, 60, size=lanes)
    lengths[:4] = 59  # a few long lanes: one span for all would be mostly padding
    tokens = torch.as_tensor(rng.normal(size=(lanes, 60, TOKEN)))
    episode = torch.as_tensor(rng.integers(0, 10, size=(lanes, 60)))
    cache = model.new_cache(lanes)
    assert cache.layers[0][0].shape == (lanes, kv_heads or heads, 64, 16 // heads)
    ways: set[str] = set()
    groups = cache.groups
    cache.groups = lambda acting: (lambda out: ways.add(read_as(out)) or out)(groups(acting))
    stepped = [[] for _ in range(lanes)]
    with torch.no_grad():
        full = [model(tokens[i:i + 1, :lengths[i]], episode[i:i + 1, :lengths[i]],
                      torch.ones(1, int(lengths[i]), dtype=torch.bool))[0] for i in range(lanes)]
        done = np.zeros(lanes, dtype=np.int64)
        while (done < lengths).any():
            waiting = np.flatnonzero(done < lengths)
            acting = waiting[rng.random(len(waiting)) < 0.7] if len(waiting) > 1 else waiting  # any subset
            if len(acting) == 0:
                continue
            at = torch.as_tensor(done[acting])
            logits = model.step(tokens[acting, at], episode[acting, at], cache, acting)
            for row, lane in enumerate(acting.tolist()):
                stepped[lane].append(logits[row])
            done[acting] += 1
    for lane in range(lanes):
        torch.testing.assert_close(torch.stack(stepped[lane]), full[lane], rtol=0, atol=1e-12)
    assert ways == {"view", "view of a run", "groups"}, ways
    assert cache.lengths.tolist() == lengths.tolist()


def read_as(groups) -> str:
    """How a step read the cache: one view of the acting lanes, one view of a run that holds them, or groups."""
    if len(groups) > 1 or groups[0].take is not None:
        return "groups"
    return "view" if groups[0].place is None else "view of a run"


def test_the_cache_is_read_the_way_that_moves_fewest_bytes() -> None:
    cache = LaneCache(1, 64, 1, 128, 4)
    cache.lengths[:] = 10
    (whole,) = cache.groups(np.arange(8, 24))  # consecutive lanes: a view, nothing copied
    assert read_as([whole]) == "view" and whole.rows == slice(8, 24) and whole.span == 11
    (run,) = cache.groups(np.array([3, 4, 6, 7]))  # lane 5 does not act: still a view, its row thrown away
    assert read_as([run]) == "view of a run" and run.rows == slice(3, 8) and run.place.tolist() == [0, 1, 3, 4]
    assert (run.mask[2, 0, 0, 1:] == -np.inf).all() and run.mask[2, 0, 0, 0] == 0
    cache.lengths[:32] = 120  # half the lanes long, half short, spread out: copies of groups of similar length
    grouped = cache.groups(np.arange(0, 64, 2))
    assert read_as(grouped) == "groups" and sorted(g.span for g in grouped) == [11, 121]
    assert sorted(torch.cat([g.take for g in grouped]).tolist()) == list(range(32))


def test_new_keys_go_to_each_lanes_ring_buffer_slot() -> None:
    cache = LaneCache(1, 3, 2, 4, 1)
    cache.lengths[:] = [0, 5, 2]
    keys = cache.layers[0][0]
    keys.view(-1, 1).index_copy_(0, cache.write_rows(np.array([2, 1])), torch.tensor([[1.0], [2.0], [3.0], [4.0]], dtype=keys.dtype))
    written = {tuple(i) for i in torch.nonzero(keys[..., 0]).tolist()}
    assert written == {(2, 0, 2), (2, 1, 2), (1, 0, 1), (1, 1, 1)}  # (lane, key/value head, slot = length % 4)
    assert keys[2, :, 2, 0].tolist() == [1.0, 2.0] and keys[1, :, 1, 0].tolist() == [3.0, 4.0]


def test_heads_that_do_not_split_into_key_value_groups_are_a_clear_error() -> None:
    with pytest.raises(ValueError, match="heads 4, kv_heads 3, d_model 16"):
        make_transformer(d_model=16, heads=4, layers=1, context=8, kv_heads=3)


def play(lanes_player, steps: int, seed: int) -> list[np.ndarray]:
    """Drive a `TransformerLanes` on random observations: 6 lanes, random subsets acting, pairs restarting and
    episodes ending at random; the actions of every call."""
    from mewa_bench.protocol.agent import Transitions

    rng = np.random.default_rng(seed)
    lanes_player.reset_task(np.arange(6), np.arange(6))
    actions = []
    for _ in range(steps):
        acting = np.flatnonzero(rng.random(6) < 0.7)
        if len(acting) == 0:
            continue
        obs = rng.integers(0, 5, size=(len(acting), 18)).astype(np.float32)
        taken = lanes_player.act(acting, obs)
        actions.append(taken)
        lanes_player.observe(acting, Transitions(obs, taken, rng.random(len(acting)), obs, np.zeros(len(acting), bool),
                                                 np.zeros(len(acting), bool)))
        ending = acting[rng.random(len(acting)) < 0.1]
        if len(ending):
            lanes_player.end_episode(ending)
        restarting = acting[rng.random(len(acting)) < 0.02]
        if len(restarting):
            lanes_player.reset_task(restarting, rng.integers(0, 1000, len(restarting)))
    return actions


@pytest.mark.parametrize("greedy", [True, False])
def test_float32_steps_take_the_float64_models_decisions(greedy: bool) -> None:
    """Played in float32 with the decisions near a boundary recomputed exactly, a lane takes the actions of the
    float64 model; a margin wide enough to recompute many decisions still does, and the float32 logits' error is far
    below the default margin."""
    from mewa_bench.agents.causal_transformer import MARGIN, TransformerLanes

    torch.manual_seed(3)
    model = make_transformer(d_model=32, heads=4, layers=2, context=48, kv_heads=2).double().eval()
    exact = play(TransformerLanes(model, 6, seed=1, greedy=greedy, sample_episodes=1, margin=0), 300, seed=2)
    for margin in (MARGIN, 0.05):
        player = TransformerLanes(model, 6, seed=1, greedy=greedy, sample_episodes=1, margin=margin, cdf_margin=margin)
        played = play(player, 300, seed=2)
        assert all(np.array_equal(a, b) for a, b in zip(played, exact))
        assert player.cache.dtype == torch.float32 and (player.recomputed > 20 or margin == MARGIN)
    tokens = torch.as_tensor(np.random.default_rng(4).normal(size=(3, 200, TOKEN)))
    episode = torch.as_tensor(np.repeat(np.arange(10), 20))[None].repeat(3, 1)
    with torch.no_grad():
        error = (model(tokens, episode, torch.ones(3, 200, dtype=torch.bool))
                 - player.model(tokens.float(), episode, torch.ones(3, 200, dtype=torch.bool)).double()).abs().max()
    assert error < MARGIN / 50, error
