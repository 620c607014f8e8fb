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
  The attention may have fewer key/value heads than query heads (`kv_heads`, each shared by a group of
  query heads, as in grouped-query attention): a lane's cache, and what a step reads, shrink by that factor.
- Cache (`LaneCache`): for every layer the keys and values of each lane's last `context` tokens, in two
  tensors allocated once ([lanes, kv_heads, context, d / heads], a ring buffer: without position embeddings
  their order does not matter), and each lane's token count. A step writes one key and value per lane and
  layer in place, then reads what the acting lanes hold: a run of consecutive lanes as a view of the cache
  (no copy), over the longest lane's span; or, when lanes at different points of their pairs would make
  that span mostly padding, in groups of lanes of similar length, each over its own span (`groups`).
  Memory traffic, not arithmetic, is what a step costs on a CPU.
- Lanes (`TransformerLanes`): what a vector agent keeps per lane besides the cache (the previous
  observation, action and reward, the new-episode flag, the episode index, the lane's generator, the pair's
  tokens so far) and how it picks actions (sampled with the lane's generator, or the most likely one). It
  steps a float32 copy of the model and takes the float64 model's decisions: a decision within `MARGIN`
  (logits) or `CDF_MARGIN` (a sampled one's uniform) of turning is recomputed by the float64 pass over the
  lane's tokens that reach the step (see the class).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mewa_bench.agents.lanes import LaneGenerators, decided, sampled_rows, sampling_cdf
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
                     episodes: int = EPISODES, actions: int = ACTIONS, kv_heads: int = 0) -> Any:
    """A causal transformer over tokens of `token_size` floats with `episodes` episode-index embeddings; its
    attention has `kv_heads` key/value heads, each shared by heads / kv_heads query heads (0: one per query head)."""
    torch = _torch()
    nn = torch.nn
    d = d_model
    kv = kv_heads or heads
    if heads % kv or d % heads:
        raise ValueError(f"heads {heads}, kv_heads {kv_heads}, d_model {d_model}: d_model must split into heads and "
                         "heads into kv_heads groups")
    head_dim, grouped = d // heads, kv != heads

    class Block(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.norm1, self.norm2 = nn.LayerNorm(d), nn.LayerNorm(d)
            self.qkv, self.out = nn.Linear(d, d + 2 * kv * head_dim), nn.Linear(d, d)
            self.mlp = nn.Sequential(nn.Linear(d, 4 * d), nn.GELU(), nn.Linear(4 * d, d))

        def split(self, x: Any) -> tuple[Any, Any, Any]:
            """Queries [B, heads, L, head_dim], keys and values [B, kv_heads, L, head_dim] of x [B, L, d]."""
            q, k, v = self.qkv(self.norm1(x)).split([d, kv * head_dim, kv * head_dim], dim=-1)
            batch, length = x.shape[0], x.shape[1]
            return (q.reshape(batch, length, heads, head_dim).transpose(1, 2),
                    *(t.reshape(batch, length, kv, head_dim).transpose(1, 2) for t in (k, v)))

        def attend(self, x: Any, q: Any, k: Any, v: Any, mask: Any) -> Any:
            """x + attention(q over k, v; `mask` True where allowed) + MLP."""
            return self.finish(x, torch.nn.functional.scaled_dot_product_attention(q, k, v, attn_mask=mask,
                                                                                   enable_gqa=grouped))

        def finish(self, x: Any, attended: Any) -> Any:
            """x + the attention's output projection + MLP (attended [B, heads, L, d / heads])."""
            x = x + self.out(attended.transpose(1, 2).reshape(x.shape))
            return x + self.mlp(self.norm2(x))

    class CausalTransformer(nn.Module):
        # the tokens a token's logits depend on (itself and those before it): each layer reaches context - 1 back
        receptive_field = layers * (context - 1) + 1

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
            groups, rows = cache.groups(lanes), cache.write_rows(lanes)
            sdpa = torch.nn.functional.scaled_dot_product_attention
            for block, (keys, values) in zip(self.blocks, cache.layers):
                q, k, v = block.split(x)
                keys.view(-1, head_dim).index_copy_(0, rows, k.reshape(-1, head_dim))
                values.view(-1, head_dim).index_copy_(0, rows, v.reshape(-1, head_dim))
                # the query heads of one key/value head as that head's queries: its keys are read once for them all
                q = q.reshape(len(lanes), kv, heads // kv, head_dim)
                attended = torch.empty_like(q)
                for group in groups:
                    group.put(attended, sdpa(group.queries(q), group.read(keys), group.read(values),
                                             attn_mask=group.mask))
                x = block.finish(x, attended.reshape(len(lanes), heads, 1, head_dim))
            cache.lengths[lanes] += 1
            return self.head(self.norm(x[:, 0]))

        def new_cache(self, lanes: int) -> LaneCache:
            """An empty cache for `lanes` lanes of this model, in its weights' dtype."""
            return LaneCache(layers, lanes, kv, context, head_dim, self.head.weight.dtype)

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
        """The group's rows of the call's queries q [n, kv_heads, heads / kv_heads, head_dim] (zeros for lanes that do
        not act)."""
        if self.take is not None:
            return q.index_select(0, self.take)
        if self.place is not None:
            return q.new_zeros((self.mask.shape[0], *q.shape[1:])).index_copy_(0, self.place, q)
        return q

    def put(self, attended: Any, out: Any) -> None:
        """Write the group's attention outputs `out` into the call's `attended` [n, heads, 1, head_dim]."""
        rows = out if self.place is None else out[self.place]
        if self.take is None:
            attended.copy_(rows)
        else:
            attended.index_copy_(0, self.take, rows)

    def read(self, layer: Any) -> Any:
        """The group's rows of a layer's keys (or values) [lanes, kv_heads, context, head_dim] over its span: a view,
        or a copy of the rows it names (index_select: about twice as fast as indexing)."""
        if isinstance(self.rows, slice):
            return layer[self.rows, :, :self.span]
        return layer[:, :, :self.span].index_select(0, self.rows)


class LaneCache:
    """Per layer the keys and values of each lane's last `context` tokens (two tensors [lanes, kv_heads, context,
    head_dim] allocated once), and each lane's token count."""

    GROUP = 16  # lanes per group when the acting lanes are read in groups of similar length

    def __init__(self, layers: int, lanes: int, kv_heads: int, context: int, head_dim: int, dtype: Any = None) -> None:
        torch = _torch()
        shape = (lanes, kv_heads, context, head_dim)
        self.context, self.dtype = context, dtype or torch.float64
        self.layers = [(torch.zeros(shape, dtype=self.dtype), torch.zeros(shape, dtype=self.dtype))
                       for _ in range(layers)]
        self.lengths = np.zeros(lanes, dtype=np.int64)

    def reset(self, lanes: np.ndarray) -> None:
        """Empty contexts for `lanes` (their old keys are masked out until overwritten)."""
        self.lengths[lanes] = 0

    def write_rows(self, lanes: np.ndarray) -> Any:
        """Where the new key (or value) of each of `lanes` and key/value heads goes, as rows of a layer's keys viewed
        [lanes * kv_heads * context, head_dim] (its ring-buffer slot), lane by lane."""
        _, kv_heads, context, _ = self.layers[0][0].shape
        slot = self.lengths[lanes] % context
        rows = (lanes[:, None] * kv_heads + np.arange(kv_heads)[None, :]) * context + slot[:, None]
        return _torch().as_tensor(rows.ravel())

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
            return [LaneGroup(None, slice(first, last + 1), span, self._mask(run_spans, span), place)]
        return [LaneGroup(torch.as_tensor(c), torch.as_tensor(lanes[c]), int(spans[c].max()),
                          self._mask(spans[c], int(spans[c].max()))) for c in chunks]

    def _mask(self, spans: np.ndarray, span: int) -> Any:
        """[len(spans), 1, 1, span] in the cache's dtype: 0 at the first spans[i] positions of row i, -inf after."""
        mask = np.where(np.arange(span)[None, :] < spans[:, None], 0.0, -np.inf)
        return _torch().as_tensor(mask, dtype=self.dtype)[:, None, None, :]


def near_a_boundary(logits: np.ndarray, probs: np.ndarray, sampling: np.ndarray, uniforms: np.ndarray,
                    margin: float, cdf_margin: float) -> np.ndarray:
    """Rows [n] whose decision is close to turning: greedy rows (not `sampling`) whose two best logits are closer than
    `margin`; sampled rows whose uniform (`uniforms`, one per sampled row) is closer than `cdf_margin` to a step of
    the cumulative distribution `probs` is sampled by."""
    close = np.zeros(len(logits), dtype=bool)
    if margin <= 0:
        return close
    best_two = np.sort(logits[~sampling], axis=1)[:, -2:]
    close[~sampling] = best_two[:, 1] - best_two[:, 0] < margin
    steps = sampling_cdf(probs[sampling])[:, :-1]
    close[sampling] = (np.abs(steps - uniforms[:, None]) < cdf_margin).any(axis=1)
    return close


class PairHistory:
    """Each lane's tokens and episode indices since its pair began (float32 [lanes, capacity, TOKEN], int64), kept
    for recomputing a lane's step exactly from its whole history; the capacity doubles when a pair outgrows it."""

    def __init__(self, num_lanes: int, capacity: int = 1024) -> None:
        self.tokens = np.zeros((num_lanes, capacity, TOKEN), dtype=np.float32)
        self.episode = np.zeros((num_lanes, capacity), dtype=np.int64)
        self.lengths = np.zeros(num_lanes, dtype=np.int64)

    def reset(self, lanes: np.ndarray) -> None:
        """New pairs on `lanes`: empty histories."""
        self.lengths[lanes] = 0

    def append(self, lanes: np.ndarray, tokens: np.ndarray, episode: np.ndarray) -> None:
        """One token (and its episode index) more for each of `lanes`."""
        if self.lengths[lanes].max() >= self.tokens.shape[1]:
            grow = self.tokens.shape[1]
            self.tokens = np.concatenate([self.tokens, np.zeros_like(self.tokens[:, :grow])], axis=1)
            self.episode = np.concatenate([self.episode, np.zeros_like(self.episode[:, :grow])], axis=1)
        at = self.lengths[lanes]
        self.tokens[lanes, at], self.episode[lanes, at] = tokens, episode
        self.lengths[lanes] += 1

    def of(self, lane: int) -> tuple[np.ndarray, np.ndarray]:
        """Lane `lane`'s tokens [n, TOKEN] and episode indices [n] so far."""
        n = int(self.lengths[lane])
        return self.tokens[lane, :n], self.episode[lane, :n]


MARGIN = 1e-3  # greedy decisions whose two best logits are closer than this are recomputed in float64
CDF_MARGIN = 1e-4  # sampled decisions whose uniform is closer than this to a step of the distribution are recomputed


class TransformerLanes:
    """Plays a causal transformer on many lanes at once under the evaluation protocol (SPEC section 6): per lane a
    cache of its pair's tokens so far, the previous observation, action and reward, the new-episode flag and the
    episode index. Actions are sampled with each lane's generator, or the most likely ones when `greedy` (from
    episode `sample_episodes` of a pair on: the first ones still sample).

    The actions are those of the float64 model (`model` as given): a step runs a float32 copy of it (half the
    bytes of cache to read, which is what a step costs on a CPU), and a decision that float32's rounding could
    have turned (greedy: the two best logits closer than `margin`; sampled: the lane's uniform closer than
    `cdf_margin` to a step of the cumulative distribution) is recomputed exactly, by the float64 model's pass over
    the lane's last tokens that reach its step (`receptive_field`). float32's errors are far below the margins
    (`benchmarks/README.md`), and the recomputation depends on the lane's own tokens only, so no lane's actions
    depend on its batch. `margin` 0 plays the float64 model at every step."""

    def __init__(self, model: Any, num_lanes: int, seed: int, greedy: bool, sample_episodes: int = 0,
                 margin: float = MARGIN, cdf_margin: float = CDF_MARGIN) -> None:
        import copy

        self.exact, self.margin, self.cdf_margin = model, margin, cdf_margin
        self.model = copy.deepcopy(model).float() if margin > 0 else model
        self.greedy, self.sample_episodes = greedy, sample_episodes
        self.generators = LaneGenerators(seed, num_lanes)
        self.cache = self.model.new_cache(num_lanes)
        self.history = PairHistory(num_lanes)
        self.previous_action = np.full(num_lanes, -1, dtype=np.int64)
        self.previous_reward = np.zeros(num_lanes)
        self.previous_obs = np.zeros((num_lanes, OBS))
        self.new_episode = np.zeros(num_lanes, dtype=np.float32)
        self.episode = np.zeros(num_lanes, dtype=np.int64)
        self.recomputed = 0  # decisions recomputed by the float64 full pass

    def reset_task(self, lanes: np.ndarray, seeds: np.ndarray) -> None:
        """New pairs: an empty context, no previous action."""
        self.generators.reset(lanes, seeds)
        self.cache.reset(lanes)
        self.history.reset(lanes)
        self.previous_action[lanes], self.previous_reward[lanes] = -1, 0.0
        self.previous_obs[lanes] = 0.0
        self.new_episode[lanes], self.episode[lanes] = 0.0, 0

    def act(self, lanes: np.ndarray, observations: Any) -> np.ndarray:
        """The model's actions for `lanes`, its context each lane's tokens so far."""
        torch = _torch()
        tokens = make_tokens(state_vector(observations), self.previous_obs[lanes], self.previous_action[lanes],
                             self.previous_reward[lanes], self.new_episode[lanes])
        episode = np.minimum(self.episode[lanes], EPISODES - 1)
        if self.margin > 0:
            self.history.append(lanes, tokens, episode)
        with torch.no_grad():
            logits = self.model.step(torch.as_tensor(tokens, dtype=self.cache.dtype), torch.as_tensor(episode),
                                     self.cache, lanes).double()
            probs = torch.softmax(logits, dim=1).numpy()
        self.new_episode[lanes] = 0.0
        sampling = sampled_rows(len(lanes), self.greedy, self.episode[lanes] < self.sample_episodes)
        uniforms = self.generators.uniforms(lanes[sampling])
        close = near_a_boundary(logits.numpy(), probs, sampling, uniforms, self.margin, self.cdf_margin)
        for row in np.flatnonzero(close):
            probs[row] = self.exact_probs(int(lanes[row]))
        self.recomputed += int(close.sum())
        return decided(probs, sampling, uniforms)

    def exact_probs(self, lane: int) -> np.ndarray:
        """The float64 model's action probabilities at lane `lane`'s last token: its full pass over the pair's tokens
        that reach it (each token attending to the `context` tokens up to it, as the cache holds)."""
        torch = _torch()
        tokens, episode = self.history.of(lane)
        tokens, episode = tokens[-self.exact.receptive_field:], episode[-self.exact.receptive_field:]
        with torch.no_grad():
            logits = self.exact(torch.as_tensor(tokens, dtype=torch.float64)[None], torch.as_tensor(episode)[None],
                                torch.ones(1, len(tokens), dtype=torch.bool))[0, -1]
            return torch.softmax(logits, dim=0).numpy()

    def observe(self, lanes: np.ndarray, transitions: Any) -> None:
        """Remember each lane's last observation, action and reward for its next token."""
        self.previous_obs[lanes] = state_vector(transitions.obs)
        self.previous_action[lanes] = transitions.action
        self.previous_reward[lanes] = transitions.reward

    def end_episode(self, lanes: np.ndarray) -> None:
        """The next token of these lanes starts their pair's next episode."""
        self.new_episode[lanes] = 1.0
        self.episode[lanes] += 1
