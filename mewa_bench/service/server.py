"""`mewa-bench serve`: the API (uvicorn, one process) and its evaluation workers (N processes).

At start: the data dir, the schema migrations, and a sweep of upload files that no row points at
(a server killed mid-upload; `uploads.sweep_orphans` says which are certainly orphaned). The
workers are child processes, restarted if one dies; on SIGINT or SIGTERM the API stops taking
requests and each worker puts its running job back in the queue. A reaper thread re-queues (or gives
up) jobs whose lease expired on a timer, so a dead worker's job shows it as soon as its lease ends.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import threading
import time
from typing import IO, TYPE_CHECKING

from mewa_bench.service.settings import Settings

if TYPE_CHECKING:
    from multiprocessing.process import BaseProcess

log = logging.getLogger("mewa_bench.service")
RESTART_DELAY = 1.0  # seconds between restarts of a dead worker
STOP_TIMEOUT = 20.0  # seconds a worker gets to put its job back before it is killed


def prepare(settings: Settings) -> IO[str]:
    """Create the data dir, migrate the database, and remove orphaned upload files (any age if this is the data dir's
    only API process, else only old ones: `uploads.hold_api_lock`). Returns the API lock, to hold while serving."""
    from sqlalchemy import select

    from mewa_bench.service.db import make_engine, migrate, session_factory
    from mewa_bench.service.models import Submission
    from mewa_bench.service.uploads import ORPHAN_AGE, hold_api_lock, share_api_lock, sweep_orphans

    from mewa_bench.service.app import make_data_dir

    make_data_dir(settings)
    lock, alone = hold_api_lock(settings)
    engine = make_engine(settings.database_url)
    try:
        migrate(engine)
        with session_factory(engine)() as s:
            referenced = set(s.scalars(select(Submission.file)))
        removed = sweep_orphans(settings, referenced, min_age=0.0 if alone else ORPHAN_AGE)
        if removed:
            log.info("removed %d upload file(s) of uploads that were never committed", len(removed))
        share_api_lock(lock)
    except BaseException:
        lock.close()
        raise
    finally:
        engine.dispose()
    return lock


class Reaper:
    """Re-queues jobs whose lease expired (and gives up those out of attempts) every `period` seconds, in a thread."""

    def __init__(self, settings: Settings, period: float) -> None:
        from mewa_bench.service.db import make_engine, session_factory

        self.period, self.lease = period, settings.lease_seconds
        self.engine = make_engine(settings.database_url)
        self.sessions = session_factory(self.engine)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="reaper", daemon=True)

    def start(self) -> Reaper:
        """Start reaping."""
        self._thread.start()
        return self

    def _run(self) -> None:
        """Reap until stopped; a database outage waits for the next round (said once when it starts and ends)."""
        from mewa_bench.service.jobs import give_up_expired, requeue_expired
        from mewa_bench.service.outages import is_outage

        failing = False
        while not self._stop.wait(self.period):
            try:
                requeued = requeue_expired(self.sessions, lease_seconds=self.lease)
                given_up = give_up_expired(self.sessions, lease_seconds=self.lease)
            except Exception as e:
                if not is_outage(e):
                    log.exception("reaper: the round failed")
                elif not failing:
                    log.warning("reaper: the database is unreachable; trying again every %.1f s", self.period)
                failing = True
                continue
            if failing:
                log.warning("reaper: the database is reachable again")
                failing = False
            if requeued or given_up:
                log.warning("reaper: %d job(s) re-queued, %d given up after their worker's lease expired",
                            requeued, given_up)

    def stop(self) -> None:
        """Stop reaping."""
        self._stop.set()
        self._thread.join()
        self.engine.dispose()


def reaper_period(settings: Settings) -> float:
    """How often the reaper looks (`jobs.reap_period` of the lease)."""
    from mewa_bench.service.jobs import reap_period

    return reap_period(settings.lease_seconds)


def _worker_entry(settings: Settings, log_level: int) -> None:
    """A worker process's main function (spawned: a fresh interpreter)."""
    from mewa_bench.service.worker import run_worker

    logging.basicConfig(level=log_level, format="%(asctime)s %(name)s[%(process)d] %(levelname)s %(message)s")
    run_worker(settings, supervised=True)


class WorkerPool:
    """N worker processes, each restarted if it dies while the pool runs."""

    def __init__(self, settings: Settings, size: int, log_level: int = logging.INFO) -> None:
        self.settings, self.size, self.log_level = settings, size, log_level
        self.processes: list[BaseProcess | None] = [None] * size
        self._context = multiprocessing.get_context("spawn")
        self._stopping = threading.Event()
        self._watcher = threading.Thread(target=self._watch, name="worker-pool", daemon=True)

    def start(self) -> None:
        """Start every worker and the thread that restarts dead ones."""
        for i in range(self.size):
            self._start(i)
        self._watcher.start()

    def _start(self, i: int) -> None:
        """Start worker `i`."""
        process = self._context.Process(target=_worker_entry, args=(self.settings, self.log_level),
                                        name=f"mewa-worker-{i}", daemon=False)
        process.start()
        self.processes[i] = process

    def _watch(self) -> None:
        """Restart workers that died while the pool runs."""
        while not self._stopping.wait(RESTART_DELAY):
            for i, process in enumerate(self.processes):
                if process is not None and not process.is_alive() and not self._stopping.is_set():
                    log.warning("worker %s (pid %s) exited with %s; starting another", i, process.pid, process.exitcode)
                    self._start(i)

    def alive(self) -> int:
        """How many workers are running now."""
        return sum(1 for p in self.processes if p is not None and p.is_alive())

    def pids(self) -> list[int]:
        """The workers' process ids."""
        return [p.pid for p in self.processes if p is not None and p.pid is not None]

    def stop(self) -> None:
        """SIGTERM every worker (each puts its job back), then wait; kill the ones that do not stop."""
        self._stopping.set()
        for process in self.processes:
            if process is not None and process.is_alive():
                os.kill(process.pid, signal.SIGTERM)
        deadline = time.monotonic() + STOP_TIMEOUT
        for process in self.processes:
            if process is not None:
                process.join(max(0.0, deadline - time.monotonic()))
                if process.is_alive():
                    process.kill()
                    process.join()


def run_server(settings: Settings, host: str = "127.0.0.1", port: int = 8000, workers: int = 1,
               log_level: str = "info") -> None:
    """Serve the API on host:port with `workers` evaluation workers, until SIGINT or SIGTERM."""
    from mewa_bench.extras import require

    uvicorn = require("uvicorn", "service", "mewa-bench serve")
    from mewa_bench.service.app import create_app

    level = getattr(logging, log_level.upper(), logging.INFO)
    logging.basicConfig(level=level, format="%(asctime)s %(name)s[%(process)d] %(levelname)s %(message)s")
    api_lock = prepare(settings)
    _warn_without_sandbox(workers)
    app = create_app(settings)
    pool = WorkerPool(settings, workers, level)
    pool.start()
    app.state.workers = lambda: (pool.alive(), workers)  # readiness and /metrics
    reaper = Reaper(settings, reaper_period(settings)).start()
    # uvicorn stops on SIGTERM or SIGINT, then raises it again with the handler it found: make that handler a no-op,
    # so that the workers are stopped below (each puts its running job back in the queue) before we exit
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda signum, frame: None)
    try:
        config = uvicorn.Config(app, host=host, port=port, log_level=log_level, timeout_graceful_shutdown=10,
                                lifespan="off")
        uvicorn.Server(config).run()
    finally:
        reaper.stop()
        pool.stop()
        app.state.engine.dispose()
        api_lock.close()


def _warn_without_sandbox(workers: int) -> None:
    """Agents are only ever run sandboxed: say so at start if this machine cannot."""
    if workers == 0:
        return
    from mewa_bench.service.sandbox import sandbox_available, sandbox_isolation

    isolation = sandbox_isolation()
    (log.warning if isolation.startswith("no cgroup") else log.info)("sandboxes: %s", isolation)

    problem = sandbox_available()
    if problem is not None:
        log.warning("agent submissions will fail on this server: it cannot sandbox agents (%s)", problem)
