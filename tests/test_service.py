"""The service's API on a real server (`mewa-bench serve`), on SQLite and on PostgreSQL: suites, boards,
datasets with HTTP Range, tokens, limits, and results uploads re-scored byte for byte as `evaluate` does."""

from __future__ import annotations

import copy
import hashlib
import json
import os
import subprocess
import sys
from typing import Callable

import httpx
import pytest
from service_harness import (AGENTS, BACKENDS, CLI, RANDOM_AGENT, Server, database_url, get, post_agent,
                             post_results, postgres, table_rows, wait_status)

from mewa_bench.design.suites import load_suite, shipped_path
from mewa_bench.files import json_text
from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.results import read_results, results_text
from mewa_bench.protocol.runner import evaluate

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


MAX_RESULTS_MB = 1
MAX_AGENT_MB = 0.05  # agent files and checkpoint archives: 52,428 bytes


@pytest.fixture(scope="module", params=BACKENDS)
def server(request, tmp_path_factory, postgres) -> Server:
    db = database_url(request.param, postgres)
    data = tmp_path_factory.mktemp(f"service-{request.param}") / "data"
    running = Server(data, db, "--seeds", "2", "--workers", "1", "--no-hidden", "--max-results-mb", str(MAX_RESULTS_MB),
                     "--max-agent-mb", str(MAX_AGENT_MB), "--max-checkpoint-mb", str(MAX_AGENT_MB),
                     "--lease-seconds", "5").start()
    running.backend = request.param
    yield running
    running.stop()


@pytest.fixture(scope="module")
def token(server) -> str:
    return server.token("alice")


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory) -> tuple[dict, bytes]:
    """A results file written by `mewa-bench evaluate` (the random agent, narrow-v1, seeds 0 and 1)."""
    out = tmp_path_factory.mktemp("evaluated") / "random-narrow-v1.json"
    subprocess.run([*CLI, "evaluate", str(RANDOM_AGENT), "--suite", "narrow-v1", "--seeds", "2",
                    "--out", str(out)], check=True, capture_output=True, timeout=300)
    return read_results(out), out.read_bytes()  # the file is schema 3: its units as columns


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Callable[[str], dict]:
    """`runs(label)`: a run of its own for each label (the random agent with another `seed` arg, so other
    episodes: not a replay of any other), evaluated in-process on the board's seeds, once per module."""
    made: dict[str, dict] = {}
    folder = tmp_path_factory.mktemp("runs")

    def run(label: str) -> dict:
        if label not in made:
            config = EvalConfig(RANDOM_AGENT, seeds=(0, 1), name=label, agent_args={"seed": str(1000 + len(made))},
                                isolated=False, out=folder / f"{label}.json")
            made[label] = evaluate(config)[0]
        return copy.deepcopy(made[label])
    return run


def variant(results: dict, name: str, change=lambda r: None) -> bytes:
    """The results under another agent name, changed by `change` (still the same run for the replay check)."""
    other = copy.deepcopy(results)
    other["agent"]["name"] = name
    change(other)
    return json_text({**other, "schema_version": 2}).encode()  # schema 2: the units as a JSON list


def test_api_describes_itself(server) -> None:
    paths = get(server, "/openapi.json").json()["paths"]
    for path in ("/api/suites", "/api/suites/{name}", "/api/suites/{name}/sha256", "/api/leaderboards",
                 "/api/leaderboards/{name}", "/api/datasets", "/api/datasets/{name}/{version}/archive",
                 "/api/submissions/results", "/api/submissions/agent", "/api/submissions/{submission_id}",
                 "/api/live", "/api/ready"):
        assert path in paths, path
    health = get(server, "/api/health").json()
    assert health["schema"] == "0005" and health["database"] == server.backend
    assert health["uploads_ranked"] is False and "sandbox" in health["sandbox_limits"]
    docs = get(server, "/docs")  # offline: no CDN, no script, every operation listed
    assert docs.status_code == 200 and "<script" not in docs.text and "cdn" not in docs.text.lower()
    assert 'data-path="/api/submissions/agent" data-method="post"' in docs.text


SECURITY = {"x-frame-options": "DENY", "x-content-type-options": "nosniff", "referrer-policy": "no-referrer"}


def test_every_answer_has_the_security_headers(server, token) -> None:
    answers = [get(server, "/"), get(server, "/docs"), get(server, "/api/health"), get(server, "/leaderboards/narrow-v1"),
               get(server, "/no/such/page"), get(server, "/api/submissions/99999"),
               post_results(server, token, b"{" * 10)]
    for answer in answers:
        assert {k: answer.headers.get(k) for k in SECURITY} == SECURITY, (answer.request.url, answer.headers)
        policy = answer.headers["content-security-policy"]
        assert "default-src 'none'" in policy and "frame-ancestors 'none'" in policy


@pytest.mark.parametrize("path", ["/api/submissions/100000000000000000000000", "/api/submissions/-1",
                                  "/api/submissions/0", "/submissions/100000000000000000000000",
                                  "/api/submissions/9223372036854775808"])
def test_ids_out_of_range_are_a_json_400(server, path) -> None:
    answer = get(server, path)
    assert answer.status_code == 400 and answer.headers["content-type"] == "application/json", answer.text
    assert answer.json()["error"] == "invalid_request" and "submission_id" in answer.json()["detail"]


@pytest.mark.parametrize("body, detail", [
    (b"[" * 100_000 + b"]" * 100_000, "nests arrays and objects more than 32 deep"),
    (b'{"agent": {"name": "x"}, "seeds": [100000000000000000000000]}', "the integer 100000000000000000000000 is out"),
    (b'{"n": ' + b"9" * 5000 + b"}", "is out of range"),
])
def test_hostile_json_is_a_json_400(server, token, body, detail) -> None:
    answer = post_results(server, token, body)
    assert answer.status_code == 400 and answer.json()["error"] == "invalid_json", answer.text
    assert detail in answer.json()["detail"]


def test_suites_list_download_and_hash(server) -> None:
    listed = {s["name"]: s for s in get(server, "/api/suites").json()}
    assert list(listed) == ["narrow-v1", "wide-v1", "narrow-v2", "wide-v2"]
    response = get(server, "/api/suites/narrow-v2")
    suite = load_suite("narrow-v2")
    assert response.content == shipped_path("narrow-v2").read_bytes()
    assert hashlib.sha256(response.content).hexdigest() == listed["narrow-v2"]["file_sha256"]
    assert response.headers["x-suite-sha256"] == suite.sha256 == listed["narrow-v2"]["sha256"]
    assert get(server, "/api/suites/narrow-v2/sha256").json()["sha256"] == suite.sha256
    assert listed["narrow-v2"]["seeds"] == 2 and listed["narrow-v2"]["pairs"] == len(suite.pairs)
    hidden = get(server, "/api/suites/narrow-v2-hidden")
    assert hidden.status_code == 404 and "never serves" in hidden.json()["detail"]
    assert get(server, "/api/suites/narrow-v9").json()["error"] == "not_found"


def test_results_upload_is_rescored_byte_for_byte(server, token, evaluated) -> None:
    results, data = evaluated
    answer = post_results(server, token, data)
    assert answer.status_code == 202, answer.text
    status = wait_status(server, answer.json()["id"])
    assert status["status"] == "done", status
    assert json_text(status["scores"]["narrow-v1"]) == json_text(results["scores"])  # the same bytes
    board = get(server, "/api/leaderboards/narrow-v1").json()
    row = next(r for r in board["rows"] if r["submission_id"] == answer.json()["id"])
    assert row["mean"] == results["scores"]["mean"]["mean"] and row["kind"] == "agent"
    assert row["source"] == "self-reported" and row["rank"] is None  # uploads are unranked unless --rank-uploads
    assert row["curve"] == [p["mean"] for p in results["scores"]["curve"]]
    assert {r["name"] for r in board["rows"] if r["kind"] == "reference"} >= {"best fixed policy", "random"}
    page = get(server, "/leaderboards/narrow-v1")  # the HTML page (service.web) shows the same row
    assert page.status_code == 200 and "random" in page.text
    entries = [e for e in table_rows(server, "entries") if e["submission_id"] == answer.json()["id"]]
    assert len(entries) == 1 and json.loads(entries[0]["scores"]) == results["scores"]


def _drop_unit(r: dict) -> None:
    del r["units"][3]


def _nan(r: dict) -> None:
    r["units"][0]["returns"][0] = float("nan")


def _tamper_normalised(r: dict) -> None:
    """A normalised return (and its score, to match) that is not its episode's return normalised."""
    r["units"][7]["normalised_returns"][4] += 0.01
    r["units"][7]["scores"][4] = r["units"][7]["normalised_returns"][4] / load_suite("narrow-v1").pairs[3].max_expected


def _own_luck(r: dict) -> None:
    """An episode played on an env seed of the run's own choosing, not the protocol's."""
    r["units"][5]["env_seeds"][3] = 12345


def _zero_steps(r: dict) -> None:
    """An episode of no steps."""
    r["units"][6]["lengths"][0] = 0


@pytest.mark.parametrize("name, change, status, error, detail", [
    ("no-units", lambda r: r.pop("units"), 422, "invalid_results", "missing field(s) units"),
    ("wrong-hash", lambda r: r["suite"].update(sha256="0" * 64), 422, "invalid_results",
     "is not the shipped narrow-v1's"),
    ("wrong-seeds", lambda r: r.update(seeds=[0, 5]), 422, "invalid_results", "ranked here with the seeds [0, 1]"),
    ("missing-unit", _drop_unit, 422, "invalid_results", "missing 1 of 32 units"),
    ("incomplete", lambda r: r.update(complete=False), 422, "invalid_results", "the run is incomplete"),
    ("unknown-suite", lambda r: r["suite"].update(name="narrow-v9"), 422, "unknown_suite", "not a public suite"),
    ("no-scores", lambda r: r["scores"].pop("raw"), 422, "invalid_results", "scores.raw.mean.mean is missing"),
    ("short-sha", lambda r: r["agent"].update(sha256="abc"), 422, "invalid_results", "agent.sha256 must be 64 hex"),
    ("renormalised", _tamper_normalised, 422, "invalid_results", "episode 4: normalised return"),
    ("own-luck", _own_luck, 422, "invalid_results", "episode 3: env seed 12345 is not the protocol's"),
    ("zero-steps", _zero_steps, 422, "invalid_results", "episode 0: length 0 is not a step count in 1.."),
])
def test_malformed_results_are_rejected_with_reasons(server, token, evaluated, name, change, status, error,
                                                     detail) -> None:
    answer = post_results(server, token, variant(evaluated[0], f"bad-{name}", change))
    assert answer.status_code == status, answer.text
    assert answer.json()["error"] == error and detail in answer.json()["detail"], answer.json()


def test_tampered_unit_columns_are_rejected(server, token, evaluated) -> None:
    raw = json.loads(evaluated[1])  # the schema-3 file as written: its units as columns
    column = raw["units"]["columns"]["returns"]
    text = column["xz_base64"]
    middle = len(text) // 2
    column["xz_base64"] = text[:middle] + ("A" if text[middle] != "A" else "B") + text[middle + 1:]
    answer = post_results(server, token, json_text({**raw, "agent": {**raw["agent"], "name": "bad-columns"}}).encode())
    assert answer.status_code == 422 and answer.json()["error"] == "invalid_results", answer.text
    detail = answer.json()["detail"]
    assert "results file: units column returns: " in detail and "damaged or edited" in detail, detail


def test_broken_and_oversized_uploads_are_rejected(server, token, evaluated) -> None:
    cases = [
        (b"{not json", 400, "invalid_json", "not valid JSON"),
        (json_text({**evaluated[0], "schema_version": 2}).encode().replace(b'"returns": [\n',
                                                                            b'"returns": [\n   NaN,\n', 1), 400,
         "invalid_json", "NaN is not a JSON number"),
        (b"", 400, "empty_upload", "is empty"),
        (b" " * (MAX_RESULTS_MB * 2**20 + 100), 413, "too_large", "limit of 1,048,576 bytes"),
        (b" " * (MAX_RESULTS_MB * 2**20 + 200_000), 413, "too_large", "larger than this endpoint's limit"),
    ]
    for data, status, error, detail in cases:
        answer = post_results(server, token, data)
        assert answer.status_code == status, answer.text
        assert answer.json()["error"] == error and detail in answer.json()["detail"], answer.json()
    missing = httpx.post(server.url + "/api/submissions/results", headers={"Authorization": f"Bearer {token}"},
                         data={"other": "x"}, timeout=60)
    assert missing.status_code == 400 and "file" in missing.json()["detail"], missing.text


def _tamper_mean(r: dict) -> None:
    r["scores"]["mean"]["mean"] += 0.01


def _tamper_episode(r: dict) -> None:
    r["units"][5]["scores"][2] += 0.01


@pytest.mark.parametrize("change, reason", [
    (_tamper_mean, "stored mean score 0.4"),
    (_tamper_episode, "episode 2: score is not normalised return / the pair's max-expected baseline"),
])
def test_tampered_results_are_rejected_after_rescoring(server, token, runs, change, reason) -> None:
    label = f"tampered-{change.__name__}"
    answer = post_results(server, token, variant(runs(label), label, change))
    assert answer.status_code == 202, answer.text  # the schema is fine: only re-scoring finds it
    status = wait_status(server, answer.json()["id"])
    assert status["status"] == "rejected" and reason in status["reason"], status
    assert status["scores"] == {} and status["jobs"][0]["state"] == "rejected"
    board = get(server, "/api/leaderboards/narrow-v1").json()
    assert answer.json()["id"] not in {r["submission_id"] for r in board["rows"]}


def _retime(r: dict) -> None:
    r["timing"].update(wall_time=123.0, finished="2031-01-01")


def _claim(r: dict) -> None:
    r["agent"].update(name="someone-else", sha256="1" * 64, agent_args={"seed": "7"})
    r["isolation"]["isolated"] = False


def _retouch(r: dict) -> None:
    r["scores"]["mean"]["low"] -= 1e-12  # an aggregate re-scoring does not compare; still the same episodes


def _relength(r: dict) -> None:
    """One episode's length changed to another valid step count: lengths are not scored, still the same run."""
    length = r["units"][2]["lengths"][1]
    r["units"][2]["lengths"][1] = length - 1 if length > 1 else length + 1


def test_replayed_uploads_are_rejected(server, token, runs) -> None:
    run = runs("replayed")
    data = results_text(run).encode()
    first = post_results(server, token, data)
    assert first.status_code == 202
    for copy_of_it in (data, variant(run, "replayed", _retime), variant(run, "another-name"),
                       variant(run, "replayed", _claim), variant(run, "replayed", _retouch),
                       variant(run, "replayed", _relength)):
        again = post_results(server, token, copy_of_it)
        assert again.status_code == 409 and again.json()["error"] == "replayed", again.text
        assert f"submission {first.json()['id']}" in again.json()["detail"]
    assert wait_status(server, first.json()["id"])["status"] == "done"
    assert sum(1 for s in table_rows(server, "submissions") if s["agent_name"] in ("replayed", "another-name")) == 1
    other = post_results(server, token, results_text(runs("not-a-replay")).encode())  # other episodes: another run
    assert other.status_code == 202, other.text


def test_a_rejected_upload_does_not_block_the_genuine_run(server, token, runs) -> None:
    run = runs("genuine")
    tampered = variant(run, "genuine", _tamper_mean)  # the same episodes, a false mean: the same digest
    first = post_results(server, token, tampered)
    assert first.status_code == 202, first.text
    assert wait_status(server, first.json()["id"])["status"] == "rejected"
    genuine = post_results(server, token, results_text(run).encode())
    assert genuine.status_code == 202, genuine.text
    assert wait_status(server, genuine.json()["id"])["status"] == "done"
    assert post_results(server, token, results_text(run).encode()).json()["error"] == "replayed"


def _widen_intervals(r: dict) -> None:
    """Every confidence bound and verdict flattered, every point estimate kept (they are all re-scoring compares)."""
    scores = r["scores"]
    estimates = [scores["mean"], scores["adaptability"], scores["iqm"], scores["skill"], *scores["curve"],
                 scores["raw"]["mean"], scores["raw"]["adaptability"], *scores["raw"]["curve"],
                 *(c["difference"] for c in scores["comparisons"].values())]
    for estimate in (e for e in estimates if isinstance(e, dict) and e.get("low") is not None):
        estimate.update(low=estimate["low"] + 0.5, high=estimate["high"] + 0.5)
    scores["verdicts"] = {verdict: True for verdict in scores["verdicts"]}
    for comparison in scores["comparisons"].values():
        if comparison["probability_of_improvement"] is not None:
            comparison["probability_of_improvement"].update(mean=1.0, low=1.0, high=1.0)


def test_the_board_keeps_the_servers_scores_not_the_submitted_intervals(server, token, runs) -> None:
    run = runs("flattered")  # a run of its own: the replay digest ignores aggregates
    answer = post_results(server, token, variant(run, "flattered", _widen_intervals))
    assert answer.status_code == 202, answer.text
    status = wait_status(server, answer.json()["id"])
    assert status["status"] in ("done", "rejected"), status
    if status["status"] == "done":  # accepted: what is stored is the recomputation, never the submitted aggregates
        recomputed = json_text(run["scores"])  # `evaluate`'s own scores of these episodes
        assert json_text(status["scores"]["narrow-v1"]) == recomputed
        entry = next(e for e in table_rows(server, "entries") if e["submission_id"] == answer.json()["id"])
        assert entry["scores"] == recomputed and json.loads(entry["row"])["mean_low"] == run["scores"]["mean"]["low"]
        board = get(server, "/api/leaderboards/narrow-v1").json()
        row = next(r for r in board["rows"] if r["submission_id"] == answer.json()["id"])
        assert (row["mean_low"], row["mean_high"]) == (run["scores"]["mean"]["low"], run["scores"]["mean"]["high"])
        assert row["curve_low"] == [p["low"] for p in run["scores"]["curve"]]
        assert row["adapts"] == run["scores"]["verdicts"]["adapts"]


def test_tokens_are_required_and_stored_hashed(server, token, runs) -> None:
    data = results_text(runs("tokens")).encode()
    assert post_results(server, None, data).json()["error"] == "missing_token"
    wrong = post_results(server, "mewa_not-a-token", data)
    assert wrong.status_code == 401 and wrong.json()["error"] == "invalid_token"
    rows = {r["name"]: r for r in table_rows(server, "tokens")}
    assert rows["alice"]["token_hash"] == hashlib.sha256(token.encode()).hexdigest()
    assert all(token not in json.dumps(r) for r in rows.values())
    bob = server.token("bob")
    db = ["--db", server.db] if server.db else []
    subprocess.run([*CLI, "serve", "token", "revoke", "bob", "--data-dir",
                    str(server.data_dir), *db], check=True, capture_output=True, timeout=120)
    assert post_results(server, bob, data).json()["error"] == "invalid_token"


def test_rate_limit_and_daily_quota_per_token(server, runs) -> None:
    hasty = server.token("hasty", rate_limit=2)
    codes = [post_results(server, hasty, b"{}").status_code for _ in range(3)]
    assert codes[:2] == [422, 422] and codes[2] == 429
    limited = post_results(server, hasty, b"{}")
    assert limited.json()["error"] == "rate_limited" and int(limited.headers["retry-after"]) >= 1
    frugal = server.token("frugal", daily_results=1)
    assert post_results(server, frugal, results_text(runs("quota-1")).encode()).status_code == 202
    over = post_results(server, frugal, results_text(runs("quota-2")).encode())
    assert over.status_code == 429 and over.json()["error"] == "quota_exceeded"
    assert "daily quota of 1 results submissions" in over.json()["detail"]


def test_oversized_agent_files_and_checkpoints_are_refused(server, token, tmp_path) -> None:
    limit = int(MAX_AGENT_MB * 2**20)
    big = tmp_path / "big_agent.py"
    big.write_text("class Agent:\n    pass\n" + "#" * limit)
    answer = post_agent(server, token, big)
    assert answer.status_code == 413 and answer.json()["error"] == "too_large", answer.text
    assert f"the agent file is larger than the limit of {limit:,} bytes" in answer.json()["detail"]
    archive = os.urandom(limit + 1)  # refused by size before anything looks inside it
    answer = post_agent(server, token, AGENTS / "class_agent.py", name="with-a-big-checkpoint",
                        checkpoint=("weights.tar.gz", archive))
    assert answer.status_code == 413 and answer.json()["error"] == "too_large", answer.text
    assert f"the checkpoint archive is larger than the limit of {limit:,} bytes" in answer.json()["detail"]
    assert not list((server.data_dir / "uploads" / "staging").glob("*"))  # the spooled part is not kept
    assert all(s["agent_name"] not in ("big_agent", "with-a-big-checkpoint") for s in table_rows(server, "submissions"))


def test_daily_agent_quota_per_token(server) -> None:
    frugal = server.token("frugal-agents", daily_agents=1)
    first = post_agent(server, frugal, AGENTS / "faulty_agent.py", name="quota-agent", agent_args={"fault": "raise"})
    assert first.status_code == 202, first.text  # it fails fast on the worker; it counts all the same
    over = post_agent(server, frugal, AGENTS / "faulty_agent.py", name="quota-agent-2", agent_args={"fault": "exit"})
    assert over.status_code == 429 and over.json()["error"] == "quota_exceeded", over.text
    assert "daily quota of 1 agent submissions" in over.json()["detail"]
    assert post_results(server, frugal, b"{}").status_code == 422  # results uploads keep their own quota
    wait_status(server, first.json()["id"], timeout=300)


def test_cli_submit_and_status(server, token, runs, tmp_path) -> None:
    path = tmp_path / "results.json"
    path.write_bytes(results_text(runs("from-the-cli")).encode())
    cli = CLI
    submitted = subprocess.run([*cli, "submit", str(path), "--server", server.url, "--token", token, "--wait",
                                "--timeout", "120"], capture_output=True, text=True, timeout=300,
                               env={"COLUMNS": "200", "PATH": "/usr/bin:/bin"})
    assert submitted.returncode == 0, submitted.stdout + submitted.stderr
    assert "accepted" in submitted.stdout and "done" in submitted.stdout
    submission = int(submitted.stdout.split("submission ")[1].split()[0])
    shown = subprocess.run([*cli, "status", str(submission), "--server", server.url], capture_output=True, text=True,
                           timeout=120, env={"COLUMNS": "200", "PATH": "/usr/bin:/bin"})
    assert shown.returncode == 0 and "narrow-v1" in shown.stdout and "done" in shown.stdout
    refused = subprocess.run([*cli, "submit", str(path), "--server", server.url, "--token", token],
                             capture_output=True, text=True, timeout=120, env={"COLUMNS": "200", "PATH": "/usr/bin:/bin"})
    assert refused.returncode == 1 and "HTTP 409" in refused.stdout and "already submitted" in refused.stdout


# -- datasets --------------------------------------------------------------------------------------
def test_dataset_archives_support_range_requests(server) -> None:
    catalog = get(server, "/api/datasets").json()
    entry = catalog["datasets"][0]
    assert entry["url"].startswith(server.url + "/api/datasets/")
    whole = get(server, entry["url"][len(server.url):])
    assert whole.status_code == 200 and len(whole.content) == entry["size"]
    assert hashlib.sha256(whole.content).hexdigest() == entry["sha256"] == whole.headers["x-content-sha256"]
    assert whole.headers["accept-ranges"] == "bytes"
    part = httpx.get(entry["url"], headers={"Range": "bytes=1000-1999"}, timeout=60)
    assert part.status_code == 206 and part.content == whole.content[1000:2000]
    assert part.headers["content-range"] == f"bytes 1000-1999/{entry['size']}"
    beyond = httpx.get(entry["url"], headers={"Range": f"bytes={entry['size'] + 10}-"}, timeout=60)
    assert beyond.status_code == 416 and beyond.headers["content-range"] == f"bytes */{entry['size']}"
    assert get(server, "/api/datasets/no-such-dataset/1.0.0/archive").json()["error"] == "unknown_dataset"


def test_datasets_download_from_a_server_resumes(server, tmp_path, monkeypatch) -> None:
    from mewa_bench.datasets.downloader import download, partial_path
    from mewa_bench.service.client import server_catalog

    monkeypatch.setenv("MEWA_CACHE_DIR", str(tmp_path / "cache"))
    catalog = server_catalog(server.url)
    entry = catalog["datasets"][0]
    archive = httpx.get(entry["url"], timeout=60).content
    half = len(archive) // 2
    partial_path(entry["sha256"]).write_bytes(archive[:half])  # what an interrupted download left
    calls = []
    got = download(entry["name"], catalog, tmp_path / "data", progress=lambda done, total: calls.append((done, total)))
    assert calls[0] == (half, len(archive)) and calls[-1] == (len(archive), len(archive))  # only the rest was fetched
    assert got.verified and got.sha256 == entry["sha256"] and (got.path / "meta" / "info.json").is_file()
    assert not partial_path(entry["sha256"]).exists()
    cli = subprocess.run([*CLI, "datasets", "download", entry["name"], "--server",
                          server.url, "--dir", str(tmp_path / "cli")], capture_output=True, text=True, timeout=300,
                         env={"COLUMNS": "200", "PATH": "/usr/bin:/bin", "MEWA_CACHE_DIR": str(tmp_path / "cache")})
    assert cli.returncode == 0 and "verified" in cli.stdout, cli.stdout + cli.stderr
    assert (tmp_path / "cli" / entry["name"] / "meta" / "info.json").is_file()


def test_the_command_line_does_not_load_the_web_stack() -> None:
    probe = ("import sys, mewa_bench.cli\nheavy = {'fastapi', 'starlette', 'sqlalchemy', 'alembic', 'uvicorn', 'httpx'}\n"
             "print(sorted({m.split('.')[0] for m in sys.modules} & heavy))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.strip() == "[]"


def test_every_command_that_opens_a_data_dir_makes_it_private(tmp_path) -> None:
    """`serve token create` (the README's first step) on a new or a loose data dir leaves it 0700, its database 0600."""
    loose = tmp_path / "loose"
    loose.mkdir(mode=0o755)
    os.chmod(loose, 0o755)
    for data in (tmp_path / "new" / "data", loose):
        made = subprocess.run([*CLI, "serve", "token", "create", "alice", "--data-dir", str(data)],
                              capture_output=True, text=True, timeout=120)
        assert made.returncode == 0, made.stderr
        assert data.stat().st_mode & 0o777 == 0o700, data
        assert (data / "service.db").stat().st_mode & 0o777 == 0o600, data


def test_an_unexpected_failure_is_a_json_500_with_the_security_headers(tmp_path, caplog) -> None:
    """A route that raises: the answer is the JSON 500 (no internals), with every security header, and the
    server's log keeps the traceback."""
    from starlette.testclient import TestClient

    from mewa_bench.service.app import create_app
    from mewa_bench.service.settings import Settings

    app = create_app(Settings(data_dir=tmp_path / "data", hidden=False))

    @app.get("/api/fail-for-the-test")
    def fail() -> None:
        raise RuntimeError("an internal detail the client must not see")

    with TestClient(app, raise_server_exceptions=False) as client:
        answer = client.get("/api/fail-for-the-test")
    assert answer.status_code == 500 and answer.json() == {"error": "internal",
                                                           "detail": "the server failed to answer this request"}
    assert {k: answer.headers.get(k) for k in SECURITY} == SECURITY
    assert "an internal detail" not in answer.text
    assert "an internal detail the client must not see" in caplog.text


def test_a_submitters_runs_of_one_algorithm_share_a_row_of_the_algorithms_table(server, token, runs, tmp_path) -> None:
    """Three uploads under the algorithm name "mine" (one through `submit`, named by the run.json beside it) make one
    row over three runs, whose mean is the runs' mean; another submitter's "mine" is a row of its own."""
    folder = tmp_path / "mine-seed1"
    folder.mkdir()
    (folder / "run.json").write_text(json.dumps({"algorithm": "mine", "seed": 1, "suite": "narrow-v1", "steps": 1}))
    path = folder / "results-narrow-v1.json"
    path.write_bytes(results_text(runs("mine-1")).encode())
    submitted = subprocess.run([*CLI, "submit", str(path), "--server", server.url, "--token", token, "--wait",
                                "--timeout", "120"], capture_output=True, text=True, timeout=300,
                               env={"COLUMNS": "200", "PATH": "/usr/bin:/bin"})
    assert submitted.returncode == 0 and "done" in submitted.stdout, submitted.stdout + submitted.stderr
    headers = {"Authorization": f"Bearer {token}"}
    for label in ("mine-2", "mine-3"):
        answer = httpx.post(server.url + "/api/submissions/results", data={"algorithm": "mine"}, headers=headers,
                            files={"file": ("r.json", results_text(runs(label)).encode(), "application/json")},
                            timeout=120)
        assert answer.status_code == 202, answer.text
        assert wait_status(server, answer.json()["id"])["status"] == "done"
    stranger = server.token("mallory-of-the-algorithms")
    answer = httpx.post(server.url + "/api/submissions/results", data={"algorithm": "mine"},
                        headers={"Authorization": f"Bearer {stranger}"},
                        files={"file": ("r.json", results_text(runs("not-mine")).encode(), "application/json")},
                        timeout=120)
    assert answer.status_code == 202 and wait_status(server, answer.json()["id"])["status"] == "done"
    bad = httpx.post(server.url + "/api/submissions/results", data={"algorithm": "no spaces <b>"}, headers=headers,
                     files={"file": ("r.json", results_text(runs("bad-name")).encode(), "application/json")},
                     timeout=120)
    assert bad.status_code == 422 and bad.json()["error"] == "invalid_algorithm", bad.text

    board = get(server, "/api/leaderboards/narrow-v1").json()
    rows = {r["algorithm"]: r for r in board["algorithms"]}
    mine = [r for name, r in rows.items() if name.startswith("mine")]
    assert len(mine) == 2, sorted(rows)  # ours and the stranger's, never merged
    ours = next(r for r in mine if r["runs"] == 3)
    other = next(r for r in mine if r["runs"] == 1)
    assert ours["source"] == "self-reported" and ours["rank"] is None  # uploads are unranked here
    assert "[submitter" in ours["algorithm"] and "[submitter" in other["algorithm"]
    expected = sum(runs(label)["scores"]["mean"]["mean"] for label in ("mine-1", "mine-2", "mine-3")) / 3
    assert abs(ours["mean"]["mean"] - expected) < 1e-9
    assert ours["mean"]["low"] < ours["mean"]["mean"] < ours["mean"]["high"]
    # a one-run algorithm shows its checkpoint's within-run intervals and verdicts, and says so
    assert other["within_run"] and other["mean"]["low"] is not None and "conditional on this checkpoint" in other["note"]
    assert ours["gap_won"]["low"] < ours["gap_won"]["mean"] < ours["gap_won"]["high"] and not ours["within_run"]
    assert ours["adapting_runs"] in (0, 1, 2, 3)
    from mewa_bench.leaderboard.algorithm_tables import gap_note

    assert board["gap_note"] == gap_note(load_suite("narrow-v1")) and "0.0190" in board["gap_note"]
    assert get(server, "/api/leaderboards/narrow-v2").json()["gap_note"] is None  # a gap of 0.44: nothing to warn of
    agents = [r for r in board["rows"] if r["kind"] != "reference"]
    assert board["verdicts"]["tests"] >= 2 * len(agents) and "Holm" in board["verdicts"]["caption"]
    assert all(r["adapts"] in (True, False) and r["gap_won"] is not None for r in agents)
    page = get(server, "/leaderboards/narrow-v1").text
    assert 'id="algorithms"' in page and 'data-runs="3"' in page and "<h2>Checkpoints</h2>" in page
    # the board leads with the algorithms table, then the figure, then the checkpoints
    assert (page.index('id="algorithms"') < page.index('id="curves"') < page.index("<h2>Checkpoints</h2>")
            < page.index('id="ranking"'))
    runs_drawn = sum(r["runs"] for r in board["algorithms"])
    assert "per algorithm (" in page and f"from {runs_drawn} runs: a submitter" in page
    assert "95% CI over training runs" in page and "per agent" not in page
    png = get(server, "/leaderboards/narrow-v1/curves.png")
    assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"

    # the figure the server draws: one panel per row of the algorithms table (the PLOTTED best), a band (over training
    # runs) only for an algorithm of several runs
    from mewa_bench.service.db import make_engine, session_factory
    from mewa_bench.service.settings import Settings
    from mewa_bench.service.web.curves import PLOTTED, board_curves

    settings = Settings(server.data_dir, server.db)  # the server's (uploads unranked)
    engine = make_engine(settings.database_url)
    try:
        with session_factory(engine)() as session:
            panels = [ax for ax in board_curves(session, settings, "narrow-v1", load_suite("narrow-v1")).axes
                      if ax.get_visible()]
    finally:
        engine.dispose()
    shown = board["algorithms"][:PLOTTED]
    expected = [f"{r['algorithm']} ({r['runs']} run{'s' if r['runs'] > 1 else ''})".replace("$", r"\$")
                + (" (privileged)" if r["privileged"] else "") for r in shown]
    titles = [" ".join(ax.get_title().split("\n")[:-1]) for ax in panels]  # a long name wraps; gap won is last
    assert titles == expected and all(len(ax.get_lines()) == 1 + 5 for ax in panels)  # and the five reference lines
    assert [len(ax.collections) for ax in panels] == [int(r["runs"] > 1) for r in shown]
    if ours in shown:
        assert f"{ours['algorithm']} (3 runs)" in titles
