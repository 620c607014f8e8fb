"""RL^2's mechanics: deterministic training, metrics and checkpoints written as
they come, resume, GAE by hand, the checkpoint played under the evaluation protocol, and the learning
test: it adapts to two opposite workers and beats the best fixed policy."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch

from mewa_bench.agents.rl2 import CHECKPOINT, METRICS, Settings, gae, settings_from, train
from mewa_bench.envs import MetaEpisodeVectorEnv
from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.runner import evaluate

TWO_WORKERS = [[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 0.0]]
AGENT = Path(__file__).parent / "agents" / "rl2_checkpoint_agent.py"


def tiny(**kw) -> Settings:
    """3 updates of 8 envs x 16 steps on the two-worker canonical task."""
    return settings_from({"num_envs": 8, "num_steps": 16, "total_steps": 3 * 8 * 16, "hidden": 16,
                          "checkpoint_every": 1, "workers": TWO_WORKERS, **kw})


def rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def test_the_env_draws_pairs_from_a_worker_set(canonical_task) -> None:
    env = MetaEpisodeVectorEnv(num_envs=64, episodes=1, task=canonical_task, workers=TWO_WORKERS)
    env.reset(seed=0)
    seen = {tuple(w) for w in env.workers}
    assert seen == {tuple(w) for w in TWO_WORKERS}
    with pytest.raises(ValueError, match="needs one `task`"):
        MetaEpisodeVectorEnv(num_envs=2, workers=TWO_WORKERS)


def test_training_is_deterministic_and_writes_as_it_goes(tmp_path: Path) -> None:
    first = train(tiny(), tmp_path / "a")
    again = train(tiny(), tmp_path / "b")
    a, b = torch.load(first, weights_only=False), torch.load(again, weights_only=False)
    assert a["update"] == b["update"] == 3
    assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"])
    metrics = rows(tmp_path / "a" / METRICS)
    assert [int(r["update"]) for r in metrics] == [1, 2, 3]
    assert all(np.isfinite(float(r["policy_loss"])) and float(r["entropy"]) > 0 for r in metrics)
    other = torch.load(train(tiny(seed=2), tmp_path / "c"), weights_only=False)
    assert not all(torch.equal(a["model"][k], other["model"][k]) for k in a["model"])


def test_resume_continues_from_the_last_checkpoint(tmp_path: Path) -> None:
    out = tmp_path / "run"
    train(tiny(), out)
    with (out / METRICS).open("a") as f:  # an update that finished after the last checkpoint: redone on resume
        f.write("4,512,0.1,nan,nan,0.0,0.0,1.0\r\n")
    train(tiny(total_steps=5 * 8 * 16), out, resume=True)
    assert [int(r["update"]) for r in rows(out / METRICS)] == [1, 2, 3, 4, 5]
    assert torch.load(out / CHECKPOINT, weights_only=False)["update"] == 5


def test_a_resumed_run_keeps_its_own_settings(tmp_path: Path) -> None:
    """Only the length of a run may change on resume; other settings are refused, naming them, and nothing of the
    run is touched (its metrics rows after the checkpoint are only dropped once the checkpoint has loaded)."""
    out = tmp_path / "run"
    train(tiny(), out)
    with (out / METRICS).open("a") as f:
        f.write("4,512,0.1,nan,nan,0.0,0.0,1.0\r\n")
    before = (out / METRICS).read_bytes(), (out / CHECKPOINT).read_bytes()
    with pytest.raises(ValueError, match=r"hidden=32 \(the run has 16\), learning_rate=0\.5 \(the run has 0\.001\)"):
        train(tiny(total_steps=4 * 8 * 16, hidden=32, learning_rate=0.5), out, resume=True)
    assert ((out / METRICS).read_bytes(), (out / CHECKPOINT).read_bytes()) == before
    train(tiny(total_steps=4 * 8 * 16), out, resume=True)
    assert torch.load(out / CHECKPOINT, weights_only=False)["update"] == 4


def test_gae_by_hand() -> None:
    settings = Settings(gamma=0.5, gae_lambda=0.5)
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    values = torch.tensor([[0.5], [1.0], [1.5]])
    dones = torch.tensor([[0.0], [1.0], [0.0]])  # the meta-episode ends at step 1
    advantages, returns = gae(rewards, values, dones, torch.tensor([2.0]), settings)
    d2 = 3.0 + 0.5 * 2.0 - 1.5
    d1 = 2.0 - 1.0  # no bootstrap across the done
    d0 = 1.0 + 0.5 * 1.0 - 0.5
    expected = [d0 + 0.25 * d1, d1, d2]
    assert advantages[:, 0].tolist() == pytest.approx(expected)
    assert (returns - advantages).tolist() == values.tolist()


def test_a_checkpoint_plays_under_the_evaluation_protocol(tmp_path: Path) -> None:
    checkpoint = train(tiny(), tmp_path / "run")
    config = EvalConfig(agent_path=AGENT, out=tmp_path / "r.json", seeds=(0, 1, 2), pairs=(0, 1),
                        checkpoint=str(checkpoint))
    results, _ = evaluate(config)
    assert len(results["units"]) == 6 and all(len(u["returns"]) == 10 for u in results["units"])
    again, _ = evaluate(EvalConfig(agent_path=AGENT, out=tmp_path / "r2.json", seeds=(0, 1, 2), pairs=(0, 1),
                                   checkpoint=str(checkpoint), lanes=1))
    assert [u["returns"] for u in again["units"]] == [u["returns"] for u in results["units"]]


def play_pairs(checkpoint: Path, task, workers: list[tuple[float, ...]], seeds: int, agent=None) -> np.ndarray:
    """Normalised returns [worker, seed, episode] of the checkpoint under the protocol's loop (10 episodes
    per pair, the agent reset per pair, luck keys fixed by worker, seed and episode); `agent`: the one-lane
    agent class (default RL2Agent)."""
    from mewa_bench.agents.rl2 import RL2Agent
    from mewa_bench.envs import MewaEnv
    from mewa_bench.protocol.agent import Transition

    agent, env = (agent or RL2Agent)(checkpoint, seed=0), MewaEnv(task=task)
    out = np.zeros((len(workers), seeds, 10))
    for i, worker in enumerate(workers):
        for seed in range(seeds):
            agent.reset_task(seed=seed)
            for k in range(10):
                obs, _ = env.reset(options={"task": task, "worker": worker, "luck_key": (i * 1000 + seed) * 10 + k})
                done = False
                while not done:
                    action = agent.act(obs)
                    following, reward, terminated, truncated, info = env.step(action)
                    agent.observe(Transition(obs, action, reward, following, terminated, truncated))
                    obs, done = following, terminated or truncated
                agent.end_episode()
                out[i, seed, k] = info["normalised_return"]
    return out


@pytest.mark.slow  # the full learning budget; the by-hand, determinism, resume and play tests run by default
def test_rl2_learns_to_adapt_to_two_opposite_workers(tmp_path: Path) -> None:
    """The learning test: greedy building is perfect for (0,1,1,1) and fails for (1,1,1,0), and
    the reverse for parallel building; trained for 4 M steps (about 2 min on one core), RL^2 improves
    from episode 1 to 10 and beats the best fixed t-optimal policy, judged with the exact engine."""
    from mewa_bench.design.exact import expected_returns
    from mewa_bench.design.policies import toptimal_family
    from mewa_bench.design.suites import load_suite

    canonical_task = load_suite("narrow-v1").tasks[0]  # the task the run trains on (settings.suite)
    workers = [tuple(w) for w in TWO_WORKERS]
    settings = settings_from({"total_steps": 4_000_000, "num_envs": 128, "num_steps": 64, "update_epochs": 2,
                              "num_minibatches": 2, "ent_coef": 0.003, "workers": TWO_WORKERS, "seed": 1,
                              "checkpoint_every": 1000})
    checkpoint = train(settings, tmp_path / "run")
    values = expected_returns(canonical_task, toptimal_family(canonical_task.N), np.array(workers))  # [P, W]
    best = values.max(axis=0)
    best_fixed = (values / best).mean(axis=1).max()  # the best single policy's mean score: 0.5 here
    scores = (play_pairs(checkpoint, canonical_task, workers, seeds=40) / best[:, None, None]).mean(axis=0)
    adaptability = scores[:, -1] - scores[:, 0]  # per seed
    half = 1.96 * adaptability.std(ddof=1) / np.sqrt(len(adaptability))
    assert adaptability.mean() - half > 0, (adaptability.mean(), half)
    gain = scores.mean(axis=1) - best_fixed
    assert gain.mean() - 1.96 * gain.std(ddof=1) / np.sqrt(len(gain)) > 0, gain.mean()


def test_the_train_command_makes_a_submission_folder(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    out = tmp_path / "rl2-run"
    result = CliRunner().invoke(app, ["train", "rl2", "--steps", "8192", "--out", str(out), "--worker", "0,1,1,1",
                                      "--worker", "1,1,1,0"])
    assert result.exit_code == 0, result.output
    assert {p.name for p in out.iterdir()} >= {"agent.py", "README.md", CHECKPOINT, METRICS, "training_curve.png"}
    from matplotlib.image import imread

    assert imread(out / "training_curve.png").shape[2] in (3, 4)
    assert "--worker 0,1,1,1 --worker 1,1,1,0" in (out / "README.md").read_text()
    results, _ = evaluate(EvalConfig(agent_path=out / "agent.py", out=tmp_path / "r.json", seeds=(0,), pairs=(0,)))
    assert len(results["units"]) == 1 and results["agent"]["name"] == "rl2-run"
    unknown = CliRunner().invoke(app, ["train", "dqn", "--steps", "10", "--out", str(tmp_path / "m")])
    assert unknown.exit_code == 2 and "dqn" in unknown.output and "only rl2" in " ".join(unknown.output.split())


def test_training_curves_skip_updates_without_a_finished_episode() -> None:
    """Early updates log NaN for episode 10 (no pair has reached it yet); the curve starts when one has."""
    import math

    from mewa_bench.reports.training_curves import smoothed

    curve = smoothed([math.nan, 0.5, 0.7, math.nan, 0.9], window=2)
    assert math.isnan(curve[0]) and curve[1:] == [0.5, 0.6, 0.7, 0.9]
