"""Hostile submissions through the real API (`serve` with bubblewrap, SQLite, one worker): each ends contained, its
submission's reason naming the rule it broke, the worker alive, nothing stuck, no scratch directory left on disk, no
board entry of a rejected submission, and the server's log free of agent output. Then a fault: a worker killed while
its agent had planted modules in its scratch directory; the reaper re-queues the job on its timer, and the retried
attempt, in a fresh scratch directory, imports none of them.

The sandbox tests skip where bubblewrap cannot run, unless MEWA_REQUIRE_SANDBOX=1 (CI), where they fail."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import httpx
import pytest
from service_harness import (AGENTS, CLI, RANDOM_AGENT, REPO, Server, get, post_agent, post_results, require_sandbox,
                             table_rows, wait_status)

from mewa_bench.design.suites import load_suite
from mewa_bench.protocol.config import unit_seed

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
HIDDEN = "narrow-v1-hidden"
FINAL = ("done", "rejected", "failed")


@pytest.fixture(scope="module")
def hidden_dir(tmp_path_factory) -> Path:
    """A hidden/ folder with narrow-v1-hidden (generated once), copied into each server's data dir."""
    from mewa_bench.service.hidden import hidden_suites

    data = tmp_path_factory.mktemp("hidden-source")
    hidden_suites(data, [HIDDEN])
    return data / "hidden"


@pytest.fixture(scope="module")
def server(tmp_path_factory, hidden_dir):
    require_sandbox()
    data = tmp_path_factory.mktemp("hostile") / "data"
    shutil.copytree(hidden_dir, data / "hidden")
    running = Server(data, None, "--seeds", "1", "--workers", "1", "--job-seconds", "20", "--scratch-mb", "32",
                     "--memory-mb", "1024", "--lease-seconds", "5",
                     "--log-level", "info").start()  # the workers' job lines too: the log is checked for agent text
    yield running
    running.stop()


def all_final(server: Server, submission_id: int, timeout: float = 300.0) -> dict:
    """A submission's status once every one of its jobs is final."""
    deadline = time.monotonic() + timeout
    while True:
        status = get(server, f"/api/submissions/{submission_id}").json()
        if all(j["state"] in FINAL for j in status["jobs"]):
            return status
        assert time.monotonic() < deadline, f"submission {submission_id} is stuck: {status['jobs']}"
        time.sleep(0.3)


def scratch_left(server: Server) -> list[Path]:
    """Scratch directories still on disk."""
    return sorted(server.data_dir.glob("jobs/*/scratch*"))


def entries_of(server: Server, submission_id: int) -> list[dict]:
    """The board entries of a submission, straight from the database."""
    return [e for e in table_rows(server, "entries") if e["submission_id"] == submission_id]


def hidden_only_seeds(hidden_dir: Path) -> str:
    """The unit seeds of the hidden suite's units (seed 0), none of which is a public narrow-v1 unit's."""
    hidden, public = load_suite(hidden_dir / f"{HIDDEN}.json"), load_suite("narrow-v1")
    seeds = {unit_seed(hidden.sha256, pair, 0) for pair in range(len(hidden.pairs))}
    assert not seeds & {unit_seed(public.sha256, pair, 0) for pair in range(len(public.pairs))}
    return ",".join(str(s) for s in sorted(seeds))


SLOW_AGENT = '''"""Sleeps `delay` seconds in every act: each call within its limit, the run without end."""
import time


class Agent:
    def __init__(self, observation_space, action_space, delay="0"):
        self.delay = float(delay)

    def act(self, observation):
        time.sleep(self.delay)
        return 0
'''


def test_the_hostile_battery_ends_contained_with_reasons(server, hidden_dir, tmp_path) -> None:
    token, other = server.token("mallory"), server.token("bystander")
    slow = tmp_path / "slow.py"
    slow.write_text(SLOW_AGENT)
    commented = tmp_path / "random-again.py"
    commented.write_text(RANDOM_AGENT.read_text() + "\n# the same agent, one comment more\n")
    submitted = {
        "chatty": post_agent(server, token, AGENTS / "chatty_agent.py", name="chatty"),
        "memory": post_agent(server, token, AGENTS / "memory_children_agent.py", name="memory",
                             agent_args={"children": "3", "megabytes": "450"}),
        "scratch": post_agent(server, token, AGENTS / "file_agent.py", name="scratch",
                              agent_args={"path": "fill.bin", "mode": "write", "size": str(8 << 20), "copies": "8"}),
        "slow": post_agent(server, token, slow, name="slow", agent_args={"delay": "9"}),
        "random": post_agent(server, token, RANDOM_AGENT, name="random"),
        "commented": post_agent(server, token, commented, name="random-again"),
        "hidden-fault": post_agent(server, token, AGENTS / "seed_fault_agent.py", name="hidden-fault",
                                   agent_args={"bad": hidden_only_seeds(hidden_dir)}),
    }
    for name, answer in submitted.items():
        assert answer.status_code == 202, (name, answer.text)
    ids = {name: answer.json()["id"] for name, answer in submitted.items()}
    final = {name: all_final(server, i) for name, i in ids.items()}

    expected = {"memory": "sandbox rule broken (memory)", "scratch": "sandbox rule broken (scratch_size)",
                "slow": "sandbox rule broken (wall_time)", "commented": "replayed run",
                "hidden-fault": "the agent failed (exception) on the hidden suite"}
    for name, reason in expected.items():
        status = final[name]
        assert status["status"] == "rejected" and reason in status["reason"], (name, status)
        assert entries_of(server, ids[name]) == [], name  # no board keeps an entry of a rejected submission
        ended = ["done", "rejected"] if name == "hidden-fault" else ["rejected", "rejected"]  # its public job was done
        assert [j["state"] for j in status["jobs"]] == ended, (name, status["jobs"])
    assert "the sandbox's processes together reached its memory limit of 1 GiB" in final["memory"]["reason"]
    assert "stopped mid-call" in final["slow"]["reason"]  # 9-second calls, each within the call limit
    slow_jobs = final["slow"]["jobs"]  # the hidden twin ended with it, without running to its own end
    assert slow_jobs[1]["error"] == "stopped: the submission's job on narrow-v1 was rejected first"
    assert slow_jobs[0]["finished"] - slow_jobs[0]["started"] < 60
    assert "replayed run: these episodes are those of submission %d on narrow-v1" % ids["random"] \
        in final["commented"]["reason"]

    for name in ("chatty", "random"):
        assert final[name]["status"] == "done", final[name]
    board = get(server, "/api/leaderboards/narrow-v1").json()
    agents = sorted((r["name"], r["source"]) for r in board["rows"] if r["kind"] == "agent")
    assert agents == [("chatty", "server-evaluated"), ("random", "server-evaluated")], board["rows"]
    assert sorted(r["rank"] for r in board["rows"] if r["kind"] == "agent") == [1, 2]
    assert {r["source"] for r in board["rows"] if r["kind"] == "reference"} == {"reference"}
    assert [a["runs"] for a in board["algorithms"]] == [1, 1]  # each a one-run algorithm named after its agent
    hidden_board = get(server, f"/api/leaderboards/{HIDDEN}").json()
    assert hidden_board["algorithms"] == []  # cell fractions would tell its size
    assert hidden_board["gap_note"] is None

    output = httpx.get(f"{server.url}/api/submissions/{ids['chatty']}/output",
                       headers={"Authorization": f"Bearer {token}"}, timeout=60)
    assert output.status_code == 200, output.text
    public, hidden = output.json()["jobs"]
    text = public["attempts"][0]["output"]
    assert "CHATTY-FORGED-LINE" in text and "the agent's output was cut here, at its limit of 1048576 bytes" in text
    assert len(text.encode()) < (1 << 20) + 200
    assert hidden["attempts"] == [] and "kept for the server's admin" in hidden["withheld"]
    stranger = httpx.get(f"{server.url}/api/submissions/{ids['chatty']}/output",
                         headers={"Authorization": f"Bearer {other}"}, timeout=60)
    assert stranger.status_code == 404 and stranger.json()["error"] == "not_found"

    assert scratch_left(server) == []
    assert get(server, "/api/health").json()["jobs"].get("running", 0) == 0
    server_log = server.log.read_text(errors="replace")
    assert "CHATTY-FORGED-LINE" not in server_log  # the server's log has none of the agent's output,
    assert "the agent was told to fail on" not in server_log  # nor the text of its exceptions
    assert "rejected (AgentRejected; the reason is kept with the job)" in server_log
    assert server.process is not None and server.process.poll() is None


def test_a_privileged_agents_results_cannot_claim_to_be_ordinary(server) -> None:
    token = server.token("trudy")
    results = json.loads((REPO / "submissions" / "oracle-t-optimal" / "results-narrow-v1.json").read_text())
    results["agent"]["privileged"], results["agent"]["name"] = False, "definitely-not-an-oracle"
    answer = post_results(server, token, json.dumps(results).encode())
    assert answer.status_code == 422 and answer.json()["error"] == "privileged_agent", answer.text
    assert "is a privileged agent's" in answer.json()["detail"]


def test_uploads_beyond_the_bound_in_flight_get_a_503(tmp_path) -> None:
    server = Server(tmp_path / "data", None, "--workers", "0", "--uploads-in-flight", "1").start()
    try:
        token = server.token("uma")
        with httpx.Client(timeout=60) as client:
            def slow_body():
                yield b"--x\r\nContent-Disposition: form-data; name=\"file\"; filename=\"r.json\"\r\n\r\n"
                time.sleep(3)
                yield b"{}\r\n--x--\r\n"

            import threading

            first: list[httpx.Response] = []
            thread = threading.Thread(target=lambda: first.append(client.post(
                f"{server.url}/api/submissions/results", content=slow_body(),
                headers={"Authorization": f"Bearer {token}", "Content-Type": "multipart/form-data; boundary=x"})))
            thread.start()
            time.sleep(1)
            second = post_results(server, token, b"{}")
            thread.join()
        assert second.status_code == 503 and second.json()["error"] == "busy", second.text
        assert second.headers["retry-after"] == "1"
        assert first[0].status_code in (400, 422), first[0].text  # the first one was read and answered
        assert server.data_dir.stat().st_mode & 0o777 == 0o700
        assert (server.data_dir / "service.db").stat().st_mode & 0o777 == 0o600
    finally:
        server.stop()


def test_a_killed_workers_job_is_re_queued_on_a_timer_and_retried_in_a_fresh_scratch(tmp_path) -> None:
    require_sandbox()
    data = tmp_path / "data"
    server = Server(data, None, "--seeds", "1", "--workers", "0", "--no-hidden", "--lease-seconds", "2").start()
    worker_log = tmp_path / "worker.log"

    def start_worker() -> subprocess.Popen:
        with open(worker_log, "a") as log:
            return subprocess.Popen([*CLI, "serve", "worker", "--data-dir", str(data), "--lease-seconds", "2"],
                                    stdout=log, stderr=subprocess.STDOUT, start_new_session=True)

    worker = start_worker()
    try:
        answer = post_agent(server, server.token("peggy"), AGENTS / "planting_agent.py", name="planter",
                            agent_args={"delay": "0.001"})
        assert answer.status_code == 202, answer.text
        submission = answer.json()["id"]
        deadline = time.monotonic() + 120
        job = None
        while time.monotonic() < deadline:
            job = next(j for j in table_rows(server, "jobs") if j["submission_id"] == submission)
            scratch = data / "jobs" / str(job["id"]) / "scratch-1"
            if job["state"] == "running" and (scratch / "resource.py").exists() and job["units_done"] >= 1:
                break
            time.sleep(0.1)
        assert (scratch / "resource.py").exists() and (scratch / "mewa_bench" / "__init__.py").exists()
        os.killpg(worker.pid, signal.SIGKILL)  # the worker and its sandbox, mid-job
        worker.wait(30)
        deadline = time.monotonic() + 30  # no worker runs now: only the server's reaper can re-queue the job
        while (status := get(server, f"/api/submissions/{submission}").json())["jobs"][0]["state"] != "queued":
            assert time.monotonic() < deadline, status
            time.sleep(0.2)
        assert "re-queued for attempt 2 of 3" in status["jobs"][0]["note"]
        worker = start_worker()
        status = wait_status(server, submission, timeout=300)
        assert status["status"] == "done", status  # a planted module imported would have ended the agent process
        job = status["jobs"][0]
        assert job["attempts"] == 2 and job["resumed_units"] >= 1
        assert scratch_left(server) == []
        assert "planted" not in worker_log.read_text()
    finally:
        if worker.poll() is None:
            os.killpg(worker.pid, signal.SIGTERM)
            worker.wait(30)
        server.stop()
