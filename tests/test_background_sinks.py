"""The background sink writer: order, draining on close, and errors surfacing in the runner."""

from __future__ import annotations

import time

import pytest

from mewa_bench.protocol.trajectory import BackgroundSinks, RunInfo, UnitRecord

RUN = RunInfo("a", "0" * 64, "narrow-v1", "1" * 64, (0,), 10, "mewa/MEWA-v0", "v0", "0.1.0")


class SlowSink:
    def __init__(self, fail_at: int | None = None) -> None:
        self.units, self.closed, self.fail_at = [], False, fail_at

    def start(self, run: RunInfo) -> None:
        self.run = run

    def add_unit(self, unit: UnitRecord) -> None:
        time.sleep(0.01)
        if unit.pair == self.fail_at:
            raise OSError("disk full")
        self.units.append(unit.pair)

    def close(self) -> None:
        self.closed = True


def unit(pair: int) -> UnitRecord:
    return UnitRecord(pair, 0, 0, {}, (0.1, 0.1))


def test_units_arrive_in_order_and_close_drains_the_queue() -> None:
    sinks = [SlowSink(), SlowSink()]
    writer = BackgroundSinks(sinks)
    writer.start(RUN)
    for p in range(20):
        writer.add_unit(unit(p))
    writer.add_unit(None)  # nothing collected: ignored
    writer.close()
    assert all(s.units == list(range(20)) and s.closed for s in sinks)


def test_a_failing_sink_is_reported_and_every_sink_still_closed() -> None:
    bad, good = SlowSink(fail_at=3), SlowSink()
    writer = BackgroundSinks([bad, good])
    writer.start(RUN)
    with pytest.raises(RuntimeError, match="disk full"):
        try:  # as in the runner: close() in a finally
            for p in range(50):
                writer.add_unit(unit(p))
                time.sleep(0.002)
        finally:
            writer.close()
    assert bad.closed and good.closed


class BadStartSink(SlowSink):
    def start(self, run: RunInfo) -> None:
        raise OSError("cannot create the log file")


def test_a_sink_that_fails_to_start_closes_the_ones_already_started() -> None:
    first, bad, last = SlowSink(), BadStartSink(), SlowSink()
    with pytest.raises(OSError, match="cannot create"):
        BackgroundSinks([first, bad, last]).start(RUN)
    assert first.closed and not last.closed  # the later sink was never started, so nothing to close
