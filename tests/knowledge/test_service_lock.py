"""The knowledge service's lease on a FalkorDB server (knowledge/service_lock.py), on a real server.

FalkorDB's client answers strings: a lease compared with bytes was never found to be its own, so it
ran out every ``lease_s`` and was taken again, each renewal between logging "held by another service",
and release never gave it back.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import threading
import time
import warnings

import pytest
import redis

from kgadapt.knowledge.embedded import EmbeddedServer
from kgadapt.knowledge.falkordb_store import FalkorDBStore
from kgadapt.knowledge.service_lock import ServiceLock, ServiceLockHeld
from kgadapt.knowledge.store import StoreSettings
from kgadapt.shared.errors import StoreUnavailable
from kgadapt.shared.proc_stat import state_of


class _Servers:
    """A fresh FalkorDB server per attempt, and stores on it (what the tests' ``server_store`` is)."""

    def __init__(self, where) -> None:
        self.server = EmbeddedServer(where, append_only=False)
        self.address = self.server.ensure()
        self.opened: list[FalkorDBStore] = []

    def __call__(self, graph: str = "g") -> FalkorDBStore:
        s = FalkorDBStore(StoreSettings(kind="falkordb", url=f"falkordb+unix://{self.address.unix_socket}",
                                        unix_socket=self.address.unix_socket, graph=graph, socket_timeout=2.0))
        s.setup()
        self.opened.append(s)
        return s

    def close(self) -> None:
        for s in self.opened:
            s.shutdown()
        self.server.stop(timeout=2.0)


def _threads_of(pid: int) -> str:
    """Every thread's stack of a hung server, for the report (gdb, where installed)."""
    gdb = shutil.which("gdb")
    if gdb is None:
        return "(no gdb here for the threads' stacks)"
    try:
        done = subprocess.run([gdb, "-p", str(pid), "-batch", "-nx", "-ex", "thread apply all bt 12"],
                              capture_output=True, text=True, timeout=60, check=False)
    except subprocess.TimeoutExpired:
        return "(gdb did not finish within 60 s)"
    return "\n".join(line for line in done.stdout.splitlines() if line.startswith(("Thread", "#")))


def _on_a_server_that_answers(tmp_path, body) -> None:
    """``body(server_store)`` on a fresh server; once more on another if the first was found hung.

    A freshly started FalkorDB (4.x on redis 8.2) now and then stops answering everything, every thread
    waiting on a lock: in CI once at its first graph statement (the store's setup restarts such a server)
    and once at a plain DEL of this test's lease key. That is FalkorDB's (its issue #2129 reports the same
    state under write load), not the lease's, which these tests are about. A timeout from a server that
    still answers PING is a failure as any other; so is a second hung server.
    """
    for attempt in (1, 2):
        servers = _Servers(tmp_path / f"store{attempt}")
        try:
            body(servers)
            return
        except (redis.TimeoutError, StoreUnavailable):
            if attempt == 2 or servers.server.answers():
                raise
            pid = servers.address.pid
            warnings.warn(f"the lease test's FalkorDB server hung ({servers.server.describe()}); "
                          f"running the test once more on a new one. Its threads:\n{_threads_of(pid)}",
                          stacklevel=1)
            servers.server.kill()
        finally:
            servers.close()


def test_the_holder_renews_its_own_lease_and_release_gives_it_back(tmp_path):
    def body(server_store):
        store = server_store()
        lock = ServiceLock(store, lease_s=30.0)  # no renewal thread round within the test
        lock.acquire()
        try:
            store.redis.pexpire(lock.key, 500)  # nearly run out
            assert lock.renew() is True
            assert store.redis.pttl(lock.key) > 20_000  # extended to a whole lease again
        finally:
            lock.release()
        assert store.redis.get(lock.key) is None  # given back: a new service need not wait for it to run out
        second = ServiceLock(server_store(), lease_s=30.0)
        second.acquire()  # at once
        second.release()
    _on_a_server_that_answers(tmp_path, body)


def test_a_lease_another_service_holds_is_neither_renewed_nor_released(tmp_path):
    def body(server_store):
        store = server_store()
        lock = ServiceLock(store, lease_s=30.0)
        lock.acquire()
        try:
            store.redis.set(lock.key, "someone else", px=30_000)  # it ran out and another took it
            assert lock.renew() is False
            with pytest.raises(ServiceLockHeld, match="someone else"):
                ServiceLock(server_store(), lease_s=0.2).acquire()
        finally:
            lock.release()
        assert store.redis.get(lock.key) == "someone else"
    _on_a_server_that_answers(tmp_path, body)


def test_a_run_out_lease_is_taken_again_by_its_holder(tmp_path):
    def body(server_store):
        store = server_store()
        lock = ServiceLock(store, lease_s=30.0)
        lock.acquire()
        try:
            store.redis.delete(lock.key)  # ran out (the holder stalled past its lease)
            assert lock.renew() is True
            assert store.redis.get(lock.key) == lock.holder
        finally:
            lock.release()

    _on_a_server_that_answers(tmp_path, body)


def test_a_renewal_whose_connection_the_server_closed_is_sent_again_on_a_new_one(tmp_path):
    # A renewal goes out on a connection of its own (packed once, for its CPU): one the server closed (a
    # restart, CLIENT KILL, a timeout) fails that renewal at most, and the next one opens another.
    def body(server_store):
        store = server_store()
        lock = ServiceLock(store, lease_s=30.0)  # no renewal thread round within the test
        lock.acquire()
        try:
            assert lock.renew() is True
            store.redis.client_kill_filter(_type="normal", skipme=True)  # every connection but this one
            outcomes = []
            for _ in range(2):
                try:
                    outcomes.append(lock.renew())
                except redis.ConnectionError:
                    outcomes.append("closed")
            assert outcomes[-1] is True, outcomes
            store.redis.pexpire(lock.key, 500)
            assert lock.renew() is True
            assert store.redis.pttl(lock.key) > 20_000  # the new connection renews the whole lease
        finally:
            lock.release()
        assert store.redis.get(lock.key) is None
    _on_a_server_that_answers(tmp_path, body)


_HOLDER = """
import sys, time
from kgadapt.knowledge.falkordb_store import FalkorDBStore
from kgadapt.knowledge.service_lock import ServiceLock
from kgadapt.knowledge.store import StoreSettings
sock = sys.argv[1]
store = FalkorDBStore(StoreSettings(kind="falkordb", url="falkordb+unix://" + sock, unix_socket=sock, graph="g"))
store.setup()
ServiceLock(store, lease_s=300.0).acquire()
print("held", flush=True)
time.sleep(600)
"""


@pytest.mark.parametrize("reaped", [True, False], ids=["reaped", "zombie"])
def test_a_service_killed_on_this_machine_leaves_its_lease_to_its_successor_at_once(tmp_path, reaped):
    # kill -9 and a restart on the same machine: the successor finds the lease's process gone (or a zombie
    # its parent has not reaped yet) and takes the lease without waiting out its 300 s.
    def body(server_store):
        store = server_store()
        child = subprocess.Popen([sys.executable, "-c", _HOLDER, str(store.settings.unix_socket)],
                                 stdout=subprocess.PIPE, text=True)
        try:
            assert child.stdout.readline().strip() == "held"
            held = store.redis.get(ServiceLock(store).key)
            assert f'"pid": {child.pid}' in held
            child.kill()
            if reaped:
                child.wait(timeout=10)
            else:  # dead, not yet waited for
                _wait_for(lambda: state_of(child.pid) == "Z")
            successor = ServiceLock(store, lease_s=300.0)
            taking = threading.Thread(target=successor.acquire, daemon=True)
            taking.start()
            taking.join(timeout=60)  # without the takeover it waits out the dead holder's 300 s lease
            assert not taking.is_alive(), "the successor waits for a dead holder's lease"
            try:
                assert store.redis.get(successor.key) == successor.holder
            finally:
                successor.release()
        finally:
            child.kill()
            child.wait(timeout=10)
            child.stdout.close()
    _on_a_server_that_answers(tmp_path, body)


def test_a_lease_of_a_living_process_elsewhere_or_unnamed_is_not_taken(tmp_path):
    # Only a process of this machine and pid namespace that has ended gives its lease up early: a holder
    # alive here, one on another machine (another boot) and one that names no process are all waited out.
    def body(server_store):
        store = server_store()
        waiter = ServiceLock(store, lease_s=0.3)
        here = json.loads(waiter.holder)
        living = dict(here, id="other")  # this very process: alive, same start time
        elsewhere = dict(here, boot="another-boot", pid=2**22 + 1)  # no such pid here, but not here either
        reused = dict(here, start=here["start"] - 1)  # this pid, but a process that started earlier: ended
        for holder, taken in ((living, False), (elsewhere, False), ({"pid": 2**22 + 1}, False), (reused, True)):
            store.redis.set(waiter.key, json.dumps(holder), px=30_000)
            if taken:
                waiter.acquire()
                assert store.redis.get(waiter.key) == waiter.holder
                waiter.release()
            else:
                with pytest.raises(ServiceLockHeld):
                    waiter.acquire()
                assert json.loads(store.redis.get(waiter.key)) == holder
    _on_a_server_that_answers(tmp_path, body)


def _wait_for(condition, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met within the wait"
        time.sleep(0.02)
