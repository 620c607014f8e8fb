"""`mewa-bench datasets`: list, inspect, download, pack and build offline datasets."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import typer
from rich.markup import escape
from rich.progress import (BarColumn, DownloadColumn, MofNCompleteColumn, Progress, TaskID, TextColumn,
                           TimeElapsedColumn, TransferSpeedColumn)
from rich.table import Table

from mewa_bench.cli.options import _ray_option
from mewa_bench.cli.typer_app import _or_exit, _print_error, console

datasets_app = typer.Typer(no_args_is_help=True, help="List, inspect, build, download and pack offline datasets.")
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
    with _build_progress(f"{name}" + (" on Ray" if where else "")) as progress, \
            (session(where) if where is not None else nullcontext()):
        result = _or_exit(lambda: build_named(name, out, frames, jobs, catalog, ray_tasks if where else None, progress))
    e = result.entry
    if result.spec.built_name != result.spec.name:
        console.print(f"built {result.spec.built_name}: the first {e['frames']:,} frames' worth of {result.spec.name} "
                      f"(frame target {result.spec.frames:,} instead of the dataset's own), under its own name")
    console.print(f"[green]ok[/green] {result.root} ({e['frames']:,} frames, {e['episodes']:,} episodes, "
                  f"{e['frames'] / result.build_seconds:,.0f} frames/s: built in {result.build_seconds:.1f} s, packed in "
                  f"{result.pack_seconds:.1f} s); sha256 {e['sha256']} in {result.catalog}")
    if result.matches_record is not None:
        verdict = "[green]matches[/green]" if result.matches_record else "[yellow]differs from[/yellow]"
        console.print(f"the archive {verdict} the sha256 the shipped catalog records for this build")
    console.print(f"load it: mewa_bench.datasets.load_training_dataset('{result.root}')")


BUILD_PHASES = {"play": "playing (frames)", "exact": "exact labels and values (jobs)", "write": "writing",
                "pack": "packing"}


@contextmanager
def _build_progress(what: str) -> Iterator[Callable[[str, int, int], None]]:
    """A rich progress bar per build phase; yields the `progress(phase, done, total)` a build reports to."""
    with Progress(TextColumn(f"{escape(what)}: {{task.description}}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=console, transient=True) as bars:
        tasks: dict[str, TaskID] = {}

        def progress(phase: str, done: int, total: int) -> None:
            if phase not in tasks:
                tasks[phase] = bars.add_task(BUILD_PHASES.get(phase, phase), total=total)
            bars.update(tasks[phase], completed=done, total=total)
        yield progress


@datasets_app.command("export")
def datasets_export(source: str = typer.Argument(..., metavar="NAME_OR_DIR", help="A training dataset's folder, or its "
                                                                                "name under --dir."),
                    format: str = typer.Option("minari", "--format", help="Export format (minari)."),
                    out: Path = typer.Option(..., "--out", help="Minari's datasets folder (use it as MINARI_DATASETS_PATH)."),
                    dir: Path = typer.Option(Path("mewa-datasets"), "--dir", help="Where NAME is looked for."),
                    dataset_id: str = typer.Option(None, "--id", help="Minari dataset id (default: the dataset's own, "
                                                                      "e.g. mewa/narrow-v2-train-expert-v1).")) -> None:
    """Export a training dataset to Minari's own format (arrow), with Minari's metadata."""
    from mewa_bench.datasets.minari_export import export_minari, find_training_dataset

    if format != "minari":
        _print_error(ValueError(f"unknown --format {format!r}; expected minari"))
        raise typer.Exit(1)
    with console.status(f"exporting {source} to Minari"):
        result = _or_exit(lambda: export_minari(find_training_dataset(source, dir), out, dataset_id))
    console.print(f"[green]ok[/green] {result.path} ({result.episodes:,} episodes, {result.steps:,} steps)")
    console.print(f"load it: MINARI_DATASETS_PATH={out} python -c \"import minari; "
                  f"print(minari.load_dataset('{result.dataset_id}'))\"")
