"""Text forms of a suite's algorithms table: Markdown lines, CSV and HTML rows."""

from __future__ import annotations

import csv
import html
import io

from mewa_bench.design.suites import Suite
from mewa_bench.leaderboard.algorithms import AlgorithmRow
from mewa_bench.protocol.aggregate import BOOTSTRAP_SAMPLES, BOOTSTRAP_SEED, MIN_RUNS
from mewa_bench.protocol.scoring import Estimate

HEADER = ("rank", "algorithm", "runs", "gap won [95% CI]", "mean score [95% CI]", "IQM [95% CI]", "s_1", "s_10",
          "adaptability [95% CI]", "adapts", "beats best fixed", "note")
CSV_HEADER = ("rank", "algorithm", "privileged", "runs", "gap_won", "gap_won_low", "gap_won_high", "mean_score",
              "mean_score_low", "mean_score_high", "iqm", "iqm_low", "iqm_high", "s_1", "s_10", "adaptability",
              "adaptability_low", "adaptability_high", "adapts", "beats_best_fixed", "adapting_runs", "intervals",
              "note")
NUMERIC = frozenset({0, 2, 3, 4, 5, 6, 7, 8})
SMALL_GAP = 0.05  # below this non-adaptive gap, gap won magnifies small differences of mean score
EXPLANATION = (
    f"One row per algorithm: its training runs (run.json's `algorithm`; a folder without one is a one-run "
    f"algorithm named after it). Gap won = (mean score - best fixed) / (1 - best fixed): the share of what only "
    f"adaptation can win that the algorithm wins (0 = the best fixed policy, 100% = max expected). Statistics over "
    f"the (run, pair) cells of pair-mean scores (<suite>-cells.csv), as rliable defines them (IQM = 25% trimmed "
    f"mean of the cells). 95% CIs resample whole training runs (bootstrap seed {BOOTSTRAP_SEED}, "
    f"{BOOTSTRAP_SAMPLES} samples, small-sample corrected: docs/protocol.md); with fewer than {MIN_RUNS} runs "
    f"they cannot include training variance (note). A one-run algorithm shows its checkpoint's within-run "
    f"intervals and verdicts (\"within run\": conditional on that checkpoint); an algorithm of several runs also "
    f"says in how many of them the checkpoint adapts.")


def gap_note(suite: Suite) -> str | None:
    """What gap won means on a suite whose non-adaptive gap is small (None otherwise)."""
    gap = float(suite.summary["non_adaptive_gap"])
    if gap >= SMALL_GAP:
        return None
    return (f"On {suite.name} the non-adaptive gap is only {gap:.4f}, so gap won magnifies small differences: a mean "
            f"score 0.01 below the best fixed policy is a gap won of {-0.01 / gap:.0%}, and most agents' gap won "
            f"is large and negative. Read it beside the mean score.")


def percent(value: float | None) -> str:
    """A share as a signed percentage with one decimal (empty when absent)."""
    return "" if value is None else f"{100 * value:+.1f}%"


def gap_cell(e: Estimate) -> str:
    """`+54.1% [+50.3%, +57.9%]`, or the value and "(no CI)"."""
    return f"{percent(e.mean)} (no CI)" if e.low is None else f"{percent(e.mean)} [{percent(e.low)}, {percent(e.high)}]"


def _ci(e: Estimate) -> str:
    """`0.9512 [0.9401, 0.9600]`, or the value and "(no CI)"."""
    return f"{e.mean:.4f} (no CI)" if e.low is None or e.high is None else f"{e.mean:.4f} [{e.low:.4f}, {e.high:.4f}]"


def _rank(row: AlgorithmRow) -> str:
    """A number, or "—" for a privileged or unranked algorithm."""
    return "—" if row.rank is None else str(row.rank)


def _name(row: AlgorithmRow) -> str:
    """The algorithm on one line, marked when privileged."""
    name = " ".join(row.algorithm.split())
    return f"{name} (privileged)" if row.privileged else name


def _yes(value: bool | None) -> str:
    """yes / no, or "—" when there is no interval to decide on."""
    return "—" if value is None else ("yes" if value else "no")


def verdict_cell(row: AlgorithmRow, value: bool | None, adapts: bool = False) -> str:
    """A verdict with what it rests on: `yes (within run)`, `no; 2 of 5 runs adapt`."""
    text = _yes(value)
    if row.within_run and value is not None:
        return f"{text} (within run)"
    if adapts and row.adapting_runs is not None:
        return f"{text}; {row.adapting_runs} of {row.runs} runs adapt"
    return text


def intervals(row: AlgorithmRow) -> str:
    """What the row's intervals resample: "over runs", "within run" or "none"."""
    return "within run" if row.within_run else ("none" if row.mean.low is None else "over runs")


def cells(row: AlgorithmRow) -> list[str]:
    """The displayed cells of a row, in HEADER order."""
    return [_rank(row), _name(row), str(row.runs), gap_cell(row.gap_won), _ci(row.mean), _ci(row.iqm),
            f"{row.s_first:.4f}", f"{row.s_last:.4f}", _ci(row.adaptability),
            verdict_cell(row, row.adapts, adapts=True), verdict_cell(row, row.beats_best_fixed), row.note]


def markdown_lines(rows: tuple[AlgorithmRow, ...]) -> list[str]:
    """The Markdown table and its explanation."""
    def md_row(values: list[str]) -> str:
        return "| " + " | ".join(v.replace("|", "\\|") for v in values) + " |"

    lines = [md_row(list(HEADER)), "|" + "---|" * len(HEADER)]
    lines += [md_row(cells(r)) for r in rows]
    return [*lines, "", EXPLANATION]


def _raw(value: float | None) -> str:
    """Full precision (repr round-trips), empty when absent."""
    return "" if value is None else repr(value)


def csv_text(rows: tuple[AlgorithmRow, ...]) -> str:
    """The algorithms table as CSV, full-precision numbers."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_HEADER)
    for r in rows:
        writer.writerow(["" if r.rank is None else r.rank, r.algorithm, "yes" if r.privileged else "no", r.runs,
                         *(_raw(v) for e in (r.gap_won, r.mean, r.iqm) for v in (e.mean, e.low, e.high)),
                         _raw(r.s_first), _raw(r.s_last),
                         *(_raw(v) for v in (r.adaptability.mean, r.adaptability.low, r.adaptability.high)),
                         _yes(r.adapts), _yes(r.beats_best_fixed),
                         "" if r.adapting_runs is None else r.adapting_runs, intervals(r), r.note])
    return out.getvalue()


def html_table(rows: tuple[AlgorithmRow, ...]) -> list[str]:
    """The algorithms table as HTML lines."""
    out = ["<table>", "<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in HEADER) + "</tr>"]
    for row in rows:
        tds = [f'<td class="n">{html.escape(c)}</td>' if i in NUMERIC else f"<td>{html.escape(c)}</td>"
               for i, c in enumerate(cells(row))]
        out.append(f'<tr class="{"privileged" if row.privileged else "agent"}">' + "".join(tds) + "</tr>")
    out.append("</table>")
    return out
