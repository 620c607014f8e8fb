"""The DPT baseline: its training sequences, its KV cache, the train command on a dataset, and the learning test."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

from mewa_bench.agents import dpt  # noqa: E402
from mewa_bench.agents.causal_transformer import OBS_SCALE, TOKEN  # noqa: E402
from mewa_bench.design.suites import load_suite  # noqa: E402

TWO_WORKERS = np.array([[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 0.0]])
pytestmark = pytest.mark.usefixtures("offline_hub")  # lerobot caches in a temp dir, the Hub forbidden


def test_a_token_holds_the_previous_transition_and_the_episode_boundaries() -> None:
    obs = np.arange(5 * 18, dtype=np.float32).reshape(5, 18)
    seqs = dpt.sequences_from_frames(obs, np.array([1, 2, 3, 0, 1]), np.array([-0.5, -1.0, -0.2, -0.1, -0.3]),
                                     np.array([3, 2, 1, 0, 3]), meta=np.array([7, 7, 7, 9, 9]),
                                     episode=np.array([0, 0, 1, 0, 0]))
    assert seqs.starts.tolist() == [0, 3, 5] and len(seqs) == 2
    t = seqs.tokens
    np.testing.assert_allclose(t[:, :18] * OBS_SCALE, obs)
    np.testing.assert_allclose(t[[1, 2, 4], 18:36] * OBS_SCALE, obs[[0, 1, 3]])  # the previous frame's
    assert not t[[0, 3], 18:42].any()  # a meta-episode's first token has no previous transition
    assert t[1, 36 + 1] == 1 and t[2, 36 + 2] == 1 and t[4, 36 + 0] == 1 and t[1, 36:40].sum() == 1
    assert t[:, 40].tolist() == pytest.approx([0.0, -0.5, -1.0, 0.0, -0.1])
    assert t[:, 41].tolist() == [0, 0, 1, 0, 0]  # new episode, not new meta-episode
    assert seqs.label.tolist() == [3, 2, 1, 0, 3] and seqs.episode.tolist() == [0, 0, 1, 0, 0]


def test_playing_with_the_kv_cache_gives_the_full_passs_logits() -> None:
    import torch

    settings = dpt.Settings(context=64)
    torch.manual_seed(0)
    model = dpt.make_model(settings).double().eval()
    rng = np.random.default_rng(0)
    length = 40
    tokens = torch.as_tensor(rng.normal(size=(2, length, TOKEN)))
    episode = torch.as_tensor(rng.integers(0, 10, size=(2, length)))
    with torch.no_grad():
        full = model(tokens, episode, torch.ones(2, length, dtype=torch.bool))
        for lanes, empty in ((np.array([0, 2]), 1), (np.array([1, 2]), 0)):  # an index, then a slice of the cache
            cache = model.new_cache(3)
            stepped = torch.stack([model.step(tokens[:, t], episode[:, t], cache, lanes) for t in range(length)], dim=1)
            torch.testing.assert_close(stepped, full, rtol=0, atol=1e-12)
            assert not cache.layers[0][0][empty].any() and cache.lengths.tolist().count(length) == 2


def test_the_ring_buffer_plays_what_the_sliding_window_trains() -> None:
    """Past `context` tokens a lane's cache keeps the last ones per layer: the full pass with each token attending to
    its last `context` tokens (as in training) gives the same logits at every step."""
    import torch

    settings = dpt.Settings(context=8, layers=2)
    torch.manual_seed(1)
    model = dpt.make_model(settings).double().eval()
    tokens = torch.as_tensor(np.random.default_rng(1).normal(size=(1, 30, TOKEN)))
    episode = torch.as_tensor(np.repeat(np.arange(3), 10))[None]
    with torch.no_grad():
        cache = model.new_cache(1)
        stepped = torch.stack([model.step(tokens[:, t], episode[:, t], cache, np.array([0])) for t in range(30)], dim=1)
        full = model(tokens, episode, torch.ones(1, 30, dtype=torch.bool))
        unlimited = dpt.make_model(dpt.Settings(context=64, layers=2)).double().eval()
        unlimited.load_state_dict(model.state_dict())
        longer = unlimited(tokens, episode, torch.ones(1, 30, dtype=torch.bool))
    torch.testing.assert_close(stepped, full, rtol=0, atol=1e-12)
    assert (stepped[0, 8:] - longer[0, 8:]).abs().max() > 1e-6  # the window matters past `context` tokens


def two_worker_sequences(meta_episodes: int, seed: int) -> dpt.Sequences:
    """Random play on the two-worker task, each frame labelled with the exact known-worker optimal action."""
    from mewa_bench.datasets.labels import optimal_labels
    from mewa_bench.datasets.tiers import play_tier
    from mewa_bench.game.table import transition_table

    suite = load_suite("narrow-v1")
    task = suite.tasks[0]
    rng = np.random.default_rng(seed)
    workers = TWO_WORKERS[np.arange(meta_episodes) % 2]
    keys = rng.integers(0, 1 << 62, size=(meta_episodes, 10), dtype=np.uint64)
    played = play_tier("random", suite.name, suite.tasks, 0, workers, keys, rng, np.arange(meta_episodes)).played
    labels, _ = optimal_labels(task, workers, played.episode // 10, played.t, played.state)
    return dpt.sequences_from_frames(transition_table(task).obs[played.state], played.action, played.reward, labels,
                                     played.episode // 10, played.episode % 10)


def test_resume_continues_from_the_last_checkpoint(tmp_path: Path) -> None:
    import csv

    import torch

    out, data = tmp_path / "run", two_worker_sequences(8, 0)
    settings = dpt.Settings(suite="narrow-v1", total_steps=2 * 16, checkpoint_every=1, d_model=16, layers=1)
    dpt.train(settings, out, data=data)
    with (out / dpt.METRICS).open("a") as f:  # an update that finished after the last checkpoint: redone on resume
        f.write("3,48,0.1,1.0,0.5\r\n")
    with pytest.raises(ValueError, match=r"d_model=32 \(the run has 16\)"):
        dpt.train(replace(settings, total_steps=4 * 16, d_model=32), out, resume=True, data=data)
    dpt.train(replace(settings, total_steps=4 * 16), out, resume=True, data=data)
    with (out / dpt.METRICS).open() as f:
        assert [int(r["update"]) for r in csv.DictReader(f)] == [1, 2, 3, 4]
    state = torch.load(out / dpt.CHECKPOINT, weights_only=False)
    assert (state["update"], state["settings"]["d_model"]) == (4, 16)


@pytest.mark.slow  # the full learning budget; the by-hand, determinism, resume and play tests run by default
def test_dpt_learns_to_adapt_to_two_opposite_workers_from_data_alone(tmp_path: Path) -> None:
    """The learning test: trained on random play labelled with the exact optimal actions (1,000 updates, about 2
    minutes on one core), DPT improves from episode 1 to 10, judged under the protocol's loop on 60 seeds per worker
    (measured: adaptability +0.10 +- 0.04, mean score 0.60 against the best fixed policy's 0.5)."""
    from test_rl2 import play_pairs

    settings = dpt.Settings(suite="narrow-v1", total_steps=16_000, checkpoint_every=10_000)
    checkpoint = dpt.train(settings, tmp_path / "run", data=two_worker_sequences(512, 0))
    returns = play_pairs(checkpoint, load_suite("narrow-v1").tasks[0], [tuple(w) for w in TWO_WORKERS], seeds=60,
                         agent=dpt.DPTAgent)
    adaptability = (returns[:, :, -1] - returns[:, :, 0]).mean(axis=0)  # per seed, over the two workers
    half = 1.96 * adaptability.std(ddof=1) / np.sqrt(len(adaptability))
    assert adaptability.mean() - half > 0, (adaptability.mean(), half)


def test_train_dpt_on_a_dataset_makes_a_submission_that_plays(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app
    from mewa_bench.datasets import build_training_dataset, training_spec
    from mewa_bench.protocol.config import EvalConfig
    from mewa_bench.protocol.runner import evaluate

    data = tmp_path / "data"
    build_training_dataset(replace(training_spec("narrow-v2-train-random-task-specific", 600), meta_batch=2), data,
                           jobs=1)
    seqs = dpt.dataset_sequences(data)
    import pyarrow.parquet as pq

    table = pq.read_table(next((data / "data").rglob("*.parquet")), columns=["optimal_action", "meta_episode_index"])
    assert seqs.label.tolist() == table.column("optimal_action").to_numpy().ravel().tolist()
    assert len(seqs) == len(np.unique(table.column("meta_episode_index").to_numpy()))

    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["train", "dpt", "--dataset", str(data), "--steps", "20", "--out", str(out)],
                                env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "training 32 meta-episodes per run (2 updates of 16; --steps 20 rounded up" in text
    assert "predictions of the dataset's labels (dpt: the optimal actions; imitation, ad: the behaviour's) (not a score" \
        in text and "episode 1 -> 10" not in text
    info = json.loads((out / "run.json").read_text())
    assert (info["algorithm"], info["suite"], info["steps"]) == ("dpt", "narrow-v2", 32)
    readme = (out / "README.md").read_text()
    assert f"--dataset {data}" in readme and readme.startswith("# dpt (narrow-v2, seed 1)\n")
    assert f"\nTraining data: {info['notes']}.\n" in readme  # what it learnt from
    results, _ = evaluate(EvalConfig(agent_path=out / "agent.py", suite="narrow-v2", out=tmp_path / "r.json",
                                     seeds=(0, 1), pairs=(0, 3)))
    assert len(results["units"]) == 4

    for args, message in ((["train", "rl2", "--dataset", str(data)],
                           "only offline algorithms (dpt, imitation, ad) take a dataset"),
                          (["train", "dpt", "--dataset", str(data), "--suite", "wide-v2"],
                           "the dataset is of narrow-v2, not wide-v2"),
                          (["train", "dpt", "--dataset", str(tmp_path)], "cannot read the dataset's metadata"),
                          (["train", "dpt"], "DPT learns from a training dataset: give --dataset")):
        refused = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
        text = " ".join(re.sub("[│╭╮╰╯─]", " ", refused.output).split())  # the error box unwrapped
        assert refused.exit_code != 0 and message in text, (args, refused.output)
