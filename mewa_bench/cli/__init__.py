"""The `mewa-bench` command line: parses arguments, calls library functions, prints with rich."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (BarColumn, DownloadColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn,
                           TimeElapsedColumn, TransferSpeedColumn)
from rich.table import Table

from mewa_bench.extras import MissingExtra
from mewa_bench.design.suites import DEFAULT_SUITE
from mewa_bench.protocol.config import default_seeds_text

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="MEWA meta-RL benchmark: evaluate agents on frozen suites, generate suites, record data.")
console = Console()


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
RAY_HELP = "Run the units as Ray tasks on a local Ray instance (needs the ray extra; --jobs caps its CPUs)."
RAY_ADDRESS_HELP = ("Run the units as Ray tasks on the Ray cluster at this address (e.g. 10.0.0.5:6379 or auto); "
                    "nodes need mewa-bench and the agent file at the same path.")


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



def _ray_option(ray: bool, address: str | None) -> str | None:
    """EvalConfig.ray from --ray / --ray-address (None: local processes), failing early without Ray."""
    if not ray and address is None:
        return None
    from mewa_bench.protocol.ray_backend import LOCAL, RayUnavailable, import_ray

    try:
        import_ray()
    except RayUnavailable as e:
        raise typer.BadParameter(str(e), param_hint="--ray") from None
    return address or LOCAL


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


@app.command()
def leaderboard(submissions: Path = typer.Option(Path("submissions"), help="Folder of submissions/<name>/ results."),
                out: Path = typer.Option(Path("leaderboards"), help="Where to write the tables, plots and page."),
                strict: bool = typer.Option(True, metavar="", help="Exit with code 1 when a results file was skipped "
                                                       "(the boards are written either way).")) -> None:
    """Validate every results file in submissions/ and write leaderboards/<suite>.md, .csv, .png and index.html."""
    from mewa_bench.leaderboard import build_leaderboards

    report = _or_exit(build_leaderboards, submissions, out)
    if not any(report.entries.values()) and not report.invalid:
        console.print(f"[yellow]no results files found in {submissions}/*/ (expected submissions/<name>/results-<suite>.json)[/yellow]")
    for path, reason in report.invalid:
        console.print(f"[yellow]skipped[/yellow] {path}: {reason}")
    for path in report.written:
        console.print(f"wrote {path}")
    if report.invalid:
        console.print(f"[yellow]{len(report.invalid)} results file(s) were invalid and skipped[/yellow]")
        if strict:
            raise typer.Exit(1)


def _mode_options(mode: str, image_size: str) -> dict:
    """Validate --mode and --image-size; in sapien mode check the render device before anything runs."""
    if mode not in ("vector", "sapien"):
        raise typer.BadParameter("expected vector or sapien", param_hint="--mode")
    try:
        height, width = (int(v) for v in image_size.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"expected HxW such as 128x128, got {image_size!r}", param_hint="--image-size") from None
    if mode == "sapien":
        from mewa_bench.render.device import RenderUnavailable, require_render_device

        try:
            require_render_device()
        except RenderUnavailable as e:
            _print_error(e)
            raise typer.Exit(1) from None
    return {"mode": mode, "image_size": (height, width)}


def _parse_ints(text: str, option: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise typer.BadParameter(f"expected integers separated by commas, got {text!r}", param_hint=option) from None


def _parse_seeds(text: str, option: str = "--seeds") -> tuple[int, ...]:
    values = _parse_ints(text, option)
    if "," not in text and len(values) == 1:
        if values[0] < 1:
            raise typer.BadParameter("a single number is a count of seeds (3 = seeds 0, 1, 2); for the one seed 0 "
                                     f"use {option} 1, for another one seed N use {option} N,", param_hint=option)
        return tuple(range(values[0]))
    return tuple(values)


def _parse_agent_args(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise typer.BadParameter(f"expected key=value, got {item!r}", param_hint="--agent-arg")
        out[key] = value
    return out


def _parse_bytes(text: str) -> int | None:
    if text.lower() in ("none", "0", ""):
        return None
    units = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}
    try:
        if text[-1].upper() in units:
            return int(float(text[:-1]) * units[text[-1].upper()])
        return int(text)
    except ValueError:
        raise typer.BadParameter(f"expected a size like 4G, 512M or none, got {text!r}", param_hint="--memory-limit") from None


suites_app = typer.Typer(no_args_is_help=True, help="List, show and verify the versioned suites.")
app.add_typer(suites_app, name="suites")


@app.command()
def generate(kind: str = typer.Argument(..., metavar="KIND", help="narrow, wide, narrow-v2 or wide-v2"),
             out: Path = typer.Option(None, "--out", help="Where to write the suite (default: ./<name>.json; "
                                                           "with --check, nothing is written unless --out is given)."),
             check: bool = typer.Option(False, "--check", metavar="", help="Compare the result byte for byte with the shipped suite."),
             validation: bool = typer.Option(False, "--validation", metavar="", help="Make the suite's validation "
                                              "suite instead: its tasks with workers curated from held-out meta-train "
                                              "draws, for tuning (<name>-validation)."),
             ray: bool = typer.Option(False, "--ray", metavar="", help="Design the candidate tasks as Ray tasks on a local Ray "
                                                           "instance (wide suites: one task per Ray task)."),
             ray_address: str = typer.Option(None, "--ray-address", help=RAY_ADDRESS_HELP)) -> None:
    """Regenerate a suite from the paper's task-design method (exact; reproduces the shipped file byte for byte)."""
    from mewa_bench.design.generate import SPECS
    from mewa_bench.design.suites import shipped_path, suite_text
    from mewa_bench.files import write_atomic

    if kind not in SPECS:
        raise typer.BadParameter(f"expected one of {', '.join(SPECS)}", param_hint="KIND")
    address = _ray_option(ray, ray_address)
    start = time.perf_counter()
    name = SPECS[kind].name + ("-validation" if validation else "")
    with console.status(f"generating {name}") as status:
        content = _or_exit(lambda: _suite_content(kind, validation, address, status.update))
    text = suite_text(content)
    if out is not None or not check:
        target = out or Path(f"{name}.json")
        write_atomic(target, text)
        console.print(f"wrote [bold]{target}[/bold] ({len(text):,} bytes) in {time.perf_counter() - start:.1f} s")
    else:
        console.print(f"generated {name} ({len(text):,} bytes) in {time.perf_counter() - start:.1f} s")
    if check:
        shipped = shipped_path(name)
        same = shipped.exists() and shipped.read_text() == text
        console.print(f"byte-identical to the shipped {shipped.name}: " + ("[green]yes[/green]" if same else "[red]NO[/red]"))
        if not same:
            raise typer.Exit(1)


def _suite_content(kind: str, validation: bool, address: str | None, progress: Callable[[str], None]) -> dict:
    """The content of suite `kind`, or of its validation suite, designed here or on Ray at `address`."""
    from contextlib import nullcontext

    from mewa_bench.design.generate import SPECS, generate_suite

    if validation:
        from mewa_bench.design.validation import validation_suite_content

        return validation_suite_content(SPECS[kind].name)
    if address is None:
        return generate_suite(kind, progress=progress)
    from mewa_bench.protocol.ray_backend import ray_map, session

    with session(address):
        return generate_suite(kind, progress=progress, map_tasks=lambda design, raws, kind_: ray_map(
            design, raws, kind_, on_done=lambda c: progress(f"{c.task.name}: designed and curated")))


@app.command()
def train(algo: str = typer.Argument(..., metavar="ALGO", help="rl2, varibad, pearl, maml or dpt (offline) "
                                                              "(mewa_bench.agents.training_io.ALGORITHMS)."),
          suite: str = typer.Option(None, help="Suite whose tasks and meta-train workers it trains on (default: "
                                               f"{DEFAULT_SUITE}; an offline run's is its dataset's)."),
          seed: list[int] = typer.Option([1], "--seed", help="Training seed (repeatable: one run per seed; "
                                                           "runs are deterministic given it)."),
          steps: int = typer.Option(None, min=1, help="Env steps to train for (default 4,000,000; dpt: "
                                                      "meta-episodes, default 40,000), rounded up to whole updates "
                                                      "(the exact number is printed before training starts)."),
          out: Path = typer.Option(None, help="Run folder (default: runs/<algo>-<suite>-seed<seed>; with several "
                                              "seeds, <out>/<algo>-<suite>-seed<seed>)."),
          resume: bool = typer.Option(False, "--resume", metavar="", help="Continue from the run folder's last checkpoint."),
          worker: list[str] = typer.Option([], "--worker", help="Train on this worker only, e.g. 0,1,1,1 "
                                                                "(repeatable; default: the suite's meta-train distribution)."),
          set_: list[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="Change one of the algorithm's "
                                         "settings, e.g. learning_rate=3e-4 (repeatable; recorded in run.json)."),
          dataset: Path = typer.Option(None, "--dataset", help="Offline algorithms (dpt): the training dataset "
                                                               "folder they learn from (`mewa-bench datasets build "
                                                               "NAME` writes mewa-datasets/NAME); its suite is the "
                                                               "run's."),
          algorithm: str = typer.Option(None, "--algorithm", help="The algorithm's name on the boards and in the "
                                                                 "run folder's name (default: ALGO; name runs with "
                                                                 "other settings apart, e.g. rl2-lr3e-4)."),
          rerun: bool = typer.Option(False, "--rerun", metavar="", help="Also log the metrics as Rerun scalars to "
                                                           "<run folder>/metrics.rrd as they come (`mewa-bench view` "
                                                           "it; with --ray, written when the seed finishes)."),
          ray: bool = typer.Option(False, "--ray", metavar="", help="One Ray task per seed on a local Ray instance."),
          ray_address: str = typer.Option(None, "--ray-address", help=RAY_ADDRESS_HELP)) -> None:
    """Train a learned meta-RL baseline; each run folder becomes a submission (agent.py, checkpoint, metrics)."""
    import shlex

    from mewa_bench.protocol.run_info import RunInfo, run_name, write_run_info
    from mewa_bench.agents.training_io import (UnknownAlgorithm, load_algorithm, setting_overrides, whole_updates,
                                               workers_arg)

    try:
        module = load_algorithm(algo)
    except UnknownAlgorithm as e:
        raise typer.BadParameter(str(e), param_hint="ALGO") from None
    try:
        overrides = setting_overrides(module.Settings, set_)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--set") from None
    algorithm = algorithm or algo
    if steps is None:
        steps = module.Settings().total_steps if hasattr(module, "STEP_UNIT") else 4_000_000
    # as given (the README's command), absolute for Ray workers whose working directory may differ
    offline = {} if dataset is None else {"dataset": str(dataset if ray_address is None and not ray else
                                                         dataset.resolve())}
    offline_algorithm = "dataset" in module.Settings.__dataclass_fields__
    if dataset is not None and not offline_algorithm:
        raise typer.BadParameter(f"{algo} learns online: only offline algorithms (dpt) take a dataset",
                                 param_hint="--dataset")
    if dataset is None and offline_algorithm:
        raise typer.BadParameter(f"{algo.upper()} learns from a training dataset: give --dataset (a folder that "
                                 f"`mewa-bench datasets build NAME` wrote)", param_hint="--dataset")
    address = _ray_option(ray, ray_address)
    jobs = []
    for s in dict.fromkeys(seed):  # each seed once, in the order given
        try:
            settings = whole_updates(module.settings_from({**overrides, **offline, "suite": suite or DEFAULT_SUITE,
                                                           "seed": s, "total_steps": steps,
                                                           "workers": workers_arg(worker)}))
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--worker" if worker or not offline else "--dataset") from None
        if suite is not None and settings.suite != suite:
            raise typer.BadParameter(f"the dataset is of {settings.suite}, not {suite}", param_hint="--suite")
        name = run_name(algorithm, settings.suite, s)  # never seed<s> alone: two algorithms' runs must not collide
        folder = (out / name if len(seed) > 1 else out) if out else Path("runs") / name
        command = " ".join(["mewa-bench train", algo, *([f"--algorithm {shlex.quote(algorithm)}"] * (algorithm != algo)),
                            *(f"--set {shlex.quote(item)}" for item in set_), "--suite", shlex.quote(settings.suite),
                            "--seed", str(s), "--steps", str(settings.total_steps), "--out", shlex.quote(str(folder)),
                            *(f"--worker {w}" for w in worker),
                            *([f"--dataset {shlex.quote(str(dataset))}"] if dataset is not None else [])])
        jobs.append((settings, folder.resolve(), resume, command))
    suite = jobs[0][0].suite
    console.print(_steps_text(steps, jobs[0][0], getattr(module, "STEP_UNIT", "env steps")))
    if address is None:
        console.print(OFFLINE_PROGRESS_TEXT if offline_algorithm else TRAIN_PROGRESS_TEXT)
    with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=console) as bar:
        if address is not None:  # one seed per Ray task; progress as seeds finish
            from mewa_bench.protocol.ray_backend import ray_map, session

            task = bar.add_task(f"{algo} on {suite}: seeds on Ray", total=len(jobs))
            with session(address):
                written = _or_exit(lambda: ray_map(module.train_job, jobs, on_done=lambda _: bar.advance(task)))
            for (settings, folder, _, _), paths in zip(jobs, written) if rerun else ():
                scalars = _or_exit(lambda: _training_scalars(folder, f"{algo} on {suite}, seed {settings.seed}", True))
                scalars.close()
                paths.append(scalars.path)
        else:
            written = []
            for settings, folder, _, command in jobs:
                task = bar.add_task(f"{algo} on {suite}, seed {settings.seed}", total=settings.total_steps)
                scalars = _or_exit(lambda: _training_scalars(folder, f"{algo} on {suite}, seed {settings.seed}",
                                                             resume)) if rerun else None

                def show(done: int, total: int, row: dict, task=task, s=settings.seed, scalars=scalars) -> None:
                    bar.update(task, completed=done, total=total, description=(
                        f"{algo} seed {s}: loss {row['loss']:.3f}, optimal-action accuracy {row['accuracy']:.2f}"
                        if "accuracy" in row else f"{algo} seed {s} meta-train: "
                        f"{row['episode_1_normalised_return']:.2f} -> {row['episode_10_normalised_return']:.2f}"))
                    if scalars is not None:
                        scalars.log(row)

                try:
                    paths = _or_exit(lambda: module.train_run(settings, folder, resume, command, progress=show))
                finally:
                    if scalars is not None:
                        scalars.close()
                written.append([*paths, scalars.path] if scalars is not None else paths)
    from mewa_bench.reports.training_curves import plot_training_curves

    for (settings, folder, _, _), paths in zip(jobs, written):
        paths.append(write_run_info(folder, RunInfo(algorithm=algorithm, seed=settings.seed, suite=suite,
                                                    steps=settings.total_steps, settings={**overrides, **offline})))
        curve = plot_training_curves({f"seed {settings.seed}": folder / module.METRICS}, folder / "training_curve.png",
                                     f"{algo} on {suite}, seed {settings.seed}")
        for path in [*paths, curve]:
            console.print(f"wrote {path}")


OFFLINE_PROGRESS_TEXT = ("progress: the loss and accuracy of its predictions of the dataset's optimal actions (not a "
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


@suites_app.command("list")
def suites_list() -> None:
    """The shipped suites, their size, hash and non-adaptive gap."""
    from mewa_bench.design.suites import ALL_SUITES, load_suite

    table = Table("suite", "tasks", "pairs", "non-adaptive gap", "sha256")
    for name in ALL_SUITES:
        s = load_suite(name)
        table.add_row(name, str(len(s.tasks)), str(len(s.pairs)), f"{s.summary['non_adaptive_gap']:.4f}", s.sha256[:16])
    console.print(table)


@suites_app.command("show")
def suites_show(name: str = typer.Argument(..., metavar="NAME", help="Suite name or path.")) -> None:
    """Tasks, curated workers and baselines of a suite."""
    from mewa_bench.design.suites import load_suite
    from mewa_bench.cli.suite_tables import pair_table, summary_table, task_table

    suite = _or_exit(load_suite, name)
    console.print(f"[bold]{suite.name}[/bold]  sha256 {suite.sha256}")
    console.print(task_table(suite))
    console.print(pair_table(suite))
    console.print(summary_table(suite))


@suites_app.command("verify")
def suites_verify(path: Path = typer.Argument(None, metavar="PATH", help="A suite file (default: every shipped suite).")) -> None:
    """Check that suite files match their recorded content hash."""
    from mewa_bench.design.suites import ALL_SUITES, load_suite

    for target in ([path] if path else list(ALL_SUITES)):
        suite = _or_exit(load_suite, target)
        console.print(f"[green]ok[/green] {suite.name}: content matches sha256 {suite.sha256[:16]}… ({suite.path})")


@suites_app.command("report")
def suites_report(out: Path = typer.Option(Path("docs"), "--out", help="Folder for suites.md and the figures.")) -> None:
    """Write the task-design report (docs/suites.md and a Fig. 2-style PNG per suite)."""
    from mewa_bench.reports.suite_report import write_report

    for path in write_report(out):
        console.print(f"wrote {path}")


results_app = typer.Typer(no_args_is_help=True, help="Results files: convert to the compact layout.")
app.add_typer(results_app, name="results")


@results_app.command("convert")
def results_convert(files: list[Path] = typer.Argument(..., metavar="FILE", help="Results files to rewrite."),
                    rescore: bool = typer.Option(False, "--rescore", metavar="", help="Recompute the scores from the units (for a file scored "
                                                 "by an older mewa-bench) instead of checking the stored ones.")) -> None:
    """Rewrite schema-2 results files as schema 3 (compact units), each after checking it: its units, env seeds
    and scores must come back exactly; a file that fails a check is left as it was."""
    from mewa_bench.protocol.results_convert import convert_results

    failed = 0
    for path in files:
        try:
            done = convert_results(path, rescore=rescore)
        except (ValueError, OSError) as e:
            _print_error(e)
            failed += 1
            continue
        if done.schema_before == 3:
            console.print(f"{escape(str(path))}: schema 3 already, left as it is")
        else:
            console.print(f"{escape(str(path))}: schema {done.schema_before} -> 3, {done.bytes_before / 1e6:.2f} MB -> "
                          f"{done.bytes_after / 1e6:.2f} MB")
        if done.rescored:
            console.print(f"  re-scored: {len(done.rescored)} score fields changed, by at most {done.largest_change:.6f} "
                          f"(first: {escape(done.rescored[0])})")
    if failed:
        raise typer.Exit(1)


datasets_app = typer.Typer(no_args_is_help=True, help="List, inspect, build, download and pack offline datasets.")
app.add_typer(datasets_app, name="datasets")
CATALOG_HELP = ("Dataset catalog (default: $MEWA_DATASETS_CATALOG, else datasets/index.json of the checkout, else the "
                "copy a wheel installs in <prefix>/share/mewa-bench/datasets).")


@datasets_app.command("list")
def datasets_list(catalog: Path = typer.Option(None, help=CATALOG_HELP)) -> None:
    """The datasets in the catalog: training data, training datasets to build, evaluation recordings."""
    from mewa_bench.cli.dataset_tables import buildable_table, evaluation_table, training_table
    from mewa_bench.datasets.catalog import load_catalog
    from mewa_bench.datasets.training_data import TRAINING_DATASETS

    content = _or_exit(load_catalog, catalog)
    console.print(training_table(content, console.width))
    console.print(buildable_table(TRAINING_DATASETS, content, console.width))
    console.print(evaluation_table(content, console.width))


@datasets_app.command("info")
def datasets_info(name: str = typer.Argument(..., metavar="NAME", help="Dataset name (or name@version)."),
                  catalog: Path = typer.Option(None, help=CATALOG_HELP)) -> None:
    """Everything known about one dataset: a catalog entry (a recording of the test pairs says so first), or a
    training dataset `datasets build` makes, with its build command."""
    from mewa_bench.datasets.catalog import load_catalog
    from mewa_bench.datasets.lookup import describe

    entry, warning = _or_exit(lambda: describe(load_catalog(catalog), name))
    if warning:
        console.print(f"[bold red]warning:[/bold red] {escape(warning)}")
    table = Table(show_header=False, box=None)
    for key, value in entry.items():
        table.add_row(f"[bold]{key}[/bold]", escape(str(value)))
    console.print(table)


@datasets_app.command("download")
def datasets_download(source: str = typer.Argument(..., metavar="SOURCE", help="Catalog name, archive URL, or Hugging Face Hub repo id."),
                      dir: Path = typer.Option(Path("mewa-datasets"), "--dir", help="Where datasets are unpacked."),
                      sha256: str = typer.Option(None, help="Expected sha256 of an archive URL not in the catalog."),
                      catalog: Path = typer.Option(None, help=CATALOG_HELP),
                      server: str = typer.Option(None, help="A mewa-bench server's URL: download from its catalog "
                                                            "(an interrupted download resumes).")) -> None:
    """Download, verify (size, sha256, episode and frame counts) and unpack a dataset atomically."""
    from mewa_bench.datasets.catalog import DatasetError, load_catalog
    from mewa_bench.datasets.downloader import download
    from mewa_bench.datasets.lookup import download_warning

    if server is not None:
        from mewa_bench.service.client import server_catalog

        content = _or_exit(server_catalog, server)  # its errors are RuntimeErrors with the server's reason
    elif catalog is not None:
        content = _or_exit(load_catalog, catalog)
    else:
        try:
            content = load_catalog()
        except DatasetError:
            content = None  # no catalog here: URLs and repo ids still work
    warning = _or_exit(download_warning, content, source)
    if warning:
        console.print(f"[bold red]warning:[/bold red] {escape(warning)}")
    with Progress(TextColumn("{task.description}"), BarColumn(), DownloadColumn(), TransferSpeedColumn(),
                  console=console, transient=True) as bar:
        task = bar.add_task(f"downloading {source}", total=None)
        result = _or_exit(lambda: download(source, content, dir, sha256=sha256,
                                           progress=lambda done, total: bar.update(task, completed=done, total=total)))
    check = "verified" if result.verified else "[yellow]not verified (no known sha256)[/yellow]"
    console.print(f"[green]ok[/green] {result.name} -> [bold]{result.path}[/bold] ({check})")
    console.print(f"load it: LeRobotDataset('mewa/{result.name}', root='{result.path}', video_backend='pyav')")


@datasets_app.command("pack")
def datasets_pack(dataset: Path = typer.Argument(..., metavar="DATASET", help="A recorded dataset folder."),
                  name: str = typer.Option(..., help="Catalog name."), version: str = typer.Option("1.0.0"),
                  suite: str = typer.Option(..., help="Suite it was recorded on."),
                  policy: str = typer.Option(..., help="Policy or agent that generated it."),
                  out: Path = typer.Option(Path("datasets"), help="Folder for the archive."),
                  url_base: str = typer.Option(None, help="Public URL prefix of the archive (default: path relative "
                                                          "to the catalog when the archive sits beside it)."),
                  catalog: Path = typer.Option(None, help=CATALOG_HELP)) -> None:
    """Archive a dataset deterministically and add its entry (size, sha256, counts, URL) to the catalog."""
    from mewa_bench.datasets.catalog import add_to_catalog, default_catalog_path, load_catalog
    from mewa_bench.datasets.pack import archive_name, pack_dataset

    catalog_path = catalog or default_catalog_path()
    if catalog_path.exists():
        _or_exit(load_catalog, catalog_path)  # a broken catalog fails before any archive is written
    entry = _or_exit(lambda: pack_dataset(dataset, out, name, version, suite, policy, url_base, catalog_path.parent))
    _or_exit(lambda: add_to_catalog(catalog_path, entry))
    console.print(f"wrote {out / archive_name(name, version)} ({entry['size']:,} bytes, sha256 {entry['sha256'][:16]}…); catalog {catalog_path}")


@datasets_app.command("build")
def datasets_build(name: str = typer.Argument(..., metavar="NAME", help="A training dataset, e.g. narrow-v2-train-expert "
                                                                         "(`datasets list` shows them all)."),
                   out: Path = typer.Option(Path("mewa-datasets"), "--out", help="Folder for the dataset and its archive."),
                   frames: int = typer.Option(None, min=1, help="Frame target (default: the dataset's, 1,000,000)."),
                   jobs: int = typer.Option(2, min=1, help="Processes for the exact labels and values (and the expert); "
                                                           "with --ray, the expert plays --jobs x 4 Ray tasks per round."),
                   catalog: Path = typer.Option(None, help="Catalog to record the archive in (default: <out>/index.json)."),
                   ray: bool = typer.Option(False, "--ray", metavar="", help="The same work as Ray tasks on a local Ray "
                                            "instance (needs the ray extra); the same bytes."),
                   address: str = typer.Option(None, "--ray-address", metavar="ADDR", help="The same on the Ray cluster at "
                                               "this address (e.g. 10.0.0.5:6379 or auto), where it pays: the expert "
                                               "tier's play spreads over the cluster's CPUs.")) -> None:
    """Build a training dataset (meta-train workers only, exact optimal labels) deterministically, pack it and
    record its sha256 in a catalog."""
    from contextlib import nullcontext

    from mewa_bench.datasets.build import build_named
    from mewa_bench.datasets.training_data import ray_tasks

    where = _ray_option(ray, address)
    if where is not None:
        from mewa_bench.protocol.ray_backend import session
    with console.status(f"building {name}" + (" on Ray" if where else "")), \
            (session(where) if where is not None else nullcontext()):
        result = _or_exit(lambda: build_named(name, out, frames, jobs, catalog, ray_tasks if where else None))
    e = result.entry
    console.print(f"[green]ok[/green] {result.root} ({e['frames']:,} frames, {e['episodes']:,} episodes, "
                  f"{e['frames'] / result.build_seconds:,.0f} frames/s: built in {result.build_seconds:.1f} s, packed in "
                  f"{result.pack_seconds:.1f} s); sha256 {e['sha256']} in {result.catalog}")
    if result.matches_record is not None:
        verdict = "[green]matches[/green]" if result.matches_record else "[yellow]differs from[/yellow]"
        console.print(f"the archive {verdict} the sha256 the shipped catalog records for this build")
    console.print(f"load it: mewa_bench.datasets.load_training_dataset('{result.root}')")


def _print_error(error: Exception) -> None:
    """Print a library error's message as it is (not as rich markup, which would eat `mewa-bench[datasets]`)."""
    console.print(f"[red]error:[/red] {escape(str(error))}")


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


def _or_exit(call, *args):
    """Call, turning a library error (bad suite, catalog, download, missing extra...) into a message and exit 1."""
    try:
        return call(*args)
    except (ValueError, RuntimeError, OSError, MissingExtra) as e:
        _print_error(e)
        raise typer.Exit(1) from None


from mewa_bench.cli.service_commands import serve_app, status, submit  # noqa: E402 (the service's commands)

from mewa_bench.cli.compare_command import compare  # noqa: E402 (algorithms over training runs)

app.add_typer(serve_app, name="serve")
app.command()(compare)
app.command()(submit)
app.command()(status)


def main() -> None:
    """Entry point of the `mewa-bench` console script."""
    app()


if __name__ == "__main__":
    main()
