"""MCAP and Rerun logs of evaluation runs (SPEC section 8), read back and checked against the results."""

from __future__ import annotations

import base64
import io
import json
import signal
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader
from PIL import Image
from rerun.chunk import RrdReader
from typer.testing import CliRunner

from mewa_bench.cli import app
from mewa_bench.design.suites import load_suite
from mewa_bench.game.rules import Event
from mewa_bench.logs import McapSink, RerunSink, open_viewer, view, viewer_command
from mewa_bench.logs.common import event_message
from mewa_bench.logs.mcap_log import HALF_TICK_NS, TICK_NS
from mewa_bench.logs.rerun_log import recording_id
from mewa_bench.logs.view import ViewerError
from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.results import read_results
from mewa_bench.protocol.runner import EvaluationError, evaluate, run_info
from mewa_bench.protocol.agent import Transition
from mewa_bench.protocol.trajectory import EpisodeRecord, RunInfo, StepRecord, UnitRecord

AGENT = Path(__file__).parent / "agents" / "delayed_fault_agent.py"
LEVELS = {"mistake": 3, "structure_returned": 3, "structure_completed": 2, "subgoal_reached": 2}


@pytest.fixture(autouse=True, scope="module")
def strict_rerun():
    """Rerun raises on misuse instead of warning."""
    before = rr.strict_mode()
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(before)


# --- a minimal JSON Schema validator for the keywords the logs use (jsonschema is not a dependency) ---

_ANNOTATIONS = {"title", "description", "contentEncoding", "$comment"}
_KEYWORDS = _ANNOTATIONS | {"type", "properties", "required", "additionalProperties", "items", "minItems",
                            "maxItems", "minimum", "maximum", "enum", "const", "oneOf"}
_TYPES = {"object": dict, "array": list, "string": str, "boolean": bool}


def _has_type(value: Any, name: str) -> bool:
    """JSON type check, with booleans not counted as numbers."""
    if name in _TYPES:
        return isinstance(value, _TYPES[name])
    if isinstance(value, bool):
        return False
    return isinstance(value, int) if name == "integer" else isinstance(value, (int, float))


def _equal(a: Any, b: Any) -> bool:
    """JSON equality (true is not 1)."""
    return isinstance(a, bool) == isinstance(b, bool) and a == b


def schema_errors(value: Any, schema: dict[str, Any], where: str = "$") -> list[str]:
    """Why `value` does not satisfy `schema` (empty if it does)."""
    unknown = set(schema) - _KEYWORDS
    if unknown:
        raise ValueError(f"{where}: the test validator does not know {sorted(unknown)}")
    if "type" in schema and not _has_type(value, schema["type"]):
        return [f"{where}: {value!r} is not of type {schema['type']}"]
    errors = []
    if "const" in schema and not _equal(value, schema["const"]):
        errors.append(f"{where}: {value!r} is not {schema['const']!r}")
    if "enum" in schema and not any(_equal(value, v) for v in schema["enum"]):
        errors.append(f"{where}: {value!r} not in {schema['enum']}")
    if "minimum" in schema and value < schema["minimum"]:
        errors.append(f"{where}: {value} < {schema['minimum']}")
    if "maximum" in schema and value > schema["maximum"]:
        errors.append(f"{where}: {value} > {schema['maximum']}")
    if "oneOf" in schema:
        matches = sum(not schema_errors(value, s, where) for s in schema["oneOf"])
        if matches != 1:
            errors.append(f"{where}: {value!r} matches {matches} of oneOf, not exactly 1")
    if isinstance(value, dict):
        properties = schema.get("properties", {})
        errors += [f"{where}: missing {k!r}" for k in schema.get("required", []) if k not in value]
        if schema.get("additionalProperties", True) is False:
            errors += [f"{where}: unexpected {k!r}" for k in value if k not in properties]
        for key, sub in properties.items():
            if key in value:
                errors += schema_errors(value[key], sub, f"{where}.{key}")
    if isinstance(value, list):
        if len(value) < schema.get("minItems", 0) or len(value) > schema.get("maxItems", len(value)):
            errors.append(f"{where}: {len(value)} items")
        if "items" in schema:
            for i, item in enumerate(value):
                errors += schema_errors(item, schema["items"], f"{where}[{i}]")
    return errors


# --- reading the files back ---

def read_mcap(path: Path) -> dict[str, Any]:
    """Header, metadata, schemas and decoded messages per topic (in file order) of a finished MCAP file."""
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None, f"{path} has no summary: the file was not finished"
        out: dict[str, Any] = {"header": reader.get_header(), "summary": summary,
                               "metadata": {m.name: m.metadata for m in reader.iter_metadata()},
                               "schemas": {}, "messages": {c.topic: [] for c in summary.channels.values()},
                               "times": {c.topic: [] for c in summary.channels.values()}}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            out["schemas"][channel.topic] = (schema.name, json.loads(schema.data))
            out["messages"][channel.topic].append(json.loads(message.data))
            out["times"][channel.topic].append((message.log_time, message.publish_time))
    return out


def rrd_rows(path: Path, entity: str) -> list[dict[str, Any]]:
    """Non-static rows logged to one entity of an .rrd file, in global-step order."""
    rows = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity and not chunk.is_static:
            columns = chunk.to_record_batch().to_pydict()
            rows += [dict(zip(columns, values)) for values in zip(*columns.values())]
    return sorted(rows, key=lambda r: r["global_step"])


def blueprint_views(path: Path) -> set[tuple[str, str]]:
    """(view class, view name) of the default blueprint in an .rrd file."""
    reader = RrdReader(path)
    [blueprint] = reader.blueprints()
    views = set()
    for chunk in reader.stream(store=blueprint):
        columns = chunk.to_record_batch().to_pydict()
        if "ViewBlueprint:class_identifier" in columns:
            views |= {(c[0], n[0]) for c, n in zip(columns["ViewBlueprint:class_identifier"],
                                                     columns["ViewBlueprint:display_name"])}
    return views


def verify_rrd(path: Path) -> None:
    """`rerun rrd verify`: the file loads, with its footer (so it was finished)."""
    out = subprocess.run([view.rerun_executable(), "rrd", "verify", str(path)], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr


def log_sinks(tmp: Path) -> list[Any]:
    """Both sinks, writing `run.mcap` and `run.rrd`; callers keep them referenced, so that only
    `close()` (not garbage collection) can have finished the files."""
    return [McapSink(tmp / "run.mcap"), RerunSink(tmp / "run.rrd")]


def run_logged(tmp: Path, agent_args: dict[str, str], sinks: list[Any], **kwargs: Any) -> Path:
    """Evaluate the test agent on pairs 0 and 1 (seed 0) with the sinks attached; the results file."""
    config = EvalConfig(agent_path=AGENT, out=tmp / "r.json", agent_args=agent_args, seeds=(0,), pairs=(0, 1),
                        isolated=False, lanes=1)  # one agent: units in order, as the fault arguments count them
    evaluate(config, sinks=sinks, **kwargs)
    return tmp / "r.json"


@pytest.fixture(scope="module")
def healthy(tmp_path_factory) -> dict[str, Any]:
    """One real evaluation (2 units of 10 episodes) logged to MCAP and Rerun."""
    tmp = tmp_path_factory.mktemp("logs")
    sinks = log_sinks(tmp)
    results = read_results(run_logged(tmp, {"fault": "none"}, sinks))
    config = EvalConfig(agent_path=AGENT, seeds=(0,), pairs=(0, 1), isolated=False)
    return {"results": results, "mcap": read_mcap(tmp / "run.mcap"), "rrd": tmp / "run.rrd", "sinks": sinks,
            "run": run_info(config, load_suite("narrow-v1"), results)}


def episodes_of(results: dict[str, Any]) -> list[dict[str, Any]]:
    """The results' episodes, unit by unit, as the logs should list them."""
    return [{"pair": u["pair"], "seed": u["seed"], "episode": k, "task": u["task"], "env_seed": u["env_seeds"][k],
             "return": u["returns"][k], "normalised_return": u["normalised_returns"][k], "score": u["scores"][k],
             "length": u["lengths"][k]} for u in results["units"] for k in range(len(u["lengths"]))]


# --- MCAP ---

def test_mcap_counts_and_values_match_the_results(healthy):
    results, log = healthy["results"], healthy["mcap"]
    messages = log["messages"]
    lengths = [n for u in results["units"] for n in u["lengths"]]
    assert len(results["units"]) == 2 and len(lengths) == 20
    counts = {c.topic: log["summary"].statistics.channel_message_counts.get(c.id, 0)
              for c in log["summary"].channels.values()}
    assert counts == {"/mewa/unit": 2, "/mewa/step": sum(lengths), "/mewa/episode": 20,
                      "/mewa/events": sum(len(s["events"]) for s in messages["/mewa/step"])}  # vector mode: no camera channel
    assert counts["/mewa/events"] > 0
    assert messages["/mewa/episode"] == episodes_of(results)
    steps = iter(messages["/mewa/step"])
    for episode in messages["/mewa/episode"]:
        played = [next(steps) for _ in range(episode["length"])]
        assert [s["step"] for s in played] == list(range(episode["length"]))
        assert {(s["pair"], s["seed"], s["episode"]) for s in played} == {
            (episode["pair"], episode["seed"], episode["episode"])}
        assert sum(s["reward"] for s in played) == pytest.approx(episode["return"], abs=1e-9)
        assert played[-1]["terminated"] or played[-1]["truncated"]
        assert not any(s["terminated"] or s["truncated"] for s in played[:-1])
        for before, after in zip(played, played[1:]):
            assert after["observation"] == before["next_observation"]
    assert [u["pair"] for u in messages["/mewa/unit"]] == [0, 1]
    assert [u["task_index"] for u in messages["/mewa/unit"]] == [u["task"] for u in results["units"]]


def test_mcap_clock_is_the_global_step(healthy):
    log = healthy["mcap"]
    steps, times = log["messages"]["/mewa/step"], log["times"]["/mewa/step"]
    assert [s["global_step"] for s in steps] == list(range(len(steps)))
    assert times == [(g * TICK_NS, g * TICK_NS) for g in range(len(steps))]
    ends = [t for t, _ in log["times"]["/mewa/episode"]]
    lengths = np.cumsum([e["length"] for e in log["messages"]["/mewa/episode"]])
    assert ends == [int(n - 1) * TICK_NS + HALF_TICK_NS for n in lengths]


def test_mcap_messages_validate_against_their_schemas(healthy):
    log = healthy["mcap"]
    names = {topic: name for topic, (name, _) in log["schemas"].items()}
    assert names == {"/mewa/unit": "mewa.Unit", "/mewa/step": "mewa.Step", "/mewa/episode": "mewa.Episode",
                     "/mewa/events": "foxglove.Log"}  # no camera frames in vector mode
    for topic, (_, schema) in log["schemas"].items():
        for message in log["messages"][topic]:
            assert schema_errors(message, schema) == [], topic
    step_schema = log["schemas"]["/mewa/step"][1]
    good = log["messages"]["/mewa/step"][0]
    assert schema_errors({k: v for k, v in good.items() if k != "reward"}, step_schema)
    assert schema_errors({**good, "terminated": 1}, step_schema)
    assert schema_errors({**good, "observation": good["observation"][:17]}, step_schema)
    assert schema_errors({**good, "events": [{"kind": "oops", "color": 0, "value": 0}]}, step_schema)
    assert schema_errors({**log["messages"]["/mewa/events"][0], "level": 7}, log["schemas"]["/mewa/events"][1])


def test_mcap_with_jsonschema_if_installed(healthy):
    jsonschema = pytest.importorskip("jsonschema")
    for topic, (_, schema) in healthy["mcap"]["schemas"].items():
        jsonschema.Draft202012Validator.check_schema(schema)
        validator = jsonschema.Draft202012Validator(schema)  # built once: jsonschema.validate rebuilds it per call
        assert healthy["mcap"]["messages"][topic]
        for message in healthy["mcap"]["messages"][topic]:
            validator.validate(message)


def test_mcap_events_are_foxglove_logs_of_the_step_events(healthy):
    log = healthy["mcap"]
    expected = [(LEVELS[e["kind"]], s["global_step"],
                 event_message(s["pair"], s["seed"], s["episode"], s["step"], Event(e["kind"], e["color"], e["value"])))
                for s in log["messages"]["/mewa/step"] for e in s["events"]]
    got = [(m["level"], m["timestamp"]["sec"] * 10**9 + m["timestamp"]["nsec"], m["message"])
           for m in log["messages"]["/mewa/events"]]
    assert got == [(level, g * TICK_NS, text) for level, g, text in expected]
    kinds = {e["kind"] for s in log["messages"]["/mewa/step"] for e in s["events"]}
    assert {"mistake", "structure_completed", "subgoal_reached"} <= kinds
    assert any(": mistake on " in text for _, _, text in expected)


def test_mcap_metadata_describes_the_run(healthy):
    log, results = healthy["mcap"], healthy["results"]
    assert log["header"].profile == "mewa"
    meta = log["metadata"]["mewa_run"]
    assert meta["agent"] == results["agent"]["name"] and meta["agent_sha256"] == results["agent"]["sha256"]
    assert meta["suite"] == "narrow-v1" and meta["suite_sha256"] == results["suite"]["sha256"]
    env = results["env"]
    assert (meta["seeds"], meta["env_id"], meta["env_version"]) == ("0", env["id"], env["version"])
    assert (meta["package_version"], meta["mode"]) == (results["package_version"], "vector")
    assert all(isinstance(v, str) for v in meta.values())


# --- Rerun ---

def test_rerun_recording_matches_the_run(healthy):
    path, log, run = healthy["rrd"], healthy["mcap"], healthy["run"]
    verify_rrd(path)
    reader = RrdReader(path)
    [recording] = reader.recordings()
    assert recording.application_id == "mewa-bench" and recording.recording_id == recording_id(run)
    views = blueprint_views(path)
    assert {("TimeSeries", "Reward"), ("BarChart", "Observation after the step"), ("TextLog", "Events")} <= views
    assert not any(name == "Camera" for _, name in views)  # no camera in vector mode
    steps = log["messages"]["/mewa/step"]
    rewards = rrd_rows(path, "/mewa/reward")
    assert [r["global_step"] for r in rewards] == list(range(len(steps)))
    assert [r["Scalars:scalars"] for r in rewards] == [[s["reward"]] for s in steps]
    assert [(r["pair"], r["episode"]) for r in rewards] == [(s["pair"], s["episode"]) for s in steps]
    actions = [r["Scalars:scalars"][0] for r in rrd_rows(path, "/mewa/action")]
    assert actions == [float(s["action"]) for s in steps]
    episodes = log["messages"]["/mewa/episode"]
    returns = rrd_rows(path, "/mewa/return")
    ends = np.cumsum([e["length"] for e in episodes]) - 1
    assert [returns[g]["Scalars:scalars"][0] for g in ends] == pytest.approx([e["return"] for e in episodes])
    normalised = rrd_rows(path, "/mewa/normalised_return")
    assert [r["global_step"] for r in normalised] == list(ends)
    assert [r["Scalars:scalars"][0] for r in normalised] == [e["normalised_return"] for e in episodes]
    bars = rrd_rows(path, "/mewa/observation")
    assert [r["BarChart:values"][0]["buffer"] for r in bars] == [s["next_observation"] for s in steps]


def test_rerun_events_match_the_mcap_log(healthy):
    path, log = healthy["rrd"], healthy["mcap"]
    events = rrd_rows(path, "/mewa/events")
    expected = log["messages"]["/mewa/events"]
    assert [r["TextLog:text"][0] for r in events] == [m["message"] for m in expected]
    assert [r["TextLog:level"][0] for r in events] == [{2: "INFO", 3: "WARN"}[m["level"]] for m in expected]
    assert [r["global_step"] * TICK_NS for r in events] == [t for t, _ in log["times"]["/mewa/events"]]
    summaries = rrd_rows(path, "/mewa/episodes")
    assert len(summaries) == 20 and summaries[0]["TextLog:text"][0].startswith("pair 0 seed 0 ep 0: return ")


# --- failures and interruptions ---

def test_a_failing_agent_leaves_readable_logs_of_the_finished_units(tmp_path):
    sinks = log_sinks(tmp_path)
    with pytest.raises(EvaluationError, match="divided by zero"):
        run_logged(tmp_path, {"fault": "raise", "after_units": "1", "at_step": "2"}, sinks)
    results = read_results(tmp_path / "r.json")
    assert [u["pair"] for u in results["units"]] == [0]
    log = read_mcap(tmp_path / "run.mcap")
    assert log["messages"]["/mewa/episode"] == episodes_of(results)
    assert len(log["messages"]["/mewa/step"]) == sum(results["units"][0]["lengths"])
    assert log["metadata"]["mewa_run"]["agent"] == "delayed_fault_agent"
    verify_rrd(tmp_path / "run.rrd")
    rewards = rrd_rows(tmp_path / "run.rrd", "/mewa/reward")
    assert [r["Scalars:scalars"][0] for r in rewards] == [s["reward"] for s in log["messages"]["/mewa/step"]]
    assert {r["pair"] for r in rewards} == {0}


def test_an_interrupted_run_leaves_readable_logs(tmp_path):
    def interrupt(done: int, total: int) -> None:
        if done == 1:
            raise KeyboardInterrupt

    sinks = log_sinks(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        run_logged(tmp_path, {"fault": "none"}, sinks, progress=interrupt)
    log = read_mcap(tmp_path / "run.mcap")
    assert [u["pair"] for u in log["messages"]["/mewa/unit"]] == [0]
    assert len(log["messages"]["/mewa/episode"]) == 10
    assert len(rrd_rows(tmp_path / "run.rrd", "/mewa/normalised_return")) == 10
    verify_rrd(tmp_path / "run.rrd")


# --- synthetic trajectories: images, determinism, sink lifecycle ---

def synthetic_run(mode: str = "sapien") -> RunInfo:
    """A made-up run description."""
    return RunInfo(agent="synthetic", agent_sha256="a" * 64, suite="narrow-v1", suite_sha256="b" * 64, seeds=(0,),
                   episodes_per_pair=2, env_id="mewa/MEWA-v0", env_version="v0", package_version="0.1.0", mode=mode)


def synthetic_unit(images: bool = True, pair: int = 3) -> UnitRecord:
    """Two short episodes with random camera frames (as SAPIEN mode will give)."""
    rng = np.random.default_rng(7)

    def frame() -> np.ndarray | None:
        return rng.integers(0, 256, size=(6, 5, 3), dtype=np.uint8) if images else None

    episodes = []
    for k, n in enumerate((3, 2)):
        obs = [np.full(18, float(i), dtype=np.float32) for i in range(n + 1)]
        seen = [{"state": o, "image": frame()} if images else o for o in obs]
        steps = tuple(StepRecord(i, Transition(seen[i], i % 4, -0.1 * (i + 1), seen[i + 1], i == n - 1, False), i,
                                 (Event("mistake", 1, 2),) if i == 0 else ()) for i in range(n))
        episodes.append(EpisodeRecord(k, 100 + k, steps, sum(s.reward for s in steps), 0.5, 0.75, frame()))
    return UnitRecord(pair, 0, 1, {"name": "t"}, (0.5, 0.25), tuple(episodes))


def write_synthetic(tmp: Path, unit: UnitRecord, mode: str = "sapien") -> tuple[Path, Path]:
    """Log one synthetic unit to both formats."""
    mcap_path, rrd_path = tmp / "s.mcap", tmp / "s.rrd"
    sinks = [McapSink(mcap_path), RerunSink(rrd_path)]
    for sink in sinks:
        sink.start(synthetic_run(mode))
        sink.add_unit(unit)
        sink.close()
    return mcap_path, rrd_path


def decode_png(message: dict[str, Any]) -> np.ndarray:
    """Pixels of a foxglove.CompressedImage PNG frame."""
    assert message["format"] == "png" and message["frame_id"] == "camera"
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(message["data"]))))


def test_camera_frames_are_png_compressed_images(tmp_path):
    unit = synthetic_unit()
    mcap_path, rrd_path = write_synthetic(tmp_path, unit)
    log = read_mcap(mcap_path)
    frames = log["messages"]["/mewa/camera"]
    expected = [img for ep in unit.episodes for img in (ep.first_image, *(s.image for s in ep.steps))]
    assert len(frames) == len(expected) == 7
    for message, image in zip(frames, expected):
        assert np.array_equal(decode_png(message), image)
    schema_name, schema = log["schemas"]["/mewa/camera"]
    assert schema_name == "foxglove.CompressedImage"
    assert all(schema_errors(m, schema) == [] for m in frames)
    # first frame with the episode's first step, each step's frame half a tick after it
    ms = [0, 50, 150, 250, 300, 350, 450]
    assert log["times"]["/mewa/camera"] == [(t * 10**6, t * 10**6) for t in ms]
    assert [(m["timestamp"]["sec"], m["timestamp"]["nsec"]) for m in frames] == [(0, t * 10**6) for t in ms]
    assert ("2D", "Camera") in blueprint_views(rrd_path)
    rows = rrd_rows(rrd_path, "/mewa/camera")
    assert [r["global_step"] for r in rows] == list(range(5))
    for row, step in zip(rows, [s for ep in unit.episodes for s in ep.steps]):
        fmt = row["Image:format"][0]
        pixels = np.array(row["Image:buffer"][0], dtype=np.uint8).reshape(fmt["height"], fmt["width"], 3)
        assert np.array_equal(pixels, step.image)


def test_synthetic_events_and_returns(tmp_path):
    unit = synthetic_unit(images=False)
    mcap_path, rrd_path = write_synthetic(tmp_path, unit, mode="vector")
    log = read_mcap(mcap_path)
    assert "/mewa/camera" not in log["messages"]  # vector mode: no camera channel at all
    assert [m["message"] for m in log["messages"]["/mewa/events"]] == [
        "pair 3 seed 0 ep 0 step 0: mistake on blue (type 2)", "pair 3 seed 0 ep 1 step 0: mistake on blue (type 2)"]
    returns = [r["Scalars:scalars"][0] for r in rrd_rows(rrd_path, "/mewa/return")]
    assert returns == pytest.approx([-0.1, -0.3, -0.6, -0.1, -0.3])
    assert [r["global_step"] for r in rrd_rows(rrd_path, "/mewa/events")] == [0, 3]


def test_identical_runs_give_identical_mcap_files(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first, _ = write_synthetic(tmp_path / "a", synthetic_unit())
    second, _ = write_synthetic(tmp_path / "b", synthetic_unit())
    assert first.read_bytes() == second.read_bytes()


def test_recording_id_is_derived_from_the_run():
    assert recording_id(synthetic_run()) == recording_id(synthetic_run())
    other = RunInfo(**{**synthetic_run().__dict__, "agent_sha256": "c" * 64})
    assert recording_id(other) != recording_id(synthetic_run())


def test_sinks_close_safely_and_refuse_misuse(tmp_path):
    sinks = [McapSink(tmp_path / "x.mcap"), RerunSink(tmp_path / "x.rrd")]
    for sink in sinks:
        sink.close()  # never started: nothing to do
        with pytest.raises(RuntimeError, match="before start"):
            sink.add_unit(synthetic_unit())
        sink.start(synthetic_run())
        with pytest.raises(RuntimeError, match="twice"):
            sink.start(synthetic_run())
        sink.close()
        sink.close()
        with pytest.raises(RuntimeError, match="after close"):
            sink.add_unit(synthetic_unit())
    assert read_mcap(tmp_path / "x.mcap")["messages"]["/mewa/step"] == []
    verify_rrd(tmp_path / "x.rrd")


def test_units_are_on_disk_before_close(tmp_path):
    sinks = [McapSink(tmp_path / "w.mcap"), RerunSink(tmp_path / "w.rrd", batch_steps=5)]  # one unit is a batch
    for sink in sinks:
        sink.start(synthetic_run())
        sink.add_unit(synthetic_unit())
    records = []
    with open(tmp_path / "w.mcap", "rb") as f, pytest.raises(EndOfFile):  # no footer yet
        for record in StreamReader(f).records:
            records.append(record)
    assert sum(isinstance(r, McapMessage) for r in records) == 17  # 1 unit, 5 steps, 2 episodes, 2 events, 7 frames
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no footer": expected while the run is going on
        assert len(rrd_rows(tmp_path / "w.rrd", "/mewa/reward")) == 5
    for sink in sinks:
        sink.close()
    verify_rrd(tmp_path / "w.rrd")


def test_a_bad_unit_leaves_nothing_half_written(tmp_path):
    unit = synthetic_unit()
    state = np.zeros(18, np.float32)
    bad_image = {"state": state, "image": np.zeros((2, 2, 3), dtype=np.float64)}
    bad_step = StepRecord(0, Transition(bad_image, 0, -1.0, bad_image, True, False), 0, ())
    bad = UnitRecord(4, 0, 1, {}, (0.5,), (EpisodeRecord(0, 1, (bad_step,), -1.0, 0.0, 0.0),))
    sink = McapSink(tmp_path / "bad.mcap")
    sink.start(synthetic_run())
    sink.add_unit(unit)
    with pytest.raises(ValueError, match="uint8"):
        sink.add_unit(bad)
    sink.close()
    log = read_mcap(tmp_path / "bad.mcap")
    assert {u["pair"] for u in log["messages"]["/mewa/unit"]} == {3}
    assert len(log["messages"]["/mewa/step"]) == 5


# --- the viewer ---

def test_viewer_command(tmp_path):
    rrd = tmp_path / "run.rrd"
    rrd.write_bytes(b"")
    native = viewer_command(rrd)
    assert Path(native[0]).is_file() and native[1:] == [str(rrd)]
    web = viewer_command(rrd, web=True, web_port=9191)
    assert web[0] == native[0] and web[-1] == str(rrd)
    assert "--web-viewer" in web and web[web.index("--bind") + 1] == "127.0.0.1"
    assert web[web.index("--web-viewer-port") + 1] == "9191"


def test_the_rerun_program_is_the_installed_one():
    out = subprocess.run([view.rerun_executable(), "--version"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "0.41.0" in out.stdout


class FinishedViewer:
    """Stands in for the viewer process: records its command and has already exited with 0."""

    pid = -1  # no process group: nothing to stop

    def __init__(self, calls: list, command: list[str], **popen_options: object) -> None:
        calls.append(command)

    def wait(self, timeout: float | None = None) -> int:
        return 0

    def poll(self) -> int:
        return 0


def test_viewer_on_a_missing_file_is_a_clear_error(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(view.subprocess, "Popen", lambda command, **kw: FinishedViewer(calls, command, **kw))
    with pytest.raises(ViewerError, match="no such file"):
        open_viewer(tmp_path / "missing.rrd")
    with pytest.raises(ViewerError, match="not a file"):
        open_viewer(tmp_path)
    assert calls == []
    rrd = tmp_path / "run.rrd"
    rrd.write_bytes(b"")
    assert open_viewer(rrd, web=True, web_port=free_port()) == 0
    assert len(calls) == 1 and "--web-viewer" in calls[0]


def test_view_without_a_display_refuses_the_native_viewer_and_starts_nothing(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(view.subprocess, "Popen", lambda command, **kw: FinishedViewer(calls, command, **kw))
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    rrd = tmp_path / "run.rrd"
    rrd.write_bytes(b"")
    result = CliRunner().invoke(app, ["view", str(rrd)])
    assert result.exit_code == 1 and "no display found" in result.output and "--web" in result.output
    assert calls == []  # nothing started: no server, no window
    monkeypatch.setenv("DISPLAY", ":99")
    assert open_viewer(rrd) == 0 and calls == [viewer_command(rrd)]


def free_port() -> int:
    """A port nobody listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_web_viewer_on_a_taken_port_says_which_and_how_to_choose_another(tmp_path):
    rrd = tmp_path / "run.rrd"
    rrd.write_bytes(b"")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ViewerError, match=rf"port {port} .*already in use.*--port"):
            open_viewer(rrd, web=True, web_port=port)


def test_sigterm_to_view_web_stops_the_viewer_and_frees_its_port(tmp_path):
    """`mewa-bench view --web` killed by SIGTERM takes its Rerun server down with it."""
    rrd = tmp_path / "run.rrd"
    sink = RerunSink(rrd)
    run_logged(tmp_path, {"fault": "none"}, [sink])
    port = free_port()
    command = [str(Path(sys.executable).parent / "mewa-bench"), "view", "--web", "--port", str(port), str(rrd)]
    viewer = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while not view.port_in_use(port):
            assert viewer.poll() is None and time.monotonic() < deadline, "the web viewer never listened"
            time.sleep(0.2)
        viewer.send_signal(signal.SIGTERM)
        assert viewer.wait(timeout=30) == 128 + signal.SIGTERM
        deadline = time.monotonic() + 15
        while view.port_in_use(port):
            assert time.monotonic() < deadline, f"port {port} still taken: the Rerun server outlived mewa-bench"
            time.sleep(0.2)
    finally:
        if viewer.poll() is None:
            viewer.kill()


def test_resuming_a_finished_run_writes_no_empty_log(tmp_path):
    run_logged(tmp_path, {"fault": "none"}, log_sinks(tmp_path))
    again = tmp_path / "again"
    again.mkdir()
    config = EvalConfig(agent_path=AGENT, out=tmp_path / "r.json", agent_args={"fault": "none"}, seeds=(0,),
                        pairs=(0, 1), isolated=False, lanes=1, resume=True)
    sinks = [McapSink(again / "run.mcap"), RerunSink(again / "run.rrd")]
    results, _ = evaluate(config, sinks=sinks)  # nothing left to play
    assert len(results["units"]) == 2
    assert list(again.iterdir()) == []


def test_rerun_batches_units_into_few_chunks_with_every_row(tmp_path):
    units = [synthetic_unit(images=False, pair=p) for p in range(12)]  # 5 steps each
    path = tmp_path / "b.rrd"
    with RerunSink(path, batch_steps=20) as sink:  # batches of 4 units (20 steps)
        sink.start(synthetic_run("vector"))
        for unit in units:
            sink.add_unit(unit)
    verify_rrd(path)
    chunks: dict[str, int] = {}
    for chunk in RrdReader(path).stream():
        if not chunk.is_static and chunk.entity_path.startswith("/mewa/"):
            chunks[chunk.entity_path] = chunks.get(chunk.entity_path, 0) + 1
    assert set(chunks) == {"/mewa/reward", "/mewa/return", "/mewa/action", "/mewa/progress", "/mewa/observation",
                           "/mewa/events", "/mewa/normalised_return", "/mewa/score", "/mewa/episodes"}
    assert all(n == 3 for n in chunks.values()), chunks  # 3 batches, one chunk per entity and batch
    steps = [(u.pair, ep.episode, s) for u in units for ep in u.episodes for s in ep.steps]
    rewards = rrd_rows(path, "/mewa/reward")
    assert [r["global_step"] for r in rewards] == list(range(len(steps))) == list(range(60))
    assert [(r["pair"], r["episode"]) for r in rewards] == [(p, k) for p, k, _ in steps]
    assert [r["Scalars:scalars"][0] for r in rewards] == pytest.approx([s.reward for _, _, s in steps])
    bars = rrd_rows(path, "/mewa/observation")
    assert [r["BarChart:values"][0]["buffer"] for r in bars] == [list(s.next_obs) for _, _, s in steps]
    ends = rrd_rows(path, "/mewa/score")
    assert [(r["global_step"], r["pair"], r["episode"]) for r in ends] == [
        (5 * p + end, p, k) for p in range(12) for k, end in ((0, 2), (1, 4))]
    assert rrd_rows(path, "/mewa/episodes")[-1]["TextLog:text"] == [
        "pair 11 seed 0 ep 1: return -0.300, normalised 0.500, score 0.750, 2 steps"]


def test_a_rerun_log_of_a_real_run_is_a_few_chunks(healthy):
    per_entity: dict[str, int] = {}
    for chunk in RrdReader(healthy["rrd"]).stream():
        if not chunk.is_static:
            per_entity[chunk.entity_path] = per_entity.get(chunk.entity_path, 0) + 1
    assert per_entity and max(per_entity.values()) == 1, per_entity  # 2 units, 20 episodes: one batch


def test_evaluate_logs_only_the_pairs_and_seeds_asked_for(tmp_path):
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    agent = Path(__file__).resolve().parents[1] / "submissions" / "random" / "agent.py"
    args = ["evaluate", str(agent), "--in-process", "--pairs", "0,1,2", "--seeds", "3",
            "--out", str(tmp_path / "r.json"), "--log", "mcap,rerun", "--log-dir", str(tmp_path / "logs")]
    result = CliRunner().invoke(app, [*args, "--log-pairs", "0,2", "--log-seeds", "1,2"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert len(read_results(tmp_path / "r.json")["units"]) == 9  # every unit scored
    log = read_mcap(tmp_path / "logs" / "r.mcap")
    assert sorted((u["pair"], u["seed"]) for u in log["messages"]["/mewa/unit"]) == [(0, 1), (0, 2), (2, 1), (2, 2)]
    assert json.loads(log["metadata"]["mewa_run"]["logged_pairs"]) == [0, 2]
    assert json.loads(log["metadata"]["mewa_run"]["logged_seeds"]) == [1, 2]
    rrd = tmp_path / "logs" / "r.rrd"
    verify_rrd(rrd)
    logged = {(r["pair"], r["episode"]) for r in rrd_rows(rrd, "/mewa/score")}
    assert logged == {(p, k) for p in (0, 2) for k in range(10)}
    assert len(rrd_rows(rrd, "/mewa/score")) == 40  # 4 units of 10 episodes
    alone = CliRunner().invoke(app, [*args[:-4], "--log-seeds", "1"], env={"COLUMNS": "200"})
    assert alone.exit_code == 2 and "--log" in alone.output
