"""LeRobot recording, packing, catalog and verified download (SPEC section 8); never touches the Hub."""

from __future__ import annotations

import hashlib
import importlib.metadata
import http.server
import io
import json
import os
import tarfile
import threading
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from mewa_bench.datasets import (DatasetError, LeRobotSink, add_to_catalog, dataset_info, download, load_catalog,
                                 load_metadata, pack_dataset, task_description)
from mewa_bench.datasets import downloader as download_mod
from mewa_bench.design.suites import load_suite
from mewa_bench.envs.mewa_env import MewaEnv
from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.runner import EvaluationError, evaluate
from mewa_bench.protocol.agent import Transition
from mewa_bench.protocol.trajectory import EpisodeRecord, RunInfo, StepRecord, UnitRecord

REPO = Path(__file__).resolve().parents[1]
AGENT = REPO / "tests" / "agents" / "delayed_fault_agent.py"
REPO_ID = "local/mewa-test"


pytestmark = pytest.mark.usefixtures("offline_hub")  # lerobot caches in a temp dir, the Hub forbidden


def load_lerobot(root: Path):
    """Open a recorded dataset offline, as users do."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(REPO_ID, root=root, video_backend="pyav")


def read_frames(root: Path) -> pd.DataFrame:
    """All frames of a dataset, read with plain pandas."""
    files = sorted((root / "data").rglob("*.parquet"))
    assert files, f"no parquet files under {root / 'data'}"
    return pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)


def tree_digest(root: Path) -> str:
    """Hash of every file path and content under `root`."""
    h = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


# -- recording a real run ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Two pairs x one seed of the random agent, recorded as a LeRobot dataset."""
    tmp = tmp_path_factory.mktemp("recorded")
    sink = LeRobotSink(tmp / "ds", REPO_ID)
    config = EvalConfig(agent_path=AGENT, out=tmp / "r.json", agent_args={"fault": "none"}, seeds=(0,),
                        pairs=(0, 1), isolated=False)
    results, _ = evaluate(config, sinks=[sink])
    return results, tmp / "ds", sink


def test_recorded_counts_and_lerobot_load(recorded):
    results, root, sink = recorded
    ds = load_lerobot(root)
    lengths = [n for u in results["units"] for n in u["lengths"]]
    assert ds.num_episodes == 2 * 10 == len(lengths)
    assert ds.num_frames == len(ds) == sum(lengths) == sink.frames
    item = ds[0]
    assert item["observation.state"].shape == (18,) and str(item["observation.state"].dtype) == "torch.float32"
    assert str(item["action"].dtype) == "torch.int64"
    assert item["task"] == task_description("narrow-v1", 0, load_suite("narrow-v1").tasks[0].to_dict())
    assert item["task"] == "MEWA narrow-v1: order red>blue>green>orange, K=5, M=3"  # never the pair (= worker)
    assert "observation.images.top" not in ds.features  # vector mode: no images
    assert not (root / "images").exists()


def test_recorded_frames_equal_the_rollout(recorded):
    results, root, _ = recorded
    df = read_frames(root)
    suite = load_suite("narrow-v1")
    units = {(u["pair"], u["seed"]): u for u in results["units"]}
    episodes = df.groupby("episode_index", sort=True)
    assert len(episodes) == 20
    assert df["next.truncated"].astype(bool).any()  # random play runs out of steps: both episode ends are checked
    seen = set()
    for _, ep in episodes:
        pair, seed, k = (int(ep[c].iloc[0]) for c in ("pair_index", "seed", "episode_in_pair"))
        for col in ("pair_index", "seed", "episode_in_pair", "worker_index", "task_index_in_suite", "env_seed"):
            assert ep[col].nunique() == 1, col
        unit = units[(pair, seed)]
        seen.add((pair, seed, k))
        assert len(ep) == unit["lengths"][k]
        assert ep["frame_index"].tolist() == list(range(len(ep)))
        assert int(ep["env_seed"].iloc[0]) == unit["env_seeds"][k]
        assert int(ep["worker_index"].iloc[0]) == pair  # narrow-v1: every pair has its own worker
        assert float(ep["next.reward"].sum()) == pytest.approx(unit["returns"][k], abs=1e-4)
        done = ep["next.done"].tolist()
        assert done == [False] * (len(ep) - 1) + [True]
        # replay the recorded actions: every observation and reward must come back exactly
        p = suite.pairs[pair]
        env = MewaEnv(task=suite.tasks[p.task_index], worker=p.worker.w)
        obs, _ = env.reset(seed=unit["env_seeds"][k], options={"task": suite.tasks[p.task_index],
                                                                "worker": p.worker.w,
                                                                "luck_key": unit["env_seeds"][k]})
        for row in ep.itertuples(index=False):
            np.testing.assert_array_equal(np.asarray(row[df.columns.get_loc("observation.state")]), obs)
            obs, reward, terminated, truncated, _ = env.step(int(row.action))
            assert np.float32(reward) == row[df.columns.get_loc("next.reward")]
            assert bool(terminated) == bool(row[df.columns.get_loc("next.terminated")])
            assert bool(truncated) == bool(row[df.columns.get_loc("next.truncated")])
            np.testing.assert_array_equal(np.asarray(row[df.columns.get_loc("next.observation.state")]), obs)
    assert seen == {(p, 0, k) for p in (0, 1) for k in range(10)}


def test_recorded_actions_are_the_agents(recorded):
    """The agent draws rng(0).integers(0, 4) once per step, its rng reset per unit."""
    _, root, _ = recorded
    df = read_frames(root).sort_values("index")
    for pair in (0, 1):
        actions = df[df["pair_index"] == pair].sort_values(["episode_in_pair", "frame_index"])["action"].tolist()
        rng = np.random.default_rng(0)
        assert actions == [int(rng.integers(0, 4)) for _ in actions]


def test_recorded_metadata(recorded):
    results, root, _ = recorded
    meta = load_metadata(root)
    assert meta["suite"] == {"name": "narrow-v1", "sha256": results["suite"]["sha256"]}
    assert meta["policy"]["sha256"] == results["agent"]["sha256"] and meta["policy"]["name"] == "delayed_fault_agent"
    assert meta["policy"]["agent_args"] == {"fault": "none"} and "checkpoint" not in meta["policy"]  # what was set
    assert meta["seeds"] == [0] and meta["mewa_bench_version"] == results["package_version"]
    assert meta["lerobot_version"] == importlib.metadata.version("lerobot")
    assert [(u["pair"], u["first_episode_index"]) for u in meta["units"]] == [(0, 0), (1, 10)]
    assert meta["units"][0]["returns"] == results["units"][0]["returns"]
    assert meta["pairs"]["1"]["worker"] == list(load_suite("narrow-v1").pairs[1].worker.w)
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["total_episodes"] == 20


def test_failed_run_still_leaves_a_valid_dataset(tmp_path):
    """The agent crashes in the second unit: the first unit's episodes are finalized and loadable."""
    sink = LeRobotSink(tmp_path / "ds", REPO_ID)
    config = EvalConfig(agent_path=AGENT, out=tmp_path / "r.json", agent_args={"fault": "raise", "after_units": "1"},
                        seeds=(0,), pairs=(0, 1), isolated=False, lanes=1)
    with pytest.raises(EvaluationError):
        evaluate(config, sinks=[sink])
    ds = load_lerobot(tmp_path / "ds")
    assert ds.num_episodes == 10
    units = load_metadata(tmp_path / "ds")["units"]
    assert [(u["pair"], u["episodes"], u["complete"]) for u in units] == [(0, 10, True)]


def test_sink_refuses_an_existing_root_and_closes_idempotently(tmp_path):
    (tmp_path / "ds").mkdir()
    with pytest.raises(FileExistsError, match="already exists"):
        LeRobotSink(tmp_path / "ds", REPO_ID).start(_run_info())
    sink = LeRobotSink(tmp_path / "empty", REPO_ID)
    sink.start(_run_info())
    sink.close()
    sink.close()
    assert not (tmp_path / "empty").exists()  # no unit: nothing written


# -- synthetic images -------------------------------------------------------------------------------

def _run_info(mode: str = "sapien") -> RunInfo:
    return RunInfo(agent="handmade", agent_sha256="0" * 64, suite="narrow-v1", suite_sha256="f" * 64, seeds=(3,),
                   episodes_per_pair=2, env_id="mewa/MEWA-v0", env_version="v0", package_version="0.1.0", mode=mode)


def _synthetic_unit(side: int, steps: int = 3, episodes: int = 2) -> UnitRecord:
    """A hand-made unit whose image pixels encode (episode, step)."""
    task = load_suite("narrow-v1").tasks[0].to_dict()
    eps = []
    for e in range(episodes):
        img = lambda t: np.full((side, side, 3), (40 * e + 10 * t) % 256, dtype=np.uint8)  # noqa: E731
        recs = []
        for t in range(steps):
            obs = np.full(18, t, dtype=np.float32)
            image = img(t + 1)
            image[0, 0] = (t, e, 255)  # a pixel PNG must keep exactly
            seen = Transition({"state": obs, "image": img(t)}, t % 4, -0.5, {"state": obs + 1, "image": image},
                              t == steps - 1, False)
            recs.append(StepRecord(t, seen, 0, ()))
        eps.append(EpisodeRecord(e, 100 + e, tuple(recs), -0.5 * steps, 0.5, 0.6, first_image=img(0)))
    return UnitRecord(pair=5, seed=3, task_index=0, task=task, worker=(0.1, 0.2, 0.3, 0.4), episodes=tuple(eps))


def test_synthetic_images_round_trip(tmp_path):
    unit = _synthetic_unit(side=8)
    sink = LeRobotSink(tmp_path / "ds", REPO_ID, image_size=(8, 8))
    sink.start(_run_info())
    sink.add_unit(unit)
    sink.close()
    ds = load_lerobot(tmp_path / "ds")
    assert ds.features["observation.images.top"]["dtype"] == "image"
    assert ds.num_episodes == 2 and ds.num_frames == 6
    i = 0
    for episode in unit.episodes:
        for t, step in enumerate(episode.steps):
            item = ds[i]
            got = (item["observation.images.top"].numpy() * 255).round().astype(np.uint8).transpose(1, 2, 0)
            # the image of observation.state: the reset image, then the previous step's result
            expected = episode.first_image if t == 0 else episode.steps[t - 1].image
            np.testing.assert_array_equal(got, expected)
            assert got[1, 1, 0] == 40 * episode.episode + 10 * t
            np.testing.assert_array_equal(item["observation.state"].numpy(), step.obs)
            assert int(item["pair_index"]) == 5 and int(item["seed"]) == 3
            assert int(item["worker_index"]) == 0  # worker not in the suite: order of appearance
            i += 1
    df = read_frames(tmp_path / "ds")  # images are PNG bytes inside the parquet
    from PIL import Image

    png = Image.open(io.BytesIO(df["observation.images.top"].iloc[1]["bytes"]))
    np.testing.assert_array_equal(np.asarray(png), unit.episodes[0].steps[0].image)


def test_images_are_checked(tmp_path):
    sink = LeRobotSink(tmp_path / "a", REPO_ID, image_size=(16, 16))
    sink.start(_run_info())
    with pytest.raises(ValueError, match="expects"):
        sink.add_unit(_synthetic_unit(side=8))
    sink.close()
    sink = LeRobotSink(tmp_path / "b", REPO_ID, video=True)
    sink.start(_run_info())
    with pytest.raises(ValueError, match="at least 32"):  # SVT-AV1 crashes the process on tiny frames
        sink.add_unit(_synthetic_unit(side=8))
    sink.close()


def test_synthetic_images_as_video(tmp_path):
    unit = _synthetic_unit(side=32, steps=4, episodes=1)
    sink = LeRobotSink(tmp_path / "ds", REPO_ID, video=True)
    sink.start(_run_info())
    sink.add_unit(unit)
    sink.close()
    ds = load_lerobot(tmp_path / "ds")
    assert ds.features["observation.images.top"]["dtype"] == "video"
    episode = unit.episodes[0]
    for i, image in enumerate([episode.first_image] + [s.image for s in episode.steps[:-1]]):
        got = ds[i]["observation.images.top"].numpy().transpose(1, 2, 0) * 255
        assert np.abs(got - image).mean() < 8  # AV1 is lossy


# -- packing and the catalog ------------------------------------------------------------------------

def make_fake_dataset(root: Path, episodes: int = 2, frames: int = 7, payload: bytes = b"frames") -> Path:
    """A minimal directory with LeRobot's info.json and a data file (enough for pack/download)."""
    (root / "meta").mkdir(parents=True)
    (root / "data" / "chunk-000").mkdir(parents=True)
    (root / "meta" / "info.json").write_text(json.dumps({"codebase_version": "v3.0", "total_episodes": episodes,
                                                         "total_frames": frames}))
    (root / "data" / "chunk-000" / "file-000.parquet").write_bytes(payload)
    return root


def test_pack_is_deterministic(tmp_path):
    ds = make_fake_dataset(tmp_path / "ds")
    a = pack_dataset(ds, tmp_path / "a", "tiny", "1", "narrow-v1", "random")
    for f in ds.rglob("*"):
        os.utime(f, (1_000_000, 1_000_000))  # other mtimes must not change the bytes
    os.chmod(ds / "meta" / "info.json", 0o600)
    b = pack_dataset(ds, tmp_path / "b", "tiny", "1", "narrow-v1", "random", url_base="https://example.org/d/")
    assert a["sha256"] == b["sha256"] and a["size"] == b["size"]
    assert (tmp_path / "a" / "tiny-1.tar.gz").read_bytes() == (tmp_path / "b" / "tiny-1.tar.gz").read_bytes()
    assert b["url"] == "https://example.org/d/tiny-1.tar.gz" and a["url"].startswith("file://")
    beside = pack_dataset(ds, tmp_path / "a", "tiny", "1", "narrow-v1", "random", catalog_dir=tmp_path / "a")
    assert beside["url"] == "tiny-1.tar.gz"  # an archive in the catalog's folder travels with it: a relative URL
    assert (a["episodes"], a["frames"]) == (2, 7)
    with tarfile.open(tmp_path / "a" / "tiny-1.tar.gz") as tar:
        names = tar.getnames()
        assert names == sorted(names) and names[0] == "tiny"
        assert all(m.mtime == 0 and m.uid == 0 and m.uname == "" for m in tar.getmembers())
    (ds / "data" / "chunk-000" / "file-000.parquet").write_bytes(b"other frames")
    c = pack_dataset(ds, tmp_path / "c", "tiny", "1", "narrow-v1", "random")
    assert c["sha256"] != a["sha256"]


def test_catalog_add_replace_and_lookup(tmp_path):
    ds = make_fake_dataset(tmp_path / "ds")
    path = tmp_path / "datasets" / "index.json"
    e1 = pack_dataset(ds, tmp_path / "out", "tiny", "9", "narrow-v1", "random")
    add_to_catalog(path, e1)
    add_to_catalog(path, {**e1, "policy": "replaced"})
    add_to_catalog(path, {**e1, "version": "10"})
    catalog = load_catalog(path)
    assert catalog["datasets"] == []  # a dataset without training metadata is never listed as training data
    assert [(e["version"], e["policy"]) for e in catalog["evaluation_recordings"]] == [("9", "replaced"), ("10", "random")]
    assert dataset_info(catalog, "tiny")["version"] == "10"  # newest: 10 > 9 numerically
    assert dataset_info(catalog, "tiny@9")["policy"] == "replaced"
    with pytest.raises(DatasetError, match="not in the catalog"):
        dataset_info(catalog, "nope")
    assert not [p for p in path.parent.iterdir() if p.name != "index.json"]  # atomic write left no temp file


@pytest.mark.parametrize("change, message", [
    ({"sha256": "abc"}, "sha256"),
    ({"episodes": "2"}, "episodes"),
    ({"hf_repo_id": "u/r"}, "exactly one"),
    ({"name": "../evil"}, "name"),
    ({"url": "ftp://x/y.tar.gz"}, "url"),
])
def test_catalog_rejects_bad_entries(tmp_path, change, message):
    entry = {"name": "tiny", "version": "1", "suite": "narrow-v1", "policy": "random", "episodes": 2, "frames": 7,
             "size": 10, "sha256": "0" * 64, "url": "https://example.org/tiny-1.tar.gz", **change}
    path = tmp_path / "index.json"
    path.write_text(json.dumps({"format_version": 1, "datasets": [entry]}))
    with pytest.raises(DatasetError, match=message):
        load_catalog(path)


def test_missing_or_broken_catalog(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        load_catalog(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text('{"format_version": 1, "datasets": [')
    with pytest.raises(DatasetError, match="not valid JSON"):
        load_catalog(tmp_path / "bad.json")


# -- download over real HTTP ------------------------------------------------------------------------

class Routes(http.server.BaseHTTPRequestHandler):
    """Serves `routes[path] = (status, body, declared_length)`; sends only `body` (short if declared is larger)."""

    routes: dict[str, tuple[int, bytes, int]] = {}

    def do_GET(self):  # noqa: N802 - http.server's name
        status, body, declared = self.routes.get(self.path, (404, b"not found", 9))
        self.send_response(status)
        self.send_header("Content-Length", str(declared))
        self.end_headers()
        self.wfile.write(body)
        self.wfile.flush()
        self.close_connection = True

    def log_message(self, *args):
        pass


@pytest.fixture
def server():
    """A local HTTP server on an ephemeral port; yields (base URL, routes dict)."""
    routes: dict[str, tuple[int, bytes, int]] = {}
    handler = type("Handler", (Routes,), {"routes": routes})
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}", routes
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join()


@pytest.fixture(scope="module")
def packed(recorded, tmp_path_factory):
    """The recorded dataset packed, with its catalog entry and archive bytes."""
    out = tmp_path_factory.mktemp("packed")
    entry = pack_dataset(recorded[1], out, "mewa-test", "1", "narrow-v1", "delayed_fault_agent")
    return entry, (out / "mewa-test-1.tar.gz").read_bytes()


def _catalog(entry: dict, base: str, **urls: str) -> dict:
    """A catalog whose versions of `entry` point at different server paths."""
    return {"format_version": 1,
            "datasets": [{**entry, "version": version, "url": f"{base}{path}"} for version, path in urls.items()]}


def test_download_verify_and_failures_keep_the_good_copy(tmp_path, server, packed):
    base, routes = server
    entry, data = packed
    bad = bytearray(data)
    bad[len(bad) // 2] ^= 0xFF
    routes["/good.tar.gz"] = (200, data, len(data))
    routes["/corrupt.tar.gz"] = (200, bytes(bad), len(bad))
    routes["/short.tar.gz"] = (200, data[: len(data) // 3], len(data))
    routes["/error.tar.gz"] = (500, b"boom", 4)
    catalog = _catalog(entry, base, good="/good.tar.gz", corrupt="/corrupt.tar.gz", short="/short.tar.gz",
                       error="/error.tar.gz")
    dest = tmp_path / "data"
    calls = []
    got = download("mewa-test@good", catalog, dest, progress=lambda done, total: calls.append((done, total)))
    assert got.path == dest / "mewa-test" and got.verified and got.sha256 == entry["sha256"]
    assert calls[0] == (0, len(data)) and calls[-1] == (len(data), len(data))
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)
    ds = load_lerobot(got.path)
    assert ds.num_frames == entry["frames"] and ds.num_episodes == entry["episodes"]
    good = tree_digest(got.path)
    for version, message in (("corrupt", "sha256 mismatch"), ("short", f"{len(data) // 3} of {len(data)} bytes"),
                             ("error", "HTTP 500")):
        with pytest.raises(DatasetError, match=message) as err:
            download(f"mewa-test@{version}", catalog, dest)
        assert f"{base}/{version}" in str(err.value)  # names the URL
        assert tree_digest(dest / "mewa-test") == good
        assert sorted(os.listdir(dest)) == ["mewa-test"]  # no temp files or folders left
    again = download("mewa-test@good", catalog, dest)  # a good download replaces the copy
    assert again.path == dest / "mewa-test" and tree_digest(again.path) == good
    assert sorted(os.listdir(dest)) == ["mewa-test"]


def test_download_direct_url_with_and_without_sha256(tmp_path, server, packed):
    base, routes = server
    entry, data = packed
    routes["/mewa-test-1.tar.gz"] = (200, data, len(data))
    url = f"{base}/mewa-test-1.tar.gz"
    dest = tmp_path / "data"
    with pytest.raises(DatasetError, match="sha256 mismatch"):
        download(url, None, dest, sha256="0" * 64)
    assert os.listdir(dest) == []
    got = download(url, None, dest, sha256=entry["sha256"])
    assert got.name == "mewa-test-1" and got.verified
    unverified = download(url, None, dest, name="other")
    assert not unverified.verified and unverified.sha256 == entry["sha256"]
    assert sorted(os.listdir(dest)) == ["mewa-test-1", "other"]


def test_download_connection_refused(tmp_path):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    with pytest.raises(DatasetError, match="cannot connect"):
        download(f"http://127.0.0.1:{port}/x.tar.gz", None, tmp_path)
    assert os.listdir(tmp_path) == []


def _evil_archive(path: Path, member: str, link: bool = False) -> Path:
    """A .tar.gz with a valid dataset plus one dangerous member."""
    with tarfile.open(path, "w:gz") as tar:
        info_json = json.dumps({"total_episodes": 2, "total_frames": 7}).encode()
        for name, data in (("evil/meta/info.json", info_json), (member, b"pwned")):
            info = tarfile.TarInfo(name)
            if link and name == member:
                info.type, info.linkname = tarfile.SYMTYPE, "/etc/passwd"
                tar.addfile(info)
            else:
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
    return path


@pytest.mark.parametrize("member, link", [("../escaped.txt", False), ("evil/../../escaped.txt", False),
                                          ("/tmp/mewa-escaped.txt", False), ("evil/data/link", True)])
def test_path_traversal_archive_rejected(tmp_path, member, link):
    archive = _evil_archive(tmp_path / "evil.tar.gz", member, link)
    dest = tmp_path / "dest"
    good = make_fake_dataset(dest / "evil")
    before = tree_digest(good)
    sha = hashlib.sha256(archive.read_bytes()).hexdigest()
    with pytest.raises(DatasetError, match="unsafe archive member"):
        download(archive.as_uri(), None, dest, sha256=sha)
    assert not (tmp_path / "escaped.txt").exists() and not Path("/tmp/mewa-escaped.txt").exists()
    assert tree_digest(good) == before and sorted(os.listdir(dest)) == ["evil"]


def test_hub_download_is_atomic(tmp_path, monkeypatch):
    """The Hub call itself is replaced; the surrounding fetch-check-install logic is real."""
    calls = []

    def fake_snapshot(repo_id, local_dir, revision=None):
        calls.append(repo_id)
        make_fake_dataset(local_dir, payload=repo_id.encode())
        (local_dir / ".cache" / "huggingface").mkdir(parents=True)

    monkeypatch.setattr(download_mod, "hub_snapshot", fake_snapshot)
    dest = tmp_path / "data"
    got = download("someone/mewa-narrow-rts", None, dest)
    assert calls == ["someone/mewa-narrow-rts"] and got.path == dest / "mewa-narrow-rts" and not got.verified
    assert not (got.path / ".cache").exists() and (got.path / "meta" / "info.json").is_file()
    good = tree_digest(got.path)

    def failing(repo_id, local_dir, revision=None):
        local_dir.mkdir(parents=True)
        (local_dir / "partial").write_text("half")
        raise ConnectionError("offline")

    def not_a_dataset(repo_id, local_dir, revision=None):
        local_dir.mkdir(parents=True)
        (local_dir / "README.md").write_text("hello")

    for fake, message in ((failing, "download failed: ConnectionError"), (not_a_dataset, "not a LeRobot dataset")):
        monkeypatch.setattr(download_mod, "hub_snapshot", fake)
        with pytest.raises(DatasetError, match=message) as err:
            download("someone/mewa-narrow-rts", None, dest)
        assert "someone/mewa-narrow-rts" in str(err.value)
        assert tree_digest(dest / "mewa-narrow-rts") == good and sorted(os.listdir(dest)) == ["mewa-narrow-rts"]


def test_hub_entry_in_catalog(tmp_path, monkeypatch):
    monkeypatch.setattr(download_mod, "hub_snapshot", lambda repo_id, local_dir, revision=None:
                        make_fake_dataset(local_dir, episodes=3, frames=9))
    entry = {"name": "hubbed", "version": "1", "suite": "narrow-v1", "policy": "random", "episodes": 2, "frames": 7,
             "hf_repo_id": "someone/hubbed"}
    with pytest.raises(DatasetError, match="total_episodes = 3, the catalog says 2"):
        download("hubbed", {"format_version": 1, "datasets": [entry]}, tmp_path)
    assert os.listdir(tmp_path) == []


def test_unknown_source(tmp_path):
    with pytest.raises(DatasetError, match="not a catalog dataset"):
        download("no-such-thing", None, tmp_path)


def test_a_vector_agent_records_the_same_frames_as_its_one_lane_twin(tmp_path):
    """`record` plays batched agents in isolated lanes; the dataset equals the one-lane twin's, frame by frame."""
    agents = REPO / "tests" / "agents"
    frames = {}
    for name, lanes in (("vector_agent", 4), ("vector_twin_agent", 1)):
        sink = LeRobotSink(tmp_path / name, REPO_ID)
        config = EvalConfig(agent_path=agents / f"{name}.py", out=tmp_path / f"{name}.json", seeds=(0, 1),
                            pairs=(0, 3), lanes=lanes, agent_args={"sampled": "true", "seed": "2"})
        results, _ = evaluate(config, sinks=[sink])
        df = read_frames(tmp_path / name)
        assert len(df) == sum(sum(u["lengths"]) for u in results["units"])
        assert len(load_lerobot(tmp_path / name)) == len(df)
        keys = ["pair_index", "seed", "episode_in_pair", "frame_index"]
        frames[name] = df.sort_values(keys)[[*keys, "action", "next.reward"]].reset_index(drop=True)
    pd.testing.assert_frame_equal(frames["vector_agent"], frames["vector_twin_agent"])
