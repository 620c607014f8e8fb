"""The small causal transformer of the offline in-context baselines (DPT, AD): its tokens, the model, its
per-lane key/value cache and the lanes that play it.

- Tokens (`make_tokens`): per frame the observation, the previous observation, the previous action one-hot,
  the previous reward and the new-episode flag (with the next observation, which is the frame's own within
  an episode, a token holds a whole transition: what the worker did); the observations scaled by
  `OBS_SCALE`. A pair's first token has no previous transition (zeros).
- Model: token and episode-index embeddings, `layers` pre-norm blocks (multi-head self-attention and an
  MLP), a final norm and an action head. No position embeddings: a token sees the tokens before it as a
  set of transitions, each of which carries what it needs (the episode index, the new-episode flag, the
  previous action and reward). `forward` scores whole sequences, each token attending to itself and the
  `context` - 1 tokens before it; `step` scores one new token per lane from the cache, the same numbers.
- Cache (`LaneCache`): for every layer the keys and values of each lane's last `context` tokens, in two
  tensors allocated once ([lanes, heads, context, d / heads], a ring buffer: without position embeddings
  their order does not matter), and each lane's token count. A step writes one key and value per lane and
  layer in place, then reads what the acting lanes hold: a run of consecutive lanes as a view of the cache
  (no copy), over the longest lane's span; or, when lanes at different points of their pairs would make
  that span mostly padding, in groups of lanes of similar length, each over its own span (`groups`).
  Memory traffic, not arithmetic, is what a step costs on a CPU.
- Lanes (`TransformerLanes`): what a vector agent keeps per lane besides the cache (the previous
  observation, action and reward, the new-episode flag, the episode index, the lane's generator) and
  how it picks actions (sampled with the lane's generator, or the most likely one).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mewa_bench.agents.lanes import LaneGenerators, pick_actions
from mewa_bench.agents.training_io import torch_module
from mewa_bench.game.relabel import observation_gather
from mewa_bench.protocol.agent import state_vector

__all__ = ["ACTIONS", "EPISODES", "LaneCache", "LaneGroup", "OBS", "OBS_SCALE", "TOKEN", "TransformerLanes", "make_tokens",
           "make_transformer", "token_gather"]

OBS_SCALE = 8.0  # the 18 env floats are block counts up to about 8; the rest is already in [-1, 1]
OBS = 18
TOKEN = 2 * OBS + 4 + 2  # observation, previous observation, previous action one-hot, previous reward, new episode
EPISODES = 10  # episode-index embeddings (later episodes share the last one)
ACTIONS = 4


def make_tokens(obs: np.ndarray, previous_obs: np.ndarray, previous_action: np.ndarray, previous_reward: np.ndarray,
                new_episode: np.ndarray) -> np.ndarray:
    """Tokens float32 [n, TOKEN] (the observations scaled by OBS_SCALE); a previous action of -1: none."""
    tokens = np.zeros((len(obs), TOKEN), dtype=np.float32)
    tokens[:, :OBS], tokens[:, OBS:2 * OBS] = np.asarray(obs) / OBS_SCALE, np.asarray(previous_obs) / OBS_SCALE
    rows = np.flatnonzero(np.asarray(previous_action) >= 0)
    tokens[rows, 2 * OBS + np.asarray(previous_action)[rows]] = 1.0
    tokens[:, -2], tokens[:, -1] = previous_reward, new_episode
    return tokens


def token_gather(renaming: np.ndarray) -> np.ndarray:
    """Indices g with renamed_tokens = tokens[..., g] when palette colour c is renamed renaming[c]
    (`game.relabel`): both observations' per-colour entries and the previous action move (int64[TOKEN])."""
    obs = observation_gather(renaming)
    action = np.empty(ACTIONS, dtype=np.int64)
    action[np.asarray(renaming)] = np.arange(ACTIONS)
    return np.r_[obs, OBS + obs, 2 * OBS + action, TOKEN - 2, TOKEN - 1]


def _torch() -> Any:
    return torch_module("the transformer baselines")


def make_transformer(d_model: int, heads: int, layers: int, context: int, token_size: int = TOKEN,
                     episodes: int = EPISODES, actions: int = ACTIONS) -> Any:
    """A causal transformer over tokens of `token_size` floats with `episodes` episode-index embeddings."""
    torch = _torch()
    nn = torch.nn
    d = d_model

    class Block(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.norm1, self.norm2 = nn.LayerNorm(d), nn.LayerNorm(d)
            self.qkv, self.out = nn.Linear(d, 3 * d), nn.Linear(d, d)
            self.mlp = nn.Sequential(nn.Linear(d, 4 * d), nn.GELU(), nn.Linear(4 * d, d))

        def split(self, x: Any) -> tuple[Any, Any, Any]:
            """Queries, keys and values [B, heads, L, d / heads] of x [B, L, d]."""
            q, k, v = self.qkv(self.norm1(x)).chunk(3, dim=-1)
            shape = (x.shape[0], x.shape[1], heads, d // heads)
            return tuple(t.reshape(shape).transpose(1, 2) for t in (q, k, v))

        def attend(self, x: Any, q: Any, k: Any, v: Any, mask: Any) -> Any:
            """x + attention(q over k, v; `mask` True where allowed) + MLP."""
            return self.finish(x, torch.nn.functional.scaled_dot_product_attention(q, k, v, attn_mask=mask))

        def finish(self, x: Any, attended: Any) -> Any:
            """x + the attention's output projection + MLP (attended [B, heads, L, d / heads])."""
            x = x + self.out(attended.transpose(1, 2).reshape(x.shape))
            return x + self.mlp(self.norm2(x))

    class CausalTransformer(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.embed, self.episode = nn.Linear(token_size, d), nn.Embedding(episodes, d)
            self.blocks = nn.ModuleList(Block() for _ in range(layers))
            self.norm, self.head = nn.LayerNorm(d), nn.Linear(d, actions)

        def inputs(self, tokens: Any, episode: Any) -> Any:
            return self.embed(tokens) + self.episode(episode)

        def forward(self, tokens: Any, episode: Any, valid: Any) -> Any:
            """Logits [B, L, actions] for whole sequences (tokens [B, L, token_size], episode [B, L], valid [B, L]
            bool), each token attending to itself and the `context` - 1 tokens before it (as a lane's cache holds)."""
            x = self.inputs(tokens, episode)
            length = x.shape[1]
            window = torch.ones(length, length, dtype=torch.bool).tril().triu(-(context - 1))
            mask = window[None, None] & valid[:, None, None, :]
            for block in self.blocks:
                x = block.attend(x, *block.split(x), mask)
            return self.head(self.norm(x))

        def step(self, tokens: Any, episode: Any, cache: LaneCache, lanes: np.ndarray) -> Any:
            """Logits [n, actions] for one new token of each of `lanes` (tokens [n, token_size], episode [n]); the
            new keys and values go into `cache`, whose counts advance by one."""
            x = self.inputs(tokens, episode)[:, None, :]
            lengths = cache.lengths[lanes]
            groups = cache.groups(lanes)
            index, slot = torch.as_tensor(lanes), torch.as_tensor(lengths % cache.context)
            sdpa = torch.nn.functional.scaled_dot_product_attention
            for block, (keys, values) in zip(self.blocks, cache.layers):
                q, k, v = block.split(x)
                keys[index, :, slot], values[index, :, slot] = k[:, :, 0], v[:, :, 0]
                attended = torch.empty_like(q)
                for group in groups:
                    group.put(attended, sdpa(group.queries(q), keys[group.rows, :, :group.span],
                                             values[group.rows, :, :group.span], attn_mask=group.mask))
                x = block.finish(x, attended)
            cache.lengths[lanes] += 1
            return self.head(self.norm(x[:, 0]))

    return CausalTransformer()


@dataclass(frozen=True)
class LaneGroup:
    """Lanes whose attention reads the cache together: which of the call's queries they take (`take`: a torch index
    into the call's lanes, or None for all), their cache rows (a slice: a view; or a torch index: a copy), the span
    of positions read, the additive mask [g, 1, 1, span] (0 where a lane has a token, -inf past its length) and,
    for a view over a run of lanes some of which do not act, where the call's lanes sit in it (`place`)."""

    take: Any
    rows: Any
    span: int
    mask: Any
    place: Any = None

    def queries(self, q: Any) -> Any:
        """The group's rows of the call's queries q [n, heads, 1, head_dim] (zeros for lanes that do not act)."""
        if self.take is not None:
            return q[self.take]
        if self.place is not None:
            return q.new_zeros((self.mask.shape[0], *q.shape[1:])).index_copy_(0, self.place, q)
        return q

    def put(self, attended: Any, out: Any) -> None:
        """Write the group's attention outputs `out` into the call's `attended` [n, heads, 1, head_dim]."""
        rows = out if self.place is None else out[self.place]
        if self.take is None:
            attended.copy_(rows)
        else:
            attended[self.take] = rows


class LaneCache:
    """Per layer the keys and values of each lane's last `context` tokens (two tensors [lanes, heads, context,
    head_dim] allocated once), and each lane's token count."""

    GROUP = 16  # lanes per group when the acting lanes are read in groups of similar length

    def __init__(self, layers: int, lanes: int, heads: int, context: int, head_dim: int) -> None:
        torch = _torch()
        shape = (lanes, heads, context, head_dim)
        self.context = context
        self.layers = [(torch.zeros(shape, dtype=torch.float64), torch.zeros(shape, dtype=torch.float64))
                       for _ in range(layers)]
        self.lengths = np.zeros(lanes, dtype=np.int64)

    def reset(self, lanes: np.ndarray) -> None:
        """Empty contexts for `lanes` (their old keys are masked out until overwritten)."""
        self.lengths[lanes] = 0

    def groups(self, lanes: np.ndarray) -> list[LaneGroup]:
        """How one step of `lanes` (distinct; before their new token is counted) reads the cache, whichever moves
        fewer bytes: a view of the run of lanes from the first to the last (lanes that do not act in it compute a
        row that is thrown away) over the longest span; or copies of groups of lanes of similar length, each over
        its own span (a copy costs about twice what it holds: written, then read)."""
        torch = _torch()
        spans = np.minimum(self.lengths[lanes] + 1, self.context)
        first, last = int(lanes.min()), int(lanes.max())
        run = (last - first + 1) * int(spans.max())
        order = np.argsort(spans, kind="stable")
        chunks = np.array_split(order, -(-len(lanes) // self.GROUP))
        if 2 * sum(len(c) * int(spans[c].max()) for c in chunks) >= run:
            span = int(spans.max())
            run_spans = np.ones(last - first + 1, dtype=np.int64)  # lanes that do not act: any valid position
            run_spans[lanes - first] = spans
            in_order = np.array_equal(lanes, np.arange(first, last + 1))
            place = None if in_order else torch.as_tensor(lanes - first)
            return [LaneGroup(None, slice(first, last + 1), span, _additive_mask(run_spans, span), place)]
        return [LaneGroup(torch.as_tensor(c), torch.as_tensor(lanes[c]), int(spans[c].max()),
                          _additive_mask(spans[c], int(spans[c].max()))) for c in chunks]


def _additive_mask(spans: np.ndarray, span: int) -> Any:
    """[len(spans), 1, 1, span]: 0 at the first spans[i] positions of row i, -inf after them."""
    mask = np.where(np.arange(span)[None, :] < spans[:, None], 0.0, -np.inf)
    return _torch().as_tensor(mask)[:, None, None, :]


class TransformerLanes:
    """Plays a causal transformer on many lanes at once under the evaluation protocol (SPEC section 6): per lane a
    cache of its pair's tokens so far, the previous observation, action and reward, the new-episode flag and the
    episode index. Actions are sampled with each lane's generator, or the most likely ones when `greedy` (from
    episode `sample_episodes` of a pair on: the first ones still sample)."""

    def __init__(self, model: Any, layers: int, heads: int, d_model: int, context: int, num_lanes: int, seed: int,
                 greedy: bool, sample_episodes: int = 0) -> None:
        self.model, self.greedy, self.sample_episodes = model, greedy, sample_episodes
        self.generators = LaneGenerators(seed, num_lanes)
        self.cache = LaneCache(layers, num_lanes, heads, context, d_model // heads)
        self.previous_action = np.full(num_lanes, -1, dtype=np.int64)
        self.previous_reward = np.zeros(num_lanes)
        self.previous_obs = np.zeros((num_lanes, OBS))
        self.new_episode = np.zeros(num_lanes, dtype=np.float32)
        self.episode = np.zeros(num_lanes, dtype=np.int64)

    def reset_task(self, lanes: np.ndarray, seeds: np.ndarray) -> None:
        """New pairs: an empty context, no previous action."""
        self.generators.reset(lanes, seeds)
        self.cache.reset(lanes)
        self.previous_action[lanes], self.previous_reward[lanes] = -1, 0.0
        self.previous_obs[lanes] = 0.0
        self.new_episode[lanes], self.episode[lanes] = 0.0, 0

    def act(self, lanes: np.ndarray, observations: Any) -> np.ndarray:
        """The model's actions for `lanes`, its context each lane's tokens so far."""
        torch = _torch()
        tokens = make_tokens(state_vector(observations), self.previous_obs[lanes], self.previous_action[lanes],
                             self.previous_reward[lanes], self.new_episode[lanes])
        with torch.no_grad():
            logits = self.model.step(torch.as_tensor(tokens, dtype=torch.float64),
                                     torch.as_tensor(np.minimum(self.episode[lanes], EPISODES - 1)), self.cache, lanes)
            probs = torch.softmax(logits, dim=1).numpy()
        self.new_episode[lanes] = 0.0
        return pick_actions(probs, lanes, self.generators, self.greedy, self.episode[lanes] < self.sample_episodes)

    def observe(self, lanes: np.ndarray, transitions: Any) -> None:
        """Remember each lane's last observation, action and reward for its next token."""
        self.previous_obs[lanes] = state_vector(transitions.obs)
        self.previous_action[lanes] = transitions.action
        self.previous_reward[lanes] = transitions.reward

    def end_episode(self, lanes: np.ndarray) -> None:
        """The next token of these lanes starts their pair's next episode."""
        self.new_episode[lanes] = 1.0
        self.episode[lanes] += 1
