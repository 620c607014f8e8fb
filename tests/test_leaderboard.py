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
    rts, best_fixed = narrow.summary["score"]["random_task_specific"], narrow.summary["score"]["best_fixed"]
    won = 100 * (rts - best_fixed) / (1 - best_fixed)  # exact: no interval
    assert f"| *random task-specific (reference)* | {won:+.1f}% | {rts:.4f} |" in md
    assert float(refs["best fixed policy"]["gap_won"]) == 0.0 and float(refs["max expected"]["gap_won"]) == 1.0


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
    assert {p.name for p in report.written} == {f"{s}{ext}" for s in suites for ext in (
        ".md", ".csv", ".png", "-algorithms.csv", "-cells.csv", "-gap-won.png")} | {"index.html"}
    assert 'src="narrow-v1-gap-won.png"' in page and "Holm" in page
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
    """Every file of the boards, the algorithms tables included, rebuilt byte for byte."""
    _, subs, out = built
    again = build_leaderboards(subs, tmp_path / "again")
    assert {p.name for p in again.written} == {p.name for p in built[0].written}
    for path in again.written:
        assert path.read_bytes() == (out / path.name).read_bytes(), path.name


def test_the_board_leads_with_the_algorithms_table(built) -> None:
    _, _, out = built
    md = (out / "narrow-v1.md").read_text()
    assert md.index("## Algorithms") < md.index("| 1 | learner | 1 |") < md.index("## Checkpoints") < md.rindex(
        "| 1 | learner |")
    assert "conditional on that checkpoint" in md and "1 run: within-run intervals, conditional on this checkpoint" in md
    # a one-run algorithm is judged on its checkpoint's interval, and says so
    assert "| 1 | learner | 1 | " in md and "| yes (within run) | no (within run) |" in md
    rows = read_csv(out / "narrow-v1-algorithms.csv")
    assert [(r["rank"], r["algorithm"], r["runs"]) for r in rows] == [("", "oracle", "1"), ("1", "learner", "1"),
                                                                       ("2", "steady", "1"), ("3", "weak", "1")]
    assert out / "narrow-v1-algorithms.csv" in built[0].written  # rebuilt byte for byte: test_output_is_deterministic


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


def test_a_panel_per_algorithm_with_the_reference_lines_and_the_best_fixed_one_on_top(narrow: Suite) -> None:
    from mewa_bench.leaderboard.assemble import make_board
    from mewa_bench.leaderboard.board import Board
    from mewa_bench.leaderboard.plot import curves_figure, gap_won_figure

    entries = [synthetic_entry(narrow, f"a-seed{i}", "a", 0.8 + 0.01 * i) for i in range(3)]
    entries += [synthetic_entry(narrow, f"other{i}", f"other{i}", 0.5 + 0.02 * i) for i in range(11)]
    board = make_board(narrow, entries, "submissions")
    assert [r.runs for r in board.algorithms if r.algorithm == "a"] == [3] and len(board.algorithms) == 12
    panels = [ax for ax in curves_figure(board).axes if ax.get_visible()]
    assert len(panels) == 12  # one per algorithm, best mean first, named with its runs and gap won
    assert panels[0].get_title().startswith("a (3 runs)\ngap won ") and "other10 (1 run)" in panels[1].get_title()
    colours = []
    for ax in panels:
        algorithm = [line for line in ax.get_lines() if line.get_marker() == "o"]
        references = [line for line in ax.get_lines() if line.get_marker() != "o"]
        assert len(algorithm) == 1 and len(references) == 5
        colours.append(tuple(np.round(matplotlib_rgba(algorithm[0].get_color()), 4)))
        best = [line for line in references if line.get_ydata()[0] == narrow.summary["score"]["best_fixed"]]
        assert len(best) == 1 and matplotlib_rgba(best[0].get_color()) == (0, 0, 0, 1) and best[0].get_linewidth() > 2
        assert best[0].get_zorder() > max(r.get_zorder() for r in references if r is not best[0])  # never hidden
    assert len(set(colours)) == 12  # more than tab10's colours
    served = curves_figure(Board(narrow, (), (), board.comparison, board.algorithms)).axes  # the service's
    assert [ax.get_title() for ax in served if ax.get_visible()] == [ax.get_title() for ax in panels]
    forest = gap_won_figure(board).axes[0]
    assert [t.get_text() for t in forest.get_yticklabels()][0] == "a (3 runs)"
    assert {t.get_text() for t in forest.texts} == {"0 = best fixed policy", "100% = max expected"}


def matplotlib_rgba(color: object) -> tuple[float, ...]:
    from matplotlib.colors import to_rgba

    return to_rgba(color)


@pytest.mark.slow
def test_committed_leaderboards_are_up_to_date_with_the_submissions(tmp_path: Path) -> None:
    repo = Path(__file__).resolve().parents[1]
    report = build_leaderboards(repo / "submissions", tmp_path)
    assert report.invalid == ()
    for suite in ("narrow-v1", "wide-v1", "narrow-v2", "wide-v2"):
        names = {e.agent for e in report.entries[suite]}  # a user's own submissions may sit beside these
        assert "bayes-explorer" in names
        if suite.endswith("v1"):
            assert names >= {"random", "random-task-specific", "bayes-adaptive", "oracle-t-optimal"}
        for name in (f"{suite}.md", f"{suite}.csv", f"{suite}-algorithms.csv", f"{suite}-cells.csv"):
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


def test_the_boards_say_when_the_gap_is_small() -> None:
    """narrow-v1's and wide-v1's non-adaptive gaps are below 0.05: their boards say that gap won is large and negative
    for anything short of the best fixed policy; the v2 boards, whose gaps are 0.38-0.44, do not."""
    from mewa_bench.leaderboard.algorithm_tables import gap_note

    repo = Path(__file__).resolve().parents[1]
    for name in ("narrow-v1", "wide-v1", "narrow-v2", "wide-v2"):
        suite = load_suite(name)
        note = gap_note(suite)
        assert (note is not None) == (suite.summary["non_adaptive_gap"] < 0.05), name
        board = (repo / "leaderboards" / f"{name}.md").read_text()
        if note is not None:
            assert note in board and f"{-0.01 / suite.summary['non_adaptive_gap']:.0%}" in note
        assert "P(> best fixed)" not in board




REPO = Path(__file__).resolve().parents[1]
SUITES = ("narrow-v1", "wide-v1", "narrow-v2", "wide-v2")
# Submissions whose exact adaptability is 0: fixed policies (random everywhere; random task-specific and the
# privileged t-optimal oracle, which is told the worker, on the one-task suites, where their policy never changes).
ZERO_ADAPTABILITY = {"narrow-v1": ("random", "random-task-specific", "oracle-t-optimal"), "wide-v1": ("random",),
                     "narrow-v2": ("random", "random-task-specific", "oracle-t-optimal"), "wide-v2": ("random",)}


def test_replays_are_shared_by_a_boards_runs_and_equal_a_fresh_replay(narrow: Suite) -> None:
    from mewa_bench.design.policies import policy_names
    from mewa_bench.design.replay import replay_returns
    from mewa_bench.game.normalise import episode_score, normalised_return
    from mewa_bench.protocol.scoring import replayed_scores

    pair = narrow.pairs[3]
    task = narrow.tasks[pair.task_index]
    keys = np.array([env_seed(narrow.sha256, pair.index, s, k) for s in range(5) for k in range(K)], dtype=np.uint64)
    first = replayed_scores(narrow, pair.index, keys)
    fresh = episode_score(normalised_return(task, replay_returns(task, policy_names(task.N), pair.worker.w, keys)),
                          pair.max_expected)
    assert np.array_equal(first, fresh) and first.shape == (len(keys), len(policy_names(task.N)))
    assert replayed_scores(narrow, pair.index, keys.copy()) is first  # the second run of a board replays nothing
    assert not first.flags.writeable
    other = replayed_scores(narrow, pair.index, keys[::-1].copy())  # other keys, another replay
    assert other is not first and np.array_equal(other, fresh[::-1])


@pytest.mark.parametrize("suite", SUITES)
def test_no_fixed_policy_is_called_adaptive_on_a_shipped_board(suite: str) -> None:
    rows = {r["agent"]: r for r in read_csv(REPO / "leaderboards" / f"{suite}.csv") if r["kind"] != "reference"}
    for name in ZERO_ADAPTABILITY[suite]:
        assert rows[name]["adapts"] == "no", (suite, name, rows[name]["adaptability_low"])
    algorithms = {r["algorithm"]: r for r in read_csv(REPO / "leaderboards" / f"{suite}-algorithms.csv")}
    for name in ZERO_ADAPTABILITY[suite]:
        assert algorithms[name]["adapts"] == "no" and algorithms[name]["intervals"] == "within run"
    if suite.endswith("v2"):  # the agent that adapts most is on the board, with a verdict
        explorer = algorithms["bayes-explorer"]
        assert explorer["adapts"] == "yes" and explorer["intervals"] == "within run"
        assert float(explorer["gap_won_low"]) < float(explorer["gap_won"]) < float(explorer["gap_won_high"])
    md = (REPO / "leaderboards" / f"{suite}.md").read_text()
    assert "Holm's weighted step-down procedure over all" in md and "at most 2.5%" in md


@pytest.mark.parametrize("suite", ["narrow-v2", "wide-v2"])
def test_the_strongest_learned_adapter_is_called_adaptive_over_its_runs(suite: str) -> None:
    """AD adapts by about +0.46 over its three runs on both v2 suites: its algorithm row says "adapts", however
    many checkpoint rows share the board's family."""
    ad = {r["algorithm"]: r for r in read_csv(REPO / "leaderboards" / f"{suite}-algorithms.csv")}["ad"]
    assert ad["runs"] == "3" and ad["intervals"] != "within run" and float(ad["adaptability_low"]) > 0.3
    assert ad["adapts"] == "yes" and ad["adapting_runs"] == "3"


def test_ad_on_the_task_structures_adapts_over_its_runs_on_wide_v2() -> None:
    """`ad-task-structures` never trained on wide-v2's tasks (only the generator's structures, renamed): its three
    runs adapt and their interval over runs is above the best fixed policy."""
    row = {r["algorithm"]: r for r in read_csv(REPO / "leaderboards" / "wide-v2-algorithms.csv")}["ad-task-structures"]
    assert row["runs"] == "3" and row["intervals"] == "over runs" and row["adapting_runs"] == "3"
    assert row["adapts"] == "yes" and float(row["gap_won_low"]) > 0 and float(row["gap_won"]) > 0.5


def test_ad_with_one_key_value_head_adapts_over_its_runs_on_wide_v2() -> None:
    """`ad-mqa` (AD's recipe with one key/value head: a quarter of the cache a step reads) wins more than half of
    wide-v2's gap over its three runs, its interval over runs above the best fixed policy, and each run adapts."""
    row = {r["algorithm"]: r for r in read_csv(REPO / "leaderboards" / "wide-v2-algorithms.csv")}["ad-mqa"]
    assert row["runs"] == "3" and row["intervals"] == "over runs" and row["adapting_runs"] == "3"
    assert row["adapts"] == "yes" and float(row["gap_won"]) > 0.5 and float(row["gap_won_low"]) > 0


def rliable_check(cells_csv: Path, algorithms_csv: Path) -> int:
    """rliable's mean and IQM of every algorithm's [runs, pairs] cells equal the algorithms table's (to 1e-4);
    the number of algorithms checked."""
    from rliable import metrics

    cells: dict[str, dict[str, dict[int, float]]] = {}
    for r in read_csv(cells_csv):
        cells.setdefault(r["algorithm"], {}).setdefault(r["run"], {})[int(r["pair"])] = float(r["score"])
    table = {r["algorithm"]: r for r in read_csv(algorithms_csv)}
    assert set(cells) == set(table)
    for name, runs in cells.items():
        matrix = np.array([[scores[p] for p in sorted(scores)] for _, scores in sorted(runs.items())])
        assert matrix.shape[0] == int(table[name]["runs"])
        assert abs(metrics.aggregate_mean(matrix) - float(table[name]["mean_score"])) < 1e-4, name
        assert abs(metrics.aggregate_iqm(matrix) - float(table[name]["iqm"])) < 1e-4, name
    return len(cells)


@pytest.mark.parametrize("suite", SUITES)
def test_the_cells_csv_reproduces_the_shipped_board_with_rliable(suite: str) -> None:
    assert rliable_check(REPO / "leaderboards" / f"{suite}-cells.csv",
                         REPO / "leaderboards" / f"{suite}-algorithms.csv") >= 5


@pytest.fixture(scope="module")
def small_real_board(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """narrow-v2's board from three shipped runs: RL² seeds 1 and 2 (one algorithm) and random task-specific."""
    import shutil

    subs = tmp_path_factory.mktemp("real") / "submissions"
    for folder in ("rl2-narrow-v2-seed1", "rl2-narrow-v2-seed2", "random-task-specific"):
        (subs / folder).mkdir(parents=True)
        for name in ("agent.py", "README.md", "run.json", "results-narrow-v2.json"):
            if (REPO / "submissions" / folder / name).exists():
                shutil.copy(REPO / "submissions" / folder / name, subs / folder / name)
    out = subs.parent / "boards"
    report = build_leaderboards(subs, out)
    assert not report.invalid and len(report.entries["narrow-v2"]) == 3
    return out


def test_a_board_of_real_runs_says_who_adapts_and_its_cells_reproduce_it(small_real_board: Path) -> None:
    from mewa_bench.protocol.results import read_results

    assert rliable_check(small_real_board / "narrow-v2-cells.csv", small_real_board / "narrow-v2-algorithms.csv") == 2
    algorithms = {r["algorithm"]: r for r in read_csv(small_real_board / "narrow-v2-algorithms.csv")}
    assert algorithms["rl2"]["runs"] == "2" and algorithms["rl2"]["intervals"] == "over runs"
    assert algorithms["rl2"]["adapting_runs"] in ("0", "1", "2")
    assert algorithms["random-task-specific"]["adapts"] == "no"
    rows = {r["agent"]: r for r in read_csv(small_real_board / "narrow-v2.csv")}
    best_fixed = load_suite("narrow-v2").summary["score"]["best_fixed"]
    for name, row in rows.items():  # gap won is the paired difference over the gap, with its interval
        if row["kind"] != "reference":
            assert float(row["gap_won"]) == pytest.approx(float(row["vs_best_fixed"]) / (1 - best_fixed), abs=1e-12)
            assert float(row["gap_won_low"]) < float(row["gap_won"]) < float(row["gap_won_high"])
    assert "pair_means" not in read_results(REPO / "submissions" / "rl2-narrow-v2-seed1" / "results-narrow-v2.json")[
        "scores"]  # a results file written before they were stored still goes on the board


def test_new_results_files_store_the_boards_cells(built) -> None:
    _, subs, out = built
    stored = read_results(subs / "learner" / "results-learner-narrow-v1.json")["scores"]["pair_means"]
    cells = [float(r["score"]) for r in read_csv(out / "narrow-v1-cells.csv") if r["algorithm"] == "learner"]
    assert cells == stored and len(cells) == 16
