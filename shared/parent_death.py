"""The parent-death signal: the kernel signals a child when the thread that forked it ends (Linux prctl).

The one place that talks to prctl; the supervisor, the launcher, ChildProcess and the embedded store's
starter use it. prctl is resolved at import, not in a freshly forked child: after fork
only async-signal-safe work is wise.
"""

from __future__ import annotations

import ctypes
import os
from typing import Callable

PR_SET_PDEATHSIG = 1
PR_SET_CHILD_SUBREAPER = 36


def _libc_prctl() -> Callable[..., int] | None:
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        return None
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    prctl.restype = ctypes.c_int
    func: Callable[..., int] = prctl
    return func


_prctl = _libc_prctl()


def set_death_signal(signum: int) -> bool:
    """Ask for ``signum`` when this process's parent thread ends; False where the kernel has no such request."""
    return _prctl is not None and _prctl(PR_SET_PDEATHSIG, signum, 0, 0, 0) == 0


def tie_to_parent(parent_pid: int, signum: int) -> bool:
    """In a freshly forked child (a preexec_fn): ask for ``signum`` when the forking thread ends, and take it at
    once if ``parent_pid`` has already died between the fork and this request (nobody would send it then).
    False when it was taken (and did not end this process)."""
    set_death_signal(signum)
    if os.getppid() != parent_pid:
        os.kill(os.getpid(), signum)
        return False
    return True


def become_subreaper() -> None:
    """Adopt this process's orphaned descendants. OSError where the kernel refuses or has no such request."""
    if _prctl is None:
        raise OSError("prctl is not available (not Linux)")
    if _prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, os.strerror(errno))
