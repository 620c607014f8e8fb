"""VariBAD (Zintgraf et al. 2020) on MEWA: a variational belief over the worker, and a policy acting on it.

One file, top to bottom (in the spirit of CleanRL): settings, the networks, the ELBO, rollouts on the
batched meta-episode env, the PPO and VAE updates, checkpoints, and `VariBADAgent`, which plays a
checkpoint under the evaluation protocol.

- Encoder: a GRU over `mewa/MEWA-Meta-v0`'s 24 floats (observation, previous action one-hot,
  previous reward, new-episode flag), carried across the 10 episodes of a pair, giving after each
  step a diagonal Gaussian posterior q(m | tau_:t) over a latent task embedding m (5 floats).
- Decoder: from (state, action, m) it predicts what the step does: the change of the 18 observation
  floats (the mistake flags and returned blocks are where the worker shows) and the reward. The
  ELBO of a meta-episode at time t decodes every transition of the whole meta-episode (past and
  future) from a sample of q(m | tau_:t), less KL(q_t || q_t-1) (q_-1 = N(0, I)); the VAE loss
  averages it over a few sampled times t and over all t for the KL. Transitions that cross into a
  new inner episode (the next state is a reset, not the action's result) are not decoded.
- VAE data: whole meta-episodes, kept in a buffer of the most recent ones (as the paper does, from
  older policies too).
- Policy and value: an MLP on (state, posterior mean, log-variance), trained with PPO; the belief is
  computed during the rollout without gradient, so the policy's loss never reaches the encoder. The
  policy sees the belief normalised by running statistics of recent beliefs: the posterior's scale
  drifts as the VAE learns (log-variances fall to about -10 while the worker shows in mean
  differences of about 0.1), which a tanh layer fed raw would barely see.
- Pairs, autoresets, the learning signal: as in `rl2` (a meta-train worker from each task's own
  distribution, or one of `workers`; autoreset steps masked; each inner episode's normalised
  return paid when it ends, see `rl2.learning_signal`).
- Deterministic for a given seed on one machine (torch's CPU kernels, one thread).

`mewa-bench train varibad` runs it (~33k env steps/s on one core on narrow-v1,
so 4 M steps in about 2 minutes; benchmarks/training.py). On a two-worker task
((0,1,1,1): greedy building is perfect; (1,1,1,0): only parallel building finishes) 4 M steps
(~3 min on one core) give adaptability +0.16 [0.13, 0.19] and +0.11 over the best fixed policy
(tests/test_varibad.py; seeds 2 and 3: +0.18 and +0.14/+0.14). The VAE needed its learning rate at
3e-3 and every transition decoded to form that belief within 4 M steps.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mewa_bench.agents.lanes import RecurrentLanes, truthy
from mewa_bench.agents.training_io import (CHECKPOINT, METRICS, append_metrics, episode_end_scores, load_for_play,
                                           make_meta_env, mean_or_nan, normalised_returns_paid, restore, resumed,
                                           save_checkpoint, settings_with, torch_module, torch_threads, workers_arg)
from mewa_bench.agents.training_io import write_submission as write_submission_files
from mewa_bench.protocol.agent import SingleLane
from mewa_bench.envs.meta_episode import META_OBS_SIZE, NEW_EPISODE, PREVIOUS_REWARD
from mewa_bench.game.palette import NUM_COLORS, OBS_SIZE

__all__ = ["CHECKPOINT", "METRICS", "Settings", "VariBADAgent", "VariBADVectorAgent", "settings_from", "train", "train_run",
           "workers_arg"]

OBS_SCALE = 8.0  # the 18 env floats are block counts up to about 8; the rest is already in [-1, 1]
STATE, META, ACTIONS = OBS_SIZE, META_OBS_SIZE, NUM_COLORS  # 18 env floats, 24 meta-episode floats, 4 actions


@dataclass
class Settings:
    """Everything a run depends on (saved in the checkpoint)."""

    suite: str = "narrow-v1"
    seed: int = 1
    total_steps: int = 4_000_000
    num_envs: int = 64
    num_steps: int = 128  # rollout length per env and PPO update
    episodes: int = 10  # inner episodes per pair
    latent: int = 5  # task embedding size
    encoder_hidden: int = 64
    decoder_hidden: int = 64
    policy_hidden: int = 64
    learning_rate: float = 7e-4  # policy and value
    vae_learning_rate: float = 3e-3  # encoder and decoder (1e-3: no belief of the two workers after 4 M steps)
    kl_weight: float = 0.1
    vae_buffer: int = 512  # meta-episodes kept for the VAE
    vae_batch: int = 16  # meta-episodes per VAE update
    vae_updates: int = 1  # VAE updates per PPO update
    elbo_times: int = 8  # posterior times t decoded per meta-episode and VAE update
    decodes: int = 0  # transitions decoded from each of them: all (0), or that many drawn at random
    gamma: float = 0.99
    gae_lambda: float = 0.95
    update_epochs: int = 4
    num_minibatches: int = 4
    clip_coef: float = 0.2
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    reward_scale: float = 0.1  # with step_rewards
    step_rewards: bool = False  # learn from the env's step rewards instead of episode normalised returns
    belief_memory: int = 10  # updates the running belief statistics mostly remember
    checkpoint_every: int = 20  # updates
    workers: list[list[float]] = field(default_factory=list)  # empty: the suite's meta-train distribution

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.num_steps


def _torch() -> Any:
    """The torch module (the train extra; the datasets extra brings it too)."""
    return torch_module("VariBAD (`mewa-bench train varibad` and its checkpoints)")


def make_model(settings: Settings) -> Any:
    """The networks: encoder (GRU -> posterior), decoder (state, action, latent -> step), policy and value."""
    torch = _torch()
    nn = torch.nn
    h_enc, h_dec, h_pol, d = settings.encoder_hidden, settings.decoder_hidden, settings.policy_hidden, settings.latent

    class VariBAD(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.embed = nn.Sequential(nn.Linear(META, 32), nn.ReLU())
            self.gru = nn.GRU(32, h_enc)
            self.mu = nn.Linear(h_enc, d)
            self.logvar = nn.Linear(h_enc, d)
            self.decoder = nn.Sequential(nn.Linear(STATE + ACTIONS + d, h_dec), nn.ReLU(),
                                         nn.Linear(h_dec, h_dec), nn.ReLU(), nn.Linear(h_dec, STATE + 1))
            self.trunk = nn.Sequential(nn.Linear(STATE + 2 * d, h_pol), nn.Tanh(), nn.Linear(h_pol, h_pol), nn.Tanh())
            self.actor = nn.Linear(h_pol, ACTIONS)
            self.critic = nn.Linear(h_pol, 1)
            # running mean and variance of the belief (mean, log-variance) the policy sees, which it sees
            # normalised: the posterior's scale drifts as the VAE learns (log-variances reach -10)
            self.register_buffer("belief_mean", torch.zeros(2 * d))
            self.register_buffer("belief_var", torch.ones(2 * d))
            self.register_buffer("belief_count", torch.tensor(1e-4))

        def encode_step(self, x: Any, h: Any, reset: Any) -> tuple[Any, Any, Any]:
            """One step for a batch: posterior mean, log-variance [B, D] and hidden [B, H] (zeroed where `reset`)."""
            h = h * (~reset).unsqueeze(1)
            out, h = self.gru(self.embed(scaled(x))[None], h[None])
            return self.mu(out[0]), self.logvar(out[0]), h[0]

        def encode(self, x: Any) -> tuple[Any, Any]:
            """Posteriors after every step of whole meta-episodes x [B, L+1, 24]: mean, log-variance [B, L+1, D]."""
            out, _ = self.gru(self.embed(scaled(x)).transpose(0, 1))
            out = out.transpose(0, 1)
            return self.mu(out), self.logvar(out)

        def decode(self, state: Any, action: Any, m: Any) -> Any:
            """Predicted [..., 19]: the change of the 18 observation floats and the reward."""
            one_hot = torch.nn.functional.one_hot(action, ACTIONS).to(state.dtype)
            return self.decoder(torch.cat([state / OBS_SCALE, one_hot, m], dim=-1))

        def act(self, state: Any, mu: Any, logvar: Any) -> tuple[Any, Any]:
            """Policy logits [B, 4] and value [B] on (state, normalised belief)."""
            belief = (torch.cat([mu, logvar], dim=-1) - self.belief_mean) / (self.belief_var + 1e-8).sqrt()
            z = self.trunk(torch.cat([state / OBS_SCALE, belief.clamp(-10.0, 10.0)], dim=-1))
            return self.actor(z), self.critic(z).squeeze(-1)

        def track_belief(self, beliefs: Any, memory: float) -> None:
            """Fold a batch of beliefs [N, 2D] into the running mean and variance (parallel Welford), the
            past weighing as at most `memory` beliefs, so that the statistics follow the VAE's drift."""
            n, mean, var = beliefs.shape[0], beliefs.mean(0), beliefs.var(0, unbiased=False)
            self.belief_count.clamp_(max=memory)
            total = self.belief_count + n
            delta = mean - self.belief_mean
            m2 = self.belief_var * self.belief_count + var * n + delta ** 2 * self.belief_count * n / total
            self.belief_mean += delta * n / total
            self.belief_var.copy_(m2 / total)
            self.belief_count.copy_(total)

        def vae_parameters(self) -> list[Any]:
            return [p for m in (self.embed, self.gru, self.mu, self.logvar, self.decoder) for p in m.parameters()]

        def policy_parameters(self) -> list[Any]:
            return [p for m in (self.trunk, self.actor, self.critic) for p in m.parameters()]

    def scaled(x: Any) -> Any:
        return torch.cat([x[..., :STATE] / OBS_SCALE, x[..., STATE:]], dim=-1)

    return VariBAD()


# ---------------------------------------------------------------------------------------------- the ELBO


def gaussian_kl(mu_q: Any, logvar_q: Any, mu_p: Any, logvar_p: Any) -> Any:
    """KL(N(mu_q, var_q) || N(mu_p, var_p)) of diagonal Gaussians, summed over the last dimension."""
    return 0.5 * (logvar_p - logvar_q + (logvar_q.exp() + (mu_q - mu_p) ** 2) / logvar_p.exp() - 1.0).sum(-1)


def kl_chain(mu: Any, logvar: Any) -> Any:
    """KL(q_t || q_t-1) for every t of [B, L+1, D] posteriors, q_-1 = N(0, I): [B, L+1]."""
    torch = _torch()

    prior_mu = torch.cat([torch.zeros_like(mu[:, :1]), mu[:, :-1]], dim=1)
    prior_logvar = torch.cat([torch.zeros_like(logvar[:, :1]), logvar[:, :-1]], dim=1)
    return gaussian_kl(mu, logvar, prior_mu, prior_logvar)


def transitions(obs: Any, lengths: Any) -> tuple[Any, Any, Any]:
    """What the decoder is asked for in meta-episodes obs [B, L+1, 24] with `lengths` [B] steps each:
    states [B, L, 18], targets [B, L, 19] (change of the observation, reward) and the mask [B, L] of
    the steps to decode (within the meta-episode and not crossing into a new inner episode)."""
    torch = _torch()

    state, following = obs[:, :-1, :STATE], obs[:, 1:]
    targets = torch.cat([following[..., :STATE] - state, following[..., PREVIOUS_REWARD:PREVIOUS_REWARD + 1]], dim=-1)
    inside = torch.arange(obs.shape[1] - 1)[None] < lengths[:, None]
    return state, targets, inside & (following[..., NEW_EPISODE] == 0)


def vae_loss(model: Any, obs: Any, actions: Any, lengths: Any, elbo_times: int, decodes: int,
             generator: Any) -> tuple[Any, Any]:
    """Negative ELBO of meta-episodes obs [B, L+1, 24], actions [B, L]: the reconstruction term (the
    meta-episode's transitions decoded from a posterior sample at `elbo_times` random times, summed
    over transitions, averaged over times; unit-variance Gaussian log-likelihood up to a constant) and
    the KL term (KL(q_t || q_t-1) averaged over the times of each meta-episode); each a batch mean.
    With `decodes` > 0 the sum over transitions is estimated from that many drawn uniformly (with
    replacement) from each meta-episode."""
    torch = _torch()

    b, d = obs.shape[0], model.mu.out_features
    mu, logvar = model.encode(obs)
    valid_t = torch.arange(obs.shape[1])[None] <= lengths[:, None]
    kl = (kl_chain(mu, logvar) * valid_t).sum(1) / valid_t.sum(1)
    times = (torch.rand(b, elbo_times, generator=generator) * (lengths[:, None] + 1)).long()  # in [0, length]
    rows = torch.arange(b)[:, None]
    eps = torch.randn(b, elbo_times, d, generator=generator)
    m = mu[rows, times] + (0.5 * logvar[rows, times]).exp() * eps  # [B, S, D]
    state, targets, mask = transitions(obs, lengths)
    weight = torch.ones(b)
    if decodes:
        picks = (torch.rand(b, decodes, generator=generator) * lengths[:, None]).long()
        state, targets, mask = state[rows, picks], targets[rows, picks], mask[rows, picks]
        actions = actions[rows, picks]
        weight = lengths / decodes
    steps = state.shape[1]
    predicted = model.decode(state[:, None].expand(-1, elbo_times, -1, -1),
                             actions[:, None].expand(-1, elbo_times, -1),
                             m[:, :, None].expand(-1, -1, steps, -1))  # [B, S, L, 19]
    error = 0.5 * ((predicted - targets[:, None]) ** 2).sum(-1)
    reconstruction = weight * (error * mask[:, None]).sum(-1).mean(1)
    return reconstruction.mean(), kl.mean()


# ---------------------------------------------------------------------------------------------- training


class EpisodeBuffer:
    """The most recent whole meta-episodes (observations and actions), for the VAE."""

    def __init__(self, capacity: int, num_envs: int, max_steps: int) -> None:
        self.obs = np.zeros((capacity, max_steps + 1, META), dtype=np.float32)
        self.actions = np.zeros((capacity, max_steps), dtype=np.int64)
        self.lengths = np.zeros(capacity, dtype=np.int64)
        self.size, self.next = 0, 0
        self.open_obs = np.zeros((num_envs, max_steps + 1, META), dtype=np.float32)  # meta-episodes under way
        self.open_actions = np.zeros((num_envs, max_steps), dtype=np.int64)
        self.open_len = np.zeros(num_envs, dtype=np.int64)

    def record(self, obs: np.ndarray, actions: np.ndarray, following: np.ndarray, done: np.ndarray,
               live: np.ndarray) -> None:
        """One env step: (obs, action) of the `live` sub-envs (not autoreset steps); meta-episodes that
        end (`done`) are closed with their last observation and stored."""
        envs = np.flatnonzero(live)
        self.open_obs[envs, self.open_len[envs]] = obs[envs]
        self.open_actions[envs, self.open_len[envs]] = actions[envs]
        self.open_len[envs] += 1
        for i in np.flatnonzero(done & live):
            n = self.open_len[i]
            slot = self.next
            self.obs[slot, :n] = self.open_obs[i, :n]
            self.obs[slot, n] = following[i]
            self.obs[slot, n + 1:] = 0.0
            self.actions[slot, :n] = self.open_actions[i, :n]
            self.lengths[slot] = n
            self.next, self.size = (slot + 1) % len(self.lengths), min(self.size + 1, len(self.lengths))
            self.open_len[i] = 0

    def sample(self, count: int, generator: Any) -> tuple[Any, Any, Any]:
        """`count` stored meta-episodes (with replacement), trimmed to the longest: obs, actions, lengths."""
        torch = _torch()

        picked = torch.randint(self.size, (count,), generator=generator).numpy()
        lengths = self.lengths[picked]
        longest = int(lengths.max())
        return (torch.as_tensor(self.obs[picked, :longest + 1]), torch.as_tensor(self.actions[picked, :longest]),
                torch.as_tensor(lengths))


def make_env(settings: Settings) -> Any:
    """The batched meta-episode env of a run."""
    return make_meta_env(settings.suite, settings.num_envs, settings.episodes, settings.workers)


@torch_threads(1)
def train(settings: Settings, out: Path, resume: bool = False,
          progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> Path:
    """Train (or resume) a run in `out`: checkpoints and metrics written as they come; the checkpoint path.

    A resumed run restarts its rollouts from the checkpoint's update (fresh env states, an empty VAE
    buffer and random streams derived from the seed and that update): deterministic, but not the
    bytes of an uninterrupted run."""
    torch = _torch()
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(settings.seed)
    state = resumed(out, settings, resume)
    model = make_model(settings)
    policy_optimizer = torch.optim.Adam(model.policy_parameters(), lr=settings.learning_rate, eps=1e-5)
    vae_optimizer = torch.optim.Adam(model.vae_parameters(), lr=settings.vae_learning_rate)
    start_update = 0 if state is None else restore(
        out, state, model, {"policy_optimizer": policy_optimizer, "vae_optimizer": vae_optimizer})
    generator = torch.Generator().manual_seed(settings.seed * 1_000_003 + start_update)
    env = make_env(settings)
    n, t_len, d = settings.num_envs, settings.num_steps, settings.latent
    history = EpisodeBuffer(settings.vae_buffer, n, settings.episodes * max(t.T for t in env.tasks))
    obs_np, _ = env.reset(seed=settings.seed + start_update)
    obs = torch.as_tensor(obs_np)
    h = torch.zeros(n, settings.encoder_hidden)
    reset = torch.ones(n, dtype=torch.bool)  # the first observation of a meta-episode (or an autoreset step)
    dummy = torch.zeros(n, dtype=torch.bool)  # this step is an autoreset step: its action is ignored
    updates = settings.total_steps // settings.steps_per_update
    for update in range(start_update, updates):
        began = time.perf_counter()
        buf = {k: torch.zeros(t_len, n) for k in ("actions", "logprobs", "values", "rewards", "dones", "valid")}
        buf_inputs = torch.zeros(t_len, n, STATE + 2 * d)  # what the policy saw: state, posterior mean, log-variance
        first_scores: list[float] = []
        last_scores: list[float] = []
        for t in range(t_len):
            with torch.no_grad():
                mu, logvar, h = model.encode_step(obs, h, reset)
                logits, value = model.act(obs[:, :STATE], mu, logvar)
                logp = torch.log_softmax(logits, dim=1)
                action = torch.multinomial(logp.exp(), 1, generator=generator).squeeze(1)
            next_obs, reward, terminated, truncated, info = env.step(action.numpy())
            done = terminated | truncated
            history.record(obs_np, action.numpy(), next_obs, done, ~dummy.numpy())
            buf_inputs[t] = torch.cat([obs[:, :STATE], mu, logvar], dim=1)
            buf["actions"][t], buf["values"][t] = action, value
            buf["logprobs"][t] = logp.gather(1, action[:, None])[:, 0]
            buf["rewards"][t] = torch.as_tensor(learning_signal(reward, info, settings), dtype=torch.float32)
            buf["dones"][t], buf["valid"][t] = torch.as_tensor(done).float(), (~dummy).float()
            first, last = episode_end_scores(info, settings.episodes)
            first_scores += first
            last_scores += last
            reset = torch.as_tensor(done) | dummy  # after an autoreset step comes a first observation
            dummy = torch.as_tensor(done)
            obs_np = next_obs
            obs = torch.as_tensor(next_obs)
        with torch.no_grad():
            mu, logvar, _ = model.encode_step(obs, h, reset)
            next_value = model.act(obs[:, :STATE], mu, logvar)[1]
        advantages, returns = gae(buf["rewards"], buf["values"], buf["dones"], next_value, settings)
        losses = ppo_update(model, policy_optimizer, settings, buf_inputs, buf, advantages, returns, generator)
        model.track_belief(buf_inputs.flatten(0, 1)[buf["valid"].flatten() > 0, STATE:],  # for the next rollout
                           memory=settings.belief_memory * settings.steps_per_update)
        losses.update(vae_update(model, vae_optimizer, settings, history, generator))
        steps = (update + 1) * settings.steps_per_update
        row = {"update": update + 1, "env_steps": steps, "seconds": round(time.perf_counter() - began, 3),
               "episode_1_normalised_return": mean_or_nan(first_scores),
               "episode_10_normalised_return": mean_or_nan(last_scores), **losses}
        append_metrics(out / METRICS, row)
        progress(steps, updates * settings.steps_per_update, row)
        if (update + 1) % settings.checkpoint_every == 0 or update + 1 == updates:
            save_checkpoint(out / CHECKPOINT, {
                "model": model.state_dict(), "policy_optimizer": policy_optimizer.state_dict(),
                "vae_optimizer": vae_optimizer.state_dict(), "settings": asdict(settings), "update": update + 1})
    return out / CHECKPOINT


def learning_signal(reward: np.ndarray, info: dict[str, Any], settings: Settings) -> np.ndarray:
    """What PPO maximises: each inner episode's normalised return paid when it ends (as `rl2`), or the
    scaled step rewards with `step_rewards=True`."""
    if settings.step_rewards:
        return reward * settings.reward_scale
    return normalised_returns_paid(reward, info)


def gae(rewards: Any, values: Any, dones: Any, next_value: Any, settings: Settings) -> tuple[Any, Any]:
    """Generalised advantage estimates and returns over a rollout [T, B] (no bootstrap across a done)."""
    torch = _torch()

    advantages = torch.zeros_like(rewards)
    last = torch.zeros_like(next_value)
    for t in reversed(range(rewards.shape[0])):
        following = next_value if t == rewards.shape[0] - 1 else values[t + 1]
        live = 1.0 - dones[t]
        delta = rewards[t] + settings.gamma * following * live - values[t]
        last = delta + settings.gamma * settings.gae_lambda * live * last
        advantages[t] = last
    return advantages, advantages + values


def ppo_update(model: Any, optimizer: Any, settings: Settings, inputs: Any, buf: dict[str, Any], advantages: Any,
               returns: Any, generator: Any) -> dict[str, float]:
    """PPO epochs over minibatches of steps (the policy sees the belief stored at rollout time, so no
    gradient reaches the encoder); autoreset steps are left out."""
    torch = _torch()

    keep = buf["valid"].flatten() > 0
    x = inputs.flatten(0, 1)[keep]
    actions, old_logprobs = buf["actions"].flatten()[keep].long(), buf["logprobs"].flatten()[keep]
    adv_all, ret_all = advantages.flatten()[keep], returns.flatten()[keep]
    d = settings.latent
    count = x.shape[0]
    per_batch = max(1, count // settings.num_minibatches)
    stats: dict[str, list[float]] = {"policy_loss": [], "value_loss": [], "entropy": []}
    for _ in range(settings.update_epochs):
        order = torch.randperm(count, generator=generator)
        for start in range(0, count - per_batch + 1, per_batch):
            idx = order[start:start + per_batch]
            logits, value = model.act(x[idx, :STATE], x[idx, STATE:STATE + d], x[idx, STATE + d:])
            logp = torch.log_softmax(logits, dim=1)
            adv = adv_all[idx]
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            ratio = (logp.gather(1, actions[idx, None])[:, 0] - old_logprobs[idx]).exp()
            clipped = ratio.clamp(1 - settings.clip_coef, 1 + settings.clip_coef)
            policy_loss = -torch.min(ratio * adv, clipped * adv).mean()
            value_loss = 0.5 * ((value - ret_all[idx]) ** 2).mean()
            entropy = -(logp.exp() * logp).sum(1).mean()
            loss = policy_loss + settings.vf_coef * value_loss - settings.ent_coef * entropy
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.policy_parameters(), settings.max_grad_norm)
            optimizer.step()
            for key, v in (("policy_loss", policy_loss), ("value_loss", value_loss), ("entropy", entropy)):
                stats[key].append(v.item())
    return {k: round(float(np.mean(v)), 6) for k, v in stats.items()}


def vae_update(model: Any, optimizer: Any, settings: Settings, episodes: EpisodeBuffer,
               generator: Any) -> dict[str, float]:
    """`vae_updates` steps on the negative ELBO of meta-episodes drawn from the buffer (none while it is empty)."""
    if episodes.size == 0:
        return {"vae_reconstruction": float("nan"), "vae_kl": float("nan")}
    stats: dict[str, list[float]] = {"vae_reconstruction": [], "vae_kl": []}
    for _ in range(settings.vae_updates):
        obs, actions, lengths = episodes.sample(settings.vae_batch, generator)
        reconstruction, kl = vae_loss(model, obs, actions, lengths, settings.elbo_times, settings.decodes, generator)
        optimizer.zero_grad()
        (reconstruction + settings.kl_weight * kl).backward()
        optimizer.step()
        stats["vae_reconstruction"].append(reconstruction.item())
        stats["vae_kl"].append(kl.item())
    return {k: round(float(np.mean(v)), 6) for k, v in stats.items()}


# ---------------------------------------------------------------------------------------------- evaluation


class VariBADVectorAgent(RecurrentLanes):
    """Plays a VariBAD checkpoint on many lanes at once under the evaluation protocol (SPEC section 6): per
    lane the encoder's hidden state (the belief) and the previous action, reward and new-episode flag
    are kept across the 10 episodes of a pair (`agents.lanes.RecurrentLanes`)."""

    def __init__(self, checkpoint: str | Path, num_lanes: int = 1, seed: int | str = 0,
                 greedy: bool | str = False) -> None:
        self.settings, self.model = load_for_play(checkpoint, Settings, make_model)
        super().__init__(self._forward, self.settings.encoder_hidden, int(num_lanes), int(seed), truthy(greedy))

    def _forward(self, x: Any, h: Any, reset: Any) -> tuple[Any, Any]:
        """The belief updated with this step's input, and the policy's logits on it."""
        mu, logvar, h = self.model.encode_step(x, h, reset)
        logits, _ = self.model.act(x[:, :STATE], mu, logvar)
        return logits, h


def VariBADAgent(checkpoint: str | Path, seed: int | str = 0, greedy: bool | str = False) -> SingleLane:
    """A one-lane VariBAD agent (the protocol's `Agent`): lane 0 of a `VariBADVectorAgent`."""
    return SingleLane(VariBADVectorAgent(checkpoint, 1, seed, greedy))


# ---------------------------------------------------------------------------------------------- runs


def settings_from(values: dict[str, Any], base: Settings | None = None) -> Settings:
    """Settings with some fields replaced (names checked)."""
    return settings_with(Settings, values, base, "VariBAD")


def write_submission(out: Path, command: str, settings: Settings) -> list[Path]:
    """Make the run folder a submission: agent.py (plays checkpoint.pt) and a README with the command."""
    return write_submission_files(out, command, settings, "varibad", "VariBAD", "VariBADVectorAgent",
                                  "VariBAD (a GRU encoder's posterior over a latent task embedding, trained as a VAE "
                                  "that decodes the meta-episode's transitions, and a policy on (state, belief) "
                                  "trained with PPO; `mewa_bench/agents/varibad.py`).")


def train_run(settings: Settings, folder: Path, resume: bool, command: str,
              progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> list[Path]:
    """Train one seed into `folder` and make it a submission; the files written."""
    checkpoint = train(settings, folder, resume, progress)
    return [checkpoint, folder / METRICS, *write_submission(folder, command, settings)]
