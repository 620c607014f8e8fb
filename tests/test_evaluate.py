"""The evaluation protocol: scoring by hand, determinism, resume, and clear errors for bad agents."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from mewa_bench.design.suites import load_suite
from mewa_bench.protocol.results import read_results, stable_view
from mewa_bench.protocol.config import EvalConfig, env_seed
from mewa_bench.protocol.runner import EvaluationError, evaluate

AGENTS = Path(__file__).parent / "agents"
FAULTY = AGENTS / "delayed_fault_agent.py"


def test_env_seeds_are_deterministic_and_distinct() -> None:
    h = load_suite("narrow-v1").sha256
    seeds = {env_seed(h, p, s, k) for p in range(16) for s in range(3) for k in range(10)}
    assert len(seeds) == 480 and all(0 <= s < 2**63 for s in seeds)
    # frozen: every shipped results file depends on this derivation (sha256 of "suite/pair/seed/episode")
    assert env_seed(h, 1, 2, 3) == 6380874493419434229


# -- runs ------------------------------------------------------------------------------------------
def run(tmp_path: Path, agent: Path, name: str = "r.json", **kw) -> tuple[dict, Path]:
    config = EvalConfig(agent_path=agent, out=tmp_path / name, **kw)
    return evaluate(config)


def test_same_agent_same_seeds_identical_results(tmp_path: Path) -> None:
    args = dict(agent_args={"fault": "none"}, seeds=(0, 1), pairs=(0, 5))
    a, _ = run(tmp_path, FAULTY, "a.json", **args)
    b, _ = run(tmp_path, FAULTY, "b.json", jobs=2, **args)
    c, _ = run(tmp_path, FAULTY, "c.json", isolated=False, **args)
    assert stable_view(a) == stable_view(b)
    assert {k for k in stable_view(a) if stable_view(a)[k] != stable_view(c)[k]} == {"isolation"}
    assert not a["complete"]  # a subset of pairs is never a rankable run
    assert [(u["pair"], u["seed"]) for u in a["units"]] == [(0, 0), (0, 1), (5, 0), (5, 1)]


def test_full_run_is_complete_and_valid(tmp_path: Path) -> None:
    results, path = run(tmp_path, FAULTY, agent_args={"fault": "none"}, seeds=(0,))
    assert results["complete"] and read_results(path)["scores"]["units"] == 16
    suite = load_suite("narrow-v1")
    assert results["suite"]["sha256"] == suite.sha256
    unit = results["units"][3]
    assert unit["scores"] == pytest.approx(np.array(unit["normalised_returns"]) / suite.pairs[3].max_expected)
    assert all(1 <= n <= 100 for u in results["units"] for n in u["lengths"])


@pytest.mark.parametrize("fault, kind, text", [
    ("raise", "exception", "ZeroDivisionError: the agent divided by zero"),
    ("invalid", "invalid_action", "returned 7"),
    ("hang", "timeout", "time limit"),
    ("memory", None, "memory"),
])
def test_bad_agent_errors_say_where_and_keep_results(tmp_path: Path, fault: str, kind: str | None, text: str) -> None:
    out = tmp_path / "r.json"
    config = EvalConfig(agent_path=FAULTY, out=out, seeds=(0,), time_limit=1.0, memory_limit=1 << 30, lanes=1,
                        agent_args={"fault": fault, "after_units": "2", "at_step": "4"})
    start = time.perf_counter()
    with pytest.raises(EvaluationError) as err:
        evaluate(config)
    assert time.perf_counter() - start < 30
    message = str(err.value)
    assert str(FAULTY) in message and "pair 2, seed 0, episode 0, step 4" in message, message
    assert text.lower() in message.lower(), message
    if kind:
        assert err.value.kind == kind
    kept = read_results(out)  # the two finished units are on disk, intact
    assert not kept["complete"] and [(u["pair"], u["seed"]) for u in kept["units"]] == [(0, 0), (1, 0)]


def test_a_failing_lane_is_named_and_the_other_lanes_stop(tmp_path: Path) -> None:
    """With several agents side by side, the error names the unit whose agent failed."""
    config = EvalConfig(agent_path=FAULTY, out=tmp_path / "r.json", seeds=(0,), pairs=(3, 4, 5), lanes=3,
                        agent_args={"fault": "raise", "after_units": "0", "at_step": "6"})
    with pytest.raises(EvaluationError) as err:
        evaluate(config)
    assert "pair 3, seed 0, episode 0, step 6" in str(err.value) and err.value.kind == "exception"


def test_broken_agent_files(tmp_path: Path) -> None:
    bad = tmp_path / "syntax_agent.py"
    bad.write_text("def make_agent(observation_space, action_space):\n    return 1 +\n")
    with pytest.raises(EvaluationError, match=r"syntax_agent\.py.*line 2"):
        run(tmp_path, bad)
    empty = tmp_path / "empty_agent.py"
    empty.write_text("x = 1\n")
    with pytest.raises(EvaluationError, match=r"empty_agent\.py.*make_agent"):
        run(tmp_path, empty, "e.json")
    with pytest.raises(EvaluationError, match="does not exist"):
        run(tmp_path, tmp_path / "missing.py", "m.json")


def test_resume_continues_without_redoing_or_losing_units(tmp_path: Path) -> None:
    flag = tmp_path / "fail-now"
    flag.write_text("")
    args = dict(seeds=(0, 1), lanes=1,
                agent_args={"fault": "raise", "after_units": "5", "at_step": "0", "flag": str(flag)})
    with pytest.raises(EvaluationError):
        run(tmp_path, FAULTY, **args)
    partial = read_results(tmp_path / "r.json")
    assert len(partial["units"]) == 5
    flag.unlink()
    with pytest.raises(ValueError, match="--resume"):
        run(tmp_path, FAULTY, **args)
    resumed, _ = run(tmp_path, FAULTY, resume=True, **args)
    assert resumed["complete"] and len(resumed["units"]) == 32
    assert resumed["units"][:5] == partial["units"]  # finished units kept as they were
    other = dict(args, seeds=(0,))
    with pytest.raises(ValueError, match="cannot resume: seeds differ"):
        run(tmp_path, FAULTY, resume=True, **other)


def test_results_file_is_valid_json_after_every_unit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from mewa_bench.protocol import runner

    monkeypatch.setattr(runner, "WRITE_INTERVAL", 0.0)  # write after every unit (the default throttles to 1 s)
    monkeypatch.setattr(runner, "WRITE_SHARE", 1.0)  # (and to a tenth of the run's time)
    seen = []

    def progress(done: int, total: int) -> None:
        path = tmp_path / "r.json"
        if path.exists():
            seen.append(len(read_results(path)["units"]))

    evaluate(EvalConfig(agent_path=FAULTY, out=tmp_path / "r.json", seeds=(0,), pairs=(0, 1, 2),
                        agent_args={"fault": "none"}), progress=progress)
    assert seen[-3:] == [1, 2, 3] or seen[-4:-1] == [1, 2, 3]


def test_malformed_results_file_is_a_clear_error(tmp_path: Path) -> None:
    from mewa_bench.protocol.results import ResultsError

    results, path = run(tmp_path, FAULTY, agent_args={"fault": "none"}, seeds=(0,), pairs=(0,))
    results["units"][0] = 5
    path.write_text(json.dumps({**results, "schema_version": 2}))
    with pytest.raises(ResultsError, match=r"r\.json: malformed results"):
        read_results(path)
    path.write_text(json.dumps(results))  # schema 3 with its units as a list, not columns
    with pytest.raises(ResultsError, match=r"r\.json: units must be an object with .* in schema 3, got list"):
        read_results(path)
    path.write_text("{not json")
    with pytest.raises(ResultsError, match=r"r\.json: not valid JSON"):
        run(tmp_path, FAULTY, agent_args={"fault": "none"}, seeds=(0,), pairs=(0,), resume=True)


SUBMISSIONS = Path(__file__).resolve().parents[1] / "submissions"


@pytest.mark.parametrize("seeds", [32, pytest.param(None, marks=pytest.mark.slow)],
                         ids=["32-seeds", "default-seeds"])  # 32: control variates apply (from 8), a wider interval
@pytest.mark.parametrize("agent, reference, privileged", [
    ("oracle-t-optimal", "max_expected", True),
    ("random", "random", False),
    ("random-task-specific", "random_task_specific", False),
])
def test_reference_agents_score_their_exact_baseline_within_ci(tmp_path: Path, agent: str, reference: str,
                                                               privileged: bool, seeds: int | None) -> None:
    chosen = {} if seeds is None else {"seeds": tuple(range(seeds))}
    results, _ = run(tmp_path, SUBMISSIONS / agent / "agent.py", isolated=False, privileged=privileged, **chosen)
    mean = results["scores"]["mean"]
    expected = load_suite("narrow-v1").summary["score"][reference]
    assert mean["low"] - 1e-9 <= expected <= mean["high"] + 1e-9, (agent, mean, expected)
    assert results["agent"]["privileged"] == privileged


def test_oracle_refuses_to_run_unprivileged(tmp_path: Path) -> None:
    with pytest.raises(EvaluationError, match="privileged"):
        run(tmp_path, SUBMISSIONS / "oracle-t-optimal" / "agent.py", isolated=False, pairs=(0,))


def test_references_are_over_the_pairs_played() -> None:
    from mewa_bench.design.references import summarise

    suite = load_suite("narrow-v1")
    whole = summarise([p.data for p in suite.pairs])
    for key, value in suite.summary["score"].items():
        assert whole["score"][key] == pytest.approx(value, abs=1e-11)
    some = summarise([p.data for p in suite.pairs[:3]])
    by_hand = np.mean([p.data["baselines"]["random"] / p.max_expected for p in suite.pairs[:3]])
    assert some["score"]["random"] == pytest.approx(by_hand)
    assert some["score"]["random"] != pytest.approx(whole["score"]["random"], abs=0.01)


def test_partial_run_reports_its_own_references(tmp_path: Path) -> None:
    results, _ = run(tmp_path, FAULTY, agent_args={"fault": "none"}, seeds=(0,), pairs=(0, 1, 2))
    assert results["baselines"]["pairs"] == [0, 1, 2] and not results["complete"]
    rts = results["baselines"]["score"]["random_task_specific"]
    assert results["scores"]["skill"]["mean"] == pytest.approx((results["scores"]["mean"]["mean"] - rts) / (1 - rts))


def test_repeated_seeds_or_pairs_are_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="repeat"):
        run(tmp_path, FAULTY, seeds=(0, 0))
    with pytest.raises(ValueError, match="repeat"):
        run(tmp_path, FAULTY, seeds=(0,), pairs=(1, 1))


def test_overwrite_and_resume_with_a_changed_agent(tmp_path: Path) -> None:
    agent = tmp_path / "my_agent.py"
    agent.write_text(FAULTY.read_text())
    args = dict(agent_args={"fault": "none"}, seeds=(0,), pairs=(0,))
    run(tmp_path, agent, **args)
    again, _ = run(tmp_path, agent, overwrite=True, **args)
    assert len(again["units"]) == 1
    agent.write_text(FAULTY.read_text() + "\n# changed\n")
    with pytest.raises(ValueError, match="agent file changed"):
        run(tmp_path, agent, resume=True, **args)
