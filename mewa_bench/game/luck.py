"""Coupled worker luck (protocol v2): every mistake draw of an episode fixed by one luck key.

The j-th time (j = 0, 1, ...) the structure of colour c receives its second block in an episode,
the worker makes a mistake of type x if `uniform(key, c, j) < w[x]`. Each draw is still an
independent Bernoulli(w[x]), so the game (the MDP) is the one of SPEC section 2; what the key adds
is that two policies played with the same key meet the same luck wherever their paths allow
(common random numbers), which is what paired comparisons and control variates feed on.

`uniform` is a counter-based generator (the SplitMix64 output function applied to
`key + (index + 1) * golden`), so a draw costs the same wherever it is needed: in the scalar env,
the batched env and the reference replays of the evaluation runner, which all call this module.
"""

from __future__ import annotations

import numpy as np

from mewa_bench.game.palette import NUM_COLORS

KEY_BOUND = 1 << 63  # luck keys are ints in [0, 2**63)
_COLOR_STRIDE = 1 << 32  # draw index = colour * stride + j
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)


def draws_per_color(horizon: int) -> int:
    """Most second blocks one colour can receive in `horizon` steps (each needs two blocks)."""
    return (horizon + 1) // 2


def uniforms(keys: np.ndarray | int, colors: np.ndarray | int, j: np.ndarray | int) -> np.ndarray:
    """u(key, c, j) in [0, 1) for broadcastable arrays of keys, colours and draw counters."""
    k = np.atleast_1d(np.asarray(keys, dtype=np.uint64))
    index = np.asarray(colors, dtype=np.uint64) * np.uint64(_COLOR_STRIDE) + np.asarray(j, dtype=np.uint64)
    z = k + (np.atleast_1d(index) + np.uint64(1)) * _GOLDEN  # uint64 arithmetic wraps, as intended
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def episode_table(key: int, horizon: int) -> list[list[float]]:
    """All draws of one episode as nested lists, [colour][j]."""
    j = np.arange(draws_per_color(horizon))
    return uniforms(key, np.arange(NUM_COLORS)[:, None], j[None, :]).tolist()


_MASK = (1 << 64) - 1
_G, _M1, _M2 = int(_GOLDEN), int(_MIX1), int(_MIX2)


def uniform(key: int, color: int, j: int) -> float:
    """One draw u(key, color, j) with Python ints: the same number as `uniforms`, for the scalar env's step."""
    z = (key + (color * _COLOR_STRIDE + j + 1) * _G) & _MASK
    z = ((z ^ (z >> 30)) * _M1) & _MASK
    z = ((z ^ (z >> 27)) * _M2) & _MASK
    return ((z ^ (z >> 31)) >> 11) * (1.0 / (1 << 53))


def check_key(key: object) -> int:
    """A luck key as an int in [0, 2**63), or a ValueError saying what was wrong."""
    if isinstance(key, bool) or not isinstance(key, (int, np.integer)) or not 0 <= int(key) < KEY_BOUND:
        raise ValueError(f"luck_key must be an int in [0, 2**63), got {key!r}")
    return int(key)
