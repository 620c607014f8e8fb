"""Training runs of the learned baselines as `mewa-bench train` makes them: one run folder per seed.

`choose_algorithm` reads the algorithm, its changed settings and its datasets (an offline algorithm
learns from one, AD from one or more, an online one takes none); `plan_runs` fixes each seed's settings (whole
updates), run folder and the command that reproduces the run; `train_here` trains the seeds one
after the other in this process, `train_on_ray` as one Ray task per seed; `finish_run` records
run.json, plots the training curve and titles the README with the run's name on the boards (and, for an offline
run, its data), which makes the folder a submission.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, Callable

from mewa_bench.agents.training_io import (UnknownAlgorithm, dataset_note, load_algorithm, setting_overrides, whole_updates,
                                           workers_arg)
from mewa_bench.design.suites import DEFAULT_SUITE
from mewa_bench.protocol.run_info import RunInfo, run_name, write_run_info

Job = tuple[Any, Path, bool, str]  # (settings, run folder, resume, command): an algorithm's train_run arguments
SeedProgress = Callable[[int, int, dict], None]  # (steps done, total, metrics row) as a run goes


class TrainingOptionError(ValueError):
    """A training option that cannot be used; `option` names it as the command line spells it (e.g. --set)."""

    def __init__(self, message: str, option: str) -> None:
        super().__init__(message)
        self.option = option


@dataclass(frozen=True)
class Algorithm:
    """What trains: the algorithm's registry name and module, its changed settings and its dataset."""

    algo: str
    module: ModuleType
    overrides: dict[str, Any]  # the changed settings (--set), recorded in run.json
    offline: dict[str, str]  # {"dataset": folder} when it learns from a dataset, else empty

    @property
    def learns_offline(self) -> bool:
        """True for an offline algorithm (it learns from a training dataset)."""
        return "dataset" in self.module.Settings.__dataclass_fields__

    @property
    def step_unit(self) -> str:
        """What its `total_steps` counts."""
        return getattr(self.module, "STEP_UNIT", "env steps")


@dataclass(frozen=True)
class TrainingPlan:
    """The runs of one training command: one job per seed, in the order given."""

    algorithm: Algorithm
    name: str  # the algorithm's name on the boards and in the run folders' names
    steps: int  # the steps asked for, before rounding up to whole updates
    jobs: list[Job]

    @property
    def suite(self) -> str:
        """The suite the runs train on."""
        return self.jobs[0][0].suite


def choose_algorithm(algo: str, settings: list[str], datasets: list[Path], absolute_dataset: bool) -> Algorithm:
    """The algorithm `algo` with its KEY=VALUE `settings` changed and its `datasets` (absolute for Ray workers,
    whose working directory may differ; else as given, as in the README's command; an algorithm whose settings
    have `more_datasets` pools several); TrainingOptionError."""
    try:
        module = load_algorithm(algo)
    except UnknownAlgorithm as e:
        raise TrainingOptionError(str(e), "ALGO") from None
    try:
        overrides = setting_overrides(module.Settings, settings)
    except ValueError as e:
        raise TrainingOptionError(str(e), "--set") from None
    folders = [str(d.resolve() if absolute_dataset else d) for d in datasets]
    offline = {} if not folders else {"dataset": folders[0], **({"more_datasets": folders[1:]} if folders[1:] else {})}
    chosen = Algorithm(algo, module, overrides, offline)
    if folders and not chosen.learns_offline:
        raise TrainingOptionError(f"{algo} learns online: only offline algorithms (dpt, imitation, ad) take a dataset", "--dataset")
    if folders[1:] and "more_datasets" not in module.Settings.__dataclass_fields__:
        raise TrainingOptionError(f"{algo} learns from one dataset (--dataset given {len(folders)} times); ad pools the "
                                  f"histories of several datasets of one suite", "--dataset")
    if not folders and chosen.learns_offline:
        raise TrainingOptionError(f"{algo.upper()} learns from a training dataset: give --dataset (a folder that "
                                  f"`mewa-bench datasets build NAME` wrote)", "--dataset")
    return chosen


def plan_runs(chosen: Algorithm, name: str, suite: str | None, seeds: list[int], steps: int | None, out: Path | None,
              resume: bool, workers: list[str], settings: list[str], datasets: list[Path]) -> TrainingPlan:
    """One job per seed (each seed once): its settings with whole updates, its run folder (under `out` when there
    are several seeds) and the `mewa-bench train` command that reproduces it; TrainingOptionError."""
    algo, module = chosen.algo, chosen.module
    if steps is None:
        steps = module.Settings().total_steps if hasattr(module, "STEP_UNIT") else 4_000_000
    jobs = []
    for s in dict.fromkeys(seeds):  # each seed once, in the order given
        try:
            seed_settings = whole_updates(module.settings_from({**chosen.overrides, **chosen.offline,
                                                                "suite": suite or DEFAULT_SUITE, "seed": s,
                                                                "total_steps": steps, "workers": workers_arg(workers)}))
        except ValueError as e:
            raise TrainingOptionError(str(e), "--worker" if workers or not chosen.offline else "--dataset") from None
        if suite is not None and seed_settings.suite != suite:
            raise TrainingOptionError(f"the dataset is of {seed_settings.suite}, not {suite}", "--suite")
        run = run_name(name, seed_settings.suite, s)  # never seed<s> alone: two algorithms' runs must not collide
        folder = (out / run if len(seeds) > 1 else out) if out else Path("runs") / run
        command = " ".join(["mewa-bench train", algo, *([f"--algorithm {shlex.quote(name)}"] * (name != algo)),
                            *(f"--set {shlex.quote(item)}" for item in settings), "--suite",
                            shlex.quote(seed_settings.suite), "--seed", str(s), "--steps",
                            str(seed_settings.total_steps), "--out", shlex.quote(str(folder)),
                            *(f"--worker {w}" for w in workers),
                            *(f"--dataset {shlex.quote(str(d))}" for d in datasets)])
        jobs.append((seed_settings, folder.resolve(), resume, command))
    return TrainingPlan(chosen, name, steps, jobs)


def train_here(plan: TrainingPlan, rerun: bool, seed_started: Callable[[Any], SeedProgress]) -> list[list[Path]]:
    """Train the plan's seeds one after the other in this process; the files each wrote.

    `seed_started(settings)` is called as a seed begins and returns its progress callback; with `rerun`
    the metrics also go to the run folder's Rerun scalars as they come.
    """
    algo, suite = plan.algorithm.algo, plan.suite
    written = []
    for settings, folder, resume, command in plan.jobs:
        show = seed_started(settings)
        scalars = _training_scalars(folder, f"{algo} on {suite}, seed {settings.seed}", resume) if rerun else None

        def progress(done: int, total: int, row: dict, show: SeedProgress = show, scalars=scalars) -> None:
            show(done, total, row)
            if scalars is not None:
                scalars.log(row)

        try:
            paths = plan.algorithm.module.train_run(settings, folder, resume, command, progress=progress)
        finally:
            if scalars is not None:
                scalars.close()
        written.append([*paths, scalars.path] if scalars is not None else paths)
    return written


def run_job(job: Job, algo: str) -> list[Path]:
    """One seed's run of algorithm `algo` (its registry name): `train_run(*job)`, a unit of work for a Ray task."""
    return load_algorithm(algo).train_run(*job)


def train_on_ray(plan: TrainingPlan, address: str, rerun: bool, seed_done: Callable[[], None]) -> list[list[Path]]:
    """Train the plan's seeds as one Ray task each on the Ray instance at `address`; the files each wrote.

    `seed_done()` is called as each seed finishes; with `rerun` the Rerun scalars are written from each run's
    metrics file afterwards.
    """
    from mewa_bench.protocol.ray_backend import ray_map, session

    algo, suite = plan.algorithm.algo, plan.suite
    with session(address):
        written = ray_map(run_job, plan.jobs, plan.algorithm.algo, on_done=lambda _: seed_done())
    for (settings, folder, _, _), paths in zip(plan.jobs, written) if rerun else ():
        scalars = _training_scalars(folder, f"{algo} on {suite}, seed {settings.seed}", True)
        scalars.close()
        paths.append(scalars.path)
    return written


def finish_run(plan: TrainingPlan, job: Job, paths: list[Path]) -> list[Path]:
    """Make a trained run folder a submission: record run.json, plot its training curve and title its README
    (`name_readme`); `paths` and the first two."""
    from mewa_bench.reports.training_curves import plot_training_curves

    settings, folder, _, _ = job
    algo, suite = plan.algorithm.algo, plan.suite
    folders = [settings.dataset, *getattr(settings, "more_datasets", [])] if plan.algorithm.learns_offline else []
    notes = "; ".join(("also " if i else "") + dataset_note(folder) for i, folder in enumerate(folders))
    info = write_run_info(folder, RunInfo(algorithm=plan.name, seed=settings.seed, suite=suite,
                                          steps=settings.total_steps, notes=notes,
                                          settings={**plan.algorithm.overrides, **plan.algorithm.offline}))
    curve = plot_training_curves({f"seed {settings.seed}": folder / plan.algorithm.module.METRICS},
                                 folder / "training_curve.png", f"{plan.name} on {suite}, seed {settings.seed}")
    name_readme(folder / "README.md", algo, plan.name, notes)
    return [*paths, info, curve]


def name_readme(readme: Path, algo: str, name: str, data: str) -> None:
    """Title a run's README with its name on the boards (`--algorithm`, when it is not the algorithm's own) and, for
    an offline run, say what it learnt from (the dataset, its frames, build command and archive sha256)."""
    from mewa_bench.files import write_atomic

    text = readme.read_text()
    if name != algo and text.startswith(f"# {algo} ("):
        text = f"# {name} (" + text[len(f"# {algo} ("):]
    if data and "\nTraining data: " not in text:
        text += f"\nTraining data: {data}.\n"
    write_atomic(readme, text)


def _training_scalars(folder: Path, name: str, replay: bool):
    """A run folder's Rerun training scalars (metrics.rrd), with the rows already in its metrics file when
    `replay` (a resumed run, or a run trained on Ray)."""
    import csv

    from mewa_bench.agents.training_io import METRICS
    from mewa_bench.logs.training_scalars import FILE, TrainingScalars

    scalars = TrainingScalars(folder / FILE, name)
    if replay and (folder / METRICS).exists():
        with (folder / METRICS).open(newline="") as f:
            for row in csv.DictReader(f):
                scalars.log(row)
    return scalars
