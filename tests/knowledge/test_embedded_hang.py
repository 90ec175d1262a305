"""An embedded FalkorDB that stops answering (alive, not dead) is restarted, and keeps what it acknowledged.

The hang is made with SIGSTOP: the process and its socket stay, nothing answers. So also for a freshly
started server that never answers its setup statements, as one did twice in CI.
"""

from __future__ import annotations

import os
import signal

import pytest

from kgadapt.knowledge.embedded import EmbeddedServer
from kgadapt.knowledge.falkordb_store import FalkorDBStore
from kgadapt.knowledge.loader import load_models
from kgadapt.knowledge.schema import ensure_indexes
from kgadapt.knowledge.store import StoreSettings, open_store
from kgadapt.shared.errors import QueryTimeLimit, StoreUnavailable
from kgadapt.shared.proc_stat import state_of
from kgadapt.shared.resources import models as shipped_models


def _alive(pid: int) -> bool:
    try:
        return state_of(pid) != "Z"
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
    # A query past the hard limit on a live server is abandoned, and the server stays. 500³ rows: about
    # 9 s on a quiet machine, well past the 2 s limit (300³ took 1.86 s there and was sometimes answered).
    store.execute("UNWIND range(1, 500) AS i CREATE (:N {i: i})")
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
        _kill_left([hung])
        try:
            first.shutdown()
        except StoreUnavailable:
            pass


# -- a fresh server that never answers its setup statements (seen twice in CI: every thread on a futex) ------


def _store_with_hook(data, on_start, *, setup_timeout=1.0):
    # setup_timeout small: the test's wall time is about two such bounds
    settings = StoreSettings(kind="embedded", url=f"embedded:{data}", data_dir=data, setup_timeout=setup_timeout)
    return FalkorDBStore(settings, server=EmbeddedServer(data, on_start=on_start))


def _stopping_the_first(stopped: list[int]):
    """A server-start hook that stops the first server started (alive, its socket open, answering nothing:
    as the hung server was) and notes its pid in ``stopped``."""
    def stop_the_first(pid: int) -> None:
        if not stopped:
            os.kill(pid, signal.SIGSTOP)
            stopped.append(pid)
    return stop_the_first


def _kill_left(pids) -> None:
    for pid in pids:
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)


def _seeded(data) -> None:
    with open_store(f"embedded:{data}") as store:
        store.execute("CREATE (:Mark {name: $name})", {"name": "before the start"})


@pytest.mark.timeout(60)
def test_a_fresh_server_that_never_answers_its_first_statement_is_killed_and_started_once_more(tmp_path):
    data = tmp_path / "store"
    _seeded(data)
    stopped: list[int] = []

    stop_the_first = _stopping_the_first(stopped)
    store = _store_with_hook(data, stop_the_first)
    try:
        store.setup()
        assert stopped and not _alive(stopped[0])
        assert store.server.address.pid != stopped[0] and store.server.starts == 2
        ensure_indexes(store)
        assert store.execute("MATCH (m:Mark) RETURN m.name AS name", read_only=True) == [{"name": "before the start"}]
    finally:
        store.shutdown()
        _kill_left(stopped)


@pytest.mark.timeout(60)
def test_when_the_restarted_server_hangs_too_the_error_says_what_each_was_doing(tmp_path):
    data = tmp_path / "store"
    stopped: list[int] = []

    def stop_every(pid: int) -> None:
        os.kill(pid, signal.SIGSTOP)
        stopped.append(pid)

    store = _store_with_hook(data, stop_every)
    try:
        with pytest.raises(StoreUnavailable) as caught:
            store.setup()
        message = str(caught.value)
        assert len(stopped) == 2, message
        # state T: stopped; the wait channel of a stopped thread (do_signal_stop) is named too
        assert f"pid {stopped[1]} state T (stopped), threads' wait channels: " in message
        assert f"pid {stopped[0]} state T (stopped)" in message
        assert "within 1 s" in message and "answers PING: no" in message
        assert not _alive(stopped[0]) and not _alive(stopped[1])  # neither left behind, hung
    finally:
        store.shutdown()
        _kill_left(stopped)


@pytest.mark.timeout(60)
def test_a_model_load_whose_own_server_stops_answering_runs_again_on_a_restarted_one(tmp_path):
    store = _store_with_hook(tmp_path / "store", None)
    store.setup()
    hung = store.server.address.pid
    try:
        store.execute("CREATE (:Mark {name: $name})", {"name": "kept"})
        os.kill(hung, signal.SIGSTOP)
        loaded = load_models(store, [shipped_models()])
        assert not _alive(hung) and store.server.address.pid != hung
        platforms = store.execute("MATCH (p:Platform) RETURN count(p) AS n", read_only=True)[0]["n"]
        assert platforms == loaded.labels["Platform"] > 0
        assert store.execute("MATCH (m:Mark) RETURN m.name AS name", read_only=True) == [{"name": "kept"}]
    finally:
        store.shutdown()
        _kill_left([hung])


def test_a_server_found_stopped_is_described_by_its_state_and_threads(tmp_path):
    server = EmbeddedServer(tmp_path / "store", append_only=False)
    address = server.ensure()
    try:
        os.kill(address.pid, signal.SIGSTOP)
        os.waitid(os.P_PID, address.pid, os.WSTOPPED | os.WNOWAIT)  # until the kernel has stopped it
        text = server.describe()
        assert text.startswith(f"pid {address.pid} state T (stopped), threads' wait channels: ")
        threads = len(os.listdir(f"/proc/{address.pid}/task"))
        counts = [int(part.rsplit(" x", 1)[1]) for part in text.split(": ", 1)[1].split(", ")]
        assert sum(counts) == threads
        assert state_of(address.pid) == "T"
    finally:
        os.kill(address.pid, signal.SIGKILL)
        server.stop()


@pytest.mark.timeout(60)
def test_a_query_sandbox_whose_fresh_server_never_answers_its_first_copy_starts_another(resp_store, monkeypatch):
    from kgadapt.knowledge import sandbox as sandbox_module

    stopped: list[int] = []

    stop_the_first = _stopping_the_first(stopped)
    # the sandbox makes its own server: hand it one that stops its first start (the seam is the hook alone)
    monkeypatch.setattr(sandbox_module, "EmbeddedServer",
                        lambda *args, **kwargs: EmbeddedServer(*args, on_start=stop_the_first, **kwargs))
    resp_store.execute("UNWIND range(1, 3) AS i CREATE (:Item {id: i})")
    box = sandbox_module.QuerySandbox(resp_store)
    try:
        box.setup()
        assert stopped and not _alive(stopped[0]) and box.pid != stopped[0]
        assert box.execute("MATCH (n:Item) RETURN count(n) AS n", limit_s=5.0) == [{"n": 3}]
    finally:
        box.shutdown()
        _kill_left(stopped)
