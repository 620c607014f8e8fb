"""Rerun log (`.rrd`) of an evaluation run (SPEC section 8); `mewa-bench view FILE` opens it.

Timelines: `global_step` (env steps of the run, from 0), `pair` and `episode` (episode index within
its pair, as in the results). Logged at global step `g`:

- `mewa/reward`, `mewa/return` (the episode's running return), `mewa/action`, `mewa/progress`: scalars
  of step `g`;
- `mewa/observation`: bar chart of the 18-float observation *after* the step (its `next_obs`);
- `mewa/camera`: the rendered image after the step, in SAPIEN mode;
- `mewa/events`: one text line per game event (INFO for progress, WARN for mistakes and returns);
- at an episode's last step, `mewa/normalised_return`, `mewa/score` and a summary line in `mewa/episodes`.

The recording id is derived from the run's settings, so the same run always gets the same id.
"""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Any

import numpy as np

from mewa_bench.extras import require
from mewa_bench.logs.common import event_message, is_warning, run_digest, run_metadata
from mewa_bench.protocol.trajectory import EpisodeRecord, RunInfo, UnitRecord

APPLICATION_ID = "mewa-bench"
TIMELINES = ("global_step", "pair", "episode")
REWARD, RETURN, ACTION, PROGRESS = "mewa/reward", "mewa/return", "mewa/action", "mewa/progress"
OBSERVATION, CAMERA, EVENTS, EPISODES = "mewa/observation", "mewa/camera", "mewa/events", "mewa/episodes"
NORMALISED_RETURN, SCORE = "mewa/normalised_return", "mewa/score"
EPISODE_WINDOW = 100  # steps shown around the time cursor: T, the longest episode
BATCH_STEPS = 16_384  # env steps per batch of columns: chunks of about 1 MB (the observations) on disk


def _rerun() -> Any:
    """The rerun module (rerun-sdk, from the logs extra)."""
    return require("rerun", "logs", "writing Rerun logs (`--log rerun`)")


def recording_id(run: RunInfo) -> str:
    """A UUID derived from the run's settings (agent and suite hashes, seeds, mode, ...)."""
    return str(uuid.UUID(hex=run_digest(run)[:32]))


def time_columns(g: np.ndarray, pair: np.ndarray, episode: np.ndarray) -> list[Any]:
    """The three timelines of rows at global steps `g`, with each row's pair and episode."""
    rr = _rerun()

    return [rr.TimeColumn("global_step", sequence=g), rr.TimeColumn("pair", sequence=pair),
            rr.TimeColumn("episode", sequence=episode)]


class _ArrowBatch:
    """A ready-made arrow array, as rerun's component batches expose theirs."""

    def __init__(self, array: Any) -> None:
        self.array = array

    def as_arrow_array(self) -> Any:
        return self.array


def bar_chart_column(values: np.ndarray) -> Any:
    """`BarChart:values` for many rows in one column: a float32 [n, k] array gives n bar charts of k bars.

    `rr.BarChart.columns` only takes a single vector, and one `rr.BarChart` per step costs ~0.4 ms
    (most of a run's logging time), so the arrow column is built directly, in the type rerun uses.
    """
    rr = _rerun()
    import pyarrow as pa  # a dependency of rerun-sdk

    values = np.ascontiguousarray(values, dtype=np.float32)
    n, k = values.shape
    [template] = rr.BarChart(values[0]).as_component_batches()
    struct_type = template.as_arrow_array().type
    union_type = struct_type.field("buffer").type  # tensor buffer: one list variant per dtype
    variants = [f.name for f in union_type]
    rows = pa.array(np.arange(0, n * k + 1, k, dtype=np.int32))
    children = [pa.ListArray.from_arrays(rows, pa.array(values.reshape(-1)), type=f.type) if f.name == "F32"
                else pa.array([], type=f.type) for f in union_type]
    type_ids = np.full(n, union_type.type_codes[variants.index("F32")], dtype=np.int8)
    buffer = pa.UnionArray.from_buffers(union_type, n, [None, pa.py_buffer(type_ids),
                                                        pa.py_buffer(np.arange(n, dtype=np.int32))], children=children)
    shape = pa.ListArray.from_arrays(pa.array(np.arange(n + 1, dtype=np.int32)), pa.array(np.full(n, k, np.uint64)),
                                     type=struct_type.field("shape").type)
    names = pa.nulls(n, struct_type.field("names").type)
    array = pa.StructArray.from_arrays([shape, names, buffer], fields=list(struct_type))
    return rr.DescribedComponentBatch(_ArrowBatch(array), rr.BarChart.descriptor_values()).partition()


def default_blueprint(camera: bool) -> Any:
    """The layout an episode reads best in: reward/return plots, observation bars, events, camera."""
    rrb = _rerun().blueprint

    recent = rrb.VisibleTimeRange("global_step", start=rrb.TimeRangeBoundary.cursor_relative(seq=-EPISODE_WINDOW),
                                  end=rrb.TimeRangeBoundary.cursor_relative(seq=0))
    plots = rrb.Vertical(
        rrb.TimeSeriesView(name="Reward", origin=REWARD, time_ranges=recent),
        rrb.TimeSeriesView(name="Return (running, per episode)", origin=RETURN, time_ranges=recent),
        rrb.TimeSeriesView(name="Action and sub-goals reached", contents=[ACTION, PROGRESS], time_ranges=recent),
        rrb.TimeSeriesView(name="Normalised return and score per episode", contents=[NORMALISED_RETURN, SCORE]),
    )
    state = [rrb.BarChartView(name="Observation after the step", origin=OBSERVATION)]
    if camera:
        state.append(rrb.Spatial2DView(name="Camera", origin=CAMERA))
    state.append(rrb.TextLogView(name="Events", contents=[EVENTS, EPISODES]))
    return rrb.Blueprint(rrb.Horizontal(plots, rrb.Vertical(*state)), rrb.TimePanel(timeline="global_step"),
                         collapse_panels=False)


class _StepRows:
    """The steps of some units as rows: global step, pair, seed and episode of each (empty episodes left out)."""

    def __init__(self, units: list[UnitRecord], first_step: int) -> None:
        self.episodes: list[tuple[UnitRecord, EpisodeRecord, int]] = []  # (unit, episode, its first global step)
        g = first_step
        for unit in units:
            for ep in unit.episodes:
                if ep.steps:
                    self.episodes.append((unit, ep, g))
                g += len(ep.steps)
        self.steps = [s for _, ep, _ in self.episodes for s in ep.steps]
        lengths = [len(ep.steps) for _, ep, _ in self.episodes]
        self.g = np.array([g0 + i for _, ep, g0 in self.episodes for i in range(len(ep.steps))], dtype=np.int64)
        self.pair = np.repeat(np.array([u.pair for u, _, _ in self.episodes], dtype=np.int64), lengths)
        self.seed = np.repeat(np.array([u.seed for u, _, _ in self.episodes], dtype=np.int64), lengths)
        self.episode = np.repeat(np.array([ep.episode for _, ep, _ in self.episodes], dtype=np.int64), lengths)

    def indexes(self, rows: np.ndarray | None = None) -> list[Any]:
        """The three timelines of the given rows (default: every step)."""
        rows = np.arange(len(self.steps)) if rows is None else rows
        return time_columns(self.g[rows], self.pair[rows], self.episode[rows])

    def episode_ends(self) -> np.ndarray:
        """The row of each episode's last step."""
        return np.cumsum([len(ep.steps) for _, ep, _ in self.episodes]) - 1


class RerunSink:
    """Streams a run's trajectories to one `.rrd` file and finishes it at `close()`.

    Units are sent in batches of at least `batch_steps` env steps, one column per entity and batch, so a
    recording has a few large chunks (what the viewer loads fast) instead of several per episode; what
    is still pending is sent at `close()`, which the runner calls when a run fails or is interrupted.
    """

    def __init__(self, path: Path | str, batch_steps: int = BATCH_STEPS) -> None:
        self.path = Path(path)
        self.batch_steps = batch_steps
        self.global_step = 0  # global step of the first pending unit's first step
        self._pending: list[UnitRecord] = []
        self._rec: Any = None

    def start(self, run: RunInfo) -> None:
        """Open the recording: file sink with its default blueprint, run properties, series styles."""
        rr = _rerun()

        if self._rec is not None:
            raise RuntimeError(f"{self.path}: RerunSink.start() called twice")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(run))
        rec.set_log_time_enabled(False)  # wall-clock time would make identical runs differ
        rec.save(self.path, default_blueprint=default_blueprint(camera=run.mode != "vector"))
        self._rec = rec
        rec.send_recording_name(f"{run.agent} on {run.suite}")
        rec.send_property("mewa_run", rr.AnyValues(**run_metadata(run)))
        self._log_styles()
        rec.flush()

    def add_unit(self, unit: UnitRecord) -> None:
        """Queue one finished unit; send the queue and flush it to the file once it holds a batch."""
        if self._rec is None:
            raise RuntimeError(f"{self.path}: RerunSink.add_unit() before start() or after close()")
        self._pending.append(unit)
        if sum(len(ep.steps) for u in self._pending for ep in u.episodes) >= self.batch_steps:
            self._send_pending()
            self._rec.flush()

    def close(self) -> None:
        """Send what is pending, flush and finish the file (footer included); safe to call more than once."""
        if self._rec is None:
            return
        try:
            self._send_pending()
        finally:
            rec, self._rec = self._rec, None
            try:
                rec.flush()
            finally:
                rec.disconnect()

    def _log_styles(self) -> None:
        """Static series names and markers, so plots read without a legend hunt."""
        rr = _rerun()

        for path, name in ((REWARD, "reward"), (RETURN, "return"), (PROGRESS, "sub-goals reached")):
            self._rec.log(path, rr.SeriesLines(names=name), static=True)
        for path, name in ((ACTION, "action (colour)"), (NORMALISED_RETURN, "normalised return"), (SCORE, "score")):
            self._rec.log(path, rr.SeriesPoints(names=name, markers="circle"), static=True)

    def _send_pending(self) -> None:
        """The pending units' steps and episode outcomes, one column per entity."""
        rr = _rerun()

        units, self._pending = self._pending, []
        rows = _StepRows(units, self.global_step)
        self.global_step += sum(len(ep.steps) for u in units for ep in u.episodes)
        if not rows.steps:
            return
        rec, steps, indexes = self._rec, rows.steps, rows.indexes()
        rewards = [np.array([s.reward for s in ep.steps], dtype=np.float64) for _, ep, _ in rows.episodes]
        series = {REWARD: np.concatenate(rewards), RETURN: np.concatenate([np.cumsum(r) for r in rewards]),
                  ACTION: np.array([s.action for s in steps], dtype=np.float64),
                  PROGRESS: np.array([s.progress for s in steps], dtype=np.float64)}
        for path, values in series.items():
            rec.send_columns(path, indexes=indexes, columns=rr.Scalars.columns(scalars=values))
        observations = np.stack([np.asarray(s.next_obs, dtype=np.float32) for s in steps])
        rec.send_columns(OBSERVATION, indexes=indexes, columns=[bar_chart_column(observations)])
        events = [(i, event_message(rows.pair[i], rows.seed[i], rows.episode[i], s.step, e),
                   "WARN" if is_warning(e) else "INFO") for i, s in enumerate(steps) for e in s.events]
        if events:
            at, texts, levels = zip(*events)
            rec.send_columns(EVENTS, indexes=rows.indexes(np.array(at)),
                             columns=rr.TextLog.columns(text=texts, level=levels))
        for i, step in enumerate(steps):  # SAPIEN mode; the batcher packs these frames into few chunks
            if step.image is not None:
                for timeline, values in zip(TIMELINES, (rows.g, rows.pair, rows.episode)):
                    rec.set_time(timeline, sequence=int(values[i]))
                rec.log(CAMERA, rr.Image(step.image))
        self._send_outcomes(rows)

    def _send_outcomes(self, rows: _StepRows) -> None:
        """Each episode's normalised return, score and summary line, at its last step."""
        rr = _rerun()

        ends = rows.episode_ends()
        indexes = rows.indexes(ends)
        episodes = [(unit, ep) for unit, ep, _ in rows.episodes]
        self._rec.send_columns(NORMALISED_RETURN, indexes=indexes, columns=rr.Scalars.columns(
            scalars=np.array([ep.normalised_return for _, ep in episodes], dtype=np.float64)))
        self._rec.send_columns(SCORE, indexes=indexes, columns=rr.Scalars.columns(
            scalars=np.array([ep.score for _, ep in episodes], dtype=np.float64)))
        texts = [f"pair {u.pair} seed {u.seed} ep {ep.episode}: return {ep.episode_return:.3f}, normalised "
                 f"{ep.normalised_return:.3f}, score {ep.score:.3f}, {len(ep.steps)} steps" for u, ep in episodes]
        self._rec.send_columns(EPISODES, indexes=indexes,
                               columns=rr.TextLog.columns(text=texts, level=["INFO"] * len(texts)))

    def __enter__(self) -> RerunSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
