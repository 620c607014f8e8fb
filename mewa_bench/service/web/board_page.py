"""A board's page: what the suite is, the algorithms table, the adaptation-curve figure (one line per
algorithm) and the ranked table of checkpoints.

The table has the static leaderboard's columns and cells (`leaderboard.render.cells`); each agent
links to its submission's status page. Every row carries its kind, rank and exact mean score as
data attributes (what the JSON API at /api/leaderboards/<board> serves).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from mewa_bench.leaderboard import algorithm_tables
from mewa_bench.leaderboard.algorithms import AlgorithmRow
from mewa_bench.leaderboard.board import Row
from mewa_bench.leaderboard.render import CHECKPOINTS, EXPLANATION, HEADER, NOTES, cells
from mewa_bench.protocol.scoring import Estimate
from mewa_bench.service.web.layout import esc, page

_ROW_FIELDS = tuple(f.name for f in dataclasses.fields(Row))
_NUMERIC = frozenset({"rank", "gap won [95% CI]", "mean score [95% CI]", "IQM", "s_1", "s_10",
                      "adaptability [95% CI]", "skill", "seeds"})
AGENT_COLUMN = HEADER.index("agent")
SHA_COLUMN = HEADER.index("agent sha256")
SHA_SHOWN = 12  # hex digits of the agent's sha256 in the table (all of it on hover and in the JSON)
SOURCES = {"server-evaluated": "server-evaluated: the server ran the agent file in its sandbox",
           "self-reported": "self-reported: a results file the submitter ran, re-scored from its episodes",
           "reference": "reference: the suite's exact reference line"}


def entries_text(n: int) -> str:
    """`1 entry`, `4 entries`."""
    return f"{n} entry" if n == 1 else f"{n} entries"


def row_of(content: dict[str, Any]) -> Row:
    """The leaderboard row inside a row of the JSON API."""
    return Row(**{k: content[k] for k in _ROW_FIELDS})


def table_row(content: dict[str, Any]) -> str:
    """One <tr>: the static leaderboard's cells, the agent linked to its submission."""
    row = row_of(content)
    tds = []
    source = str(content.get("source", "reference"))
    for column, (header, text) in enumerate(zip(HEADER, cells(row), strict=True)):
        inner = esc(text)
        if column == AGENT_COLUMN and content.get("submission_id") is not None:
            inner = f'<a href="/submissions/{int(content["submission_id"])}">{inner}</a>'
        if column == SHA_COLUMN and len(text) > SHA_SHOWN:
            inner = f'<code title="{esc(text)}">{esc(text[:SHA_SHOWN])}…</code>'
        tds.append(f'<td class="n">{inner}</td>' if header in _NUMERIC else f"<td>{inner}</td>")
        if column == AGENT_COLUMN:
            tds.append(f'<td class="source" title="{esc(SOURCES.get(source, source))}">{esc(source)}</td>')
    submission = "" if content.get("submission_id") is None else f' data-submission="{int(content["submission_id"])}"'
    rank = "" if row.rank is None else row.rank
    return (f'<tr class="{esc(row.kind)}" data-kind="{esc(row.kind)}" data-source="{esc(source)}" data-rank="{rank}" '
            f'data-mean="{row.mean!r}"{submission}>' + "".join(tds) + "</tr>")


def algorithm_row(content: dict[str, Any]) -> AlgorithmRow:
    """The algorithms-table row inside the JSON API's `algorithms`."""
    fields = {f.name: content[f.name] for f in dataclasses.fields(AlgorithmRow)}
    for name in ("gap_won", "iqm", "mean", "adaptability"):
        fields[name] = Estimate(**fields[name])
    fields["run_names"] = tuple(fields["run_names"])
    return AlgorithmRow(**fields)


def algorithms_html(board: dict[str, Any]) -> str:
    """The algorithms table (the static boards' cells), each row with its source; empty when there is no run (and
    on a hidden board)."""
    if not board.get("algorithms"):
        return ""
    source_at = algorithm_tables.HEADER.index("algorithm")
    head = "".join(f"<th>{esc(h)}</th>" + ("<th>source</th>" if i == source_at else "")
                   for i, h in enumerate(algorithm_tables.HEADER))
    rows = []
    for content in board["algorithms"]:
        row = algorithm_row(content)
        tds = []
        for i, text in enumerate(algorithm_tables.cells(row)):
            tds.append(f'<td class="n">{esc(text)}</td>' if i in algorithm_tables.NUMERIC else f"<td>{esc(text)}</td>")
            if i == source_at:
                tds.append(f'<td class="source">{esc(content["source"])}</td>')
        kind = "privileged" if row.privileged else "agent"
        rows.append(f'<tr class="{kind}" data-algorithm="{esc(row.algorithm)}" data-runs="{row.runs}">'
                    + "".join(tds) + "</tr>")
    return (f'<h2>Algorithms</h2><table id="algorithms"><thead><tr>{head}</tr></thead><tbody>\n'
            + "\n".join(rows) + f'\n</tbody></table><p class="muted">{esc(algorithm_tables.EXPLANATION)}</p>')


def captions_html(board: dict[str, Any]) -> str:
    """What decides the board's verdicts, and what gap won means on its suite when its gap is small."""
    verdicts, note = board.get("verdicts"), board.get("gap_note")
    return ((f'<p class="muted" id="verdicts">{esc(verdicts["caption"])}</p>' if verdicts else "")
            + (f'<p class="muted" id="gap-note">{esc(note)}</p>' if note else ""))


def _facts(board: dict[str, Any]) -> str:
    """What the board ranks: the suite and its hash (public), or only that it is hidden."""
    name = esc(board["board"])
    if board["hidden"]:
        twin = esc(board["public_twin"])
        what = (f'a <strong>hidden test suite</strong>: agents submitted for <a href="/leaderboards/{twin}">{twin}</a> '
                f"are also evaluated here, on tasks and workers the server never serves")
    elif board["suite"] is not None:
        sha256 = esc(board["suite"]["sha256"])
        what = f'public suite <a href="/api/suites/{name}">{name}</a>, sha256 <code>{sha256}</code>'
    else:
        what = "a public suite"
    return (f'<p class="facts">{what}; {entries_text(board["entries"])}, ranked with {board["seeds"]} seeds per pair. '
            f'As JSON: <a href="/api/leaderboards/{name}">/api/leaderboards/{name}</a>.</p>')


def counted(n: int, noun: str) -> str:
    """`1 algorithm`, `4 runs`."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _figure(board: dict[str, Any], figure_version: str | None, plotted: int, drawn: tuple[int, int]) -> str:
    """The figure, or why there is none; `drawn`: the (algorithms, runs) it is drawn from."""
    name = esc(board["board"])
    if figure_version is None:
        return ('<p class="muted">No figure yet: the server has not generated this hidden suite (no agent was '
                "evaluated on it).</p>")
    algorithms, runs = drawn
    shown = (f"the {plotted} best of {counted(algorithms, 'algorithm')}" if algorithms > plotted
             else counted(algorithms, "algorithm"))
    caption = ("Adaptation curves: no run to draw yet, only the suite's exact reference lines (dashed)." if not runs
               else f"Adaptation curves, one panel per algorithm ({shown}, from {counted(runs, 'run')}: a "
                    f"submitter's runs under one algorithm name): mean score s_k of episode k with the same hidden "
                    f"worker, band: 95% CI over training runs (none for a one-run algorithm), gap won in each "
                    f"panel's title; in every panel the suite's exact reference lines, the best fixed policy in "
                    f"bold black.")
    return (f'<figure><img id="curves" src="/leaderboards/{name}/curves.png?v={esc(figure_version)}" '
            f'alt="Adaptation curves on {name}: score s_k per episode k for each algorithm, with the reference lines" '
            f'width="900"><figcaption>{esc(caption)}</figcaption></figure>')


def board_html(board: dict[str, Any], figure_version: str | None, plotted: int,
               drawn: tuple[int, int] = (0, 0)) -> str:
    """The whole page of a board (the JSON of /api/leaderboards/<board>): the algorithms table (public boards),
    the figure (one panel per algorithm, `drawn`: from how many algorithms and runs), then the checkpoints' table."""
    head = "".join(f"<th>{esc(h)}</th>" + ("<th>source</th>" if h == "agent" else "") for h in HEADER)
    rows = "\n".join(table_row(r) for r in board["rows"])
    notes = "".join(f"<li>{esc(n)}</li>" for n in NOTES)
    terms = "".join(f"<dt>{esc(t)}</dt><dd>{esc(text)}</dd>" for t, text in EXPLANATION)
    kind = "hidden" if board["hidden"] else "public"
    algorithms = algorithms_html(board)
    checkpoints = f'<h2>Checkpoints</h2><p class="muted">{esc(CHECKPOINTS)}</p>' if algorithms else ""
    body = (f'<div id="board" data-board="{esc(board["board"])}" data-kind="{kind}">{_facts(board)}'
            f"{captions_html(board)}{algorithms}{_figure(board, figure_version, plotted, drawn)}\n{checkpoints}"
            f'<table id="ranking"><thead><tr>{head}</tr></thead><tbody>\n{rows}\n</tbody></table>\n'
            f'<p class="muted">Sources: {"; ".join(esc(t) for t in SOURCES.values())}. Self-reported rows are '
            f"{'ranked' if board.get('uploads_ranked') else 'unranked'} on this server.</p>"
            f"<ul class=\"muted\">{notes}</ul><dl class=\"muted\">{terms}</dl></div>")
    title = f"Leaderboard: {board['board']}" + (" (hidden test suite)" if board["hidden"] else "")
    return page(title, body)
