"""The query sandbox copies the robot's graph again when that graph was written to, and only then.

Real FalkorDB servers: the session's RESP server holds the robot's graph and,
as in the fleet benchmark (and any server shared by several robots), other
graphs and keys that others write. Copies are counted on the primary as its
``DUMP`` calls, so the count does not depend on the sandbox's own bookkeeping.
"""

from __future__ import annotations

import threading

import pytest
import redis

from kgadapt.knowledge.falkordb_store import FalkorDBStore
from kgadapt.knowledge.sandbox import QuerySandbox
from kgadapt.knowledge.store import StoreSettings

COUNT = "MATCH (n:Item) RETURN count(n) AS items, sum(n.value) AS total"


def _dumps(client: redis.Redis) -> int:
    """DUMP calls the primary has served so far (each is one sandbox copy)."""
    return int(client.info("commandstats").get("cmdstat_dump", {}).get("calls", 0))


@pytest.fixture
def primary(resp_server):
    client = redis.Redis(unix_socket_path=resp_server.address.unix_socket, socket_timeout=60)
    yield client
    client.close()


@pytest.fixture
def sandbox(resp_store):
    resp_store.execute("UNWIND range(1, 5) AS i CREATE (:Item {id: i, value: 1})")
    box = QuerySandbox(resp_store)
    box.setup()
    yield box
    box.shutdown()


def _answer(box: QuerySandbox) -> tuple[int, int]:
    rows = box.execute(COUNT, limit_s=30.0)  # no graph at all: no rows
    return (rows[0]["items"], rows[0]["total"]) if rows else (0, 0)


def test_writes_to_other_graphs_and_keys_of_the_same_server_do_not_copy_the_graph_again(resp_store, primary,
                                                                                        sandbox):
    """Other robots' graphs and services' leases on one server: the robot's own graph is not copied for them."""
    other = f"{resp_store.settings.graph}_other_robot"
    try:
        assert _answer(sandbox) == (5, 5)
        before = _dumps(primary)
        for i in range(20):
            # What other robots' services do to the shared server between two questions to this one:
            primary.execute_command("GRAPH.QUERY", other, f"MERGE (r:FleetRobot {{name: 'x'}}) SET r.last_seen = {i}")
            primary.set(f"kgadapt:knowledge-service:{other}", "holder", px=3000)
            primary.pexpire(f"kgadapt:knowledge-service:{other}", 3000)
            assert _answer(sandbox) == (5, 5)
        assert _dumps(primary) - before == 0
        assert sandbox.copies == 1  # the first copy, at setup
    finally:
        primary.delete(other, f"kgadapt:knowledge-service:{other}")


def test_a_write_made_any_way_shows_in_the_next_answer(resp_store, resp_server, primary, sandbox):
    assert _answer(sandbox) == (5, 5)
    graph = resp_store.settings.graph
    # Through the project's store API, as the knowledge service and the CLI tools write.
    resp_store.execute("MATCH (n:Item {id: 1}) SET n.value = 10")
    assert _answer(sandbox) == (5, 14)  # a property update: the counts alone would not show it
    # Straight to the server by another store object and by a bare client (redis-cli alike).
    second = FalkorDBStore(StoreSettings(kind="falkordb", url=resp_store.url, unix_socket=resp_store.settings.unix_socket,
                                         graph=graph))
    second.setup()
    try:
        second.execute("MATCH (n:Item {id: 2}) SET n.value = 3")
    finally:
        second.shutdown()
    assert _answer(sandbox) == (5, 16)
    primary.execute_command("GRAPH.QUERY", graph, "MATCH (n:Item {id: 3}) DELETE n")
    assert _answer(sandbox) == (4, 15)
    resp_store.execute_atomic([("CREATE (:Item {id: 6, value: 100})", {}), ("CREATE (:Item {id: 7, value: 1})", {})])
    assert _answer(sandbox) == (6, 116)
    # The whole graph deleted and made anew.
    primary.execute_command("GRAPH.DELETE", graph)
    assert _answer(sandbox) == (0, 0)
    primary.execute_command("GRAPH.QUERY", graph, "CREATE (:Item {id: 1, value: 7})")
    assert _answer(sandbox) == (1, 7)
    # Unchanged since: no copy.
    copies = sandbox.copies
    assert _answer(sandbox) == (1, 7)
    assert sandbox.copies == copies


def test_a_write_still_running_while_the_graph_is_copied_shows_once_it_has_answered(resp_store, sandbox):
    """FalkorDB flags the watch when a write starts and again when it commits: a copy taken in between
    (without the write) is taken again."""
    for rows in (100_000, 150_000):
        before = _answer(sandbox)
        writer_done = threading.Event()
        errors: list[BaseException] = []

        def write(rows: int = rows) -> None:
            writer = FalkorDBStore(StoreSettings(kind="falkordb", url=resp_store.url,
                                                 unix_socket=resp_store.settings.unix_socket,
                                                 graph=resp_store.settings.graph, socket_timeout=120.0))
            writer.setup()
            try:
                writer.execute("UNWIND range(1, $rows) AS i CREATE (:Item {id: 1000 + i, value: 1})", {"rows": rows})
            except BaseException as exc:  # noqa: BLE001 - reported by the test below
                errors.append(exc)
            finally:
                writer.shutdown()
                writer_done.set()

        thread = threading.Thread(target=write)
        thread.start()
        while not writer_done.is_set():  # questions while the write runs: some copies land mid-write
            _answer(sandbox)
        thread.join()
        assert not errors
        assert _answer(sandbox) == (before[0] + rows, before[1] + rows)


def test_a_watch_lost_with_its_connection_copies_the_graph_again(resp_store, primary, sandbox):
    """The client reconnects silently after its connection is dropped; the new one watches nothing, so
    the next question must not trust it."""
    assert _answer(sandbox) == (5, 5)
    watching = [c for c in primary.client_list() if int(c.get("watch", 0)) > 0]
    assert len(watching) == 1, watching
    primary.execute_command("CLIENT", "KILL", "ID", watching[0]["id"])
    resp_store.execute("MATCH (n:Item {id: 1}) SET n.value = 2")  # the watch that would have seen it is gone
    assert _answer(sandbox) == (5, 6)


def test_the_sandbox_server_keeps_house_once_a_second_with_one_query_thread(sandbox):
    """A sandbox answers one question at a time: Redis' 10 Hz housekeeping and a thread per core only cost
    the robot CPU while idle (0.2 % of a core per server; two per robot, half a core for 100 robots here)."""
    assert _answer(sandbox) == (5, 5)
    with open(f"/proc/{sandbox.pid}/cmdline", "rb") as f:  # Redis retitles itself "... unixsocket:<path>"
        title = f.read().decode().replace("\0", " ")
    client = redis.Redis(unix_socket_path=title.split("unixsocket:")[1].split()[0], socket_timeout=30)
    try:
        assert client.config_get("hz") == {"hz": "1"}
        assert client.execute_command("GRAPH.CONFIG", "GET", "THREAD_COUNT") == [b"THREAD_COUNT", 1]
    finally:
        client.close()


def _queries_run(box: QuerySandbox) -> int:
    """Read-only queries the sandbox's own server has run."""
    client = redis.Redis(unix_socket_path=box.unix_socket)
    try:
        return int(client.info("commandstats").get("cmdstat_graph.RO_QUERY", {}).get("calls", 0))
    finally:
        client.close()


def test_a_cacheable_question_asked_again_of_an_unchanged_graph_is_answered_without_running_it(resp_store, primary,
                                                                                             sandbox):
    """An idle robot asked the same named query again answers from the rows it has; a write to its graph, made
    any way, shows in the very next answer; other questions always run."""
    by_value = "MATCH (n:Item) WHERE n.value >= $at_least RETURN count(n) AS items"
    assert sandbox.execute(COUNT, limit_s=30.0, cacheable=True) == [{"items": 5, "total": 5}]
    run = _queries_run(sandbox)
    for _ in range(10):
        assert sandbox.execute(COUNT, limit_s=30.0, cacheable=True) == [{"items": 5, "total": 5}]
    assert _queries_run(sandbox) == run and sandbox.cached_answers == 10
    # The parameters are part of the question: 1 and 1.0 and True are three questions.
    for value in (1, 1.0, True, 2):
        sandbox.execute(by_value, {"at_least": value}, limit_s=30.0, cacheable=True)
    assert _queries_run(sandbox) == run + 4
    # A question not marked cacheable (free Cypher) runs every time.
    sandbox.execute(COUNT, limit_s=30.0)
    sandbox.execute(COUNT, limit_s=30.0)
    assert _queries_run(sandbox) == run + 6
    # A write through the store API, then straight to the server: each shows in the next answer.
    resp_store.execute("MATCH (n:Item {id: 1}) SET n.value = 10")
    assert sandbox.execute(COUNT, limit_s=30.0, cacheable=True) == [{"items": 5, "total": 14}]
    primary.execute_command("GRAPH.QUERY", resp_store.settings.graph, "CREATE (:Item {id: 6, value: 1})")
    assert sandbox.execute(COUNT, limit_s=30.0, cacheable=True) == [{"items": 6, "total": 15}]
    assert sandbox.execute(by_value, {"at_least": 2}, limit_s=30.0, cacheable=True) == [{"items": 1}]


def test_a_server_killed_while_the_graph_was_written_is_started_again_and_shows_the_write(resp_store, sandbox):
    """The next question finds the copy stale and the server gone: a new server, not a failure at every
    question from then on (the copy is taken before any query could notice the server was gone)."""
    import os
    import signal

    assert sandbox.execute(COUNT, limit_s=30.0, cacheable=True) == [{"items": 5, "total": 5}]
    os.kill(sandbox.pid, signal.SIGKILL)
    resp_store.execute("MATCH (n:Item {id: 2}) SET n.value = 3")
    assert sandbox.execute(COUNT, limit_s=30.0, cacheable=True) == [{"items": 5, "total": 7}]
    assert sandbox.execute(COUNT, limit_s=30.0) == [{"items": 5, "total": 7}]
    assert sandbox.restarts == 1


def test_every_named_query_gives_the_same_rows_on_the_same_graph():
    """The knowledge service marks its named queries cacheable: none may read a clock or draw a random number."""
    import re

    from kgadapt.knowledge import queries

    varying = re.compile(r"\b(rand|randomUUID|timestamp|date|datetime|localdatetime|localtime|time)\s*\(", re.I)
    for name, query in queries.QUERIES.items():
        text = query.text_for(queries.check_params(name, {
            p: {"str": "x", "int": 1, "float": 1.0, "bool": True}.get(spec.type, "x")
            for p, spec in query.params.items() if spec.required}))
        assert not varying.search(text), f"named query {name!r} reads a clock or a random number"


def test_the_answers_kept_are_bounded_in_count_and_in_rows(resp_store):
    from kgadapt.knowledge.sandbox import SandboxSettings

    resp_store.execute("UNWIND range(1, 5) AS i CREATE (:Item {id: i, value: 1})")
    box = QuerySandbox(resp_store, SandboxSettings(answer_cache=2, answer_cache_rows=6))
    box.setup()
    try:
        rows = "MATCH (n:Item) WHERE n.value >= $v RETURN n.id AS id ORDER BY id"
        box.execute(rows, {"v": 1}, limit_s=30.0, cacheable=True)  # 5 rows kept
        run = _queries_run(box)
        box.execute(rows, {"v": 1}, limit_s=30.0, cacheable=True)
        assert _queries_run(box) == run
        box.execute(rows, {"v": 0}, limit_s=30.0, cacheable=True)  # 5 more: 10 > 6, the first goes
        box.execute(rows, {"v": 1}, limit_s=30.0, cacheable=True)
        assert _queries_run(box) == run + 2
        for v in (2, 3, 4):  # no rows each: three answers, at most two kept
            box.execute(rows, {"v": v}, limit_s=30.0, cacheable=True)
        box.execute(rows, {"v": 2}, limit_s=30.0, cacheable=True)
        assert _queries_run(box) == run + 6
        box.execute(rows, {"v": 4}, limit_s=30.0, cacheable=True)
        assert _queries_run(box) == run + 6
    finally:
        box.shutdown()
