"""What the learned baselines' batched (vector) agents share: per-lane generators and recurrent lanes.

A vector agent plays every lane of an agent process with one network call per step (SPEC section
6, batched agents). Two things keep its results independent of how lanes are batched:
- each lane draws from its own generator, seeded from the agent's seed and the unit's seed exactly
  as a one-lane agent seeds its own, and `LaneGenerators.choice` draws as `Generator.choice(n, p=p)`
  does (inverse CDF of one uniform), so one lane's draws never depend on the others;
- the networks' decisions are float64's, so that a batch's matrix kernels, which round differently at
  another batch size, cannot flip an action (float32's rounding would, about once in 10^6 decisions):
  the recurrent ones play in float64; the transformers (`causal_transformer.TransformerLanes`) step in
  float32 and recompute in float64 the rare decisions that float32 could have turned.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from mewa_bench.agents.training_io import torch_module
from mewa_bench.protocol.agent import state_vector


def truthy(value: bool | str) -> bool:
    """An agent arg ("true", "1", "yes" or a bool) as a bool."""
    return str(value).lower() in ("true", "1", "yes")


class LaneGenerators:
    """One `np.random.Generator` per lane, `default_rng([seed, unit seed])` from each lane's reset_task."""

    def __init__(self, seed: int, num_lanes: int) -> None:
        self.seed = seed
        self.generators = [np.random.default_rng([seed]) for _ in range(num_lanes)]

    def reset(self, lanes: np.ndarray, seeds: np.ndarray) -> None:
        """New units begin on `lanes` with these protocol seeds."""
        for lane, seed in zip(lanes.tolist(), seeds.tolist()):
            self.generators[lane] = np.random.default_rng([self.seed, seed])

    def choice(self, lanes: np.ndarray, probs: np.ndarray) -> np.ndarray:
        """One action per lane drawn from `probs` [n, k] (rows need not be normalised) with the lane's
        generator, the value `Generator.choice(k, p=row / row.sum())` would give."""
        return inverse_cdf(probs, self.uniforms(lanes))

    def uniforms(self, lanes: np.ndarray) -> np.ndarray:
        """The next uniform of each lane's generator (what `choice` draws)."""
        return np.array([self.generators[lane].random() for lane in lanes.tolist()])

    def __getitem__(self, lane: int) -> np.random.Generator:
        return self.generators[lane]


def sampling_cdf(probs: np.ndarray) -> np.ndarray:
    """The cumulative distribution `Generator.choice` samples by, of each row of `probs` [n, k]."""
    p = probs / probs.sum(axis=1, keepdims=True)
    cdf = p.cumsum(axis=1)
    cdf /= cdf[:, -1:]
    return cdf


def inverse_cdf(probs: np.ndarray, uniforms: np.ndarray) -> np.ndarray:
    """The action `Generator.choice(k, p=row / row.sum())` gives for a row of `probs` [n, k] and its uniform [n]."""
    return (sampling_cdf(probs) <= uniforms[:, None]).sum(axis=1).astype(np.int64)


def sampled_rows(n: int, greedy: bool, sampling: np.ndarray | None = None) -> np.ndarray:
    """Which of `n` rows sample their action: all unless `greedy`; when greedy, the rows where `sampling` is True."""
    if not greedy:
        return np.ones(n, dtype=bool)
    return np.zeros(n, dtype=bool) if sampling is None else np.asarray(sampling, dtype=bool)


def decided(probs: np.ndarray, sampled: np.ndarray, uniforms: np.ndarray) -> np.ndarray:
    """The most likely action of each row of `probs` [n, k], except that the `sampled` rows take the action their
    uniform (one per sampled row) draws, as `Generator.choice` would."""
    actions = np.argmax(probs, axis=1).astype(np.int64)
    actions[sampled] = inverse_cdf(probs[sampled], uniforms)
    return actions


def pick_actions(probs: np.ndarray, lanes: np.ndarray, generators: LaneGenerators, greedy: bool,
                 sampling: np.ndarray | None = None) -> np.ndarray:
    """The most likely actions (`greedy`) or actions sampled with each lane's generator; when greedy, the lanes
    where `sampling` [n] is True still sample (e.g. a pair's first episodes)."""
    sampled = sampled_rows(len(lanes), greedy, sampling)
    return decided(probs, sampled, generators.uniforms(lanes[sampled]))


Forward = Callable[[Any, Any, Any], tuple[Any, Any]]  # (x [n, 24], h [n, H], reset [n]) -> (logits, new h)


class RecurrentLanes:
    """A recurrent meta-RL agent's lanes (RL^2's policy, VariBAD's encoder): per lane the hidden state and
    the previous action, reward and new-episode flag, kept across the 10 episodes of a pair."""

    def __init__(self, forward: Forward, hidden: int, num_lanes: int, seed: int, greedy: bool,
                 sample_episodes: int = 0) -> None:
        torch = torch_module("the learned baselines")
        self.forward = forward
        self.greedy = greedy
        self.sample_episodes = sample_episodes  # when greedy: the first episodes of a pair still sample
        self.episode = np.zeros(num_lanes, dtype=np.int64)
        self.generators = LaneGenerators(seed, num_lanes)
        self.h = torch.zeros(num_lanes, hidden, dtype=torch.float64)
        self.previous_action = np.full(num_lanes, -1, dtype=np.int64)
        self.previous_reward = np.zeros(num_lanes)
        self.new_episode = np.zeros(num_lanes)
        self.first = np.ones(num_lanes, dtype=bool)

    def reset_task(self, lanes: np.ndarray, seeds: np.ndarray) -> None:
        """New pairs: zero hidden state, no previous action."""
        self.generators.reset(lanes, seeds)
        self.h[lanes] = 0.0
        self.previous_action[lanes], self.previous_reward[lanes], self.new_episode[lanes] = -1, 0.0, 0.0
        self.first[lanes] = True
        self.episode[lanes] = 0

    def act(self, lanes: np.ndarray, observations: Any) -> np.ndarray:
        """The policy's actions for `lanes` (sampled with each lane's generator, or the most likely if greedy)."""
        from mewa_bench.envs.meta_episode import meta_observation

        torch = torch_module("the learned baselines")
        x = meta_observation(state_vector(observations), self.previous_action[lanes], self.previous_reward[lanes],
                             self.new_episode[lanes])
        index = torch.as_tensor(lanes)
        with torch.no_grad():
            logits, h = self.forward(torch.as_tensor(x, dtype=torch.float64), self.h[index],
                                     torch.as_tensor(self.first[lanes]))
            self.h[index] = h
            probs = torch.softmax(logits, dim=1).numpy()
        self.first[lanes] = False
        return pick_actions(probs, lanes, self.generators, self.greedy, self.episode[lanes] < self.sample_episodes)

    def observe(self, lanes: np.ndarray, transitions: Any) -> None:
        """Remember each lane's last action and reward for its next input."""
        self.previous_action[lanes] = transitions.action
        self.previous_reward[lanes] = transitions.reward
        self.new_episode[lanes] = 0.0

    def end_episode(self, lanes: np.ndarray) -> None:
        """The next observation of these lanes starts their pair's next episode."""
        self.new_episode[lanes] = 1.0
        self.episode[lanes] += 1


class LaneSteps:
    """The steps each lane has observed (since its last `clear`), as growing per-lane arrays."""

    def __init__(self, num_lanes: int, obs_size: int, capacity: int = 64) -> None:
        self.count = np.zeros(num_lanes, dtype=np.int64)
        self.obs = np.zeros((num_lanes, capacity, obs_size), dtype=np.float32)
        self.next_obs = np.zeros_like(self.obs)
        self.action = np.zeros((num_lanes, capacity), dtype=np.int64)
        self.reward = np.zeros((num_lanes, capacity))
        self.done = np.zeros((num_lanes, capacity), dtype=bool)

    def add(self, lanes: np.ndarray, transitions: Any) -> None:
        """Append one step (a `Transitions` row) to each of `lanes`."""
        at = self.count[lanes]
        if at.max() >= self.action.shape[1]:
            self._grow()
        self.obs[lanes, at] = state_vector(transitions.obs)
        self.next_obs[lanes, at] = state_vector(transitions.next_obs)
        self.action[lanes, at] = transitions.action
        self.reward[lanes, at] = transitions.reward
        self.done[lanes, at] = transitions.terminated | transitions.truncated
        self.count[lanes] = at + 1

    def clear(self, lanes: np.ndarray) -> None:
        """Forget the steps of `lanes`."""
        self.count[lanes] = 0

    def _grow(self) -> None:
        """Double the capacity of every array (keeping what is stored)."""
        for name in ("obs", "next_obs", "action", "reward", "done"):
            old = getattr(self, name)
            new = np.zeros((old.shape[0], 2 * old.shape[1], *old.shape[2:]), dtype=old.dtype)
            new[:, :old.shape[1]] = old
            setattr(self, name, new)
