"""`mewa-bench datasets export --format minari`: read back with Minari's own reader and replayed in its recovered env."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from mewa_bench.cli import app
from mewa_bench.datasets import build_training_dataset, training_spec
from mewa_bench.design.suites import load_suite

pytestmark = pytest.mark.usefixtures("offline_hub")  # lerobot caches in a temp dir, the Hub forbidden
# Two meta-episodes of ten episodes of random play, which runs out of steps often (truncations to check).
SPEC = replace(training_spec("narrow-v2-train-random", 300), meta_batch=2)
DATASET_ID = SPEC.dataset_id  # a 300-frame build is its own dataset: mewa/narrow-v2-train-random-frames300-v1


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, Path]:
    """A tiny training dataset (two meta-episodes of ten episodes) and its Minari export, made by the CLI."""
    root = tmp_path_factory.mktemp("minari")
    build_training_dataset(SPEC, root / "source", jobs=1)
    result = CliRunner().invoke(app, ["datasets", "export", str(root / "source"), "--format", "minari",
                                      "--out", str(root / "minari")])
    assert result.exit_code == 0, result.output
    return root / "source", root / "minari"


@pytest.fixture
def dataset(exported, monkeypatch):
    import minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(exported[1]))
    return minari.load_dataset(DATASET_ID)


def lerobot_frames(root: Path):
    import pandas as pd

    return pd.concat([pq.read_table(f).to_pandas() for f in sorted((root / "data").rglob("*.parquet"))],
                     ignore_index=True)


def test_the_same_episodes_and_steps(exported, dataset) -> None:
    df = lerobot_frames(exported[0])
    assert dataset.total_episodes == df["episode_index"].nunique() == 20
    assert dataset.total_steps == len(df)
    for episode in dataset.iterate_episodes():
        rows = df[df["episode_index"] == episode.id]
        np.testing.assert_array_equal(episode.observations[:-1], np.stack(rows["observation.state"]))
        np.testing.assert_array_equal(episode.observations[-1], rows["next.observation.state"].iloc[-1])
        np.testing.assert_array_equal(episode.actions, rows["action"].to_numpy().reshape(-1))
        np.testing.assert_array_equal(episode.rewards.astype(np.float32), rows["next.reward"].to_numpy().reshape(-1))
        np.testing.assert_array_equal(episode.terminations, rows["next.terminated"].to_numpy().reshape(-1))
        np.testing.assert_array_equal(episode.truncations, rows["next.truncated"].to_numpy().reshape(-1))
        assert episode.terminations[-1] or episode.truncations[-1]
        info = episode.infos
        assert len(info["luck_key"]) == len(rows) + 1
        for key in ("meta_episode_index", "episode_in_meta_episode", "suite_task_index", "luck_key"):
            assert (info[key] == rows[key].iloc[0]).all(), key
        np.testing.assert_array_equal(info["worker"][0], rows["worker"].iloc[0])
        np.testing.assert_array_equal(info["optimal_action"][:-1], rows["optimal_action"].to_numpy().reshape(-1))
        assert info["optimal_action"][-1] == -1


def test_the_recovered_env_replays_every_episode_exactly(dataset) -> None:
    env = dataset.recover_environment()
    assert env.spec.id == "mewa/MEWA-v0"
    metadata = list(dataset.storage.get_episode_metadata(range(dataset.total_episodes)))
    for episode, meta in zip(dataset.iterate_episodes(), metadata):
        obs, _ = env.reset(options=meta["options"])
        np.testing.assert_array_equal(obs, episode.observations[0])
        for t, action in enumerate(episode.actions):
            obs, reward, terminated, truncated, _ = env.step(int(action))
            np.testing.assert_array_equal(obs, episode.observations[t + 1])
            assert reward == episode.rewards[t]  # float64, exactly the env's
            assert (terminated, truncated) == (episode.terminations[t], episode.truncations[t])


def test_the_metadata_is_minaris_own(exported, dataset) -> None:
    import json

    import minari

    meta = dataset.storage.metadata
    mewa = json.loads((exported[0] / "meta" / "mewa.json").read_text())
    assert meta["algorithm_name"] == "random"
    assert dataset.spec.env_spec.id == "mewa/MEWA-v0" and dataset.spec.env_spec.kwargs["tasks"][0]["name"] == \
        load_suite("narrow-v2").tasks[0].name  # the data's distribution: the suite's tasks, meta-train workers
    assert minari.__version__ in meta["minari_version"]
    assert dataset.observation_space.shape == (18,) and dataset.action_space.n == 4
    task = load_suite("narrow-v2").tasks[0]
    r_min = task.T * task.rewards[0]  # SPEC section 2's bounds, written out
    r_max = (task.M - 1) * task.rewards[0] + task.M * sum(task.rewards[1:])
    random = np.mean([m["random"] for m in mewa["meta_episodes"]])
    assert meta["ref_min_score"] == pytest.approx(r_min + random * (r_max - r_min), abs=1e-12)
    np.testing.assert_allclose(minari.get_normalized_score(dataset, np.array([meta["ref_min_score"],
                                                                            meta["ref_max_score"]])), [0.0, 1.0])
    returns = np.array([e.rewards.sum() for e in dataset.iterate_episodes()])
    assert meta["ref_min_score"] < returns.mean() < meta["ref_max_score"]  # raw returns, not normalised ones


def test_an_existing_export_is_never_overwritten(exported) -> None:
    result = CliRunner().invoke(app, ["datasets", "export", str(exported[0]), "--format", "minari",
                                      "--out", str(exported[1])])
    assert result.exit_code == 1 and "already exists" in result.output
    result = CliRunner().invoke(app, ["datasets", "export", "no-such-dataset", "--out", str(exported[1])])
    assert result.exit_code == 1 and "download it first" in result.output


def test_a_build_from_before_next_truncated_exports_the_same_truncations(exported) -> None:
    """A version 1.0.0 build has no `next.truncated`: its truncations are `next.done` and not `next.terminated`,
    the values the column holds."""
    from mewa_bench.datasets.minari_export import _episode_buffers, _frames

    frames, tasks = _frames(exported[0]), load_suite("narrow-v2").tasks
    older = {k: v for k, v in frames.items() if k != "next.truncated"}
    now, before = list(_episode_buffers(frames, tasks)), list(_episode_buffers(older, tasks))
    assert sum(int(np.sum(b.truncations)) for b in now) > 0  # the data holds truncations to compare
    for a, b in zip(now, before, strict=True):
        np.testing.assert_array_equal(a.truncations, b.truncations)
        np.testing.assert_array_equal(a.terminations, b.terminations)
