"""A process tree's resident memory, read without walking every process of the machine.

The host monitor counts its own process tree (itself and every descendant)
against its memory budget ten times a second. ``psutil``'s
``children(recursive=True)`` finds descendants by reading the parent of every
process on the machine, about 0.8 ms with 67 processes and in proportion to
more, most of it Python holding the GIL beside the camera. Linux lists each
thread's children in ``/proc/<pid>/task/<tid>/children`` (every kernel built
with CONFIG_PROC_CHILDREN, the default of the common distributions), so the
tree is read from its own processes alone, and each one's RSS from
``/proc/<pid>/statm``.

Those lists are exact only while nothing in them exits: a child exiting
while its parent's list is read can make the kernel leave out a sibling that
lives on (proc_tid_children(5)). So a listing that lacks a process the last
reading had (an exit, or a sibling left out beside one) is not taken: that
reading walks every process with psutil, as it does where the lists are
missing or cannot be read and wherever an exact answer is asked for
(``exact=True``, the deployer's check before a start). A child born since the last reading and
left out beside an exit it did not know of is counted one reading later.

A process that exits between being listed and being read is left out, as
psutil's walk leaves it out.
"""

from __future__ import annotations

import logging
import os
import threading
from typing import Collection

import psutil

log = logging.getLogger(__name__)
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def _children(pid: int) -> list[int]:
    """The direct children of ``pid`` from its threads' children lists (any thread may fork)."""
    found: list[int] = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/children", "rb") as f:
                found.extend(int(child) for child in f.read().split())
        except (FileNotFoundError, ProcessLookupError):
            continue  # the thread ended between the listing and the read
    return found


def _rss(pid: int) -> int:
    with open(f"/proc/{pid}/statm", "rb") as f:
        return int(f.read().split()[1]) * _PAGE


class ProcessTree:
    """The resident memory of the process ``root`` and all its descendants. Thread-safe."""

    def __init__(self, root: int, *, listed: bool | None = None) -> None:
        self.root = root
        # Whether this kernel lists children per thread: None, found out on the first read; False, psutil's walk.
        self._listed = listed
        self._lock = threading.Lock()
        self._last: set[int] = set()  # the last reading's processes
        self.walks = 0  # readings that walked every process (the lists not there, not trusted, or not asked for)

    def listed(self) -> bool:
        """Whether this kernel lists each thread's children (read once)."""
        if self._listed is None:
            self._listed = os.path.exists(f"/proc/{self.root}/task/{self.root}/children")
        return self._listed

    def pids(self, *, exact: bool = False) -> list[int]:
        """``root`` and its descendants; ``exact``: from psutil's walk of every process."""
        with self._lock:
            tree = None
            if not exact and self.listed():
                try:
                    tree = self._from_lists()
                except OSError as exc:  # e.g. not allowed to read them (a hardened unit): walk from now on
                    log.warning("process tree of %d: cannot read /proc children lists (%s); walking every "
                                "process instead", self.root, exc)
                    self._listed = False
            if tree is None or not self._last.issubset(tree):  # an exit, or a process left out beside one
                tree = self._walked()
                self.walks += 1
            self._last = set(tree)
            return tree

    def rss_bytes(self, *, left_out: Collection[int] = (), exact: bool = False) -> int:
        """Resident memory of the tree's processes but ``left_out``, in bytes."""
        total = 0
        pids = self.pids(exact=exact)
        read = _rss if self.listed() else _psutil_rss  # after pids(): lists found unreadable there mean psutil
        for pid in pids:
            if pid in left_out:
                continue
            try:
                total += read(pid)
            except (FileNotFoundError, ProcessLookupError, psutil.NoSuchProcess):  # exited since it was listed
                continue
            except (OSError, psutil.Error):  # not readable this way: psutil's own reading, else left out
                try:
                    total += _psutil_rss(pid)
                except psutil.Error:
                    continue
        return total

    def _from_lists(self) -> list[int]:
        tree, index = [self.root], 0
        while index < len(tree):
            try:
                tree.extend(_children(tree[index]))
            except (FileNotFoundError, ProcessLookupError):  # exited: its children went to the reaper, out of this tree too
                pass
            index += 1
        return tree

    def _walked(self) -> list[int]:
        try:
            root = psutil.Process(self.root)
            return [self.root, *(child.pid for child in root.children(recursive=True))]
        except psutil.Error:
            return [self.root]


def _psutil_rss(pid: int) -> int:
    rss: int = psutil.Process(pid).memory_info().rss
    return rss
