"""Test harness of the service: real servers (`mewa-bench serve` in a subprocess) on SQLite and PostgreSQL.

PostgreSQL is Debian's (`apt-get install postgresql`, done by .ci/setup): a throw-away cluster made
with initdb in a temp dir and started with pg_ctl, as the unprivileged `postgres` user when the
tests run as root. Without it the PostgreSQL variants skip, unless MEWA_REQUIRE_POSTGRES=1 (CI),
where they fail. A small file system for the disk-full tests is a tmpfs mounted for the test (root
only); where mounting is impossible they skip, unless MEWA_REQUIRE_MOUNT=1 (CI), where they fail.
"""

from __future__ import annotations

import atexit
import contextlib
import glob
import json
import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

import httpx
import pytest

REPO = Path(__file__).resolve().parents[1]
AGENTS = REPO / "tests" / "agents"
RANDOM_AGENT = REPO / "submissions" / "random" / "agent.py"
STARTUP_TIMEOUT = 60.0
# the console script beside this interpreter (the package is installed in the venv that runs the tests)
CLI = [str(Path(sys.executable).with_name("mewa-bench"))]


def free_port() -> int:
    """A TCP port nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# -- PostgreSQL ------------------------------------------------------------------------------------
def postgres_bin() -> Path | None:
    """The newest installed PostgreSQL's bin dir (Debian: /usr/lib/postgresql/<major>/bin), or None."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[-3]))
    if found:
        return Path(found[-1]).parent
    initdb = shutil.which("initdb")
    return Path(initdb).parent if initdb else None


class Postgres:
    """A PostgreSQL cluster in a temp dir, listening on 127.0.0.1 only."""

    def __init__(self, root: Path) -> None:
        self.bin = postgres_bin()
        assert self.bin is not None
        self.root, self.port = root, free_port()
        self.data, self.sockets = root / "data", root / "sockets"
        self.user = "postgres" if os.geteuid() == 0 else None
        self.databases = 0

    def _run(self, *command: str) -> None:
        """Run a PostgreSQL program (as the postgres user when we are root)."""
        prefix = ["runuser", "-u", self.user, "--"] if self.user else []
        subprocess.run([*prefix, *command], check=True, capture_output=True, text=True, timeout=120)

    def start(self) -> None:
        """initdb and start the cluster."""
        self.sockets.mkdir(parents=True)
        if self.user:  # a folder of its own under /tmp, which the postgres user can reach
            uid = pwd.getpwnam(self.user).pw_uid
            for path in (self.root, self.sockets):
                os.chown(path, uid, -1)
        self._run(str(self.bin / "initdb"), "-D", str(self.data), "-A", "trust", "-U", "mewa", "--no-sync")
        self.start_again()

    def start_again(self) -> None:
        """Start the (stopped) cluster on its port."""
        options = f"-p {self.port} -k {self.sockets} -c listen_addresses=127.0.0.1 -c fsync=off -c max_connections=200"
        self._run(str(self.bin / "pg_ctl"), "-D", str(self.data), "-o", options, "-l", str(self.root / "log"),
                  "-w", "start")

    def stop(self) -> None:
        """Stop the cluster at once."""
        self._run(str(self.bin / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "-w", "stop")

    def new_database(self) -> str:
        """A fresh, empty database's URL."""
        self.databases += 1
        name = f"mewa{self.databases}"
        self._run(str(self.bin / "createdb"), "-h", "127.0.0.1", "-p", str(self.port), "-U", "mewa", name)
        return f"postgresql://mewa@127.0.0.1:{self.port}/{name}"


_CLUSTER: list[Postgres] = []


def postgres_cluster() -> Postgres | None:
    """The test session's PostgreSQL cluster (started on first use, stopped at exit), or None when PostgreSQL is
    not installed; with MEWA_REQUIRE_POSTGRES=1 (CI) a missing PostgreSQL fails the test instead."""
    if _CLUSTER:
        return _CLUSTER[0]
    if postgres_bin() is None or (os.geteuid() == 0 and shutil.which("runuser") is None):
        if os.environ.get("MEWA_REQUIRE_POSTGRES") == "1":
            pytest.fail("MEWA_REQUIRE_POSTGRES=1 but PostgreSQL is not installed (apt-get install postgresql)")
        return None
    cluster = Postgres(Path(tempfile.mkdtemp(prefix="mewa-postgres-")))
    atexit.register(_remove, cluster)
    cluster.start()
    _CLUSTER.append(cluster)
    return cluster


def _remove(cluster: Postgres) -> None:
    """Stop the cluster and remove its folder."""
    if (cluster.data / "postmaster.pid").exists():
        cluster.stop()
    shutil.rmtree(cluster.root, ignore_errors=True)


@pytest.fixture(scope="session")
def postgres():
    """The session's PostgreSQL cluster (None without PostgreSQL: the postgresql variants skip, or fail in CI)."""
    return postgres_cluster()


BACKENDS = ["sqlite", "postgresql"]
# The longest end-to-end tests (a real job, a killed server) run on PostgreSQL in the slow tier only: the
# default tier keeps PostgreSQL in the API tests, the queue, the migrations and the database outage.
BACKENDS_POSTGRES_SLOW = ["sqlite", pytest.param("postgresql", marks=pytest.mark.slow)]


def database_url(backend: str, postgres: Postgres | None) -> str | None:
    """None for SQLite in the data dir; a fresh database for PostgreSQL (or a skip)."""
    if backend == "sqlite":
        return None
    if postgres is None:
        pytest.skip("PostgreSQL is not installed (set MEWA_REQUIRE_POSTGRES=1 to fail instead)")
    return postgres.new_database()


def require_sandbox() -> None:
    """Agent jobs need the sandbox (bubblewrap): skip without it, or fail where it is required (CI)."""
    from mewa_bench.service.sandbox import sandbox_available

    problem = sandbox_available()
    if problem is not None:
        if os.environ.get("MEWA_REQUIRE_SANDBOX") == "1":
            pytest.fail(f"MEWA_REQUIRE_SANDBOX=1 but agents cannot be sandboxed here: {problem}")
        pytest.skip(f"agents cannot be sandboxed here: {problem}")


@contextlib.contextmanager
def small_filesystem(where: Path, size_mb: int, inodes: int) -> Iterator[Path]:
    """A tmpfs of `size_mb` MiB and `inodes` files mounted at `where` for the block, unmounted after it. Skips where
    it cannot be mounted (not root, no mount), or fails with MEWA_REQUIRE_MOUNT=1 (CI)."""
    where.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m,nr_inodes={inodes},mode=0755", "tmpfs",
                              str(where)], capture_output=True, text=True) if shutil.which("mount") else None
    if mounted is None or mounted.returncode != 0:
        why = "no mount command" if mounted is None else (mounted.stderr.strip() or f"mount exited {mounted.returncode}")
        if os.environ.get("MEWA_REQUIRE_MOUNT") == "1":
            pytest.fail(f"MEWA_REQUIRE_MOUNT=1 but a small tmpfs cannot be mounted here (run as root): {why}")
        pytest.skip(f"a small file system cannot be mounted here (mounting a tmpfs needs root): {why}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "--lazy", str(where)], check=True, capture_output=True)


# -- servers ---------------------------------------------------------------------------------------
class Server:
    """`mewa-bench serve` in a subprocess; restartable on the same data dir and database."""

    def __init__(self, data_dir: Path, db: str | None, *options: str, env: dict[str, str] | None = None) -> None:
        self.data_dir, self.db, self.options = data_dir, db, list(options)
        self.env = dict(env or {})  # added to the server's environment at each start (e.g. a crash point)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.process: subprocess.Popen | None = None
        self.log = data_dir.parent / f"{data_dir.name}-server.log"

    def command(self) -> list[str]:
        """The `mewa-bench serve` command line."""
        db = ["--db", self.db] if self.db else []
        return [*CLI, "serve", "--data-dir", str(self.data_dir), *db,
                "--port", str(self.port), "--log-level", "warning", *self.options]

    def start(self) -> Server:
        """Start the server; returns when it answers."""
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", **self.env}
        with open(self.log, "a") as log:
            self.process = subprocess.Popen(self.command(), stdout=log, stderr=subprocess.STDOUT, env=env,
                                            start_new_session=True)
        deadline = time.monotonic() + STARTUP_TIMEOUT
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"the server exited with {self.process.returncode}:\n{self.log.read_text()[-3000:]}")
            try:
                if get(self, "/api/health").status_code == 200:
                    return self
            except (OSError, httpx.HTTPError):
                pass
            time.sleep(0.2)
        raise RuntimeError(f"the server did not answer within {STARTUP_TIMEOUT} s:\n{self.log.read_text()[-3000:]}")

    def stop(self) -> None:
        """SIGTERM, as an admin would; the server stops its workers."""
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.kill()
        self.process = None

    def kill(self) -> None:
        """SIGKILL the server and everything it started (its process group): a crash."""
        if self.process is not None:
            try:
                os.killpg(self.process.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.process.wait(30)
        self.process = None

    def token(self, name: str, **limits: int) -> str:
        """A new API token, made with the admin command."""
        db = ["--db", self.db] if self.db else []
        flags = [f"--{k.replace('_', '-')}={v}" for k, v in limits.items()]
        out = subprocess.run([*CLI, "serve", "token", "create", name,
                              "--data-dir", str(self.data_dir), *db, *flags],
                             check=True, capture_output=True, text=True, timeout=120)
        return out.stdout.strip().splitlines()[-1]


def get(server: Server, path: str, **kw: Any):
    """GET a path of the server."""
    return httpx.get(server.url + path, timeout=60, **kw)


def post_results(server: Server, token: str | None, data: bytes, name: str = "results.json"):
    """Upload a results file."""
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return httpx.post(server.url + "/api/submissions/results", files={"file": (name, data, "application/json")},
                      headers=headers, timeout=120)


def post_agent(server: Server, token: str, agent: Path, suite: str = "narrow-v1", name: str | None = None,
               agent_args: dict[str, str] | None = None, checkpoint: tuple[str, bytes] | None = None):
    """Submit an agent (and a checkpoint archive)."""
    files = [("agent", (agent.name, agent.read_bytes(), "text/x-python"))]
    if checkpoint is not None:
        files.append(("checkpoint", (checkpoint[0], checkpoint[1], "application/gzip")))
    data: dict[str, Any] = {"suite": suite, "name": name or agent.stem}
    if agent_args:
        data["agent_arg"] = [f"{k}={v}" for k, v in agent_args.items()]
    return httpx.post(server.url + "/api/submissions/agent", files=files, data=data,
                      headers={"Authorization": f"Bearer {token}"}, timeout=120)


def wait_status(server: Server, submission_id: int, timeout: float = 120.0,
                final: tuple[str, ...] = ("done", "rejected", "failed")) -> dict[str, Any]:
    """Poll a submission until it reaches a final state."""
    deadline = time.monotonic() + timeout
    while True:
        status = get(server, f"/api/submissions/{submission_id}").json()
        if status["status"] in final:
            return status
        if time.monotonic() > deadline:
            raise AssertionError(f"submission {submission_id} still {status['status']} after {timeout} s: "
                                 f"{json.dumps(status)[:2000]}")
        time.sleep(0.2)


def table_rows(server: Server, table: str) -> list[dict[str, Any]]:
    """Every row of a table, read straight from the server's database."""
    from sqlalchemy import text

    from mewa_bench.service.db import make_engine
    from mewa_bench.service.settings import Settings

    engine = make_engine(Settings(server.data_dir, server.db).database_url)
    try:
        with engine.connect() as connection:
            return [dict(r._mapping) for r in connection.execute(text(f"SELECT * FROM {table} ORDER BY id"))]
    finally:
        engine.dispose()


PACED_AGENT = '''"""Random play, reseeded per unit, sleeping `delay` seconds per act: a run long enough to interrupt or to stop the database under."""
import time

import numpy as np


class Agent:
    def __init__(self, observation_space, action_space, delay="0"):
        self.delay, self.rng = float(delay), np.random.default_rng(0)

    def reset_task(self, seed=None):
        self.rng = np.random.default_rng(seed)

    def act(self, observation):
        time.sleep(self.delay)
        return int(self.rng.integers(0, 4))
'''
