"""MCAP log of an evaluation run (SPEC section 8), readable by the `mcap` reader and Foxglove.

Channels, all JSON-encoded with JSON schemas:

- `/mewa/unit`: one message per (pair, seed) unit: its task and worker.
- `/mewa/step`: one message per env step (observation, action, reward, flags, events, next observation).
- `/mewa/episode`: one message per episode (return, normalised return, score, length).
- `/mewa/events`: `foxglove.Log` messages, one per game event (INFO for progress, WARNING for setbacks).
- `/mewa/camera`: `foxglove.CompressedImage` PNG frames, when the run renders images (SAPIEN mode).

Times come from a synthetic clock, so identical runs give identical files: env step number `g` of
the run (from 0) is logged at `g * 100 ms`; the frame after step `g` and the episode summary at
`g * 100 ms + 50 ms`; an episode's first frame with its first step. The run's description is the
file's `mewa_run` metadata record.
"""

from __future__ import annotations

import base64
import io
import json
from pathlib import Path
from typing import IO, Any

import numpy as np

from mewa_bench.extras import require
from mewa_bench.logs.common import event_message, is_warning, run_metadata
from mewa_bench.protocol.trajectory import EpisodeRecord, RunInfo, StepRecord, UnitRecord

TICK_NS = 100_000_000  # one env step of the synthetic clock
HALF_TICK_NS = TICK_NS // 2
PROFILE = "mewa"
METADATA_NAME = "mewa_run"
FRAME_ID = "camera"
LOG_INFO, LOG_WARNING = 2, 3  # foxglove.LogLevel

TOPIC_UNIT, TOPIC_STEP, TOPIC_EPISODE = "/mewa/unit", "/mewa/step", "/mewa/episode"
TOPIC_EVENTS, TOPIC_CAMERA = "/mewa/events", "/mewa/camera"

_INT = {"type": "integer"}
_COUNT = {"type": "integer", "minimum": 0}
_NUMBER = {"type": "number"}
_OBSERVATION = {"type": "array", "items": _NUMBER, "minItems": 18, "maxItems": 18,
                "description": "float32[18] observation (SPEC section 2)"}
_TIME = {"type": "object", "title": "time",
         "properties": {"sec": {"type": "integer", "minimum": 0},
                        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}},
         "required": ["sec", "nsec"]}


def _record(title: str, description: str, properties: dict[str, Any]) -> dict[str, Any]:
    """A closed JSON schema of an object whose listed properties are all required."""
    return {"title": title, "description": description, "type": "object", "properties": properties,
            "required": list(properties), "additionalProperties": False}


EVENT_SCHEMA = _record("mewa.Event", "Something that happened during a step", {
    "kind": {"type": "string", "enum": ["mistake", "structure_completed", "structure_returned", "subgoal_reached"]},
    "color": {"type": "integer", "minimum": 0, "maximum": 3},
    "value": _INT,
})
STEP_SCHEMA = _record("mewa.Step", "One env step of an evaluation episode", {
    "global_step": _COUNT, "pair": _COUNT, "seed": _INT, "episode": _COUNT, "step": _COUNT,
    "observation": _OBSERVATION, "action": {"type": "integer", "minimum": 0, "maximum": 3}, "reward": _NUMBER,
    "terminated": {"type": "boolean"}, "truncated": {"type": "boolean"}, "progress": _COUNT,
    "events": {"type": "array", "items": EVENT_SCHEMA}, "next_observation": _OBSERVATION,
})
EPISODE_SCHEMA = _record("mewa.Episode", "One finished episode of a (pair, seed) unit", {
    "pair": _COUNT, "seed": _INT, "episode": _COUNT, "task": _COUNT, "env_seed": _COUNT, "return": _NUMBER,
    "normalised_return": _NUMBER, "score": _NUMBER, "length": _COUNT,
})
UNIT_SCHEMA = _record("mewa.Unit", "A (pair, seed) unit: the task and worker its episodes were played on", {
    "pair": _COUNT, "seed": _INT, "task_index": _COUNT, "task": {"type": "object"},
    "worker": {"type": "array", "items": {"type": "number", "minimum": 0, "maximum": 1}},
    "episodes": _COUNT,
})
# The Foxglove well-known schemas, as JSON schemas (field names and types as Foxglove defines them).
LOG_SCHEMA = {
    "title": "foxglove.Log", "description": "A log message", "type": "object",
    "properties": {
        "timestamp": {**_TIME, "description": "Timestamp of log message"},
        "level": {"title": "foxglove.LogLevel", "description": "Log level",
                  "oneOf": [{"title": name, "const": i}
                            for i, name in enumerate(("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL"))]},
        "message": {"type": "string", "description": "Log message"},
        "name": {"type": "string", "description": "Process or node name"},
        "file": {"type": "string", "description": "Filename"},
        "line": {"type": "integer", "minimum": 0, "description": "Line number in the file"},
    },
    "required": ["timestamp", "level", "message", "name", "file", "line"],
}
COMPRESSED_IMAGE_SCHEMA = {
    "title": "foxglove.CompressedImage", "description": "A compressed image", "type": "object",
    "properties": {
        "timestamp": {**_TIME, "description": "Timestamp of image"},
        "frame_id": {"type": "string", "description": "Frame of reference for the image"},
        "data": {"type": "string", "contentEncoding": "base64", "description": "Compressed image data"},
        "format": {"type": "string", "description": "Image format: `png`"},
    },
    "required": ["timestamp", "frame_id", "data", "format"],
}
CHANNELS: dict[str, dict[str, Any]] = {
    TOPIC_UNIT: UNIT_SCHEMA, TOPIC_STEP: STEP_SCHEMA, TOPIC_EPISODE: EPISODE_SCHEMA,
    TOPIC_EVENTS: LOG_SCHEMA, TOPIC_CAMERA: COMPRESSED_IMAGE_SCHEMA,
}

Message = tuple[str, int, dict[str, Any]]  # (topic, log time in ns, JSON-ready payload)


def time_of(ns: int) -> dict[str, int]:
    """A `{sec, nsec}` Foxglove time."""
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def png_bytes(image: np.ndarray) -> bytes:
    """PNG encoding of a uint8 [H, W, 3] (or [H, W]) image."""
    from PIL import Image

    array = np.asarray(image)
    if array.dtype != np.uint8:
        raise ValueError(f"camera images must be uint8, got {array.dtype}")
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


def image_message(image: np.ndarray, ns: int) -> Message:
    """A `foxglove.CompressedImage` frame."""
    data = base64.b64encode(png_bytes(image)).decode("ascii")
    return TOPIC_CAMERA, ns, {"timestamp": time_of(ns), "frame_id": FRAME_ID, "data": data, "format": "png"}


def step_messages(unit: UnitRecord, episode: int, step: StepRecord, g: int) -> list[Message]:
    """The step record, its events as log lines and its camera frame."""
    ns = g * TICK_NS
    payload = {
        "global_step": g, "pair": unit.pair, "seed": unit.seed, "episode": episode, "step": int(step.step),
        "observation": np.asarray(step.obs, dtype=np.float64).tolist(), "action": int(step.action),
        "reward": float(step.reward), "terminated": bool(step.terminated), "truncated": bool(step.truncated),
        "progress": int(step.progress),
        "events": [{"kind": e.kind, "color": int(e.color), "value": int(e.value)} for e in step.events],
        "next_observation": np.asarray(step.next_obs, dtype=np.float64).tolist(),
    }
    out: list[Message] = [(TOPIC_STEP, ns, payload)]
    for e in step.events:
        out.append((TOPIC_EVENTS, ns, {
            "timestamp": time_of(ns), "level": LOG_WARNING if is_warning(e) else LOG_INFO,
            "message": event_message(unit.pair, unit.seed, episode, int(step.step), e),
            "name": f"mewa/pair-{unit.pair}/seed-{unit.seed}", "file": "", "line": 0,
        }))
    if step.image is not None:
        out.append(image_message(step.image, ns + HALF_TICK_NS))
    return out


def episode_messages(unit: UnitRecord, ep: EpisodeRecord, g0: int) -> list[Message]:
    """Everything logged for one episode whose first step is global step `g0`."""
    out: list[Message] = []
    if ep.first_image is not None:
        out.append(image_message(ep.first_image, g0 * TICK_NS))
    for i, step in enumerate(ep.steps):
        out.extend(step_messages(unit, ep.episode, step, g0 + i))
    end = (g0 + max(len(ep.steps), 1) - 1) * TICK_NS + HALF_TICK_NS
    out.append((TOPIC_EPISODE, end, {
        "pair": unit.pair, "seed": unit.seed, "episode": ep.episode, "task": unit.task_index,
        "env_seed": int(ep.env_seed), "return": float(ep.episode_return),
        "normalised_return": float(ep.normalised_return), "score": float(ep.score), "length": len(ep.steps),
    }))
    return out


def unit_messages(unit: UnitRecord, g0: int) -> list[Message]:
    """Everything logged for one (pair, seed) unit whose first step is global step `g0`."""
    out: list[Message] = [(TOPIC_UNIT, g0 * TICK_NS, {
        "pair": unit.pair, "seed": unit.seed, "task_index": unit.task_index, "task": unit.task,
        "worker": [float(w) for w in unit.worker], "episodes": len(unit.episodes),
    })]
    for ep in unit.episodes:
        out.extend(episode_messages(unit, ep, g0))
        g0 += len(ep.steps)
    return out


def encode(payload: dict[str, Any]) -> bytes:
    """Compact, deterministic JSON."""
    return json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()


class McapSink:
    """Writes a run's trajectories to one MCAP file as the run progresses; `close()` always finishes the file."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self.global_step = 0
        self._file: IO[bytes] | None = None
        self._writer: Any = None
        self._channels: dict[str, int] = {}
        self._sequence: dict[str, int] = {}

    def start(self, run: RunInfo) -> None:
        """Create the file: header, schemas, channels and the run's metadata."""
        from mewa_bench import __version__

        mcap_writer = require("mcap.writer", "logs", "writing MCAP logs (`--log mcap`)")

        if self._writer is not None:
            raise RuntimeError(f"{self.path}: McapSink.start() called twice")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = mcap_writer.Writer(self._file)
        self._writer.start(profile=PROFILE, library=f"mewa-bench {__version__}")
        for topic, schema in CHANNELS.items():
            if topic == TOPIC_CAMERA and run.mode == "vector":
                continue  # no images in vector mode: no empty camera channel
            schema_id = self._writer.register_schema(name=schema["title"], encoding="jsonschema",
                                                     data=json.dumps(schema).encode())
            self._channels[topic] = self._writer.register_channel(topic=topic, message_encoding="json",
                                                                  schema_id=schema_id)
            self._sequence[topic] = 0
        self._writer.add_metadata(METADATA_NAME, run_metadata(run))
        self._flush()

    def add_unit(self, unit: UnitRecord) -> None:
        """Write one finished unit and flush it to disk."""
        if self._writer is None:
            raise RuntimeError(f"{self.path}: McapSink.add_unit() before start() or after close()")
        # Encode everything first: an error (a bad image, say) then leaves no half-written unit.
        messages = [(topic, ns, encode(payload)) for topic, ns, payload in unit_messages(unit, self.global_step)]
        for topic, ns, data in messages:
            self._writer.add_message(self._channels[topic], log_time=ns, data=data, publish_time=ns,
                                     sequence=self._sequence[topic])
            self._sequence[topic] += 1
        self.global_step += sum(len(ep.steps) for ep in unit.episodes)
        self._flush()

    def close(self) -> None:
        """Write the summary and footer and close the file; safe to call more than once."""
        writer, file = self._writer, self._file
        self._writer = self._file = None
        try:
            if writer is not None:
                writer.finish()
        finally:
            if file is not None:
                file.close()

    def _flush(self) -> None:
        """Push everything written so far (as complete chunks) to the OS."""
        self._writer.flush()
        self._file.flush()

    def __enter__(self) -> McapSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
