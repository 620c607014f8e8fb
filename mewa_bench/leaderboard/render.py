"""Text forms of a leaderboard: Markdown, CSV and the static HTML index (no external assets)."""

from __future__ import annotations

import csv
import html
import io

from mewa_bench.leaderboard import algorithm_tables
from mewa_bench.leaderboard.algorithm_tables import percent
from mewa_bench.leaderboard.board import PRIVILEGED, REFERENCE, Board, Row
from mewa_bench.leaderboard.judging import family_caption
from mewa_bench.protocol.verdicts import FAMILY_ALPHA, PROCEDURE

HEADER = ("rank", "agent", "gap won [95% CI]", "mean score [95% CI]", "IQM", "s_1", "s_10", "adaptability [95% CI]",
          "adapts", "beats best fixed", "skill", "seeds", "date", "package version", "agent sha256")
CSV_HEADER = ("rank", "agent", "kind", "gap_won", "gap_won_low", "gap_won_high", "mean_score", "mean_score_low",
              "mean_score_high", "iqm", "s_1", "s_10", "adaptability", "adaptability_low", "adaptability_high",
              "vs_best_fixed", "vs_best_fixed_low", "vs_best_fixed_high", "adapts", "beats_best_fixed", "skill", "seeds",
              "date", "package_version", "agent_sha256", "file")
UNRANKED = "—"
_NUMERIC = frozenset({0, 2, 3, 4, 5, 6, 7, 10, 11})  # HEADER columns aligned right
SHORT_SHA = 12

EXPLANATION = (
    ("gap won", "(mean score - best fixed) / (1 - best fixed): the share of the non-adaptive gap (what only "
                "adaptation can win) that an agent wins; 0 = the best fixed policy, 100% = max expected. A "
                "checkpoint's comes from its paired difference with the best fixed policy on the same luck."),
    ("score", "s_k = the normalised return of episode k divided by the pair's max-expected baseline (1.0 = as "
              "good as the best t-optimal policy that knows the worker), averaged over pairs x seeds. The mean "
              "score averages s_1..s_10; 95% bootstrap CIs resample seeds within each pair (small-sample "
              "corrected), recomputed from each results file's units."),
    ("adaptability", "mean(s_10 - s_1): how much an agent improves over the 10 episodes with the same "
                     "hidden worker."),
    ("protocol 2", "worker luck is coupled to each episode's seed and the reference policies are replayed on "
                   "the same seeds as control variates (unbiased, far less noise); CIs resample seeds within "
                   "each pair. IQM: rliable's interquartile mean, over the pair means (docs/protocol.md)."),
    ("verdicts", f"adapts = adaptability > 0; beats best fixed = gap won > 0. One-sided tests on each row's own "
                 f"interval statistic, decided together by {PROCEDURE} procedure over every test a board shows (on a "
                 f"board with algorithms of several runs, theirs and the checkpoint rows' half of the family each), so "
                 f"that the chance of any false \"yes\" on a board is at most {FAMILY_ALPHA:.1%} (a fixed policy is "
                 f"not called adaptive because a board has many rows)."),
    ("skill", "(S - S_rts) / (1 - S_rts), with S the mean score and S_rts that of the random task-specific "
              "baseline: 0 = knows the game but ignores the worker, 1 = the best t-optimal policy per worker."),
)


def _num(value: float | None) -> str:
    """Four decimals for the tables (empty when absent)."""
    return "" if value is None else f"{value:.4f}"


def _with_ci(value: float, low: float | None, high: float | None) -> str:
    """`0.9512 [0.9401, 0.9600]`, or the bare value for exact reference lines."""
    return _num(value) if low is None or high is None else f"{value:.4f} [{low:.4f}, {high:.4f}]"


def _verdict(value: bool | None, row: Row | None = None) -> str:
    """yes / no for agents ("—" without an interval), empty for reference lines."""
    if value is None:
        return "" if row is None or row.kind == REFERENCE else "—"
    return "yes" if value else "no"


def _gap(row: Row) -> str:
    """The gap won cell: a percentage with its CI (exact for reference lines)."""
    if row.gap_won is None:
        return ""
    if row.gap_won_low is None or row.gap_won_high is None:
        return percent(row.gap_won)
    return f"{percent(row.gap_won)} [{percent(row.gap_won_low)}, {percent(row.gap_won_high)}]"


def _rank(row: Row) -> str:
    """The rank cell: a number, "—" for privileged agents, empty for reference lines."""
    if row.kind == PRIVILEGED:
        return UNRANKED
    return "" if row.rank is None else str(row.rank)


def _name(row: Row) -> str:
    """The agent cell's text, on one line."""
    name = " ".join(row.name.split())
    if row.kind == PRIVILEGED:
        return f"{name} (privileged)"
    return f"{name} (reference)" if row.kind == REFERENCE else name


def cells(row: Row) -> list[str]:
    """The displayed cells of a row, in HEADER order."""
    return [_rank(row), _name(row), _gap(row), _with_ci(row.mean, row.mean_low, row.mean_high), _num(row.iqm),
            _num(row.s_first), _num(row.s_last), _with_ci(row.adaptability, row.adaptability_low, row.adaptability_high),
            _verdict(row.adapts, row), _verdict(row.beats_best_fixed, row),
            _num(row.skill), "" if row.seeds is None else str(row.seeds), row.date, row.package_version,
            row.agent_sha256[:SHORT_SHA]]


def suite_facts(board: Board, quote: str = "") -> str:
    """One sentence identifying the suite (`quote` wraps the hash, e.g. in Markdown backticks)."""
    s = board.suite
    return (f"Suite {s.name} (version {s.content['version']}, {len(s.pairs)} pairs), sha256 {quote}{s.sha256}{quote}; "
            f"non-adaptive gap {s.summary['non_adaptive_gap']:.4f} (1 - the best fixed policy's score: "
            f"what only adaptation can win).")


CHECKPOINTS = ("One row per trained checkpoint (results file). Its CIs resample evaluation seeds within each pair: "
               "they are conditional on that checkpoint and say nothing about another training run of the same "
               "algorithm (the algorithms table above does).")
NOTES = ("Reference rows are exact expected values computed from the suite (not sampled): fixed policies, "
         "so s_1 = s_10 and adaptability is 0.",
         "Privileged agents are told the worker; they are listed for comparison but not ranked (rank —).")


def markdown(board: Board, image_name: str) -> str:
    """The Markdown leaderboard of one suite."""
    def md_row(values: list[str]) -> str:
        return "| " + " | ".join(v.replace("|", "\\|") for v in values) + " |"

    lines = [f"# Leaderboard: {board.suite.name}", "", suite_facts(board, "`"), ""]
    lines += [f"{c}" for c in captions(board)]
    if board.algorithms:
        lines += ["## Algorithms", "", *algorithm_tables.markdown_lines(board.algorithms), ""]
    lines += ["## Checkpoints", "", CHECKPOINTS, ""]
    lines += [md_row(list(HEADER)), "|" + "---|" * len(HEADER)]
    for row in board.rows:
        values = cells(row)
        if row.kind == REFERENCE:
            values[1] = f"*{values[1]}*"
        lines.append(md_row(values))
    lines += ["", *(f"- {n}" for n in NOTES), *(f"- **{term}**: {text}" for term, text in EXPLANATION)]
    lines += ["", f"![Adaptation curves on {board.suite.name}, one panel per algorithm]({image_name})", ""]
    if board.algorithms:
        forest = gap_image(image_name)
        lines += [f"![Gap won per algorithm on {board.suite.name}, with 95% CIs]({forest})", "",
                  f"The board's cells (algorithm, run, pair, adjusted pair-mean score): {cells_name(board.suite.name)}.",
                  ""]
    return "\n".join(lines)


def gap_image(image_name: str) -> str:
    """The forest plot's file name beside the curves' (`narrow-v2.png` -> `narrow-v2-gap-won.png`)."""
    return image_name.removesuffix(".png") + "-gap-won.png"


def cells_name(suite: str) -> str:
    """The cells CSV of a suite's board."""
    return f"{suite}-cells.csv"


def captions(board: Board) -> list[str]:
    """What the board's verdicts are decided by, and what gap won means on its suite, as paragraphs (+ blank)."""
    out = []
    if board.family is not None:
        checkpoints = sum(r.kind != REFERENCE for r in board.rows)
        several = sum(not a.within_run and a.mean.low is not None for a in board.algorithms)
        out += [family_caption(board.family, checkpoints, several), ""]
    note = algorithm_tables.gap_note(board.suite)
    return out + ([note, ""] if note else [])


def _raw(value: float | int | None) -> str:
    """A CSV number at full precision (repr round-trips), empty when absent."""
    return "" if value is None else repr(value)


def csv_text(board: Board) -> str:
    """The CSV leaderboard of one suite: full-precision numbers, rank empty unless ranked."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_HEADER)
    for r in board.rows:
        writer.writerow(["" if r.rank is None else r.rank, r.name, r.kind, _raw(r.gap_won), _raw(r.gap_won_low),
                         _raw(r.gap_won_high), _raw(r.mean), _raw(r.mean_low),
                         _raw(r.mean_high), _raw(r.iqm), _raw(r.s_first), _raw(r.s_last), _raw(r.adaptability),
                         _raw(r.adaptability_low), _raw(r.adaptability_high), _raw(r.vs_best_fixed),
                         _raw(r.vs_best_fixed_low), _raw(r.vs_best_fixed_high), _verdict(r.adapts, r),
                         _verdict(r.beats_best_fixed, r), _raw(r.skill), _raw(r.seeds),
                         r.date, r.package_version, r.agent_sha256, r.file])
    return out.getvalue()


_CSS = """body{font-family:sans-serif;max-width:100em;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:1em 0;font-size:.9em}th,td{border:1px solid #ccc;padding:.3em .6em}
th{background:#f0f0f0}td.n{text-align:right;font-variant-numeric:tabular-nums}tr.reference{color:#555;font-style:italic}
tr.privileged{color:#654}img{max-width:100%}code{font-size:.9em}"""


def _html_table(board: Board) -> list[str]:
    """The rows of one suite as an HTML table."""
    out = ["<table>", "<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in HEADER) + "</tr>"]
    for row in board.rows:
        tds = [f'<td class="n">{html.escape(c)}</td>' if i in _NUMERIC else f"<td>{html.escape(c)}</td>"
               for i, c in enumerate(cells(row))]
        out.append(f'<tr class="{row.kind}">' + "".join(tds) + "</tr>")
    out.append("</table>")
    return out


def index_html(boards: list[Board], files: dict[str, tuple[str, ...]]) -> str:
    """The static page: every suite's tables and figure; `files` maps suite -> (md, csv, png, ...) names."""
    out = ["<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
           "<title>MEWA leaderboards</title>", f"<style>{_CSS}</style>", "</head>", "<body>",
           "<h1>MEWA leaderboards</h1>", "<dl>"]
    for term, text in EXPLANATION:
        out += [f"<dt><b>{html.escape(term)}</b></dt>", f"<dd>{html.escape(text)}</dd>"]
    out.append("</dl>")
    out += [f"<p>{html.escape(n)}</p>" for n in NOTES]
    for board in boards:
        md, csv_name, png = (html.escape(f) for f in files[board.suite.name][:3])
        name = html.escape(board.suite.name)
        out += [f'<h2 id="{name}">{name}</h2>', f"<p>{html.escape(suite_facts(board))}</p>"]
        out += [f"<p>{html.escape(c)}</p>" for c in captions(board) if c]
        if board.algorithms:
            out += ["<h3>Algorithms</h3>", *algorithm_tables.html_table(board.algorithms),
                    f"<p>{html.escape(algorithm_tables.EXPLANATION)}</p>",
                    f'<p><img src="{html.escape(gap_image(files[board.suite.name][2]))}" '
                    f'alt="Gap won per algorithm on {name}, with 95% CIs"></p>']
        out += [f'<p><img src="{png}" alt="Adaptation curves on {name}, one panel per algorithm"></p>',
                "<h3>Checkpoints</h3>", f"<p>{html.escape(CHECKPOINTS)}</p>", *_html_table(board),
                f'<p>Also as <a href="{md}">Markdown</a> and <a href="{csv_name}">CSV</a>'
                + "".join(f', <a href="{html.escape(f)}">{html.escape(f)}</a>' for f in files[board.suite.name][3:]
                          if f.endswith(".csv"))
                + ".</p>"]
    out += ["</body>", "</html>", ""]
    return "\n".join(out)
