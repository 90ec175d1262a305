"""The malloc arena cap takes effect: a process with eight allocating threads keeps to two arenas.

glibc's ``malloc_stats()`` lists one "Arena N:" block per arena on stderr.
"""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="the arena cap is glibc's")

CHILD = """
import ctypes, sys, threading
from kgadapt.shared.allocator import cap_arenas
if sys.argv[1] == "cap":
    assert cap_arenas(), "mallopt refused"
ready = threading.Barrier(8)
def work():
    keep = [bytearray(200_000) for _ in range(20)]
    ready.wait()  # every thread holds its memory at once: no arena is handed on
threads = [threading.Thread(target=work) for _ in range(8)]
for t in threads:
    t.start()
for t in threads:
    t.join()
ctypes.CDLL(None).malloc_stats()
"""


def arenas(mode: str) -> int:
    env = {k: v for k, v in __import__("os").environ.items() if k != "MALLOC_ARENA_MAX"}
    done = subprocess.run([sys.executable, "-c", CHILD, mode], capture_output=True, text=True, timeout=60, env=env)
    assert done.returncode == 0, done.stderr
    return sum(1 for line in done.stderr.splitlines() if line.startswith("Arena "))


def test_eight_threads_use_at_most_two_arenas_once_capped_and_more_without():
    assert arenas("plain") > 2  # the default this guards against
    assert 1 <= arenas("cap") <= 2


def test_the_environment_wins(monkeypatch):
    from kgadapt.shared.allocator import cap_arenas

    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
    assert cap_arenas() is False
