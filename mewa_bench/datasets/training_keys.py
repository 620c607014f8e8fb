"""Luck keys of training data, from a key space disjoint from the evaluation protocol's.

The protocol plays every episode with luck key = env seed = sha256("<suite hash>/<pair>/<seed>/<episode>")
(`mewa_bench.protocol.config.env_seed`). A training episode's key is sha256 of
"mewa-bench/training-data/<dataset id>/<meta-episode>/<episode>": the hashed texts of the two
spaces can never be equal (a protocol text starts with 64 hex digits and has three '/'), so the keys
meet only through a 63-bit sha256 collision; `check_training_keys` also compares them with every
key of the ranked protocol (each shipped suite's default seeds), so a dataset with one is refused.
"""

from __future__ import annotations

import hashlib
from functools import lru_cache

import numpy as np

TRAINING_KEY_PREFIX = "mewa-bench/training-data"
PROTOCOL_EPISODES = 10  # episodes per (pair, seed) unit under the protocol


class TrainingDataError(ValueError):
    """A training dataset that would touch the evaluation set (a curated worker, a protocol luck key), or
    one that is malformed; the message says what and where."""


def training_luck_key(dataset_id: str, meta_episode: int, episode: int) -> int:
    """The luck key of one training episode: an int in [0, 2**63)."""
    digest = hashlib.sha256(f"{TRAINING_KEY_PREFIX}/{dataset_id}/{meta_episode}/{episode}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def training_luck_keys(dataset_id: str, meta_episodes: np.ndarray, episodes: np.ndarray) -> np.ndarray:
    """Luck keys of many training episodes, uint64 [n]."""
    return np.array([training_luck_key(dataset_id, int(m), int(e)) for m, e in zip(meta_episodes, episodes)],
                    dtype=np.uint64)


@lru_cache(maxsize=1)
def protocol_luck_keys() -> np.ndarray:
    """Every luck key of the ranked protocol on the shipped suites (each suite's default seeds), sorted uint64."""
    from mewa_bench.design.suites import ALL_SUITES, load_suite
    from mewa_bench.protocol.config import default_seeds, env_seed

    keys = []
    for name in ALL_SUITES:
        suite = load_suite(name)
        for pair in range(len(suite.pairs)):
            for seed in default_seeds(name):
                keys.extend(env_seed(suite.sha256, pair, seed, e) for e in range(PROTOCOL_EPISODES))
    return np.unique(np.array(keys, dtype=np.uint64))


def check_training_keys(keys: np.ndarray, where: str) -> None:
    """Raise TrainingDataError if any key is one the protocol plays (or not a valid luck key)."""
    arr = np.asarray(keys)
    if arr.size and (arr.dtype.kind not in "iu" or (arr.dtype.kind == "i" and arr.min() < 0)
                     or int(arr.max()) >= 1 << 63):
        raise TrainingDataError(f"{where}: luck keys must be ints in [0, 2**63)")
    hits = np.flatnonzero(np.isin(arr.astype(np.uint64), protocol_luck_keys()))
    if hits.size:
        raise TrainingDataError(f"{where}: {hits.size} episode(s) use a luck key of the evaluation protocol "
                                f"(first: row {int(hits[0])}, key {int(arr[hits[0]])}); training data must never "
                                "replay the ranked episodes")
