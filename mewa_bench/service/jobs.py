"""The job queue, persisted in the database: states, leases, attempts.

A worker claims a job with one conditional UPDATE whose candidate row comes from a sub-select:
`... FOR UPDATE SKIP LOCKED` on PostgreSQL (concurrent workers skip each other's rows), a plain
sub-select on SQLite (whose write lock makes the statement atomic). A claim sets a lease that the
worker renews; a job whose lease expired (its worker crashed, was killed, or hung) is re-queued by
the reaper (`requeue_expired`, run before every claim), which says so in the job's `note` ("the
worker's lease expired at ...; re-queued for attempt N of M"), up to `max_attempts` claims, after
which it fails with the reason (`give_up_expired`). Every state change after the claim is
conditional on the lease owner, so a worker that lost its lease can change nothing. The jobs of one
submission end together: when one is rejected or fails, the others stop (`end_siblings`; a running
one's worker finds its lease gone and kills its sandbox) and no board keeps an entry of it.

Infrastructure faults (the database unreachable, the disk full) are not the agent's: a worker hands
its job back (`hand_back`) without counting the attempt, counting an infrastructure retry instead,
up to `max_infra_retries`, after which the job fails saying so. A lease that lapsed while no process
could reach the database is not reaped at once when it comes back: every reaping process records its
contact in `service_clock`, and after a gap longer than a few reaper rounds only leases that expired
before the gap are reaped until a lease's length has passed, so a surviving worker renews first.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from mewa_bench.service.models import DONE, FAILED, QUEUED, REJECTED, RUNNING, BoardEntry, Job, ServiceClock, Submission

STOPPED = "stopped: "  # the head of the error of a job ended because another job of its submission did

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker


@dataclass(frozen=True)
class Claimed:
    """A job as its worker sees it after claiming it."""

    id: int
    submission_id: int
    kind: str
    board: str
    hidden: bool
    seeds: tuple[int, ...]
    attempts: int
    max_attempts: int


def add_job(session: Session, submission_id: int, kind: str, board: str, hidden: bool, seeds: tuple[int, ...],
            max_attempts: int) -> Job:
    """Queue a job (in the caller's transaction, with its submission)."""
    job = Job(submission_id=submission_id, kind=kind, board=board, hidden=hidden, seeds=json.dumps(list(seeds)),
              state=QUEUED, attempts=0, max_attempts=max_attempts, units_done=0, units_total=0, created=time.time())
    session.add(job)
    return job


def utc_text(seconds: float) -> str:
    """Unix seconds as 'YYYY-MM-DD HH:MM:SS UTC'."""
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(seconds))


def reap_period(lease_seconds: float) -> float:
    """How often the server's reaper looks: a fraction of the lease, between 0.2 and 5 seconds."""
    return min(5.0, max(0.2, lease_seconds / 4))


def reap_cutoff(session: Session, now: float, lease_seconds: float) -> float:
    """Record this contact with the database; returns the time before which an expired lease may be reaped (`now`,
    or the start of a gap in the contacts for a lease's length after it ended)."""
    clock = session.get(ServiceClock, 1, with_for_update=True)  # its one row, made by the migration
    if now - clock.last_contact > 2 * reap_period(lease_seconds):
        clock.gap_start, clock.resumed = clock.last_contact, now
    clock.last_contact = max(clock.last_contact, now)
    return now if now >= clock.resumed + lease_seconds else min(now, clock.gap_start)


def requeue_expired(sessions: sessionmaker[Session], now: float | None = None, lease_seconds: float = 60.0) -> int:
    """Put the running jobs whose lease expired (attempts left) back in the queue, each with a note saying so;
    returns how many. Each update is conditional on the very lease it found expired: two reapers re-queue a job once."""
    from sqlalchemy import select, update

    now = time.time() if now is None else now
    with sessions() as session, session.begin():
        cutoff = reap_cutoff(session, now, lease_seconds)
        stale = session.execute(select(Job.id, Job.lease_expires, Job.attempts, Job.max_attempts, Job.note).where(
            Job.state == RUNNING, Job.lease_expires < cutoff, Job.attempts < Job.max_attempts)).all()
        requeued = 0
        for job_id, expired, attempts, max_attempts, note in stale:
            line = (f"{utc_text(now)}: the worker's lease expired at {utc_text(expired)} (it crashed, was killed or "
                    f"stalled); re-queued for attempt {attempts + 1} of {max_attempts}")
            requeued += session.execute(
                update(Job).where(Job.id == job_id, Job.state == RUNNING, Job.lease_expires == expired)
                .values(state=QUEUED, lease_owner=None, lease_expires=None,
                        note=line if not note else f"{note}\n{line}")).rowcount
        return requeued


def give_up_expired(sessions: sessionmaker[Session], now: float | None = None, lease_seconds: float = 60.0) -> int:
    """Fail the jobs whose lease expired after their last allowed attempt; returns how many."""
    from sqlalchemy import update

    now = time.time() if now is None else now
    with sessions() as session, session.begin():
        cutoff = reap_cutoff(session, now, lease_seconds)
        given_up = session.execute(
            update(Job).where(Job.state == RUNNING, Job.lease_expires < cutoff, Job.attempts >= Job.max_attempts)
            .values(state=FAILED, finished=now, lease_owner=None, lease_expires=None,
                    error="the service gave up: the worker running this job stopped (crashed, killed or lost its "
                          "lease) on each of its attempts")
            .returning(Job.id, Job.submission_id)).all()
        for job_id, submission_id in given_up:
            end_siblings(session, submission_id, job_id, FAILED, now)
        for submission_id in {s for _, s in given_up}:
            free_digest(session, submission_id)
        return len(given_up)


def end_siblings(session: Session, submission_id: int, job_id: int, state: str, now: float | None = None) -> None:
    """Job `job_id` was rejected or failed: its submission's other unfinished jobs stop, and its entries go."""
    from sqlalchemy import delete, select, update

    now = time.time() if now is None else now
    board = session.scalar(select(Job.board).where(Job.id == job_id))
    session.execute(update(Job).where(Job.submission_id == submission_id, Job.id != job_id,
                                      Job.state.in_((QUEUED, RUNNING)))
                    .values(state=REJECTED, finished=now, lease_owner=None, lease_expires=None,
                            error=f"{STOPPED}the submission's job on {board} was {state} first"))
    session.execute(delete(BoardEntry).where(BoardEntry.submission_id == submission_id))


def free_digest(session: Session, submission_id: int) -> None:
    """Let the upload of a rejected or failed submission come again: its digest no longer blocks a replay.

    The row keeps a digest derived from the old one and its id (unique, never an upload's), so the
    genuine run can follow a tampered copy of it, and an upload that failed on the server can be retried.
    """
    submission = session.get(Submission, submission_id)
    if submission is not None:
        submission.digest = hashlib.sha256(f"freed/{submission.id}/{submission.digest}".encode()).hexdigest()


def claim(sessions: sessionmaker[Session], owner: str, lease_seconds: float, now: float | None = None) -> Claimed | None:
    """Claim the oldest queued job (after re-queuing the expired ones), or None (first come, first served: a flood
    of results uploads cannot starve agent evaluations)."""
    from sqlalchemy import select, update
    from sqlalchemy.orm import aliased

    now = time.time() if now is None else now
    requeue_expired(sessions, now, lease_seconds)
    candidates = aliased(Job)
    candidate = (select(candidates.id).where(candidates.state == QUEUED, candidates.attempts < candidates.max_attempts)
                 .order_by(candidates.id).limit(1)
                 .with_for_update(skip_locked=True).scalar_subquery())
    with sessions() as session, session.begin():
        job_id = session.execute(
            update(Job).where(Job.id == candidate, Job.state == QUEUED)
            .values(state=RUNNING, lease_owner=owner, lease_expires=now + lease_seconds, attempts=Job.attempts + 1,
                    started=now, error=None)
            .returning(Job.id)).scalar()
        if job_id is None:
            return None
        job = session.get(Job, job_id)
        return Claimed(job.id, job.submission_id, job.kind, job.board, job.hidden, tuple(json.loads(job.seeds)),
                       job.attempts, job.max_attempts)


def renew(sessions: sessionmaker[Session], job_id: int, owner: str, lease_seconds: float,
          progress: tuple[int, int] | None = None) -> bool:
    """Extend a lease (and record progress); False if the lease is no longer this worker's."""
    from sqlalchemy import update

    values: dict = {"lease_expires": time.time() + lease_seconds}
    if progress is not None:
        values["units_done"], values["units_total"] = progress
    with sessions() as session, session.begin():
        result = session.execute(update(Job).where(Job.id == job_id, Job.lease_owner == owner, Job.state == RUNNING)
                                 .values(**values))
        return result.rowcount == 1


def record_resume(sessions: sessionmaker[Session], job_id: int, owner: str, done: int, total: int) -> None:
    """Note how many units the current attempt found already done (it resumes after them)."""
    from sqlalchemy import update

    with sessions() as session, session.begin():
        session.execute(update(Job).where(Job.id == job_id, Job.lease_owner == owner, Job.state == RUNNING)
                        .values(resumed_units=done, units_done=done, units_total=total))


def release(sessions: sessionmaker[Session], job_id: int, owner: str, error: str | None = None,
            count_attempt: bool = False) -> bool:
    """Put a running job back in the queue (a worker stopping, or a retry after an error)."""
    from sqlalchemy import update

    values: dict = {"state": QUEUED, "lease_owner": None, "lease_expires": None, "error": error}
    if not count_attempt:
        values["attempts"] = Job.attempts - 1
    with sessions() as session, session.begin():
        result = session.execute(update(Job).where(Job.id == job_id, Job.lease_owner == owner, Job.state == RUNNING)
                                 .values(**values))
        return result.rowcount == 1


INFRA_FAULT = "infrastructure fault"  # the head of a note line of a hand-back


def hand_back(sessions: sessionmaker[Session], job_id: int, owner: str, reason: str, max_infra_retries: int) -> str | None:
    """An infrastructure fault stopped the job: back in the queue without counting the attempt (an infrastructure
    retry instead), or failed once it has had `max_infra_retries` of them. Returns the job's new state (None: the
    lease was lost)."""
    from sqlalchemy import select, update

    now = time.time()
    with sessions() as session, session.begin():
        row = session.execute(select(Job.infra_retries, Job.note).where(
            Job.id == job_id, Job.lease_owner == owner, Job.state == RUNNING)).one_or_none()
        if row is None:
            return None
        retries, note = row
        if retries >= max_infra_retries:
            session.execute(update(Job).where(Job.id == job_id).values(attempts=Job.attempts - 1,
                                                                       infra_retries=Job.infra_retries + 1))
            close(session, job_id, owner, FAILED, f"the service gave up: {retries + 1} infrastructure faults stopped "
                                                  f"this job, the last: {reason}")
            return FAILED
        line = (f"{utc_text(now)}: {INFRA_FAULT} ({reason}); handed back without counting the attempt "
                f"(infrastructure retry {retries + 1} of {max_infra_retries})")
        session.execute(update(Job).where(Job.id == job_id, Job.lease_owner == owner, Job.state == RUNNING).values(
            state=QUEUED, lease_owner=None, lease_expires=None, attempts=Job.attempts - 1,
            infra_retries=Job.infra_retries + 1, note=line if not note else f"{note}\n{line}"))
        return QUEUED


def close(session: Session, job_id: int, owner: str, state: str, error: str | None = None) -> bool:
    """End a job in the caller's transaction (done, rejected or failed); False if the lease was lost."""
    from sqlalchemy import update

    assert state in (DONE, REJECTED, FAILED)
    values: dict = {"state": state, "error": error, "finished": time.time(), "lease_owner": None, "lease_expires": None}
    if state == DONE:
        values["units_done"] = Job.units_total  # the last units finished after the last progress record
    closed = session.execute(update(Job).where(Job.id == job_id, Job.lease_owner == owner, Job.state == RUNNING)
                             .values(**values).returning(Job.submission_id)).scalars().all()
    if closed and state != DONE:
        end_siblings(session, closed[0], job_id, state)
        free_digest(session, closed[0])
    return len(closed) == 1


def queue_counts(session: Session) -> dict[str, int]:
    """How many jobs are in each state."""
    from sqlalchemy import func, select

    return {state: n for state, n in session.execute(select(Job.state, func.count()).group_by(Job.state))}

