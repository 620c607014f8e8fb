"""MAML (Finn et al. 2017) on MEWA: a feed-forward policy that adapts its weights by policy gradient
after every episode of a pair.

One file, top to bottom (in the spirit of CleanRL): settings, the network (plain tensors so that each
pair can hold its own adapted copy), the inner step, rollouts on the batched meta-episode env, the
outer PPO update, checkpoints, and `MAMLAgent`, which plays a checkpoint under the evaluation protocol.

- Policy: an MLP on the env's 18 floats (no memory, no previous action or reward): all that it learns
  about the worker it learns through its weights.
- Inner loop: after episode k of a pair, one policy-gradient step on that episode's trajectory,
  theta_{k+1} = theta_k + alpha * grad_theta sum_t log pi(a_t | s_t) A_t, with A_t the generalised
  advantage (gamma = 1 within the episode, lambda = `gae_lambda`) from a critic V(s, k) that is
  meta-learned and never adapted. `alpha` is one learned step size per weight tensor (Meta-SGD-like,
  Li et al. 2017), initialised at `inner_lr`. The pair's parameters are theta_0 + alpha * G, G the sum
  of its inner gradients so far; G is reset when a new pair begins (`reset_task`).
- Outer loop: first-order MAML. Every inner episode of every pair is scored with the parameters it
  was played with, theta_0 + alpha * G, and PPO's clipped surrogate of all 10 episodes is maximised
  over theta_0 and alpha with G held fixed (no gradient through the inner gradients): the gradient for
  theta_0 is first order, the one for alpha exact given G. The evaluation protocol scores all 10
  episodes of a pair, so the pre-adaptation episode counts as much as the adapted ones.
- Pairs: each meta-episode draws a task of the suite and a meta-train worker from the task's own
  distribution (never a curated test worker), or one of `workers` when given. Rollouts run on
  `MetaEpisodeVectorEnv`; an outer update uses the episodes that ended during its rollout (an episode
  cut by the rollout's end is finished in the next one, its behaviour log-probabilities kept for the
  PPO ratio).
- Reward: the env's step rewards times `reward_scale` (what the agent sees at evaluation; their
  undiscounted sum is the episode return, an affine function of the normalised return scored).
- Deterministic for a given seed on one machine (explicit generators, one thread).

`mewa-bench train maml` runs it, about 10k env steps/s end to end on one core of
a busy machine (benchmarks/training.py). Learning test (tests/test_maml.py): 1 M steps on narrow-v1's
meta-train workers; on 100 fresh meta-train workers its mean score is 0.9885 against the random
task-specific baseline's exact 0.9778 (+0.0107 +- 0.0018), and it does not adapt (s_10 - s_1 about
0; the paper's MAML: -0.1). On the two-worker task ((0,1,1,1), (1,1,1,0)) 2 M steps gave 0.564
against 0.521, +0.015 from episode 1 to 10 (not a test).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mewa_bench.agents.lanes import LaneGenerators, LaneSteps, pick_actions, truthy
from mewa_bench.protocol.agent import SingleLane, state_vector
from mewa_bench.agents.training_io import (CHECKPOINT, METRICS, append_metrics, episode_end_scores, load_for_play,
                                           make_meta_env, mean_or_nan, restore, resumed, save_checkpoint, settings_with,
                                           torch_module, torch_threads, write_submission)

__all__ = ["CHECKPOINT", "METRICS", "MAMLAgent", "MAMLVectorAgent", "Settings", "make_agent", "settings_from", "train", "train_run"]

OBS_SIZE = 18
ACTIONS = 4
OBS_SCALE = 8.0  # block counts up to about 8; flags are 0/1


@dataclass
class Settings:
    """Everything a run depends on (saved in the checkpoint)."""

    suite: str = "narrow-v1"
    seed: int = 1
    total_steps: int = 4_000_000
    num_envs: int = 64
    num_steps: int = 128  # env steps per env and outer update
    episodes: int = 10  # inner episodes per pair
    hidden: int = 64
    inner_lr: float = 0.05  # initial inner step size alpha (per weight tensor)
    learn_inner_lr: bool = True
    learning_rate: float = 1e-3  # outer Adam step size
    gae_lambda: float = 0.95
    update_epochs: int = 4
    num_minibatches: int = 4
    clip_coef: float = 0.2
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    reward_scale: float = 0.1
    checkpoint_every: int = 20  # outer updates
    workers: list[list[float]] = field(default_factory=list)  # empty: the suite's meta-train distribution

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.num_steps


def _torch() -> Any:
    """The torch module (the train extra)."""
    return torch_module("MAML (`mewa-bench train maml` and its checkpoints)")


def make_model(settings: Settings) -> Any:
    """theta_0 (the policy's weights as plain tensors), the log inner step sizes and the critic."""
    torch = _torch()
    nn = torch.nn

    class MAMLModel(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            h = settings.hidden
            layers = [nn.Linear(OBS_SIZE, h), nn.Linear(h, h), nn.Linear(h, ACTIONS)]
            nn.init.orthogonal_(layers[-1].weight, 0.01)  # a near-uniform first policy
            nn.init.zeros_(layers[-1].bias)
            # weights stored [in, out] so that a batch of them multiplies with bmm
            self.theta = nn.ParameterList([p for layer in layers for p in (layer.weight.T.detach().clone(),
                                                                           layer.bias.detach().clone())])
            self.log_lr = nn.Parameter(torch.full((len(self.theta),), float(np.log(settings.inner_lr))),
                                       requires_grad=settings.learn_inner_lr)
            self.critic = nn.Sequential(nn.Linear(OBS_SIZE + settings.episodes, h), nn.Tanh(), nn.Linear(h, h),
                                        nn.Tanh(), nn.Linear(h, 1))

        def adapted(self, grads: list[Any]) -> list[Any]:
            """theta_0 + alpha * G for a batch of accumulated inner gradients G (each [B, *shape])."""
            lr = self.log_lr.exp()
            return [p.unsqueeze(0) + lr[i] * g for i, (p, g) in enumerate(zip(self.theta, grads))]

        def value(self, obs: Any, k: Any) -> Any:
            """V(s, k) for observations [..., 18] and inner-episode indices k [...]."""
            onehot = torch.nn.functional.one_hot(k.clamp(max=settings.episodes - 1), settings.episodes).to(obs.dtype)
            return self.critic(torch.cat([obs / OBS_SCALE, onehot], dim=-1)).squeeze(-1)

    return MAMLModel()


def policy_logits(params: list[Any], obs: Any) -> Any:
    """Logits [B, L, 4] of a batch of policies (params [B, ...]) on observations [B, L, 18]."""
    torch = _torch()
    w1, b1, w2, b2, w3, b3 = params
    h = torch.tanh(torch.baddbmm(b1.unsqueeze(1), obs / OBS_SCALE, w1))
    h = torch.tanh(torch.baddbmm(b2.unsqueeze(1), h, w2))
    return torch.baddbmm(b3.unsqueeze(1), h, w3)


def zero_grads(model: Any, n: int) -> list[Any]:
    """Accumulated inner gradients G of n fresh pairs (all zero)."""
    torch = _torch()
    return [torch.zeros((n, *p.shape)) for p in model.theta]


def episode_advantages(rewards: Any, values: Any, mask: Any, lam: float) -> Any:
    """GAE with gamma = 1 over padded whole episodes [B, L] (each ends at its last valid step):
    A_t = sum_{u >= t} lam^(u - t) delta_u, one matrix product."""
    torch = _torch()
    following = torch.nn.functional.pad(values[:, 1:] * mask[:, 1:], (0, 1))
    delta = (rewards + following - values) * mask
    steps = torch.arange(rewards.shape[1], dtype=rewards.dtype)
    gap = steps.unsqueeze(0) - steps.unsqueeze(1)  # [t, u] = u - t
    decay = torch.where(gap >= 0, lam ** gap.clamp(min=0), torch.zeros((), dtype=rewards.dtype))
    return delta @ decay.T

def inner_gradients(model: Any, grads: list[Any], obs: Any, actions: Any, rewards: Any, mask: Any, k: Any,
                    settings: Settings) -> list[Any]:
    """The policy gradient of each episode [B, L] at its pair's adapted weights: what G adds after it."""
    torch = _torch()
    with torch.no_grad():
        params = [p.detach().requires_grad_(True) for p in model.adapted(grads)]
        advantages = episode_advantages(rewards, model.value(obs, k.unsqueeze(1).expand_as(actions)), mask,
                                        settings.gae_lambda)
    with torch.enable_grad():
        logp = torch.distributions.Categorical(logits=policy_logits(params, obs)).log_prob(actions)
        objective = (logp * advantages * mask).sum(dim=1) / mask.sum(dim=1).clamp(min=1.0)
        return list(torch.autograd.grad(objective.sum(), params))


class EpisodeBuffer:
    """The running inner episode of each env (padded to the horizon) and the episodes that ended."""

    def __init__(self, n: int, horizon: int) -> None:
        torch = _torch()
        self.obs = torch.zeros(n, horizon, OBS_SIZE)
        self.actions = torch.zeros(n, horizon, dtype=torch.long)
        self.logprobs = torch.zeros(n, horizon)
        self.rewards = torch.zeros(n, horizon)
        self.length = torch.zeros(n, dtype=torch.long)
        self.done: list[dict[str, Any]] = []

    def add(self, rows: Any, obs: Any, actions: Any, logprobs: Any, rewards: Any) -> None:
        """One step of the envs in `rows`."""
        at = self.length[rows]
        self.obs[rows, at], self.actions[rows, at] = obs, actions
        self.logprobs[rows, at], self.rewards[rows, at] = logprobs, rewards
        self.length[rows] += 1

    def take(self, rows: Any) -> dict[str, Any]:
        """The finished episodes of `rows`, padded to their longest (and cleared in the buffer)."""
        torch = _torch()
        longest = int(self.length[rows].max())
        mask = (torch.arange(longest).unsqueeze(0) < self.length[rows].unsqueeze(1)).float()
        out = {"obs": self.obs[rows, :longest].clone(), "actions": self.actions[rows, :longest].clone(),
               "logprobs": self.logprobs[rows, :longest].clone(), "rewards": self.rewards[rows, :longest].clone(),
               "mask": mask}
        self.length[rows] = 0
        return out


@torch_threads(1)
def train(settings: Settings, out: Path, resume: bool = False,
          progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> Path:
    """Train (or resume) a run in `out`: checkpoints and metrics written as they come; the checkpoint path.

    A resumed run restarts its rollouts from the checkpoint's update (fresh pairs and random streams
    derived from the seed and that update): deterministic, but not the bytes of an uninterrupted run."""
    torch = _torch()
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(settings.seed)
    state = resumed(out, settings, resume)
    model = make_model(settings)
    optimizer = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=settings.learning_rate,
                                 eps=1e-5)
    start_update = 0 if state is None else restore(out, state, model, {"optimizer": optimizer})
    generator = torch.Generator().manual_seed(settings.seed * 1_000_003 + start_update)
    env = make_meta_env(settings.suite, settings.num_envs, settings.episodes, settings.workers)
    obs_np, _ = env.reset(seed=settings.seed + start_update)
    n = settings.num_envs
    buffer = EpisodeBuffer(n, max(t.T for t in env.tasks))
    grads = zero_grads(model, n)
    dummy = torch.zeros(n, dtype=torch.bool)  # this step is an autoreset step: its action is ignored
    updates = settings.total_steps // settings.steps_per_update
    for update in range(start_update, updates):
        began = time.perf_counter()
        first_scores: list[float] = []
        last_scores: list[float] = []
        with torch.no_grad():
            params = model.adapted(grads)  # each env's weights, refreshed where G changes
            for _ in range(settings.num_steps):
                obs = torch.as_tensor(obs_np[:, :OBS_SIZE])
                logits = policy_logits(params, obs.unsqueeze(1)).squeeze(1)
                action = torch.multinomial(torch.softmax(logits, dim=1), 1, generator=generator).squeeze(1)
                logprob = torch.log_softmax(logits, dim=1).gather(1, action.unsqueeze(1)).squeeze(1)
                obs_np, reward, _, _, info = env.step(action.numpy())
                live = torch.nonzero(~dummy).squeeze(1)
                buffer.add(live, obs[live], action[live], logprob[live],
                           torch.as_tensor(reward, dtype=torch.float32)[live] * settings.reward_scale)
                first, last = episode_end_scores(info, settings.episodes)
                first_scores += first
                last_scores += last
                ended = torch.as_tensor(info["inner_done"]) & ~dummy
                if ended.any():
                    rows = torch.nonzero(ended).squeeze(1)
                    end_episodes(model, settings, buffer, grads, params, rows,
                                 torch.as_tensor(info["episode_in_trial"])[rows])
                dummy = torch.as_tensor(info["inner_done"] & (info["episode_in_trial"] == settings.episodes - 1))
        losses = outer_update(model, optimizer, settings, buffer.done, generator)
        buffer.done = []
        steps = (update + 1) * settings.steps_per_update
        row = {"update": update + 1, "env_steps": steps, "seconds": round(time.perf_counter() - began, 3),
               "episode_1_normalised_return": mean_or_nan(first_scores),
               "episode_10_normalised_return": mean_or_nan(last_scores), **losses}
        append_metrics(out / METRICS, row)
        progress(steps, updates * settings.steps_per_update, row)
        if (update + 1) % settings.checkpoint_every == 0 or update + 1 == updates:
            save_checkpoint(out / CHECKPOINT, {"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                                               "settings": asdict(settings), "update": update + 1})
    return out / CHECKPOINT


def end_episodes(model: Any, settings: Settings, buffer: EpisodeBuffer, grads: list[Any], params: list[Any],
                 rows: Any, k: Any) -> None:
    """The inner episodes k of envs `rows` ended: keep them (with the G they were played with) for the
    outer update, take each pair's inner step, and start G afresh where the pair's last episode ended."""
    torch = _torch()
    episode = {**buffer.take(rows), "k": k, "grads": [g[rows].clone() for g in grads]}
    buffer.done.append(episode)
    adapt = k < settings.episodes - 1  # after the last episode the pair changes: no step
    if adapt.any():
        step = inner_gradients(model, [g[adapt] for g in episode["grads"]], episode["obs"][adapt],
                               episode["actions"][adapt], episode["rewards"][adapt], episode["mask"][adapt],
                               k[adapt], settings)
        for g, s in zip(grads, step):
            g[rows[adapt]] += s
    for g in grads:
        g[rows[~adapt]] = 0.0
    with torch.no_grad():
        for p, fresh in zip(params, model.adapted([g[rows] for g in grads])):
            p[rows] = fresh


def outer_update(model: Any, optimizer: Any, settings: Settings, episodes: list[dict[str, Any]],
                 generator: Any) -> dict[str, float]:
    """PPO epochs over minibatches of whole episodes, each played with its pair's theta_0 + alpha * G."""
    torch = _torch()

    if not episodes:
        return {"policy_loss": float("nan"), "value_loss": float("nan"), "entropy": float("nan"),
                "inner_lr": round(float(model.log_lr.detach().exp().mean()), 6)}
    longest = max(e["obs"].shape[1] for e in episodes)

    def stacked(key: str) -> Any:
        parts = [e[key] for e in episodes]
        if parts[0].dim() == 1:
            return torch.cat(parts)
        return torch.cat([torch.nn.functional.pad(p, (0, 0) * (p.dim() - 2) + (0, longest - p.shape[1]))
                          for p in parts])

    obs, actions, old_logp, rewards, mask, k = (stacked(key) for key in
                                                ("obs", "actions", "logprobs", "rewards", "mask", "k"))
    grads = [torch.cat([e["grads"][i] for e in episodes]) for i in range(len(model.theta))]
    ks = k.unsqueeze(1).expand_as(actions)
    with torch.no_grad():
        advantages = episode_advantages(rewards, model.value(obs, ks), mask, settings.gae_lambda)
        returns = advantages + model.value(obs, ks)
    n = obs.shape[0]
    per_batch = max(1, n // settings.num_minibatches)
    stats: dict[str, list[float]] = {"policy_loss": [], "value_loss": [], "entropy": []}
    for _ in range(settings.update_epochs):
        order = torch.randperm(n, generator=generator)
        for start in range(0, n, per_batch):
            rows = order[start:start + per_batch]
            m = mask[rows]
            count = m.sum().clamp(min=1.0)
            dist = torch.distributions.Categorical(
                logits=policy_logits(model.adapted([g[rows] for g in grads]), obs[rows]))
            adv = advantages[rows]
            mean = (adv * m).sum() / count
            adv = (adv - mean) / ((((adv - mean) ** 2) * m).sum() / count).sqrt().add(1e-8)
            ratio = (dist.log_prob(actions[rows]) - old_logp[rows]).exp()
            clipped = ratio.clamp(1 - settings.clip_coef, 1 + settings.clip_coef)
            policy_loss = -(torch.min(ratio * adv, clipped * adv) * m).sum() / count
            value_loss = 0.5 * (((model.value(obs[rows], ks[rows]) - returns[rows]) ** 2) * m).sum() / count
            entropy = (dist.entropy() * m).sum() / count
            loss = policy_loss + settings.vf_coef * value_loss - settings.ent_coef * entropy
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), settings.max_grad_norm)
            optimizer.step()
            for key, value in (("policy_loss", policy_loss), ("value_loss", value_loss), ("entropy", entropy)):
                stats[key].append(value.item())
    return {**{key: round(float(np.mean(v)), 6) for key, v in stats.items()},
            "inner_lr": round(float(model.log_lr.detach().exp().mean()), 6)}


class MAMLVectorAgent:
    """Plays a MAML checkpoint on many lanes at once under the evaluation protocol (SPEC section 6): per lane
    theta_0 on a pair's first episode, one inner policy-gradient step on its own trajectory after each
    episode, back to theta_0 when a new pair begins. The lanes' adapted weights are stacked ([lanes,
    ...], as in training) so one batched pass acts for all lanes, and the inner steps of the lanes
    that end an episode together are one backward pass: the gradient of their summed objectives with
    respect to each lane's own weights is that lane's own gradient."""

    def __init__(self, checkpoint: str | Path, num_lanes: int = 1, seed: int | str = 0,
                 greedy: bool | str = False) -> None:
        torch = _torch()
        self.settings, self.model = load_for_play(checkpoint, Settings, make_model)
        self.greedy = truthy(greedy)
        self.generators = LaneGenerators(int(seed), int(num_lanes))
        self.steps = LaneSteps(int(num_lanes), OBS_SIZE)
        self.episode = np.zeros(int(num_lanes), dtype=np.int64)
        self.grads = [g.double() for g in zero_grads(self.model, int(num_lanes))]
        with torch.no_grad():
            self.params = self.model.adapted(self.grads)

    def reset_task(self, lanes: np.ndarray, seeds: np.ndarray) -> None:
        """New pairs: theta_0 again, no episode played."""
        self.generators.reset(lanes, seeds)
        self.steps.clear(lanes)
        self.episode[lanes] = 0
        for g in self.grads:
            g[lanes] = 0.0
        self._adapt(lanes)

    def act(self, lanes: np.ndarray, observations: Any) -> np.ndarray:
        """Each lane's adapted policy's action (sampled with the lane's generator, or the most likely if greedy)."""
        torch = _torch()
        obs = np.zeros((len(self.episode), 1, OBS_SIZE))  # every lane's policy runs: cheaper than gathering weights
        obs[lanes, 0] = state_vector(observations)
        with torch.no_grad():
            logits = policy_logits(self.params, torch.as_tensor(obs))[torch.as_tensor(lanes), 0]
            probs = torch.softmax(logits, dim=1).numpy()
        return pick_actions(probs, lanes, self.generators, self.greedy)

    def observe(self, lanes: np.ndarray, transitions: Any) -> None:
        """Keep the steps for the inner updates at the episodes' ends."""
        self.steps.add(lanes, transitions)

    def end_episode(self, lanes: np.ndarray) -> None:
        """The inner step of each lane on the episode it just played."""
        torch = _torch()
        played = lanes[self.steps.count[lanes] > 0]
        if played.size:
            longest = int(self.steps.count[played].max())
            mask = torch.as_tensor(np.arange(longest)[None, :] < self.steps.count[played][:, None], dtype=torch.float64)
            obs = torch.as_tensor(self.steps.obs[played, :longest], dtype=torch.float64)
            actions = torch.as_tensor(self.steps.action[played, :longest])
            rewards = torch.as_tensor(self.steps.reward[played, :longest]) * self.settings.reward_scale * mask
            index = torch.as_tensor(played)
            step = inner_gradients(self.model, [g[index] for g in self.grads], obs, actions, rewards, mask,
                                   torch.as_tensor(self.episode[played]), self.settings)
            for g, s in zip(self.grads, step):
                g[index] += s
            self._adapt(played)
        self.episode[lanes] += 1
        self.steps.clear(lanes)

    def _adapt(self, lanes: np.ndarray) -> None:
        """theta_0 + alpha * G for `lanes`."""
        torch = _torch()
        index = torch.as_tensor(lanes)
        with torch.no_grad():
            for p, fresh in zip(self.params, self.model.adapted([g[index] for g in self.grads])):
                p[index] = fresh


def MAMLAgent(checkpoint: str | Path, seed: int | str = 0, greedy: bool | str = False) -> SingleLane:
    """A one-lane MAML agent (the protocol's `Agent`): lane 0 of a `MAMLVectorAgent`."""
    return SingleLane(MAMLVectorAgent(checkpoint, 1, seed, greedy))


def make_agent(observation_space: Any = None, action_space: Any = None, checkpoint: str | Path | None = None,
               seed: int | str = 0, greedy: bool | str = False) -> SingleLane:
    """The agent file's factory (the protocol's `make_agent`)."""
    if checkpoint is None:
        raise ValueError("the MAML agent needs checkpoint=<path of a checkpoint.pt>")
    return MAMLAgent(checkpoint, seed=seed, greedy=greedy)


def settings_from(values: dict[str, Any], base: Settings | None = None) -> Settings:
    """Settings with some fields replaced (names checked)."""
    return settings_with(Settings, values, base, "MAML")


def train_run(settings: Settings, folder: Path, resume: bool, command: str,
              progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> list[Path]:
    """Train one seed into `folder` and make it a submission; the files written."""
    checkpoint = train(settings, folder, resume, progress)
    return [checkpoint, folder / METRICS, *write_submission(
        folder, command, settings, "maml", "MAML", "MAMLVectorAgent",
        "MAML (a feed-forward policy adapted by one policy-gradient step after each episode, meta-trained with "
        "first-order MAML and PPO; `mewa_bench/agents/maml.py`).")]
