"""`mewa-bench leaderboard`: validate every results file under `submissions/` and write the leaderboards.

Per shipped suite: `<suite>.md`, `<suite>.csv` (checkpoints), `<suite>.png` (adaptation curves, a panel per
algorithm), `<suite>-gap-won.png` (gap won per algorithm), `<suite>-algorithms.csv` and `<suite>-cells.csv`
(algorithm, run, pair, adjusted pair-mean score: rliable's input); plus one `index.html`. Invalid
results files are skipped and reported with the reason, never silently. The output depends only on
the inputs (sorted iteration, no current timestamps), and every file is written atomically.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mewa_bench.design.suites import ALL_SUITES, load_suite
from mewa_bench.files import write_atomic
from mewa_bench.leaderboard import algorithm_tables, cells
from mewa_bench.leaderboard.assemble import make_board
from mewa_bench.leaderboard.board import Board
from mewa_bench.leaderboard.plot import plot_curves, plot_gap_won
from mewa_bench.leaderboard.render import cells_name, csv_text, gap_image, index_html, markdown
from mewa_bench.leaderboard.validate import Entry, InvalidResults, SuiteCache, find_results_files, load_entry


@dataclass(frozen=True)
class LeaderboardReport:
    """What a build did: files written, valid entries per suite (table order), skipped files with reasons."""

    written: tuple[Path, ...]
    entries: dict[str, tuple[Entry, ...]]
    invalid: tuple[tuple[Path, str], ...]


def collect(submissions_dir: Path) -> tuple[dict[str, list[Entry]], list[tuple[Path, str]]]:
    """Valid entries grouped by suite, and (file, reason) for every results file that was rejected."""
    if not submissions_dir.is_dir():
        raise NotADirectoryError(f"{submissions_dir}: no such submissions folder")
    suites = SuiteCache()
    entries: dict[str, list[Entry]] = {name: [] for name in ALL_SUITES}
    invalid: list[tuple[Path, str]] = []
    for path in find_results_files(submissions_dir):
        try:
            entry = load_entry(path, suites)
        except InvalidResults as e:
            invalid.append((path, str(e)))
        else:
            twin = next((e for e in entries[entry.suite] if e.path.parent == entry.path.parent), None)
            clone = next((e for e in entries[entry.suite] if e.agent_sha256 == entry.agent_sha256), None)
            if twin is not None:
                invalid.append((path, f"{twin.path.name} of the same submission folder is already on the "
                                      f"{entry.suite} board: one row per submission"))
            elif clone is not None:
                invalid.append((path, f"the same agent file (sha256 {entry.agent_sha256[:12]}…) is already on the "
                                      f"{entry.suite} board as {clone.path.parent.name}: one row per agent"))
            else:
                entries[entry.suite].append(entry)
    return entries, invalid


def write_board(board: Board, out_dir: Path) -> tuple[Path, ...]:
    """Write one suite's Markdown, checkpoints CSV, curves PNG, and (with runs) its algorithms CSV, cells CSV and
    gap-won PNG."""
    name = board.suite.name
    md, csv_path, png = out_dir / f"{name}.md", out_dir / f"{name}.csv", out_dir / f"{name}.png"
    write_atomic(md, markdown(board, png.name))
    write_atomic(csv_path, csv_text(board))
    plot_curves(board, png)
    written = [md, csv_path, png]
    algorithms, cells_path, forest = (out_dir / f"{name}-algorithms.csv", out_dir / cells_name(name),
                                      out_dir / gap_image(png.name))
    write_atomic(algorithms, algorithm_tables.csv_text(board.algorithms))
    write_atomic(cells_path, cells.csv_text(board))
    plot_gap_won(board, forest)
    return (*written, algorithms, cells_path, forest)


def build_leaderboards(submissions_dir: Path, out_dir: Path) -> LeaderboardReport:
    """Validate `submissions_dir/*/` results files and write every shipped suite's leaderboard to `out_dir`."""
    submissions_dir, out_dir = Path(submissions_dir), Path(out_dir)
    entries, invalid = collect(submissions_dir)
    boards = [make_board(load_suite(name), entries[name], submissions_dir.name) for name in ALL_SUITES]
    written: list[Path] = []
    files: dict[str, tuple[str, ...]] = {}
    for board in boards:
        paths = write_board(board, out_dir)
        written += paths
        files[board.suite.name] = tuple(p.name for p in paths)
    index = out_dir / "index.html"
    write_atomic(index, index_html(boards, files))
    written.append(index)
    return LeaderboardReport(tuple(written), {b.suite.name: b.entries for b in boards}, tuple(invalid))
