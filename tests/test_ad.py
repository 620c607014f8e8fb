"""Algorithm Distillation: its windows of learning histories, its play (the tokens a lane builds are the ones it
was trained on), the train command on a dataset, and the learning test (it adapts in context on the two-worker
task, from data alone)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from mewa_bench.agents import ad  # noqa: E402
from mewa_bench.agents.causal_transformer import OBS  # noqa: E402
from test_relabel import renamed_by_hand  # noqa: E402
from two_worker_task import assert_adapts_and_beats_the_best_fixed_policy, judge, learner_histories  # noqa: E402
pytestmark = pytest.mark.usefixtures("offline_hub")  # lerobot caches in a temp dir, the Hub forbidden


def test_a_window_is_whole_episodes_of_one_history_starting_afresh() -> None:
    frames = learner_histories(4, 20, 0)
    data = ad.windows_from(frames)
    assert len(data) == 4 and data.episode_counts().tolist() == [20] * 4
    sequences, first = np.array([2, 0]), np.array([7, 0])
    tokens, episode, label, valid = (t.numpy() for t in ad.window_batch(data, sequences, first, 3, "action"))
    frame = np.arange(len(frames.action))
    for row, (s, e0) in enumerate(zip(sequences, first)):
        in_history = (frame >= frames.starts[s]) & (frame < frames.starts[s + 1])
        rows = np.flatnonzero(in_history & (frames.episode >= e0) & (frames.episode < e0 + 3))
        n = len(rows)
        assert valid[row].sum() == n and valid[row, :n].all()
        assert (label[row, :n] == frames.action[rows]).all()
        assert (episode[row, :n] == frames.episode[rows] - e0).all() and episode[row, 0] == 0
        assert (tokens[row, :n, :OBS] * 8.0 == frames.observation[rows]).all()
        assert not tokens[row, 0, OBS:].any()  # the window's first token: no previous transition
        assert (tokens[row, 1:n, OBS:] == data.tokens[rows[1:], OBS:]).all()  # later ones: the history's own
    optimal = ad.window_batch(data, sequences, first, 3, "optimal_action")[2].numpy()
    assert (optimal[valid] == 3).all()


def test_a_renamed_window_is_the_same_history_under_other_colour_names() -> None:
    data = ad.windows_from(learner_histories(4, 20, 0))
    sequences, first, p = np.array([2, 0]), np.array([7, 0]), np.array([[2, 0, 3, 1], [1, 3, 0, 2]])
    plain = [t.numpy() for t in ad.window_batch(data, sequences, first, 3, "action")]
    renamed = [t.numpy() for t in ad.window_batch(data, sequences, first, 3, "action", p)]
    assert (plain[1] == renamed[1]).all() and (plain[3] == renamed[3]).all()  # episodes, valid
    for row in range(2):
        n = int(plain[3][row].sum())
        before, after = plain[0][row, :n], renamed[0][row, :n]
        for t in range(n):
            assert (after[t, :OBS] == renamed_by_hand(before[t, :OBS], p[row])).all()
            assert (after[t, OBS:2 * OBS] == renamed_by_hand(before[t, OBS:2 * OBS], p[row])).all()
            assert (after[t, 2 * OBS + p[row]] == before[t, 2 * OBS:2 * OBS + 4]).all()  # previous action
        assert (after[:, -2:] == before[:, -2:]).all()  # previous reward, new episode
        assert (renamed[2][row, :n] == p[row][plain[2][row, :n]]).all()  # the learner's action, renamed


def test_a_lane_plays_on_the_tokens_it_was_trained_on(tmp_path: Path) -> None:
    """Replaying a history's first 3 episodes through the agent's lanes (lanes 0 and 2 of 3, both the same
    history) gives the model exactly the tokens and episode indices of that window in training, so the cached
    play's logits are the full pass's."""
    from mewa_bench.protocol.agent import Transitions

    frames = learner_histories(2, 3, 1)
    data = ad.windows_from(frames)
    settings = ad.Settings(suite="narrow-v1", total_steps=16, batch=16, d_model=16, heads=2, checkpoint_every=1)
    checkpoint = ad.train(settings, tmp_path / "run", data=data)
    agent = ad.ADVectorAgent(checkpoint, num_lanes=3, seed=0, greedy=True)
    seen: list[tuple] = []
    step = agent.model.step
    agent.model.step = lambda tokens, episode, cache, lanes: seen.append((tokens, episode)) or step(tokens, episode,
                                                                                                     cache, lanes)
    lanes = np.array([0, 2])
    agent.reset_task(lanes, np.array([5, 6]))
    begin, end = int(frames.starts[1]), int(frames.starts[2])
    for f in range(begin, end):
        if f > begin and frames.episode[f] != frames.episode[f - 1]:
            agent.end_episode(lanes)
        obs = np.repeat(frames.observation[f][None], 2, axis=0)
        agent.act(lanes, obs)
        agent.observe(lanes, Transitions(obs, np.repeat(frames.action[f], 2), np.repeat(float(frames.reward[f]), 2),
                                         obs, np.zeros(2, bool), np.zeros(2, bool)))
    tokens, episode, _, valid = ad.window_batch(data, np.array([1]), np.array([0]), 3, "action")
    played = torch.stack([lane_tokens for lane_tokens, _ in seen]).to(torch.float32)  # [L, 2 lanes, TOKEN]
    for lane in range(2):
        torch.testing.assert_close(played[:, lane], tokens[0], rtol=0, atol=1e-6)
        assert (torch.stack([lane_episode[lane] for _, lane_episode in seen]) == episode[0]).all()
    assert agent.cache.lengths.tolist() == [end - begin, 0, end - begin]
    for lane in (0, 2):  # what an exact recomputation of the lane's step reads
        kept_tokens, kept_episode = agent.history.of(lane)
        assert np.array_equal(kept_tokens, tokens[0].numpy()) and np.array_equal(kept_episode, episode[0].numpy())
    with torch.no_grad():
        full = agent.exact(tokens.double(), episode, valid)[0]
        cache = agent.exact.new_cache(1)
        cached = torch.stack([agent.exact.step(tokens[0, t:t + 1].double(), episode[0, t:t + 1], cache,
                                               np.array([0]))[0] for t in range(end - begin)])
    torch.testing.assert_close(cached, full, rtol=0, atol=1e-10)


def test_pooled_windows_are_each_datasets_histories_in_turn() -> None:
    first, second = ad.windows_from(learner_histories(3, 12, 0)), ad.windows_from(learner_histories(2, 12, 1))
    both = ad.pooled([first, second])
    assert len(both) == 5 and both.episode_counts().tolist() == [12] * 5
    for sequence, (part, own) in enumerate([(first, 0), (first, 1), (first, 2), (second, 0), (second, 1)]):
        for label in ("action", "optimal_action"):
            pooled = ad.window_batch(both, np.array([sequence]), np.array([2]), 10, label)
            alone = ad.window_batch(part, np.array([own]), np.array([2]), 10, label)
            assert all(torch.equal(a, b) for a, b in zip(pooled, alone))
    assert ad.pooled([first]) is first


def test_ad_learns_to_adapt_to_two_opposite_workers_from_data_alone(tmp_path: Path) -> None:
    """The learning test: trained on 256 posterior-sampling histories of 10 episodes (300 updates of 8), the
    transformer improves from episode 1 to 10 in context and beats the best fixed policy, judged under the
    protocol's loop on 20 seeds per worker, each on a lane (measured: adaptability +0.62 +- 0.07, +0.40 over the
    best fixed policy; after 120 updates of 16 it fails: -0.12)."""
    settings = ad.Settings(suite="narrow-v1", total_steps=300 * 8, batch=8, d_model=32, context=256,
                           checkpoint_every=10_000)
    checkpoint = ad.train(settings, tmp_path / "run", data=ad.windows_from(learner_histories(256, 10, 0)))
    played_as_submitted = lambda checkpoint, lanes: ad.ADVectorAgent(checkpoint, lanes, greedy=True)  # noqa: E731
    assert_adapts_and_beats_the_best_fixed_policy(*judge(checkpoint, 20, played_as_submitted))


def test_a_run_is_deterministic_for_its_seed_and_thread_count(tmp_path: Path) -> None:
    """Two runs on two threads give the same weights; the caller's thread count is restored after training and a
    count below 1 is a clear error."""
    data = ad.windows_from(learner_histories(16, 10, 0))
    base = ad.Settings(suite="narrow-v1", total_steps=12 * 8, batch=8, d_model=32, layers=2, context=256)
    before = torch.get_num_threads()

    def weights(threads: int, name: str) -> dict:
        checkpoint = ad.train(replace(base, threads=threads), tmp_path / name, data=data)
        return torch.load(checkpoint, weights_only=False)["model"]

    first, second = weights(2, "a"), weights(2, "b")
    assert all(torch.equal(first[k], second[k]) for k in first)
    assert torch.get_num_threads() == before
    with pytest.raises(ValueError, match="threads 0: expected at least 1"):
        ad.train(replace(base, threads=0), tmp_path / "d", data=data)


def test_train_ad_on_a_dataset_makes_a_submission_that_plays(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app
    from mewa_bench.datasets import build_training_dataset, training_spec
    from mewa_bench.protocol.config import EvalConfig
    from mewa_bench.protocol.runner import evaluate

    data = tmp_path / "data"
    build_training_dataset(replace(training_spec("narrow-v2-train-learning-histories", 1), meta_batch=2), data, jobs=1)
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["train", "ad", "--dataset", str(data), "--steps", "3", "--out", str(out),
                                      "--set", "batch=2", "--set", "d_model=8", "--set", "heads=2",
                                      "--set", "max_start=40"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "training 4 windows per run (2 updates of 2; --steps 3 rounded up" in " ".join(result.output.split())
    info = json.loads((out / "run.json").read_text())
    assert (info["algorithm"], info["suite"], info["steps"]) == ("ad", "narrow-v2", 4)
    assert info["settings"]["max_start"] == 40 and 'greedy="true"' in (out / "agent.py").read_text()
    results, _ = evaluate(EvalConfig(agent_path=out / "agent.py", suite="narrow-v2", out=tmp_path / "r.json",
                                     seeds=(0, 1), pairs=(0, 3)))
    assert len(results["units"]) == 4


def test_train_ad_pools_the_histories_of_several_datasets_of_one_suite(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app
    from mewa_bench.datasets import build_training_dataset, training_spec

    data = {}
    for seed in (1, 2):
        data[seed] = tmp_path / f"data{seed}"
        spec = replace(training_spec("narrow-v2-train-learning-histories", 1), meta_batch=2, seed=seed)
        build_training_dataset(spec, data[seed], jobs=1)
    out = tmp_path / "run"
    options = ["--steps", "2", "--set", "batch=2", "--set", "d_model=8", "--set", "heads=2"]
    result = CliRunner().invoke(app, ["train", "ad", "--dataset", str(data[1]), "--dataset", str(data[2]),
                                      "--out", str(out), *options], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    info = json.loads((out / "run.json").read_text())
    assert info["settings"]["more_datasets"] == [str(data[2])]
    assert info["notes"].count("trained on narrow-v2-train-learning-histories") == 2 and "; also trained on" in info["notes"]
    assert f"--dataset {data[1]} --dataset {data[2]}" in (out / "README.md").read_text()
    settings = ad.settings_from(info["settings"] | {"suite": "narrow-v2"})
    alone = [ad.read_windows(replace(settings, dataset=str(data[s]), more_datasets=[])) for s in (1, 2)]
    both = ad.read_windows(settings)
    assert len(both) == len(alone[0]) + len(alone[1]) == 4
    assert (both.tokens == np.concatenate([alone[0].tokens, alone[1].tokens])).all()

    other = tmp_path / "other"  # a dataset of another suite (its metadata is all the check reads)
    (other / "meta").mkdir(parents=True)
    meta = json.loads((data[2] / "meta" / "mewa.json").read_text())
    (other / "meta" / "mewa.json").write_text(json.dumps({**meta, "suite": {**meta["suite"], "name": "wide-v2"}}))
    result = CliRunner().invoke(app, ["train", "ad", "--dataset", str(data[1]), "--dataset", str(other),
                                      "--out", str(tmp_path / "bad"), *options], env={"COLUMNS": "200"})
    assert result.exit_code != 0 and "a dataset of wide-v2, not of narrow-v2" in " ".join(result.output.split())
    result = CliRunner().invoke(app, ["train", "dpt", "--dataset", str(data[1]), "--dataset", str(data[2]),
                                      "--out", str(tmp_path / "dpt")], env={"COLUMNS": "200"})
    assert result.exit_code != 0 and "dpt learns from one dataset" in " ".join(result.output.split())
    assert not (tmp_path / "bad").exists() and not (tmp_path / "dpt").exists()
