"""What the learned baselines share (mewa_bench.agents.training_io): the registry and each algorithm's
interface, settings, the meta-train env, metrics files, atomic checkpoints and the submission folder."""

from __future__ import annotations

import csv
import importlib
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from mewa_bench.agents import training_io
from mewa_bench.agents.training_io import (ALGORITHMS, UnknownAlgorithm, append_metrics, available_algorithms,
                                           episode_end_scores, keep_metrics_until, load_algorithm, load_checkpoint,
                                           make_meta_env, normalised_returns_paid, save_checkpoint, settings_with,
                                           torch_threads, workers_arg, write_submission)


@dataclass
class Toy:
    suite: str = "narrow-v1"
    seed: int = 1
    rate: float = 0.5
    workers: list[list[float]] = field(default_factory=list)


def test_the_registry_loads_the_algorithms_that_exist_and_names_them_otherwise() -> None:
    names = available_algorithms()
    assert names[:2] == ["rl2", "varibad"] and set(names) <= set(ALGORITHMS)
    assert load_algorithm("varibad").__name__ == "mewa_bench.agents.varibad"
    with pytest.raises(UnknownAlgorithm) as caught:
        load_algorithm("dqn")
    message = str(caught.value)
    assert "'dqn'" in message and all(name in message for name in names)


@pytest.mark.parametrize("name", available_algorithms())
def test_every_available_algorithm_offers_what_the_train_command_calls(name: str) -> None:
    module = load_algorithm(name)
    assert is_dataclass(module.Settings)
    assert {"suite", "seed", "total_steps", "workers"} <= {f.name for f in fields(module.Settings)}
    if "dataset" in {f.name for f in fields(module.Settings)}:  # offline: the dataset decides the workers
        with pytest.raises(ValueError, match="learns from a dataset: its workers are the dataset's"):
            module.settings_from({"workers": [[0.0, 1.0, 1.0, 1.0]]})
        settings = module.settings_from({"seed": 7, "total_steps": 10})
        assert (settings.seed, settings.total_steps, settings.workers) == (7, 10, [])
    else:
        settings = module.settings_from({"seed": 7, "total_steps": 10, "workers": [[0.0, 1.0, 1.0, 1.0]]})
        assert (settings.seed, settings.total_steps, settings.workers) == (7, 10, [[0.0, 1.0, 1.0, 1.0]])
    with pytest.raises(ValueError, match="no_such_setting"):
        module.settings_from({"no_such_setting": 1})
    assert callable(module.train_run) and module.METRICS.endswith(".csv")


def test_torch_threads_sets_the_count_inside_and_gives_the_callers_back() -> None:
    callers = torch.get_num_threads()
    with torch_threads(callers + 1):
        assert torch.get_num_threads() == callers + 1
    with pytest.raises(RuntimeError, match="inside"), torch_threads(callers + 1):
        raise RuntimeError("inside")
    assert torch.get_num_threads() == callers
    with pytest.raises(ValueError, match="threads 0: expected at least 1"), torch_threads(0):
        pass


@pytest.mark.parametrize("name", available_algorithms())
def test_every_trainer_gives_the_callers_thread_count_back_even_when_it_fails(name: str, tmp_path: Path) -> None:
    module = load_algorithm(name)
    out = tmp_path / "a-file"
    out.write_text("not a folder")
    callers = torch.get_num_threads()
    with torch_threads(callers + 2):
        with pytest.raises(FileExistsError):
            module.train(module.settings_from({}), out)
        assert torch.get_num_threads() == callers + 2


def test_settings_with_checks_names_and_keeps_the_base() -> None:
    base = settings_with(Toy, {"rate": 0.25})
    assert settings_with(Toy, {"seed": 3}, base) == Toy(seed=3, rate=0.25)
    with pytest.raises(ValueError, match=r"unknown Toy setting\(s\) \['speed'\]; known: .*'rate'"):
        settings_with(Toy, {"speed": 2})


def test_workers_arg_parses_the_repeatable_option() -> None:
    assert workers_arg(["0,1,1,1", "1,1,1,0"]) == [[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 0.0]]
    with pytest.raises(ValueError, match="'0,one'"):
        workers_arg(["0,one"])


def test_the_meta_train_env_draws_the_suite_or_the_given_workers() -> None:
    from mewa_bench.design.suites import load_suite

    suite = load_suite("wide-v1")
    env = make_meta_env("wide-v1", num_envs=32, episodes=2)
    env.reset(seed=0)
    assert [t.key() for t in env.tasks] == [t.key() for t in suite.tasks]
    fixed = make_meta_env("wide-v1", num_envs=32, episodes=2, workers=[[0.0, 1.0, 1.0, 1.0]])
    fixed.reset(seed=0)
    assert [t.key() for t in fixed.tasks] == [suite.tasks[0].key()]
    assert {tuple(w) for w in fixed.workers} == {(0.0, 1.0, 1.0, 1.0)}


def test_episode_ends_give_the_scores_and_the_signal() -> None:
    info = {"normalised_return": np.array([0.5, 0.9, 0.0, 0.7]), "episode_in_trial": np.array([0, 9, 0, 3]),
            "_normalised_return": np.array([True, True, False, True])}
    assert episode_end_scores(info, episodes=10) == ([0.5], [0.9])
    assert normalised_returns_paid(np.full(4, -1.0), info).tolist() == [0.5, 0.9, 0.0, 0.7]
    assert normalised_returns_paid(np.full(4, -1.0), {"episode_in_trial": np.zeros(4)}).tolist() == [0.0] * 4


def read(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_metrics_are_appended_and_cut_back_on_resume(tmp_path: Path) -> None:
    path = tmp_path / "metrics.csv"
    for update in (1, 2, 3):
        append_metrics(path, {"update": update, "env_steps": 100 * update, "loss": 0.5 / update})
        assert [int(r["update"]) for r in read(path)] == list(range(1, update + 1))  # on disk as it comes
    keep_metrics_until(path, 2)
    assert read(path) == [{"update": "1", "env_steps": "100", "loss": "0.5"},
                          {"update": "2", "env_steps": "200", "loss": "0.25"}]
    append_metrics(path, {"update": 3, "env_steps": 300, "loss": 0.1})
    assert [r["loss"] for r in read(path)] == ["0.5", "0.25", "0.1"]
    keep_metrics_until(tmp_path / "absent.csv", 1)  # nothing to cut
    assert not (tmp_path / "absent.csv").exists()


class Unpicklable:
    def __reduce__(self):
        raise RuntimeError("cannot be saved")


def test_checkpoints_are_written_atomically(tmp_path: Path) -> None:
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"model": {"w": torch.arange(3.0)}, "update": 4})
    state = load_checkpoint(path)
    assert state["update"] == 4 and torch.equal(state["model"]["w"], torch.arange(3.0))
    with pytest.raises(RuntimeError, match="cannot be saved"):  # the save fails half-way through
        save_checkpoint(path, {"model": {"w": torch.zeros(3)}, "update": 5, "bad": Unpicklable()})
    assert load_checkpoint(path)["update"] == 4  # the previous checkpoint is intact
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]  # no temporary file left
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_checkpoint(tmp_path / "missing.pt")


def test_a_submission_folder_plays_its_checkpoint_with_the_algorithm_class(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    out = Path("runs/x")
    out.mkdir(parents=True)
    written = write_submission(out, "mewa-bench train varibad --seed 3", Toy(seed=3), "varibad", "VariBAD",
                               "VariBADVectorAgent", "VariBAD, one line.")
    agent_text, readme = (p.read_text() for p in written)
    assert "from mewa_bench.agents.varibad import VariBADVectorAgent" in agent_text
    assert "mewa-bench evaluate runs/x/agent.py --suite narrow-v1" in agent_text and str(tmp_path) not in agent_text
    assert readme.startswith("# varibad (narrow-v1, seed 3)\n\nVariBAD, one line.")
    assert "```\nmewa-bench train varibad --seed 3\n```" in readme
    spec = importlib.util.spec_from_file_location("submitted", written[0])
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.PRIVILEGED is False and callable(module.make_vector_agent)


def test_importing_the_shared_layer_does_not_import_torch() -> None:
    import subprocess
    import sys

    code = "import sys, mewa_bench.agents.training_io as t; t.available_algorithms(); print('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout == "False\n"
    assert training_io.__doc__ and "train_run" in training_io.__doc__
