"""A process tree's resident memory, read without walking every process of the machine.

The host monitor counts its own process tree (itself and every descendant)
against its memory budget ten times a second. ``psutil``'s
``children(recursive=True)`` finds descendants by reading the parent of every
process on the machine, about 0.8 ms with 67 processes and in proportion to
more, most of it Python holding the GIL beside the camera. Linux lists each
thread's children in ``/proc/<pid>/task/<tid>/children`` (every kernel built
with CONFIG_PROC_CHILDREN, the default of the common distributions), so the
tree is read from its own processes alone, and each one's RSS from
``/proc/<pid>/statm``. Where those files are missing, psutil's walk is used.

A process that exits between being listed and being read is left out, as
psutil's walk leaves it out.
"""

from __future__ import annotations

import os
from typing import Collection

import psutil

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
    """The resident memory of the process ``root`` and all its descendants."""

    def __init__(self, root: int, *, listed: bool | None = None) -> None:
        self.root = root
        # Whether this kernel lists children per thread: None, found out on the first read; False, psutil's walk.
        self._listed = listed

    def listed(self) -> bool:
        """Whether this kernel lists each thread's children (read once)."""
        if self._listed is None:
            self._listed = os.path.exists(f"/proc/{self.root}/task/{self.root}/children")
        return self._listed

    def pids(self) -> list[int]:
        """``root`` and its descendants, parents before their children."""
        if not self.listed():
            return self._walked()
        tree, index = [self.root], 0
        while index < len(tree):
            try:
                tree.extend(_children(tree[index]))
            except (FileNotFoundError, ProcessLookupError):  # exited: its children went to the reaper, out of this tree too
                pass
            index += 1
        return tree

    def rss_bytes(self, *, left_out: Collection[int] = ()) -> int:
        """Resident memory of the tree's processes but ``left_out``, in bytes."""
        if not self.listed():
            return self._walked_rss(left_out)
        total = 0
        for pid in self.pids():
            if pid in left_out:
                continue
            try:
                total += _rss(pid)
            except (FileNotFoundError, ProcessLookupError):  # exited since it was listed
                continue
        return total

    def _walked(self) -> list[int]:
        try:
            root = psutil.Process(self.root)
            return [self.root, *(child.pid for child in root.children(recursive=True))]
        except psutil.Error:
            return [self.root]

    def _walked_rss(self, left_out: Collection[int]) -> int:
        total = 0
        for pid in self._walked():
            if pid in left_out:
                continue
            try:
                total += psutil.Process(pid).memory_info().rss
            except psutil.Error:
                continue
        return total
