"""What the learned baselines share: the algorithm registry, the meta-train env, metrics and
checkpoint files, and the submission folder a run becomes. No torch at import time.

An algorithm is a module listed in `ALGORITHMS` that exposes (what `mewa-bench train` calls):

- `Settings`: a dataclass of everything a run depends on, saved in its checkpoint; it has at least
  `suite`, `seed`, `total_steps` and `workers` (list of worker vectors; empty: the suite's
  meta-train distribution), and the property `steps_per_update` (a run trains whole updates).
- `settings_from(values: dict, base=None) -> Settings`: fields replaced, unknown names a ValueError
  naming them (`settings_with` below does it for any dataclass).
- `train_run(settings, folder, resume, command, progress=...) -> list[Path]`: train (or resume from
  the folder's last checkpoint) and make the folder a submission (`write_submission`); the files
  written. `progress(env_steps_done, env_steps_total, row)` is called after every update with the
  metrics row just written.
- `METRICS`: the metrics file name in the run folder. Every row has `update`, `env_steps` and the
  meta-train `episode_1_normalised_return` / `episode_10_normalised_return` (NaN when no such
  episode ended during the update), which the progress bar and the training curve read.
- A vector agent class `XVectorAgent(checkpoint, num_lanes=1, seed=0, greedy=False)` with the batched
  protocol's `reset_task`, `act`, `observe`, `end_episode` (`protocol.agent.VectorAgent`), named in
  the submission's agent.py, and `XAgent(checkpoint, seed=0, greedy=False)`, its one-lane view.
"""

from __future__ import annotations

import csv
import importlib
import importlib.util
import os
from dataclasses import asdict, fields, is_dataclass
from io import StringIO
from pathlib import Path
from types import ModuleType
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any, TypeVar

import numpy as np

from mewa_bench.extras import require

CHECKPOINT = "checkpoint.pt"
METRICS = "metrics.csv"
ALGORITHMS = {  # name -> module (one file per algorithm)
    "rl2": "mewa_bench.agents.rl2",
    "varibad": "mewa_bench.agents.varibad",
    "pearl": "mewa_bench.agents.pearl",
    "maml": "mewa_bench.agents.maml",
    "dpt": "mewa_bench.agents.dpt",  # offline: learns from a training dataset (train --dataset)
    "imitation": "mewa_bench.agents.imitation",  # offline: imitates a behaviour's own actions (GRU)
    "ad": "mewa_bench.agents.ad",  # offline: Algorithm Distillation of the learning histories (transformer)
}

S = TypeVar("S")


class UnknownAlgorithm(ValueError):
    """An algorithm name that is not in the registry, or whose module is not there (yet)."""


def available_algorithms() -> list[str]:
    """The registered algorithms whose module exists, in registry order."""
    return [name for name, module in ALGORITHMS.items() if importlib.util.find_spec(module) is not None]


def load_algorithm(name: str) -> ModuleType:
    """The module of algorithm `name`; UnknownAlgorithm listing those available otherwise."""
    if name not in available_algorithms():
        names = available_algorithms()
        listed = names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]
        raise UnknownAlgorithm(f"unknown algorithm {name!r}: only {listed} {'is' if len(names) == 1 else 'are'} "
                               f"available")
    return importlib.import_module(ALGORITHMS[name])


def torch_module(feature: str) -> Any:
    """The torch module (the train extra; the datasets extra brings it too)."""
    return require("torch", "train", feature)


@contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """torch's CPU threads set to `count` inside the block (or the decorated function) and the caller's count given
    back after it; a count below 1 is a ValueError. Every trainer runs inside one."""
    if count < 1:
        raise ValueError(f"threads {count}: expected at least 1")
    torch = torch_module("training")
    callers = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(callers)


def settings_with(cls: type[S], values: dict[str, Any], base: S | None = None, name: str = "") -> S:
    """`cls` settings with some fields replaced (names checked against the dataclass)."""
    assert is_dataclass(cls)
    start = asdict(base) if base is not None else asdict(cls())
    unknown = set(values) - {f.name for f in fields(cls)}
    if unknown:
        raise ValueError(f"unknown {name or cls.__name__} setting(s) {sorted(unknown)}; known: {sorted(start)}")
    return cls(**{**start, **values})


def offline_settings(cls: type[S], values: dict[str, Any], base: S | None = None, name: str = "") -> S:
    """An offline algorithm's settings (`settings_with`): no worker list (the dataset's workers are its own),
    and the suite is the one the named dataset was built for (a clear error if it is not a training dataset)."""
    settings = settings_with(cls, values, base, name)
    if settings.workers:  # type: ignore[attr-defined]
        raise ValueError(f"{name or cls.__name__} learns from a dataset: its workers are the dataset's (--worker does "
                         "not apply)")
    if settings.dataset:  # type: ignore[attr-defined]
        from mewa_bench.datasets.training_data import read_training_meta

        meta = read_training_meta(settings.dataset)  # type: ignore[attr-defined]
        settings = settings_with(cls, {"suite": meta["suite"]["name"]}, settings, name)
        for folder in getattr(settings, "more_datasets", []):
            suite = read_training_meta(folder)["suite"]["name"]
            if suite != meta["suite"]["name"]:
                raise ValueError(f"{folder}: a dataset of {suite}, not of {meta['suite']['name']} (the first "
                                 f"dataset's): pooled datasets must be of one suite")
    return settings


def dataset_note(dataset: str | Path) -> str:
    """What a run's run.json says of its training dataset: its name, frames and build command, and the sha256 of its
    archive when the catalog beside it (`datasets build` writes `<out>/index.json`) records one."""
    import json

    from mewa_bench.datasets.training_data import read_training_meta

    meta = read_training_meta(dataset)
    note = f"trained on {meta['name']} ({meta['total_steps']:,} frames; `{meta['build_command']}`)"
    catalog = Path(dataset).parent / "index.json"
    entries = json.loads(catalog.read_text()).get("datasets", []) if catalog.exists() else []
    entry = next((e for e in entries if (e.get("name"), e.get("version")) == (meta["name"], meta["version"])), None)
    return note if entry is None else f"{note}; archive sha256 {entry['sha256']}"


RUN_OPTIONS = ("suite", "seed", "total_steps", "workers", "dataset", "more_datasets")  # set by `train` with options of their own


def setting_overrides(cls: type, items: Sequence[str]) -> dict[str, Any]:
    """`learning_rate=3e-4`, `hidden=256`, ... (`train --set`) as values of the types of `cls`'s defaults;
    ValueError naming the bad item."""
    defaults = asdict(cls())
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = (part.strip() for part in item.partition("="))
        if not sep or not key:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE, e.g. learning_rate=3e-4")
        if key in RUN_OPTIONS:
            raise ValueError(f"--set {key}: set it with train's own option (--suite, --seed, --steps, --worker, "
                             f"--dataset)")
        if key not in defaults:
            raise ValueError(f"--set {key}: not a {cls.__name__} setting; known: {', '.join(sorted(defaults))}")
        default = defaults[key]
        try:
            if isinstance(default, bool):
                if text.lower() not in ("true", "false"):
                    raise ValueError("expected true or false")
                out[key] = text.lower() == "true"
            elif isinstance(default, (int, float, str)):
                out[key] = type(default)(text)
            else:
                raise ValueError(f"a {type(default).__name__} setting cannot be set from the command line")
        except ValueError as e:
            raise ValueError(f"--set {item!r}: {key} is a {type(default).__name__} ({e})") from None
    return out


def whole_updates(settings: S) -> S:
    """`settings` with `total_steps` rounded up to whole updates (training runs whole updates only)."""
    per_update = settings.steps_per_update  # type: ignore[attr-defined]
    updates = max(1, -(-settings.total_steps // per_update))  # type: ignore[attr-defined]
    return settings_with(type(settings), {"total_steps": updates * per_update}, base=settings)


def workers_arg(text: Sequence[str]) -> list[list[float]]:
    """`--worker 0,1,1,1 --worker 1,1,1,0` as lists of floats (ValueError naming a bad one)."""
    out = []
    for item in text:
        try:
            out.append([float(v) for v in item.split(",")])
        except ValueError:
            raise ValueError(f"worker {item!r} is not comma-separated numbers") from None
    return out


def make_meta_env(suite: str, num_envs: int, episodes: int, workers: Sequence[Sequence[float]] = ()) -> Any:
    """The batched meta-episode env of a run: the suite's tasks with meta-train workers drawn from each
    task's own distribution (never a curated test worker), or the suite's first task with `workers`."""
    from mewa_bench.design.suites import load_suite
    from mewa_bench.envs.meta_episode import MetaEpisodeVectorEnv

    tasks = load_suite(suite).tasks
    if workers:
        return MetaEpisodeVectorEnv(num_envs, episodes, task=tasks[0], workers=[list(w) for w in workers])
    return MetaEpisodeVectorEnv(num_envs, episodes, tasks=tasks)


def episode_end_scores(info: dict[str, Any], episodes: int) -> tuple[list[float], list[float]]:
    """Normalised returns of the first and of the last inner episodes that ended on this step."""
    if "normalised_return" not in info:
        return [], []
    ended, k = info["_normalised_return"], info["episode_in_trial"]
    scores = info["normalised_return"]
    return scores[ended & (k == 0)].tolist(), scores[ended & (k == episodes - 1)].tolist()


def normalised_returns_paid(reward: np.ndarray, info: dict[str, Any]) -> np.ndarray:
    """Each inner episode's normalised return on the step that ends it, 0 elsewhere (see rl2's
    `learning_signal` for why the learned baselines learn from this by default)."""
    if "normalised_return" not in info:
        return np.zeros_like(reward)
    return np.where(info["_normalised_return"], info["normalised_return"], 0.0)


def mean_or_nan(values: list[float]) -> float:
    """Mean of a list, NaN when it is empty (an update in which no such episode ended)."""
    return float(np.mean(values)) if values else float("nan")


def append_metrics(path: Path, row: dict[str, Any]) -> None:
    """Append one row to the metrics CSV (header on the first), flushed at once."""
    new = not path.exists()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(row))
        if new:
            writer.writeheader()
        writer.writerow(row)



def fit_labels(model: Any, optimizer: Any, logits: Any, label: Any, valid: Any, settings: Any, update: int,
               updates: int, began: float, out: Path, progress: Any) -> None:
    """One supervised update of an offline algorithm (cross-entropy on the valid frames' labels, clipped
    gradients), its metrics row and, on schedule, its checkpoint: `update` counts from 0, `began` is the
    run's perf_counter start."""
    import time

    torch = torch_module("offline training")
    loss = torch.nn.functional.cross_entropy(logits[valid], label[valid])
    optimizer.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), settings.max_grad_norm)
    optimizer.step()
    accuracy = (logits[valid].argmax(dim=-1) == label[valid]).float().mean()
    steps = (update + 1) * settings.steps_per_update
    row = {"update": update + 1, "env_steps": steps, "seconds": round(time.perf_counter() - began, 3),
           "episode_1_normalised_return": float("nan"), "episode_10_normalised_return": float("nan"),
           "loss": round(loss.item(), 6), "accuracy": round(accuracy.item(), 6)}
    append_metrics(out / METRICS, row)
    progress(steps, updates * settings.steps_per_update, row)
    if (update + 1) % settings.checkpoint_every == 0 or update + 1 == updates:
        save_checkpoint(out / CHECKPOINT, {"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                                           "settings": asdict(settings), "update": update + 1})


def keep_metrics_until(path: Path, update: int) -> None:
    """Drop the metrics rows of updates after `update` (atomically): a resumed run redoes them."""
    from mewa_bench.files import write_atomic

    if not path.exists():
        return
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        kept, names = [r for r in reader if int(r["update"]) <= update], reader.fieldnames or []
    text = StringIO()
    writer = csv.DictWriter(text, fieldnames=names, lineterminator="\r\n")
    writer.writeheader()
    writer.writerows(kept)
    write_atomic(path, text.getvalue())


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """`torch.save(state)` atomically (a temporary sibling, then rename)."""
    torch = torch_module("saving a checkpoint")
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        torch.save(state, tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def load_checkpoint(path: Path) -> dict[str, Any]:
    """A checkpoint written by `save_checkpoint` (a clear error when the file is missing)."""
    torch = torch_module("loading a checkpoint")
    if not Path(path).exists():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    return torch.load(path, weights_only=False)


def resumed(out: Path, settings: S, resume: bool) -> dict[str, Any] | None:
    """The state of `out`'s checkpoint when the run resumes from it (None for a fresh run).

    A resumed run keeps its own settings; only its length may change (to train on from a finished
    run). Other settings than the checkpoint's are a ValueError naming them, so that the run folder's
    README, agent.py and run.json, written from the settings given, always describe the run.
    """
    path = Path(out) / CHECKPOINT
    if not (resume and path.exists()):
        return None
    state = load_checkpoint(path)
    saved = type(settings)(**state["settings"])
    changed = [f.name for f in fields(saved)
               if f.name != "total_steps" and getattr(saved, f.name) != getattr(settings, f.name)]
    if changed:
        given = ", ".join(f"{name}={getattr(settings, name)!r} (the run has {getattr(saved, name)!r})" for name in changed)
        raise ValueError(f"{path}: a resumed run keeps its own settings, only the number of steps may change; this "
                         f"one was given {given}. Re-run the command that started it, with --resume.")
    return state


def restore(out: Path, state: dict[str, Any], model: Any, optimizers: dict[str, Any],
            optimizer_states: dict[str, Any] | None = None) -> int:
    """A checkpoint's weights into `model` and each optimizer's state (from `optimizer_states`, default the checkpoint
    itself, by key); then the metrics rows written after the checkpoint are dropped (they will be redone). The update
    to go on from."""
    model.load_state_dict(state["model"])
    for key, optimizer in optimizers.items():
        optimizer.load_state_dict((state if optimizer_states is None else optimizer_states)[key])
    keep_metrics_until(Path(out) / METRICS, state["update"])
    return int(state["update"])


def load_for_play(checkpoint: str | Path, settings_class: type[S], build: Any) -> tuple[S, Any]:
    """A checkpoint's settings and `build(settings)` with its weights, in float64 evaluation mode on one
    compute thread: how every vector agent plays (float64 so that the batch size cannot flip an action; the
    transformers step a float32 copy and recompute in float64 what float32 could flip)."""
    torch = torch_module("playing a checkpoint")
    torch.set_num_threads(1)
    state = load_checkpoint(Path(checkpoint))
    settings = settings_class(**state["settings"])
    model = build(settings)
    model.load_state_dict(state["model"])
    return settings, model.double().eval()


AGENT_FILE = '''"""{title} agent trained by `{command}`; plays the checkpoint beside this file.

Evaluate it: `mewa-bench evaluate {folder}/agent.py --suite {suite}`.
"""

from pathlib import Path

from {module} import {agent_class}

PRIVILEGED = False


def make_vector_agent(observation_space, action_space, num_lanes, seed="0", checkpoint=None, greedy="{greedy}"):
    return {agent_class}(checkpoint or Path(__file__).with_name("{checkpoint}"), num_lanes, seed=seed, greedy=greedy)
'''


def write_submission(out: Path, command: str, settings: Any, algorithm: str, title: str, agent_class: str,
                     description: str, greedy: bool = False) -> list[Path]:
    """Make a run folder a submission: agent.py (plays CHECKPOINT with `agent_class` of the algorithm's
    module, sampling its actions unless `greedy`) and a README with the exact command, the settings and where
    the metrics are."""
    from mewa_bench.files import write_atomic

    agent = out / "agent.py"
    shown = os.path.relpath(out) if Path(out).resolve().is_relative_to(Path.cwd()) else str(out)  # no machine paths
    write_atomic(agent, AGENT_FILE.format(title=title, command=command, folder=shown, suite=settings.suite,
                                          module=ALGORITHMS[algorithm], agent_class=agent_class,
                                          checkpoint=CHECKPOINT, greedy=str(greedy).lower()))
    readme = out / "README.md"
    write_atomic(readme, f"# {algorithm} ({settings.suite}, seed {settings.seed})\n\n{description}\n\nTrained with:"
                         f"\n\n```\n{command}\n```\n\nSettings: `{asdict(settings)}`. Training metrics: `{METRICS}`.\n")
    return [agent, readme]
