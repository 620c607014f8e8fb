"""The record / datasets / evaluate --log commands end to end, and the shipped dataset catalog."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mewa_bench.cli import app
from mewa_bench.datasets.catalog import add_to_catalog, load_catalog, recorded_build
from mewa_bench.datasets.training_data import DEFAULT_VERSION
from mewa_bench.protocol.results import read_results

REPO = Path(__file__).resolve().parents[1]
CATALOG = REPO / "datasets" / "index.json"
runner = CliRunner()


@pytest.fixture(autouse=True)
def offline_hub(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")


def test_shipped_catalog_archives_match_their_entries() -> None:
    import io
    import tarfile

    from mewa_bench.design.suites import load_suite
    from mewa_bench.protocol.results import PROTOCOL_VERSION

    raw = json.loads(CATALOG.read_text())
    recordings = raw["evaluation_recordings"]
    assert {"narrow-v1", "narrow-v2", "wide-v2"} <= {entry["suite"] for entry in recordings}
    assert all(entry["kind"] == "training" for entry in raw["datasets"])  # never a recording of test pairs
    for entry in raw["datasets"]:  # the shipped training data: archive and metadata agree
        data = (CATALOG.parent / entry["url"]).read_bytes()
        assert len(data) < 2**20 and len(data) == entry["size"] and hashlib.sha256(data).hexdigest() == entry["sha256"]
        assert entry["suite_sha256"] == load_suite(entry["suite"]).sha256
        with tarfile.open(fileobj=io.BytesIO(data)) as tar:
            meta_file = next(m for m in tar.getmembers() if m.name.endswith("meta/mewa.json"))
            meta = json.loads(tar.extractfile(meta_file).read())
        assert meta["kind"] == "training" and meta["behaviour"]["sha256"] == entry["policy_sha256"]
        assert (meta["ref_min_score"], meta["ref_max_score"]) == (entry["ref_min_score"], entry["ref_max_score"])
    for entry in recordings:
        assert entry["kind"] == "evaluation-recording" and "TEST pairs" in entry["warning"]
        archive = CATALOG.parent / entry["url"]  # shipped archives sit beside the catalog
        data = archive.read_bytes()
        assert len(data) == entry["size"] and hashlib.sha256(data).hexdigest() == entry["sha256"]
        assert entry["suite_sha256"] == load_suite(entry["suite"]).sha256
        # recorded by the code as it is now: a baseline policy by the policy agent, else the submission's agent.py
        baseline = REPO / "mewa_bench" / "protocol" / "policy_agent.py"
        agent = REPO / "submissions" / entry["policy"] / "agent.py"
        current = {hashlib.sha256(path.read_bytes()).hexdigest() for path in (baseline, agent) if path.exists()}
        assert entry["policy_sha256"] in current, f"{entry['name']}: re-record it with this version"
        with tarfile.open(fileobj=io.BytesIO(data)) as tar:
            meta_file = next(m for m in tar.getmembers() if m.name.endswith("meta/mewa.json"))
            meta = json.loads(tar.extractfile(meta_file).read())
        assert meta["protocol_version"] == PROTOCOL_VERSION, f"{entry['name']}: re-record under this protocol"
        assert meta["policy"]["sha256"] == entry["policy_sha256"] and meta["suite"]["name"] == entry["suite"]
        assert meta["policy"]["name"] == entry["policy"]  # an agent file is named by its submission folder


def test_download_a_shipped_dataset_and_load_it_with_lerobot(tmp_path: Path) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    name = load_catalog(CATALOG)["evaluation_recordings"][0]["name"]
    result = runner.invoke(app, ["datasets", "download", name, "--dir", str(tmp_path), "--catalog", str(CATALOG)])
    assert result.exit_code == 0, result.output
    assert "verified" in result.output
    assert "warning" in result.output and "TEST pairs" in " ".join(result.output.split())  # said before it lands
    entry = next(e for e in load_catalog(CATALOG)["evaluation_recordings"] if e["name"] == name)
    ds = LeRobotDataset(f"mewa/{name}", root=tmp_path / name, video_backend="pyav")
    assert ds.num_episodes == entry["episodes"] and ds.num_frames == entry["frames"]
    # the README's fast read of the index columns agrees with frame-by-frame indexing
    names = ["pair_index", "seed", "episode_in_pair", "episode_index"]
    cols = ds.hf_dataset.select_columns(names).with_format("numpy")[:]
    for i in (0, 1, ds.num_frames // 2, ds.num_frames - 1):
        assert [int(cols[n][i]) for n in names] == [int(ds[i][n]) for n in names]
    assert len(set(cols["pair_index"].tolist())) > 1
    listed = runner.invoke(app, ["datasets", "list", "--catalog", str(CATALOG)])
    assert listed.exit_code == 0 and name[:6] in listed.output
    flat = " ".join(listed.output.split())
    assert "Training data" in flat and "Evaluation recordings" in flat and "never train on these" in flat
    assert flat.index("Training data") < flat.index("Evaluation recordings")
    info = runner.invoke(app, ["datasets", "info", name, "--catalog", str(CATALOG)])
    assert info.exit_code == 0 and "warning" in info.output and "TEST pairs" in " ".join(info.output.split())
    training = load_catalog(CATALOG)["datasets"][0]["name"]
    clean = runner.invoke(app, ["datasets", "info", training, "--catalog", str(CATALOG)])
    assert clean.exit_code == 0 and "warning" not in clean.output
    missing = runner.invoke(app, ["datasets", "info", "no-such-dataset", "--catalog", str(CATALOG)])
    assert missing.exit_code == 1 and "no-such-dataset" in " ".join(missing.output.split())


def test_a_buildable_training_dataset_is_known_to_info_and_download(tmp_path: Path) -> None:
    name = "narrow-v2-train-learning-histories"
    assert name not in {e["name"] for e in load_catalog(CATALOG)["datasets"]}  # listed as buildable only
    listed = " ".join(runner.invoke(app, ["datasets", "list", "--catalog", str(CATALOG)]).output.split())
    assert name in listed
    info = runner.invoke(app, ["datasets", "info", name, "--catalog", str(CATALOG)])
    flat = " ".join(info.output.split())
    assert info.exit_code == 0, info.output
    assert f"mewa-bench datasets build {name}" in flat and "learning-histories" in flat and "warning" not in flat
    assert "tasks the suite's" in flat
    generated = runner.invoke(app, ["datasets", "info", "wide-v2-train-generated-tasks", "--catalog", str(CATALOG)])
    assert "tasks 200 that the suite's generator draws (not the suite's)" in " ".join(generated.output.split())
    recorded = recorded_build(load_catalog(CATALOG), name, DEFAULT_VERSION)["sha256"]  # the current version's
    assert recorded[:40] in flat.replace(" ", "")
    fetched = runner.invoke(app, ["datasets", "download", name, "--dir", str(tmp_path), "--catalog", str(CATALOG)])
    assert fetched.exit_code == 1 and f"datasets build {name}" in " ".join(fetched.output.split())
    assert list(tmp_path.iterdir()) == []  # nothing fetched or left behind


def test_record_pack_download_round_trip(tmp_path: Path) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    out = tmp_path / "rec"
    result = runner.invoke(app, ["record", "--policy", "max-expected", "--out", str(out), "--pairs", "0,2",
                                 "--log", "mcap", "--log-dir", str(tmp_path / "logs")])
    assert result.exit_code == 0, result.output
    results = read_results(tmp_path / "rec.results.json")
    assert results["agent"]["privileged"] and len(results["units"]) == 2
    frames = sum(sum(u["lengths"]) for u in results["units"])
    assert (tmp_path / "logs" / "rec.results.mcap").exists()
    catalog = tmp_path / "cat" / "index.json"
    packed = runner.invoke(app, ["datasets", "pack", str(out), "--name", "rec", "--suite", "narrow-v1", "--policy",
                                 "max-expected", "--out", str(catalog.parent), "--catalog", str(catalog)])
    assert packed.exit_code == 0, packed.output
    written = json.loads(catalog.read_text())  # a recording of suite pairs: an evaluation recording, never training data
    assert written["datasets"] == [] and written["evaluation_recordings"][0]["url"] == "rec-1.0.0.tar.gz"  # relative
    got = runner.invoke(app, ["datasets", "download", "rec", "--dir", str(tmp_path / "dl"), "--catalog", str(catalog)])
    assert got.exit_code == 0, got.output
    ds = LeRobotDataset("mewa/rec", root=tmp_path / "dl" / "rec", video_backend="pyav")
    assert ds.num_episodes == 20 and ds.num_frames == frames
    again = runner.invoke(app, ["record", "--policy", "max-expected", "--out", str(out)])
    assert again.exit_code == 1 and "already exists" in " ".join(again.output.split())
    broken = tmp_path / "broken" / "index.json"
    broken.parent.mkdir()
    broken.write_text("{not json")
    refused = runner.invoke(app, ["datasets", "pack", str(out), "--name", "rec", "--suite", "narrow-v1", "--policy",
                                  "max-expected", "--out", str(broken.parent), "--catalog", str(broken)])
    assert refused.exit_code == 1 and "error" in refused.output
    assert list(broken.parent.iterdir()) == [broken]  # no archive written beside a catalog that cannot take it


def test_adding_to_a_catalog_keeps_relative_urls(tmp_path: Path) -> None:
    catalog = tmp_path / "index.json"
    base = {"version": "1.0.0", "suite": "narrow-v1", "policy": "p", "episodes": 1, "frames": 1, "size": 1,
            "sha256": "0" * 64}
    add_to_catalog(catalog, {**base, "name": "a", "url": "a-1.0.0.tar.gz"})
    add_to_catalog(catalog, {**base, "name": "b", "url": "b-1.0.0.tar.gz"})
    section = "evaluation_recordings"  # entries that do not say they are training data
    assert [e["url"] for e in json.loads(catalog.read_text())[section]] == ["a-1.0.0.tar.gz", "b-1.0.0.tar.gz"]
    assert load_catalog(catalog)[section][0]["url"] == (tmp_path / "a-1.0.0.tar.gz").as_uri()
    add_to_catalog(catalog, {**base, "name": "a", "url": "a-1.0.0.tar.gz", "kind": "training"})
    moved = json.loads(catalog.read_text())
    assert [e["name"] for e in moved["datasets"]] == ["a"] and [e["name"] for e in moved[section]] == ["b"]


def test_evaluate_log_option_errors_clearly(tmp_path: Path) -> None:
    result = runner.invoke(app, ["evaluate", str(REPO / "submissions" / "random" / "agent.py"), "--log", "csv",
                                 "--out", str(tmp_path / "r.json")])
    assert result.exit_code == 1 and "unknown log kind" in " ".join(result.output.split())


def test_cli_rejects_unknown_policies_and_missing_submission_folders(tmp_path: Path) -> None:
    bad = runner.invoke(app, ["record", "--policy", "max_expected", "--out", str(tmp_path / "d")])
    text = " ".join(bad.output.split())
    assert bad.exit_code == 2 and "max-expected" in text and not (tmp_path / "d").exists()
    missing = runner.invoke(app, ["leaderboard", "--submissions", str(tmp_path / "nothing"), "--out", str(tmp_path / "lb")])
    assert missing.exit_code == 1 and "no such submissions folder" in " ".join(missing.output.split())


def test_a_log_dir_that_cannot_be_created_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "a-file").write_text("")
    result = runner.invoke(app, ["evaluate", str(REPO / "submissions" / "random" / "agent.py"), "--seeds", "1",
                                 "--pairs", "0", "--log", "mcap", "--log-dir", str(tmp_path / "a-file" / "logs"),
                                 "--out", str(tmp_path / "r.json")])
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit)  # a message, not a traceback
    assert "error:" in result.output and "Not a directory" in result.output
    assert not (tmp_path / "r.json").exists()


def test_recording_twice_gives_the_same_bytes(tmp_path: Path) -> None:
    from mewa_bench.datasets.pack import pack_dataset

    entries = []
    for run in ("a", "b"):
        out = tmp_path / run / "ds"  # the same folder name: the default repo id follows it
        result = runner.invoke(app, ["record", "--policy", "random-task-specific", "--pairs", "0,1", "--out", str(out)])
        assert result.exit_code == 0, result.output
        entries.append(pack_dataset(out, tmp_path / run / "packed", "same", "1", "narrow-v1", "random-task-specific"))
    files = sorted(p.relative_to(tmp_path / "a" / "ds") for p in (tmp_path / "a" / "ds").rglob("*") if p.is_file())
    for name in files:
        assert (tmp_path / "a" / "ds" / name).read_bytes() == (tmp_path / "b" / "ds" / name).read_bytes(), name
    assert entries[0]["sha256"] == entries[1]["sha256"]


def test_a_wheel_carries_the_shipped_catalog_and_its_archives(tmp_path: Path) -> None:
    """Built as pip builds it, the wheel installs datasets/ under <prefix>/share/mewa-bench/datasets, and an
    install without the checkout finds that catalog; its relative URLs resolve to the installed archives."""
    import subprocess
    import sys
    import zipfile

    from mewa_bench.datasets.catalog import INSTALLED_DATASETS, catalog_entries, default_catalog_path

    root = Path(__file__).resolve().parents[1]
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path / "wheel"),
                            str(root)], capture_output=True, text=True, timeout=600)
    assert built.returncode == 0, built.stderr
    wheel = zipfile.ZipFile(next((tmp_path / "wheel").glob("mewa_bench-*.whl")))
    prefix = tmp_path / "prefix"
    for name in wheel.namelist():  # what pip does with a wheel's .data/data/ tree: it goes under the prefix
        if ".data/data/" in name:
            target = prefix / name.split(".data/data/", 1)[1]
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(wheel.read(name))
    path = default_catalog_path(checkout=tmp_path / "no-checkout" / "index.json", prefix=prefix)
    assert path == prefix / INSTALLED_DATASETS / "index.json"
    shipped = catalog_entries(load_catalog(root / "datasets" / "index.json", resolve=False))
    installed = catalog_entries(load_catalog(path))
    assert [e["name"] for e in installed] == [e["name"] for e in shipped]
    for entry in installed:
        archive = Path(entry["url"].removeprefix("file://"))
        assert archive.parent == path.parent and hashlib.sha256(archive.read_bytes()).hexdigest() == entry["sha256"]
    assert default_catalog_path(prefix=prefix) == root / "datasets" / "index.json"  # a checkout reads its own
