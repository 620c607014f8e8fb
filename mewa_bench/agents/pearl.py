"""PEARL (Rakelly et al. 2019) on MEWA: a probabilistic context encoder and discrete soft actor-critic.

One file, top to bottom (in the spirit of CleanRL): settings, the networks, the posterior over the
latent task variable z, the replay of each training pair, rollouts on the batched meta-episode env,
the SAC update, checkpoints, and `PEARLAgent`, which plays a checkpoint under the evaluation protocol.

- Context encoder: each transition (s, one-hot a, r, s', done; s' zeroed where the episode ended)
  gives a Gaussian factor N(mu_i, sigma_i^2) over z (an MLP). The posterior is the product of the
  prior N(0, I) and the factors of the context (with the prior in the product, an empty context
  gives the prior: a pair's first episode), and the KL to the prior is weighted by `kl_weight`.
- Discrete SAC (Christodoulou 2019) on (s, z): twin Q-networks giving a value per action with target
  networks (Polyak `tau`), a softmax actor, and the entropy temperature alpha tuned automatically
  towards `target_entropy_ratio * log 4`. The critic's loss trains the encoder (through z,
  reparameterised); the actor sees z without gradient, as in PEARL.
- Temperature: the soft value pays alpha * entropy at every step, and every step of MEWA costs only
  0.23-1.0 (its step rewards), so a bonus near that pays the agent for long episodes: with alpha
  starting at 1 (the usual choice) SAC learned to stall, below uniform random play. alpha starts at
  `initial_alpha` and the target entropy is low (0.15 of log 4; others tuned 0.5-0.8 on Atari, where
  many actions are equivalent, but here almost every step's action matters).
- Episodes: every inner episode ends the SAC episode (no bootstrap across it: the protocol scores
  each episode's return; a time limit is the end of the scored episode too). The reward is the
  env's step reward times `reward_scale`, discounted by gamma = 0.999, near the undiscounted return
  the protocol scores (with 0.99 and Adam at 3e-4, one of two seeds stayed below the random
  task-specific baseline after 1 M steps; with 0.999 and 1e-3 both beat it).
- Replay: one slot per training pair (one meta-episode of `episodes` inner episodes on one (task,
  worker) pair), the last `buffer_pairs` pairs kept. A gradient step draws `meta_batch` pairs; for
  each, an RL batch of `batch_size` of its transitions and a context as the agent has it when it
  is scored: the pair's first j episodes for j drawn uniformly in 0..episodes-1, subsampled to at
  most `context_size` transitions.
- Posterior sampling (as at evaluation): each pair starts with z from the prior; at the start of
  each later episode z is drawn again from the posterior given (a subsample of at most
  `context_size` of) the pair's transitions so far. `reset_task` forgets the context.
- Pairs: each meta-episode draws a task of the suite and a meta-train worker from the task's own
  distribution (never a curated test worker), or one of `workers` when given.
- Deterministic for a given seed on one machine (a torch.Generator for actions and z, an
  np.random.Generator for replay sampling, one thread). A resumed run starts with an empty replay.

`mewa-bench train pearl` runs it, about 6.5k env steps/s end to end on one core of
a busy machine (benchmarks/training.py; the SAC updates take most of it). Learning test
(tests/test_pearl.py): 600 k steps on narrow-v1's meta-train workers; on 100 fresh meta-train
workers its mean score is 0.9906 against the random task-specific baseline's exact 0.9778
(+0.0128 +- 0.0015). It does not adapt: the posterior stays near the prior on the meta-train
workers (KL about 0.01), as the paper's PEARL (adaptability 0.001). On the two-worker task, after 1 M
steps, it plays (1,1,1,0) well (0.98) and never finishes with (0,1,1,1) (0.0), although its encoder
tells them apart (KL about 5): 0.489 against the baseline's 0.521.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mewa_bench.protocol.agent import SingleLane, state_vector
from mewa_bench.agents.lanes import LaneGenerators, LaneSteps, pick_actions, truthy
from mewa_bench.agents.training_io import (CHECKPOINT, METRICS, append_metrics, episode_end_scores, load_for_play,
                                           make_meta_env, mean_or_nan, restore, resumed, save_checkpoint, settings_with,
                                           torch_module, torch_threads, write_submission)

__all__ = ["CHECKPOINT", "METRICS", "PEARLAgent", "PEARLVectorAgent", "Settings", "make_agent", "settings_from", "train", "train_run"]

OBS_SIZE = 18
ACTIONS = 4
OBS_SCALE = 8.0  # block counts up to about 8; flags are 0/1
CONTEXT_SIZE = 2 * OBS_SIZE + ACTIONS + 2  # s, one-hot a, r, s', done


@dataclass
class Settings:
    """Everything a run depends on (saved in the checkpoint)."""

    suite: str = "narrow-v1"
    seed: int = 1
    total_steps: int = 2_000_000
    num_envs: int = 32
    num_steps: int = 64  # env steps per env between two rounds of gradient steps
    gradient_steps: int = 32  # SAC updates per round
    episodes: int = 10  # inner episodes per pair
    latent: int = 5
    hidden: int = 64
    encoder_hidden: int = 64
    meta_batch: int = 16  # pairs per gradient step
    batch_size: int = 32  # RL transitions per pair and gradient step
    context_size: int = 64  # at most this many context transitions per posterior
    buffer_pairs: int = 1000
    learning_rate: float = 1e-3
    gamma: float = 0.999  # near 1: the protocol scores the undiscounted episode return
    tau: float = 0.005
    target_entropy_ratio: float = 0.15  # of log 4 (see the module docstring)
    initial_alpha: float = 0.05  # the entropy bonus is paid per step: keep it below the smallest |reward|
    kl_weight: float = 0.1
    reward_scale: float = 1.0
    learning_starts: int = 20_000  # env steps collected (after a start or a resume) before the first update
    checkpoint_every: int = 50  # rounds
    workers: list[list[float]] = field(default_factory=list)  # empty: the suite's meta-train distribution

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.num_steps


def _torch() -> Any:
    """The torch module (the train extra)."""
    return torch_module("PEARL (`mewa-bench train pearl` and its checkpoints)")


def make_model(settings: Settings) -> Any:
    """The encoder, the actor, the twin critics and their targets, and the log temperature."""
    torch = _torch()
    nn = torch.nn

    def mlp(inputs: int, hidden: int, outputs: int) -> Any:
        return nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                             nn.Linear(hidden, outputs))

    class PEARLModel(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            s, h, z = OBS_SIZE + settings.latent, settings.hidden, settings.latent
            self.encoder = mlp(CONTEXT_SIZE, settings.encoder_hidden, 2 * z)
            self.actor = mlp(s, h, ACTIONS)
            self.q1, self.q2 = mlp(s, h, ACTIONS), mlp(s, h, ACTIONS)
            self.q1_target, self.q2_target = mlp(s, h, ACTIONS), mlp(s, h, ACTIONS)
            self.q1_target.load_state_dict(self.q1.state_dict())
            self.q2_target.load_state_dict(self.q2.state_dict())
            self.log_alpha = nn.Parameter(torch.tensor(float(np.log(settings.initial_alpha))))

        def posterior(self, context: Any, mask: Any) -> tuple[Any, Any]:
            """Mean and variance [B, latent] of N(0, I) times the factors of contexts [B, C, 42] (mask [B, C])."""
            out = self.encoder(context)
            mu, var = out[..., :z_dim], nn.functional.softplus(out[..., z_dim:]).clamp(min=1e-7)
            precision = 1.0 + (mask.unsqueeze(-1) / var).sum(dim=1)
            mean = (mask.unsqueeze(-1) * mu / var).sum(dim=1) / precision
            return mean, 1.0 / precision

        def logits(self, obs: Any, z: Any) -> Any:
            """The actor's logits for observations [..., 18] and latents [..., latent]."""
            return self.actor(torch.cat([obs / OBS_SCALE, z], dim=-1))

    z_dim = settings.latent
    return PEARLModel()


def context_features(obs: Any, actions: Any, rewards: Any, next_obs: Any, done: Any) -> Any:
    """The encoder's input [..., 42] for transitions (next observation zeroed where the episode ended)."""
    torch = _torch()
    live = (~done).to(obs.dtype).unsqueeze(-1)
    return torch.cat([obs / OBS_SCALE, torch.nn.functional.one_hot(actions, ACTIONS).to(obs.dtype),
                      rewards.to(obs.dtype).unsqueeze(-1), next_obs / OBS_SCALE * live,
                      done.to(obs.dtype).unsqueeze(-1)], dim=-1)


def kl_to_prior(mean: Any, var: Any) -> Any:
    """KL(N(mean, var) || N(0, I)) per row."""
    return 0.5 * (var + mean ** 2 - 1.0 - var.log()).sum(dim=-1)


class PairReplay:
    """One slot of transitions per training pair (its meta-episode), the last `pairs` pairs kept."""

    def __init__(self, pairs: int, capacity: int, episodes: int) -> None:
        self.obs = np.zeros((pairs, capacity, OBS_SIZE), dtype=np.uint8)  # block counts and flags
        self.next_obs = np.zeros((pairs, capacity, OBS_SIZE), dtype=np.uint8)
        self.actions = np.zeros((pairs, capacity), dtype=np.int64)
        self.rewards = np.zeros((pairs, capacity), dtype=np.float32)
        self.done = np.zeros((pairs, capacity), dtype=bool)
        self.length = np.zeros(pairs, dtype=np.int64)
        self.episode_ends = np.zeros((pairs, episodes), dtype=np.int64)  # length after each inner episode
        self.episodes_done = np.zeros(pairs, dtype=np.int64)
        self.next_slot = 0
        self.filled = 0

    def new_slots(self, n: int) -> np.ndarray:
        """n empty slots for new pairs (the oldest pairs are forgotten)."""
        slots = (self.next_slot + np.arange(n)) % len(self.length)
        self.next_slot = int((self.next_slot + n) % len(self.length))
        self.filled = min(len(self.length), self.filled + n)
        self.length[slots] = 0
        self.episodes_done[slots] = 0
        return slots

    def add(self, slots: np.ndarray, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray,
            next_obs: np.ndarray, done: np.ndarray) -> None:
        """One transition per slot; an ended inner episode is counted."""
        at = self.length[slots]
        self.obs[slots, at], self.next_obs[slots, at] = obs, next_obs
        self.actions[slots, at], self.rewards[slots, at], self.done[slots, at] = actions, rewards, done
        self.length[slots] += 1
        ended = slots[done]
        self.episode_ends[ended, np.minimum(self.episodes_done[ended], self.episode_ends.shape[1] - 1)] = \
            self.length[ended]
        self.episodes_done[ended] += 1

    def transitions(self, slots: np.ndarray, index: np.ndarray) -> dict[str, Any]:
        """Transitions index [B, K] of slots [B] as tensors."""
        torch = _torch()
        rows = slots[:, None]
        return {"obs": torch.as_tensor(self.obs[rows, index], dtype=torch.float32),
                "actions": torch.as_tensor(self.actions[rows, index]),
                "rewards": torch.as_tensor(self.rewards[rows, index]),
                "next_obs": torch.as_tensor(self.next_obs[rows, index], dtype=torch.float32),
                "done": torch.as_tensor(self.done[rows, index])}

    def context(self, slots: np.ndarray, prefix: np.ndarray, size: int, rng: np.random.Generator) -> tuple[Any, Any]:
        """Encoder inputs [B, size, 42] and mask [B, size]: at most `size` of each slot's first `prefix`
        transitions, drawn without replacement (all of them when there are fewer)."""
        torch = _torch()
        index = np.zeros((len(slots), size), dtype=np.int64)
        mask = np.zeros((len(slots), size), dtype=np.float32)
        for i, count in enumerate(prefix):
            chosen = np.arange(count) if count <= size else np.sort(rng.choice(count, size, replace=False))
            index[i, :len(chosen)], mask[i, :len(chosen)] = chosen, 1.0
        t = self.transitions(slots, index)
        return (context_features(t["obs"], t["actions"], t["rewards"], t["next_obs"], t["done"]),
                torch.as_tensor(mask))

    def sample(self, settings: Settings, rng: np.random.Generator) -> dict[str, Any]:
        """A meta-batch: pairs, their RL batches and their contexts (a prefix of j episodes, j uniform)."""
        candidates = np.flatnonzero(self.length[:self.filled] > 0)
        slots = rng.choice(candidates, settings.meta_batch, replace=len(candidates) < settings.meta_batch)
        index = (rng.random((len(slots), settings.batch_size)) * self.length[slots, None]).astype(np.int64)
        batch = self.transitions(slots, index)
        j = (rng.random(len(slots)) * (np.minimum(self.episodes_done[slots], settings.episodes - 1) + 1)).astype(int)
        prefix = np.where(j > 0, self.episode_ends[slots, np.maximum(j - 1, 0)], 0)
        batch["context"], batch["context_mask"] = self.context(slots, prefix, settings.context_size, rng)
        return batch


def sac_update(model: Any, optimizers: dict[str, Any], batch: dict[str, Any], settings: Settings,
               generator: Any) -> dict[str, float]:
    """One gradient step: critics and encoder (with the KL), actor, temperature, target networks."""
    torch = _torch()
    f = torch.nn.functional

    mean, var = model.posterior(batch["context"], batch["context_mask"])
    z = mean + var.sqrt() * torch.randn(mean.shape, generator=generator)
    kl = kl_to_prior(mean, var).mean()
    zb = z.unsqueeze(1).expand(-1, settings.batch_size, -1)
    state = torch.cat([batch["obs"] / OBS_SCALE, zb], dim=-1)
    alpha = model.log_alpha.detach().exp()
    with torch.no_grad():
        following = torch.cat([batch["next_obs"] / OBS_SCALE, zb.detach()], dim=-1)
        logp_next = f.log_softmax(model.actor(following), dim=-1)
        q_next = torch.min(model.q1_target(following), model.q2_target(following))
        v_next = (logp_next.exp() * (q_next - alpha * logp_next)).sum(dim=-1)
        target = batch["rewards"] * settings.reward_scale + settings.gamma * (~batch["done"]).float() * v_next
    action = batch["actions"].unsqueeze(-1)
    q1, q2 = model.q1(state).gather(-1, action).squeeze(-1), model.q2(state).gather(-1, action).squeeze(-1)
    q_loss = f.mse_loss(q1, target) + f.mse_loss(q2, target)
    optimizers["critic"].zero_grad()
    (q_loss + settings.kl_weight * kl).backward()
    optimizers["critic"].step()

    state = state.detach()  # the actor sees z without gradient
    logp = f.log_softmax(model.actor(state), dim=-1)
    probs = logp.exp()
    with torch.no_grad():
        q = torch.min(model.q1(state), model.q2(state))
    actor_loss = (probs * (alpha * logp - q)).sum(dim=-1).mean()
    optimizers["actor"].zero_grad()
    actor_loss.backward()
    optimizers["actor"].step()

    entropy = -(probs.detach() * logp.detach()).sum(dim=-1).mean()
    alpha_loss = model.log_alpha * (entropy - settings.target_entropy_ratio * np.log(ACTIONS))
    optimizers["alpha"].zero_grad()
    alpha_loss.backward()
    optimizers["alpha"].step()

    with torch.no_grad():
        for net, target_net in ((model.q1, model.q1_target), (model.q2, model.q2_target)):
            for p, tp in zip(net.parameters(), target_net.parameters()):
                tp.mul_(1.0 - settings.tau).add_(settings.tau * p)
    return {"q_loss": q_loss.item(), "actor_loss": actor_loss.item(), "entropy": entropy.item(),
            "alpha": alpha.item(), "kl": kl.item()}


def make_optimizers(model: Any, settings: Settings) -> dict[str, Any]:
    """Adam for the critics with the encoder, the actor and the temperature."""
    torch = _torch()
    critic = [*model.encoder.parameters(), *model.q1.parameters(), *model.q2.parameters()]
    return {"critic": torch.optim.Adam(critic, lr=settings.learning_rate, foreach=True),
            "actor": torch.optim.Adam(model.actor.parameters(), lr=settings.learning_rate, foreach=True),
            "alpha": torch.optim.Adam([model.log_alpha], lr=settings.learning_rate, foreach=True)}


def sample_latent(model: Any, context: Any, mask: Any, noise: Any) -> Any:
    """z from the posterior given contexts [B, C, 42] (mask [B, C]) and standard normal noise [B, latent]."""
    mean, var = model.posterior(context, mask)
    return mean + var.sqrt() * noise


@torch_threads(1)
def train(settings: Settings, out: Path, resume: bool = False,
          progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> Path:
    """Train (or resume) a run in `out`: checkpoints and metrics written as they come; the checkpoint path.

    A resumed run restarts from the checkpoint's round with fresh pairs, random streams derived from
    the seed and that round, and an empty replay that it refills (`learning_starts` env steps) before
    updating again: deterministic, but not the bytes of an uninterrupted run."""
    torch = _torch()

    if settings.buffer_pairs < 10 * settings.num_envs:  # a pair still being played must never lose its slot
        raise ValueError(f"PEARL setting buffer_pairs={settings.buffer_pairs} must be at least 10 x num_envs "
                         f"({10 * settings.num_envs})")
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(settings.seed)
    state = resumed(out, settings, resume)
    model = make_model(settings)
    optimizers = make_optimizers(model, settings)
    start_update = 0 if state is None else restore(out, state, model, optimizers, state["optimizers"])
    generator = torch.Generator().manual_seed(settings.seed * 1_000_003 + start_update)
    rng = np.random.default_rng([settings.seed, start_update])
    env = make_meta_env(settings.suite, settings.num_envs, settings.episodes, settings.workers)
    obs_np, _ = env.reset(seed=settings.seed + start_update)
    n = settings.num_envs
    replay = PairReplay(settings.buffer_pairs, settings.episodes * max(t.T for t in env.tasks), settings.episodes)
    slots = replay.new_slots(n)
    z = torch.randn((n, settings.latent), generator=generator)  # from the prior: no context yet
    dummy = np.zeros(n, dtype=bool)  # this step is an autoreset step: its action is ignored
    collected = 0
    updates = settings.total_steps // settings.steps_per_update
    for update in range(start_update, updates):
        began = time.perf_counter()
        first_scores: list[float] = []
        last_scores: list[float] = []
        for _ in range(settings.num_steps):
            obs = obs_np[:, :OBS_SIZE]
            with torch.no_grad():
                probs = torch.softmax(model.logits(torch.as_tensor(obs), z), dim=-1)
                action = torch.multinomial(probs, 1, generator=generator).squeeze(1).numpy()
            obs_np, reward, _, _, info = env.step(action)
            first, last = episode_end_scores(info, settings.episodes)
            first_scores += first
            last_scores += last
            live = ~dummy
            ended = info["inner_done"] & live
            replay.add(slots[live], obs[live], action[live], reward[live], obs_np[live, :OBS_SIZE], ended[live])
            final = ended & (info["episode_in_trial"] == settings.episodes - 1)
            later = np.flatnonzero(ended & ~final)  # the next inner episode of the same pair: z from the posterior
            if later.size:
                context, mask = replay.context(slots[later], replay.length[slots[later]], settings.context_size, rng)
                with torch.no_grad():
                    z[later] = sample_latent(model, context, mask,
                                             torch.randn((later.size, settings.latent), generator=generator))
            starting = np.flatnonzero(dummy)  # a new pair begins with this step's observation: the prior
            if starting.size:
                slots[starting] = replay.new_slots(starting.size)
                z[starting] = torch.randn((starting.size, settings.latent), generator=generator)
            dummy = final
        collected += settings.steps_per_update
        stats: dict[str, list[float]] = {}
        if collected >= settings.learning_starts:
            for _ in range(settings.gradient_steps):
                for key, value in sac_update(model, optimizers, replay.sample(settings, rng), settings,
                                             generator).items():
                    stats.setdefault(key, []).append(value)
        steps = (update + 1) * settings.steps_per_update
        row = {"update": update + 1, "env_steps": steps, "seconds": round(time.perf_counter() - began, 3),
               "episode_1_normalised_return": mean_or_nan(first_scores),
               "episode_10_normalised_return": mean_or_nan(last_scores),
               **{key: round(float(np.mean(stats[key])), 6) if key in stats else float("nan")
                  for key in ("q_loss", "actor_loss", "entropy", "alpha", "kl")}}
        append_metrics(out / METRICS, row)
        progress(steps, updates * settings.steps_per_update, row)
        if (update + 1) % settings.checkpoint_every == 0 or update + 1 == updates:
            save_checkpoint(out / CHECKPOINT, {"model": model.state_dict(), "settings": asdict(settings),
                                               "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
                                               "update": update + 1})
    return out / CHECKPOINT


class PEARLVectorAgent:
    """Plays a PEARL checkpoint on many lanes at once under the evaluation protocol (SPEC section 6): per
    lane z from the prior in a pair's first episode, then from the posterior given its own transitions
    of the pair's earlier episodes (at most `context_size` of them, subsampled), drawn again at every
    episode start; one actor pass per step for all lanes, one encoder pass for the lanes ending an episode."""

    def __init__(self, checkpoint: str | Path, num_lanes: int = 1, seed: int | str = 0,
                 greedy: bool | str = False) -> None:
        torch = _torch()
        self.settings, self.model = load_for_play(checkpoint, Settings, make_model)
        self.greedy = truthy(greedy)
        self.generators = LaneGenerators(int(seed), int(num_lanes))
        self.steps = LaneSteps(int(num_lanes), OBS_SIZE)
        self.z = torch.zeros(int(num_lanes), self.settings.latent, dtype=torch.float64)

    def reset_task(self, lanes: np.ndarray, seeds: np.ndarray) -> None:
        """New pairs: no context, z from the prior."""
        torch = _torch()
        self.generators.reset(lanes, seeds)
        self.steps.clear(lanes)
        for lane in lanes.tolist():
            self.z[lane] = torch.as_tensor(self.generators[lane].standard_normal(self.settings.latent))

    def act(self, lanes: np.ndarray, observations: Any) -> np.ndarray:
        """The policy's actions given each lane's z (sampled with the lane's generator, or the most likely if greedy)."""
        torch = _torch()
        with torch.no_grad():
            logits = self.model.logits(torch.as_tensor(state_vector(observations), dtype=torch.float64),
                                       self.z[torch.as_tensor(lanes)])
            probs = torch.softmax(logits, dim=1).numpy()
        return pick_actions(probs, lanes, self.generators, self.greedy)

    def observe(self, lanes: np.ndarray, transitions: Any) -> None:
        """Keep the transitions as context for the pairs' next episodes."""
        self.steps.add(lanes, transitions)

    def end_episode(self, lanes: np.ndarray) -> None:
        """Draw z for each lane's next episode from the posterior given (a subsample of) its pair's transitions."""
        torch = _torch()
        size, buffer = self.settings.context_size, self.steps
        picked, noise = [], []
        for lane in lanes.tolist():
            count, rng = int(buffer.count[lane]), self.generators[lane]
            picked.append(np.arange(count) if count <= size else np.sort(rng.choice(count, size, replace=False)))
            noise.append(rng.standard_normal(self.settings.latent))
        width = max(1, max(len(rows) for rows in picked))
        rows = np.zeros((len(picked), width), dtype=np.int64)
        mask = np.zeros((len(picked), width))
        for i, chosen in enumerate(picked):
            rows[i, :len(chosen)], mask[i, :len(chosen)] = chosen, 1.0
        at = (lanes[:, None], rows)
        context = context_features(*(torch.as_tensor(a) for a in (buffer.obs[at].astype(np.float64), buffer.action[at],
                                                                  buffer.reward[at],
                                                                  buffer.next_obs[at].astype(np.float64),
                                                                  buffer.done[at])))
        with torch.no_grad():
            self.z[torch.as_tensor(lanes)] = sample_latent(self.model, context, torch.as_tensor(mask),
                                                           torch.as_tensor(np.stack(noise)))


def PEARLAgent(checkpoint: str | Path, seed: int | str = 0, greedy: bool | str = False) -> SingleLane:
    """A one-lane PEARL agent (the protocol's `Agent`): lane 0 of a `PEARLVectorAgent`."""
    return SingleLane(PEARLVectorAgent(checkpoint, 1, seed, greedy))


def make_agent(observation_space: Any = None, action_space: Any = None, checkpoint: str | Path | None = None,
               seed: int | str = 0, greedy: bool | str = False) -> SingleLane:
    """The agent file's factory (the protocol's `make_agent`)."""
    if checkpoint is None:
        raise ValueError("the PEARL agent needs checkpoint=<path of a checkpoint.pt>")
    return PEARLAgent(checkpoint, seed=seed, greedy=greedy)


def settings_from(values: dict[str, Any], base: Settings | None = None) -> Settings:
    """Settings with some fields replaced (names checked)."""
    return settings_with(Settings, values, base, "PEARL")


def train_run(settings: Settings, folder: Path, resume: bool, command: str,
              progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> list[Path]:
    """Train one seed into `folder` and make it a submission; the files written."""
    checkpoint = train(settings, folder, resume, progress)
    return [checkpoint, folder / METRICS, *write_submission(
        folder, command, settings, "pearl", "PEARL", "PEARLVectorAgent",
        "PEARL (a probabilistic context encoder and discrete soft actor-critic with automatic temperature, "
        "posterior sampling per episode; `mewa_bench/agents/pearl.py`).")]
