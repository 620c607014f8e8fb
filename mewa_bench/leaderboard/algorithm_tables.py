"""Text forms of a suite's algorithms table: Markdown lines, CSV and HTML rows."""

from __future__ import annotations

import csv
import html
import io

import numpy as np

from mewa_bench.design.suites import Suite
from mewa_bench.leaderboard.algorithms import AlgorithmRow
from mewa_bench.protocol.aggregate import BOOTSTRAP_SAMPLES, BOOTSTRAP_SEED, MIN_RUNS
from mewa_bench.protocol.scoring import Estimate, reference_line_cells

HEADER = ("rank", "algorithm", "runs", "IQM [95% CI]", "mean score [95% CI]", "s_1", "s_10",
          "adaptability [95% CI]", "P(> best fixed) [95% CI]", "adapts", "beats best fixed", "note")
CSV_HEADER = ("rank", "algorithm", "privileged", "runs", "iqm", "iqm_low", "iqm_high", "mean_score", "mean_score_low",
              "mean_score_high", "s_1", "s_10", "adaptability", "adaptability_low", "adaptability_high",
              "p_improvement_over_best_fixed", "p_improvement_over_best_fixed_low",
              "p_improvement_over_best_fixed_high", "adapts", "beats_best_fixed", "note")
NUMERIC = frozenset({0, 2, 3, 4, 5, 6, 7, 8})
EXPLANATION = (
    f"One row per algorithm: its training runs (run.json's `algorithm`; a folder without one is a one-run "
    f"algorithm named after it). Statistics over the (run, pair) cells of pair-mean scores, as rliable defines "
    f"them: IQM = 25% trimmed mean of the cells, P(> best fixed) = the fraction of cells above the best fixed "
    f"policy's exact pair score. 95% CIs resample whole training runs (bootstrap seed {BOOTSTRAP_SEED}, "
    f"{BOOTSTRAP_SAMPLES} samples, small-sample corrected: docs/protocol.md); with fewer than {MIN_RUNS} runs "
    f"they cannot include training variance (note). Verdicts: adapts = adaptability CI above 0; beats best fixed "
    f"= mean-score CI above the best fixed policy's score.")


def best_fixed_note(suite: Suite) -> str | None:
    """What P(> best fixed) can say on a suite whose best fixed policy scores only 0 or 1 on its pairs (None otherwise)."""
    values = np.round(reference_line_cells(suite)["best_fixed"], 9)
    if not np.all((values == 0) | (values == 1)):
        return None
    zeros = int(np.sum(values == 0))
    return (f"On {suite.name} the best fixed policy scores exactly 0 on {zeros} of its {len(values)} pairs and 1 on "
            f"the others, so P(> best fixed) is {zeros / len(values):.4f} for any agent whose pair scores lie strictly "
            f"between 0 and 1: it counts pairs, not how much better. Read the mean score and its verdict.")


def _ci(e: Estimate) -> str:
    """`0.9512 [0.9401, 0.9600]`, or the value and "(no CI)"."""
    return f"{e.mean:.4f} (no CI)" if e.low is None or e.high is None else f"{e.mean:.4f} [{e.low:.4f}, {e.high:.4f}]"


def _rank(row: AlgorithmRow) -> str:
    """A number, or "—" for a privileged algorithm."""
    return "—" if row.privileged else str(row.rank)


def _name(row: AlgorithmRow) -> str:
    """The algorithm on one line, marked when privileged."""
    name = " ".join(row.algorithm.split())
    return f"{name} (privileged)" if row.privileged else name


def _yes(value: bool, e: Estimate) -> str:
    """yes / no, or "—" when there is no interval to decide on."""
    return "—" if e.low is None else ("yes" if value else "no")


def cells(row: AlgorithmRow) -> list[str]:
    """The displayed cells of a row, in HEADER order."""
    return [_rank(row), _name(row), str(row.runs), _ci(row.iqm), _ci(row.mean), f"{row.s_first:.4f}",
            f"{row.s_last:.4f}", _ci(row.adaptability), _ci(row.over_best_fixed),
            _yes(row.adapts, row.adaptability), _yes(row.beats_best_fixed, row.mean), row.note]


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
                         *(_raw(v) for e in (r.iqm, r.mean) for v in (e.mean, e.low, e.high)),
                         _raw(r.s_first), _raw(r.s_last),
                         *(_raw(v) for e in (r.adaptability, r.over_best_fixed) for v in (e.mean, e.low, e.high)),
                         _yes(r.adapts, r.adaptability), _yes(r.beats_best_fixed, r.mean), r.note])
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
