"""The service's workers on a real server (SQLite and PostgreSQL): agent submissions evaluated in the sandbox on
public and hidden suites with `evaluate`'s scores, hostile agents, the job queue, and faults (a worker killed
mid-job, the server killed mid-upload or before a job ran): nothing lost, nothing half-written, nothing twice."""

from __future__ import annotations

import html
import io
import json
import multiprocessing
import os
import re
import shutil
import signal
import socket
import subprocess
import tarfile
import time
from pathlib import Path

import httpx
import pytest
from service_harness import (AGENTS, BACKENDS, BACKENDS_POSTGRES_SLOW, CLI, PACED_AGENT, RANDOM_AGENT, Server,
                             database_url, get, post_agent, post_results, postgres, require_sandbox, table_rows,
                             wait_status)

from mewa_bench.files import json_text
from mewa_bench.protocol.results import read_results, results_text
from mewa_bench.service.faults import CRASH_VARIABLE

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


HIDDEN = "narrow-v1-hidden"
PACED_ARGS = {"delay": "0.0005"}


@pytest.fixture(scope="session")
def hidden_dir(tmp_path_factory) -> Path:
    """A data dir's hidden/ folder with narrow-v1-hidden generated once (about 10 s), copied into each server's."""
    from mewa_bench.service.hidden import hidden_suites

    data = tmp_path_factory.mktemp("hidden-source")
    hidden_suites(data, [HIDDEN])
    return data / "hidden"


def new_server(tmp_path_factory, backend: str, postgres, hidden_dir: Path | None, *options: str) -> Server:
    db = database_url(backend, postgres)
    data = tmp_path_factory.mktemp(f"jobs-{backend}") / "data"
    if hidden_dir is not None:
        shutil.copytree(hidden_dir, data / "hidden")
    else:
        options = (*options, "--no-hidden")
    return Server(data, db, "--seeds", "2", *options).start()


def evaluate_cli(tmp_path: Path, agent: Path, suite: str | Path, *args: str) -> dict:
    """`mewa-bench evaluate` on seeds 0 and 1: the scores the service must reproduce."""
    out = tmp_path / f"evaluate-{agent.stem}-{Path(str(suite)).stem}.json"
    subprocess.run([*CLI, "evaluate", str(agent), "--suite", str(suite), "--seeds", "2", "--out", str(out), *args],
                   check=True, capture_output=True, timeout=600)
    return read_results(out)


@pytest.fixture(scope="session")
def references(tmp_path_factory, hidden_dir) -> dict[str, dict]:
    """`mewa-bench evaluate` of the random agent on narrow-v1 and on its hidden twin, and of the paced agent."""
    folder = tmp_path_factory.mktemp("references")
    paced = folder / "paced.py"
    paced.write_text(PACED_AGENT)
    return {"public": evaluate_cli(folder, RANDOM_AGENT, "narrow-v1"),
            "hidden": evaluate_cli(folder, RANDOM_AGENT, hidden_dir / f"{HIDDEN}.json"),
            "paced": evaluate_cli(folder, paced, "narrow-v1", *[f"--agent-arg={k}={v}" for k, v in PACED_ARGS.items()])}


@pytest.mark.parametrize("backend", BACKENDS_POSTGRES_SLOW)
def test_agent_scores_on_public_and_hidden_boards_equal_evaluate(backend, tmp_path_factory, postgres, hidden_dir,
                                                                 references) -> None:
    require_sandbox()
    server = new_server(tmp_path_factory, backend, postgres, hidden_dir, "--workers", "2")
    try:
        token = server.token("carol")
        answer = post_agent(server, token, RANDOM_AGENT, "narrow-v1", name="random")
        assert answer.status_code == 202, answer.text
        public, hidden = references["public"], references["hidden"]  # the server's hidden suite is this one
        status = wait_status(server, answer.json()["id"], timeout=300)
        assert status["status"] == "done", status
        assert [(j["board"], j["hidden"]) for j in status["jobs"]] == [("narrow-v1", False), (HIDDEN, True)]
        assert json_text(status["scores"]["narrow-v1"]) == json_text(public["scores"])  # byte for byte
        withheld = ("units", "control_variates", "comparisons")  # publicly: nothing that counts the hidden pairs
        assert json_text(status["scores"][HIDDEN]) == json_text({k: v for k, v in hidden["scores"].items()
                                                                  if k not in withheld})
        shown = status["jobs"][1]
        assert (shown["units_done"], shown["units_total"], shown["resumed_units"], shown["progress"]) == \
            (None, None, None, 1.0)
        page = get(server, f"/submissions/{answer.json()['id']}")
        assert page.status_code == 200 and f'<tr data-board="{HIDDEN}" data-mean=' in page.text
        full = admin_view(server, answer.json()["id"])  # the admin sees every byte
        assert json_text(full["scores"][HIDDEN]) == json_text(hidden["scores"])
        assert full["jobs"][1]["units_total"] == full["jobs"][1]["units_done"] == hidden["scores"]["units"]
        board = get(server, f"/api/leaderboards/{HIDDEN}").json()
        assert board["hidden"] and board["suite"] is None and board["public_twin"] == "narrow-v1"
        assert [r["name"] for r in board["rows"] if r["kind"] == "agent"] == ["random"]
        listed = {b["board"]: b for b in get(server, "/api/leaderboards").json()}
        assert listed[HIDDEN]["hidden"] and listed[HIDDEN]["entries"] == 1 and listed["narrow-v1"]["entries"] == 1
        assert get(server, f"/api/suites/{HIDDEN}").status_code == 404
        again = post_agent(server, token, RANDOM_AGENT, "narrow-v1", name="random")
        assert again.status_code == 409 and again.json()["error"] == "replayed"
    finally:
        server.stop()


def every_job_final(server: Server, submission_id: int, timeout: float = 300.0) -> dict:
    """A submission's status once each of its jobs is final (it is rejected as soon as one of them is)."""
    deadline = time.monotonic() + timeout
    while True:
        status = get(server, f"/api/submissions/{submission_id}").json()
        if all(j["state"] in ("done", "rejected", "failed") for j in status["jobs"]):
            return status
        assert time.monotonic() < deadline, f"submission {submission_id}'s jobs are not final: {status['jobs']}"
        time.sleep(0.2)


def admin_view(server: Server, submission_id: int) -> dict:
    """`mewa-bench serve show ID`: the whole record, as the server's admin sees it."""
    db = ["--db", server.db] if server.db else []
    shown = subprocess.run([*CLI, "serve", "show", str(submission_id), "--data-dir", str(server.data_dir), *db],
                           check=True, capture_output=True, text=True, timeout=120)
    return json.loads(shown.stdout)


def _archive(members: dict[str, bytes], links: tuple[str, ...] = ()) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
        for name in links:
            info = tarfile.TarInfo(name)
            info.type, info.linkname = tarfile.SYMTYPE, "/etc/passwd"
            tar.addfile(info)
    return buffer.getvalue()


CHECKPOINT_AGENT = '''"""Plays the action written in weights.json beside this file (its checkpoint)."""
import json
from pathlib import Path


class Agent:
    def __init__(self, observation_space, action_space):
        self.action = json.loads(Path(__file__).with_name("weights.json").read_text())["action"]

    def act(self, observation):
        return self.action
'''


def test_agent_uploads_are_checked_and_hostile_agents_fail_with_reasons(tmp_path_factory, tmp_path, postgres,
                                                                        hidden_dir) -> None:
    require_sandbox()
    server = new_server(tmp_path_factory, "sqlite", postgres, hidden_dir, "--workers", "2")
    try:
        token = server.token("mallory")
        bad = {"not-python.py": (b"def make_agent(:\n", "line 1"), "no-agent.py": (b"x = 1\n", "defines neither"),
               "latin.py": (b"\xff\xfe", "not UTF-8")}
        for name, (source, detail) in bad.items():
            path = tmp_path / name
            path.write_bytes(source)
            answer = post_agent(server, token, path)
            assert answer.status_code == 422 and detail in answer.json()["detail"], answer.text
        unknown = post_agent(server, token, RANDOM_AGENT, "narrow-v9", name="random")
        assert unknown.status_code == 422 and unknown.json()["error"] == "unknown_suite"
        agent = tmp_path / "constant.py"
        agent.write_text(CHECKPOINT_AGENT)
        for members, links, detail in (({"../weights.json": b"{}"}, (), "leaves the archive directory"),
                                       ({"agent.py": b"x"}, (), "would replace the agent file"),
                                       ({"weights.json": b"{}"}, ("link",), "is a link")):
            answer = post_agent(server, token, agent, checkpoint=("c.tar.gz", _archive(members, links)))
            assert answer.status_code == 422 and detail in answer.json()["detail"], answer.text
        assert post_agent(server, token, agent, checkpoint=("c.tar.gz", b"not a tar")).json()["error"] == "invalid_checkpoint"
        good = post_agent(server, token, agent, checkpoint=("c.tar.gz", _archive({"weights.json": b'{"action": 2}'})))
        assert good.status_code == 202, good.text

        hidden_file = server.data_dir / "hidden" / f"{HIDDEN}.json"
        reader = post_agent(server, token, AGENTS / "file_agent.py", name="reader",
                            agent_args={"path": str(hidden_file), "mode": "read"})
        network = post_agent(server, token, AGENTS / "network_agent.py", name="network", agent_args={"how": "python"})
        raw = post_agent(server, token, AGENTS / "network_agent.py", name="raw-network", agent_args={"how": "raw"})
        leaky = post_agent(server, token, AGENTS / "leaky_agent.py", name="leaky")
        for answer in (reader, network, raw, leaky):
            assert answer.status_code == 202, answer.text
        assert wait_status(server, good.json()["id"], timeout=300)["status"] == "done"
        read = every_job_final(server, reader.json()["id"])
        assert read["status"] == "rejected" and "sandbox rule broken (filesystem)" in read["reason"], read
        assert str(server.data_dir) not in read["reason"]
        if not read["jobs"][0]["error"].startswith("stopped: "):  # else the hidden job failed first: a coarse reason
            assert "<data dir>/hidden" in read["reason"], read["reason"]
        for answer in (network, raw):
            status = every_job_final(server, answer.json()["id"])
            assert status["status"] == "rejected", status
            if status["jobs"][0]["error"].startswith("stopped: "):  # the hidden job failed first: its coarse reason
                assert "on the hidden suite" in status["reason"] and "errno" not in status["reason"], status
            else:
                assert "network" in status["reason"].lower(), status
        hidden_read = every_job_final(server, reader.json()["id"])["jobs"][1]
        assert hidden_read["board"] == HIDDEN and hidden_read["error"] in (  # it failed too, or was stopped first
            "sandbox rule broken (filesystem) on the hidden suite (details of runs on a hidden suite are kept for "
            "the server's admin)", "stopped: the submission's job on narrow-v1 was rejected first"), hidden_read
        leaked = every_job_final(server, leaky.json()["id"])
        assert leaked["status"] == "rejected", leaked
        if leaked["jobs"][0]["error"].startswith("stopped: "):  # the hidden job failed first and ended the public one
            assert "LEAK" not in leaked["reason"] and "on the hidden suite" in leaked["reason"], leaked["reason"]
        else:
            assert "LEAK" in leaked["reason"]  # on the public suite: the whole text
        text = json.dumps(leaked["jobs"][1])
        assert "LEAK" not in text and "pair" not in text
        assert "the agent failed (exception) on the hidden suite" in text or \
            "stopped: the submission's job on narrow-v1 was rejected first" in text
        page = get(server, f"/submissions/{leaky.json()['id']}").text
        hidden_row = page.split(f'<tr data-board="{HIDDEN}"')[1].split("</tr>")[0]
        assert "LEAK" not in hidden_row and ("on the hidden suite" in hidden_row or "stopped: " in hidden_row)
        full = admin_view(server, leaky.json()["id"])["jobs"][1]  # the admin sees the whole text, if it ran
        assert full["error"] == "stopped: the submission's job on narrow-v1 was rejected first" or (
            full["error"].startswith("the agent failed (exception): agent ") and ", pair " in full["error"]
            and "LEAK [[" in full["error"]), full["error"]
        boards = {b["board"]: b["entries"] for b in get(server, "/api/leaderboards").json()}
        assert boards["narrow-v1"] == 1 and boards[HIDDEN] == 1  # only the good agent
    finally:
        server.stop()


def _job(server: Server, submission_id: int, board: str = "narrow-v1") -> dict:
    return next(j for j in table_rows(server, "jobs") if j["submission_id"] == submission_id and j["board"] == board)


def _units_on_disk(path: Path) -> int:
    try:
        return len(read_results(path)["units"])
    except ValueError:  # not written yet (ResultsError)
        return 0


def _paced_job_midway(server: Server, tmp_path: Path, user: str) -> tuple[int, Path]:
    """Submit the paced agent as `user` and wait until its job is running with some of its 32 units on disk;
    the submission id and the job's results file."""
    paced = tmp_path / "paced.py"
    paced.write_text(PACED_AGENT)
    answer = post_agent(server, server.token(user), paced, "narrow-v1", agent_args=PACED_ARGS)
    assert answer.status_code == 202, answer.text
    submission = answer.json()["id"]
    deadline = time.monotonic() + 120
    while (job := _job(server, submission))["state"] != "running" and time.monotonic() < deadline:
        time.sleep(0.05)
    results = server.data_dir / "jobs" / str(job["id"]) / "results.json"
    while not 0 < _units_on_disk(results) < 32 and time.monotonic() < deadline:
        time.sleep(0.05)
    return submission, results


@pytest.mark.parametrize("backend", BACKENDS_POSTGRES_SLOW)
def test_a_worker_killed_mid_job_resumes_from_its_last_finished_unit(backend, tmp_path_factory, tmp_path, postgres,
                                                                      references) -> None:
    require_sandbox()
    server = new_server(tmp_path_factory, backend, postgres, None, "--workers", "1", "--lease-seconds", "2")
    try:
        submission, results = _paced_job_midway(server, tmp_path, "dave")
        worker = int(_job(server, submission)["lease_owner"].split(":")[1])
        os.kill(worker, signal.SIGKILL)  # mid-job: some units are in the results file, the rest are not
        kept = _units_on_disk(results)
        assert 0 < kept < 32, kept
        reference = references["paced"]
        status = wait_status(server, submission, timeout=300)
        assert status["status"] == "done", status
        job = _job(server, submission)
        assert job["attempts"] == 2 and job["resumed_units"] == kept  # the second claim started after those units
        shown = status["jobs"][0]["note"]  # the reaper says what it did, on the status and on the page
        assert re.fullmatch(r"\S+ \S+ UTC: the worker's lease expired at \S+ \S+ UTC \(it crashed, was killed or "
                            r"stalled\); re-queued for attempt 2 of 3", shown), shown
        assert shown in html.unescape(get(server, f"/submissions/{submission}").text)
        finished = read_results(results)
        assert finished["units"] == reference["units"]  # the same as an uninterrupted run, each unit once
        assert json_text(status["scores"]["narrow-v1"]) == json_text(reference["scores"])
        assert [e["job_id"] for e in table_rows(server, "entries")] == [job["id"]]
    finally:
        server.stop()


def test_a_job_stopped_cleanly_goes_back_to_the_queue_and_resumes_after_restart(tmp_path_factory, tmp_path, postgres,
                                                                               references) -> None:
    require_sandbox()
    server = new_server(tmp_path_factory, "sqlite", postgres, None, "--workers", "1")
    try:
        submission, results = _paced_job_midway(server, tmp_path, "grace")
        server.stop()  # SIGTERM: the worker puts its job back (`jobs.release`) and keeps its finished units
        kept = _units_on_disk(results)
        job = _job(server, submission)
        assert 0 < kept < 32 and job["state"] == "queued" and job["attempts"] == 0, (kept, job)
        assert job["lease_owner"] is None and job["note"] is None  # a clean stop is not a lost lease
        server.start()
        status = wait_status(server, submission, timeout=300)
        assert status["status"] == "done", status
        job = _job(server, submission)
        assert job["attempts"] == 1 and job["resumed_units"] == kept  # one counted attempt, resumed after the units
        assert read_results(results)["units"] == references["paced"]["units"]
        assert json_text(status["scores"]["narrow-v1"]) == json_text(references["paced"]["scores"])
    finally:
        server.stop()


def _start_upload(server: Server, token: str, total: int) -> socket.socket:
    """A results upload that has sent its headers and half its body, then stalls."""
    boundary = "mewa-boundary"
    head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"r.json\"\r\n"
            f"Content-Type: application/json\r\n\r\n").encode()
    body_length = len(head) + total + len(f"\r\n--{boundary}--\r\n")
    connection = socket.create_connection(("127.0.0.1", server.port))
    connection.sendall((f"POST /api/submissions/results HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {token}\r\n"
                        f"Content-Type: multipart/form-data; boundary={boundary}\r\n"
                        f"Content-Length: {body_length}\r\n\r\n").encode() + head + b"{" + b" " * (total // 2))
    return connection


@pytest.mark.parametrize("backend", BACKENDS_POSTGRES_SLOW)
def test_server_killed_mid_upload_or_before_scoring_loses_nothing(backend, tmp_path_factory, postgres,
                                                                  references) -> None:
    server = new_server(tmp_path_factory, backend, postgres, None, "--workers", "1", "--lease-seconds", "2")
    try:
        token = server.token("erin")
        results = references["public"]
        stalled = _start_upload(server, token, 400_000)
        time.sleep(0.5)
        server.kill()  # the server and its worker, mid-upload
        stalled.close()
        assert table_rows(server, "submissions") == [] and table_rows(server, "jobs") == []
        server.start()
        assert not list((server.data_dir / "uploads" / "results").glob("*"))  # nothing half-written either

        answer = post_results(server, token, results_text(results).encode())
        assert answer.status_code == 202
        server.kill()  # accepted, and perhaps being scored: the row and its job survive
        server.start()
        status = wait_status(server, answer.json()["id"], timeout=120)
        assert status["status"] == "done" and json_text(status["scores"]["narrow-v1"]) == json_text(results["scores"])
        assert len(table_rows(server, "submissions")) == 1 and len(table_rows(server, "entries")) == 1
        server.stop()
        server.start()  # a clean stop and start changes nothing
        assert len(table_rows(server, "entries")) == 1 and get(server, "/api/leaderboards").json()[0]["entries"] == 1
    finally:
        server.stop()


def _crashed_upload(send) -> None:
    """An upload the server dies in (at its crash point): no answer comes."""
    with pytest.raises(httpx.HTTPError):
        send()


def _uploaded_files(server: Server) -> list[Path]:
    """The results files and agent folders in the data dir."""
    uploads = server.data_dir / "uploads"
    return sorted([*(uploads / "results").glob("*"), *(uploads / "agents").glob("*")])


@pytest.mark.parametrize("backend", BACKENDS_POSTGRES_SLOW)
def test_server_killed_between_storing_an_upload_and_committing_it_leaves_nothing(backend, tmp_path_factory,
                                                                                  postgres, references) -> None:
    server = new_server(tmp_path_factory, backend, postgres, None, "--workers", "1")
    server.stop()
    try:
        token = server.token("frank")
        data = results_text(references["public"]).encode()
        server.env = {CRASH_VARIABLE: "results-stored"}
        server.start()
        _crashed_upload(lambda: post_results(server, token, data))
        stored = _uploaded_files(server)
        assert len(stored) == 1 and stored[0].read_bytes() == data  # the file was whole on disk, its row never came
        assert table_rows(server, "submissions") == [] and table_rows(server, "jobs") == []
        server.kill()  # the rest of its process group (its worker)

        server.env = {CRASH_VARIABLE: "agent-stored"}
        server.start()  # alone on its data dir: the minutes-young orphan goes at once
        assert _uploaded_files(server) == []
        _crashed_upload(lambda: post_agent(server, token, AGENTS / "faulty_agent.py", name="crashed",
                                           agent_args={"fault": "raise"}))
        assert [p.parent.name for p in _uploaded_files(server)] == ["agents"]
        assert table_rows(server, "submissions") == []
        server.kill()

        server.env = {}
        server.start()
        assert _uploaded_files(server) == [] and table_rows(server, "submissions") == []
        assert not list((server.data_dir / "uploads" / "staging").glob("*"))
        answer = post_results(server, token, data)  # not a replay: nothing of the crashed upload remains
        assert answer.status_code == 202, answer.text
        status = wait_status(server, answer.json()["id"], timeout=120)
        assert status["status"] == "done" and json_text(status["scores"]["narrow-v1"]) == \
            json_text(references["public"]["scores"])
        assert len(table_rows(server, "submissions")) == 1 and len(_uploaded_files(server)) == 1
    finally:
        server.stop()


def _orphans(settings, now: float) -> dict[str, Path]:
    """Upload files of each kind, old (two minutes) or young (a second), with and without a row."""
    uploads = settings.uploads_dir
    files = {"kept-results": uploads / "results" / "a.json", "old-results": uploads / "results" / "b.json",
             "young-results": uploads / "results" / "c.json", "old-tmp": uploads / "results" / ".d.json.x.tmp",
             "kept-agent": uploads / "agents" / "u1" / "kept" / "agent.py",
             "old-agent": uploads / "agents" / "u2" / "lost" / "agent.py",
             "young-agent": uploads / "agents" / "u3" / "lost" / "agent.py",
             "old-staging": uploads / "staging" / "e.checkpoint"}
    for name, path in files.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(name)
        when = now - (1.0 if name.startswith("young") else 120.0)
        for touched in (path, path.parent, path.parent.parent):
            os.utime(touched, (when, when))
    return files


def _left(settings, files: dict[str, Path]) -> set[str]:
    """Which of `files` are still there."""
    return {name for name, path in files.items() if path.exists()}


def test_sweep_orphans_removes_rowless_uploads_older_than_its_age(tmp_path) -> None:
    from mewa_bench.service.settings import Settings
    from mewa_bench.service.uploads import ORPHAN_AGE, sweep_orphans

    settings = Settings(tmp_path / "data")
    now = time.time()
    files = _orphans(settings, now)
    referenced = {"uploads/results/a.json", "uploads/agents/u1/kept/agent.py"}
    removed = sweep_orphans(settings, referenced, now=now)
    assert ORPHAN_AGE > 1.0
    assert _left(settings, files) == {"kept-results", "young-results", "kept-agent", "young-agent"}
    assert sorted(p.as_posix() for p in removed) == ["uploads/agents/u2", "uploads/results/.d.json.x.tmp",
                                                     "uploads/results/b.json", "uploads/staging/e.checkpoint"]
    sweep_orphans(settings, referenced, now=now, min_age=0.0)  # no upload in flight: any age
    assert _left(settings, files) == {"kept-results", "kept-agent"}


def test_at_start_a_lone_api_process_sweeps_every_orphan_and_one_beside_others_only_old_ones(tmp_path) -> None:
    import fcntl

    from mewa_bench.service.server import prepare
    from mewa_bench.service.settings import Settings
    from mewa_bench.service.uploads import API_LOCK

    settings = Settings(tmp_path / "data")
    settings.data_dir.mkdir(parents=True)
    files = _orphans(settings, time.time())
    with open(settings.data_dir / API_LOCK, "a") as running:  # another API process serving this data dir
        fcntl.flock(running, fcntl.LOCK_SH)
        prepare(settings).close()
        assert _left(settings, files) == {"young-results", "young-agent"}  # maybe the other's uploads in flight
        lock = prepare(settings)
        try:  # a running API process holds the lock shared: a third one starting is not alone either
            with open(settings.data_dir / API_LOCK, "a") as probe:
                with pytest.raises(BlockingIOError):
                    fcntl.flock(probe, fcntl.LOCK_EX | fcntl.LOCK_NB)
        finally:
            lock.close()
    prepare(settings).close()  # alone: nothing can be in flight
    assert _left(settings, files) == set()


# -- the queue itself ------------------------------------------------------------------------------
def _claim_all(url: str, owner: str, out: multiprocessing.Queue) -> None:
    from mewa_bench.service.db import make_engine, session_factory, transaction
    from mewa_bench.service.jobs import claim, close

    engine = make_engine(url)
    sessions = session_factory(engine)
    claimed = []
    while (job := claim(sessions, owner, 30.0)) is not None:
        claimed.append(job.id)
        with transaction(sessions) as s:
            assert close(s, job.id, owner, "done")
    out.put(claimed)
    engine.dispose()


@pytest.mark.parametrize("backend", BACKENDS)
def test_queue_claims_each_job_once_and_expires_leases(backend, tmp_path, postgres) -> None:
    from mewa_bench.service.db import make_engine, migrate, session_factory, transaction
    from mewa_bench.service.jobs import add_job, claim, close, give_up_expired, renew, requeue_expired
    from mewa_bench.service.models import Submission, Token

    url = database_url(backend, postgres) or f"sqlite:///{tmp_path / 'queue.db'}"
    engine = make_engine(url)
    migrate(engine)
    sessions = session_factory(engine)
    with transaction(sessions) as s:
        s.add(Token(name="q", token_hash="0" * 64, created=0.0, revoked=False))
        s.flush()
        for i in range(60):
            sub = Submission(token_id=1, kind="results", suite="narrow-v1", digest=f"{i:064d}", agent_name="a",
                             agent_sha256="0" * 64, file="x", created=0.0)
            s.add(sub)
            s.flush()
            add_job(s, sub.id, "score", "narrow-v1", False, (0,), max_attempts=2)
    context = multiprocessing.get_context("spawn")
    out = context.Queue()
    workers = [context.Process(target=_claim_all, args=(url, f"w{i}", out)) for i in range(4)]
    for w in workers:
        w.start()
    claimed = [job for _ in workers for job in out.get(timeout=120)]
    for w in workers:
        w.join(60)
    assert sorted(claimed) == list(range(1, 61))  # every job once, none twice

    with transaction(sessions) as s:
        add_job(s, 1, "evaluate", "wide-v1", False, (0,), max_attempts=2)
    now = time.time()  # the clock is passed explicitly: the test does not depend on the machine's speed
    first = claim(sessions, "a", lease_seconds=10.0, now=now)
    for later in (3, 6):  # reapers reach the database every few seconds (a longer gap would delay reaping: below)
        requeue_expired(sessions, now=now + later, lease_seconds=10.0)
    assert first is not None and first.attempts == 1 and claim(sessions, "b", 10.0, now=now + 9) is None
    second = claim(sessions, "b", lease_seconds=10.0, now=now + 11)  # the lease expired: another worker takes it
    assert second is not None and second.id == first.id and second.attempts == 2
    with sessions() as s:
        from mewa_bench.service.jobs import utc_text
        from mewa_bench.service.models import Job

        note = s.get(Job, first.id).note
        assert note == (f"{utc_text(now + 11)}: the worker's lease expired at {utc_text(now + 10)} (it crashed, was "
                        f"killed or stalled); re-queued for attempt 2 of 2")
    assert not renew(sessions, first.id, "a", 10.0)  # the first owner can no longer touch it
    with transaction(sessions) as s:
        assert not close(s, first.id, "a", "done")
    later = now + 11 + 3600  # b stopped renewing long ago
    assert claim(sessions, "c", 10.0, now=later) is None  # two attempts were allowed
    # no process reached the database for an hour (as in an outage): a lease that lapsed in that gap waits a lease's
    # length for its worker to renew it, then it is given up
    assert give_up_expired(sessions, now=later, lease_seconds=10.0) == 0
    assert give_up_expired(sessions, now=later + 10, lease_seconds=10.0) == 1
    with sessions() as s:
        from mewa_bench.service.models import Job

        job = s.get(Job, first.id)
        assert job.state == "failed" and "gave up" in job.error
        assert s.get(Submission, 1).digest != f"{0:064d}"  # a failed upload gives its digest up ...
    with transaction(sessions) as s:  # ... so the same upload can come again
        s.add(Submission(token_id=1, kind="results", suite="narrow-v1", digest=f"{0:064d}", agent_name="a",
                         agent_sha256="0" * 64, file="x", created=0.0))
    engine.dispose()


@pytest.mark.parametrize("backend", BACKENDS)
def test_migrations_create_exactly_the_models(backend, tmp_path, postgres) -> None:
    from alembic.autogenerate import compare_metadata
    from alembic.runtime.migration import MigrationContext

    from mewa_bench.service.db import make_engine, migrate
    from mewa_bench.service.models import Base

    engine = make_engine(database_url(backend, postgres) or f"sqlite:///{tmp_path / 'm.db'}")
    migrate(engine)
    migrate(engine)  # idempotent
    with engine.connect() as connection:
        assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
    engine.dispose()
