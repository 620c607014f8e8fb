"""Load on `mewa-bench serve`: 200 concurrent results uploads and 20 agent submissions against a local server.

The server is started here (`mewa-bench serve`, SQLite in a temp data dir, or `--db URL` for PostgreSQL)
with `--workers` evaluation workers and boards ranked with `--seeds` seeds. Twenty submitters each get
a token (made straight in the database before the clock) and send their share of the load, all at once.

- Results uploads: distinct runs, since the server refuses the same episodes under another name as a
  replay: the shipped narrow-v1 results files (every agent in submissions/) cut to the board's seeds and
  scored again (`protocol.results.finish`, as `evaluate` does), then runs of the random agent with its
  agent arg `seed` = 1000, 1001, ... (evaluated here, in-process, before the clock starts).
- Agent submissions: submissions/random/agent.py with its agent arg `seed` = 2000..2019 (distinct submissions:
  the replay check hashes the agent file, its args and the suite), evaluated in the sandbox on narrow-v1
  (and on its hidden twin with `--hidden`).

Then it waits until every submission is final and checks that each was stored and scored exactly once:
one submission row and one stored file per upload, its jobs all done, one board entry per job and none
else, each re-scored upload's scores equal to those `finish` wrote, every status done in the API, and a
replayed upload (also under another agent name) refused with 409, and `/metrics` (read with prometheus_client's
parser) counting the jobs by state, the submissions, the attempts and the accepted uploads as the database
holds them. It prints throughput and p50/p95 latency of the uploads (until
accepted, and until scored) and of the agent evaluations (until accepted, and until done).

    .venv/bin/python benchmarks/service_load.py [--uploads 200] [--agents 20] [--seeds 4] [--workers 2] [--db URL]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mewa_bench.design.suites import load_suite
from mewa_bench.files import json_text
from mewa_bench.protocol.results import finish, read_results, results_text

REPO = Path(__file__).resolve().parents[1]
AGENT = REPO / "submissions" / "random" / "agent.py"
SUITE = "narrow-v1"
SUBMITTERS = 20
CLI = [str(Path(sys.executable).with_name("mewa-bench"))]
POLL_SECONDS = 0.25
FINAL = ("done", "rejected", "failed")


@dataclass
class Sent:
    """One submission as the client saw it: when it was sent, answered, and seen final."""

    kind: str
    name: str
    token: str
    sent: float = 0.0
    answered: float = 0.0
    status_code: int = 0
    submission_id: int | None = None
    final: float | None = None
    final_status: str | None = None
    expected_scores: dict[str, Any] | None = None
    body: bytes = b""
    agent_args: dict[str, str] = field(default_factory=dict)
    busy: int = 0  # 503 answers (the server receiving its limit of submissions at once), each retried
    resets: int = 0  # connections the server closed before answering, each retried


# -- the load --------------------------------------------------------------------------------------
def base_results(seeds: int) -> list[dict[str, Any]]:
    """Every shipped narrow-v1 results file, cut to seeds 0..seeds-1 and scored again."""
    suite = load_suite(SUITE)
    out = []
    for path in sorted((REPO / "submissions").glob(f"*/results-{SUITE}.json")):
        results = read_results(path)
        results["units"] = [u for u in results["units"] if u["seed"] < seeds]
        results["seeds"] = list(range(seeds))
        out.append(finish(results, suite))
    return out


def random_runs(count: int, seeds: int, scratch: Path) -> list[dict[str, Any]]:
    """`count` runs of the random agent, each with its own `seed` arg (so its own episodes)."""
    from mewa_bench.protocol.config import EvalConfig
    from mewa_bench.protocol.runner import evaluate

    return [evaluate(EvalConfig(agent_path=AGENT, suite=SUITE, seeds=tuple(range(seeds)), name=f"random-{1000 + i}",
                                agent_args={"seed": str(1000 + i)}, isolated=False, out=scratch / f"run-{i}.json"))[0]
            for i in range(count)]


def results_uploads(count: int, seeds: int, tokens: list[str], scratch: Path) -> list[Sent]:
    """`count` distinct results uploads (shipped runs, then random-agent runs), spread over the tokens."""
    runs = base_results(seeds)[:count]
    runs += random_runs(count - len(runs), seeds, scratch)
    uploads = []
    for i, results in enumerate(runs):
        name = f"{results['agent']['name']}-load-{i:03d}"
        renamed = {**results, "agent": {**results["agent"], "name": name}}
        uploads.append(Sent("results", name, tokens[i % len(tokens)], body=results_text(renamed).encode(),
                            expected_scores=results["scores"]))
    return uploads


def agent_submissions(count: int, tokens: list[str]) -> list[Sent]:
    """`count` distinct agent submissions: the random agent with its `seed` arg 2000..2000+count-1 (never the
    shipped random run's seed 0, whose results are among the uploads: the same run twice is one row)."""
    return [Sent("agent", f"random-load-{i:02d}", tokens[i % len(tokens)], agent_args={"seed": str(2000 + i)})
            for i in range(count)]


async def send(client: Any, url: str, item: Sent, jitter: random.Random) -> None:
    """POST one submission (again after Retry-After, with jitter, while the server is busy) and note when it was
    answered."""
    headers = {"Authorization": f"Bearer {item.token}"}
    item.sent = time.perf_counter()
    import httpx

    while True:
        try:
            if item.kind == "results":
                response = await client.post(f"{url}/api/submissions/results", headers=headers,
                                             files={"file": (f"{item.name}.json", item.body, "application/json")})
            else:
                data = {"suite": SUITE, "name": item.name,
                        "agent_arg": [f"{k}={v}" for k, v in item.agent_args.items()]}
                response = await client.post(f"{url}/api/submissions/agent", headers=headers, data=data,
                                             files={"agent": (AGENT.name, AGENT.read_bytes(), "text/x-python")})
        except (httpx.ReadError, httpx.WriteError, httpx.RemoteProtocolError):
            item.resets += 1
            await asyncio.sleep(jitter.uniform(0.2, 1.0))
            continue
        if response.status_code != 503:
            break
        item.busy += 1
        await asyncio.sleep(float(response.headers.get("retry-after", "1")) * jitter.uniform(0.2, 1.0))
    item.answered = time.perf_counter()
    item.status_code = response.status_code
    if response.status_code == 202:
        item.submission_id = response.json()["id"]
    else:
        print(f"  {item.kind} {item.name}: HTTP {response.status_code} {response.text[:300]}", file=sys.stderr)


async def watch(client: Any, url: str, items: list[Sent], timeout: float) -> None:
    """Poll the submissions list until every accepted submission is final; note when each became final."""
    by_id = {i.submission_id: i for i in items if i.submission_id is not None}
    deadline = time.perf_counter() + timeout
    while any(i.final is None for i in by_id.values()):
        if time.perf_counter() > deadline:
            left = sum(1 for i in by_id.values() if i.final is None)
            raise TimeoutError(f"{left} submissions still not final after {timeout:.0f} s")
        now = time.perf_counter()
        for s in (await client.get(f"{url}/api/submissions", params={"limit": 500})).json():
            item = by_id.get(s["id"])
            if item is not None and item.final is None and s["status"] in FINAL:
                item.final, item.final_status = now, s["status"]
        await asyncio.sleep(POLL_SECONDS)


async def run_load(url: str, items: list[Sent], timeout: float) -> tuple[float, float]:
    """Fire every submission at once, then watch them; returns (start, end of the burst)."""
    import httpx

    limits = httpx.Limits(max_connections=len(items) + 10, max_keepalive_connections=len(items) + 10)
    async with httpx.AsyncClient(limits=limits, timeout=timeout) as client:
        start = time.perf_counter()
        jitter = random.Random(0)
        await asyncio.gather(*(send(client, url, item, jitter) for item in items))
        burst_end = time.perf_counter()
        await watch(client, url, items, timeout)
    return start, burst_end


# -- the baseline: the same work in this process, without a server, a database or a sandbox ----------
@dataclass(frozen=True)
class Baseline:
    """Seconds per item of the work behind each submission, done in this process one at a time."""

    check: float  # the API's checks of a results upload (parse, schema, suite hash, units)
    score: float  # a worker's re-scoring of an upload
    evaluate: float  # `evaluate` of the random agent (isolated, not sandboxed) on the board's seeds, and its scoring


def measure_baseline(uploads: list[Sent], seeds: int, scratch: Path, sample: int = 9) -> Baseline:
    """Time the checks and re-scoring of `sample` uploads and one evaluation of the agent."""
    from mewa_bench.leaderboard.validate import SuiteCache
    from mewa_bench.protocol.config import EvalConfig
    from mewa_bench.protocol.runner import evaluate
    from mewa_bench.service.scoring import score_upload
    from mewa_bench.service.settings import Settings
    from mewa_bench.service.uploads import check_results, parse_results

    settings, suites = Settings(scratch / "baseline", seeds=seeds), SuiteCache()
    chosen = uploads[1:sample + 1]
    score_upload(parse_results(uploads[0].body), tuple(range(seeds)), 0)  # imports, caches
    start = time.perf_counter()
    checked = [check_results(u.body, settings, suites) for u in chosen]
    check = (time.perf_counter() - start) / len(chosen)
    start = time.perf_counter()
    for u, c in zip(chosen, checked):  # as a worker does: the stored bytes parsed again, then re-scored
        score_upload(parse_results(u.body), c.seeds, 0)
    score = (time.perf_counter() - start) / len(chosen)
    start = time.perf_counter()
    evaluate(EvalConfig(agent_path=AGENT, suite=SUITE, seeds=tuple(range(seeds)), out=scratch / "baseline.json",
                        agent_args={"seed": "0"}))
    return Baseline(check, score, time.perf_counter() - start)


# -- the server ------------------------------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(data_dir: Path, db: str | None, port: int, args: argparse.Namespace) -> subprocess.Popen:
    """`mewa-bench serve` in its own process group, once it answers /api/health."""
    import httpx

    command = [*CLI, "serve", "--data-dir", str(data_dir), "--port", str(port), "--workers", str(args.workers),
               "--seeds", str(args.seeds), "--log-level", "warning", "--hidden" if args.hidden else "--no-hidden"]
    if db:
        command += ["--db", db]
    log = open(data_dir.parent / "server.log", "w")
    process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                               env={**os.environ, "OMP_NUM_THREADS": "1"})
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"the server exited with {process.returncode}: see {log.name}")
        try:
            if httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=5).status_code == 200:
                return process
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise RuntimeError("the server did not answer within 120 s")


def stop_server(process: subprocess.Popen) -> None:
    """SIGTERM (the server stops its workers), SIGKILL of the group if it does not stop."""
    process.send_signal(signal.SIGTERM)
    try:
        process.wait(60)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait(30)


def make_tokens(data_dir: Path, db: str | None, count: int) -> list[str]:
    """`count` submitters' tokens, made in the database (the server's defaults as their limits)."""
    from mewa_bench.service.db import make_engine, session_factory, transaction
    from mewa_bench.service.settings import Settings
    from mewa_bench.service.tokens import create_token

    engine = make_engine(Settings(data_dir, db).database_url)
    try:
        with transaction(session_factory(engine)) as session:
            return [create_token(session, f"submitter-{i:02d}") for i in range(count)]
    finally:
        engine.dispose()


# -- the checks ------------------------------------------------------------------------------------
def tables(data_dir: Path, db: str | None) -> dict[str, list[dict[str, Any]]]:
    """The service's tables, read straight from its database."""
    from sqlalchemy import text

    from mewa_bench.service.db import make_engine
    from mewa_bench.service.settings import Settings

    engine = make_engine(Settings(data_dir, db).database_url)
    try:
        with engine.connect() as connection:
            return {t: [dict(r._mapping) for r in connection.execute(text(f"SELECT * FROM {t} ORDER BY id"))]
                    for t in ("submissions", "jobs", "entries")}
    finally:
        engine.dispose()


GAVE_WAY = re.compile(r"its row gave way to submission (\d+)")


def check_exactly_once(items: list[Sent], data_dir: Path, db: str | None, boards_per_agent: int) -> list[str]:
    """Every submission stored once and scored once; returns the problems found (none: all good)."""
    problems = []
    rows = tables(data_dir, db)
    submissions = {s["id"]: s for s in rows["submissions"]}
    accepted = [i for i in items if i.submission_id is not None]
    if len(accepted) != len(items):
        problems.append(f"{len(items) - len(accepted)} of {len(items)} submissions were not accepted")
    if sorted(submissions) != sorted(i.submission_id for i in accepted):
        problems.append(f"{len(submissions)} submission rows for {len(accepted)} accepted submissions")
    jobs_of: dict[int, list[dict]] = {}
    for job in rows["jobs"]:
        jobs_of.setdefault(job["submission_id"], []).append(job)
    entries_of_job: dict[int, list[dict]] = {}
    for entry in rows["entries"]:
        entries_of_job.setdefault(entry["job_id"], []).append(entry)
    # An upload whose run the server then evaluated itself (the shipped random agent's results are what the
    # server's evaluation of random with seed 0 plays) gives its row way: one row per run, the server's.
    superseded = {j["id"]: int(m.group(1)) for j in rows["jobs"] if (m := GAVE_WAY.search(j["note"] or ""))}
    boards_of = {(e["submission_id"], e["board"]) for e in rows["entries"]}
    for item in accepted:
        row = submissions.get(item.submission_id)
        if row is None or row["agent_name"] != item.name or row["kind"] != item.kind:
            problems.append(f"submission {item.submission_id} ({item.name}): row missing or not this upload: {row}")
            continue
        if not (data_dir / row["file"]).is_file():
            problems.append(f"submission {item.submission_id}: its file {row['file']} is missing")
        jobs = jobs_of.get(item.submission_id, [])
        if len(jobs) != (1 if item.kind == "results" else boards_per_agent):
            problems.append(f"submission {item.submission_id}: {len(jobs)} jobs")
        for job in jobs:
            entries = entries_of_job.get(job["id"], [])
            if job["id"] in superseded:
                if job["state"] != "done" or entries or (superseded[job["id"]], job["board"]) not in boards_of:
                    problems.append(f"job {job['id']} of submission {item.submission_id} gave way to submission "
                                    f"{superseded[job['id']]}, which has no row on {job['board']}")
                continue
            if job["state"] != "done" or len(entries) != 1:
                problems.append(f"job {job['id']} of submission {item.submission_id}: {job['state']}, "
                                f"{len(entries)} board entries, error {job['error']}")
            elif item.expected_scores is not None and json.loads(entries[0]["scores"]) != item.expected_scores:
                problems.append(f"submission {item.submission_id}: the server's scores differ from finish()'s")
        if item.final_status != "done":
            problems.append(f"submission {item.submission_id} ({item.name}) ended {item.final_status}")
    if len(rows["entries"]) != sum(len(j) for j in jobs_of.values()) - len(superseded):
        problems.append(f"{len(rows['entries'])} board entries for {sum(len(j) for j in jobs_of.values())} jobs, "
                        f"{len(superseded)} of which gave way")
    stored = len(list((data_dir / "uploads" / "results").glob("*.json")))
    agents = len(list((data_dir / "uploads" / "agents").iterdir())) if (data_dir / "uploads" / "agents").exists() else 0
    want_results = sum(1 for i in accepted if i.kind == "results")
    if (stored, agents) != (want_results, len(accepted) - want_results):
        problems.append(f"{stored} results files and {agents} agent folders stored for {want_results} and "
                        f"{len(accepted) - want_results} accepted submissions")
    return problems


def metrics_agree(url: str, items: list[Sent], data_dir: Path, db: str | None) -> list[str]:
    """`/metrics` against the database (jobs by state, submissions, attempts) and the accepted uploads (count and
    bytes); returns the differences."""
    import httpx
    from prometheus_client.parser import text_string_to_metric_families

    text = httpx.get(f"{url}/metrics", timeout=60).text
    samples = {(s.name, tuple(sorted(s.labels.items()))): s.value
               for family in text_string_to_metric_families(text) for s in family.samples}
    rows = tables(data_dir, db)
    expected = {("mewa_submissions", (("kind", kind),)): sum(r["kind"] == kind for r in rows["submissions"])
                for kind in ("results", "agent")}
    for state in FINAL + ("queued", "running"):
        expected[("mewa_jobs", (("state", state),))] = sum(j["state"] == state for j in rows["jobs"])
    expected[("mewa_job_attempts_total", ())] = sum(j["attempts"] for j in rows["jobs"])
    uploads = [i for i in items if i.kind == "results" and i.submission_id is not None]
    expected[("mewa_upload_bytes_count", (("kind", "results"),))] = len(uploads)
    expected[("mewa_upload_bytes_sum", (("kind", "results"),))] = sum(len(i.body) for i in uploads)
    return [f"/metrics {name}{dict(labels)} = {samples.get((name, labels))}, expected {value}"
            for (name, labels), value in expected.items() if samples.get((name, labels)) != value]


def replay_is_refused(url: str, item: Sent) -> bool:
    """Posting an accepted upload again, as it was and under another agent name, answers 409 naming it."""
    import httpx

    results = json.loads(item.body)
    renamed = {**results, "agent": {**results["agent"], "name": "someone-else"}}
    for body in (item.body, json_text(renamed).encode()):
        response = httpx.post(f"{url}/api/submissions/results", headers={"Authorization": f"Bearer {item.token}"},
                              files={"file": ("again.json", body, "application/json")}, timeout=120)
        if not (response.status_code == 409 and f"submission {item.submission_id}" in response.json()["detail"]):
            return False
    return True


# -- the report ------------------------------------------------------------------------------------
def latency_line(label: str, seconds: list[float]) -> str:
    p50, p95 = np.percentile(seconds, [50, 95])
    return f"{label:<44}{p50:>9.2f}{p95:>9.2f}{max(seconds):>9.2f}"


def report(items: list[Sent], start: float, burst_end: float, base: Baseline, workers: int) -> None:
    uploads = [i for i in items if i.kind == "results" and i.final is not None]  # the accepted ones
    agents = [i for i in items if i.kind == "agent" and i.final is not None]
    print(f"\n{'':<44}{'p50 s':>9}{'p95 s':>9}{'max s':>9}")
    print(latency_line(f"results upload, sent -> 202 ({len(uploads)})", [i.answered - i.sent for i in uploads]))
    print(latency_line("results upload, sent -> scored", [i.final - i.sent for i in uploads]))
    if agents:
        print(latency_line(f"agent submission, sent -> 202 ({len(agents)})", [i.answered - i.sent for i in agents]))
        print(latency_line("agent submission, sent -> evaluated", [i.final - i.sent for i in agents]))
    accepted_by = max(i.answered for i in uploads) - start
    scored_by = max(i.final for i in uploads) - start
    accept_rate, score_rate = len(uploads) / accepted_by, len(uploads) / scored_by
    busy = sum(i.busy for i in items)
    print(f"\nburst: {len(items)} requests answered in {burst_end - start:.2f} s ({busy} busy answers (503) retried "
          f"by {sum(1 for i in items if i.busy)} of them: the server receives a few submissions at once; "
          f"{sum(i.resets for i in items)} connections reset and retried)")
    print(f"{'throughput':<44}{'measured':>12}{'baseline':>12}{'ratio':>8}")
    print(f"{'results uploads accepted/s (API: 1 process)':<44}{accept_rate:>12.1f}{1 / base.check:>12.1f}"
          f"{accept_rate * base.check:>8.2f}")
    print(f"{f'results uploads scored/s ({workers} workers)':<44}{score_rate:>12.1f}{workers / base.score:>12.1f}"
          f"{score_rate * base.score / workers:>8.2f}")
    if agents:
        agents_by = max(i.final for i in agents) - start
        label = f"agents evaluated/min ({workers} workers)"
        print(f"{label:<44}{len(agents) / agents_by * 60:>12.1f}{workers / base.evaluate * 60:>12.1f}"
              f"{len(agents) / agents_by * base.evaluate / workers:>8.2f}")
    work = len(uploads) * base.score + len(agents) * base.evaluate  # seconds, one job at a time in this process
    all_done = max(i.final for i in uploads + agents) - start
    print(f"{'every job done in s (work / workers)':<44}{all_done:>12.1f}{work / workers:>12.1f}"
          f"{work / workers / all_done:>8.2f}")
    print(f"(the workers take jobs oldest first, so uploads and agents share them: each rate's baseline assumes the "
          f"workers did nothing else. Baseline: one at a time in this process, {base.check * 1000:.0f} ms to check an "
          f"upload, {base.score * 1000:.0f} ms to re-score one, {base.evaluate:.2f} s to evaluate the agent unsandboxed)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--uploads", type=int, default=200, help="concurrent results uploads")
    parser.add_argument("--agents", type=int, default=20, help="concurrent agent submissions")
    parser.add_argument("--seeds", type=int, default=4, help="seeds the boards rank with (units = 16 x seeds)")
    parser.add_argument("--workers", type=int, default=2, help="the server's evaluation workers")
    parser.add_argument("--hidden", action="store_true", help="evaluate the agents on the hidden twin too")
    parser.add_argument("--db", default=None, help="a PostgreSQL URL (default: SQLite in a temp data dir)")
    parser.add_argument("--timeout", type=float, default=900.0, help="give up after this many seconds")
    args = parser.parse_args()

    root = Path(tempfile.mkdtemp(prefix="mewa-service-load-"))
    data_dir, port = root / "data", free_port()
    tokens_wanted = min(SUBMITTERS, max(args.uploads, args.agents, 1))
    server = start_server(data_dir, args.db, port, args)
    try:
        tokens = make_tokens(data_dir, args.db, tokens_wanted)
        print(f"building {args.uploads} results files ({args.seeds} seeds, {16 * args.seeds} units each) ...")
        items = results_uploads(args.uploads, args.seeds, tokens, root) + agent_submissions(args.agents, tokens)
        base = measure_baseline(items, args.seeds, root)
        url = f"http://127.0.0.1:{port}"
        print(f"server: {url}, {'database ' + args.db.split('@')[-1] if args.db else 'SQLite'}, {args.workers} "
              f"worker(s); {len(tokens)} submitters; firing {args.uploads} uploads + {args.agents} agents at once")
        try:
            start, burst_end = asyncio.run(run_load(url, items, args.timeout))
        except TimeoutError:
            print(f"server log and data kept in {root}", file=sys.stderr)
            raise
        report(items, start, burst_end, base, args.workers)
        problems = check_exactly_once(items, data_dir, args.db, 2 if args.hidden else 1)
        problems += metrics_agree(url, items, data_dir, args.db)
        uploads = [i for i in items if i.kind == "results" and i.submission_id is not None]
        if uploads and not replay_is_refused(url, uploads[0]):
            problems.append("a replayed upload was not refused with 409")
        if not problems and check_exactly_once(items, data_dir, args.db, 2 if args.hidden else 1):
            problems.append("the replayed upload changed the tables")
    finally:
        stop_server(server)
    if problems:
        print(f"\nFAILED: {len(problems)} problem(s); server log and data in {root}")
        for p in problems[:30]:
            print(f"  - {p}")
        sys.exit(1)
    print(f"\nexactly once: {len(items)} submissions, each stored once (one row, one file) and scored once "
          f"(its jobs done, one board entry per job but where an upload's run gave way to the server's own "
          f"evaluation of it, re-scored uploads equal to finish()'s scores); replay refused; /metrics equal to the "
          f"database")
    shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
