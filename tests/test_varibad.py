"""VariBAD: the ELBO's pieces by hand, whole meta-episodes kept for the VAE, the policy's
loss kept out of the encoder, deterministic training with metrics and checkpoints written as they
come, resume, the checkpoint played under the evaluation protocol, the train command, and the
learning test on two opposite workers judged with the exact engine."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from mewa_bench.agents.varibad import (CHECKPOINT, METRICS, EpisodeBuffer, Settings, VariBADAgent, gaussian_kl,
                                       kl_chain, make_model, ppo_update, settings_from, train, transitions, vae_loss,
                                       vae_update)
from mewa_bench.envs import MetaEpisodeVectorEnv
from mewa_bench.envs.meta_episode import meta_observation
from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.runner import evaluate

TWO_WORKERS = [[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 0.0]]
AGENT = Path(__file__).parent / "agents" / "varibad_checkpoint_agent.py"


def tiny(**kw) -> Settings:
    """3 updates of 8 envs x 64 steps on the two-worker canonical task (small networks; the VAE starts
    once a meta-episode has ended)."""
    return settings_from({"num_envs": 8, "num_steps": 64, "total_steps": 3 * 8 * 64, "episodes": 2,
                          "encoder_hidden": 16, "decoder_hidden": 16, "policy_hidden": 16, "vae_batch": 4,
                          "checkpoint_every": 1, "workers": TWO_WORKERS, **kw})


def rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


# ---------------------------------------------------------------------------------------------- the ELBO


def test_gaussian_kl_by_hand() -> None:
    mu_q, logvar_q = torch.tensor([1.0, 0.0]), torch.tensor([0.5, 0.0])
    zero = torch.zeros(2)
    # KL(N(1, e^0.5) || N(0, 1)) = 0.5 (e^0.5 + 1 - 1 - 0.5); the second dimension is N(0, 1) itself
    assert gaussian_kl(mu_q, logvar_q, zero, zero).item() == pytest.approx(0.5 * (math.exp(0.5) - 0.5))
    mu_p, logvar_p = torch.tensor([0.2, -1.0]), torch.tensor([-0.3, 0.7])
    q = torch.distributions.Normal(mu_q, (0.5 * logvar_q).exp())
    p = torch.distributions.Normal(mu_p, (0.5 * logvar_p).exp())
    assert gaussian_kl(mu_q, logvar_q, mu_p, logvar_p).item() == pytest.approx(
        torch.distributions.kl_divergence(q, p).sum().item(), rel=1e-6)


def test_kl_chain_compares_each_posterior_with_the_one_before() -> None:
    mu = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [1.0, 2.0]]])
    logvar = torch.zeros(1, 4, 2)
    # q_0 = prior: 0; a unit shift of the mean under unit variance: 0.5; no change: 0; a shift of 2: 2
    assert kl_chain(mu, logvar)[0].tolist() == pytest.approx([0.0, 0.5, 0.0, 2.0])


def meta_episode() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A hand-made meta-episode of 3 steps (the 2nd step ends an inner episode) padded to 4."""
    s0, s1, s2, s3 = (np.full(18, v, dtype=np.float32) for v in (0.0, 1.0, 5.0, 3.0))
    obs = np.stack([meta_observation(s0, -1, 0.0, 0.0), meta_observation(s1, 2, -0.5, 0.0),
                    meta_observation(s2, 1, -0.25, 1.0),  # a new inner episode starts: s2 is a reset, not the result
                    meta_observation(s3, 0, -1.0, 0.0), np.zeros(24, dtype=np.float32)])
    return torch.as_tensor(obs)[None], torch.tensor([[2, 1, 0, 0]]), torch.tensor([3])


def test_transitions_are_decoded_within_inner_episodes_only() -> None:
    obs, _, lengths = meta_episode()
    state, targets, mask = transitions(obs, lengths)
    assert state[0, :, 0].tolist() == [0.0, 1.0, 5.0, 3.0]
    assert targets[0, 0].tolist() == [1.0] * 18 + [-0.5]  # the change of each float, then the reward
    assert targets[0, 2].tolist() == [-2.0] * 18 + [-1.0]
    assert mask[0].tolist() == [True, False, True, False]  # the reset and the padding are not decoded


def test_vae_loss_by_hand_on_a_tiny_case() -> None:
    """A decoder that always predicts c and an encoder whose posterior is a constant N(m, e^v)."""
    obs, actions, lengths = meta_episode()
    model = make_model(settings_from({"latent": 2, "encoder_hidden": 8, "decoder_hidden": 8}))
    with torch.no_grad():
        last = model.decoder[-1]
        last.weight.zero_()
        last.bias.copy_(torch.cat([torch.full((18,), 0.5), torch.tensor([-0.5])]))
        for head, value in ((model.mu, torch.tensor([1.0, -1.0])), (model.logvar, torch.tensor([0.0, math.log(2.0)]))):
            head.weight.zero_()
            head.bias.copy_(value)
    generator = torch.Generator().manual_seed(0)
    reconstruction, kl = vae_loss(model, obs, actions, lengths, elbo_times=3, decodes=0, generator=generator)
    # step 0: targets 1.0 (x18) and -0.5; step 2: -2.0 (x18) and -1.0; step 1 crosses into a new episode
    by_hand = 0.5 * (18 * 0.5 ** 2 + 0.0) + 0.5 * (18 * 2.5 ** 2 + 0.5 ** 2)
    assert reconstruction.item() == pytest.approx(by_hand)
    # only q_0 differs from what came before: KL(N((1,-1), diag(1,2)) || N(0, I)) = 0.5 ((1 + 1 - 1 - 0) +
    # (2 + 1 - 1 - log 2)), averaged over the 4 posteriors of the meta-episode (the first, then one per step)
    assert kl.item() == pytest.approx(0.5 * (3.0 - math.log(2.0)) / 4, rel=1e-6)
    sampled, _ = vae_loss(model, obs, actions, lengths, elbo_times=3, decodes=20_000, generator=generator)
    assert sampled.item() == pytest.approx(by_hand, rel=0.05)  # the sum over transitions estimated from draws


# ---------------------------------------------------------------------------------------------- mechanics


def test_the_buffer_keeps_whole_meta_episodes_as_the_env_played_them() -> None:
    from mewa_bench.design.suites import load_suite

    env = MetaEpisodeVectorEnv(num_envs=3, episodes=2, task=load_suite("narrow-v1").tasks[0], workers=TWO_WORKERS)
    buffer = EpisodeBuffer(capacity=50, num_envs=3, max_steps=200)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    live = np.ones(3, dtype=bool)
    played: list[list[np.ndarray]] = [[], [], []]  # each env's meta-episode under way: obs, action, obs, ...
    finished = []
    for _ in range(150):
        actions = rng.integers(0, 4, size=3)
        following, _, terminated, truncated, _ = env.step(actions)
        done = terminated | truncated
        buffer.record(obs, actions, following, done, live)
        for i in np.flatnonzero(live):
            played[i] += [obs[i], actions[i]]
            if done[i]:
                finished.append(played[i] + [following[i]])
                played[i] = []
        live = ~done  # the step after an end is an autoreset step: its action is ignored
        obs = following
    assert buffer.size == len(finished) >= 3
    for k, episode in enumerate(finished):
        n = (len(episode) - 1) // 2
        assert buffer.lengths[k] == n
        assert np.array_equal(buffer.obs[k, :n + 1], np.stack(episode[0::2]))
        assert buffer.actions[k, :n].tolist() == [int(a) for a in episode[1::2]]
        assert buffer.obs[k, 0, 18:].tolist() == [0.0] * 6  # a pair's first observation: no previous action
        assert buffer.obs[k, :n + 1, 23].sum() == 1.0  # 2 inner episodes: one new-episode flag


def test_the_policy_loss_never_reaches_the_encoder() -> None:
    settings = settings_from({"latent": 2, "encoder_hidden": 8, "decoder_hidden": 8, "policy_hidden": 8})
    model = make_model(settings)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    generator = torch.Generator().manual_seed(0)
    t, n = 6, 4
    buf = {"actions": torch.randint(0, 4, (t, n), generator=generator).float(), "logprobs": torch.full((t, n), -1.4),
           "valid": torch.ones(t, n)}
    inputs = torch.rand(t, n, 18 + 4, generator=generator)
    optimizer = torch.optim.Adam(model.policy_parameters())
    ppo_update(model, optimizer, settings, inputs, buf, torch.randn(t, n, generator=generator), torch.rand(t, n),
               generator)
    changed = {k.split(".")[0] for k, v in model.state_dict().items() if not torch.equal(v, before[k])}
    assert changed == {"trunk", "actor", "critic"}
    obs, actions, lengths = meta_episode()
    episodes = EpisodeBuffer(capacity=1, num_envs=1, max_steps=3)
    episodes.obs[0], episodes.actions[0, :3], episodes.lengths[0], episodes.size = obs[0, :4].numpy(), [2, 1, 0], 3, 1
    moved = {k: v.clone() for k, v in model.state_dict().items()}
    vae_update(model, torch.optim.Adam(model.vae_parameters()), settings, episodes, generator)
    changed = {k.split(".")[0] for k, v in model.state_dict().items() if not torch.equal(v, moved[k])}
    assert changed == {"embed", "gru", "mu", "logvar", "decoder"}


def test_the_policy_sees_the_belief_normalised_by_recent_statistics() -> None:
    model = make_model(settings_from({"latent": 1, "encoder_hidden": 4, "decoder_hidden": 4, "policy_hidden": 4}))
    model.track_belief(torch.tensor([[1.0, -4.0], [3.0, -6.0]]), memory=100)  # from the start (N(0, 1) weighing 1e-4)
    assert model.belief_mean.tolist() == pytest.approx([2.0, -5.0], abs=5e-3)
    assert model.belief_var.tolist() == pytest.approx([1.0, 1.0], abs=5e-3)
    model.track_belief(torch.tensor([[5.0, -8.0], [7.0, -10.0]]), memory=100)  # all four: mean 4, variance 5
    assert model.belief_mean.tolist() == pytest.approx([4.0, -7.0], abs=5e-3)
    assert model.belief_var.tolist() == pytest.approx([5.0, 5.0], abs=5e-3)
    model.track_belief(torch.tensor([[4.0, -7.0]] * 8), memory=2)  # the past weighs as 2 beliefs: 2/10 of it
    assert model.belief_var.tolist() == pytest.approx([1.0, 1.0], abs=5e-3)
    # the policy depends on the belief only relative to those statistics: shifting both changes nothing
    state, mu, logvar = torch.rand(3, 18), torch.randn(3, 1), torch.randn(3, 1)
    logits, value = model.act(state, mu, logvar)
    with torch.no_grad():
        model.belief_mean += torch.tensor([0.5, -2.0])
    shifted_logits, shifted_value = model.act(state, mu + 0.5, logvar - 2.0)
    assert torch.allclose(logits, shifted_logits, atol=1e-6) and torch.allclose(value, shifted_value, atol=1e-6)


def test_training_is_deterministic_and_writes_as_it_goes(tmp_path: Path) -> None:
    seen = []
    first = train(tiny(), tmp_path / "a", progress=lambda steps, total, row: seen.append(
        (steps, total, len(rows(tmp_path / "a" / METRICS)))))
    assert seen == [(512, 1536, 1), (1024, 1536, 2), (1536, 1536, 3)]  # each row on disk when reported
    again = train(tiny(), tmp_path / "b")
    a, b = torch.load(first, weights_only=False), torch.load(again, weights_only=False)
    assert a["update"] == b["update"] == 3
    assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"])
    metrics = rows(tmp_path / "a" / METRICS)
    assert [int(r["update"]) for r in metrics] == [1, 2, 3]
    assert all(np.isfinite(float(r["policy_loss"])) and float(r["entropy"]) > 0 for r in metrics)
    assert np.isfinite(float(metrics[-1]["vae_reconstruction"])) and float(metrics[-1]["vae_kl"]) >= 0
    other = torch.load(train(tiny(seed=2), tmp_path / "c"), weights_only=False)
    assert not all(torch.equal(a["model"][k], other["model"][k]) for k in a["model"])


def test_resume_continues_from_the_last_checkpoint(tmp_path: Path) -> None:
    out = tmp_path / "run"
    train(tiny(), out)
    with (out / METRICS).open("a") as f:  # an update that finished after the last checkpoint: redone on resume
        f.write("4,2048,0.1,nan,nan,0.0,0.0,1.0,nan,nan\r\n")
    train(tiny(total_steps=5 * 8 * 64), out, resume=True)
    assert [int(r["update"]) for r in rows(out / METRICS)] == [1, 2, 3, 4, 5]
    state = torch.load(out / CHECKPOINT, weights_only=False)
    assert state["update"] == 5 and state["settings"]["total_steps"] == 5 * 8 * 64


def test_a_checkpoint_plays_under_the_evaluation_protocol(tmp_path: Path) -> None:
    checkpoint = train(tiny(), tmp_path / "run")
    config = EvalConfig(agent_path=AGENT, out=tmp_path / "r.json", seeds=(0, 1, 2), pairs=(0, 1),
                        checkpoint=str(checkpoint))
    results, _ = evaluate(config)
    assert len(results["units"]) == 6 and all(len(u["returns"]) == 10 for u in results["units"])
    again, _ = evaluate(EvalConfig(agent_path=AGENT, out=tmp_path / "r2.json", seeds=(0, 1, 2), pairs=(0, 1),
                                   checkpoint=str(checkpoint), lanes=1))
    assert [u["returns"] for u in again["units"]] == [u["returns"] for u in results["units"]]


def test_the_train_command_makes_a_submission_folder(tmp_path: Path) -> None:
    from matplotlib.image import imread
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    out = tmp_path / "varibad-run"
    result = CliRunner().invoke(app, ["train", "varibad", "--suite", "narrow-v1", "--steps", "16384", "--out", str(out),
                                      "--worker", "0,1,1,1", "--worker", "1,1,1,0", "--rerun"])
    assert result.exit_code == 0, result.output
    assert {p.name for p in out.iterdir()} >= {"agent.py", "README.md", CHECKPOINT, METRICS, "training_curve.png",
                                               "metrics.rrd"}
    steps, entropy = zip(*rrd_scalars(out / "metrics.rrd", "/train/entropy"))
    written = rows(out / METRICS)
    assert list(steps) == [int(r["env_steps"]) for r in written] == [8192, 16384]
    assert list(entropy) == pytest.approx([float(r["entropy"]) for r in written])
    assert imread(out / "training_curve.png").shape[2] in (3, 4)
    assert "mewa-bench train varibad --suite narrow-v1 --seed 1 --steps 16384" in (out / "README.md").read_text()
    assert "VariBADVectorAgent" in (out / "agent.py").read_text()
    results, _ = evaluate(EvalConfig(agent_path=out / "agent.py", out=tmp_path / "r.json", seeds=(0,), pairs=(0,)))
    assert len(results["units"]) == 1 and results["agent"]["name"] == "varibad-run"
    unknown = CliRunner().invoke(app, ["train", "dqn", "--steps", "10", "--out", str(tmp_path / "m")])
    assert unknown.exit_code == 2 and "'dqn'" in unknown.output and "varibad" in unknown.output


def rrd_scalars(path: Path, entity: str) -> list[tuple[int, float]]:
    """(env_steps, value) of the scalars logged to one entity of a training .rrd, in step order."""
    from rerun.chunk import RrdReader

    found = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity and not chunk.is_static:
            columns = chunk.to_record_batch().to_pydict()
            [values] = [v for k, v in columns.items() if k.endswith("Scalars:scalars")]
            found += [(step, value[0]) for step, value in zip(columns["env_steps"], values)]
    return sorted(found)


# ---------------------------------------------------------------------------------------------- learning


def play_pairs(checkpoint: Path, task, workers: list[tuple[float, ...]], seeds: int) -> np.ndarray:
    """Normalised returns [worker, seed, episode] of the checkpoint under the protocol's loop (10 episodes
    per pair, the agent reset per pair, luck keys fixed by worker, seed and episode)."""
    from mewa_bench.envs import MewaEnv
    from mewa_bench.protocol.agent import Transition

    agent, env = VariBADAgent(checkpoint, seed=0), MewaEnv(task=task)
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


LEARNING = {"total_steps": 4_000_000, "num_envs": 128, "num_steps": 64, "update_epochs": 2, "num_minibatches": 2,
            "ent_coef": 0.003, "workers": TWO_WORKERS, "seed": 1, "checkpoint_every": 1000}


@pytest.mark.slow  # the full learning budget; the by-hand, determinism, resume and play tests run by default
def test_varibad_learns_to_adapt_to_two_opposite_workers(tmp_path: Path) -> None:
    """The learning test: greedy building is perfect for (0,1,1,1) and fails for (1,1,1,0), and
    the reverse for parallel building; trained on them, VariBAD improves from episode 1 to 10 and beats
    the best fixed t-optimal policy, judged with the exact engine."""
    from mewa_bench.design.exact import expected_returns
    from mewa_bench.design.policies import toptimal_family
    from mewa_bench.design.suites import load_suite

    canonical_task = load_suite("narrow-v1").tasks[0]  # the task the run trains on (settings.suite)
    workers = [tuple(w) for w in TWO_WORKERS]
    checkpoint = train(settings_from(LEARNING), tmp_path / "run")
    values = expected_returns(canonical_task, toptimal_family(canonical_task.N), np.array(workers))  # [P, W]
    best = values.max(axis=0)
    best_fixed = (values / best).mean(axis=1).max()  # the best single policy's mean score: 0.5 here
    scores = (play_pairs(checkpoint, canonical_task, workers, seeds=40) / best[:, None, None]).mean(axis=0)
    adaptability = scores[:, -1] - scores[:, 0]  # per seed
    half = 1.96 * adaptability.std(ddof=1) / np.sqrt(len(adaptability))
    assert adaptability.mean() - half > 0, (adaptability.mean(), half)
    gain = scores.mean(axis=1) - best_fixed
    assert gain.mean() - 1.96 * gain.std(ddof=1) / np.sqrt(len(gain)) > 0, gain.mean()
