"""The service's web pages in a real browser: Debian's Chromium, headless, driven by Playwright, against a real
server (`mewa-bench serve`) and a real worker (`mewa-bench serve worker`).

Results files are the shipped ones cut to seeds 0 and 1 (and re-scored by `protocol.results.finish`, as
`evaluate` does). The pages must show what the JSON API serves: the same rows in the same order, the same
ranks and scores, the figure, each submission's status as it changes. Screenshots of the pages go to
`test-artifacts/` (or $MEWA_TEST_ARTIFACTS). Without Playwright or Chromium the tests skip, unless
MEWA_REQUIRE_BROWSER=1 (CI), where they fail.
"""

from __future__ import annotations

import os
import signal
import subprocess
import tempfile
from pathlib import Path
from typing import Any, Iterator

import pytest
from service_harness import CLI, RANDOM_AGENT, REPO, Server, get, post_agent, post_results, wait_status

from mewa_bench.design.suites import load_suite
from mewa_bench.protocol.results import finish, read_results, results_text

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
CHROMIUM = Path(os.environ.get("MEWA_CHROMIUM", "/usr/bin/chromium"))
# Headless on a machine without a network: no GPU, no background requests that the closed network would refuse.
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]
ARTIFACTS = Path(os.environ.get("MEWA_TEST_ARTIFACTS", REPO / "test-artifacts"))
SEEDS = 2
SCREEN_WIDTH = 1280  # the pages must be usable on a laptop's screen: no table running off it
PAGE_TIMEOUT_MS = 90_000
# markup for the page, and "$$" that matplotlib would parse as math in the figure's legend
FIGURE_LOADED = "() => { const i = document.querySelector('img#curves'); return i.complete && i.naturalWidth > 0 }"
HOSTILE_NAME = '<img src="x" onerror="document.title=\'injected\'"> $$'


def shipped_results(agent: str, name: str | None = None) -> dict[str, Any]:
    """A shipped narrow-v1 results file cut to seeds 0..SEEDS-1 and scored again; renamed if `name` (still
    the same run for the server's replay check: each shipped agent's file can be uploaded once)."""
    results = read_results(REPO / "submissions" / agent / "results-narrow-v1.json")
    results["units"] = [u for u in results["units"] if u["seed"] < SEEDS]
    results["seeds"] = list(range(SEEDS))
    finish(results, load_suite("narrow-v1"))
    if name is not None:
        results["agent"]["name"] = name
    return results


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """A Chromium with a fresh profile (a Playwright browser context), or a skip/failure saying what is missing."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        missing = "Playwright is not installed (pip install 'mewa-bench[test]')"
    else:
        missing = None if CHROMIUM.exists() else f"Chromium is not at {CHROMIUM} (apt-get install chromium)"
    if missing is not None:
        if os.environ.get("MEWA_REQUIRE_BROWSER") == "1":
            pytest.fail(f"MEWA_REQUIRE_BROWSER=1 but {missing}")
        pytest.skip(f"{missing}; set MEWA_REQUIRE_BROWSER=1 to fail instead")
    with sync_playwright() as playwright, tempfile.TemporaryDirectory(prefix="mewa-chromium-") as profile:
        context = playwright.chromium.launch_persistent_context(
            profile, executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_FLAGS,
            viewport={"width": SCREEN_WIDTH, "height": 900})
        context.set_default_timeout(PAGE_TIMEOUT_MS)
        yield context
        context.close()


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator[Server]:
    """A server without workers of its own: submissions stay queued until the `worker` fixture starts one."""
    running = Server(tmp_path_factory.mktemp("browser") / "data", None, "--seeds", str(SEEDS), "--workers", "0",
                     "--rank-uploads").start()  # uploads ranked: the ranking below has several agents
    yield running
    running.stop()


@pytest.fixture(scope="module")
def token(server) -> str:
    return server.token("browser")


@pytest.fixture(scope="module")
def worker(server) -> Iterator[subprocess.Popen]:
    """`mewa-bench serve worker` on the server's data dir, stopped with SIGTERM at the end."""
    with open(server.data_dir.parent / "worker.log", "a") as log:
        command = [*CLI, "serve", "worker", "--data-dir", str(server.data_dir), "--lease-seconds", "5"]
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                                   env={**os.environ, "OMP_NUM_THREADS": "1"})
    yield process
    process.send_signal(signal.SIGTERM)
    process.wait(30)


@pytest.fixture
def page(browser) -> Iterator[Any]:
    """A new tab (asked for first by each test: without a browser, the test skips before a server starts)."""
    tab = browser.new_page()
    yield tab
    tab.close()


def screenshot(page: Any, name: str) -> Path:
    """A full-page PNG kept as a test artifact."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / name
    page.screenshot(path=str(path), full_page=True)
    assert path.stat().st_size > 10_000
    return path


def submit(server: Server, token: str, results: dict[str, Any]) -> int:
    answer = post_results(server, token, results_text(results).encode())
    assert answer.status_code == 202, answer.text
    return answer.json()["id"]


def test_status_page_reloads_itself_until_the_submission_is_scored(page, server, token, request) -> None:
    results = shipped_results("bayes-adaptive")
    submission = submit(server, token, results)
    page.goto(f"{server.url}/submissions/{submission}")
    assert page.locator("#status").get_attribute("data-status") == "queued"  # no worker runs yet
    assert page.locator('meta[http-equiv="refresh"]').count() == 1
    assert page.locator('#jobs tr[data-board="narrow-v1"]').get_attribute("data-state") == "queued"
    assert "bayes-adaptive" in page.locator("p", has=page.locator("#status")).inner_text()

    request.getfixturevalue("worker")  # now a worker scores it; the open page must follow by reloading itself
    page.wait_for_selector('#status[data-status="done"]')
    status = get(server, f"/api/submissions/{submission}").json()
    assert status["status"] == "done"
    assert page.locator('meta[http-equiv="refresh"]').count() == 0  # final: no more reloads
    assert page.locator('#jobs tr[data-board="narrow-v1"]').get_attribute("data-state") == "done"
    shown = page.locator('#scores tr[data-board="narrow-v1"]')
    scores = status["scores"]["narrow-v1"]
    assert float(shown.get_attribute("data-mean")) == scores["mean"]["mean"] == results["scores"]["mean"]["mean"]
    mean = scores["mean"]
    assert shown.locator("td").nth(1).inner_text() == f"{mean['mean']:.4f} [{mean['low']:.4f}, {mean['high']:.4f}]"
    screenshot(page, "service-submission-done.png")


def test_leaderboard_page_shows_the_api_ranking_and_the_figure(page, server, token, worker) -> None:
    renamed = (("random", "random"), ("oracle-t-optimal", "oracle"), ("random-task-specific", HOSTILE_NAME))
    ids = {name: submit(server, token, shipped_results(agent, name)) for agent, name in renamed}
    for submission in ids.values():
        assert wait_status(server, submission)["status"] == "done"
    board = get(server, "/api/leaderboards/narrow-v1").json()

    page.goto(server.url + "/")
    listed = page.locator('#public-boards tr[data-board="narrow-v1"]')
    assert listed.get_attribute("data-entries") == str(board["entries"])
    assert board["entries"] >= 3
    assert page.locator("#hidden-boards tr[data-board]").count() == 4  # each public suite's hidden twin
    shown = {int(s) for s in page.locator("#submissions tr[data-submission]").evaluate_all(
        "rows => rows.map(r => r.dataset.submission)")}
    assert set(ids.values()) <= shown
    listed.locator("a").click()  # a real navigation, as a person would
    page.wait_for_url(f"{server.url}/leaderboards/narrow-v1")
    assert page.locator("#board").get_attribute("data-kind") == "public"

    rows = page.locator("#ranking tbody tr")
    assert rows.count() == len(board["rows"]) == board["entries"] + 5  # and the suite's five reference lines
    header = page.locator("#ranking thead th").all_inner_texts()
    column = {name: header.index(name) for name in ("rank", "agent", "mean score [95% CI]", "s_1", "s_10")}
    for i, expected in enumerate(board["rows"]):
        row = rows.nth(i)
        cells = row.locator("td").all_inner_texts()
        assert row.get_attribute("data-kind") == expected["kind"]
        assert row.get_attribute("data-source") == expected["source"] == \
            ("reference" if expected["kind"] == "reference" else "self-reported")
        assert float(row.get_attribute("data-mean")) == expected["mean"]
        rank = {"agent": str(expected["rank"]), "privileged": "—", "reference": ""}[expected["kind"]]
        assert cells[column["rank"]] == rank
        assert cells[column["agent"]].startswith(expected["name"])  # the text, never markup
        low, high = expected["mean_low"], expected["mean_high"]
        assert cells[column["mean score [95% CI]"]] == (f"{expected['mean']:.4f}" if low is None else
                                                        f"{expected['mean']:.4f} [{low:.4f}, {high:.4f}]")
        assert cells[column["s_1"]] == f"{expected['s_first']:.4f}"
        assert cells[column["s_10"]] == f"{expected['s_last']:.4f}"
        if expected["submission_id"] is not None:
            link = row.locator("a")
            assert link.get_attribute("href") == f"/submissions/{expected['submission_id']}"
    ranks = {r["submission_id"]: r["rank"] for r in board["rows"] if r["kind"] == "agent"}
    assert ranks[ids[HOSTILE_NAME]] < ranks[ids["random"]]  # random task-specific (0.87) beats random (0.47)
    oracle = page.locator(f'#ranking tr[data-submission="{ids["oracle"]}"]')
    assert oracle.get_attribute("data-kind") == "privileged" and oracle.get_attribute("data-rank") == ""

    assert page.locator('img[src="x"]').count() == 0 and page.title() != "injected"  # the hostile name stayed text
    assert page.evaluate("document.documentElement.scrollWidth") <= SCREEN_WIDTH  # nothing runs off the screen
    assert page.locator("#ranking").evaluate("t => t.getBoundingClientRect().right") <= SCREEN_WIDTH
    figure = page.locator("img#curves")
    page.wait_for_function(FIGURE_LOADED)
    assert figure.evaluate("i => i.naturalWidth") > 600 and figure.evaluate("i => i.naturalHeight") > 300
    png = page.request.get(server.url + figure.get_attribute("src"))
    assert png.status == 200 and png.headers["content-type"] == "image/png" and png.body()[:8] == b"\x89PNG\r\n\x1a\n"
    caption = page.locator("figure figcaption").inner_text()  # one panel per algorithm, from every run
    algorithms, runs = len(board["algorithms"]), sum(r["runs"] for r in board["algorithms"])
    assert f"{algorithms} algorithms, from {runs} runs:" in caption and runs == board["entries"] >= 3
    after = "t => t.compareDocumentPosition(document.querySelector('#curves'))"
    assert page.locator("#algorithms").evaluate(after) == 4  # the figure follows the algorithms table
    screenshot(page, "service-leaderboard-narrow-v1.png")


def test_a_rejected_submission_shows_its_reason(page, server, token, worker) -> None:
    tampered = shipped_results("bayes-explorer", "tampered")  # a run no other test uploads (else: a replay)
    tampered["scores"]["mean"]["mean"] += 0.01  # passes the upload checks; re-scoring finds it
    submission = submit(server, token, tampered)
    status = wait_status(server, submission)
    assert status["status"] == "rejected"
    page.goto(f"{server.url}/submissions/{submission}")
    assert page.locator("#status").get_attribute("data-status") == "rejected"
    assert page.locator("#reason").inner_text() == status["reason"] and "disagrees" in status["reason"]
    assert page.locator("#scores").count() == 0
    board = get(server, "/api/leaderboards/narrow-v1").json()
    assert submission not in {r["submission_id"] for r in board["rows"]}
    screenshot(page, "service-submission-rejected.png")


def test_missing_pages_answer_404(page, server) -> None:
    for path in ("/leaderboards/narrow-v9", "/submissions/100000"):
        response = page.goto(server.url + path)
        assert response.status == 404 and "does not exist" in page.locator("body").inner_text()


def test_an_agent_on_the_public_and_the_hidden_board(page, server, token, worker) -> None:
    from mewa_bench.service.sandbox import sandbox_available

    problem = sandbox_available()
    if problem is not None:  # the same rule as the sandbox's own tests
        if os.environ.get("MEWA_REQUIRE_SANDBOX", "").strip() not in ("", "0"):
            pytest.fail(f"MEWA_REQUIRE_SANDBOX is set but agents cannot be sandboxed here: {problem}")
        pytest.skip(f"no sandbox here: {problem}")
    hidden_url = f"{server.url}/leaderboards/narrow-v1-hidden"
    page.goto(hidden_url)
    assert page.locator("img#curves").count() == 0  # no agent evaluated there yet: the hidden suite is not generated

    answer = post_agent(server, token, RANDOM_AGENT, "narrow-v1", name="random-agent")
    assert answer.status_code == 202, answer.text
    submission = answer.json()["id"]
    page.goto(f"{server.url}/submissions/{submission}")  # reloads itself while the worker evaluates
    page.wait_for_selector('#status[data-status="done"]', timeout=240_000)
    status = get(server, f"/api/submissions/{submission}").json()
    hidden_suite = load_suite(server.data_dir / "hidden" / "narrow-v1-hidden.json")  # made from the server's seed
    for board, suite in (("narrow-v1", load_suite("narrow-v1")), ("narrow-v1-hidden", hidden_suite)):
        units = len(suite.pairs) * SEEDS
        job = page.locator(f'#jobs tr[data-board="{board}"]')
        assert job.get_attribute("data-state") == "done"
        bar = job.locator("progress")
        # a hidden suite's size is not shown: its progress is a percentage
        shown = ("100", "100") if board.endswith("-hidden") else (str(units), str(units))
        assert (bar.get_attribute("value"), bar.get_attribute("max")) == shown, status["jobs"]
        shown = page.locator(f'#scores tr[data-board="{board}"]')
        assert float(shown.get_attribute("data-mean")) == status["scores"][board]["mean"]["mean"]

    page.goto(hidden_url)
    assert page.locator("#board").get_attribute("data-kind") == "hidden"
    assert "hidden test suite" in page.locator("h1").inner_text()
    facts = page.locator("p.facts")
    assert facts.locator('a[href="/leaderboards/narrow-v1"]').count() == 1  # its public twin
    assert facts.locator('a[href^="/api/suites/"]').count() == 0 and facts.locator("code").count() == 0  # no suite
    board = get(server, "/api/leaderboards/narrow-v1-hidden").json()
    row = page.locator(f'#ranking tr[data-submission="{submission}"]')
    ours = next(r for r in board["rows"] if r["submission_id"] == submission)
    assert row.get_attribute("data-rank") == str(ours["rank"]) == "1" and "random-agent" in row.inner_text()
    assert float(row.get_attribute("data-mean")) == ours["mean"] == status["scores"]["narrow-v1-hidden"]["mean"]["mean"]
    assert row.get_attribute("data-source") == ours["source"] == "server-evaluated"
    assert page.evaluate("document.documentElement.scrollWidth") <= SCREEN_WIDTH  # the table fits the screen
    page.wait_for_function(FIGURE_LOADED)
    screenshot(page, "service-leaderboard-narrow-v1-hidden.png")
