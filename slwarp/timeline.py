"""Where a command's wall time goes: named marks on the wall clock, for bench.command_wall.

With $SLWARP_TIMELINE set to a file, `mark(name)` records (name, time.time()) and `write()` appends them as one
JSON line {"pid", "marks": [[name, seconds since the epoch], ...]} to that file; unset, both do nothing. Wall-clock
seconds (not perf_counter) so that the process that started this one can place the marks against its own clock.
"""
from __future__ import annotations

import json
import os
import time

_FILE = os.environ.get("SLWARP_TIMELINE")
_marks: list[tuple[str, float]] = []


def mark(name: str) -> None:
    """Record that the command reached `name` now (only with $SLWARP_TIMELINE set)."""
    if _FILE:
        _marks.append((name, time.time()))


def write() -> None:
    """Append this process's marks to $SLWARP_TIMELINE (one JSON line) and forget them."""
    if _FILE and _marks:
        with open(_FILE, "a") as f:
            f.write(json.dumps({"pid": os.getpid(), "marks": _marks}) + "\n")
        _marks.clear()
