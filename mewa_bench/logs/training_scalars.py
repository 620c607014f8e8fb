"""Rerun scalars of a training run (`mewa-bench train ... --rerun`): every metrics row as it comes.

One `.rrd` per run folder (`metrics.rrd`), flushed after every row, so `mewa-bench view` shows the
run so far while it trains. Timeline `env_steps`; one scalar entity per numeric metrics column,
under `train/` (the episode-1 and episode-10 normalised returns, the losses, seconds per update).
"""

from __future__ import annotations

import math
import uuid
from pathlib import Path
from typing import Any

from mewa_bench.extras import require

APPLICATION_ID = "mewa-bench-train"
FILE = "metrics.rrd"


class TrainingScalars:
    """Streams metrics rows to `path` (a Rerun recording named after the run)."""

    def __init__(self, path: Path, run_name: str) -> None:
        rr = require("rerun", "logs", "Rerun training scalars (`mewa-bench train --rerun`)")
        self._rr = rr
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._rec = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid5(uuid.NAMESPACE_URL, run_name))
        self._rec.set_log_time_enabled(False)  # the env-step timeline only: the same rows, the same file
        self._rec.save(self.path)
        self._rec.send_recording_name(run_name)

    def log(self, row: dict[str, Any]) -> None:
        """One metrics row at its `env_steps` (NaN and non-numeric fields are left out)."""
        self._rec.set_time("env_steps", sequence=int(float(row["env_steps"])))
        for name, value in row.items():
            if name in ("env_steps", "update"):
                continue
            try:
                number = float(value)
            except (TypeError, ValueError):
                continue
            if not math.isnan(number):
                self._rec.log(f"train/{name}", self._rr.Scalars(number))
        self._rec.flush()

    def close(self) -> None:
        """Finish the file."""
        self._rec.flush()
        self._rec.disconnect()
