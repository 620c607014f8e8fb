"""Leaderboards from synthetic results files: ranking, reference rows, outputs, and rejected files."""

from __future__ import annotations

import csv
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from mewa_bench.design.suites import Suite, load_suite
from mewa_bench.leaderboard import Entry, LeaderboardReport, build_leaderboards
from mewa_bench.protocol.results import PROTOCOL_VERSION, SCHEMA_VERSION, read_results, write_results
from mewa_bench.game.normalise import return_bounds
from mewa_bench.protocol.config import default_seeds, env_seed
from mewa_bench.protocol.scoring import score_units

SEEDS = list(default_seeds("narrow-v1"))  # only runs with the protocol's default seeds are ranked
K = 10
# name -> (score level at episode 1, gain by episode 10, privileged)
AGENTS = {"steady": (0.90, 0.0, False), "learner": (0.88, 0.08, False), "weak": (0.70, 0.01, False),
          "oracle": (1.0, 0.0, True)}


@pytest.fixture(scope="module")
def narrow() -> Suite:
    return load_suite("narrow-v1")


def agent_text(name: str, seed: int) -> str:
    """The agent.py of a synthetic submission (its sha256 goes into the results)."""
    return f"# synthetic agent {name}, seed {seed}\n"


def write_submission(folder: Path, name: str, seed: int) -> None:
    """A submission folder's agent.py and README.md."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "agent.py").write_text(agent_text(name, seed))
    (folder / "README.md").write_text(f"# {name}\n")


def make_results(suite: Suite, name: str, start: float, gain: float, privileged: bool = False,
                 seed: int = 0) -> dict:
    """A complete results dict in the schema of protocol/results.py, scores computed as the runner does."""
    rng = np.random.default_rng(seed)
    units = []
    for pair in suite.pairs:
        for s in SEEDS:
            curve = start + gain * np.arange(K) / (K - 1) + rng.normal(0.0, 0.01, K)
            normalised = (curve * pair.max_expected).tolist()
            r_min, r_max = return_bounds(suite.tasks[pair.task_index])
            units.append({"pair": pair.index, "seed": s, "task": pair.task_index,
                          "env_seeds": [env_seed(suite.sha256, pair.index, s, k) for k in range(K)],
                          "returns": [r_min + v * (r_max - r_min) for v in normalised],
                          "normalised_returns": normalised, "lengths": [20] * K,
                          "scores": [v / pair.max_expected for v in normalised]})
    scores = score_units(suite, units, suite.summary["score"]["random_task_specific"])
    return {
        "schema_version": SCHEMA_VERSION, "protocol_version": PROTOCOL_VERSION, "complete": True,
        "agent": {"name": name, "file": f"submissions/{name}/agent.py",
                  "sha256": hashlib.sha256(agent_text(name, seed).encode()).hexdigest(),
                  "privileged": privileged, "agent_args": {}, "checkpoint": None},
        "suite": {"name": suite.name, "version": suite.content["version"], "sha256": suite.sha256},
        "env": {"id": suite.content["env_id"], "version": "v0", "mode": "vector"},
        "package_version": "0.1.0", "seeds": SEEDS, "episodes_per_pair": K, "pairs": None,
        "isolation": {"isolated": True, "time_limit": 10.0, "memory_limit": None},
        "units": units, "scores": scores.to_dict(),
        "baselines": {"score": suite.summary["score"], "skill": suite.summary["skill"]},
        "timing": {"started": "2025-03-01T10:00:00+00:00", "finished": "2025-03-02T11:30:00+00:00",
                   "wall_time": 12.5, "units": {}},
        "machine": {"platform": "test"},
    }


def invalid_variants(suite: Suite) -> dict[str, tuple[object, str]]:
    """File name -> (content, a fragment the skip reason must contain)."""
    base = make_results(suite, "bad", 0.8, 0.0, seed=9)
    wrong_hash = {**base, "suite": {**base["suite"], "sha256": "0" * 64}}
    incomplete = {**base, "complete": False}
    missing = {**base, "units": [u for u in base["units"] if u["pair"] != 3]}
    future = {**base, "schema_version": 99}
    scores = dict(base["scores"])
    scores["mean"] = {**scores["mean"], "mean": scores["mean"]["mean"] + 0.01}
    tampered = {**base, "scores": scores}
    odd_types = {**base, "schema_version": 2, "units": [5] + base["units"][1:]}  # a JSON list can hold anything
    few_seeds = {**base, "seeds": SEEDS[:3], "units": [u for u in base["units"] if u["seed"] < 3]}
    own_luck = edited_unit(base, 5, "env_seeds", 3, 12345)  # a run may not choose its episodes' seeds
    zero_steps = edited_unit(base, 6, "lengths", 0, 0)
    renormalised = edited_unit(base, 7, "normalised_returns", 2, base["units"][7]["normalised_returns"][2] + 0.01)
    return {"results-odd-types.json": (odd_types, "malformed"), "results-wrong-hash.json": (wrong_hash, "sha256"), "results-incomplete.json": (incomplete, "incomplete"),
            "results-missing.json": (missing, f"missing {len(SEEDS)} of {16 * len(SEEDS)} units"),
            "results-schema99.json": (future, "schema_version 99"),
            "results-few-seeds.json": (few_seeds, "default seeds"),
            "results-tampered.json": (tampered, "mean score"), "results-garbage.json": ("{not json", "not valid JSON"),
            "results-own-luck.json": (own_luck, "episode 3: env seed 12345 is not the protocol's"),
            "results-zero-steps.json": (zero_steps, "episode 0: length 0 is not a step count in 1..100"),
            "results-renormalised.json": (renormalised, "episode 2: normalised return")}


def edited_unit(results: dict, unit: int, field: str, episode: int, value: object) -> dict:
    """A copy of `results` with one episode's `field` of one unit replaced."""
    units = [dict(u) for u in results["units"]]
    units[unit][field] = [value if k == episode else v for k, v in enumerate(units[unit][field])]
    return {**results, "units": units}


@pytest.fixture(scope="module")
def built(narrow: Suite, tmp_path_factory: pytest.TempPathFactory) -> tuple[LeaderboardReport, Path, Path]:
    """Submissions with four valid agents and seven broken files; the leaderboards built from them."""
    root = tmp_path_factory.mktemp("lb")
    subs = root / "submissions"
    for i, (name, (start, gain, privileged)) in enumerate(AGENTS.items()):
        write_submission(subs / name, name, i)
        write_results(subs / name / f"results-{name}-narrow-v1.json", make_results(narrow, name, start, gain,
                                                                                    privileged, seed=i))
    (subs / "steady" / "notes.json").write_text('{"not": "a results file"}')  # ignored: no schema_version
    write_submission(subs / "bad", "bad", 9)
    for file, (content, _) in invalid_variants(narrow).items():
        path = subs / "bad" / file
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, str):
            path.write_text(content)
        elif content["schema_version"] == SCHEMA_VERSION:
            write_results(path, content)  # the units as columns, as `evaluate` writes them
        else:
            path.write_text(json.dumps(content))
    out = root / "leaderboards"
    return build_leaderboards(subs, out), subs, out


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_ranking_order_and_privileged_unranked(built) -> None:
    report, _, _ = built
    entries = report.entries["narrow-v1"]
    assert [e.agent for e in entries] == ["oracle", "learner", "steady", "weak"]
    rows = [r for r in read_csv(built[2] / "narrow-v1.csv") if r["kind"] != "reference"]
    assert [(r["rank"], r["agent"]) for r in rows] == [("", "oracle"), ("1", "learner"), ("2", "steady"),
                                                       ("3", "weak")]
    md = (built[2] / "narrow-v1.md").read_text()
    assert "| — | oracle (privileged) |" in md
    assert "| 1 | learner |" in md and "| 3 | weak |" in md
    assert "not ranked" in md
    assert report.entries["wide-v1"] == ()


def test_csv_numbers_match_results(built, narrow: Suite) -> None:
    _, subs, out = built
    results = read_results(subs / "learner" / "results-learner-narrow-v1.json")
    row = next(r for r in read_csv(out / "narrow-v1.csv") if r["agent"] == "learner")
    sc = results["scores"]
    assert float(row["mean_score"]) == pytest.approx(sc["mean"]["mean"], abs=1e-12)
    # the adjusted mean is not the raw one, whose value is kept in the file beside it
    assert sc["raw"]["mean"]["mean"] == pytest.approx(np.mean([u["scores"] for u in results["units"]]), abs=1e-12)
    assert float(row["mean_score_low"]) == pytest.approx(sc["mean"]["low"], abs=1e-12)
    assert float(row["mean_score_high"]) == pytest.approx(sc["mean"]["high"], abs=1e-12)
    assert float(row["s_1"]) == pytest.approx(sc["curve"][0]["mean"], abs=1e-12)
    assert float(row["s_10"]) == pytest.approx(sc["curve"][-1]["mean"], abs=1e-12)
    assert float(row["adaptability"]) == pytest.approx(sc["adaptability"]["mean"], abs=1e-12)
    assert float(row["adaptability"]) == pytest.approx(0.08, abs=0.01)
    assert float(row["skill"]) == pytest.approx(sc["skill"]["mean"], abs=1e-12)
    assert row["seeds"] == str(len(SEEDS)) and row["date"] == "2025-03-02" and row["package_version"] == "0.1.0"
    assert row["agent_sha256"] == results["agent"]["sha256"]


def test_reference_rows_have_the_suites_values(built, narrow: Suite) -> None:
    out = built[2]
    refs = {r["agent"]: r for r in read_csv(out / "narrow-v1.csv") if r["kind"] == "reference"}
    keys = {"random": "random", "random task-specific": "random_task_specific", "best fixed policy": "best_fixed",
            "max expected": "max_expected", "known-worker optimum": "known_worker_optimum"}
    assert set(refs) == set(keys)
    for label, key in keys.items():
        assert refs[label]["rank"] == ""
        assert float(refs[label]["mean_score"]) == narrow.summary["score"][key]
        assert float(refs[label]["skill"]) == narrow.summary["skill"][key]
    assert float(refs["max expected"]["mean_score"]) == 1.0
    md = (out / "narrow-v1.md").read_text()
    assert "exact expected values" in md and narrow.sha256 in md
    assert f"{narrow.summary['non_adaptive_gap']:.4f}" in md
    assert f"| *random task-specific (reference)* | {narrow.summary['score']['random_task_specific']:.4f} |" in md


def test_png_and_html(built) -> None:
    import matplotlib.image

    report, _, out = built
    for suite in ("narrow-v1", "wide-v1"):
        image = matplotlib.image.imread(out / f"{suite}.png")
        assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100
    page = (out / "index.html").read_text()
    for name in AGENTS:
        assert name in page
    assert 'src="narrow-v1.png"' in page and 'src="wide-v1.png"' in page
    assert "http" not in page and "<script" not in page
    suites = ("narrow-v1", "wide-v1", "narrow-v2", "wide-v2")
    assert {p.name for p in report.written} == {f"{s}{ext}" for s in suites
                                                for ext in (".md", ".csv", ".png", "-algorithms.csv")} | {"index.html"}
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary files left


def test_invalid_files_reported_and_skipped(built, narrow: Suite) -> None:
    report, subs, out = built
    reasons = {path.name: reason for path, reason in report.invalid}
    expected = invalid_variants(narrow)
    assert set(reasons) == set(expected)
    for file, (_, fragment) in expected.items():
        assert fragment in reasons[file], (file, reasons[file])
    assert all(e.agent != "bad" for e in report.entries["narrow-v1"])
    assert "bad" not in (out / "narrow-v1.csv").read_text()


def test_tampered_curve_point_is_rejected(narrow: Suite, tmp_path: Path) -> None:
    results = make_results(narrow, "sneaky", 0.8, 0.0)
    results["scores"]["curve"][-1]["mean"] += 0.05  # a better s_10 than its units show
    write_submission(tmp_path / "subs" / "sneaky", "sneaky", 0)
    write_results(tmp_path / "subs" / "sneaky" / "results-x.json", results)
    report = build_leaderboards(tmp_path / "subs", tmp_path / "out")
    assert report.entries["narrow-v1"] == ()
    assert "s_10" in report.invalid[0][1]


def test_output_is_deterministic(built, tmp_path: Path) -> None:
    _, subs, out = built
    again = build_leaderboards(subs, tmp_path / "again")
    for path in again.written:
        assert path.read_bytes() == (out / path.name).read_bytes(), path.name


def test_the_board_leads_with_the_algorithms_table_and_rebuilds_it_byte_for_byte(built, tmp_path: Path) -> None:
    _, subs, out = built
    md = (out / "narrow-v1.md").read_text()
    assert md.index("## Algorithms") < md.index("| 1 | learner | 1 |") < md.index("## Checkpoints") < md.rindex(
        "| 1 | learner |")
    assert "conditional on that checkpoint" in md and "1 run: no interval over training runs" in md
    rows = read_csv(out / "narrow-v1-algorithms.csv")
    assert [(r["rank"], r["algorithm"], r["runs"]) for r in rows] == [("", "oracle", "1"), ("1", "learner", "1"),
                                                                       ("2", "steady", "1"), ("3", "weak", "1")]
    again = build_leaderboards(subs, tmp_path / "again")
    name = "narrow-v1-algorithms.csv"
    assert (tmp_path / "again" / name).read_bytes() == (out / name).read_bytes()
    assert again.written


def test_runs_of_one_algorithm_share_a_row(narrow: Suite, tmp_path: Path) -> None:
    subs = tmp_path / "submissions"
    for i in range(3):
        folder = subs / f"algo-narrow-v1-seed{i}"
        write_submission(folder, folder.name, 20 + i)
        (folder / "run.json").write_text(json.dumps({"algorithm": "algo", "seed": i, "suite": "narrow-v1"}))
        write_results(folder / "results-narrow-v1.json",
                      make_results(narrow, folder.name, 0.80 + 0.03 * i, 0.02, seed=20 + i))
    report = build_leaderboards(subs, tmp_path / "boards")
    assert not report.invalid
    rows = read_csv(tmp_path / "boards" / "narrow-v1-algorithms.csv")
    assert [(r["algorithm"], r["runs"], r["note"]) for r in rows] == [("algo", "3", "")]
    assert float(rows[0]["mean_score_low"]) < float(rows[0]["mean_score"]) < float(rows[0]["mean_score_high"])
    assert len(read_csv(tmp_path / "boards" / "narrow-v1.csv")) == 3 + 5  # checkpoints and reference lines


def synthetic_entry(suite: Suite, name: str, algorithm: str, level: float) -> Entry:
    """A board entry whose scores are made up (no results file): level on every pair and episode."""
    from mewa_bench.protocol.scoring import Comparison, Estimate, Scores

    e = Estimate(level, level - 0.01, level + 0.01)
    scores = Scores(curve=(e,) * K, mean=e, iqm=e, adaptability=Estimate(0.0, -0.01, 0.01), skill=e, raw={},
                    comparisons={"best_fixed": Comparison(Estimate(level - 0.98, -1.0, -0.9), None)}, units=16,
                    control_variates={}, pairs=tuple(range(len(suite.pairs))),
                    pair_curves=np.full((len(suite.pairs), K), level))
    return Entry(suite=suite.name, agent=name, path=Path(name) / "results.json", privileged=False, scores=scores,
                 seeds=tuple(SEEDS), date="", package_version="", agent_sha256=name, algorithm=algorithm)


def test_one_line_per_algorithm_and_no_two_lines_share_colour_and_style(narrow: Suite) -> None:
    from mewa_bench.leaderboard.board import Board, make_board
    from mewa_bench.leaderboard.plot import curves_figure

    entries = [synthetic_entry(narrow, f"a-seed{i}", "a", 0.8 + 0.01 * i) for i in range(3)]
    entries += [synthetic_entry(narrow, f"other{i}", f"other{i}", 0.5 + 0.02 * i) for i in range(11)]
    board = make_board(narrow, entries, "submissions")
    assert [r.runs for r in board.algorithms if r.algorithm == "a"] == [3] and len(board.algorithms) == 12
    lines = curves_figure(board).axes[0].get_lines()
    styles = [(tuple(np.round(matplotlib_rgba(line.get_color()), 4)), str(line.get_linestyle())) for line in lines]
    assert len(lines) == 12 + 5 and len(set(styles)) == len(styles)  # 12 algorithms: more than tab10's colours
    colours = [colour for colour, _ in styles]
    assert len(set(colours[:12])) == 12 and not set(colours[:12]) & set(colours[12:])  # algorithms: a colour each
    served = curves_figure(Board(narrow, (), (), board.comparison, board.algorithms)).axes[0].get_lines()  # service's
    assert len(served) == 12 + 5 and [x.get_label() for x in served] == [x.get_label() for x in lines]  # same lines


def matplotlib_rgba(color: object) -> tuple[float, ...]:
    from matplotlib.colors import to_rgba

    return to_rgba(color)


def test_committed_leaderboards_are_up_to_date_with_the_submissions(tmp_path: Path) -> None:
    repo = Path(__file__).resolve().parents[1]
    report = build_leaderboards(repo / "submissions", tmp_path)
    assert report.invalid == ()
    for suite in ("narrow-v1", "wide-v1", "narrow-v2", "wide-v2"):
        names = {e.agent for e in report.entries[suite]}  # a user's own submissions may sit beside these
        assert "bayes-explorer" in names
        if suite.endswith("v1"):
            assert names >= {"random", "random-task-specific", "bayes-adaptive", "oracle-t-optimal"}
        for name in (f"{suite}.md", f"{suite}.csv", f"{suite}-algorithms.csv"):
            assert (tmp_path / name).read_text() == (repo / "leaderboards" / name).read_text()
    assert (tmp_path / "index.html").read_text() == (repo / "leaderboards" / "index.html").read_text()


def test_submitted_results_were_produced_by_the_shipped_agent_files() -> None:
    repo = Path(__file__).resolve().parents[1]
    for results_file in sorted((repo / "submissions").glob("*/results-*.json")):
        recorded = json.loads(results_file.read_text())["agent"]["sha256"]
        actual = hashlib.sha256((results_file.parent / "agent.py").read_bytes()).hexdigest()
        assert recorded == actual, f"{results_file}: re-run the evaluation, agent.py changed since"


def test_a_changed_agent_file_invalidates_its_results(tmp_path: Path) -> None:
    import shutil

    repo = Path(__file__).resolve().parents[1]
    sub = tmp_path / "subs" / "random"
    shutil.copytree(repo / "submissions" / "random", sub)
    (sub / "agent.py").write_text((sub / "agent.py").read_text() + "\n# edited after evaluating\n")
    report = build_leaderboards(tmp_path / "subs", tmp_path / "lb")
    results = sorted(sub.glob("results-*.json"))
    assert len(results) == 4
    assert sorted(path for path, _ in report.invalid) == results
    assert all("re-run the evaluation" in why for _, why in report.invalid)


def test_a_submission_needs_its_agent_and_readme_and_is_ranked_once(narrow: Suite, tmp_path: Path) -> None:
    subs = tmp_path / "subs"
    results = make_results(narrow, "alone", 0.8, 0.0, seed=4)
    write_results(subs / "alone" / "results-narrow-v1.json", results)  # no agent.py, no README.md
    write_submission(subs / "first", "alone", 4)  # the same agent file submitted twice
    write_results(subs / "first" / "results-narrow-v1.json", results)
    write_submission(subs / "second", "alone", 4)
    write_results(subs / "second" / "results-narrow-v1.json", results)
    report = build_leaderboards(subs, tmp_path / "out")
    assert [e.path.parent.name for e in report.entries["narrow-v1"]] == ["first"]
    reasons = {path.parent.name: why for path, why in report.invalid}
    assert "no agent.py and no README.md" in reasons["alone"]
    assert "already on the narrow-v1 board as first" in reasons["second"]


def test_the_leaderboard_command_fails_when_it_skipped_a_file(narrow: Suite, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    subs = tmp_path / "subs"
    write_results(subs / "alone" / "results-narrow-v1.json", make_results(narrow, "alone", 0.8, 0.0))
    args = ["leaderboard", "--submissions", str(subs), "--out", str(tmp_path / "out")]
    strict = CliRunner().invoke(app, args)
    assert strict.exit_code == 1 and "skipped" in strict.output
    assert (tmp_path / "out" / "narrow-v1.md").exists()  # the boards are written either way
    assert CliRunner().invoke(app, [*args, "--no-strict"]).exit_code == 0


def test_an_agent_name_with_dollar_signs_is_drawn_as_text(narrow: Suite, tmp_path: Path) -> None:
    """matplotlib would parse `$...$` in a legend label as mathtext (and fail on `$$`); a name is plain text."""
    subs = tmp_path / "submissions"
    for i, name in enumerate(("$$", r"cost $\frac{")):
        folder = subs / f"agent{i}"
        write_submission(folder, name, i)
        write_results(folder / "results-narrow-v1.json", make_results(narrow, name, 0.8, 0.1, seed=i))
    report = build_leaderboards(subs, tmp_path / "boards")
    assert (tmp_path / "boards" / "narrow-v1.png").stat().st_size > 0
    assert {e.agent for e in report.entries["narrow-v1"]} == {"$$", r"cost $\frac{"} and not report.invalid


def test_the_board_says_when_p_over_best_fixed_only_counts_pairs() -> None:
    """narrow-v2's best fixed policy scores 0 or 1 on every pair (read here from the suite file's t-optimal values),
    so its board says what P(> best fixed) means there; the other suites' boards have no such note."""
    from mewa_bench.design.suites import load_suite
    from mewa_bench.leaderboard.algorithm_tables import best_fixed_note
    from mewa_bench.design.policies import policy_names

    for name in ("narrow-v1", "wide-v1", "wide-v2"):
        assert best_fixed_note(load_suite(name)) is None
    suite = load_suite("narrow-v2")
    fixed = [p.data["toptimal"][policy_names(suite.tasks[p.task_index].N).index(
        suite.content["tasks"][p.task_index]["curation"]["best_fixed_policy"])] for p in suite.pairs]
    zeros = sum(v == 0 for v in fixed)
    assert 0 < zeros < len(fixed) and all(v == 0 or v == pytest.approx(p.max_expected) for v, p in zip(fixed, suite.pairs))
    note = best_fixed_note(suite)
    assert f"0 on {zeros} of its {len(fixed)} pairs" in note and f"{zeros / len(fixed):.4f}" in note
    board = (Path(__file__).resolve().parents[1] / "leaderboards" / "narrow-v2.md").read_text()
    assert note in board
