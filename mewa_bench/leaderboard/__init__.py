"""Leaderboards from submitted results files (SPEC section 7): validation, tables, figures, HTML."""

from mewa_bench.leaderboard.build import LeaderboardReport, build_leaderboards
from mewa_bench.leaderboard.validate import Entry, InvalidResults

__all__ = ["Entry", "InvalidResults", "LeaderboardReport", "build_leaderboards"]
