"""The service's tables (SQLAlchemy ORM): tokens, submissions, jobs and board entries.

Times are Unix seconds (floats) so that leases compare the same way on SQLite and PostgreSQL.
Exactly-once rules live in unique constraints, not in code: one submission per upload digest
(replays), one job per (submission, board), one board entry per job, one entry per run and board.
"""

from __future__ import annotations

from sqlalchemy import Boolean, Float, ForeignKey, Integer, String, Text, UniqueConstraint
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

# Job states: queued -> running -> done | rejected (the submission's fault: tampered results, a failing
# or hostile agent) | failed (the service gave up: max_attempts claims without finishing).
QUEUED, RUNNING, DONE, REJECTED, FAILED = "queued", "running", "done", "rejected", "failed"
JOB_STATES = (QUEUED, RUNNING, DONE, REJECTED, FAILED)
RESULTS, AGENT = "results", "agent"  # submission kinds
SCORE, EVALUATE = "score", "evaluate"  # job kinds
# What a board row's scores rest on: the server's own evaluation of an agent file, a results file the submitter
# ran (re-scored from its episodes, but played where the server cannot see), or the suite's reference lines.
SERVER_EVALUATED, SELF_REPORTED, REFERENCE_SOURCE = "server-evaluated", "self-reported", "reference"


class Base(DeclarativeBase):
    """The service's metadata."""


class Token(Base):
    """A submitter's API token; only its sha256 is stored. Limits left empty take the server's defaults."""

    __tablename__ = "tokens"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(100), unique=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    created: Mapped[float] = mapped_column(Float)
    revoked: Mapped[bool] = mapped_column(Boolean, default=False)
    rate_per_minute: Mapped[int | None] = mapped_column(Integer, nullable=True)
    daily_results: Mapped[int | None] = mapped_column(Integer, nullable=True)
    daily_agents: Mapped[int | None] = mapped_column(Integer, nullable=True)


class Submission(Base):
    """One accepted upload: a results file or an agent (with its files under the data dir)."""

    __tablename__ = "submissions"
    __table_args__ = (UniqueConstraint("token_id", "idempotency_key", name="uq_submissions_token_key"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    token_id: Mapped[int] = mapped_column(ForeignKey("tokens.id"), index=True)
    kind: Mapped[str] = mapped_column(String(16))
    suite: Mapped[str] = mapped_column(String(100))
    digest: Mapped[str] = mapped_column(String(64), unique=True)  # what makes two uploads the same (replays)
    agent_name: Mapped[str] = mapped_column(String(100))
    agent_sha256: Mapped[str] = mapped_column(String(64))
    file: Mapped[str] = mapped_column(String(500))  # relative to the data dir
    agent_args: Mapped[str | None] = mapped_column(Text, nullable=True)  # JSON object, for agent submissions
    algorithm: Mapped[str | None] = mapped_column(String(100), nullable=True)  # the submitter's name for its algorithm
    created: Mapped[float] = mapped_column(Float, index=True)
    idempotency_key: Mapped[str | None] = mapped_column(String(200), nullable=True)  # the client's, per token


class Job(Base):
    """A unit of work for the workers: re-score a results file, or evaluate an agent on one board."""

    __tablename__ = "jobs"
    __table_args__ = (UniqueConstraint("submission_id", "board"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    submission_id: Mapped[int] = mapped_column(ForeignKey("submissions.id"), index=True)
    kind: Mapped[str] = mapped_column(String(16))
    board: Mapped[str] = mapped_column(String(100))  # a public suite, or a hidden suite's name
    hidden: Mapped[bool] = mapped_column(Boolean, default=False)
    seeds: Mapped[str] = mapped_column(Text)  # JSON list: the seeds this board ranks with, fixed at submission
    state: Mapped[str] = mapped_column(String(16), default=QUEUED, index=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0)  # claims that count against the agent
    infra_retries: Mapped[int] = mapped_column(Integer, default=0, server_default="0")  # hand-backs after infrastructure faults
    max_attempts: Mapped[int] = mapped_column(Integer)
    lease_owner: Mapped[str | None] = mapped_column(String(100), nullable=True)
    lease_expires: Mapped[float | None] = mapped_column(Float, nullable=True)
    units_done: Mapped[int] = mapped_column(Integer, default=0)
    units_total: Mapped[int] = mapped_column(Integer, default=0)
    resumed_units: Mapped[int | None] = mapped_column(Integer, nullable=True)  # units already done when the last claim started
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    note: Mapped[str | None] = mapped_column(Text, nullable=True)  # what the service did to it (re-queued: why, when)
    created: Mapped[float] = mapped_column(Float)
    started: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished: Mapped[float | None] = mapped_column(Float, nullable=True)


class BoardEntry(Base):
    """A scored run on a board: written once, in the transaction that finishes its job."""

    __tablename__ = "entries"
    __table_args__ = (UniqueConstraint("board", "run_digest", name="uq_entries_board_run"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    submission_id: Mapped[int] = mapped_column(ForeignKey("submissions.id"), index=True)
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id"), unique=True)
    board: Mapped[str] = mapped_column(String(100), index=True)
    hidden: Mapped[bool] = mapped_column(Boolean, default=False)
    agent_name: Mapped[str] = mapped_column(String(100))
    agent_sha256: Mapped[str] = mapped_column(String(64))
    privileged: Mapped[bool] = mapped_column(Boolean, default=False)
    mean: Mapped[float] = mapped_column(Float)
    row: Mapped[str] = mapped_column(Text)  # JSON: the leaderboard row (`leaderboard.board.Row` fields)
    scores: Mapped[str] = mapped_column(Text)  # JSON: the scores recomputed on the server, as a results file has them
    algorithm: Mapped[str | None] = mapped_column(String(100), nullable=True)  # None: a one-run algorithm (the agent)
    pair_curves: Mapped[str | None] = mapped_column(Text, nullable=True)  # JSON [pairs][episodes]: the run's cells
    created: Mapped[float] = mapped_column(Float)
    source: Mapped[str] = mapped_column(String(20), default=SERVER_EVALUATED, server_default=SERVER_EVALUATED)
    run_digest: Mapped[str | None] = mapped_column(String(64), nullable=True)  # the run's episodes (one row per run)


class ServiceClock(Base):
    """One row: when a process that reaps expired leases last reached the database, and the latest gap in that
    (an outage, or nobody looking), so that leases that lapsed only in a gap get a grace to be renewed."""

    __tablename__ = "service_clock"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    last_contact: Mapped[float] = mapped_column(Float)
    gap_start: Mapped[float] = mapped_column(Float)  # the last contact before the latest gap
    resumed: Mapped[float] = mapped_column(Float)  # the first contact after it
