"""The transformer baselines' shared model and lane cache: lanes stepped in any subsets and at any lengths, read
whole or in groups of similar length, give each lane the logits of the full pass over its own sequence."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from mewa_bench.agents.causal_transformer import TOKEN, LaneCache, make_transformer  # noqa: E402


def test_lanes_at_different_lengths_in_any_subsets_get_their_full_passs_logits() -> None:
    torch.manual_seed(0)
    model = make_transformer(d_model=16, heads=2, layers=2, context=64).double().eval()
    rng = np.random.default_rng(0)
    lanes = 40
    lengths = rng.integers(1, 60, size=lanes)
    lengths[:4] = 59  # a few long lanes: one span for all would be mostly padding
    tokens = torch.as_tensor(rng.normal(size=(lanes, 60, TOKEN)))
    episode = torch.as_tensor(rng.integers(0, 10, size=(lanes, 60)))
    cache = LaneCache(2, lanes, 2, 64, 8)
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
