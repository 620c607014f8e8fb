"""The imitation baseline: its step-by-step play against its full pass, the train command on a dataset, and the
learning test (it adapts in context on the two-worker task, from data alone)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from mewa_bench.agents import imitation  # noqa: E402
from mewa_bench.design.suites import load_suite  # noqa: E402

TWO_WORKERS = np.array([[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 0.0]])
pytestmark = pytest.mark.usefixtures("offline_hub")  # lerobot caches in a temp dir, the Hub forbidden


def test_step_by_step_play_gives_the_full_passs_logits() -> None:
    """Two lanes of three stepped with `step` (zero state at each sequence's start, as a lane is reset) give the
    logits of the full pass over the whole sequences."""
    torch.manual_seed(0)
    policy = imitation.make_policy(16).double().eval()
    x = torch.as_tensor(np.random.default_rng(0).normal(size=(2, 30, 24)))
    with torch.no_grad():
        full = policy(x)
        h = torch.full((3, 16), 5.0, dtype=torch.float64)  # stale states: the reset must clear them
        lanes, stepped = torch.tensor([0, 2]), []
        for t in range(30):
            logits, h[lanes] = policy.step(x[:, t], h[lanes], torch.tensor([t == 0, t == 0]))
            stepped.append(logits)
    torch.testing.assert_close(torch.stack(stepped, dim=1), full, rtol=0, atol=1e-12)
    assert (h[1] == 5.0).all()


def two_worker_histories(histories: int, seed: int):
    """Posterior-sampling learners (the learning-histories tier's behaviour) playing 10 episodes on each of the two
    opposite workers: an adaptive behaviour that, like the expert tier's, does not know the worker."""
    from mewa_bench.datasets.learning_histories import play_histories
    from mewa_bench.datasets.meta_episodes import MetaEpisodeDataset, frames_in_sequences
    from mewa_bench.game.table import transition_table

    task = load_suite("narrow-v1").tasks[0]
    rng = np.random.default_rng(seed)
    workers = TWO_WORKERS[np.arange(histories) % 2]
    keys = rng.integers(0, 1 << 62, size=(histories, 10), dtype=np.uint64)
    played, _ = play_histories(task, workers, keys, rng)
    frames = frames_in_sequences(np.arange(len(played.t)), transition_table(task).obs[played.state], played.action,
                                 played.reward, np.zeros(len(played.t)), played.episode // 10, played.episode % 10)
    return MetaEpisodeDataset(frames)


def judge(checkpoint: Path, seeds: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Per seed the adaptability (s_10 - s_1) and the mean score over the 10 episodes (both means over the two workers,
    on the max-expected scale) of the checkpoint played greedily under the protocol's loop, and the best fixed
    t-optimal policy's mean score."""
    from test_rl2 import play_pairs

    from mewa_bench.design.exact import expected_returns
    from mewa_bench.design.policies import toptimal_family

    task = load_suite("narrow-v1").tasks[0]
    values = expected_returns(task, toptimal_family(task.N), TWO_WORKERS)  # [P, W]
    best = values.max(axis=0)
    agent = lambda checkpoint, seed: imitation.ImitationAgent(checkpoint, seed, greedy=True)  # noqa: E731
    returns = play_pairs(checkpoint, task, [tuple(w) for w in TWO_WORKERS], seeds=seeds, agent=agent)
    scores = (returns / best[:, None, None]).mean(axis=0)  # [seed, episode]
    return scores[:, -1] - scores[:, 0], scores.mean(axis=1), float((values / best).mean(axis=1).max())


def test_imitation_learns_to_adapt_to_two_opposite_workers_from_data_alone(tmp_path: Path) -> None:
    """The learning test: trained on 256 posterior-sampling histories (300 updates of 16, about a minute on one core),
    the GRU improves from episode 1 to 10 in context and beats the best fixed policy, judged under the protocol's loop
    on 40 seeds per worker (measured: adaptability +0.50 on every seed, its first episode's fixed policy suiting one
    worker of the two and its tenth perfect on both. Untrained (one update): +0.00 exactly, and it fails)."""
    settings = imitation.Settings(suite="narrow-v1", total_steps=300 * 16, batch=16, hidden=64, checkpoint_every=10_000)
    checkpoint = imitation.train(settings, tmp_path / "run", data=two_worker_histories(256, 0))
    adaptability, score, best_fixed = judge(checkpoint, seeds=40)
    half = 1.96 * adaptability.std(ddof=1) / np.sqrt(len(adaptability))
    assert adaptability.mean() - half > 0, (adaptability.mean(), half)
    gain = score - best_fixed
    assert gain.mean() - 1.96 * gain.std(ddof=1) / np.sqrt(len(gain)) > 0, gain.mean()


def test_train_imitation_on_a_dataset_makes_a_submission_that_plays(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app
    from mewa_bench.datasets import build_training_dataset, training_spec
    from mewa_bench.protocol.config import EvalConfig
    from mewa_bench.protocol.runner import evaluate

    data = tmp_path / "data"
    build_training_dataset(replace(training_spec("narrow-v2-train-expert", 1), meta_batch=2), data, jobs=1)
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["train", "imitation", "--dataset", str(data), "--steps", "3", "--out", str(out),
                                      "--set", "batch=2", "--set", "hidden=8"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "training 4 meta-episodes per run (2 updates of 2; --steps 3 rounded up" in " ".join(result.output.split())
    info = json.loads((out / "run.json").read_text())
    assert (info["algorithm"], info["suite"], info["steps"]) == ("imitation", "narrow-v2", 4)
    assert 'greedy="true"' in (out / "agent.py").read_text() and f"--dataset {data}" in (out / "README.md").read_text()
    results, _ = evaluate(EvalConfig(agent_path=out / "agent.py", suite="narrow-v2", out=tmp_path / "r.json",
                                     seeds=(0, 1), pairs=(0, 3)))
    assert len(results["units"]) == 4
    refused = CliRunner().invoke(app, ["train", "imitation", "--dataset", str(data), "--worker", "0,1,1,1"],
                                 env={"COLUMNS": "200"})
    assert refused.exit_code != 0 and "its workers are the dataset's" in " ".join(refused.output.split())
