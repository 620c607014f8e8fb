"""Agent loading, action checking and the isolated / in-process agent runners."""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
from gymnasium import spaces

import mewa_bench
from mewa_bench.envs.mewa_env import MewaEnv
from mewa_bench.protocol.agent import (AgentLoadError, Transition, agent_sha256, check_action,
                                       load_agent)
from mewa_bench.protocol.isolation import (AgentError, InProcessAgent, IsolatedAgent,
                                           make_agent_runner)

AGENTS = Path(__file__).resolve().parent / "agents"
OBSERVATION_SPACE = spaces.Box(0.0, 255.0, shape=(18,), dtype=np.float32)
ACTION_SPACE = spaces.Discrete(4)
OBS = np.arange(18, dtype=np.float32)
NEXT_OBS = OBS + 1


def runner(name: str, isolated: bool, **kwargs):
    """A runner for the fixture agent `name` with the MEWA spaces."""
    return make_agent_runner(AGENTS / name, OBSERVATION_SPACE, ACTION_SPACE, isolated=isolated, **kwargs)


def faulty(fault: str, isolated: bool = True, value: str = "0", **limits):
    """A runner for the faulty agent, misbehaving as `fault` says."""
    return runner("faulty_agent.py", isolated, agent_args={"fault": fault, "value": value}, **limits)


def assert_reaped(pid: int) -> None:
    """The process `pid` has exited and been waited for (a zombie would still exist)."""
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def read_log(path: Path) -> list[dict]:
    """The calls the recording agent logged."""
    return [json.loads(line) for line in path.read_text().splitlines()]


# -- loading --------------------------------------------------------------------------------------
def test_load_make_agent_style_passes_agent_args_and_checkpoint():
    agent = load_agent(AGENTS / "recording_agent.py", OBSERVATION_SPACE, ACTION_SPACE,
                       {"start": "2", "lr": "0.1"}, checkpoint="ckpt.pt")
    assert (agent.start, agent.extra) == (2, {"lr": "0.1", "checkpoint": "ckpt.pt"})
    assert agent.act(OBS) == 2 and agent.act(OBS) == 3
    assert type(agent).__module__.startswith("_mewa_agent_")


def test_load_class_style_reads_its_checkpoint(tmp_path):
    checkpoint = tmp_path / "action.txt"
    checkpoint.write_text("3")
    agent = load_agent(str(AGENTS / "class_agent.py"), OBSERVATION_SPACE, ACTION_SPACE, checkpoint=str(checkpoint))
    assert agent.act(OBS) == 3
    assert not hasattr(agent, "observe")


def test_each_load_is_a_fresh_module():
    first = load_agent(AGENTS / "class_agent.py", OBSERVATION_SPACE, ACTION_SPACE)
    second = load_agent(AGENTS / "class_agent.py", OBSERVATION_SPACE, ACTION_SPACE)
    assert type(first) is not type(second)


def test_agent_sha256_is_of_the_file_bytes(tmp_path):
    file = tmp_path / "a.py"
    file.write_bytes(b"x = 1\n")
    assert agent_sha256(file) == hashlib.sha256(b"x = 1\n").hexdigest()


def test_checkpoint_given_twice():
    with pytest.raises(AgentLoadError, match=r"class_agent\.py: the checkpoint is given twice"):
        load_agent(AGENTS / "class_agent.py", OBSERVATION_SPACE, ACTION_SPACE, {"checkpoint": "a"}, checkpoint="b")


def test_missing_file():
    with pytest.raises(AgentLoadError, match=r"nowhere\.py does not exist"):
        load_agent(AGENTS / "nowhere.py", OBSERVATION_SPACE, ACTION_SPACE)


def test_syntax_error_names_file_and_line(tmp_path):
    file = tmp_path / "broken_agent.py"
    file.write_text("def make_agent(observation_space, action_space):\n    return 1\n\ndef act(:\n")
    with pytest.raises(AgentLoadError, match=r"broken_agent\.py: syntax error at line 4"):
        load_agent(file, OBSERVATION_SPACE, ACTION_SPACE)


def test_exception_at_import_gives_the_exception():
    with pytest.raises(AgentLoadError, match=r"import_error_agent\.py: importing it raised ModuleNotFoundError: "
                                             r"No module named 'a_module_that_does_not_exist' \(at .*line 3\)"):
        load_agent(AGENTS / "import_error_agent.py", OBSERVATION_SPACE, ACTION_SPACE)


def test_missing_api():
    with pytest.raises(AgentLoadError, match=r"no_api_agent\.py defines neither .*make_agent.* nor a class Agent"):
        load_agent(AGENTS / "no_api_agent.py", OBSERVATION_SPACE, ACTION_SPACE)


def test_object_without_act():
    with pytest.raises(AgentLoadError, match=r"no_act_agent\.py: make_agent\(\.\.\.\) returned a Policy object, "
                                             r"which has no act\(observation\) method"):
        load_agent(AGENTS / "no_act_agent.py", OBSERVATION_SPACE, ACTION_SPACE)


def test_construction_failure_and_unknown_agent_arg():
    with pytest.raises(AgentLoadError, match=r"Agent\(observation_space, action_space, fault='raise_at_init'\) "
                                             r"raised RuntimeError: cannot build this agent"):
        load_agent(AGENTS / "faulty_agent.py", OBSERVATION_SPACE, ACTION_SPACE, {"fault": "raise_at_init"})
    with pytest.raises(AgentLoadError, match="unexpected keyword argument 'colour'"):
        load_agent(AGENTS / "class_agent.py", OBSERVATION_SPACE, ACTION_SPACE, {"colour": "red"})


# -- actions --------------------------------------------------------------------------------------
@pytest.mark.parametrize("value", [0, 3, np.int64(2), np.uint8(1), np.array(3), np.array(1, dtype=np.int32)])
def test_check_action_accepts_integers_in_range(value):
    action = check_action(value, 4)
    assert type(action) is int and action == int(value)


@pytest.mark.parametrize("value, problem", [
    (4, "out of range"), (-1, "out of range"), (np.int64(7), "out of range"), (True, "not an integer"),
    (np.bool_(True), "not an integer"), (1.0, "not an integer"), (np.float32(2), "not an integer"),
    ("a", "not an integer"), (None, "not an integer"), (np.array([1]), "not an integer"),
    (np.array(1.0), "not an integer"),
])
def test_check_action_rejects_everything_else(value, problem):
    with pytest.raises(ValueError, match=f"act\\(\\) returned .*{problem}: expected an int in 0..3"):
        check_action(value, 4)


# -- runners: a good agent ------------------------------------------------------------------------
@pytest.mark.parametrize("isolated", [True, False])
def test_runner_calls_every_method_in_order(tmp_path, isolated):
    log = tmp_path / "calls.jsonl"
    with runner("recording_agent.py", isolated, agent_args={"log": str(log), "start": "1"},
                checkpoint="model.bin") as agent:
        agent.reset_task()
        first = agent.step(None, OBS)
        second = agent.step(Transition(OBS, first, -0.5, NEXT_OBS, False, False), NEXT_OBS)
        agent.end_episode(Transition(NEXT_OBS, second, 0.0, NEXT_OBS, True, False))
        assert (first, second) == (1, 2)
        agent.reset_task()
        assert agent.act(OBS) == 1
        agent.observe(Transition(OBS, 1, -1.0, NEXT_OBS, False, True))
        agent.end_episode()
    calls = read_log(log)
    assert [call["call"] for call in calls] == ["init", "reset_task", "act", "observe", "act", "observe",
                                                "end_episode", "reset_task", "act", "observe", "end_episode"]
    assert calls[0]["extra"] == {"checkpoint": "model.bin"} and calls[0]["start"] == "1"
    assert calls[0]["obs_shape"] == [18] and calls[0]["num_actions"] == 4
    assert calls[2] == {"call": "act", "obs_type": "ndarray", "obs": OBS.tolist()}
    assert calls[3] == {"call": "observe", "action": 1, "reward": -0.5, "obs": OBS.tolist(),
                        "next_obs": NEXT_OBS.tolist(), "terminated": False, "truncated": False}
    assert calls[5]["terminated"] is True and calls[9]["truncated"] is True


@pytest.mark.parametrize("isolated", [True, False])
def test_agent_without_optional_methods(tmp_path, isolated):
    checkpoint = tmp_path / "action.txt"
    checkpoint.write_text("2")
    agent = runner("class_agent.py", isolated, checkpoint=str(checkpoint))
    agent.reset_task()
    assert agent.step(None, OBS) == 2
    assert agent.step(Transition(OBS, 2, -0.1, NEXT_OBS, False, False), NEXT_OBS) == 2
    agent.end_episode(Transition(NEXT_OBS, 2, 0.0, NEXT_OBS, True, False))
    agent.close()
    agent.close()
    with pytest.raises(RuntimeError, match="closed"):
        agent.act(OBS)


def test_closing_reaps_the_child():
    agent = runner("class_agent.py", isolated=True)
    assert agent.act(OBS) == 0
    agent.close()
    assert_reaped(agent.pid)


# -- runners: failures ----------------------------------------------------------------------------
@pytest.mark.parametrize("isolated", [True, False])
def test_load_errors_come_back_with_the_loaders_message(tmp_path, isolated):
    file = tmp_path / "broken_agent.py"
    file.write_text("x = (\n")
    with pytest.raises(AgentLoadError) as direct:
        load_agent(file, OBSERVATION_SPACE, ACTION_SPACE)
    with pytest.raises(AgentError) as via_runner:
        make_agent_runner(file, OBSERVATION_SPACE, ACTION_SPACE, isolated=isolated)
    assert via_runner.value.kind == "load" and str(via_runner.value) == str(direct.value)


@pytest.mark.parametrize("isolated", [True, False])
def test_exception_in_act(isolated):
    agent = faulty("raise", isolated)
    with pytest.raises(AgentError) as caught:
        agent.act(OBS)
    error = caught.value
    assert error.kind == "exception"
    message = str(error)
    assert "faulty_agent.py: act() raised ValueError: boom: the agent's act failed" in message
    assert "agent traceback" in message and "in misbehave" in message and 'raise ValueError("boom' in message
    assert "mewa_bench/protocol/" not in message  # the runner's own frames are left out
    with pytest.raises(AgentError, match="boom") as again:
        agent.act(OBS)
    assert again.value.kind == "exception"
    if isolated:
        assert_reaped(agent.pid)


@pytest.mark.parametrize("isolated", [True, False])
def test_sys_exit_in_act_is_an_exception(isolated):
    with faulty("sys_exit", isolated) as agent:
        with pytest.raises(AgentError, match=r"act\(\) raised SystemExit: 5") as caught:
            agent.act(OBS)
    assert caught.value.kind == "exception"


def test_exception_in_observe_names_observe():
    with faulty("raise_in_observe") as agent:
        with pytest.raises(AgentError, match=r"observe\(\) raised KeyError: 'missing'"):
            agent.step(Transition(OBS, 0, -1.0, NEXT_OBS, False, False), NEXT_OBS)


@pytest.mark.parametrize("isolated", [True, False])
@pytest.mark.parametrize("value", ["7", "1.5", "'a'", "True"])
def test_invalid_action(isolated, value):
    agent = faulty("return", isolated, value=value)
    with pytest.raises(AgentError, match=f"act\\(\\) returned {value} ") as caught:
        agent.step(None, OBS)
    assert caught.value.kind == "invalid_action"
    if isolated:
        assert_reaped(agent.pid)


def test_hang_is_killed_at_the_time_limit():
    agent = faulty("hang", time_limit=1.0)
    agent.reset_task()  # the first call after loading gets the (longer) load time limit
    started = time.monotonic()
    with pytest.raises(AgentError, match=r"act\(\) did not finish within the time limit of 1 s") as caught:
        agent.act(OBS)
    assert caught.value.kind == "timeout"
    assert time.monotonic() - started < 2.5
    assert_reaped(agent.pid)


def test_memory_blow_up_is_stopped_by_the_memory_limit():
    agent = faulty("memory", memory_limit=1 << 30)
    with pytest.raises(AgentError) as caught:
        agent.act(OBS)
    assert caught.value.kind in ("memory", "crash")
    assert "MemoryError" in str(caught.value) and "1 GiB" in str(caught.value)
    assert_reaped(agent.pid)


@pytest.mark.parametrize("fault, how", [("exit", "exit code 3"), ("segfault", "killed by signal SIGSEGV")])
def test_a_dying_child_is_reported_and_the_parent_carries_on(fault, how):
    agent = faulty(fault)
    with pytest.raises(AgentError, match=rf"the agent process died during act\(\) \({how}\)") as caught:
        agent.act(OBS)
    assert caught.value.kind == "crash"
    assert_reaped(agent.pid)
    with runner("class_agent.py", isolated=True) as healthy:
        assert healthy.act(OBS) == 0


def test_isolated_agent_cannot_see_the_parent(monkeypatch, small_task):
    monkeypatch.setattr(mewa_bench, "_parent_marker", "hidden worker", raising=False)
    env = MewaEnv(task=small_task, worker=(0.5, 0.3, 0.15))
    with faulty("spy", isolated=False) as in_process, faulty("spy", isolated=True) as isolated:
        assert in_process.act(OBS) == 3  # the marker and the env are both within reach in-process
        assert isolated.act(OBS) == 0
    assert env.worker is not None


def test_make_agent_runner_types_and_discrete_check():
    with runner("class_agent.py", isolated=False) as agent:
        assert isinstance(agent, InProcessAgent) and agent.name == "class_agent.py"
    with runner("class_agent.py", isolated=True) as agent:
        assert isinstance(agent, IsolatedAgent)
    with pytest.raises(ValueError, match="Discrete"):
        make_agent_runner(AGENTS / "class_agent.py", OBSERVATION_SPACE, spaces.Discrete(4, start=1))


# -- lanes: several agent objects, one round trip per batch of calls --------------------------------

@pytest.mark.parametrize("isolated", [True, False])
def test_lanes_are_independent_agents_answering_one_batch(isolated: bool) -> None:
    from mewa_bench.protocol.isolation import END_EPISODE, RESET_TASK, STEP

    with runner("recording_agent.py", isolated, agent_args={"start": "1"}, lanes=3) as agents:
        assert agents.lanes == 3
        assert agents.batch([(0, RESET_TASK, (None, None)), (2, RESET_TASK, (None, None))]) == [None, None]
        first = agents.batch([(0, STEP, (None, OBS)), (1, STEP, (None, OBS)), (2, STEP, (None, OBS))])
        again = agents.batch([(0, STEP, (None, OBS)), (2, STEP, (None, OBS))])
        assert first == [1, 1, 1] and again == [2, 2]  # each lane counts its own acts
        transition = Transition(OBS, 2, -1.0, NEXT_OBS, True, False)
        assert agents.batch([(1, END_EPISODE, (transition,))]) == [None]


def test_a_hang_inside_a_batch_is_stopped_at_the_per_call_limit_and_named() -> None:
    from mewa_bench.protocol.isolation import RESET_TASK, STEP

    agent = faulty("hang", time_limit=1.0, lanes=4)
    agent.batch([(lane, RESET_TASK, (None, None)) for lane in range(4)])
    started = time.monotonic()
    with pytest.raises(AgentError, match=r"observe\(\)/act\(\) did not finish within the time limit of 1 s") as caught:
        agent.batch([(lane, STEP, (None, OBS)) for lane in range(4)])
    assert caught.value.kind == "timeout" and caught.value.index == 0
    assert time.monotonic() - started < 2.5  # the child's own timer, not 4 x the limit
    assert_reaped(agent.pid)


def test_reset_task_passes_the_unit_seed_only_to_agents_that_take_one(tmp_path: Path) -> None:
    seeded = tmp_path / "seeded_agent.py"
    seeded.write_text("class Agent:\n    def __init__(self, o, a):\n        self.seen = None\n"
                      "    def reset_task(self, seed=None):\n        self.seen = seed\n"
                      "    def act(self, obs):\n        return self.seen % 4\n")
    plain = tmp_path / "plain_agent.py"
    plain.write_text("class Agent:\n    def __init__(self, o, a):\n        pass\n"
                     "    def reset_task(self):\n        pass\n    def act(self, obs):\n        return 3\n")
    for isolated in (True, False):
        with make_agent_runner(seeded, OBSERVATION_SPACE, ACTION_SPACE, isolated=isolated) as agent:
            agent.reset_task(None, 4 * 1000 + 2)
            assert agent.act(OBS) == 2
        with make_agent_runner(plain, OBSERVATION_SPACE, ACTION_SPACE, isolated=isolated) as agent:
            agent.reset_task(None, 7)  # no seed parameter: called without it
            assert agent.act(OBS) == 3
