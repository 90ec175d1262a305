"""Other robots' door of the knowledge service: askers in turn, and their work in a lower-priority process.

An in-process service on a real FalkorDB and real Zenoh sessions on loopback;
the questions are sent as another robot sends them (a Zenoh get on
``knowledge/query/<name>``), its name in the query's attachment.
"""

from __future__ import annotations

import os
import queue
import signal
import threading

import pytest

from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.schema import ensure_indexes
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.shared import keys, messages
from kgadapt.shared.fair_queue import FairQueue
from kgadapt.shared.proc_stat import stat_fields, state_of
from tests.zenoh.conftest import MODEL_HOSTS, wait_for, wait_until_serving


def _serve(resp_store, zenoh_pair, robot, **settings):
    server, _ = zenoh_pair
    ensure_indexes(resp_store)
    resp_store.execute("UNWIND $names AS name MERGE (:Platform {name: name})", {"names": list(MODEL_HOSTS)})
    svc = KnowledgeService(resp_store, ServiceSettings(robot=robot, **settings))
    svc.setup(server)
    return svc


def _ask(session, robot: str, asker: str) -> str:
    """"ok", or the error text, of one ``platforms`` question asked as ``asker``."""
    payload = messages.encode("query_request", {"params": {}})
    for reply in session.get(keys.knowledge_query(robot, "platforms"), payload=payload, timeout=60,
                             attachment=asker.encode()):
        if reply.ok is not None:
            return "ok"
        return reply.err.payload.to_bytes().decode()
    return "no reply"


def test_one_askers_flood_cannot_take_another_askers_share(resp_store, zenoh_pair, robot):
    svc = _serve(resp_store, zenoh_pair, robot, public_workers=1, max_pending_public=32, max_pending_per_asker=4,
                 own_first_wait_s=120.0)
    _, session = zenoh_pair
    try:
        wait_until_serving(session, robot)
        answers: queue.Queue[tuple[str, str]] = queue.Queue()

        def ask(asker: str) -> None:
            answers.put((asker, _ask(session, robot, asker)))

        with svc.own_first.serving():  # the public worker waits: every question queues meanwhile
            # Its first question is held by the worker before the rest come (on a loaded machine the worker
            # could otherwise take it only after the line had filled, and one more would be refused).
            flood = [threading.Thread(target=ask, args=("quad2",)) for _ in range(40)]  # more than the whole bound
            flood[0].start()
            wait_for(lambda: svc.own_first.waiting == 1, 30, "the public worker holding quad2's first question")
            for t in flood[1:]:
                t.start()
            # The flood's questions beyond its own line (and the one the worker holds) are refused at once.
            refused = [answers.get(timeout=30) for _ in range(40 - 4 - 1)]
            assert {who for who, _ in refused} == {"quad2"}
            assert all("busy" in text for _, text in refused), refused
            other = threading.Thread(target=ask, args=("quad3",))
            other.start()
            with pytest.raises(queue.Empty):  # quad3's question waits its turn, it is not refused
                answers.get(timeout=1.0)
        rest = [answers.get(timeout=60) for _ in range(4 + 1 + 1)]
        assert ("quad3", "ok") in rest
        assert [text for _, text in rest] == ["ok"] * 6
        # quad3 took its turn after one more of quad2's (whose line was first), not after all of them.
        assert rest.index(("quad3", "ok")) <= 2, rest
        for t in [*flood, other]:
            t.join(10)
    finally:
        svc.shutdown()


def test_the_fair_queue_serves_askers_in_turn_within_their_bounds():
    fair = FairQueue(maxsize=5, per_asker=3, asker_of=lambda item: item[0])
    for item in [("a", 1), ("a", 2), ("a", 3)]:
        fair.put_nowait(item)
    with pytest.raises(queue.Full):
        fair.put_nowait(("a", 4))  # a's line is full
    fair.put_nowait(("b", 1))
    fair.put_nowait(("c", 1))
    with pytest.raises(queue.Full):
        fair.put_nowait(("d", 1))  # the whole is full
    assert [fair.get_nowait() for _ in range(5)] == [("a", 1), ("b", 1), ("c", 1), ("a", 2), ("a", 3)]
    with pytest.raises(queue.Empty):
        fair.get_nowait()


def _cpu_ticks(pid: int) -> int:
    fields = stat_fields(pid)
    return int(fields[11]) + int(fields[12])  # utime + stime


def test_other_robots_questions_are_read_and_encoded_in_a_lower_priority_process(resp_store, zenoh_pair, robot):
    svc = _serve(resp_store, zenoh_pair, robot, public_workers=1, public_nice=19)
    _, session = zenoh_pair
    try:
        wait_until_serving(session, robot)
        resp_store.execute("UNWIND range(1, 3000) AS i CREATE (:Bulk {name: 'n' + toString(i), pad: 'x' + toString(i)})")
        [worker] = svc.public_processes
        assert worker.pid != os.getpid()
        assert os.getpriority(os.PRIO_PROCESS, worker.pid) >= min(19, os.getpriority(os.PRIO_PROCESS, 0) + 19)
        before = _cpu_ticks(worker.pid)
        outsider = KnowledgeClient(session, robot, timeout=30.0)
        for _ in range(5):
            rows = outsider.cypher("MATCH (n:Bulk) RETURN n.name AS name, n.pad AS pad")
            assert len(rows) == 1000  # the Cypher subset's row bound
        # The rows were read and encoded there: it spent CPU on them (each 1,000-row answer costs tens of ms).
        assert _cpu_ticks(worker.pid) > before
        # And a question past its limit stops there too, answered as such.
        with pytest.raises(Exception, match="time limit"):
            outsider.cypher("MATCH (a), (b), (c), (d) RETURN count(*) AS n")
        assert outsider.cypher("RETURN 1 AS one") == [{"one": 1}]  # the worker answers again afterwards
        # A worker process that dies is started afresh for the next question; that question is answered.
        os.kill(worker.pid, signal.SIGKILL)
        wait_for(lambda: _gone(worker.pid), 10, "the killed worker reaped")
        assert outsider.cypher("RETURN 2 AS two") == [{"two": 2}]
        assert worker.restarts == 1 and svc.stats()["public_worker_restarts"] == 1
        last = worker.pid
    finally:
        svc.shutdown()
    assert last is not None and _gone(last)  # shutdown ended it


def _gone(pid: int) -> bool:
    """Ended (a zombie not yet reaped by the service counts as ended)."""
    try:
        return state_of(pid) == "Z"
    except FileNotFoundError:
        return True


def _primary_dumps(resp_store) -> int:
    """DUMP calls the store's server has served: each is a public worker's sandbox copying a graph."""
    return int(resp_store.redis.info("commandstats").get("cmdstat_dump", {}).get("calls", 0))


def test_other_robots_answers_show_every_write_and_the_graph_is_copied_only_for_writes_to_it(resp_store, zenoh_pair,
                                                                                             robot):
    """One server holding several robots' graphs (the fleet bench, a shared falkordb://): writes to the others
    and their services' leases copy nothing here; a write to this robot's graph, through the service or
    straight to the store, shows in its next public answer."""
    import time

    svc = _serve(resp_store, zenoh_pair, robot, public_workers=1)
    other = f"{resp_store.settings.graph}_neighbour"
    redis = resp_store.redis

    def free_mb() -> dict[str, float | None]:
        rows = messages.decode(svc.answer_named("platforms", None, public=True), "rows")["rows"]
        return {row["platform"]: row["memory_free_mb"] for row in rows}

    try:
        # Its roll calls (at setup and 5 s later) write its roster, which is kept beside this graph: running
        # on, they copy nothing either.
        free_mb()  # the copy taken after the service's own setup writes (every platform marked offline)
        before = _primary_dumps(resp_store)
        for i in range(10):
            redis.execute_command("GRAPH.QUERY", other, f"MERGE (r:FleetRobot {{name: 'n'}}) SET r.last_seen = {i}")
            redis.set(f"kgadapt:knowledge-service:{other}", "holder", px=3000)
            # A fleet question asking this robot's roster (no roll call: it announces nothing) writes nothing.
            svc.answer_named("fleet_roster", None, public=True)
            assert free_mb()["h1"] is None
        assert _primary_dumps(resp_store) - before == 0
        # A write through the service (a write verb), then one straight to the store (a CLI tool, redis-cli).
        svc.answer_write("platform", messages.encode("write_request", {"params": {
            "name": "h1", "time": time.time(), "memory_total_mb": 4000.0, "memory_free_mb": 1234.0}}))
        assert free_mb()["h1"] == 1234.0
        resp_store.execute("MATCH (p:Platform {name: 'h2'}) SET p.memory_free_mb = 777.0")
        assert free_mb()["h2"] == 777.0
        redis.execute_command("GRAPH.QUERY", resp_store.settings.graph,
                              "MATCH (p:Platform {name: 'h2'}) SET p.memory_free_mb = 778.0")
        assert free_mb()["h2"] == 778.0
    finally:
        svc.shutdown()
        redis.delete(other, f"kgadapt:knowledge-service:{other}")


def test_a_worker_that_dies_before_it_is_ready_is_started_once_more_and_the_log_says_how_it_ended(resp_store, caplog):
    from kgadapt.knowledge.public_worker import PublicWorker

    resp_store.execute("CREATE (:Mark {name: 'm'})")
    worker = PublicWorker(resp_store)
    worker.start()
    first = worker.pid
    assert first is not None
    os.kill(first, signal.SIGKILL)  # before it said it was ready
    try:
        with caplog.at_level("WARNING", logger="kgadapt.knowledge.public_worker"):
            worker.wait_ready()
        assert worker.restarts == 1 and worker.pid not in (None, first)
        assert "killed by signal SIGKILL" in caplog.text
        reply = messages.decode(worker.execute("MATCH (m:Mark) RETURN m.name AS name", {}, limit_ms=5000,
                                               what="marks"), "rows")
        assert reply["rows"] == [{"name": "m"}]  # the second process answers
    finally:
        worker.shutdown()
