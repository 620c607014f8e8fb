"""What the docs and help pages state agrees with the code: seed counts, protocol naming, no tracker notes."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mewa_bench.cli import app
from mewa_bench.protocol.config import DEFAULT_SEED_COUNTS, OTHER_SUITES_SEED_COUNT, default_seeds
from mewa_bench.protocol.results import PROTOCOL_VERSION

ROOT = Path(__file__).resolve().parents[1]
DOCS = ["README.md", "docs/protocol.md", "docs/baselines.md", "docs/suites.md"]
PAIRS = {"narrow": 16, "wide": 80}  # pairs of the shipped suites of each family
NUMBER = r"(?<![\w.])(\d[\d,]*)"


def seed_statements(text: str) -> list[tuple[str, int, str]]:
    """Every statement of a default seed count in `text`: (suite family, number stated, the words)."""
    found = []
    for m in re.finditer(NUMBER + r"\**(?: seeds)?\**\s+on\s+(narrow|wide)\b", text):
        found.append((m.group(2), int(m.group(1).replace(",", "")), m.group(0)))
    for m in re.finditer(NUMBER + r" narrow, (\d+) wide|" + NUMBER + r" / (\d+) seeds", text):
        narrow, wide = (m.group(1), m.group(2)) if m.group(1) else (m.group(3), m.group(4))
        found += [("narrow", int(narrow), m.group(0)), ("wide", int(wide), m.group(0))]
    for family, pairs in PAIRS.items():
        for m in re.finditer(rf"\b{pairs} pairs x (\d+) seeds", text):
            found.append((family, int(m.group(1)), m.group(0)))
    return found


def seed_count_errors(text: str) -> list[str]:
    """Statements in `text` that contradict protocol.config's default seed counts."""
    errors = [f"{words!r}: {family} suites default to {DEFAULT_SEED_COUNTS[family]}"
              for family, n, words in seed_statements(text) if n != DEFAULT_SEED_COUNTS[family]]
    for m in re.finditer(r"(\d+) on suites of your own", text):
        if int(m.group(1)) != OTHER_SUITES_SEED_COUNT:
            errors.append(f"{m.group(0)!r}: suites of your own default to {OTHER_SUITES_SEED_COUNT}")
    for m in re.finditer(r"\bseeds?\b[^()\n]{0,40}\(default (\d+)", text):
        if int(m.group(1)) not in DEFAULT_SEED_COUNTS.values():
            errors.append(f"{m.group(0)!r}: no suite family defaults to {m.group(1)} seeds")
    for m in re.finditer(r"\((\d+) pairs, ([\d,]+) units\)", text):
        family = {v: k for k, v in PAIRS.items()}.get(int(m.group(1)))
        if family and int(m.group(2).replace(",", "")) != PAIRS[family] * DEFAULT_SEED_COUNTS[family]:
            errors.append(f"{m.group(0)!r}: {PAIRS[family]} pairs x {DEFAULT_SEED_COUNTS[family]} seeds")
    return errors


def test_the_check_sees_a_contradicting_figure() -> None:
    assert seed_count_errors("For every pair and every seed (default 50, protocol 2), the agent")
    assert seed_count_errors("**128 seeds** on narrow-v1/v2 (16 pairs, 2,048 units)")
    assert seed_count_errors("(the suites' default seeds: 256 narrow, 50 wide)")
    assert seed_count_errors("7 on suites of your own")
    n, w = DEFAULT_SEED_COUNTS["narrow"], DEFAULT_SEED_COUNTS["wide"]
    assert seed_count_errors(f"{n} on narrow-v1/v2 (16 pairs), {w} on wide-v1/v2; 0.981 on narrow-v1; rl2 on wide") == []


@pytest.mark.parametrize("doc", DOCS)
def test_docs_state_the_default_seed_counts_of_protocol_config(doc: str) -> None:
    text = (ROOT / doc).read_text()
    assert seed_count_errors(text) == []
    assert {family for family, _, _ in seed_statements(text)} == {"narrow", "wide"}, doc  # stated, not absent


def test_the_config_and_the_evaluate_help_agree() -> None:
    assert len(default_seeds("narrow-v2")) == DEFAULT_SEED_COUNTS["narrow"]
    assert len(default_seeds("wide-v1-hidden")) == DEFAULT_SEED_COUNTS["wide"]
    assert len(default_seeds("my-suite")) == OTHER_SUITES_SEED_COUNT
    result = CliRunner().invoke(app, ["evaluate", "--help"], env={"COLUMNS": "200"})
    text = " ".join(result.output.replace("│", " ").split())
    assert seed_count_errors(text) == []
    expected = (f"{DEFAULT_SEED_COUNTS['narrow']} on narrow-*, {DEFAULT_SEED_COUNTS['wide']} on wide-*, "
                f"{OTHER_SUITES_SEED_COUNT} on suites of your own")
    assert expected in text


def test_protocol_versions_are_named_without_the_package_version() -> None:
    for doc in DOCS:
        text = (ROOT / doc).read_text()
        assert not re.search(r"protocol \d+ \((?:package|version|v)\s*\d", text, re.I), doc
    result = CliRunner().invoke(app, ["info"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    [line] = [line for line in result.output.splitlines() if line.split()[:1] == ["protocol"]]
    assert line.split()[1] == str(PROTOCOL_VERSION)


TRACKER = re.compile(r"\bissues?\b|\bissue's\b|\(#\d+\)", re.I)  # the tracker is not the reader's
STATUS = re.compile(r"^\W*Status\s*[(:]")  # a status paragraph: "Status (in progress): ..."


def tracker_notes(paths: list[Path], root: Path = ROOT) -> list[str]:
    """Lines that name a tracker issue or start a status note ("issue 12", "(#12)", "Status: ...")."""
    return [f"{path.relative_to(root)}:{n}: {line.strip()}" for path in paths
            for n, line in enumerate(path.read_text().splitlines(), 1) if TRACKER.search(line) or STATUS.search(line)]


def test_the_tracker_check_sees_a_note(tmp_path: Path) -> None:
    note = tmp_path / "rl2.py"
    note.write_text('"""RL^2 (issue 12): trains."""\n# colour #1\nx = 1  # fixed in (#40)\n'
                    '"""\nStatus (in progress): no\ncheckpoint yet; the status (a word) is fine.\n"""\n'
                    '# as the Issue asked\n# the tissue and issuer are words\n')
    assert [line.split(": ", 1)[0] for line in tracker_notes([note], tmp_path)] == ["rl2.py:1", "rl2.py:3", "rl2.py:5",
                                                                                     "rl2.py:8"]


def test_code_and_docs_name_no_tracker_issues() -> None:
    paths = [p for p in [*(ROOT / "mewa_bench").rglob("*.py"), *(ROOT / "tests").rglob("*.py"),
                         *(ROOT / "benchmarks").rglob("*.py"), ROOT / "benchmarks" / "README.md",
                         *(ROOT / d for d in DOCS), ROOT / "docs" / "architecture.md"] if p.resolve() != Path(__file__).resolve()]
    assert tracker_notes(paths) == []


def test_the_baselines_page_says_what_is_public_and_it_is_true() -> None:
    from mewa_bench.design.suites import load_suite

    text = " ".join((ROOT / "docs" / "baselines.md").read_text().split())
    denial = r"workers (?:are|were) not (?:public|published)|(?:test|curated) workers are (?:not public|secret)"
    assert not re.search(denial, text, re.I)
    assert "curated (task, worker) pairs *with the workers themselves*" in text
    assert "SPEC section 6" in text and "The test set is the service's hidden suites" in text
    result = CliRunner().invoke(app, ["suites", "show", "narrow-v2"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    for pair in load_suite("narrow-v2").pairs:  # what the page says `suites show` prints: every curated worker
        assert " ".join(f"{w:.2f}" for w in pair.worker.w) in result.output


def readme_section(title: str) -> str:
    """The README's `## title` section, up to the next `## `."""
    text = (ROOT / "README.md").read_text()
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start:end if end > 0 else None]


def test_the_readme_names_every_shipped_suite_and_counts_them_right() -> None:
    from mewa_bench.design.suites import ALL_SUITES

    section = readme_section("Suites")
    words = {2: "Two", 3: "Three", 4: "Four", 5: "Five", 6: "Six"}
    assert f"{words[len(ALL_SUITES)]} frozen, versioned test suites" in section
    for name in ALL_SUITES:
        assert f"`{name}`" in section, name


def test_the_command_table_names_every_algorithm_train_takes() -> None:
    from mewa_bench.agents.training_io import ALGORITHMS

    table = readme_section("Command line")
    [row] = [line for line in table.splitlines() if line.startswith("| `mewa-bench train ")]
    named = re.match(r"\| `mewa-bench train ([\w\\|]+) ", row).group(1).split("\\|")
    assert named == list(ALGORITHMS)
    *first, last = ALGORITHMS
    assert f"{', '.join(first)} or {last}" in " ".join(
        CliRunner().invoke(app, ["train", "--help"], env={"COLUMNS": "200"}).output.replace("│", " ").split())


def test_what_the_readme_says_read_results_gives_is_what_it_gives() -> None:
    from mewa_bench.protocol.results import read_results

    text = " ".join((ROOT / "README.md").read_text().split())
    m = re.search(r"`mewa_bench\.protocol\.results\.read_results\(path\)` gives the whole file as a dict, checked, "
                  r"with its `units` decoded into a list of dicts \(([\w, ]+)\)", text)
    assert m, "the README's sentence on read_results changed: keep it true"
    results = read_results(ROOT / "submissions" / "rl2-narrow-v2-seed1" / "results-narrow-v2.json")
    assert {"agent", "suite", "seeds", "scores", "units"} <= results.keys()
    assert isinstance(results["units"], list) and set(results["units"][0]) == set(m.group(1).split(", "))


@pytest.mark.parametrize("command", [["evaluate"], ["train"], ["submit"], ["record"]])
def test_the_default_suite_is_the_one_the_docs_recommend_for_adaptation(command: list[str]) -> None:
    from mewa_bench.design.suites import DEFAULT_SUITE

    section = " ".join(readme_section("Suites").split())
    recommended = re.search(r"- `(\S+)`, `(\S+)`: (?:(?!- `).)*?the suites for measuring adaptation", section)
    assert recommended and DEFAULT_SUITE in recommended.groups()
    text = " ".join(CliRunner().invoke(app, [*command, "--help"], env={"COLUMNS": "200"}).output.replace("│", " ")
                    .split())
    assert re.search(rf"\[default: {DEFAULT_SUITE}\]|default: {DEFAULT_SUITE}\b", text), text
