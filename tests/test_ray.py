"""Evaluation units as Ray tasks on a real local Ray instance (127.0.0.1): the same results as a
local run, a killed worker retried, resume across backends, a clear error for a missing cluster."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import ray

from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.ray_backend import LOCAL, RayUnavailable, connect
from mewa_bench.protocol.results import read_results, stable_view, write_results
from mewa_bench.protocol.runner import evaluate

AGENTS = Path(__file__).parent / "agents"
REPO = Path(__file__).resolve().parents[1]
RANDOM = REPO / "submissions" / "random" / "agent.py"


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    """One local Ray head for the module (evaluate joins it instead of starting its own)."""
    ray.init(address="local", num_cpus=2, _node_ip_address="127.0.0.1", include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def config(tmp_path: Path, name: str, agent: Path = RANDOM, **kw) -> EvalConfig:
    """A small run: pairs 0-3, seeds 0-2, 4 units per batch (so several Ray tasks)."""
    return EvalConfig(agent_path=agent, out=tmp_path / name, seeds=(0, 1, 2), pairs=(0, 1, 2, 3), lanes=4, **kw)


def test_a_ray_run_gives_the_local_results(tmp_path: Path) -> None:
    on_ray, _ = evaluate(config(tmp_path, "ray.json", ray=LOCAL))
    local, _ = evaluate(config(tmp_path, "local.json", jobs=2))
    assert stable_view(on_ray) == stable_view(local)
    assert on_ray["execution"]["ray"] == LOCAL and local["execution"]["ray"] is None
    assert len(on_ray["units"]) == 12


def test_a_killed_worker_is_retried_and_nothing_is_counted_twice(tmp_path: Path) -> None:
    marker = tmp_path / "killed"
    agent = AGENTS / "kills_its_worker_once.py"
    args = {"marker": str(marker)}
    on_ray, _ = evaluate(config(tmp_path, "ray.json", agent, agent_args=args, ray=LOCAL))
    assert marker.read_text() == "killed once"  # a worker really died mid-unit
    local, _ = evaluate(config(tmp_path, "local.json", agent, agent_args=args))
    assert stable_view(on_ray) == stable_view(local)
    assert sorted((u["pair"], u["seed"]) for u in on_ray["units"]) == [(p, s) for p in range(4) for s in range(3)]


def test_resume_across_backends(tmp_path: Path) -> None:
    full, path = evaluate(config(tmp_path, "full.json"))
    interrupted = {k: v for k, v in read_results(path).items() if k not in ("scores", "baselines")}
    interrupted["units"] = interrupted["units"][:5]
    interrupted["complete"] = False
    write_results(tmp_path / "part.json", interrupted)
    resumed, _ = evaluate(replace(config(tmp_path, "part.json", ray=LOCAL), resume=True))
    assert stable_view(resumed) == stable_view(full)


def test_an_unreachable_cluster_is_a_clear_error_and_writes_nothing(tmp_path: Path) -> None:
    with pytest.raises(RayUnavailable, match="cannot reach the Ray cluster at 127.0.0.1:1"):
        connect("127.0.0.1:1", None)
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    out = tmp_path / "r.json"
    result = CliRunner().invoke(app, ["evaluate", str(RANDOM), "--seeds", "1", "--pairs", "0",
                                      "--ray-address", "127.0.0.1:1", "--out", str(out)])
    assert result.exit_code == 1 and "cannot reach the Ray cluster" in " ".join(result.output.split())
    assert not out.exists()


def test_a_worker_dying_beyond_the_retries_is_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from mewa_bench.protocol import ray_backend
    from mewa_bench.protocol.runner import EvaluationError

    monkeypatch.setattr(ray_backend, "MAX_RETRIES", 0)
    run = config(tmp_path, "r.json", AGENTS / "kills_its_worker_once.py", agent_args={"marker": str(tmp_path / "m")},
                 ray=LOCAL)
    with pytest.raises(EvaluationError, match="run again with --resume") as err:
        evaluate(run)
    assert err.value.kind == "crash"
    if run.out.exists():  # whatever finished before the failure is kept, whole units only
        assert all(len(u["returns"]) == 10 for u in read_results(run.out)["units"])


@pytest.mark.slow  # about 25 s; the default tier keeps Ray's evaluate, retries and resume
def test_record_on_ray_writes_the_same_dataset(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    for where, extra in (("ray", ["--ray"]), ("local", [])):
        out = tmp_path / where / "ds"
        result = CliRunner().invoke(app, ["record", "--policy", "random-task-specific", "--pairs", "0,1,2",
                                          "--seeds", "2", "--out", str(out), *extra])
        assert result.exit_code == 0, result.output
    files = sorted(p.relative_to(tmp_path / "local" / "ds") for p in (tmp_path / "local" / "ds").rglob("*") if p.is_file())
    assert files
    for name in files:
        assert (tmp_path / "ray" / "ds" / name).read_bytes() == (tmp_path / "local" / "ds" / name).read_bytes(), name


@pytest.mark.slow  # narrow about 40 s, wide about 100 s: the default tier keeps Ray's evaluate, retries and resume
@pytest.mark.parametrize("kind", ["narrow", "wide"])
def test_generate_on_ray_reproduces_the_shipped_suite(kind: str) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    result = CliRunner().invoke(app, ["generate", kind, "--check", "--ray"])
    assert result.exit_code == 0, result.output
    assert f"byte-identical to the shipped {kind}-v1.json: yes" in " ".join(result.output.split())


@pytest.mark.slow  # about 40 s: two RL² seeds, twice; the default tier keeps Ray's evaluate, retries and resume
def test_train_one_seed_per_ray_task_gives_the_local_runs(tmp_path: Path) -> None:
    import csv

    import torch
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    for where, extra in (("ray", ["--ray"]), ("local", [])):
        result = CliRunner().invoke(app, ["train", "rl2", "--suite", "narrow-v1", "--steps", "8192", "--seed", "1", "--seed", "2",
                                          "--worker", "0,1,1,1", "--out", str(tmp_path / where), *extra])
        assert result.exit_code == 0, result.output
    for seed in (1, 2):
        on_ray = torch.load(tmp_path / "ray" / f"rl2-narrow-v1-seed{seed}" / "checkpoint.pt", weights_only=False)
        local = torch.load(tmp_path / "local" / f"rl2-narrow-v1-seed{seed}" / "checkpoint.pt", weights_only=False)
        assert all(torch.equal(on_ray["model"][k], local["model"][k]) for k in local["model"])

        def metrics(where: str) -> list[dict[str, str]]:
            with (tmp_path / where / f"rl2-narrow-v1-seed{seed}" / "metrics.csv").open() as f:
                return [{k: v for k, v in row.items() if k != "seconds"} for row in csv.DictReader(f)]

        assert metrics("ray") == metrics("local")
    assert not all(torch.equal(a, b) for a, b in zip(
        torch.load(tmp_path / "local" / "rl2-narrow-v1-seed1" / "checkpoint.pt", weights_only=False)["model"].values(),
        torch.load(tmp_path / "local" / "rl2-narrow-v1-seed2" / "checkpoint.pt", weights_only=False)["model"].values()))


def test_a_vector_agent_on_ray_gives_the_one_lane_local_results(tmp_path: Path) -> None:
    vector = AGENTS / "vector_agent.py"
    args = {"agent_args": {"sampled": "true"}}
    on_ray, _ = evaluate(config(tmp_path, "ray.json", agent=vector, ray=LOCAL, **args))
    local, _ = evaluate(replace(config(tmp_path, "local.json", agent=vector, **args), lanes=1))
    assert stable_view(on_ray)["units"] == stable_view(local)["units"]
    assert len(on_ray["units"]) == 12


@pytest.mark.slow  # about 50 s: the expert tier's play and exact labels, twice
def test_a_training_dataset_built_on_ray_has_the_local_bytes(tmp_path: Path) -> None:
    """The expert tier (its play and the exact values as Ray tasks) gives byte-identical files to a one-process build."""
    from mewa_bench.datasets.training_data import build_training_dataset, ray_tasks, training_spec

    spec = replace(training_spec("narrow-v2-train-expert", 1), meta_batch=6)
    build_training_dataset(spec, tmp_path / "ray", jobs=2, map_tasks=ray_tasks)
    build_training_dataset(spec, tmp_path / "local", jobs=1)
    files = sorted(p.relative_to(tmp_path / "local") for p in (tmp_path / "local").rglob("*") if p.is_file())
    assert any(f.suffix == ".parquet" for f in files)
    for name in files:
        assert (tmp_path / "ray" / name).read_bytes() == (tmp_path / "local" / name).read_bytes(), name
