"""RL^2 (Duan et al. 2016, Wang et al. 2016) on MEWA: a recurrent policy trained with PPO on meta-episodes.

One file, top to bottom (in the spirit of CleanRL): settings, the network, rollouts on the batched
meta-episode env, the PPO update, checkpoints, and `RL2Agent`, which plays a checkpoint under the
evaluation protocol.

- Inputs: `mewa/MEWA-Meta-v0`'s 24 floats (the observation, the previous action one-hot, the
  previous reward, the new-episode flag); the GRU's hidden state is carried across the 10 episodes
  of a pair and reset when a new pair begins, so whatever the policy learns about the worker it
  learns in context.
- Pairs: each meta-episode draws a task of the suite and a meta-train worker from the task's own
  distribution (never a curated test worker), or one of `workers` when given.
- Autoresets: the batched env ends a meta-episode and starts the next on the following step, which
  ignores the action (`AutoresetMode.NEXT_STEP`); those steps are masked out of the loss, and the
  hidden state is zero on the first observation of every meta-episode, as when the agent is scored.
- Deterministic for a given seed on one machine (torch's CPU kernels, one thread).

- What it learns from: each inner episode's normalised return, paid when the episode ends
  (`learning_signal`; the raw step rewards are still in the observation). Discounted raw rewards,
  which are most negative right after a new episode starts, taught it to stall before the last
  sub-goal (0.745 with a mistake-free worker, against 0.907 for random play).

Learning test (tests/test_rl2.py): on a two-worker task ((0,1,1,1): greedy building is perfect;
(1,1,1,0): only parallel building finishes) 4 M steps (~2 min on one core, ~32k steps/s) give
adaptability +0.16 [0.14, 0.18] and +0.14 over the best fixed policy. Runs on the shipped suites:
`submissions/rl2-*`, compared with the paper in docs/baselines.md.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mewa_bench.agents.lanes import RecurrentLanes, truthy
from mewa_bench.agents.training_io import (CHECKPOINT, METRICS, append_metrics, episode_end_scores, load_for_play,
                                           make_meta_env, mean_or_nan, normalised_returns_paid, restore, resumed,
                                           save_checkpoint, settings_with, torch_module, torch_threads, workers_arg)
from mewa_bench.agents.training_io import write_submission as write_submission_files
from mewa_bench.protocol.agent import SingleLane

__all__ = ["CHECKPOINT", "METRICS", "RL2Agent", "RL2VectorAgent", "Settings", "gae", "settings_from", "train", "train_run",
           "workers_arg"]

OBS_SCALE = 8.0  # the 18 env floats are block counts up to about 8; the rest is already in [-1, 1]


@dataclass
class Settings:
    """Everything a run depends on (saved in the checkpoint)."""

    suite: str = "narrow-v1"
    seed: int = 1
    total_steps: int = 2_000_000
    num_envs: int = 64
    num_steps: int = 128  # rollout length per env and update (truncated backpropagation through time)
    episodes: int = 10  # inner episodes per pair
    hidden: int = 128
    learning_rate: float = 1e-3
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
    checkpoint_every: int = 20  # updates
    workers: list[list[float]] = field(default_factory=list)  # empty: the suite's meta-train distribution

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.num_steps


def _torch() -> Any:
    """The torch module (the train extra; the datasets extra brings it too)."""
    return torch_module("RL^2 (`mewa-bench train rl2` and its checkpoints)")


def make_policy(hidden: int) -> Any:
    """The network: encoder, GRU, actor and critic heads."""
    torch = _torch()
    nn = torch.nn

    class RL2Policy(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.encoder = nn.Sequential(nn.Linear(24, hidden), nn.Tanh())
            self.gru = nn.GRUCell(hidden, hidden)
            self.actor = nn.Linear(hidden, 4)
            self.critic = nn.Linear(hidden, 1)

        def step(self, obs: torch.Tensor, h: torch.Tensor, reset: torch.Tensor) -> tuple[torch.Tensor, ...]:
            """One step for a batch: logits [B, 4], value [B], next hidden [B, H] (h zeroed where `reset`)."""
            h = h * (~reset).unsqueeze(1)
            h = self.gru(self.encoder(scaled(obs)), h)
            return self.actor(h), self.critic(h).squeeze(1), h

    def scaled(obs: Any) -> Any:
        return torch.cat([obs[:, :18] / OBS_SCALE, obs[:, 18:]], dim=1)

    return RL2Policy()


def make_env(settings: Settings) -> Any:
    """The batched meta-episode env of a run."""
    return make_meta_env(settings.suite, settings.num_envs, settings.episodes, settings.workers)


@torch_threads(1)
def train(settings: Settings, out: Path, resume: bool = False,
          progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> Path:
    """Train (or resume) a run in `out`: checkpoints and metrics written as they come; the checkpoint path.

    A resumed run restarts its rollouts from the checkpoint's update (fresh env states and random
    streams derived from the seed and that update): deterministic, but not the bytes of an
    uninterrupted run."""
    torch = _torch()
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(settings.seed)
    state = resumed(out, settings, resume)
    policy = make_policy(settings.hidden)
    optimizer = torch.optim.Adam(policy.parameters(), lr=settings.learning_rate, eps=1e-5)
    start_update = 0 if state is None else restore(out, state, policy, {"optimizer": optimizer})
    generator = torch.Generator().manual_seed(settings.seed * 1_000_003 + start_update)
    env = make_env(settings)
    obs_np, _ = env.reset(seed=settings.seed + start_update)
    n, t_len = settings.num_envs, settings.num_steps
    obs = torch.as_tensor(obs_np)
    h = torch.zeros(n, settings.hidden)
    reset = torch.ones(n, dtype=torch.bool)  # the first observation of a meta-episode (or an autoreset step)
    dummy = torch.zeros(n, dtype=torch.bool)  # this step is an autoreset step: its action is ignored
    updates = settings.total_steps // settings.steps_per_update
    for update in range(start_update, updates):
        began = time.perf_counter()
        buf = {k: torch.zeros(t_len, n) for k in ("actions", "logprobs", "values", "rewards", "dones")}
        buf_obs = torch.zeros(t_len, n, 24)
        buf_reset = torch.zeros(t_len, n, dtype=torch.bool)
        buf_valid = torch.zeros(t_len, n, dtype=torch.bool)
        h0 = h.clone()
        first_scores: list[float] = []
        last_scores: list[float] = []
        for t in range(t_len):
            buf_obs[t], buf_reset[t], buf_valid[t] = obs, reset, ~dummy
            with torch.no_grad():
                logits, value, h = policy.step(obs, h, reset)
                dist = torch.distributions.Categorical(logits=logits)
                action = torch.multinomial(dist.probs, 1, generator=generator).squeeze(1)
            next_obs, reward, terminated, truncated, info = env.step(action.numpy())
            done = torch.as_tensor(terminated | truncated)
            buf["actions"][t], buf["logprobs"][t], buf["values"][t] = action, dist.log_prob(action), value
            buf["rewards"][t] = torch.as_tensor(learning_signal(reward, info, settings), dtype=torch.float32)
            buf["dones"][t] = done.float()
            first, last = episode_end_scores(info, settings.episodes)
            first_scores += first
            last_scores += last
            reset = done | dummy  # after an autoreset step comes a first observation
            dummy = done
            obs = torch.as_tensor(next_obs)
        with torch.no_grad():
            next_value = policy.step(obs, h, reset)[1]
        advantages, returns = gae(buf["rewards"], buf["values"], buf["dones"], next_value, settings)
        losses = ppo_update(policy, optimizer, settings, buf_obs, buf_reset, buf_valid, h0, buf, advantages, returns,
                            generator)
        steps = (update + 1) * settings.steps_per_update
        row = {"update": update + 1, "env_steps": steps, "seconds": round(time.perf_counter() - began, 3),
               "episode_1_normalised_return": mean_or_nan(first_scores),
               "episode_10_normalised_return": mean_or_nan(last_scores),
               **losses}
        append_metrics(out / METRICS, row)
        progress(steps, updates * settings.steps_per_update, row)
        if (update + 1) % settings.checkpoint_every == 0 or update + 1 == updates:
            save_checkpoint(out / CHECKPOINT, {"model": policy.state_dict(), "optimizer": optimizer.state_dict(),
                                               "settings": asdict(settings), "update": update + 1})
    return out / CHECKPOINT


def learning_signal(reward: np.ndarray, info: dict[str, Any], settings: Settings) -> np.ndarray:
    """What PPO maximises: by default each inner episode's normalised return, paid when it ends.

    The env's step rewards are negative and most negative right after a new episode starts, so a
    discounted sum of them pays the agent for stalling before the last sub-goal (the next episode's
    -1 rewards come later); the protocol scores each episode's normalised return instead, and paying
    exactly that at the episode's end has no such incentive. `step_rewards=True` uses the raw rewards.
    """
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


def ppo_update(policy: Any, optimizer: Any, settings: Settings, obs: Any, reset: Any, valid: Any, h0: Any,
               buf: dict[str, Any], advantages: Any, returns: Any, generator: Any) -> dict[str, float]:
    """PPO epochs over minibatches of whole env sequences (the GRU is replayed from each rollout's start)."""
    torch = _torch()

    n = obs.shape[1]
    per_batch = n // settings.num_minibatches
    stats: dict[str, list[float]] = {"policy_loss": [], "value_loss": [], "entropy": []}
    for _ in range(settings.update_epochs):
        order = torch.randperm(n, generator=generator)
        for start in range(0, n, per_batch):
            envs = order[start:start + per_batch]
            h = h0[envs]
            logits, values = [], []
            for t in range(obs.shape[0]):
                step_logits, step_value, h = policy.step(obs[t, envs], h, reset[t, envs])
                logits.append(step_logits)
                values.append(step_value)
            dist = torch.distributions.Categorical(logits=torch.stack(logits))
            new_value = torch.stack(values)
            mask = valid[:, envs].float()
            count = mask.sum().clamp(min=1.0)
            adv = advantages[:, envs]
            mean = (adv * mask).sum() / count
            std = (((adv - mean) ** 2 * mask).sum() / count).sqrt()
            adv = (adv - mean) / (std + 1e-8)
            ratio = (dist.log_prob(buf["actions"][:, envs]) - buf["logprobs"][:, envs]).exp()
            clipped = ratio.clamp(1 - settings.clip_coef, 1 + settings.clip_coef)
            policy_loss = -(torch.min(ratio * adv, clipped * adv) * mask).sum() / count
            value_loss = 0.5 * (((new_value - returns[:, envs]) ** 2) * mask).sum() / count
            entropy = (dist.entropy() * mask).sum() / count
            loss = policy_loss + settings.vf_coef * value_loss - settings.ent_coef * entropy
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), settings.max_grad_norm)
            optimizer.step()
            for key, value in (("policy_loss", policy_loss), ("value_loss", value_loss), ("entropy", entropy)):
                stats[key].append(value.item())
    return {k: round(float(np.mean(v)), 6) for k, v in stats.items()}


class RL2VectorAgent(RecurrentLanes):
    """Plays an RL^2 checkpoint on many lanes at once under the evaluation protocol (SPEC section 6): per
    lane the hidden state and the previous action, reward and new-episode flag are kept across the 10
    episodes of a pair (`agents.lanes.RecurrentLanes`); one forward pass per step for all lanes."""

    def __init__(self, checkpoint: str | Path, num_lanes: int = 1, seed: int | str = 0,
                 greedy: bool | str = False) -> None:
        self.settings, self.policy = load_for_play(checkpoint, Settings, lambda s: make_policy(s.hidden))
        super().__init__(self._forward, self.settings.hidden, int(num_lanes), int(seed), truthy(greedy))

    def _forward(self, x: Any, h: Any, reset: Any) -> tuple[Any, Any]:
        logits, _, h = self.policy.step(x, h, reset)
        return logits, h


def RL2Agent(checkpoint: str | Path, seed: int | str = 0, greedy: bool | str = False) -> SingleLane:
    """A one-lane RL^2 agent (the protocol's `Agent`): lane 0 of an `RL2VectorAgent`."""
    return SingleLane(RL2VectorAgent(checkpoint, 1, seed, greedy))


def settings_from(values: dict[str, Any], base: Settings | None = None) -> Settings:
    """Settings with some fields replaced (names checked)."""
    return settings_with(Settings, values, base, "RL^2")


def write_submission(out: Path, command: str, settings: Settings) -> list[Path]:
    """Make the run folder a submission: agent.py (plays checkpoint.pt) and a README with the command."""
    return write_submission_files(out, command, settings, "rl2", "RL^2", "RL2VectorAgent",
                                  "RL^2 (a GRU policy trained with PPO on meta-episodes; `mewa_bench/agents/rl2.py`).")


def train_run(settings: Settings, folder: Path, resume: bool, command: str,
              progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> list[Path]:
    """Train one seed into `folder` and make it a submission; the files written."""
    checkpoint = train(settings, folder, resume, progress)
    return [checkpoint, folder / METRICS, *write_submission(folder, command, settings)]
