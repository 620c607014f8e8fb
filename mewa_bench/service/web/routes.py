"""The pages' routes: `/`, `/leaderboards/<board>` (and its figure), `/submissions/<id>`.

Answers are HTML (a 404 is an HTML page too, for a person with a browser); the data are the JSON
API's own (`service.boards`, `routes.submissions`).
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request
from fastapi.responses import HTMLResponse, Response

from mewa_bench.service import boards
from mewa_bench.service.routes.context import SubmissionId, session, settings_of
from mewa_bench.service.web import board_page, curves, index_page, layout, status_page

router = APIRouter(tags=["pages"])
LATEST = 20  # submissions on the front page


@router.get("/", response_class=HTMLResponse, summary="The front page")
def front_page(request: Request, db=Depends(session)) -> HTMLResponse:
    """Every board, the job queue and the latest submissions."""
    from mewa_bench.service.jobs import queue_counts
    from mewa_bench.service.routes.submissions import recent_submissions

    content = index_page.index_html(boards.boards_index(db, settings_of(request)), recent_submissions(db, LATEST),
                                    queue_counts(db))
    return HTMLResponse(content)


@router.get("/leaderboards/{name}", response_class=HTMLResponse, summary="A board's page")
def leaderboard_page(name: str, request: Request, db=Depends(session)) -> HTMLResponse:
    """The ranked table with its adaptation-curve figure."""
    settings = settings_of(request)
    content = boards.board(db, settings, name)
    if content is None:
        return HTMLResponse(layout.not_found_page(f"Leaderboard {name!r}"), status_code=404)
    suite = curves.board_suite(settings, name, content["hidden"])
    version, drawn = None, (0, 0)
    if suite is not None:
        key = curves.board_version(db, settings, name, suite)
        version = f"{key.entries}-{key.newest or 0}"
        drawn = curves.drawn_from(boards.board_algorithms(db, settings, name, suite))  # cached: the figure's too
    return HTMLResponse(board_page.board_html(content, version, curves.PLOTTED, drawn))


@router.get("/leaderboards/{name}/curves.png", response_class=Response, summary="A board's adaptation curves (PNG)",
            responses={200: {"content": {"image/png": {}}}})
def leaderboard_figure(name: str, request: Request, db=Depends(session)) -> Response:
    """The figure of `mewa-bench leaderboard`: s_k per algorithm (the 10 best) with its band over training runs,
    and the suite's reference lines."""
    settings = settings_of(request)
    hidden = dict(boards.board_names(settings)).get(name)
    if hidden is None:
        return HTMLResponse(layout.not_found_page(f"Leaderboard {name!r}"), status_code=404)
    suite = curves.board_suite(settings, name, hidden)
    if suite is None:
        return HTMLResponse(layout.not_found_page(f"A figure of {name!r} (its hidden suite is not generated yet)"),
                            status_code=404)
    key = curves.board_version(db, settings, name, suite)
    etag = f'"{key.entries}-{key.newest or 0}-{key.suite_sha256[:16]}"'
    headers = {"Cache-Control": "no-cache", "ETag": etag}  # the browser asks again, and gets a 304 if nothing changed
    if request.headers.get("if-none-match") == etag:
        return Response(status_code=304, headers=headers)
    return Response(curves.board_figure(db, settings, key, suite), media_type="image/png", headers=headers)


@router.get("/submissions/{submission_id}", response_class=HTMLResponse, summary="A submission's page")
def submission_page(submission_id: SubmissionId, db=Depends(session)) -> HTMLResponse:
    """Status, jobs and their progress, the reason of a rejection, the scores; reloads itself until final."""
    from mewa_bench.service.models import Submission
    from mewa_bench.service.routes.submissions import describe

    submission = db.get(Submission, submission_id)
    if submission is None:
        return HTMLResponse(layout.not_found_page(f"Submission {submission_id}"), status_code=404)
    return HTMLResponse(status_page.status_html(describe(db, submission)))
