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
from two_worker_task import assert_adapts_and_beats_the_best_fixed_policy, judge, learner_histories  # noqa: E402
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
    """Posterior-sampling learners' 10 episodes on each of the two opposite workers, as a `MetaEpisodeDataset`: an
    adaptive behaviour that, like the expert tier's, does not know the worker."""
    from mewa_bench.datasets.meta_episodes import MetaEpisodeDataset

    return MetaEpisodeDataset(learner_histories(histories, 10, seed))


def test_imitation_learns_to_adapt_to_two_opposite_workers_from_data_alone(tmp_path: Path) -> None:
    """The learning test: trained on 256 posterior-sampling histories (300 updates of 16, about a minute on one core),
    the GRU improves from episode 1 to 10 in context and beats the best fixed policy, judged under the protocol's loop
    on 40 seeds per worker, each on a lane (measured: adaptability +0.50 on every seed, its first episode's fixed
    policy suiting one worker of the two and its tenth perfect on both. After 100 updates of 16 it has not learnt to
    switch: +0.00 exactly, and it fails; shorter runs than 300 updates sit at that edge: 200 updates of 8 passed in
    one process and failed in another)."""
    settings = imitation.Settings(suite="narrow-v1", total_steps=300 * 16, batch=16, hidden=64, checkpoint_every=10_000)
    checkpoint = imitation.train(settings, tmp_path / "run", data=two_worker_histories(256, 0))
    greedy = lambda checkpoint, lanes: imitation.ImitationVectorAgent(checkpoint, lanes, greedy=True)  # noqa: E731
    assert_adapts_and_beats_the_best_fixed_policy(*judge(checkpoint, 40, greedy))


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
