"""Submissions: results files and agents in, their status out.

A submission is accepted (202) only after every check that needs no scoring has passed; it is then
stored and queued in one transaction with its jobs (re-scoring for a results file; evaluation on
the public suite and on its hidden twin for an agent). Rejections are 4xx with the reason: 400
malformed, 401 token, 409 replayed, 413 too large, 422 content, 429 rate limit or quota.

What the public status (this JSON and the page `/submissions/<id>`) shows of a job on a hidden
suite: whatever a board of that suite shows anyway, and nothing from which its pairs could be
learned. Its error is reduced to its kind ("the agent failed (exception)", "sandbox rule broken
(network)", "the service gave up"): the full text names the pair, seed, episode and step and
carries the agent's own output, which an agent could fill with what it saw of the hidden workers.
Its unit counts are replaced by a progress in tenths (units = pairs x seeds would give the number
of curated pairs), and its scores lose `units`, `control_variates` (episode counts) and
`comparisons` (per-reference differences and probabilities of improvement), keeping the means,
CIs, curve, adaptability, skill and verdicts its board row has. The full record stays in the
database, shown to the admin by `mewa-bench serve show ID`. Public suites' jobs are shown whole.

An `Idempotency-Key` header (1-200 visible ASCII characters, the client's choice, one per
submission) makes a submission safe to send again: a resend with the same key by the same token
is answered 200 with the submission the first one made (its id and current status), whether or not
the first answer reached the client, instead of a 409 replay. An upload is written to the data dir
only if it fits above the disk's reserve (`storage`), else it is a 507.
"""

from __future__ import annotations

import json
import re
import time
from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, Depends, File, Form, Header, Request, Response, UploadFile

from mewa_bench.design.suites import DEFAULT_SUITE
from mewa_bench.service.errors import ApiError, not_found, unprocessable
from mewa_bench.service.faults import crash_point
from mewa_bench.service.jobs import STOPPED
from mewa_bench.service.limits import DAY, quota_error
from mewa_bench.service.models import AGENT, DONE, EVALUATE, FAILED, QUEUED, REJECTED, RESULTS, RUNNING, SCORE
from mewa_bench.service.privileged import known_privileged
from mewa_bench.service.routes.context import SubmissionId, session, settings_of, submitter
from mewa_bench.service.uploads import (check_agent, check_algorithm, check_archive, check_results, copy_limited, remove_upload,
                                        staging_path, store_agent, store_results)

if TYPE_CHECKING:
    from pathlib import Path

    from sqlalchemy.orm import Session

    from mewa_bench.service.models import Submission, Token

router = APIRouter(prefix="/api/submissions", tags=["submissions"])


def read_limited(upload: UploadFile, limit: int, what: str) -> bytes:
    """An uploaded part's bytes, or a 413 naming the part and its limit."""
    data = upload.file.read(limit + 1)
    if len(data) > limit:
        raise ApiError(413, "too_large", f"{what} is larger than the limit of {limit:,} bytes")
    if not data:
        raise ApiError(400, "empty_upload", f"{what} is empty")
    return data


IDEMPOTENCY_KEY = re.compile(r"^[\x21-\x7e]{1,200}$")
KEY_HELP = "Any string of 1-200 visible ASCII characters, new for each submission: a resend with the same key " \
           "answers 200 with the submission the first one made."


def checked_key(key: str | None) -> str | None:
    """An Idempotency-Key header as given, None when absent, or a 400."""
    if key is None:
        return None
    if not IDEMPOTENCY_KEY.match(key):
        raise ApiError(400, "invalid_idempotency_key", "the Idempotency-Key header must be 1-200 visible ASCII "
                                                       "characters (letters, digits, punctuation; no spaces)")
    return key


def _keyed(s: Session, token: Token, key: str | None, kind: str) -> int | None:
    """The id of the submission this token made with this key (a 422 if it was of the other kind), or None."""
    from sqlalchemy import select

    from mewa_bench.service.models import Submission

    if key is None:
        return None
    row = s.execute(select(Submission.id, Submission.kind).where(Submission.token_id == token.id,
                                                                 Submission.idempotency_key == key)).one_or_none()
    if row is not None and row.kind != kind:
        raise unprocessable("idempotency_key_reused", f"this Idempotency-Key was used for submission {row.id}, a "
                                                      f"{row.kind} submission; use a new key for each submission")
    return None if row is None else row.id


def _resent(request: Request, response: Response, submission_id: int) -> dict[str, Any]:
    """The 200 answer of a resend: the submission the key made first, with its status now."""
    from sqlalchemy import select

    from mewa_bench.service.models import Job

    response.status_code = 200
    with request.app.state.sessions() as s:
        states = list(s.scalars(select(Job.state).where(Job.submission_id == submission_id)))
    return {"id": submission_id, "status": overall_status(states), "url": f"/api/submissions/{submission_id}",
            "resent": True}


def _commit(request: Request, token: Token, kind: str, suite: str, digest: str, agent_name: str, agent_sha256: str,
            relative: Path, jobs: list[tuple[str, str, bool, tuple[int, ...]]], agent_args: dict[str, str] | None = None,
            algorithm: str | None = None, key: str | None = None) -> tuple[int, bool]:
    """Store the submission and its jobs in one transaction, after the idempotency, replay and quota checks; returns
    its id and whether it is new (False: the key's earlier submission, nothing stored)."""
    from sqlalchemy import func, select
    from sqlalchemy.exc import IntegrityError

    from mewa_bench.service.db import transaction
    from mewa_bench.service.jobs import add_job
    from mewa_bench.service.models import Submission, Token

    settings = settings_of(request)
    limits = settings.limits
    now = time.time()
    try:
        with transaction(request.app.state.sessions) as s:
            s.execute(select(Token.id).where(Token.id == token.id).with_for_update())  # one quota count at a time
            if (earlier := _keyed(s, token, key, kind)) is not None:
                return earlier, False
            _refuse_replay(s, digest, kind)
            limit = token.daily_results if kind == RESULTS else token.daily_agents
            limit = (limits.daily_results if kind == RESULTS else limits.daily_agents) if limit is None else limit
            count, oldest = s.execute(select(func.count(), func.min(Submission.created)).where(
                Submission.token_id == token.id, Submission.kind == kind, Submission.created > now - DAY)).one()
            if count >= limit:
                raise quota_error("results" if kind == RESULTS else "agent", limit, oldest or now, now)
            submission = Submission(token_id=token.id, kind=kind, suite=suite, digest=digest, agent_name=agent_name,
                                    agent_sha256=agent_sha256, file=relative.as_posix(), created=now,
                                    algorithm=algorithm, idempotency_key=key,
                                    agent_args=None if agent_args is None else json.dumps(agent_args, sort_keys=True))
            s.add(submission)
            s.flush()
            for job_kind, board, hidden, seeds in jobs:
                add_job(s, submission.id, job_kind, board, hidden, seeds, settings.max_attempts)
            return submission.id, True
    except IntegrityError:  # the same upload (or key) committed concurrently by another request
        with request.app.state.sessions() as s:
            if (earlier := _keyed(s, token, key, kind)) is not None:
                return earlier, False
            _refuse_replay(s, digest, kind)
        raise


def _refuse_replay(s: Session, digest: str, kind: str) -> None:
    """A 409 if an upload with this digest was accepted before."""
    from sqlalchemy import select

    from mewa_bench.service.models import Submission

    earlier = s.scalar(select(Submission.id).where(Submission.digest == digest))
    if earlier is not None:
        what = "run (the same suite, seeds and episodes, whatever agent name it is under)" if kind == RESULTS else \
            "agent (the same agent file, checkpoint, agent args and suite)"
        raise ApiError(409, "replayed", f"this {what} was already submitted as submission {earlier} "
                                        f"(/api/submissions/{earlier}); a replayed upload is not scored again")


def _accepted(submission_id: int) -> dict[str, Any]:
    """The 202 answer of an accepted submission."""
    return {"id": submission_id, "status": QUEUED, "url": f"/api/submissions/{submission_id}"}


@router.post("/results", status_code=202, summary="Submit a results file")
def submit_results(request: Request, response: Response, file: UploadFile = File(..., description="A results file of `mewa-bench evaluate`."),
                   algorithm: str | None = Form(None, description="The algorithm this run is one training run of "
                                                                  "(runs under one name share a row of the algorithms "
                                                                  "table; default: a one-run algorithm named after the "
                                                                  "agent)."),
                   idempotency_key: str | None = Header(None, description=KEY_HELP),
                   token=Depends(submitter)) -> dict[str, Any]:
    """Checked now (schema, suite and its hash, seeds, units); re-scored from its episodes by a worker."""
    settings = settings_of(request)
    key = checked_key(idempotency_key)
    with request.app.state.sessions() as s:  # closed before anything else opens one (SQLite: one writer at a time)
        earlier = _keyed(s, token, key, RESULTS)
        privileged = known_privileged(s)
    if earlier is not None:
        return _resent(request, response, earlier)
    request.app.state.rate.check(token.id, _rate(token, settings))
    algorithm = check_algorithm(algorithm)
    data = read_limited(file, settings.limits.results_bytes, "the results file")
    checked = check_results(data, settings, request.app.state.suites, privileged)
    request.app.state.storage.ensure_room(len(data))
    relative = store_results(settings, data)
    request.app.state.storage.stored()
    crash_point("results-stored")
    try:
        submission_id, new = _commit(request, token, RESULTS, checked.suite, checked.digest, checked.agent_name,
                                     checked.agent_sha256, relative, [(SCORE, checked.suite, False, checked.seeds)],
                                     algorithm=algorithm, key=key)
    except BaseException:
        remove_upload(settings, relative)
        raise
    if not new:
        remove_upload(settings, relative)
        return _resent(request, response, submission_id)
    request.app.state.metrics.uploaded(RESULTS, len(data))
    crash_point("results-committed")
    return _accepted(submission_id)


@router.post("/agent", status_code=202, summary="Submit an agent for evaluation")
def submit_agent(request: Request, response: Response,
                 agent: UploadFile = File(..., description="The agent: a .py file with make_agent(...) or class Agent."),
                 checkpoint: UploadFile | None = File(None, description="Optional .tar(.gz), unpacked beside the agent file."),
                 suite: str = Form(DEFAULT_SUITE, description="The public suite to evaluate on (and its hidden twin)."),
                 name: str | None = Form(None, description="The agent's name on the boards (default: the file name)."),
                 agent_arg: list[str] = Form([], description="key=value passed to make_agent (repeatable)."),
                 algorithm: str | None = Form(None, description="The algorithm this run is one training run of "
                                                                "(runs under one name share a row of the algorithms "
                                                                "table; default: a one-run algorithm named after the "
                                                                "agent)."),
                 idempotency_key: str | None = Header(None, description=KEY_HELP),
                 token=Depends(submitter)) -> dict[str, Any]:
    """Queued for the workers: evaluated in the sandbox on `suite` and on its hidden twin."""
    from mewa_bench.service.boards import hidden_boards, hidden_twin

    settings = settings_of(request)
    limits = settings.limits
    storage = request.app.state.storage
    key = checked_key(idempotency_key)
    with request.app.state.sessions() as s:
        earlier = _keyed(s, token, key, AGENT)
    if earlier is not None:
        return _resent(request, response, earlier)
    request.app.state.rate.check(token.id, _rate(token, settings))
    algorithm = check_algorithm(algorithm)
    source = read_limited(agent, limits.agent_bytes, "the agent file")
    archive: Path | None = None
    size = len(source)
    try:
        checkpoint_sha256 = None
        if checkpoint is not None and checkpoint.filename:
            storage.ensure_room(size + (checkpoint.size or 0))  # the archive is copied into the data dir first
            archive = staging_path(settings, ".checkpoint")
            checkpoint_sha256 = copy_limited(checkpoint.file, archive, limits.checkpoint_bytes, "the checkpoint archive")
            size += archive.stat().st_size
            unpacked = check_archive(archive, limits.checkpoint_unpacked_bytes)
            storage.ensure_room(len(source) + unpacked)
        checked = check_agent(source, agent.filename or "agent.py", name, suite, agent_arg, checkpoint_sha256)
        jobs = [(EVALUATE, suite, False, settings.seeds_for(suite))]
        jobs += [(EVALUATE, board, True, settings.seeds_for(board)) for board in hidden_boards(settings)
                 if hidden_twin(board) == suite]
        if archive is None:
            storage.ensure_room(size)
        relative = store_agent(settings, checked, archive)
        storage.stored()
    finally:
        if archive is not None:
            archive.unlink(missing_ok=True)
    crash_point("agent-stored")
    try:
        submission_id, new = _commit(request, token, AGENT, suite, checked.digest, checked.name, checked.agent_sha256,
                                     relative, jobs, checked.agent_args, algorithm=algorithm, key=key)
    except BaseException:
        remove_upload(settings, relative)
        raise
    if not new:
        remove_upload(settings, relative)
        return _resent(request, response, submission_id)
    request.app.state.metrics.uploaded(AGENT, size)
    crash_point("agent-committed")
    return _accepted(submission_id)


def _rate(token: Token, settings) -> int:
    """The token's rate limit, or the server's."""
    return settings.limits.rate_per_minute if token.rate_per_minute is None else token.rate_per_minute


def overall_status(states: list[str]) -> str:
    """A submission's status from its jobs': rejected or failed if any is, done if all are, else running/queued."""
    for state in (REJECTED, FAILED):
        if state in states:
            return state
    if states and all(s == DONE for s in states):
        return DONE
    return RUNNING if RUNNING in states or DONE in states else QUEUED


def describe(s: Session, submission: Submission, full: bool = False) -> dict[str, Any]:
    """A submission's status, its jobs and its scores; hidden-suite jobs as the public may see them unless `full`
    (the admin's view)."""
    from sqlalchemy import select

    from mewa_bench.service.models import BoardEntry, Job

    jobs = s.scalars(select(Job).where(Job.submission_id == submission.id).order_by(Job.id)).all()
    entries = {e.job_id: e for e in s.scalars(select(BoardEntry).where(BoardEntry.submission_id == submission.id))}
    status = overall_status([j.state for j in jobs])
    shown = [_job_view(j) if full or not j.hidden else public_job(_job_view(j)) for j in jobs]
    # the reason: a job that failed on its own (not one stopped with it), the public one first (a hidden one's is coarse)
    failed = sorted((j for j in shown if j["state"] in (REJECTED, FAILED)),
                    key=lambda j: ((j["error"] or "").startswith(STOPPED), j["hidden"]))
    scores: dict[str, Any] = {}
    for j in (j for j in jobs if j.id in entries):
        stored = json.loads(entries[j.id].scores)
        scores[j.board] = stored if full or not j.hidden else public_scores(stored)
    return {
        "id": submission.id, "kind": submission.kind, "suite": submission.suite, "agent": submission.agent_name,
        "agent_sha256": submission.agent_sha256, "algorithm": submission.algorithm, "created": submission.created,
        "status": status,
        "reason": f"{failed[0]['board']}: {failed[0]['error']}" if failed else None, "jobs": shown, "scores": scores,
    }


def _job_view(job: Any) -> dict[str, Any]:
    """Everything the database has on a job that a status shows."""
    return {"board": job.board, "hidden": job.hidden, "kind": job.kind, "state": job.state, "attempts": job.attempts,
            "units_done": job.units_done, "units_total": job.units_total, "resumed_units": job.resumed_units,
            "progress": None if not job.units_total else job.units_done / job.units_total,
            "error": job.error, "note": job.note, "started": job.started, "finished": job.finished}


# The kind of error at the head of a job's error (worker.run_job, evaluation.run_agent_job): what the public may see
_ERROR_KIND = re.compile(r"^(sandbox rule broken \([a-z_]+\)|the agent failed \([a-z_]+\)|the service gave up)")
WITHHELD = "details of runs on a hidden suite are kept for the server's admin"
HIDDEN_SCORE_FIELDS = ("units", "control_variates", "comparisons")


def public_reason(error: str | None) -> str | None:
    """A hidden job's error as the public sees it: its kind only."""
    if error is None:
        return None
    if error.startswith(STOPPED):  # names the other board only
        return error
    kind = _ERROR_KIND.match(error)
    return f"{kind.group(1) if kind else 'an error'} on the hidden suite ({WITHHELD})"


def public_job(job: dict[str, Any]) -> dict[str, Any]:
    """A hidden job as the public sees it: no unit counts (progress in tenths), the kind of its error only."""
    progress = job["progress"]
    return {**job, "units_done": None, "units_total": None, "resumed_units": None, "error": public_reason(job["error"]),
            "progress": None if progress is None else int(progress * 10) / 10}


def public_scores(scores: dict[str, Any]) -> dict[str, Any]:
    """A hidden board's scores as the public sees them: without unit and episode counts and the comparisons."""
    return {k: v for k, v in scores.items() if k not in HIDDEN_SCORE_FIELDS}


@router.get("/{submission_id}", summary="A submission's status")
def submission_status(submission_id: SubmissionId, db=Depends(session)) -> dict[str, Any]:
    """queued, running, done, rejected (with the reason) or failed; each job's progress; the scores once done."""
    from mewa_bench.service.models import Submission

    submission = db.get(Submission, submission_id)
    if submission is None:
        raise not_found(f"submission {submission_id}")
    return describe(db, submission)


def recent_submissions(db: Session, limit: int) -> list[dict[str, Any]]:
    """The latest submissions, newest first, with their status."""
    from sqlalchemy import select

    from mewa_bench.service.models import Job, Submission

    subs = db.scalars(select(Submission).order_by(Submission.id.desc()).limit(limit)).all()
    states: dict[int, list[str]] = {}
    if subs:
        for sid, state in db.execute(select(Job.submission_id, Job.state).where(Job.submission_id.in_([x.id for x in subs]))):
            states.setdefault(sid, []).append(state)
    return [{"id": x.id, "kind": x.kind, "suite": x.suite, "agent": x.agent_name, "created": x.created,
             "status": overall_status(states.get(x.id, [])), "url": f"/api/submissions/{x.id}"} for x in subs]


@router.get("/{submission_id}/output", summary="The agent's output (its submitter only)")
def submission_output(submission_id: SubmissionId, request: Request, token=Depends(submitter),
                      db=Depends(session)) -> dict[str, Any]:
    """What the agent printed (stdout and stderr, capped per attempt) on the public suite, for the token that
    submitted it; a hidden suite's output is kept for the server's admin."""
    from sqlalchemy import select

    from mewa_bench.service.models import Job, Submission

    submission = db.get(Submission, submission_id)
    if submission is None or submission.token_id != token.id:  # another's submission does not exist for you
        raise not_found(f"submission {submission_id} of this token")
    jobs = []
    for job in db.scalars(select(Job).where(Job.submission_id == submission_id).order_by(Job.id)):
        attempts = [] if job.hidden else job_output(settings_of(request), job.id)
        jobs.append({"board": job.board, "hidden": job.hidden, "attempts": attempts,
                     "withheld": WITHHELD if job.hidden else None})
    return {"id": submission_id, "jobs": jobs}


def job_output(settings, job_id: int) -> list[dict[str, Any]]:
    """A job's output logs, one per attempt, oldest first."""
    folder = settings.jobs_dir / str(job_id)
    logs = sorted(folder.glob("output-*.log"), key=lambda p: int(p.stem.split("-")[1])) if folder.is_dir() else []
    return [{"attempt": int(log.stem.split("-")[1]), "output": log.read_bytes().decode("utf-8", "replace")}
            for log in logs]


@router.get("", summary="The latest submissions")
def list_submissions(limit: int = 50, db=Depends(session)) -> list[dict[str, Any]]:
    """Newest first (at most 500)."""
    if not 1 <= limit <= 500:
        raise ApiError(400, "invalid_limit", f"limit must be between 1 and 500, got {limit}")
    return recent_submissions(db, limit)
