"""A submission's page: its status, each job's progress and attempts, the reason of a rejection or
failure, and its scores once done. Until the submission is final the page reloads itself."""

from __future__ import annotations

from typing import Any

from mewa_bench.service.web.layout import esc, number, page, utc, with_ci

FINAL = ("done", "rejected", "failed")
REFRESH_SECONDS = 2


def _progress(job: dict[str, Any]) -> str:
    """A progress bar of the units done (evaluations; in percent on a hidden suite, whose size is not shown), or the
    state alone (re-scoring has no units)."""
    done, total = job["units_done"], job["units_total"]
    if total is None and job["progress"] is not None:
        percent = round(100 * job["progress"])
        return f'<progress value="{percent}" max="100">{percent}%</progress> <span class="units">{percent}%</span>'
    if not total:
        return {"done": "scored", "queued": "waiting for a worker", "running": "scoring"}.get(job["state"], "")
    resumed = "" if not job["resumed_units"] else f", resumed after {job['resumed_units']}"
    return (f'<progress value="{done}" max="{total}">{done}/{total}</progress> '
            f'<span class="units">{done}/{total} units{resumed}</span>')


def _job_row(job: dict[str, Any]) -> str:
    board = esc(job["board"])
    hidden = " (hidden)" if job["hidden"] else ""
    error = "" if not job["error"] else esc(job["error"])
    if job["note"]:
        error += f'<div class="note">{esc(job["note"])}</div>'
    return (f'<tr data-board="{board}" data-state="{esc(job["state"])}"><td><a href="/leaderboards/{board}">{board}</a>'
            f"{hidden}</td><td>{esc(job['kind'])}</td><td>{esc(job['state'])}</td><td>{_progress(job)}</td>"
            f"<td class=\"n\">{job['attempts']}</td><td>{utc(job['started'])}</td><td>{utc(job['finished'])}</td>"
            f"<td>{error}</td></tr>")


def _scores_row(board: str, scores: dict[str, Any]) -> str:
    """A board's scores (a hidden board's publicly without its units: `routes.submissions.public_scores`)."""
    curve = scores["curve"]
    return (f'<tr data-board="{esc(board)}" data-mean="{scores["mean"]["mean"]!r}"><td>{esc(board)}</td>'
            f'<td class="n">{with_ci(scores["mean"])}</td><td class="n">{number(curve[0]["mean"])}</td>'
            f'<td class="n">{number(curve[-1]["mean"])}</td><td class="n">{with_ci(scores["adaptability"])}</td>'
            f'<td class="n">{number(scores["skill"]["mean"])}</td><td class="n">{scores.get("units", "")}</td></tr>')


def status_html(status: dict[str, Any]) -> str:
    """The page of a submission (the JSON of /api/submissions/<id>)."""
    state = status["status"]
    final = state in FINAL
    facts = (f'<p><span id="status" class="status {esc(state)}" data-status="{esc(state)}">{esc(state)}</span> '
             f"{esc(status['kind'])} submission of <strong>{esc(status['agent'])}</strong> for "
             f'<a href="/leaderboards/{esc(status["suite"])}">{esc(status["suite"])}</a>, '
             f"submitted {utc(status['created'])}; agent sha256 <code>{esc(status['agent_sha256'])}</code>.</p>")
    reason = "" if not status["reason"] else f'<h2>Reason</h2><p id="reason" class="reason">{esc(status["reason"])}</p>'
    jobs = "".join(_job_row(j) for j in status["jobs"])
    body = [facts, reason, '<h2>Jobs</h2><table id="jobs"><thead><tr><th>board</th><th>job</th><th>state</th>'
            "<th>progress</th><th>attempts</th><th>started</th><th>finished</th><th>error, notes</th></tr></thead>"
            f"<tbody>{jobs}</tbody></table>"]
    if status["scores"]:
        rows = "".join(_scores_row(board, s) for board, s in status["scores"].items())
        body.append('<h2>Scores</h2><table id="scores"><thead><tr><th>board</th><th>mean score [95% CI]</th>'
                    "<th>s_1</th><th>s_10</th><th>adaptability [95% CI]</th><th>skill</th><th>units</th></tr></thead>"
                    f"<tbody>{rows}</tbody></table>")
    refresh = "" if final else (f'<p class="muted">This page reloads every {REFRESH_SECONDS} s until the submission '
                                "is done.</p>")
    body.append(f'{refresh}<p class="muted">As JSON: <a href="/api/submissions/{status["id"]}">'
                f"/api/submissions/{status['id']}</a></p>")
    return page(f"Submission {status['id']}", "\n".join(body), None if final else REFRESH_SECONDS)
