"""Times as a person reads them: ``14:02:31 UTC (3 min ago)`` instead of ``1.795e+09``.

The graph and the messages keep epoch seconds (float, UTC); only what is
printed for people goes through here. JSON output keeps the epoch numbers.
"""

from __future__ import annotations

import time
from datetime import datetime, timezone
from typing import Any

# Column names whose values are epoch seconds in query rows (knowledge/schema.py's run-time properties).
TIME_COLUMNS = frozenset({"time", "at", "start_time", "end_time", "last_seen", "online_since", "calibrated_at",
                          "decision_time", "started_at", "ready_at", "ended_at", "last_heartbeat", "frame_time"})
# Anything before 2001-09-09 is not one of our timestamps (a duration, a count): left as it is.
_EPOCH_MIN = 1e9


def is_epoch(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value >= _EPOCH_MIN


def duration(seconds: float) -> str:
    """``42 s``, ``3 min``, ``2 h 05 min``, ``3 d 4 h``."""
    s = max(0.0, float(seconds))
    if s < 100:
        return f"{s:.0f} s" if s >= 10 else f"{s:.1f} s"
    if s < 3600:
        return f"{s / 60:.0f} min"
    if s < 86400:
        return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min"
    return f"{int(s // 86400)} d {int(s % 86400 // 3600)} h"


def ago(t: Any, now: float | None = None) -> str:
    """``12 s ago`` (``?`` when ``t`` is not a time; ``in 3 s`` for a clock ahead of ours)."""
    if not isinstance(t, (int, float)) or isinstance(t, bool):
        return "?"
    delta = (time.time() if now is None else now) - float(t)
    return f"{duration(delta)} ago" if delta >= -0.5 else f"in {duration(-delta)}"


def clock(t: Any, now: float | None = None) -> str:
    """``14:02:31 UTC``, with the date when ``t`` is not today (UTC)."""
    if not is_epoch(t):
        return "?" if t is None else str(t)
    when = datetime.fromtimestamp(float(t), tz=timezone.utc)
    today = datetime.fromtimestamp(time.time() if now is None else now, tz=timezone.utc).date()
    return when.strftime("%H:%M:%S UTC" if when.date() == today else "%Y-%m-%d %H:%M:%S UTC")


def stamp(t: Any, now: float | None = None) -> str:
    """``14:02:31 UTC (12 s ago)``: both, for tables people read."""
    if not is_epoch(t):
        return "?" if t is None else str(t)
    return f"{clock(t, now)} ({ago(t, now)})"
