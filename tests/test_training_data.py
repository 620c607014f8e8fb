"""Training datasets: meta-train workers only, exact labels and reference scores, byte-reproducible, read by lerobot."""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from mewa_bench.datasets import (DatasetError, TrainingDataError, add_to_catalog, build_training_dataset,
                                 check_training_dataset, download, load_catalog, load_training_dataset, pack_dataset,
                                 training_spec)
from mewa_bench.datasets import training_data
from mewa_bench.datasets.training_data import dataset_suite, training_suite
from mewa_bench.datasets.bulk_writer import write_lerobot_dataset
from mewa_bench.design.exact import expected_returns
from mewa_bench.design.policies import toptimal_family
from mewa_bench.design.suites import ALL_SUITES, load_suite
from mewa_bench.envs.mewa_env import MewaEnv
from mewa_bench.game.table import transition_table
from mewa_bench.protocol.config import default_seeds, env_seed

SMALL = {"random": 600, "random-task-specific": 600, "learning-histories": 1, "expert": 1, "task-inferring-histories": 1,
         "generated-tasks": 1}
GENERATED = ("wide-v2", "generated-tasks")


pytestmark = pytest.mark.usefixtures("offline_hub")  # lerobot caches in a temp dir, the Hub forbidden


def small_spec(suite: str, tier: str):
    """A few meta-episodes of a tier (two per round; a pool of four generated tasks where it has one)."""
    spec = training_spec(f"{suite}-train-{tier}", SMALL[tier])
    return replace(spec, meta_batch=2, history_episodes=20, generated_tasks=min(spec.generated_tasks, 4))


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """One small dataset per tier on narrow-v2, and on wide-v2 (several tasks) the random task-specific tier and the
    task-inferring histories (whose learner must tell its look-alike tasks apart), also on generated tasks."""
    out = tmp_path_factory.mktemp("training")
    roots = {}
    tiers = ("random", "random-task-specific", "learning-histories", "expert")
    wide = [("wide-v2", "random-task-specific"), ("wide-v2", "task-inferring-histories"), GENERATED]
    for suite, tier in [("narrow-v2", t) for t in tiers] + wide:
        roots[(suite, tier)] = out / f"{suite}-{tier}"
        build_training_dataset(small_spec(suite, tier), roots[(suite, tier)], jobs=1)
    return roots


def frames(root: Path) -> pd.DataFrame:
    """All frames, read with plain pyarrow."""
    return pd.concat([pq.read_table(f).to_pandas() for f in sorted((root / "data").rglob("*.parquet"))],
                     ignore_index=True)


def meta(root: Path) -> dict:
    return json.loads((root / "meta" / "mewa.json").read_text())


def tasks_of(root: Path) -> tuple:
    """The tasks a dataset's `suite_task_index` indexes (its suite's, or its generated ones)."""
    return dataset_suite(meta(root), root).tasks


def curated() -> np.ndarray:
    """Every curated worker of every shipped suite, padded to 4 components with 0 (as the frames store them)."""
    rows = [list(p.worker.w) + [0.0] * (4 - len(p.worker.w)) for s in ALL_SUITES for p in load_suite(s).pairs]
    return np.array(rows)


def protocol_keys() -> set[int]:
    """The ranked protocol's luck keys (= env seeds) on every shipped suite."""
    out = set()
    for name in ALL_SUITES:
        suite = load_suite(name)
        for pair in range(len(suite.pairs)):
            for seed in default_seeds(name):
                out.update(env_seed(suite.sha256, pair, seed, e) for e in range(10))
    return out


def test_no_frame_has_a_curated_worker_or_a_protocol_luck_key(built):
    tests, keys = curated(), protocol_keys()
    for key, root in built.items():
        df = frames(root)
        workers = np.unique(np.stack(df["worker"].to_numpy()), axis=0)
        assert len(workers) == df["meta_episode_index"].nunique()  # one worker per meta-episode
        for w in workers:
            assert np.abs(tests - w).max(axis=1).min() > 1e-9, f"{key}: worker {w} is curated"
        assert not set(df["luck_key"].tolist()) & keys, key
        m = meta(root)
        assert m["kind"] == "training" and m["suite"]["name"] == key[0]
        assert len(m["meta_episodes"]) == df["meta_episode_index"].nunique()


def test_generated_tasks_are_the_wide_generators_drawn_from_the_datasets_seed(built):
    root = built[GENERATED]
    m, df, public = meta(root), frames(root), load_suite("wide-v2")
    tasks = tasks_of(root)
    assert m["spec"]["generated_tasks"] == len(tasks) == 4 and m["suite"]["sha256"] == public.sha256
    assert [t.name.split("-")[:2] for t in tasks] == [["generated", f"{i:03d}"] for i in range(4)]
    assert set(df["suite_task_index"]) <= set(range(4))
    assert check_training_dataset(root) == m  # every worker in its own generated task's meta-train support
    assert "generated tasks" in m["worker_distribution"]["task_choice"] and "generator drew" in m["columns"]["suite_task_index"]
    eq1 = {(t.N, t.M): t.rewards for t in public.tasks}  # Eq. 1's rewards depend on N and M only
    assert any((t.N, t.M) in eq1 for t in tasks)
    for task in tasks:
        assert (task.N, task.M) not in eq1 or np.allclose(task.rewards, eq1[(task.N, task.M)], rtol=0, atol=1e-11)
        assert [f["name"] for f in task.to_dict()["worker_distribution"]["families"]] == ["paper", "overloaded"]
        assert sum(task.worker_blocks) == 8 and task.M <= task.K
    spec = small_spec(*GENERATED)
    assert training_suite(replace(spec, generated_tasks=6)).tasks[:4] == tasks  # a larger pool starts with them
    assert "generated_tasks" not in meta(built[("wide-v2", "task-inferring-histories")])["spec"]  # bytes as before
    assert "task_structures" not in meta(built[("wide-v2", "task-inferring-histories")])["spec"] and "task_structures" not in m["spec"]
    with pytest.raises(ValueError, match="narrow-v2 has one task"):
        training_suite(replace(small_spec("narrow-v2", "random"), generated_tasks=3))


def test_a_dataset_from_a_test_worker_is_refused(tmp_path, monkeypatch):
    suite = load_suite("narrow-v2")
    test_worker = np.array(suite.pairs[3].worker.w)

    def sample(tasks, rng, n):  # the meta-train sampler replaced by one that hands out a curated worker
        return np.zeros(n, dtype=np.int64), np.tile(test_worker, (n, 1))

    monkeypatch.setattr(training_data, "sample_training_pairs", sample)
    with pytest.raises(TrainingDataError, match="curated test worker of narrow-v2 pair 3"):
        build_training_dataset(small_spec("narrow-v2", "random"), tmp_path / "bad", jobs=1)
    assert not (tmp_path / "bad").exists() and list(tmp_path.iterdir()) == []


def _tamper(root: Path, column: str, value) -> None:
    """Rewrite one frame's value of a column in place (as a hand-edited or malicious dataset would)."""
    path = sorted((root / "data").rglob("*.parquet"))[0]
    table = pq.read_table(path)
    values = table.column(column).to_pylist()
    values[5] = value
    i = table.schema.get_field_index(column)
    pq.write_table(table.set_column(i, table.schema.field(i), pa.array(values, type=table.schema.field(i).type)), path)


def test_a_tampered_dataset_is_refused_when_loaded(built, tmp_path):
    source = built[("narrow-v2", "random")]
    check_training_dataset(source)  # the good one passes
    worker = tmp_path / "worker"
    shutil.copytree(source, worker)
    _tamper(worker, "worker", list(load_suite("wide-v2").pairs[0].worker.w))
    with pytest.raises(TrainingDataError, match=r"worker \[0.0, 0.0, 0.0, 1.0\] .* is the curated test worker of"):
        load_training_dataset(worker)
    key = tmp_path / "key"
    shutil.copytree(source, key)
    suite = load_suite("narrow-v2")
    _tamper(key, "luck_key", env_seed(suite.sha256, 2, 7, 4))
    with pytest.raises(TrainingDataError, match="luck key of the evaluation protocol"):
        check_training_dataset(key)
    recording = tmp_path / "recording"
    shutil.copytree(source, recording)
    (recording / "meta" / "mewa.json").write_text(json.dumps({"format": "mewa-bench-lerobot"}))
    with pytest.raises(TrainingDataError, match="not a mewa-bench training dataset"):
        load_training_dataset(recording)


def _independent_q(task, worker: np.ndarray, horizon: int) -> np.ndarray:
    """Q[k, s, a] with k steps left, by plain backward induction over the rules' transition table."""
    table = transition_table(task)
    w = np.append(worker[: task.N], 0.0)
    p_bad = w[np.where(table.mistake_type < 0, task.N, table.mistake_type)]  # [S, 4]
    value = np.zeros(table.n_states)
    out = np.zeros((horizon + 1, table.n_states, 4))
    for k in range(1, horizon + 1):
        ok = table.reward[table.next_ok] + value[table.next_ok]
        bad = table.reward[table.next_mistake] + value[table.next_mistake]
        q = (1 - p_bad) * ok + p_bad * bad
        q[table.terminal] = 0.0
        out[k] = q
        value = q.max(axis=1)
    return out


def test_stored_optimal_actions_are_the_exact_optimum(built):
    rng = np.random.default_rng(5)
    for key in (("narrow-v2", "random"), ("narrow-v2", "learning-histories"), ("wide-v2", "random-task-specific"),
                GENERATED):
        root = built[key]
        df, tasks = frames(root), tasks_of(root)
        checked = 0
        for m in rng.choice(df["meta_episode_index"].unique(), size=2, replace=False):
            rows = df[df["meta_episode_index"] == m]
            task = tasks[int(rows["suite_task_index"].iloc[0])]
            q = _independent_q(task, np.asarray(rows["worker"].iloc[0]), task.T)
            table = transition_table(task)
            index = {o.tobytes(): i for i, o in enumerate(table.obs)}
            for _, frame in rows.sample(n=min(40, len(rows)), random_state=1).iterrows():
                s = index[np.asarray(frame["observation.state"], dtype=np.float32).tobytes()]
                qs = q[task.T - int(frame["frame_index"]), s]
                assert qs[int(frame["optimal_action"])] >= qs.max() - 1e-12, (key, m, dict(frame))
                checked += 1
        assert checked >= 20


def test_stored_reference_scores_are_the_exact_engines(built):
    for key, root in built.items():
        m, df = meta(root), frames(root)
        tasks = tasks_of(root)
        rand, best = [], []
        for record in m["meta_episodes"]:
            task = tasks[record["task"]]
            values = expected_returns(task, (*toptimal_family(task.N), "random"), [record["worker"]])[:, 0]
            rand.append(values[-1])
            best.append(values[:-1].max())
            assert abs(record["max_expected"] - values[:-1].max()) < 1e-11
        assert abs(m["ref_min_score"] - np.mean(rand)) < 1e-11 and abs(m["ref_max_score"] - np.mean(best)) < 1e-11
        if key[1] in ("expert", "task-inferring-histories", GENERATED[1]):
            assert "expected_return" not in df.columns  # an adaptive agent's behaviour has no fixed value
            continue
        first = df.groupby(["meta_episode_index", "episode_in_meta_episode"]).first()
        policies = m["behaviour"]["policies"]
        for (meta_index, _), frame in first.sample(n=6, random_state=2).iterrows():
            record = m["meta_episodes"][meta_index]
            task = tasks[record["task"]]
            policy = policies[record["task"]][int(frame["behaviour_policy"])]
            exact = expected_returns(task, (policy,), [record["worker"]])[0, 0]
            assert abs(frame["expected_return"] - exact) < 1e-11
            assert abs(frame["expected_score"] - exact / max(record["max_expected"], 0.1)) < 1e-11


def test_episodes_replay_in_the_env_with_their_luck_keys(built):
    for key in (("narrow-v2", "random"), ("narrow-v2", "expert"), ("wide-v2", "random-task-specific"),
                ("wide-v2", "task-inferring-histories"), GENERATED):
        df, tasks = frames(built[key]), tasks_of(built[key])
        env = MewaEnv(task=tasks[0], worker=[0.1] * tasks[0].N)
        for episode in (0, int(df["episode_index"].max())):
            rows = df[df["episode_index"] == episode]
            task = tasks[int(rows["suite_task_index"].iloc[0])]
            obs, _ = env.reset(options={"task": task, "worker": list(rows["worker"].iloc[0][: task.N]),
                                        "luck_key": int(rows["luck_key"].iloc[0])})
            for _, frame in rows.iterrows():
                assert np.array_equal(obs, frame["observation.state"])
                obs, reward, terminated, truncated, _ = env.step(int(frame["action"]))
                assert np.array_equal(obs, frame["next.observation.state"])
                assert np.float32(reward) == frame["next.reward"] and terminated == frame["next.terminated"]
                assert truncated == frame["next.truncated"]
            assert terminated or truncated


def test_a_truncation_is_marked_where_the_step_limit_ends_an_episode(built):
    """`next.truncated` is Gymnasium's: the episode's last frame when its T steps ran out before the task was done."""
    truncations = 0
    for root in built.values():
        df, tasks = frames(root), tasks_of(root)
        horizon = np.array([tasks[i].T for i in df["suite_task_index"]])
        last = np.r_[df["episode_index"].to_numpy()[1:] != df["episode_index"].to_numpy()[:-1], True]
        expected = last & (df["frame_index"].to_numpy() + 1 == horizon) & ~df["next.terminated"].to_numpy(bool)
        np.testing.assert_array_equal(df["next.truncated"].to_numpy(bool), expected)
        np.testing.assert_array_equal(df["next.done"].to_numpy(bool), df["next.terminated"].to_numpy(bool) | expected)
        truncations += int(expected.sum())
    assert truncations > 0  # the random tiers run out of steps


def test_meta_episodes_and_blocks_are_marked(built):
    m = meta(built[("narrow-v2", "learning-histories")])
    df = frames(built[("narrow-v2", "learning-histories")])
    assert m["episodes_per_meta_episode"] == 20 and set(df["episode_in_meta_episode"]) == set(range(20))
    assert (df["block_index"] == df["episode_in_meta_episode"] // 10).all()
    assert (df["episode_in_block"] == df["episode_in_meta_episode"] % 10).all()
    firsts = df.groupby("episode_index").first()
    assert (firsts["frame_index"] == 0).all() and firsts.groupby("meta_episode_index").size().eq(20).all()
    for tier in ("random", "expert"):
        d = frames(built[("narrow-v2", tier)])
        assert set(d["episode_in_meta_episode"]) == set(range(10)) and (d["block_index"] == 0).all()
    # the learner learns: its last block's exact expected score beats its first block's
    per_episode = firsts.groupby("episode_in_meta_episode")["expected_score"].mean()
    assert per_episode[10:].mean() > per_episode[:3].mean()


def _tree(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_a_rebuild_gives_the_same_bytes_and_sha256(built, tmp_path):
    for key in (("narrow-v2", "learning-histories"), ("wide-v2", "random-task-specific"), GENERATED):
        again = tmp_path / f"{key[0]}-{key[1]}"
        reports: list[tuple[str, int, int]] = []
        # parallel exact values, reported as they go: the same bytes
        build_training_dataset(small_spec(*key), again, jobs=2, progress=lambda *report: reports.append(report))
        assert _tree(again) == _tree(built[key])
        _check_progress(reports, small_spec(*key).frames, frames(again))
        a = pack_dataset(built[key], tmp_path / "a", "x", "1", key[0], key[1])
        b = pack_dataset(again, tmp_path / "b", "x", "1", key[0], key[1])
        assert a["sha256"] == b["sha256"] and a["kind"] == "training"
        assert a["ref_max_score"] == meta(again)["ref_max_score"]


def _check_progress(reports: list[tuple[str, int, int]], target: int, columns: pd.DataFrame) -> None:
    """A build's progress reports: phases in order, each from 0 to its total; the frames played add up to the
    dataset's, past the target only by whole rounds."""
    assert [phase for phase, _, _ in reports] == sorted((phase for phase, _, _ in reports),
                                                        key=["play", "exact", "write"].index)
    for phase in ("play", "exact", "write"):
        mine = [(done, total) for p, done, total in reports if p == phase]
        assert mine[0][0] == 0 and len(mine) >= 2, (phase, mine)
        assert all(a[0] <= b[0] for a, b in zip(mine, mine[1:])), (phase, mine)
        assert mine[-1][0] == mine[-1][1], (phase, mine)
    play = [(done, total) for p, done, total in reports if p == "play"]
    assert play[0] == (0, target) and play[-1][0] == len(columns["action"]) >= target


def test_lerobot_reads_every_dataset(built):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    for key, root in built.items():
        df, m = frames(root), meta(root)
        ds = LeRobotDataset(m["dataset_id"], root=root, video_backend="pyav")
        assert ds.num_frames == len(df) == m["total_steps"] and ds.num_episodes == m["total_episodes"]
        for i in (0, len(df) - 1):
            item = ds[i]
            assert item["optimal_action"].item() == df["optimal_action"][i]
            assert np.array_equal(item["observation.state"].numpy(), df["observation.state"][i])
            assert item["luck_key"].item() == df["luck_key"][i]
            assert item["episode_index"].item() == df["episode_index"][i]


def test_the_bulk_writer_matches_lerobots_own_writer(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {"observation.state": {"dtype": "float32", "shape": (3,), "names": ["a", "b", "c"]},
                "action": {"dtype": "int64", "shape": (1,), "names": ["colour"]},
                "next.done": {"dtype": "bool", "shape": (1,), "names": None},
                "worker": {"dtype": "float64", "shape": (4,), "names": None},
                "expected_return": {"dtype": "float64", "shape": (1,), "names": None}}
    rng = np.random.default_rng(0)
    lengths = [3, 5, 1, 4]
    tasks = ["task 0", "task 1", "task 0", "task 2"]
    n = sum(lengths)
    columns = {"observation.state": rng.random((n, 3)).astype(np.float32), "action": rng.integers(0, 4, n),
               "next.done": rng.random(n) < 0.3, "worker": rng.random((n, 4)), "expected_return": rng.random(n)}
    ours = tmp_path / "bulk"
    write_lerobot_dataset(ours, features, columns, np.array(lengths), tasks, 10, "mewa/MEWA-v0")
    theirs = LeRobotDataset.create("mewa/ref", 10, features=features, root=tmp_path / "ref",
                                   robot_type="mewa/MEWA-v0", use_videos=False)
    f = 0
    for length, task in zip(lengths, tasks):
        for _ in range(length):
            theirs.add_frame({**{k: np.atleast_1d(v[f]) for k, v in columns.items()}, "task": task})
            f += 1
        theirs.save_episode()
    theirs.finalize()
    ref = tmp_path / "ref"
    assert json.loads((ours / "meta/info.json").read_text()) == json.loads((ref / "meta/info.json").read_text())
    assert pd.read_parquet(ours / "meta/tasks.parquet").equals(pd.read_parquet(ref / "meta/tasks.parquet"))
    data = "data/chunk-000/file-000.parquet"
    a, b = pq.read_table(ours / data), pq.read_table(ref / data)
    assert a.schema.remove_metadata() == b.schema.remove_metadata()
    assert a.equals(b.replace_schema_metadata(a.schema.metadata))
    hf = lambda t: json.loads(t.schema.metadata[b"huggingface"])["info"]  # noqa: E731
    assert hf(a) == hf(b)
    episodes = "meta/episodes/chunk-000/file-000.parquet"
    ea, eb = pq.read_table(ours / episodes), pq.read_table(ref / episodes)
    assert ea.schema == eb.schema
    exact = [c for c in ea.column_names if not c.split("/")[-1].startswith("q")]  # lerobot's quantiles: histogram estimates
    for column in exact:
        x, y = ea.column(column).to_pylist(), eb.column(column).to_pylist()
        if column.startswith("stats/"):
            assert np.allclose(np.array(x, dtype=float), np.array(y, dtype=float)), column
        else:
            assert x == y, column
    sa, sb = (json.loads((root / "meta/stats.json").read_text()) for root in (ours, ref))
    assert sa.keys() == sb.keys()
    for key in sa:
        for stat in ("min", "max", "mean", "std", "count"):
            assert np.allclose(sa[key][stat], sb[key][stat]), (key, stat)
    mine = LeRobotDataset("mewa/bulk", root=ours, video_backend="pyav")
    for i in range(n):
        x, y = mine[i], theirs[i]
        assert x.keys() == y.keys() and all(str(x[k]) == str(y[k]) for k in x), i


def test_shipped_training_dataset_downloads_and_a_bad_copy_never_replaces_it(tmp_path):
    catalog_path = Path(__file__).resolve().parents[1] / "datasets" / "index.json"
    catalog = load_catalog(catalog_path)
    entry = catalog["datasets"][0]
    got = download(entry["name"], catalog, tmp_path / "data")
    assert got.verified and load_training_dataset(got.path).num_frames == entry["frames"]
    good = _tree(got.path)
    archive = Path(entry["url"].removeprefix("file://")).read_bytes()
    short = tmp_path / "short.tar.gz"
    short.write_bytes(archive[: len(archive) // 2])
    with pytest.raises(DatasetError, match="downloaded .* bytes, the catalog says"):
        download(entry["name"], {**catalog, "datasets": [{**entry, "url": short.as_uri()}]}, tmp_path / "data")
    assert _tree(got.path) == good
    # an archive that verifies (its own size and sha256) but holds a test worker is refused too
    bad_root = tmp_path / "bad" / entry["name"]
    shutil.copytree(got.path, bad_root)
    _tamper(bad_root, "worker", list(load_suite("narrow-v2").pairs[0].worker.w))
    bad = pack_dataset(bad_root, tmp_path / "packed", entry["name"], entry["version"], entry["suite"], entry["policy"])
    add_to_catalog(tmp_path / "index.json", bad)
    with pytest.raises(DatasetError, match="refused: .*curated test worker"):
        download(entry["name"], load_catalog(tmp_path / "index.json"), tmp_path / "data")
    assert _tree(got.path) == good and sorted(p.name for p in (tmp_path / "data").iterdir()) == [entry["name"]]


def test_shipped_training_dataset_rebuilds_to_its_catalog_sha256(tmp_path):
    from mewa_bench.datasets.build import build_named

    entry = load_catalog(Path(__file__).resolve().parents[1] / "datasets" / "index.json")["datasets"][0]
    result = build_named(entry["name"], tmp_path, jobs=1)
    assert result.entry["sha256"] == entry["sha256"] and result.matches_record is True
    assert load_catalog(tmp_path / "index.json")["datasets"][0]["sha256"] == entry["sha256"]


def test_the_expert_plays_the_same_episodes_in_parallel_processes():
    from mewa_bench.datasets.expert_rollout import play_expert_parallel
    from mewa_bench.datasets.tiers import expert_path
    from mewa_bench.datasets.training_workers import sample_training_pairs

    suite = load_suite("narrow-v2")
    task_idx, workers = sample_training_pairs(suite.tasks, np.random.default_rng(3), 3)
    keys = np.arange(1, 7, dtype=np.uint64).reshape(3, 2) * np.uint64(7919)
    seeds = np.array([11, 12, 13])
    path = expert_path("bayes-adaptive")
    one = play_expert_parallel(path, suite.name, suite.tasks, task_idx, workers, keys, seeds, jobs=1)
    two = play_expert_parallel(path, suite.name, suite.tasks, task_idx, workers, keys, seeds, jobs=2)
    for field in ("episode", "t", "state", "action", "next_state", "reward", "lengths", "returns"):
        assert np.array_equal(getattr(one, field), getattr(two, field)), field


@pytest.mark.slow  # about a minute; smaller rebuilds' bytes are checked by default (test_a_rebuild_gives_the_same_bytes...)
def test_a_full_size_build_gives_the_sha256_the_shipped_catalog_records(tmp_path):
    """The 1 M-frame random tier of narrow-v2 (about 20 s), rebuilt from scratch: the archive's sha256 is the one
    the shipped catalog's `builds` section records, so every recorded build can be checked the same way."""
    from mewa_bench.datasets.build import build_named

    catalog = load_catalog(Path(__file__).resolve().parents[1] / "datasets" / "index.json")
    recorded = {b["name"]: b for b in catalog["builds"]}
    assert {"narrow-v2-train-random", "wide-v2-train-learning-histories"} <= set(recorded)
    result = build_named("narrow-v2-train-random", tmp_path, jobs=2)
    assert result.entry["frames"] >= 1_000_000 and result.entry["frames"] == recorded["narrow-v2-train-random"]["frames"]
    assert result.matches_record is True, (result.entry["sha256"], result.recorded_sha256)


def test_a_build_with_another_frame_target_has_a_name_of_its_own(tmp_path):
    """`datasets build NAME --frames N` (N not the dataset's own target) builds NAME-framesN, says so, and holds the
    first rounds of a larger build (the same seeds)."""
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    result = CliRunner().invoke(app, ["datasets", "build", "narrow-v2-train-random", "--frames", "3000", "--jobs", "1",
                                      "--out", str(tmp_path)], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    root = tmp_path / "narrow-v2-train-random-frames3000"
    assert "built narrow-v2-train-random-frames3000" in " ".join(result.output.split())
    assert not (tmp_path / "narrow-v2-train-random").exists()
    assert meta(root)["name"] == "narrow-v2-train-random-frames3000"
    assert meta(root)["build_command"] == "mewa-bench datasets build narrow-v2-train-random --frames 3000"
    assert [e["name"] for e in load_catalog(tmp_path / "index.json")["datasets"]] == [root.name]
    larger = tmp_path / "larger"
    build_training_dataset(training_spec("narrow-v2-train-random", 30_000), larger, jobs=1)  # two rounds of 64
    small, big = frames(root), frames(larger)
    assert len(big) > len(small)
    for column in ("action", "luck_key", "optimal_action", "meta_episode_index"):
        assert np.array_equal(np.stack(big[column][:len(small)]), np.stack(small[column])), column
