"""glibc's malloc arenas, capped in the long-running processes.

glibc gives each new thread its own malloc arena, up to eight per core. In
a process with 25-45 threads (Zenoh's runtime, our workers) memory freed in
one arena is not reused by the others, and RSS creeps. Measured side by side
in two 30-minute soaks of the whole robot under the same seeded faults (load
about 20 on 2 cores): the knowledge service grew 67.7 -> 74.7 MiB (+10.3 %)
after the warm-up with glibc's default and 66.0 -> 69.2 MiB (+4.8 %, flat in
the last 10 minutes) with two arenas (docs/reliability.md).

``cap_arenas()`` must run before the process starts its threads: arenas
already made stay. ``MALLOC_ARENA_MAX`` in the environment, when set, wins.
"""

from __future__ import annotations

import ctypes
import logging
import os
import platform

log = logging.getLogger(__name__)

ARENAS = 2
_M_ARENA_MAX = -8  # from glibc's malloc.h


def cap_arenas(count: int = ARENAS) -> bool:
    """Limit glibc's malloc to ``count`` arenas; True when the limit was set here.

    Does nothing (False) off glibc or when ``MALLOC_ARENA_MAX`` is set.
    """
    if os.environ.get("MALLOC_ARENA_MAX") or platform.libc_ver()[0] != "glibc":
        return False
    try:
        done = ctypes.CDLL(None).mallopt(_M_ARENA_MAX, count)
    except (OSError, AttributeError) as exc:
        log.debug("mallopt unavailable: %s", exc)
        return False
    return bool(done)
