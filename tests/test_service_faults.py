"""The service under faults, through the real API and real processes: the data dir's disk full (a small tmpfs), the
database stopped mid-job (Debian's PostgreSQL, `-m immediate`), the server SIGKILLed between committing a submission
and answering it; and what an operator watches (`/api/live`, `/api/ready`, `/metrics`) equal to what the database
holds. Each fault has a control that shows it happened (the 507s, the 503s, the dead server)."""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import tarfile
import time
from pathlib import Path

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from service_harness import (CLI, PACED_AGENT, RANDOM_AGENT, Server, get, post_agent, post_results, postgres,  # noqa: F401
                             require_sandbox, small_filesystem, table_rows, wait_status)

from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.results import results_text
from mewa_bench.protocol.runner import evaluate
from mewa_bench.service.faults import CRASH_VARIABLE
from mewa_bench.service.storage import free_bytes

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
MiB = 1 << 20


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> list[bytes]:
    """Four distinct runs of the random agent on narrow-v1, seeds 0 and 1, as results files' bytes."""
    folder = tmp_path_factory.mktemp("fault-runs")
    made = []
    for i in range(4):
        config = EvalConfig(RANDOM_AGENT, seeds=(0, 1), name=f"random-{i}", agent_args={"seed": str(3000 + i)},
                            isolated=False, out=folder / f"run-{i}.json")
        made.append(results_text(evaluate(config)[0]).encode())
    return made


def metrics(server: Server) -> dict[tuple[str, tuple], float]:
    """`/metrics` read with prometheus_client's own parser: {(sample name, sorted labels): value}."""
    answer = get(server, "/metrics")
    assert answer.status_code == 200 and answer.headers["content-type"].startswith("text/plain"), answer.text
    return {(sample.name, tuple(sorted(sample.labels.items()))): sample.value
            for family in text_string_to_metric_families(answer.text) for sample in family.samples}


def _checkpoint(files: int) -> tuple[str, bytes]:
    """A .tar.gz of `files` small files."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        for i in range(files):
            info = tarfile.TarInfo(f"weights/part-{i}.bin")
            info.size = 100
            tar.addfile(info, io.BytesIO(bytes(100)))
    return "weights.tar.gz", buffer.getvalue()


def _stored(data: Path) -> list[str]:
    """Every file under the data dir's uploads/ and every folder in its agents/ and staging/, relative to it."""
    uploads = data / "uploads"
    return sorted(p.relative_to(data).as_posix() for p in [*(uploads / "agents").glob("*"),
                                                          *(uploads / "staging").glob("*"), *uploads.rglob("*")]
                  if p.is_file() or p.parent.name in ("agents", "staging"))


def _fill(path: Path, size: int) -> None:
    """A file of `size` bytes, allocated (tmpfs counts allocated pages)."""
    with open(path, "wb") as f:
        os.posix_fallocate(f.fileno(), 0, size)


def _inodes_used_up(folder: Path) -> list[Path]:
    """Empty files made until the file system has no inode left; returns them."""
    folder.mkdir()
    made = []
    while True:
        try:
            path = folder / str(len(made))
            path.touch()
            made.append(path)
        except OSError as e:
            assert e.errno == 28, e  # ENOSPC
            return made


def test_a_full_disk_is_a_507_before_anything_is_written_and_reads_go_on(tmp_path, runs) -> None:
    with small_filesystem(tmp_path / "disk", size_mb=24, inodes=300) as disk:
        data = disk / "data"
        server = Server(data, None, "--workers", "0", "--seeds", "2", "--no-hidden", "--reserve-mb", "4")
        server.log = tmp_path / "server.log"  # off the full disk
        server.start()
        try:
            token = server.token("fay")
            first = post_results(server, token, runs[0])
            assert first.status_code == 202, first.text  # the control: uploads are stored while there is room
            stored = _stored(data)

            filler = disk / "filler"  # the disk fills: 1 MiB short of the reserve
            _fill(filler, free_bytes(data) - 3 * MiB)
            refused = [post_results(server, token, runs[1]), post_agent(server, token, RANDOM_AGENT, name="full"),
                       post_results(server, token, runs[1])]
            free = free_bytes(data)
            for answer in refused:
                assert answer.status_code == 507 and answer.json()["error"] == "storage_full", answer.text
                assert f"{free:,} bytes free" in answer.json()["detail"] and "4,194,304 kept in reserve" in \
                       answer.json()["detail"]
            assert _stored(data) == stored  # nothing written
            assert get(server, "/api/leaderboards/narrow-v1").status_code == 200  # reads go on
            assert get(server, f"/api/submissions/{first.json()['id']}").json()["status"] == "queued"
            assert get(server, "/leaderboards/narrow-v1").status_code == 200
            ready = get(server, "/api/ready")
            assert ready.status_code == 503 and "below the reserve" in ready.json()["checks"]["disk"], ready.text
            assert ready.json()["checks"]["database"] == "ok" and get(server, "/api/live").status_code == 200
            log = server.log.read_text()
            assert log.count("storage full") == 1, log  # once for the episode, not per request

            filler.unlink()  # space again: the same upload goes through, and the log says so once
            second = post_results(server, token, runs[1])
            assert second.status_code == 202, second.text
            assert server.log.read_text().count("storage available again") == 1
            assert get(server, "/api/ready").status_code == 200

            stored = _stored(data)  # out of space midway: no inode left, though the bytes are free
            made = _inodes_used_up(disk / "inodes")
            answer = post_results(server, token, runs[2])
            assert answer.status_code == 507 and answer.json()["error"] == "storage_full", answer.text
            for path in made[-3:]:  # room for the archive and two folders, not for the checkpoint's files
                path.unlink()
            answer = post_agent(server, token, RANDOM_AGENT, name="unpacked", checkpoint=_checkpoint(20))
            assert answer.status_code == 507 and answer.json()["error"] == "storage_full", answer.text
            assert _stored(data) == stored  # no partial file left: no temp file, no half-unpacked agent
            assert server.log.read_text().count("storage full") == 2  # a second episode
            for path in made[:-3]:
                path.unlink()
            third = post_results(server, token, runs[2])
            assert third.status_code == 202, third.text
            samples = metrics(server)
            assert samples[("mewa_rejections_total", (("reason", "storage_full"), ("status", "507")))] == 5
            assert samples[("mewa_submissions", (("kind", "results"),))] == 3
        finally:
            server.stop()


def test_metrics_equal_the_database_and_a_resend_after_a_kill_gets_the_first_answer(tmp_path, runs) -> None:
    server = Server(tmp_path / "data", None, "--workers", "1", "--seeds", "2", "--no-hidden", "--max-results-mb", "1",
                    "--lease-seconds", "5").start()
    try:
        token = server.token("gus")
        keyed = {"Authorization": f"Bearer {token}", "Idempotency-Key": "first-upload"}
        files = {"file": ("r.json", runs[0], "application/json")}
        url = server.url + "/api/submissions/results"
        first = httpx.post(url, files=files, headers=keyed, timeout=60)
        assert first.status_code == 202, first.text
        again = httpx.post(url, files=files, headers=keyed, timeout=60)
        assert again.status_code == 200 and again.json()["id"] == first.json()["id"] and again.json()["resent"]
        # the rejections the metrics must count: a replay without the key, the key on the other endpoint, a bad key,
        # an oversized upload, an unknown token
        assert post_results(server, token, runs[0]).status_code == 409
        other = httpx.post(server.url + "/api/submissions/agent", headers=keyed, timeout=60,
                           files={"agent": ("a.py", RANDOM_AGENT.read_bytes(), "text/x-python")})
        assert other.status_code == 422 and other.json()["error"] == "idempotency_key_reused", other.text
        bad_key = httpx.post(url, files=files, headers={**keyed, "Idempotency-Key": "two words"}, timeout=60)
        assert bad_key.status_code == 400 and bad_key.json()["error"] == "invalid_idempotency_key"
        assert post_results(server, token, b" " * (MiB + 1)).status_code == 413
        assert post_results(server, "mewa_not-a-token", runs[1]).status_code == 401
        second = post_results(server, token, runs[1])
        assert second.status_code == 202
        for answer in (first, second):
            assert wait_status(server, answer.json()["id"], timeout=120)["status"] == "done"

        samples = metrics(server)
        jobs, submissions = table_rows(server, "jobs"), table_rows(server, "submissions")
        for state in ("queued", "running", "done", "rejected", "failed"):
            assert samples[("mewa_jobs", (("state", state),))] == sum(j["state"] == state for j in jobs)
        assert samples[("mewa_submissions", (("kind", "results"),))] == len(submissions) == 2
        assert samples[("mewa_job_attempts_total", ())] == sum(j["attempts"] for j in jobs) == 2
        assert samples[("mewa_job_infra_retries_total", ())] == sum(j["infra_retries"] for j in jobs) == 0
        assert samples[("mewa_job_duration_seconds_count", (("kind", "score"),))] == 2
        durations = sum(j["finished"] - j["started"] for j in jobs)
        assert samples[("mewa_job_duration_seconds_sum", (("kind", "score"),))] == pytest.approx(durations)
        assert samples[("mewa_upload_bytes_count", (("kind", "results"),))] == 2
        assert samples[("mewa_upload_bytes_sum", (("kind", "results"),))] == len(runs[0]) + len(runs[1])
        rejected = {dict(labels)["reason"]: (dict(labels)["status"], value) for (name, labels), value in samples.items()
                    if name == "mewa_rejections_total"}
        assert rejected == {"replayed": ("409", 1), "idempotency_key_reused": ("422", 1),
                            "invalid_idempotency_key": ("400", 1), "too_large": ("413", 1), "invalid_token": ("401", 1)}
        assert samples[("mewa_database_up", ())] == 1 and samples[("mewa_workers_alive", ())] == 1
        ready = get(server, "/api/ready")
        assert ready.status_code == 200 and ready.json()["checks"] == {"database": "ok", "disk": "ok", "workers": "ok"}

        # the server dies (SIGKILL) after committing an upload and before answering it; `submit` resends it with its
        # key until the restarted server answers: the submission the first send made, stored once
        server.stop()
        server.env[CRASH_VARIABLE] = "results-committed"
        server.start()
        upload = tmp_path / "run-2.json"
        upload.write_bytes(runs[2])
        client = subprocess.Popen([*CLI, "submit", str(upload), "--server", server.url, "--token", token],
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert server.process.wait(60) == -9  # the control: it died at the crash point
        server.process = None
        del server.env[CRASH_VARIABLE]
        server.start()
        out, _ = client.communicate(timeout=180)
        assert client.returncode == 0, out
        rows = [s for s in table_rows(server, "submissions") if s["agent_name"] == "random-2"]
        assert len(rows) == 1 and rows[0]["idempotency_key"].startswith("mewa-")
        assert re.search(rf"submission\s+{rows[0]['id']}\s+accepted", out) and "had arrived before" in out, out
        assert wait_status(server, rows[0]["id"], timeout=120)["status"] == "done"
    finally:
        server.stop()


def _children(pid: int) -> set[int]:
    """The pids of a process's children."""
    found = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout.split()
    return {int(p) for p in found}


def test_a_database_outage_mid_job_costs_no_attempt_and_no_worker(tmp_path, postgres) -> None:  # noqa: F811
    require_sandbox()
    if postgres is None:
        pytest.skip("PostgreSQL is not installed (set MEWA_REQUIRE_POSTGRES=1 to fail instead)")
    server = Server(tmp_path / "data", postgres.new_database(), "--workers", "2", "--seeds", "2", "--no-hidden",
                    "--max-attempts", "1", "--lease-seconds", "4", "--log-level", "info").start()
    try:
        token = server.token("hal")
        agent = tmp_path / "paced.py"
        agent.write_text(PACED_AGENT)
        answer = post_agent(server, token, agent, name="paced", agent_args={"delay": "0.001"})
        assert answer.status_code == 202, answer.text
        submission = answer.json()["id"]
        deadline = time.monotonic() + 120
        while (job := get(server, f"/api/submissions/{submission}").json()["jobs"][0])["units_done"] < 1:
            assert time.monotonic() < deadline and job["state"] in ("queued", "running"), job
            time.sleep(0.2)
        workers = _children(server.process.pid)

        postgres.stop()  # mid-job, for about 8 s
        stopped = time.monotonic()
        status = get(server, f"/api/submissions/{submission}")
        assert status.status_code == 503 and status.json()["error"] == "database_unavailable", status.text
        assert status.headers["retry-after"] == "5"
        upload = post_results(server, token, b"{}")
        assert upload.status_code == 503 and upload.json()["error"] == "database_unavailable", upload.text
        ready = get(server, "/api/ready")
        assert ready.status_code == 503 and ready.json()["checks"]["database"].startswith("unreachable"), ready.text
        assert get(server, "/api/live").status_code == 200
        assert metrics(server)[("mewa_database_up", ())] == 0
        time.sleep(max(0.0, 8.0 - (time.monotonic() - stopped)))
        postgres.start_again()

        status = wait_status(server, submission, timeout=300)
        job = status["jobs"][0]
        assert status["status"] == "done" and job["attempts"] == 1, status  # done once, on its one allowed attempt
        (row,) = [j for j in table_rows(server, "jobs") if j["submission_id"] == submission]
        assert row["infra_retries"] == 0 and "lease expired" not in (row["note"] or "")
        assert len([e for e in table_rows(server, "entries") if e["submission_id"] == submission]) == 1
        assert _children(server.process.pid) == workers  # no worker exited and was replaced
        log = server.log.read_text()
        assert "the database is unreachable" in log and "exited with" not in log, log[-3000:]
    finally:
        server.stop()


def test_leases_lapsed_in_a_gap_wait_for_their_worker_and_infrastructure_retries_are_capped(tmp_path) -> None:
    from mewa_bench.service.db import make_engine, migrate, session_factory, transaction
    from mewa_bench.service.jobs import add_job, claim, hand_back, renew, requeue_expired
    from mewa_bench.service.models import Job, Submission, Token

    engine = make_engine(f"sqlite:///{tmp_path / 'queue.db'}")
    migrate(engine)
    sessions = session_factory(engine)
    with transaction(sessions) as s:
        s.add(Token(name="q", token_hash="0" * 64, created=0.0, revoked=False))
        s.flush()
        for i in range(3):
            s.add(Submission(token_id=1, kind="results", suite="narrow-v1", digest=f"{i:064d}", agent_name="a",
                             agent_sha256="0" * 64, file="x", created=0.0))
            s.flush()
            add_job(s, i + 1, "score", "narrow-v1", False, (0,), max_attempts=2)
    t = 1000.0
    lease = 4.0  # reaper rounds every second: more than 2 s without any contact is a gap
    early = claim(sessions, "a", lease, now=t)  # its worker dies: the lease lapses at t + 4, contacts go on
    held = claim(sessions, "b", lease, now=t + 1)  # its worker survives the outage to come: lease until t + 5
    assert [requeue_expired(sessions, now=t + k, lease_seconds=lease) for k in (2, 3, 4, 4.5)] == [0, 0, 0, 1]
    # nobody reaches the database from t + 4.5 to t + 15 (an outage): b's lease lapses at t + 5, inside the gap
    assert requeue_expired(sessions, now=t + 15, lease_seconds=lease) == 0  # a fresh worker leaves it to b ...
    assert renew(sessions, held.id, "b", lease)  # ... which renews it
    with transaction(sessions) as s:  # had b died in the gap instead, its job is re-queued a lease after the gap
        s.get(Job, held.id).lease_expires = t + 5
    assert [requeue_expired(sessions, now=t + k, lease_seconds=lease) for k in (17, 18, 19.5)] == [0, 0, 1]
    with sessions() as s:
        assert [s.get(Job, i).state for i in (early.id, held.id)] == ["queued", "queued"]

    for n in (1, 2):  # infrastructure hand-backs: no attempt counted, up to the cap, then failed saying so
        job = claim(sessions, "c", lease, now=t + 100 * n)
        assert job.id == early.id and job.attempts == 2
        assert hand_back(sessions, job.id, "c", "OperationalError: connection refused", max_infra_retries=2) == "queued"
        with sessions() as s:
            row = s.get(Job, job.id)
            assert (row.state, row.attempts, row.infra_retries) == ("queued", 1, n)
            assert f"infrastructure retry {n} of 2" in row.note
    job = claim(sessions, "c", lease, now=t + 300)
    assert hand_back(sessions, job.id, "c", "OperationalError: connection refused", max_infra_retries=2) == "failed"
    with sessions() as s:
        row = s.get(Job, job.id)
        assert (row.state, row.attempts, row.infra_retries) == ("failed", 1, 3)
        assert row.error.startswith("the service gave up: 3 infrastructure faults stopped this job")
    engine.dispose()
