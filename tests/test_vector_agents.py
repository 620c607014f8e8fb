"""Batched (vector) agents: one object plays every lane of an agent process.

The test agent (`agents/vector_agent.py`) computes its actions in exact integer arithmetic, so any
difference between runs is the runner's doing: results must be the same function of (agent, seeds)
whatever the number of lanes, jobs or isolation, and equal to its one-lane twin's. Every malformed
answer is caught with an error that names the file and the lane's pair, seed, episode and step, and
the finished units stay on disk for --resume.
"""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mewa_bench.protocol.agent import SingleLane, Transition, check_actions, load_agent, load_lanes
from mewa_bench.protocol.config import EPISODES_PER_PAIR, EvalConfig
from mewa_bench.protocol.results import read_results
from mewa_bench.protocol.runner import EvaluationError, evaluate

AGENTS = Path(__file__).parent / "agents"
VECTOR, TWIN = AGENTS / "vector_agent.py", AGENTS / "vector_twin_agent.py"
REPO = Path(__file__).resolve().parents[1]
PAIRS, SEEDS = (0, 3, 7, 12), (0, 1, 2)


def run(tmp_path: Path, name: str, agent: Path = VECTOR, **kw) -> dict:
    kw = {"suite": "narrow-v2", "seeds": SEEDS, "pairs": PAIRS, **kw}
    results, _ = evaluate(EvalConfig(agent_path=agent, out=tmp_path / name, **kw))
    return results


def units(results: dict) -> str:
    """The played units, as bytes, in (pair, seed) order."""
    return json.dumps(sorted(results["units"], key=lambda u: (u["pair"], u["seed"])), sort_keys=True)


@pytest.mark.parametrize("sampled", ["false", "true"])
def test_results_do_not_depend_on_lanes_jobs_or_isolation_and_equal_the_one_lane_twin(tmp_path: Path,
                                                                                      sampled: str) -> None:
    args = {"agent_args": {"sampled": sampled, "seed": "5"}}
    reference = run(tmp_path, "lanes1.json", lanes=1, **args)
    assert len(reference["units"]) == len(PAIRS) * len(SEEDS)
    for name, kw in (("lanes5.json", {"lanes": 5}), ("lanes64.json", {"lanes": 64}),
                     ("jobs2.json", {"lanes": 2, "jobs": 2}), ("inprocess.json", {"lanes": 3, "isolated": False})):
        assert units(run(tmp_path, name, **kw, **args)) == units(reference), name
    twin = run(tmp_path, "twin.json", agent=TWIN, lanes=4, **args)
    assert units(twin) == units(reference)
    assert twin["scores"] == reference["scores"]


def test_sampled_and_greedy_play_differ_so_the_generators_are_used(tmp_path: Path) -> None:
    greedy = run(tmp_path, "g.json", lanes=4, seeds=(0,), agent_args={"sampled": "false"})
    sampled = run(tmp_path, "s.json", lanes=4, seeds=(0,), agent_args={"sampled": "true"})
    assert units(greedy) != units(sampled)


MALFORMED = [
    ("raise", "exception", r"act\(\) for 2 lanes raised ZeroDivisionError: the vector agent divided by zero"),
    ("short", "invalid_action", r"act\(\) returned shape \(1,\) for 2 lanes: expected an integer array of shape \(2,\)"),
    ("two_d", "invalid_action", r"act\(\) returned shape \(2, 1\) for 2 lanes"),
    ("float", "invalid_action", r"act\(\) returned an array of dtype float64: expected integer actions"),
    ("nan", "invalid_action", r"act\(\) returned NaN in a float64 array"),
    ("range", "invalid_action", r"act\(\) returned action 7, out of range: expected an int in 0..3"),
]


@pytest.mark.parametrize("isolated", [True, False], ids=["isolated", "in-process"])
@pytest.mark.parametrize("fault,kind,message", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_a_malformed_batched_answer_names_the_lane_and_resume_finishes_the_run(
        tmp_path: Path, fault: str, kind: str, message: str, isolated: bool) -> None:
    flag = tmp_path / "armed"
    flag.write_text("")
    args = {"agent_args": {"fault": fault, "at_call": "700", "flag": str(flag)}, "lanes": 2, "isolated": isolated,
            "seeds": (0, 1), "pairs": (0, 3, 7)}
    with pytest.raises(EvaluationError) as caught:
        run(tmp_path, "run.json", **args)
    text = str(caught.value)
    assert caught.value.kind == kind and re.search(message, text), text
    assert re.search(r"agent \S*vector_agent\.py, pair \d+, seed \d, episode \d, step \d+", text), text
    kept = read_results(tmp_path / "run.json")
    assert 1 <= len(kept["units"]) < 6  # units finished before the fault are on disk
    flag.unlink()
    resumed = run(tmp_path, "run.json", resume=True, **args)
    clean = run(tmp_path, "clean.json", **{**args, "agent_args": {}})
    assert units(resumed) == units(clean)


@pytest.mark.parametrize("fault,kind,message", [
    ("hang", "timeout", r"act\(\) for 2 lanes did not finish within the time limit of 1 s"),
    ("crash", "crash", r"the agent process died during a batch of 2 calls \(exit code 3\)"),
    ("memory", "memory", r"MemoryError.*\n.*the agent ran out of memory \(its limit is 1 GiB\)"),
])
def test_a_hanging_dying_or_bloated_vector_agent_is_stopped_and_named(tmp_path: Path, fault: str, kind: str,
                                                                      message: str) -> None:
    args = {"agent_args": {"fault": fault, "at_call": "700"}, "lanes": 2, "seeds": (0, 1), "pairs": (0, 3, 7),
            "time_limit": 1.0, "memory_limit": 1 << 30}
    with pytest.raises(EvaluationError) as caught:
        run(tmp_path, "run.json", **args)
    text = str(caught.value)
    assert caught.value.kind == kind and re.search(message, text, re.DOTALL), text
    assert re.search(r"agent \S*vector_agent\.py, pair \d+, seed \d, episode \d, step \d+"
                     + (r" \(the first of a batch of 2 lanes\)" if fault == "crash" else ":"), text), text
    assert 1 <= len(read_results(tmp_path / "run.json")["units"]) < 6


def test_check_actions_accepts_integer_arrays_lists_and_tensors_only() -> None:
    torch = pytest.importorskip("torch")
    for good in (np.array([0, 3], dtype=np.int32), [1, 2], torch.tensor([3, 0])):
        assert check_actions(good, 2, 4).tolist() == np.asarray(good).tolist()
    for bad in (np.array([0.0, 1.0]), [[0, 1]], np.array([0, 4]), np.array([-1, 0]), "01", None):
        with pytest.raises(ValueError):
            check_actions(bad, 2, 4)


def test_load_lanes_prefers_the_vector_agent_and_a_vector_only_file_loads_as_one_lane() -> None:
    from gymnasium import spaces

    from mewa_bench.envs.mewa_env import MewaEnv

    env = MewaEnv()
    vector = load_lanes(VECTOR, env.observation_space, env.action_space, 3)
    assert not isinstance(vector, list) and vector.memory.shape == (3,)
    assert isinstance(load_lanes(TWIN, env.observation_space, env.action_space, 3), list)
    one = load_agent(VECTOR, env.observation_space, env.action_space, {"sampled": "true"})
    assert isinstance(one, SingleLane)
    twin = load_agent(TWIN, env.observation_space, env.action_space, {"sampled": "true"})
    obs, _ = env.reset(seed=3)
    for agent in (one, twin):
        agent.reset_task(seed=11)
    for _ in range(20):  # the one-lane view of the vector agent plays as its twin does
        action = one.act(obs)
        assert action == twin.act(obs)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        for agent in (one, twin):
            agent.observe(Transition(obs, action, float(reward), next_obs, terminated, truncated))
        obs = next_obs
        if terminated or truncated:
            break
    assert isinstance(spaces.Discrete(4), spaces.Discrete)


def test_the_readme_batched_gru_example_runs_under_evaluate(tmp_path: Path) -> None:
    pytest.importorskip("torch")
    readme = (REPO / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", readme, re.S)
    example = next(b for b in blocks if "class VectorAgent" in b and "import torch" in b)
    agent = tmp_path / "my_batched_agent.py"
    agent.write_text(example)
    one = run(tmp_path, "lanes4.json", agent=agent, lanes=4, seeds=(0,), pairs=(0, 1))
    again = run(tmp_path, "lanes4-again.json", agent=agent, lanes=4, seeds=(0,), pairs=(0, 1))
    assert len(one["units"]) == 2 and units(one) == units(again)  # seeded: same seeds, same play


def test_agent_processes_run_one_compute_thread_unless_the_user_sets_a_number(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    from mewa_bench.envs.mewa_env import MewaEnv
    from mewa_bench.protocol.isolation import make_agent_runner

    agent = tmp_path / "threads_agent.py"
    agent.write_text("import os\n\nclass Agent:\n    def __init__(self, o, a):\n        pass\n\n"
                     "    def act(self, obs):\n        return int(os.environ.get('OMP_NUM_THREADS', '0'))\n")
    env = MewaEnv()
    obs, _ = env.reset(seed=0)
    for value, expected in ((None, 1), ("3", 3)):
        if value is None:
            monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
        else:
            monkeypatch.setenv("OMP_NUM_THREADS", value)
        with make_agent_runner(agent, env.observation_space, env.action_space) as runner:
            assert runner.act(obs) == expected


def test_a_logged_vector_agent_run_records_every_step(tmp_path: Path) -> None:
    """MCAP and Rerun logs of a batched run, read back with each format's reader: every step, every episode."""
    pytest.importorskip("mcap")
    pytest.importorskip("rerun")
    from mcap.reader import make_reader
    from test_logs import rrd_rows, verify_rrd

    from mewa_bench.logs import McapSink, RerunSink
    from mewa_bench.logs.mcap_log import TOPIC_STEP
    from mewa_bench.logs.rerun_log import ACTION, SCORE

    config = EvalConfig(agent_path=VECTOR, out=tmp_path / "r.json", suite="narrow-v2", seeds=(0,), pairs=(0, 3),
                        lanes=2)
    sinks = [McapSink(tmp_path / "run.mcap"), RerunSink(tmp_path / "run.rrd")]
    results, _ = evaluate(config, sinks=sinks)
    with open(tmp_path / "run.mcap", "rb") as f:
        topics = [c.topic for _, c, _ in make_reader(f).iter_messages()]
    steps = sum(sum(u["lengths"]) for u in results["units"])
    assert steps > 0 and topics.count(TOPIC_STEP) == steps
    verify_rrd(tmp_path / "run.rrd")
    assert len(rrd_rows(tmp_path / "run.rrd", f"/{ACTION}")) == steps
    scores = {(r["pair"], r["episode"]) for r in rrd_rows(tmp_path / "run.rrd", f"/{SCORE}")}
    assert scores == {(p, k) for p in (0, 3) for k in range(10)}


LOGGED = '''import json
import importlib.util

spec = importlib.util.spec_from_file_location("vector_agent", {base!r})
base = importlib.util.module_from_spec(spec)
spec.loader.exec_module(base)


class VectorAgent(base.VectorAgent):
    """The test agent, writing which lanes begin a unit (reset_task) and end an episode to `log`, in call order."""

    def __init__(self, observation_space, action_space, num_lanes, log, **kwargs):
        super().__init__(observation_space, action_space, num_lanes, **kwargs)
        self.log = log

    def record(self, call, lanes):
        with open(self.log, "a") as f:
            f.write(json.dumps([call, [int(lane) for lane in lanes]]) + "\\n")

    def reset_task(self, lanes, seeds):
        self.record("reset", lanes)
        super().reset_task(lanes, seeds)

    def end_episode(self, lanes):
        self.record("end", lanes)
        super().end_episode(lanes)
'''


def test_a_lane_whose_unit_ends_begins_the_next_unit_waiting(tmp_path: Path) -> None:
    """Three units on two lanes: the lane that finishes first plays the third, whichever lane that is (dealt in turn,
    lane 0 would play it after its own first unit and leave lane 1 idle)."""
    agent, log = tmp_path / "logged_agent.py", tmp_path / "calls.jsonl"
    agent.write_text(LOGGED.format(base=str(VECTOR)))
    run(tmp_path, "r.json", agent=agent, lanes=2, pairs=(0,), seeds=(0, 1, 2), isolated=False,
        agent_args={"log": str(log)})
    calls = [json.loads(line) for line in log.read_text().splitlines()]
    assert calls[0] == ["reset", [0, 1]]
    episodes, first_done = {0: 0, 1: 0}, None
    for at, (call, lanes) in enumerate(calls):
        if call == "end":
            for lane in lanes:
                episodes[lane] += 1
            done = [lane for lane in lanes if episodes[lane] == EPISODES_PER_PAIR]
            if done and first_done is None:
                first_done = done[0]
                begins = next(i for i in range(at + 1, len(calls)) if calls[i][0] == "reset")
                assert calls[begins] == ["reset", [first_done]] and begins - at <= 2  # in the next round (after
                # the other lane's end of episode, when it has one in that round)
    assert first_done == 1  # the seeds make lane 1's unit the shorter: dealt in turn, it would have stayed idle
    assert sum(call == "reset" for call, _ in calls) == 2
