"""A worker process: claims jobs from the queue, runs them, and writes each result exactly once.

While a job runs, a heartbeat thread renews its lease and records its progress; if the lease is
lost (the worker stalled past it and another worker took the job) the job stops at its next unit
and this worker writes nothing. A job ends in one transaction that closes it (conditional on the
lease) and inserts its board entry (unique per job), so a result can neither be lost between the
two nor written twice. SIGTERM stops the worker cleanly: the running job goes back to the queue and
its finished units stay in its results file for the next claim.

An agent job's attempt gets a fresh scratch directory (`jobs/<id>/scratch-<attempt>`), removed when
the attempt ends however it ends (and swept if a killed worker left one), and a log of its own for
the agent's output (`jobs/<id>/output-<attempt>.log`). While it runs, the sandbox's watchdog stops
it mid-call if the heartbeat finds the lease gone (another worker took the job, or another job of
the submission was rejected and stopped this one).

A database outage does not end a worker: its loop waits for the database (`outages.until_reachable`),
its heartbeat keeps trying to renew, and a job's final write is retried until it is done (each is
conditional on the lease, so a write that did commit before the connection dropped is not made
twice). A job stopped by an infrastructure fault (the database, a full disk) is handed back without
counting an attempt against the agent (`jobs.hand_back`).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import socket
import secrets
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

from mewa_bench.service.db import make_engine, session_factory, transaction
from mewa_bench.service.jobs import (Claimed, claim, close, give_up_expired, hand_back, record_resume, release,
                                     renew, utc_text)
from mewa_bench.service.models import (DONE, FAILED, REJECTED, RUNNING, SCORE, SELF_REPORTED, SERVER_EVALUATED,
                                       BoardEntry, Job, Submission)
from mewa_bench.service.outages import is_outage, until_reachable
from mewa_bench.service.settings import Settings
from mewa_bench.service.storage import is_disk_full

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

    from mewa_bench.service.scoring import Scored

log = logging.getLogger("mewa_bench.service.worker")
PROGRESS_SECONDS = 5.0  # the longest a job's recorded progress lags behind (and the longest between lease renewals)


class LeaseLost(Exception):
    """Another worker owns the job now; this one must stop without writing anything."""


class StopWorker(BaseException):
    """Raised in the worker's main thread by SIGTERM or SIGINT (a BaseException: no `except Exception` swallows it)."""


class Heartbeat:
    """Renews a job's lease every third of its length (at least every PROGRESS_SECONDS) and records progress,
    in a thread."""

    def __init__(self, sessions: sessionmaker[Session], job: Claimed, owner: str, lease_seconds: float) -> None:
        self.sessions, self.job, self.owner, self.lease = sessions, job, owner, lease_seconds
        self.latest: tuple[int, int] | None = None
        self.first = True
        self.lost = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"lease-{job.id}", daemon=True)

    def __enter__(self) -> Heartbeat:
        """Start renewing."""
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        """Stop renewing (the job is ending)."""
        self._stop.set()
        self._thread.join()

    def cancel_reason(self) -> str | None:
        """Why the job must stop now (polled by the sandbox's watchdog), or None."""
        if self.lost.is_set():
            return f"job {self.job.id}: this worker no longer holds the job (its lease expired, or another job of " \
                   f"its submission ended it)"
        return None

    def progress(self, done: int, total: int) -> None:
        """The evaluation's progress callback: the first call says where this attempt resumes."""
        if self.lost.is_set():
            raise LeaseLost(f"job {self.job.id}: the lease was lost")
        if self.first:
            try:
                record_resume(self.sessions, self.job.id, self.owner, done, total)
                self.first = False
            except Exception as e:  # shown on the status only: recorded at a later unit if the database is away
                if not is_outage(e):
                    raise
        self.latest = (done, total)

    def _run(self) -> None:
        """Renew until stopped, or until the lease is found lost."""
        failing_since = None
        while not self._stop.wait(min(max(0.1, self.lease / 3), PROGRESS_SECONDS)):
            try:
                if not renew(self.sessions, self.job.id, self.owner, self.lease, self.latest):
                    self.lost.set()
                    return
            except Exception as e:  # try again at the next beat: after an outage the first renewal keeps the job
                if failing_since is None:
                    failing_since = time.monotonic()
                    (log.warning if is_outage(e) else log.exception)(
                        "job %s: renewing the lease failed (%s); retrying at every beat", self.job.id,
                        str(e).splitlines()[0][:200])
                continue
            if failing_since is not None:
                log.warning("job %s: the lease is renewed again after %.1f s", self.job.id,
                            time.monotonic() - failing_since)
                failing_since = None


def worker_id() -> str:
    """host:pid:random, the lease owner of this process's claims."""
    return f"{socket.gethostname()[:40]}:{os.getpid()}:{secrets.token_hex(4)}"


def _stop_on_signals() -> None:
    """SIGTERM (the server stopping its workers) and SIGINT (Ctrl-C reaches the whole process group) stop cleanly."""
    def handler(signum, frame) -> None:
        """Stop the main thread where it is."""
        raise StopWorker()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


def run_worker(settings: Settings, supervised: bool = False, max_jobs: int | None = None) -> None:
    """Claim and run jobs until SIGTERM (or `max_jobs`); `supervised`: also stop when the parent process dies."""
    _stop_on_signals()
    parent = os.getppid()
    engine = make_engine(settings.database_url)
    sessions = session_factory(engine)
    owner = worker_id()
    log.info("worker %s started", owner)
    done = 0

    def orphaned() -> bool:
        """Whether the server that started this worker is gone."""
        return supervised and os.getppid() != parent

    try:
        until_reachable(lambda: sweep_scratch(settings, sessions), f"worker {owner}", gone=orphaned)
        while max_jobs is None or done < max_jobs:
            if orphaned():
                log.warning("worker %s: the server is gone, stopping", owner)
                return
            job = until_reachable(lambda: _next_job(settings, sessions, owner), f"worker {owner}", gone=orphaned)
            if job is None:
                time.sleep(settings.poll_seconds)
                continue
            try:
                run_job(settings, sessions, job, owner)
            except Exception as e:  # an outage while the job's lease was found lost: nothing of it is this worker's
                if not is_outage(e):
                    raise
                log.warning("job %s: left to its lease (this worker lost it while the database was away)", job.id)
            until_reachable(lambda: sweep_scratch(settings, sessions), f"worker {owner}")
            done += 1
    except StopWorker:
        log.info("worker %s stopped", owner)
    except Exception as e:
        if not (orphaned() and is_outage(e)):
            raise
        log.warning("worker %s: the server is gone and the database with it, stopping", owner)
    finally:
        engine.dispose()


def _next_job(settings: Settings, sessions: sessionmaker[Session], owner: str) -> Claimed | None:
    """Give up the jobs out of attempts whose lease expired, then claim the oldest queued job (None: none)."""
    give_up_expired(sessions, lease_seconds=settings.lease_seconds)
    return claim(sessions, owner, settings.lease_seconds)


def run_job(settings: Settings, sessions: sessionmaker[Session], job: Claimed, owner: str) -> None:
    """Run one claimed job to its end: done (with its entry), rejected, failed, or back in the queue."""
    log.info("job %s (%s, %s) claimed by %s, attempt %s", job.id, job.kind, job.board, owner, job.attempts)
    from mewa_bench.leaderboard.validate import InvalidResults
    from mewa_bench.service.evaluation import AgentRejected
    from mewa_bench.service.sandbox import SandboxCancelled

    with Heartbeat(sessions, job, owner, settings.lease_seconds) as beat:
        def retried(action, what: str):
            """`action()` retried through database outages while this worker holds the job."""
            return until_reachable(action, f"job {job.id}: {what}", gone=beat.lost.is_set)

        try:
            scored = _score(settings, sessions, job, beat)
        except (InvalidResults, AgentRejected) as e:
            retried(lambda: _close(sessions, job.id, owner, REJECTED, str(e)), "closing it rejected")
            log.info("job %s rejected (%s; the reason is kept with the job)", job.id, type(e).__name__)
            return
        except (LeaseLost, SandboxCancelled):
            log.warning("job %s: this worker no longer holds it (lease lost, or stopped with its submission)", job.id)
            return
        except StopWorker:
            try:
                release(sessions, job.id, owner)
            except Exception:  # the database is away: the lease expires instead
                log.warning("job %s: could not put it back in the queue (its lease will expire)", job.id)
            raise
        except Exception as e:
            reason = f"{type(e).__name__}: {str(e).splitlines()[0][:300] if str(e) else ''}"
            if is_outage(e) or is_disk_full(e):
                state = retried(lambda: hand_back(sessions, job.id, owner, reason, settings.max_infra_retries),
                                "handing it back")
                log.warning("job %s: stopped by an infrastructure fault (%s); %s", job.id, reason,
                            "given up" if state == FAILED else "handed back without counting the attempt")
                return
            log.exception("job %s failed on attempt %s", job.id, job.attempts)
            if job.attempts >= job.max_attempts:
                retried(lambda: _close(sessions, job.id, owner, FAILED,
                                       f"the service gave up after {job.attempts} attempts: {reason}"), "closing it")
            else:
                retried(lambda: release(sessions, job.id, owner, error=reason, count_attempt=True), "re-queuing it")
            return
        finally:
            shutil.rmtree(_scratch(settings, job), ignore_errors=True)
        if not beat.lost.is_set():  # the heartbeat goes on while the result is written (retried through an outage)
            retried(lambda: _finish(sessions, job, owner, scored), "writing its result")


def _close(sessions: sessionmaker[Session], job_id: int, owner: str, state: str, error: str) -> bool:
    """End a job rejected or failed, in a transaction of its own."""
    with transaction(sessions) as session:
        return close(session, job_id, owner, state, error)


def _finish(sessions: sessionmaker[Session], job: Claimed, owner: str, scored: Scored) -> None:
    """Close a scored job with its board entry, or rejected if its run is on the board already (one row per run); the
    server's own evaluation of a run supersedes a self-reported upload of it."""
    from sqlalchemy.exc import IntegrityError

    try:
        _finish_once(sessions, job, owner, scored)
    except IntegrityError:  # another worker put the same run on the board between our look and our insert
        log.info("job %s: its run reached the board from another job at the same time; looking again", job.id)
        _finish_once(sessions, job, owner, scored)


def _finish_once(sessions: sessionmaker[Session], job: Claimed, owner: str, scored: Scored) -> None:
    """One try of `_finish` in one transaction."""
    from sqlalchemy import select

    source = SELF_REPORTED if job.kind == SCORE else SERVER_EVALUATED
    with transaction(sessions) as session:
        earlier = session.scalar(select(BoardEntry).where(BoardEntry.board == job.board,
                                                          BoardEntry.run_digest == scored.run_digest))
        if earlier is not None and (earlier.source != SELF_REPORTED or source != SERVER_EVALUATED):
            reason = (f"replayed run: these episodes are those of submission {earlier.submission_id} on {job.board} "
                      f"already (one run is one row, whatever its agent file's comments or name)")
            if close(session, job.id, owner, REJECTED, reason):
                log.info("job %s rejected: %s", job.id, reason)
            return
        if not close(session, job.id, owner, DONE):
            return
        if earlier is not None:  # the upload's row gives way to the server's evaluation of the same run
            _note(session, earlier.job_id, f"{utc_text(time.time())}: its row gave way to submission "
                                           f"{job.submission_id}, the server's own evaluation of the same run")
            session.delete(earlier)
            session.flush()
        row = json.loads(scored.row)
        algorithm = session.scalar(select(Submission.algorithm).where(Submission.id == job.submission_id))
        session.add(BoardEntry(submission_id=job.submission_id, job_id=job.id, board=job.board, hidden=job.hidden,
                               agent_name=row["name"], agent_sha256=row["agent_sha256"], privileged=scored.privileged,
                               mean=scored.mean, row=scored.row, scores=scored.scores, created=time.time(),
                               run_digest=scored.run_digest, source=source, algorithm=algorithm,
                               pair_curves=scored.pair_curves))
    log.info("job %s done", job.id)


def _note(session: Session, job_id: int, line: str) -> None:
    """Add a line to a job's note."""
    job = session.get(Job, job_id)
    if job is not None:
        job.note = line if not job.note else f"{job.note}\n{line}"


def _scratch(settings: Settings, job: Claimed) -> Path:
    """This attempt's scratch directory."""
    return settings.jobs_dir / str(job.id) / f"scratch-{job.attempts}"


def sweep_scratch(settings: Settings, sessions: sessionmaker[Session]) -> list[Path]:
    """Remove the scratch directories of jobs that are not running (left by killed workers); returns them."""
    from sqlalchemy import select

    found = [p for p in settings.jobs_dir.glob("*/scratch*") if p.parent.name.isdigit()]
    if not found:
        return []
    with sessions() as session:
        running = set(session.scalars(select(Job.id).where(Job.state == RUNNING)))
    removed = [p for p in found if int(p.parent.name) not in running]
    for path in removed:
        shutil.rmtree(path, ignore_errors=True)
    return removed


def _score(settings: Settings, sessions: sessionmaker[Session], job: Claimed, beat: Heartbeat) -> Scored:
    """The job's work: re-score an upload, or evaluate an agent and score its run."""
    from mewa_bench.design.suites import load_suite
    from mewa_bench.service.evaluation import AgentJob, run_agent_job, suite_of
    from mewa_bench.service.scoring import score_evaluation, score_upload
    from mewa_bench.service.uploads import parse_results

    def read() -> tuple[str, str, str | None]:
        """What the job's submission says."""
        with sessions() as session:
            submission = session.get(Submission, job.submission_id)
            return submission.file, submission.agent_name, submission.agent_args

    file, name, args = until_reachable(read, f"job {job.id}: reading its submission", gone=beat.lost.is_set)
    path = settings.data_dir / file
    if job.kind == SCORE:
        return score_upload(parse_results(path.read_bytes()), job.seeds, job.submission_id)
    job_dir = settings.jobs_dir / str(job.id)
    job_dir.mkdir(parents=True, exist_ok=True)
    os.chmod(job_dir, 0o700)
    for left in job_dir.glob("scratch*"):  # a fresh scratch for every attempt: nothing an earlier one wrote is kept
        shutil.rmtree(left, ignore_errors=True)
    agent = AgentJob(agent_file=path, board=job.board, hidden=job.hidden, seeds=job.seeds, name=name,
                     agent_args=json.loads(args or "{}"), out=job_dir / "results.json", scratch=_scratch(settings, job),
                     output_log=job_dir / f"output-{job.attempts}.log")
    results = run_agent_job(settings, agent, beat.progress, cancel=beat.cancel_reason)
    return score_evaluation(results, load_suite(suite_of(settings, job.board, job.hidden)), job.submission_id)
