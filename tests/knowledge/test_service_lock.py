"""The knowledge service's lease on a FalkorDB server (knowledge/service_lock.py), on a real server.

FalkorDB's client answers strings: a lease compared with bytes was never found to be its own, so it
ran out every ``lease_s`` and was taken again, each renewal between logging "held by another service",
and release never gave it back.
"""

from __future__ import annotations

import pytest

from kgadapt.knowledge.embedded import EmbeddedServer
from kgadapt.knowledge.falkordb_store import FalkorDBStore
from kgadapt.knowledge.service_lock import ServiceLock, ServiceLockHeld
from kgadapt.knowledge.store import StoreSettings


@pytest.fixture
def server_store(tmp_path):
    server = EmbeddedServer(tmp_path / "store", append_only=False)
    address = server.ensure()

    def store(graph: str = "g") -> FalkorDBStore:
        s = FalkorDBStore(StoreSettings(kind="falkordb", url=f"falkordb+unix://{address.unix_socket}",
                                        unix_socket=address.unix_socket, graph=graph, socket_timeout=2.0))
        s.setup()
        opened.append(s)
        return s
    opened: list[FalkorDBStore] = []
    yield store
    for s in opened:
        s.shutdown()
    server.stop()


def test_the_holder_renews_its_own_lease_and_release_gives_it_back(server_store):
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


def test_a_lease_another_service_holds_is_neither_renewed_nor_released(server_store):
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


def test_a_run_out_lease_is_taken_again_by_its_holder(server_store):
    store = server_store()
    lock = ServiceLock(store, lease_s=30.0)
    lock.acquire()
    try:
        store.redis.delete(lock.key)  # ran out (the holder stalled past its lease)
        assert lock.renew() is True
        assert store.redis.get(lock.key) == lock.holder
    finally:
        lock.release()
