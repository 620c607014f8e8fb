"""Trajectory logs of evaluation runs (SPEC section 8): MCAP for Foxglove, `.rrd` for Rerun, and the viewer.

The sinks plug into `mewa_bench.protocol.runner.evaluate(..., sinks=[...])`. `mcap`, `rerun` and
Pillow are imported only when a sink starts writing, never by importing this package.
"""

from mewa_bench.logs.mcap_log import McapSink
from mewa_bench.logs.rerun_log import RerunSink
from mewa_bench.logs.view import open_viewer, viewer_command

__all__ = ["McapSink", "RerunSink", "open_viewer", "viewer_command"]
