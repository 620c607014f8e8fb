"""PEARL: deterministic training, metrics and checkpoints written as they come, resume, the
posterior as a product of Gaussians (checked against sequential Bayesian updates), the replay's
context prefixes, the temperature moving towards its target, the evaluation agent's posterior
sampling and reset per pair, the train command's submission played under the evaluation protocol,
and the learning test: on the narrow-v1 meta-train distribution it beats the random task-specific
baseline, judged with the exact engine."""

from __future__ import annotations

import csv
import itertools
from pathlib import Path

import numpy as np
import pytest
import torch

from mewa_bench.agents.pearl import (CHECKPOINT, CONTEXT_SIZE, METRICS, PairReplay, PEARLAgent, kl_to_prior,
                                     make_model, make_optimizers, sac_update, settings_from, train)
from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.runner import evaluate

TWO_WORKERS = [[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 0.0]]


def tiny(**kw):
    """3 rounds of 8 envs x 32 steps and 2 gradient steps each on the two-worker canonical task."""
    return settings_from({"num_envs": 8, "num_steps": 32, "gradient_steps": 2, "total_steps": 3 * 8 * 32,
                          "learning_starts": 0, "hidden": 16, "encoder_hidden": 16, "meta_batch": 4, "batch_size": 8,
                          "context_size": 8, "buffer_pairs": 80, "checkpoint_every": 1, "workers": TWO_WORKERS, **kw})


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
    assert all(np.isfinite(float(r["q_loss"])) and float(r["alpha"]) > 0 for r in metrics)
    other = torch.load(train(tiny(seed=2), tmp_path / "c"), weights_only=False)
    assert not all(torch.equal(a["model"][k], other["model"][k]) for k in a["model"])
    with pytest.raises(ValueError, match="buffer_pairs=20 must be at least 10 x num_envs"):
        train(tiny(buffer_pairs=20), tmp_path / "d")


def test_resume_continues_from_the_last_checkpoint(tmp_path: Path) -> None:
    out = tmp_path / "run"
    train(tiny(), out)
    with (out / METRICS).open("a") as f:  # a round that finished after the last checkpoint: redone on resume
        f.write("4,1024,0.1,nan,nan,0.0,0.0,1.0,1.0,0.0\r\n")
    train(tiny(total_steps=5 * 8 * 32), out, resume=True)
    assert [int(r["update"]) for r in rows(out / METRICS)] == [1, 2, 3, 4, 5]
    assert torch.load(out / CHECKPOINT, weights_only=False)["update"] == 5


def test_the_posterior_is_the_prior_times_the_context_factors() -> None:
    """Against Bayes' rule applied one factor at a time (1-D Gaussians per latent dimension)."""
    model = make_model(tiny(latent=3))
    context = torch.randn(2, 5, CONTEXT_SIZE, generator=torch.Generator().manual_seed(0))
    mask = torch.tensor([[1.0, 1.0, 0.0, 1.0, 0.0], [0.0] * 5])
    with torch.no_grad():
        mean, var = model.posterior(context, mask)
        out = model.encoder(context)
    factor_mean, factor_var = out[..., :3], torch.nn.functional.softplus(out[..., 3:])
    m, v = np.zeros(3), np.ones(3)  # the prior
    for i in (0, 1, 3):
        fm, fv = factor_mean[0, i].numpy().astype(float), factor_var[0, i].numpy().astype(float)
        m, v = (m * fv + fm * v) / (v + fv), v * fv / (v + fv)
    assert mean[0].tolist() == pytest.approx(m.tolist(), rel=1e-4, abs=1e-6)
    assert var[0].tolist() == pytest.approx(v.tolist(), rel=1e-4)
    assert mean[1].tolist() == [0.0, 0.0, 0.0] and var[1].tolist() == [1.0, 1.0, 1.0]  # no context: the prior
    reference = torch.distributions.kl_divergence(torch.distributions.Normal(mean[0], var[0].sqrt()),
                                                  torch.distributions.Normal(0.0, 1.0)).sum()
    assert float(kl_to_prior(mean, var)[0]) == pytest.approx(float(reference), rel=1e-5)


def test_contexts_come_from_the_pairs_earlier_episodes() -> None:
    """A context drawn with a prefix holds only that prefix's transitions, at most `size`, no repeats."""
    replay = PairReplay(pairs=2, capacity=50, episodes=3)
    slots = replay.new_slots(2)
    rng = np.random.default_rng(0)
    for t in range(30):
        obs = np.full((2, 18), t % 256)  # the step index, to recognise transitions
        replay.add(slots, obs, np.array([0, 1]), np.array([-1.0, -0.5]), obs, np.array([t in (9, 19, 29)] * 2))
    assert replay.episode_ends[slots[0]].tolist() == [10, 20, 30]
    context, mask = replay.context(slots, np.array([10, 20]), size=6, rng=rng)
    steps = (context[..., 0] * 8.0).round().int()  # the observation's first float, unscaled
    assert mask.sum(dim=1).tolist() == [6.0, 6.0]
    assert steps[0].max() < 10 and steps[1].max() < 20
    assert all(len(set(row.tolist())) == 6 for row in steps)
    context, mask = replay.context(slots, np.array([0, 4]), size=6, rng=rng)
    assert mask.sum(dim=1).tolist() == [0.0, 4.0]


def test_the_temperature_falls_while_the_policy_is_more_random_than_its_target() -> None:
    from mewa_bench.agents.training_io import make_meta_env

    settings = tiny()
    model, generator, rng = make_model(settings), torch.Generator().manual_seed(0), np.random.default_rng(0)
    optimizers = make_optimizers(model, settings)
    replay = PairReplay(8, 1000, settings.episodes)
    env = make_meta_env(settings.suite, 8, settings.episodes, settings.workers)
    obs, _ = env.reset(seed=0)
    slots = replay.new_slots(8)
    for _ in range(100):
        action = rng.integers(0, 4, 8)
        following, reward, _, _, info = env.step(action)
        replay.add(slots, obs[:, :18], action, reward, following[:, :18], info["inner_done"])
        obs = following
    alphas = [sac_update(model, optimizers, replay.sample(settings, rng), settings, generator)["alpha"]
              for _ in range(20)]
    assert alphas[0] == pytest.approx(settings.initial_alpha)  # the first policy is near uniform, above its target
    assert all(b < a for a, b in itertools.pairwise(alphas))


def test_the_agent_samples_z_per_episode_from_its_own_context_and_forgets_on_reset_task(tmp_path: Path) -> None:
    from mewa_bench.design.suites import load_suite
    from mewa_bench.envs import MewaEnv
    from mewa_bench.protocol.agent import Transition

    task = load_suite("narrow-v1").tasks[0]
    agent = PEARLAgent(train(tiny(), tmp_path / "run"), seed=3)
    env = MewaEnv(task=task)

    lane = agent.vector_agent  # the one-lane agent plays lane 0 of a PEARLVectorAgent

    def pair() -> list[torch.Tensor]:
        zs = [lane.z[0].clone()]
        for k in range(3):
            obs, _ = env.reset(options={"task": task, "worker": tuple(TWO_WORKERS[1]), "luck_key": k})
            done = False
            while not done:
                action = agent.act(obs)
                following, reward, terminated, truncated, _ = env.step(action)
                agent.observe(Transition(obs, action, reward, following, terminated, truncated))
                obs, done = following, terminated or truncated
            agent.end_episode()
            zs.append(lane.z[0].clone())
        return zs

    agent.reset_task()  # as the runner does before a pair's first episode
    first = pair()
    assert lane.steps.count[0] > 0 and not torch.equal(first[0], first[1])
    agent.reset_task()
    assert lane.steps.count[0] == 0 and torch.equal(lane.z[0], first[0])  # the prior draw of the same seed
    assert all(torch.equal(a, b) for a, b in zip(pair(), first))


def test_the_train_command_makes_a_submission_that_plays_under_the_protocol(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    out = tmp_path / "pearl-run"
    result = CliRunner().invoke(app, ["train", "pearl", "--steps", "4096", "--out", str(out), "--worker", "0,1,1,1",
                                      "--worker", "1,1,1,0"])
    assert result.exit_code == 0, result.output
    assert {p.name for p in out.iterdir()} >= {"agent.py", "README.md", CHECKPOINT, METRICS, "training_curve.png"}
    assert "mewa-bench train pearl" in (out / "README.md").read_text()
    config = {"agent_path": out / "agent.py", "seeds": (0, 1, 2), "pairs": (0, 1)}
    results, _ = evaluate(EvalConfig(out=tmp_path / "r.json", **config))
    assert len(results["units"]) == 6 and all(len(u["returns"]) == 10 for u in results["units"])
    assert results["agent"]["name"] == "pearl-run"
    again, _ = evaluate(EvalConfig(out=tmp_path / "r2.json", lanes=1, **config))
    assert [u["returns"] for u in again["units"]] == [u["returns"] for u in results["units"]]


def play_pairs(agent: PEARLAgent, task, workers: np.ndarray, seeds: int) -> np.ndarray:
    """Normalised returns [worker, seed, episode] under the protocol's loop (10 episodes per pair, the
    agent reset per pair, luck keys fixed by worker, seed and episode)."""
    from mewa_bench.envs import MewaEnv
    from mewa_bench.protocol.agent import Transition

    env = MewaEnv(task=task)
    out = np.zeros((len(workers), seeds, 10))
    for i, worker in enumerate(workers):
        for seed in range(seeds):
            agent.reset_task(seed=seed)
            for k in range(10):
                obs, _ = env.reset(options={"task": task, "worker": tuple(worker),
                                            "luck_key": (i * 1000 + seed) * 10 + k})
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
def test_pearl_beats_random_task_specific_on_its_training_distribution(tmp_path: Path) -> None:
    """The learning test: 600 k steps on narrow-v1's meta-train workers (about 2-3 min on one
    core); on 100 fresh workers from that distribution (4 seeds x 10 episodes each) the agent's mean
    score (normalised return / the worker's max-expected baseline) is above the random task-specific
    baseline's exact one, the 95% interval over workers clear of it."""
    from mewa_bench.design.exact import expected_returns
    from mewa_bench.design.policies import RandomTaskSpecific, toptimal_family
    from mewa_bench.design.suites import load_suite
    from mewa_bench.envs.pairs import PairSource

    suite = load_suite("narrow-v1")
    task = suite.tasks[0]
    checkpoint = train(settings_from({"total_steps": 600_000, "seed": 1, "checkpoint_every": 1000}), tmp_path / "run")
    _, workers = PairSource.build(None, None, suite.tasks).sample(np.random.default_rng(12345), 100)
    best = expected_returns(task, toptimal_family(task.N), workers).max(axis=0)
    rts = expected_returns(task, [RandomTaskSpecific()], workers)[0]
    gain = play_pairs(PEARLAgent(checkpoint, seed=0), task, workers, seeds=4).mean(axis=(1, 2)) / best - rts / best
    half = 1.96 * gain.std(ddof=1) / np.sqrt(len(gain))
    assert gain.mean() - half > 0, (gain.mean(), half)
