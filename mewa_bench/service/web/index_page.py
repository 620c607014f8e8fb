"""The front page: the public boards, the hidden boards, the job queue and the latest submissions."""

from __future__ import annotations

from typing import Any

from mewa_bench.service.web.layout import esc, number, page, utc


def _boards(boards: list[dict[str, Any]], hidden: bool) -> str:
    if not any(b["hidden"] == hidden for b in boards):
        return '<p class="muted">None on this server (it runs without hidden evaluation).</p>'
    rows = "".join(f'<tr data-board="{esc(b["board"])}" data-entries="{b["entries"]}"><td><a href="/leaderboards/'
                   f'{esc(b["board"])}">{esc(b["board"])}</a></td><td class="n">{b["entries"]}</td>'
                   f'<td class="n">{number(b["best_mean"])}</td></tr>' for b in boards if b["hidden"] == hidden)
    table_id = "hidden-boards" if hidden else "public-boards"
    return (f'<table id="{table_id}"><thead><tr><th>board</th><th>entries</th><th>best mean score</th></tr></thead>'
            f"<tbody>{rows}</tbody></table>")


def _submissions(submissions: list[dict[str, Any]]) -> str:
    if not submissions:
        return '<p class="muted">No submissions yet.</p>'
    rows = "".join(f'<tr data-submission="{s["id"]}" data-status="{esc(s["status"])}"><td class="n">'
                   f'<a href="/submissions/{s["id"]}">{s["id"]}</a></td><td>{esc(s["agent"])}</td>'
                   f'<td>{esc(s["kind"])}</td><td>{esc(s["suite"])}</td>'
                   f'<td><span class="status {esc(s["status"])}">{esc(s["status"])}</span></td>'
                   f"<td>{utc(s['created'])}</td></tr>" for s in submissions)
    return (f'<table id="submissions"><thead><tr><th>id</th><th>agent</th><th>kind</th><th>suite</th><th>status</th>'
            f"<th>submitted</th></tr></thead><tbody>{rows}</tbody></table>")


def index_html(boards: list[dict[str, Any]], submissions: list[dict[str, Any]], queue: dict[str, int]) -> str:
    """Every board, the queue's counts by state, and the latest submissions."""
    counts = ", ".join(f"{n} {esc(state)}" for state, n in sorted(queue.items())) or "empty"
    body = (f"<h2>Public suites</h2>{_boards(boards, False)}"
            '<h2>Hidden test suites</h2><p class="muted">Agents submitted for a public suite are also evaluated '
            f"on its hidden twin; only the scores are shown.</p>{_boards(boards, True)}"
            f'<h2>Latest submissions</h2><p class="muted">Job queue: {counts}.</p>{_submissions(submissions)}'
            '<p class="muted">Submit with <code>mewa-bench submit FILE --server URL --token TOKEN</code>; '
            'the API is described at <a href="/docs">/docs</a>.</p>')
    return page("MEWA benchmark service", body)
