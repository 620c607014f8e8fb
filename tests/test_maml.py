"""MAML: deterministic training, metrics and checkpoints written as they come, resume, the
inner step's advantages by hand, the evaluation agent adapting after each episode and resetting per
pair, the train command's submission played under the evaluation protocol, and the learning test:
on the narrow-v1 meta-train distribution it beats the random task-specific baseline, judged with the
exact engine."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch

from mewa_bench.agents.maml import CHECKPOINT, METRICS, MAMLAgent, episode_advantages, settings_from, train
from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.runner import evaluate

TWO_WORKERS = [[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 0.0]]


def tiny(**kw):
    """3 outer updates of 8 envs x 64 steps on the two-worker canonical task."""
    return settings_from({"num_envs": 8, "num_steps": 64, "total_steps": 3 * 8 * 64, "hidden": 16,
                          "checkpoint_every": 1, "workers": TWO_WORKERS, **kw})


def rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def test_training_is_deterministic_and_writes_as_it_goes(tmp_path: Path) -> None:
    a = torch.load(train(tiny(), tmp_path / "a"), weights_only=False)
    b = torch.load(train(tiny(), tmp_path / "b"), weights_only=False)
    assert a["update"] == b["update"] == 3
    assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"])
    metrics = rows(tmp_path / "a" / METRICS)
    assert [int(r["update"]) for r in metrics] == [1, 2, 3]
    assert all(np.isfinite(float(r["policy_loss"])) and float(r["entropy"]) > 0 for r in metrics)
    assert float(metrics[-1]["inner_lr"]) != pytest.approx(tiny().inner_lr, abs=1e-9)  # the step size is learned
    other = torch.load(train(tiny(seed=2), tmp_path / "c"), weights_only=False)
    assert not all(torch.equal(a["model"][k], other["model"][k]) for k in a["model"])


def test_resume_continues_from_the_last_checkpoint(tmp_path: Path) -> None:
    out = tmp_path / "run"
    train(tiny(), out)
    with (out / METRICS).open("a") as f:  # an update that finished after the last checkpoint: redone on resume
        f.write("4,2048,0.1,nan,nan,0.0,0.0,1.0,0.05\r\n")
    train(tiny(total_steps=5 * 8 * 64), out, resume=True)
    assert [int(r["update"]) for r in rows(out / METRICS)] == [1, 2, 3, 4, 5]
    assert torch.load(out / CHECKPOINT, weights_only=False)["update"] == 5


def test_episode_advantages_by_hand() -> None:
    """GAE with gamma = 1 inside each padded episode, nothing carried past its last step."""
    rewards = torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 0.0]])
    values = torch.tensor([[0.5, 1.0, 1.5], [2.0, 1.0, 9.0]])
    mask = torch.tensor([[1.0, 1.0, 1.0], [1.0, 1.0, 0.0]])  # the second episode is 2 steps long
    advantages = episode_advantages(rewards, values, mask, 0.5)
    d = [1.0 + 1.0 - 0.5, 2.0 + 1.5 - 1.0, 3.0 - 1.5]
    e = [4.0 + 1.0 - 2.0, 5.0 - 1.0]
    assert advantages[0].tolist() == pytest.approx([d[0] + 0.5 * d[1] + 0.25 * d[2], d[1] + 0.5 * d[2], d[2]])
    assert advantages[1].tolist() == pytest.approx([e[0] + 0.5 * e[1], e[1], 0.0])


def play_episode(agent: MAMLAgent, task, worker, luck_key: int) -> float:
    """One episode of the agent on a pair (scalar env, the protocol's calls); its normalised return."""
    from mewa_bench.envs import MewaEnv
    from mewa_bench.protocol.agent import Transition

    env = MewaEnv(task=task)
    obs, _ = env.reset(options={"task": task, "worker": tuple(worker), "luck_key": luck_key})
    done = False
    while not done:
        action = agent.act(obs)
        following, reward, terminated, truncated, info = env.step(action)
        agent.observe(Transition(obs, action, reward, following, terminated, truncated))
        obs, done = following, terminated or truncated
    agent.end_episode()
    return float(info["normalised_return"])


def test_the_agent_adapts_after_each_episode_and_forgets_on_reset_task(tmp_path: Path) -> None:
    from mewa_bench.design.suites import load_suite

    task = load_suite("narrow-v1").tasks[0]
    agent = MAMLAgent(train(tiny(hidden=32), tmp_path / "run"), seed=3)
    lane = agent.vector_agent  # the one-lane agent plays lane 0 of a MAMLVectorAgent: its parameters per lane
    theta_0 = [p.clone() for p in lane.params]
    first = [play_episode(agent, task, TWO_WORKERS[0], k) for k in range(3)]
    assert all(not torch.equal(a, b) for a, b in zip(theta_0, lane.params))  # adapted by its own episodes
    agent.reset_task()
    assert all(torch.equal(a, b) for a, b in zip(theta_0, lane.params))
    assert [play_episode(agent, task, TWO_WORKERS[0], k) for k in range(3)] == first  # same seed, same pair


def test_the_train_command_makes_a_submission_that_plays_under_the_protocol(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    out = tmp_path / "maml-run"
    result = CliRunner().invoke(app, ["train", "maml", "--steps", "16384", "--out", str(out), "--worker", "0,1,1,1",
                                      "--worker", "1,1,1,0"])
    assert result.exit_code == 0, result.output
    assert {p.name for p in out.iterdir()} >= {"agent.py", "README.md", CHECKPOINT, METRICS, "training_curve.png"}
    assert "mewa-bench train maml" in (out / "README.md").read_text()
    config = {"agent_path": out / "agent.py", "seeds": (0, 1, 2), "pairs": (0, 1)}
    results, _ = evaluate(EvalConfig(out=tmp_path / "r.json", **config))
    assert len(results["units"]) == 6 and all(len(u["returns"]) == 10 for u in results["units"])
    assert results["agent"]["name"] == "maml-run"
    again, _ = evaluate(EvalConfig(out=tmp_path / "r2.json", lanes=1, **config))
    assert [u["returns"] for u in again["units"]] == [u["returns"] for u in results["units"]]


def play_pairs(agent, task, workers: np.ndarray, seeds: int) -> np.ndarray:
    """Normalised returns [worker, seed, episode] under the protocol's loop (10 episodes per pair, the
    agent reset per pair, luck keys fixed by worker, seed and episode)."""
    out = np.zeros((len(workers), seeds, 10))
    for i, worker in enumerate(workers):
        for seed in range(seeds):
            agent.reset_task(seed=seed)
            for k in range(10):
                out[i, seed, k] = play_episode(agent, task, worker, (i * 1000 + seed) * 10 + k)
    return out


def beats_random_task_specific(agent, task, workers: np.ndarray, seeds: int) -> tuple[float, float]:
    """Mean over workers of the agent's score minus the exact random task-specific score (both relative
    to the worker's max-expected baseline), and its 95% half-width over workers."""
    from mewa_bench.design.exact import expected_returns
    from mewa_bench.design.policies import RandomTaskSpecific, toptimal_family

    best = expected_returns(task, toptimal_family(task.N), workers).max(axis=0)
    rts = expected_returns(task, [RandomTaskSpecific()], workers)[0]
    gain = play_pairs(agent, task, workers, seeds).mean(axis=(1, 2)) / best - rts / best
    return float(gain.mean()), float(1.96 * gain.std(ddof=1) / np.sqrt(len(gain)))


@pytest.mark.slow  # the full learning budget; the by-hand, determinism, resume and play tests run by default
def test_maml_beats_random_task_specific_on_its_training_distribution(tmp_path: Path) -> None:
    """The learning test: 1 M steps on narrow-v1's meta-train workers (about 2 min on one core);
    on 100 fresh workers from that distribution (4 seeds x 10 episodes each) the agent's mean score is
    above the random task-specific baseline's exact one, the 95% interval clear of it."""
    from mewa_bench.design.suites import load_suite
    from mewa_bench.envs.pairs import PairSource

    suite = load_suite("narrow-v1")
    checkpoint = train(settings_from({"total_steps": 1_000_000, "seed": 1, "checkpoint_every": 1000}),
                       tmp_path / "run")
    _, workers = PairSource.build(None, None, suite.tasks).sample(np.random.default_rng(12345), 100)
    gain, half = beats_random_task_specific(MAMLAgent(checkpoint, seed=0), suite.tasks[0], workers, seeds=4)
    assert gain - half > 0, (gain, half)
