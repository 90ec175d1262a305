"""One process's line in ``/proc/<pid>/stat``, split in one place (proc_pid_stat(5)).

The second field is the command name in parentheses, and it may hold spaces and
parentheses of its own, so the line is split after its *last* ``)``. What psutil
gives does not cover our uses: the start time in clock ticks (the service lease
compares it as the kernel wrote it) and the bounds of the argument area (the
launcher writes a detector's title there).
"""

from __future__ import annotations

# Indexes into stat_fields(): the man page's field number minus 3.
STATE = 0  # (3) R, S, D, T, t, Z, ...
START_TIME = 19  # (22) clock ticks after boot
ARG_START = 45  # (48)
ARG_END = 46  # (49)


def stat_fields(pid: int | str = "self") -> list[bytes]:
    """The fields after the command name; OSError if the process is gone (FileNotFoundError) or unreadable."""
    with open(f"/proc/{pid}/stat", "rb") as handle:
        line = handle.read()
    _, closing, rest = line.rpartition(b")")
    if not closing:
        raise OSError(f"/proc/{pid}/stat: no command name in {line[:80]!r}")
    return rest.split()


def state_of(pid: int | str) -> str:
    """The process's state letter (``S``, ``T``, ``Z``, ...); OSError as :func:`stat_fields`."""
    fields = stat_fields(pid)
    if not fields:
        raise OSError(f"/proc/{pid}/stat: no state")
    return fields[STATE].decode()
