"""What a service instance is: its data dir, its database and its limits.

The data dir holds everything that is not in the database: `service.db` (the default SQLite
database), `uploads/` (results files, agent files and checkpoints as submitted), `jobs/<id>/`
(each evaluation job's results file, resumed after a crash, and its scratch dir) and whatever the
hidden suites need (`hidden`). Imports nothing heavy: the CLI builds settings before any import of
the web stack.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from mewa_bench.protocol.config import default_seeds

MiB = 1 << 20
HIDDEN_SUFFIX = "-hidden"  # a hidden suite's board is named after its public twin: narrow-v2-hidden


@dataclass(frozen=True)
class Limits:
    """Upload sizes, request rates and quotas; a token may carry its own rate and quotas (`tokens`)."""

    results_bytes: int = 16 * MiB  # parsed whole in memory; a ranked results file is 0.2-0.4 MB (schema 2: ~9 MB)
    agent_bytes: int = 1 * MiB
    checkpoint_bytes: int = 256 * MiB
    checkpoint_unpacked_bytes: int = 1024 * MiB
    rate_per_minute: int = 60  # submissions per token and minute
    daily_results: int = 200  # results uploads per token and 24 hours
    daily_agents: int = 20  # agent submissions per token and 24 hours
    uploads_in_flight: int = 4  # submissions read at once by the API process; more get a 503 with Retry-After


@dataclass(frozen=True)
class Settings:
    """One service instance; the API server and its workers must be started with the same settings."""

    data_dir: Path
    db_url: str | None = None  # None: SQLite at data_dir/service.db
    limits: Limits = field(default_factory=Limits)
    seeds: int | None = None  # None: the protocol's seeds per suite; n: seeds 0..n-1 everywhere (test servers)
    lease_seconds: float = 60.0  # a worker that stops renewing its lease for this long loses its job
    max_attempts: int = 3  # claims of one job before it is given up (crashed workers, lost leases)
    poll_seconds: float = 0.5  # how often an idle worker looks for a job
    hidden: bool = True  # evaluate agents on the hidden suites too
    catalog: Path | None = None  # dataset catalog served (default: data_dir/datasets/index.json, else the shipped one)
    memory_bytes: int = 4 << 30  # an agent process's memory (the protocol's default), and its sandbox's as a whole
    job_seconds: float = 6 * 3600.0  # wall-clock limit of one agent job's attempt, enforced mid-call
    scratch_bytes: int = 1 << 30  # an agent job's scratch directory on disk
    output_bytes: int = 1 << 20  # an agent's stdout and stderr kept per attempt, in the job's own log
    rank_uploads: bool = False  # rank self-reported results uploads beside server-evaluated agents
    reserve_bytes: int = 256 * MiB  # free space kept on the data dir's disk: an upload that would go below it gets a 507
    max_infra_retries: int = 10  # hand-backs of one job after infrastructure faults (database, disk) before it fails

    def __post_init__(self) -> None:
        """Keep the data dir absolute: workers and the sandbox see the same paths."""
        object.__setattr__(self, "data_dir", Path(self.data_dir).resolve())

    @property
    def database_url(self) -> str:
        """The SQLAlchemy URL (the embedded default needs no set-up)."""
        return self.db_url or f"sqlite:///{self.data_dir / 'service.db'}"

    @property
    def uploads_dir(self) -> Path:
        """Results files, agent files and checkpoints as submitted."""
        return self.data_dir / "uploads"

    @property
    def jobs_dir(self) -> Path:
        """Each evaluation job's results file and scratch dir."""
        return self.data_dir / "jobs"

    def seeds_for(self, board: str) -> tuple[int, ...]:
        """The seeds runs on a board are ranked with (a hidden board: those of its public twin)."""
        if self.seeds is not None:
            return tuple(range(self.seeds))
        return default_seeds(board.removesuffix(HIDDEN_SUFFIX))

    def replace(self, **changes) -> Settings:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)
