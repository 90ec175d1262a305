"""The host monitor's process tree: its own processes found and their memory read from /proc, as psutil finds them.

Real processes: a child that holds 40 MiB and forks a grandchild from a thread other than its main one
(any thread may fork, and Linux lists each thread's children apart), the grandchild holding 24 MiB.
"""

from __future__ import annotations

import os
import subprocess
import sys

import psutil
import pytest

from kgadapt.shared.process_tree import ProcessTree

MIB = 1024 * 1024

_CHILD = r"""
import subprocess, sys, threading
held = bytearray(40 * 1024 * 1024)
grandchild = []
def fork():
    grandchild.append(subprocess.Popen([sys.executable, "-c",
        "import sys; held = bytearray(24 * 1024 * 1024); print('ready', flush=True); sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True))
thread = threading.Thread(target=fork)
thread.start(); thread.join()
grandchild[0].stdout.readline()
print(grandchild[0].pid, flush=True)
sys.stdin.read()
grandchild[0].stdin.close(); grandchild[0].wait()
"""


@pytest.fixture
def family():
    child = subprocess.Popen([sys.executable, "-c", _CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        line = child.stdout.readline()
        assert line.strip(), "the child did not start its grandchild"
        yield child.pid, int(line)
    finally:
        child.stdin.close()
        child.wait(timeout=10)


def _same(a: int, b: int) -> bool:
    """Two readings of idle processes' memory, a moment apart: the same but for a few pages."""
    return abs(a - b) <= 512 * 1024


def _psutil_rss(pids) -> int:
    return sum(psutil.Process(pid).memory_info().rss for pid in pids)


@pytest.mark.skipif(not os.path.exists(f"/proc/{os.getpid()}/task/{os.getpid()}/children"),
                    reason="this kernel does not list children per thread")
def test_the_tree_read_from_its_own_processes_is_psutils_tree(family):
    child, grandchild = family
    tree = ProcessTree(child)
    assert tree.listed()
    assert tree.pids() == [child, grandchild]  # the grandchild was forked by a second thread
    assert set(ProcessTree(os.getpid()).pids()) >= {os.getpid(), child, grandchild}
    assert _same(tree.rss_bytes(), _psutil_rss([child, grandchild]))
    assert tree.rss_bytes() >= (40 + 24) * MIB
    assert _same(tree.rss_bytes(left_out={grandchild}), _psutil_rss([child]))
    assert tree.rss_bytes() - tree.rss_bytes(left_out={grandchild}) >= 24 * MIB


def test_without_children_lists_psutils_walk_gives_the_same(family):
    child, grandchild = family
    walked, listed = ProcessTree(child, listed=False), ProcessTree(child)
    assert sorted(walked.pids()) == sorted(listed.pids()) == sorted([child, grandchild])
    assert _same(walked.rss_bytes(), _psutil_rss([child, grandchild]))
    assert _same(listed.rss_bytes(), _psutil_rss([child, grandchild]))


@pytest.mark.parametrize("listed", [True, False])
def test_a_tree_whose_root_is_gone_holds_nothing(listed):
    if listed and not ProcessTree(os.getpid()).listed():
        pytest.skip("this kernel does not list children per thread")
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    tree = ProcessTree(gone.pid, listed=listed)
    assert tree.pids() == [gone.pid]
    assert tree.rss_bytes() == 0


class _LeavingOut(ProcessTree):
    """The kernel's children lists as they can read while a child exits: a sibling that lives on left out."""

    leave_out: int | None = None

    def _from_lists(self) -> list[int]:
        return [pid for pid in super()._from_lists() if pid != self.leave_out]


@pytest.mark.skipif(not os.path.exists(f"/proc/{os.getpid()}/task/{os.getpid()}/children"),
                    reason="this kernel does not list children per thread")
def test_a_listing_that_lacks_a_process_of_the_last_one_is_not_taken(family):
    child, grandchild = family
    tree = _LeavingOut(child)
    assert tree.pids() == [child, grandchild] and tree.walks == 0  # the lists alone
    tree.leave_out = grandchild  # as when a sibling exits while the lists are read
    assert sorted(tree.pids()) == [child, grandchild] and tree.walks == 1  # psutil's walk found it
    assert _same(tree.rss_bytes(), _psutil_rss([child, grandchild])) and tree.walks == 2
    tree.leave_out = None
    assert tree.pids() == [child, grandchild] and tree.walks == 2  # the lists again
    assert sorted(tree.pids(exact=True)) == [child, grandchild] and tree.walks == 3  # asked for: the walk


class _Unreadable(ProcessTree):
    """Children lists this process may not read (a hardened unit, another user's process)."""

    def _from_lists(self) -> list[int]:
        raise PermissionError(13, "Permission denied", f"/proc/{self.root}/task/{self.root}/children")


def test_children_lists_that_cannot_be_read_give_way_to_psutils_walk(family):
    child, grandchild = family
    tree = _Unreadable(child, listed=True)
    assert sorted(tree.pids()) == [child, grandchild] and not tree.listed()
    assert _same(tree.rss_bytes(), _psutil_rss([child, grandchild]))
