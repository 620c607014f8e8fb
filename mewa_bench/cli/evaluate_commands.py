"""Playing agents: `evaluate` (score on a suite), `record` (a LeRobot dataset), `view` (a Rerun log), `rollout`
(random play) and `info` (versions)."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.table import Table

from mewa_bench.cli.options import (RAY_ADDRESS_HELP, RAY_HELP, _mode_options, _parse_agent_args, _parse_bytes,
                                    _parse_ints, _parse_seeds, _ray_option)
from mewa_bench.cli.typer_app import _print_error, app, console
from mewa_bench.design.suites import DEFAULT_SUITE
from mewa_bench.extras import MissingExtra
from mewa_bench.protocol.config import default_seeds_text


@app.command()
def info() -> None:
    """Show versions of mewa-bench and its key dependencies, the env ids, Python and the platform."""
    from mewa_bench.cli.system_info import system_info

    table = Table(show_header=False, box=None)
    for key, value in system_info().items():
        table.add_row(f"[bold]{key}[/bold]", str(value))
    console.print(table)


@app.command()
def rollout(episodes: int = typer.Option(3, min=1, help="Episodes to play."),
            seed: int = typer.Option(0, help="Seed of the env and the policy."),
            render: bool = typer.Option(False, "--render", metavar="", help="Print every step as text.")) -> None:
    """Play a few episodes of the default env (narrow-v1 task, meta-train workers) with random actions."""
    from mewa_bench.envs.rollout import random_rollouts

    table = Table("episode", "worker", "steps", "return", "normalised")
    for ep in random_rollouts(episodes, seed, render=console.print if render else None):
        table.add_row(str(ep.index), ", ".join(f"{w:.2f}" for w in ep.worker), str(ep.steps),
                      f"{ep.episode_return:.2f}", f"{ep.normalised_return:.3f}")
    console.print(table)


DEFAULT_SEEDS_HELP = f"the suite's protocol seeds: {default_seeds_text()}"
LOG_HELP = ("Trajectory logs to write: mcap, rerun or mcap,rerun. A ranked run's logs are large (random agent: about "
            "220 MB of MCAP and 370 MB of .rrd on a narrow suite, 340 MB and 600 MB on a wide one): log a subset with "
            "--log-pairs / --log-seeds.")


@app.command()
def evaluate(
    agent: Path = typer.Argument(..., metavar="AGENT", help="Your agent: a .py file with make_vector_agent(...) / class VectorAgent (batched: all lanes in one call) or make_agent(...) / class Agent (one lane per object); see the README."),
    suite: str = typer.Option(DEFAULT_SUITE, help="Suite name (narrow-v2, wide-v2: built to measure adaptation; narrow-v1, wide-v1: the paper's) or path."),
    seeds: str = typer.Option("default", show_default=False, help="Number of seeds (0..n-1) or a comma list, e.g. 0,1,2; default: "
                              f"{DEFAULT_SEEDS_HELP} (ranked runs use exactly these)."),
    out: Path = typer.Option(None, help="Results file (default: results/<agent>-<suite>.json)."),
    name: str = typer.Option(None, help="Agent name in the results (default: from the file name)."),
    agent_arg: list[str] = typer.Option([], "--agent-arg", metavar="K=V", help="key=value passed to make_agent / Agent (repeatable)."),
    checkpoint: str = typer.Option(None, help="Checkpoint path passed to the agent as checkpoint=..."),
    in_process: bool = typer.Option(False, "--in-process", metavar="", help="Run the agent in this process (debugging; no limits)."),
    time_limit: float = typer.Option(10.0, help="Seconds per agent call (0 = none)."),
    memory_limit: str = typer.Option("4G", help="Agent address-space limit, e.g. 4G, 512M, or none."),
    privileged: bool = typer.Option(False, "--privileged", metavar="", help="Tell the agent the hidden pair (reference agents only; never ranked)."),
    jobs: int = typer.Option(1, min=1, metavar="N", help="Parallel worker processes over (pair, seed) units."),
    lanes: int = typer.Option(64, min=1, metavar="N", help="Units played side by side per process, one IPC round trip per step for "
                              "all: a vector agent gets them in one call, a one-lane agent as that many objects; 1 = one "
                              "unit at a time."),
    resume: bool = typer.Option(False, "--resume", metavar="", help="Continue an interrupted run in the same results file (same agent file)."),
    overwrite: bool = typer.Option(False, "--overwrite", metavar="", help="Replace an existing results file."),
    pairs: str = typer.Option(None, help="Only these pairs, e.g. 0,3 (a partial run, for quick checks)."),
    log: str = typer.Option(None, help=LOG_HELP),
    log_dir: Path = typer.Option(Path("logs"), help="Folder for the log files (named after the results file)."),
    log_pairs: str = typer.Option(None, help="Log only these pairs, e.g. 0,3 (every unit is still played and scored)."),
    log_seeds: str = typer.Option(None, help="Log only these seeds: a count (2 = seeds 0, 1) or a comma list."),
    mode: str = typer.Option("vector", help="vector (float32[18]) or sapien ({'state', 'image'} rendered by SAPIEN)."),
    image_size: str = typer.Option("128x128", help="Image size HxW in sapien mode."),
    ray: bool = typer.Option(False, "--ray", metavar="", help=RAY_HELP),
    ray_address: str = typer.Option(None, "--ray-address", help=RAY_ADDRESS_HELP),
) -> None:
    """Score an agent on a frozen suite under the 10-episode adaptation protocol and write a results file."""
    from mewa_bench.protocol.config import EvalConfig
    from mewa_bench.cli.results_tables import results_table

    config = EvalConfig(
        agent_path=agent, suite=suite, seeds=None if seeds == "default" else _parse_seeds(seeds), out=out, name=name,
        agent_args=_parse_agent_args(agent_arg), checkpoint=checkpoint, isolated=not in_process,
        time_limit=time_limit or None, memory_limit=_parse_bytes(memory_limit), privileged=privileged,
        jobs=jobs, lanes=lanes, resume=resume, overwrite=overwrite,
        pairs=tuple(_parse_ints(pairs, "--pairs")) if pairs else None, ray=_ray_option(ray, ray_address),
        **_mode_options(mode, image_size))
    results, path, logs = _run_with_progress(config, log, log_dir, f"{agent.name} on {suite}",
                                             resume_hint="re-run the same command with --resume to continue",
                                             log_subset=_log_subset(log, log_pairs, log_seeds))
    console.print(results_table(results))
    console.print(f"results: [bold]{path}[/bold]" + ("" if results["complete"] else " (partial run: not rankable)"))
    for p in logs:
        console.print(f"log: {p}")


def _log_subset(log: str | None, pairs: str | None, seeds: str | None) -> dict:
    """make_log_sinks' pairs and seeds from --log-pairs and --log-seeds (which need --log)."""
    if (pairs or seeds) and not log:
        raise typer.BadParameter("--log-pairs and --log-seeds choose what --log writes: add --log mcap or rerun",
                                 param_hint="--log")
    return {"pairs": tuple(_parse_ints(pairs, "--log-pairs")) if pairs else None,
            "seeds": _parse_seeds(seeds, "--log-seeds") if seeds else None}


def _run_with_progress(config, log: str | None, log_dir: Path, label: str, extra_sinks=(), resume_hint: str = "",
                       log_subset: dict | None = None):
    """Run `evaluate` with a progress bar, log sinks and clear errors; (results, results path, log paths)."""
    from mewa_bench.logs.files import make_log_sinks, parse_log_kinds
    from mewa_bench.protocol.config import default_results_path
    from mewa_bench.protocol.runner import EvaluationError, evaluate
    from mewa_bench.design.suites import load_suite

    try:
        kinds = parse_log_kinds(log)
        stem = (config.out or default_results_path(config, load_suite(config.suite))).stem
        sinks = [*make_log_sinks(kinds, log_dir, stem, **(log_subset or {})), *extra_sinks]
    except (ValueError, OSError) as e:  # bad --log, or a --log-dir that cannot be created
        _print_error(e)
        raise typer.Exit(1) from None
    with Progress(SpinnerColumn(), TextColumn("[progress.description]{task.description}"), BarColumn(),
                  MofNCompleteColumn(), TimeElapsedColumn(), console=console, transient=True) as bar:
        task = bar.add_task(label, total=None)
        try:
            results, path = evaluate(config, progress=lambda done, total: bar.update(task, completed=done, total=total),
                                     sinks=sinks)
        except EvaluationError as e:
            bar.stop()
            _print_error(e)
            out = config.out or default_results_path(config, load_suite(config.suite))
            if out.exists():
                console.print(f"The units finished before the error are kept in {out}. If the failure was not the "
                              f"agent's fault (a time limit too tight, an interruption), "
                              f"{resume_hint or 'run again with another --results file'}; "
                              "a changed agent file needs a new run.")
            raise typer.Exit(1) from None
        except (ValueError, MissingExtra) as e:  # bad suite, results file or option; a log/dataset extra missing
            bar.stop()
            _print_error(e)
            raise typer.Exit(1) from None
        except (RuntimeError, OSError) as e:  # a log/dataset sink failed, or a file could not be written
            bar.stop()
            console.print(f"[red]error:[/red] {type(e).__name__}: {e}")
            raise typer.Exit(1) from None
    return results, path, [s.path for s in sinks if hasattr(s, "path") and s.path.exists()]


@app.command()
def record(
    policy: str = typer.Option(..., help="A baseline policy (random, random-task-specific, max-expected, "
                                         "toptimal(rho1=R1,rho2=R2,q=Q)) or an agent .py file."),
    out: Path = typer.Option(..., help="Dataset folder to create (LeRobot v3.0; must not exist)."),
    suite: str = typer.Option(DEFAULT_SUITE, help="Suite name or path."),
    seeds: str = typer.Option("1", help="Number of seeds (0..n-1) or a comma list."),
    repo_id: str = typer.Option(None, help="LeRobot repo id of the dataset (default: mewa/<folder name>)."),
    fps: int = typer.Option(10, help="Frames per second stored in the dataset."),
    results: Path = typer.Option(None, help="Results file of the rollout (default: <out>.results.json)."),
    agent_arg: list[str] = typer.Option([], "--agent-arg", help="key=value passed to the agent (repeatable)."),
    privileged: bool = typer.Option(False, "--privileged", metavar="", help="Tell an agent file the hidden pair (e.g. the oracle)."),
    jobs: int = typer.Option(1, min=1, help="Parallel worker processes over (pair, seed) units."),
    log: str = typer.Option(None, help="Also write trajectory logs: mcap, rerun or mcap,rerun."),
    log_dir: Path = typer.Option(Path("logs"), help="Folder for the log files."),
    pairs: str = typer.Option(None, help="Only these pairs, e.g. 0,3."),
    mode: str = typer.Option("vector", help="vector, or sapien to also record camera images."),
    image_size: str = typer.Option("128x128", help="Image size HxW in sapien mode."),
    video: bool = typer.Option(False, "--video", metavar="", help="Store sapien images as AV1 video (smaller, lossy) instead of PNG."),
    ray: bool = typer.Option(False, "--ray", metavar="", help=RAY_HELP),
    ray_address: str = typer.Option(None, "--ray-address", help=RAY_ADDRESS_HELP),
) -> None:
    """Roll out a baseline policy or an agent under the evaluation protocol and record a LeRobot dataset."""
    from mewa_bench.datasets.lerobot_recorder import LeRobotSink
    from mewa_bench.protocol.config import rollout_config

    if out.exists():
        console.print(f"[red]error:[/red] {out} already exists (LeRobot creates the dataset folder itself)")
        raise typer.Exit(1)
    try:
        config = rollout_config(policy, _parse_agent_args(agent_arg), privileged, suite=suite, seeds=_parse_seeds(seeds),
                                out=results or out.with_name(out.name + ".results.json"), jobs=jobs,
                                pairs=tuple(_parse_ints(pairs, "--pairs")) if pairs else None,
                                ray=_ray_option(ray, ray_address), **_mode_options(mode, image_size))
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--policy") from None
    sink = LeRobotSink(out, repo_id or f"mewa/{out.name}", fps=fps, video=video)
    results_data, path, logs = _run_with_progress(config, log, log_dir, f"recording {policy} on {suite}", [sink])
    console.print(f"dataset: [bold]{out}[/bold] ({sink.frames:,} frames, {len(results_data['units']) * config.episodes} "
                  f"episodes, {sink.frames_per_second:,.0f} frames/s); results: {path}")
    for p in logs:
        console.print(f"log: {p}")


@app.command()
def view(file: Path = typer.Argument(..., metavar="FILE", help="A Rerun recording (.rrd) written with --log rerun."),
         web: bool = typer.Option(False, "--web", metavar="", help="Serve the web viewer on 127.0.0.1 instead of opening a window."),
         port: int = typer.Option(None, help="Port of the web viewer.")) -> None:
    """Open a Rerun recording in the Rerun viewer (a native window, or with --web the web viewer)."""
    from mewa_bench.logs.view import ViewerError, open_viewer

    if file.suffix != ".rrd":
        console.print(f"[red]error:[/red] {file} is not a Rerun recording (.rrd); MCAP files open in Foxglove")
        raise typer.Exit(1)
    try:
        code = open_viewer(file, web=web, web_port=port)
    except ViewerError as e:
        _print_error(e)
        raise typer.Exit(1) from None
    raise typer.Exit(code)
