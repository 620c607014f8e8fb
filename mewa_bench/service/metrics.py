"""Prometheus metrics of a service instance (`GET /metrics`, made with `prometheus_client`).

What the database knows is read from it at each scrape, so it is the same whichever process
scrapes and survives restarts: jobs by state (the queue's depth), submissions by kind, the age of
the oldest queued job, claims counted against agents, infrastructure retries, re-queues by cause
(read from the jobs' notes), and the durations of finished jobs' last attempts. During a database
outage these are left out and `mewa_database_up` is 0. What only the API process sees is counted
in it: error answers by reason and status (413s from the body limit and 503s from the upload gate
included), sizes of accepted uploads. Free space on the data dir's disk, its reserve, and the
workers alive are read at each scrape.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Iterator

from mewa_bench.service.models import JOB_STATES

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

    from mewa_bench.service.storage import StorageGuard

DURATION_BUCKETS = (1.0, 5.0, 15.0, 60.0, 300.0, 900.0, 3600.0, 4 * 3600.0, 12 * 3600.0)
SIZE_BUCKETS = tuple(float(1 << k) for k in range(10, 30, 2))  # 1 KiB .. 256 MiB
REQUEUE_CAUSES = {"lease_expired": "the worker's lease expired", "infrastructure": "infrastructure fault"}


class Metrics:
    """One app's registry: counters the API process keeps, and a collector reading the database and the disk."""

    def __init__(self, sessions: sessionmaker[Session], storage: StorageGuard,
                 workers: Callable[[], tuple[int, int]]) -> None:
        from prometheus_client import CollectorRegistry, Counter, Histogram

        self.registry = CollectorRegistry(auto_describe=True)
        self.rejections = Counter("mewa_rejections", "Error answers of the API by reason (the JSON error code) and "
                                                     "HTTP status", ["reason", "status"], registry=self.registry)
        self.upload_bytes = Histogram("mewa_upload_bytes", "Sizes of accepted uploads (results files; agent files "
                                                           "with their checkpoint archive)", ["kind"],
                                      buckets=SIZE_BUCKETS, registry=self.registry)
        self.registry.register(_Collector(sessions, storage, workers))

    def rejected(self, reason: str, status: int) -> None:
        """Count an error answer."""
        self.rejections.labels(reason=reason, status=str(status)).inc()

    def uploaded(self, kind: str, size: int) -> None:
        """Count an accepted upload's size."""
        self.upload_bytes.labels(kind=kind).observe(size)

    def render(self, accept: str | None) -> tuple[bytes, str]:
        """The exposition the scraper's Accept header asks for (text 0.0.4 by default, or OpenMetrics) and its
        content type."""
        from prometheus_client.exposition import choose_encoder

        encoder, content_type = choose_encoder(accept or "")
        return encoder(self.registry), content_type


class _Collector:
    """The metrics read at each scrape."""

    def __init__(self, sessions: sessionmaker[Session], storage: StorageGuard,
                 workers: Callable[[], tuple[int, int]]) -> None:
        self.sessions, self.storage, self.workers = sessions, storage, workers

    def describe(self) -> list[Any]:
        """Nothing to describe ahead (registering must not query the database)."""
        return []

    def collect(self) -> Iterator[Any]:
        """Disk, workers, and what the database says (if it can be reached)."""
        from prometheus_client.core import GaugeMetricFamily

        from mewa_bench.service.outages import is_outage

        yield GaugeMetricFamily("mewa_data_dir_free_bytes", "Free bytes on the data dir's disk", value=self.storage.free())
        yield GaugeMetricFamily("mewa_data_dir_reserve_bytes", "Bytes kept free: uploads below this get a 507",
                                value=self.storage.reserve)
        alive, expected = self.workers()
        yield GaugeMetricFamily("mewa_workers_alive", "Worker processes of this server running", value=alive)
        yield GaugeMetricFamily("mewa_workers_expected", "Worker processes this server runs (--workers)", value=expected)
        try:
            families = list(database_metrics(self.sessions))
        except Exception as e:
            if not is_outage(e):
                raise
            families = []
        yield GaugeMetricFamily("mewa_database_up", "1 if the database answered this scrape", value=1 if families else 0)
        yield from families


def database_metrics(sessions: sessionmaker[Session]) -> Iterator[Any]:
    """The metric families read from the database."""
    import time

    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily
    from sqlalchemy import func, select

    from mewa_bench.service.models import QUEUED, Job, Submission

    with sessions() as s:
        states = dict(s.execute(select(Job.state, func.count()).group_by(Job.state)).all())
        kinds = dict(s.execute(select(Submission.kind, func.count()).group_by(Submission.kind)).all())
        attempts, infra = s.execute(select(func.coalesce(func.sum(Job.attempts), 0),
                                           func.coalesce(func.sum(Job.infra_retries), 0))).one()
        oldest = s.scalar(select(func.min(Job.created)).where(Job.state == QUEUED))
        notes = s.scalars(select(Job.note).where(Job.note.is_not(None))).all()
        durations = s.execute(select(Job.kind, Job.finished - Job.started).where(
            Job.finished.is_not(None), Job.started.is_not(None))).all()
    jobs = GaugeMetricFamily("mewa_jobs", "Jobs in each state (queued: the queue's depth)", labels=["state"])
    for state in JOB_STATES:
        jobs.add_metric([state], states.get(state, 0))
    yield jobs
    submissions = GaugeMetricFamily("mewa_submissions", "Submissions stored, by kind", labels=["kind"])
    for kind in ("results", "agent"):
        submissions.add_metric([kind], kinds.get(kind, 0))
    yield submissions
    yield GaugeMetricFamily("mewa_queue_oldest_seconds", "Age of the oldest queued job (0: none queued)",
                            value=0.0 if oldest is None else max(0.0, time.time() - oldest))
    yield CounterMetricFamily("mewa_job_attempts", "Claims of jobs counted against their agents", value=attempts)
    yield CounterMetricFamily("mewa_job_infra_retries", "Jobs handed back after an infrastructure fault (database, "
                                                        "disk), not counted as attempts", value=infra)
    requeues = CounterMetricFamily("mewa_job_requeues", "Jobs put back in the queue, by cause", labels=["cause"])
    lines = [line for note in notes for line in note.splitlines()]
    for cause, marker in REQUEUE_CAUSES.items():
        requeues.add_metric([cause], sum(1 for line in lines if marker in line))
    yield requeues
    yield _histogram(HistogramMetricFamily, durations)


def _histogram(family: Any, durations: list[tuple[str, float]]) -> Any:
    """Durations of finished jobs' last attempts as a histogram per job kind."""
    histogram = family("mewa_job_duration_seconds", "Wall-clock time of the attempt that finished each job",
                       labels=["kind"])
    for kind in sorted({k for k, _ in durations}):
        values = [max(0.0, d) for k, d in durations if k == kind]
        buckets = [(str(b), sum(1 for v in values if v <= b)) for b in DURATION_BUCKETS] + [("+Inf", len(values))]
        histogram.add_metric([kind], buckets, sum(values))
    return histogram
