"""The meta-episode loader: whole meta-episodes, blocks and windows of a training dataset as the recurrent agents see
them, checked against the frames lerobot reads and against an agent's own lane bookkeeping."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from mewa_bench.agents.lanes import RecurrentLanes  # noqa: E402
from mewa_bench.datasets import build_training_dataset, load_training_dataset, training_spec  # noqa: E402
from mewa_bench.datasets.meta_episodes import (MetaEpisodeDataset, frames_in_sequences, pad_batch,  # noqa: E402
                                               previous_transition)

pytestmark = pytest.mark.usefixtures("offline_hub")  # lerobot caches in a temp dir, the Hub forbidden


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """Two expert meta-episodes and two 20-episode learning histories on narrow-v2."""
    out = tmp_path_factory.mktemp("meta_episodes")
    roots = {}
    for tier in ("expert", "learning-histories"):
        spec = replace(training_spec(f"narrow-v2-train-{tier}", 1), meta_batch=2, history_episodes=20)
        roots[tier] = out / tier
        build_training_dataset(spec, roots[tier], jobs=1)
    return roots


def test_previous_transitions_by_hand() -> None:
    data = frames_in_sequences(np.arange(6), np.zeros((6, 18)), np.array([1, 2, 3, 0, 1, 2]),
                               np.array([-0.5, -1.0, -0.2, -0.1, -0.3, -0.4]), np.zeros(6),
                               group=np.array([4, 4, 4, 4, 9, 9]), episode=np.array([0, 0, 1, 1, 0, 1]))
    previous_action, previous_reward, new_episode, first = previous_transition(data)
    assert previous_action.tolist() == [-1, 1, 2, 3, -1, 1]  # across an episode boundary, not across sequences
    assert previous_reward.tolist() == pytest.approx([0.0, -0.5, -1.0, -0.2, 0.0, -0.3])
    assert new_episode.tolist() == [0, 0, 1, 0, 0, 1] and first.tolist() == [1, 0, 0, 0, 1, 0]


def test_meta_episodes_hold_the_frames_lerobot_reads_in_play_order(built) -> None:
    root = built["expert"]
    data = MetaEpisodeDataset(root)
    frames = load_training_dataset(root)  # lerobot's LeRobotDataset, after the dataset's checks
    assert len(data) == 2 and sum(len(data[i]["action"]) for i in range(len(data))) == frames.num_frames
    for i in range(len(data)):
        item = data[i]
        rows = [frames[int(f)] for f in item["frame"]]
        assert {int(r["meta_episode_index"]) for r in rows} == {i}
        episodes = [int(r["episode_in_meta_episode"]) for r in rows]
        assert episodes == item["episode"].tolist() and episodes == sorted(episodes) and set(episodes) == set(range(10))
        assert [int(r["frame_index"]) for r in rows][:3] == [0, 1, 2]
        torch.testing.assert_close(item["observation"], torch.stack([r["observation.state"] for r in rows]))
        assert item["action"].tolist() == [int(r["action"]) for r in rows]
        assert item["optimal_action"].tolist() == [int(r["optimal_action"]) for r in rows]
        rewards = torch.stack([r["next.reward"].reshape(()) for r in rows])
        torch.testing.assert_close(item["previous_reward"][1:], rewards[:-1])


def test_inputs_are_what_a_recurrent_agents_lanes_build_when_playing(built) -> None:
    """Replay each meta-episode through `RecurrentLanes` (RL^2's and the imitation agent's bookkeeping): the input it
    builds at every step is the loader's."""
    data = MetaEpisodeDataset(built["expert"])
    for i in range(len(data)):
        item, seen = data[i], []

        def forward(x, h, reset):
            seen.append((x[0].clone(), bool(reset[0])))
            return torch.zeros(1, 4, dtype=torch.float64), h

        lanes, lane = RecurrentLanes(forward, 8, 1, 0, greedy=True), np.array([0])
        lanes.reset_task(lane, np.array([0]))
        episode = item["episode"].tolist()
        for t in range(len(episode)):
            if t > 0 and episode[t] != episode[t - 1]:
                lanes.end_episode(lane)
            lanes.act(lane, item["observation"][t:t + 1].numpy())
            lanes.observe(lane, SimpleNamespace(action=np.array([int(item["action"][t])]),
                                                reward=np.array([float(item["previous_reward"][t + 1])
                                                                 if t + 1 < len(episode) else 0.0])))
        built_inputs = torch.stack([x for x, _ in seen]).float()
        torch.testing.assert_close(built_inputs, item["inputs"], rtol=0, atol=0)
        assert [r for _, r in seen] == item["first"].tolist()


def test_blocks_and_windows_cut_the_same_frames(built) -> None:
    whole = MetaEpisodeDataset(built["learning-histories"])
    blocks = MetaEpisodeDataset(built["learning-histories"], unit="block")
    assert len(whole) == 2 and len(blocks) == 4
    for i in range(2):
        a, b = blocks[2 * i], blocks[2 * i + 1]
        assert torch.equal(torch.cat([a["frame"], b["frame"]]), whole[i]["frame"])
        assert b["first"][0] and b["previous_action"][0] == -1 and b["episode"][0] == 0  # a block starts afresh
        assert not whole[i]["first"][len(a["frame"])]
    windows = MetaEpisodeDataset(built["learning-histories"], window=100, stride=60)
    for w in range(len(windows)):
        item = windows[w]
        sequence = int(item["sequence"][0])
        begin = int(torch.nonzero(whole[sequence]["frame"] == item["frame"][0])[0])
        for key in ("inputs", "action", "optimal_action", "episode", "first"):
            assert torch.equal(item[key], whole[sequence][key][begin:begin + len(item["frame"])]), key
    covered = sorted(set(np.concatenate([windows[w]["frame"].numpy() for w in range(len(windows))]).tolist()))
    assert covered == sorted(np.concatenate([whole[i]["frame"].numpy() for i in range(2)]).tolist())
    assert max(len(windows[w]["frame"]) for w in range(len(windows))) == 100


def test_a_padded_batch_marks_its_valid_frames(built) -> None:
    data = MetaEpisodeDataset(built["expert"])
    batch = pad_batch([data[0], data[1]])
    lengths = [len(data[0]["action"]), len(data[1]["action"])]
    assert batch["inputs"].shape == (2, max(lengths), 24) and batch["valid"].sum(dim=1).tolist() == lengths
    assert torch.equal(batch["action"][1, :lengths[1]], data[1]["action"])
    loader = torch.utils.data.DataLoader(data, batch_size=2, collate_fn=pad_batch)
    assert torch.equal(next(iter(loader))["inputs"], batch["inputs"])
    with pytest.raises(ValueError, match="unit 'episode'"):
        MetaEpisodeDataset(built["expert"], unit="episode")


def test_the_first_episodes_of_each_history(built) -> None:
    whole = MetaEpisodeDataset(built["learning-histories"])
    first = MetaEpisodeDataset(built["learning-histories"], episodes=3)
    assert len(first) == 2
    for i in range(2):
        n = int((whole[i]["episode"] < 3).sum())
        assert n < len(whole[i]["frame"]) and first[i]["episode"].max() == 2
        for key in ("inputs", "frame", "action", "first"):
            assert torch.equal(first[i][key], whole[i][key][:n]), key
