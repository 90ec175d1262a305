"""An embedded FalkorDB that stops answering (alive, not dead) is restarted, and keeps what it acknowledged.

The hang is made with SIGSTOP: the process and its socket stay, nothing answers.
"""

from __future__ import annotations

import os
import signal

import pytest

from kgadapt.knowledge.store import open_store
from kgadapt.shared.errors import QueryTimeLimit, StoreUnavailable


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.fixture
def store(tmp_path):
    store = open_store(f"embedded:{tmp_path / 'store'}", socket_timeout=2.0)
    store.setup()
    yield store
    pid = store.server.address.pid if store.server and store.server.address else None
    store.shutdown()
    if pid and _alive(pid):
        os.kill(pid, signal.SIGKILL)


def test_a_hung_server_is_killed_and_restarted_and_the_next_query_finds_every_acknowledged_write(store):
    store.execute("CREATE (:Mark {name: $name})", {"name": "before the hang"})
    hung = store.server.address.pid
    os.kill(hung, signal.SIGSTOP)

    with pytest.raises(QueryTimeLimit, match="restarted"):
        store.execute("MATCH (m:Mark) RETURN m.name AS name", read_only=True)

    assert not _alive(hung)
    assert store.server.address.pid != hung
    rows = store.execute("MATCH (m:Mark) RETURN m.name AS name", read_only=True)
    assert rows == [{"name": "before the hang"}]


def test_a_busy_server_that_still_answers_ping_is_left_running(store):
    # A query past the hard limit on a live server is abandoned, and the server stays.
    store.execute("UNWIND range(1, 300) AS i CREATE (:N {i: i})")
    pid = store.server.address.pid
    with pytest.raises(QueryTimeLimit) as caught:
        store.execute("MATCH (a:N), (b:N), (c:N) RETURN count(*) AS n", read_only=True)
    assert "restarted" not in str(caught.value)
    assert _alive(pid) and store.server.address.pid == pid


def test_a_hung_server_found_by_another_process_is_replaced_not_joined(tmp_path):
    first = open_store(f"embedded:{tmp_path / 'store'}", socket_timeout=2.0)
    first.setup()
    hung = first.server.address.pid
    try:
        first.execute("CREATE (:Mark {name: $name})", {"name": "kept"})
        os.kill(hung, signal.SIGSTOP)
        second = open_store(f"embedded:{tmp_path / 'store'}", socket_timeout=2.0)
        second.setup()  # finds server.json, no PING answer: kills the hung one, starts its own
        try:
            assert not _alive(hung)
            assert second.server.owned and second.server.address.pid != hung
            assert second.execute("MATCH (m:Mark) RETURN m.name AS name", read_only=True) == [{"name": "kept"}]
        finally:
            second.shutdown()
    finally:
        if _alive(hung):
            os.kill(hung, signal.SIGKILL)
        try:
            first.shutdown()
        except StoreUnavailable:
            pass
