"""`mewa-bench train`: parses the options, runs `mewa_bench.training_runs`, shows the progress and what it wrote."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from mewa_bench.cli.options import RAY_ADDRESS_HELP, _ray_option
from mewa_bench.cli.typer_app import _or_exit, app, console
from mewa_bench.design.suites import DEFAULT_SUITE


@app.command()
def train(algo: str = typer.Argument(..., metavar="ALGO", help="rl2, varibad, pearl, maml, dpt, imitation or ad (the last three offline) "
                                                              "(mewa_bench.agents.training_io.ALGORITHMS)."),
          suite: str = typer.Option(None, help="Suite whose tasks and meta-train workers it trains on (default: "
                                               f"{DEFAULT_SUITE}; an offline run's is its dataset's)."),
          seed: list[int] = typer.Option([1], "--seed", help="Training seed (repeatable: one run per seed; "
                                                           "runs are deterministic given it)."),
          steps: int = typer.Option(None, min=1, help="Env steps to train for (default 4,000,000; dpt, "
                                                      "imitation: meta-episodes, default 40,000; ad: windows, default 32,000), rounded up to whole updates "
                                                      "(the exact number is printed before training starts)."),
          out: Path = typer.Option(None, help="Run folder (default: runs/<algo>-<suite>-seed<seed>; with several "
                                              "seeds, <out>/<algo>-<suite>-seed<seed>)."),
          resume: bool = typer.Option(False, "--resume", metavar="", help="Continue from the run folder's last checkpoint."),
          worker: list[str] = typer.Option([], "--worker", help="Train on this worker only, e.g. 0,1,1,1 "
                                                                "(repeatable; default: the suite's meta-train distribution)."),
          set_: list[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="Change one of the algorithm's "
                                         "settings, e.g. learning_rate=3e-4 (repeatable; recorded in run.json)."),
          dataset: list[Path] = typer.Option([], "--dataset", help="Offline algorithms (dpt, imitation, ad): the training dataset "
                                                                   "folder they learn from (`mewa-bench datasets build "
                                                                   "NAME` writes mewa-datasets/NAME); its suite is the "
                                                                   "run's. ad: repeatable, pooling the histories of "
                                                                   "several datasets of one suite."),
          algorithm: str = typer.Option(None, "--algorithm", help="The algorithm's name on the boards and in the "
                                                                 "run folder's name (default: ALGO; name runs with "
                                                                 "other settings apart, e.g. rl2-lr3e-4)."),
          rerun: bool = typer.Option(False, "--rerun", metavar="", help="Also log the metrics as Rerun scalars to "
                                                           "<run folder>/metrics.rrd as they come (`mewa-bench view` "
                                                           "it; with --ray, written when the seed finishes)."),
          ray: bool = typer.Option(False, "--ray", metavar="", help="One Ray task per seed on a local Ray instance."),
          ray_address: str = typer.Option(None, "--ray-address", help=RAY_ADDRESS_HELP)) -> None:
    """Train a learned meta-RL baseline; each run folder becomes a submission (agent.py, checkpoint, metrics)."""
    from mewa_bench.training_runs import (TrainingOptionError, choose_algorithm, finish_run, plan_runs, train_here,
                                          train_on_ray)

    try:
        chosen = choose_algorithm(algo, set_, dataset, absolute_dataset=ray_address is not None or ray)
    except TrainingOptionError as e:
        raise typer.BadParameter(str(e), param_hint=e.option) from None
    address = _ray_option(ray, ray_address)
    try:
        plan = plan_runs(chosen, algorithm or algo, suite, seed, steps, out, resume, worker, set_, dataset)
    except TrainingOptionError as e:
        raise typer.BadParameter(str(e), param_hint=e.option) from None
    suite = plan.suite
    console.print(_steps_text(plan.steps, plan.jobs[0][0], chosen.step_unit))
    if address is None:
        console.print(OFFLINE_PROGRESS_TEXT if chosen.learns_offline else TRAIN_PROGRESS_TEXT)
    with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=console) as bar:
        if address is not None:  # one seed per Ray task; progress as seeds finish
            task = bar.add_task(f"{algo} on {suite}: seeds on Ray", total=len(plan.jobs))
            written = _or_exit(lambda: train_on_ray(plan, address, rerun, lambda: bar.advance(task)))
        else:
            def seed_started(settings) -> Callable[[int, int, dict], None]:
                """A bar for the seed `settings` train, and its progress callback."""
                task = bar.add_task(f"{algo} on {suite}, seed {settings.seed}", total=settings.total_steps)

                def show(done: int, total: int, row: dict, task=task, s=settings.seed) -> None:
                    bar.update(task, completed=done, total=total, description=(
                        f"{algo} seed {s}: loss {row['loss']:.3f}, label accuracy {row['accuracy']:.2f}"
                        if "accuracy" in row else f"{algo} seed {s} meta-train: "
                        f"{row['episode_1_normalised_return']:.2f} -> {row['episode_10_normalised_return']:.2f}"))

                return show

            written = _or_exit(lambda: train_here(plan, rerun, seed_started))
    for job, paths in zip(plan.jobs, written):
        for path in finish_run(plan, job, paths):
            console.print(f"wrote {path}")


OFFLINE_PROGRESS_TEXT = ("progress: the loss and accuracy of its predictions of the dataset's labels (dpt: the optimal "
                         "actions; imitation, ad: the behaviour's) (not a "
                         "score: `evaluate` plays the suite's curated test workers, which the dataset never holds)")
TRAIN_PROGRESS_TEXT = ("progress: meta-train normalised return, episode 1 -> 10 of a pair (not a score: `evaluate` "
                       "scores the suite's curated test workers, which training never meets; see the README)")


def _steps_text(asked: int, settings, unit: str = "env steps") -> str:
    """What a run will train: the exact env steps (or the offline algorithm's unit) and updates, and whether
    --steps was rounded up."""
    per, total = settings.steps_per_update, settings.total_steps
    rounded = f"; --steps {asked:,} rounded up to whole updates" if total != asked else ""
    updates = total // per
    return f"training {total:,} {unit} per run ({updates:,} update{'s' * (updates != 1)} of {per:,}{rounded})"
