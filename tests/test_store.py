"""The store interface behaves the same on every backend."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from kgadapt.knowledge.store import assert_read_only, open_store, parse_store_url, read_only_verdicts
from kgadapt.shared.errors import ConfigError, QueryError, ReadOnlyViolation

TRICKY = ['a"b', "it's", "back\\slash", "x\ny", "ü€", "a'}) DETACH DELETE n //", "$param", ""]


def _splices(store) -> bool:
    return getattr(store, "_splices_params", False)


def test_values_travel_as_parameters_and_come_back_unchanged(store):
    # FalkorDB's Bolt listener pastes parameters into query text; there quotes are refused.
    safe = [v for v in TRICKY if not _splices(store) or ("'" not in v and "\\" not in v)]
    for value in safe:
        store.execute("CREATE (:Probe {v: $v})", {"v": value})
    rows = store.execute("MATCH (p:Probe) RETURN p.v AS v ORDER BY v", read_only=True)
    assert sorted(r["v"] for r in rows) == sorted(safe)


def test_a_server_that_splices_parameters_gets_no_quoted_strings(bolt_store):
    assert _splices(bolt_store), "FalkorDB's Bolt listener was expected to splice parameters"
    with pytest.raises(QueryError, match="pastes parameters"):
        bolt_store.execute("MATCH (p) WHERE p.v = $v RETURN 1 AS p", {"v": "x' RETURN 1 AS p //"})


def test_injection_shaped_values_do_not_change_the_graph(store):
    store.execute("CREATE (:Probe {v: 1})")
    store.execute("MATCH (p:Probe) WHERE p.v = $v RETURN p", {"v": "1}) DETACH DELETE p //"})
    assert store.execute("MATCH (p:Probe) RETURN count(p) AS c")[0]["c"] == 1


def test_read_only_path_refuses_writes(store):
    with pytest.raises(ReadOnlyViolation):
        store.execute("CREATE (:Nope)", read_only=True)
    with pytest.raises(ReadOnlyViolation):
        store.execute("MATCH (n) DETACH DELETE n", read_only=True)
    assert store.execute("MATCH (n:Nope) RETURN count(n) AS c")[0]["c"] == 0


def test_a_read_on_a_graph_never_written_returns_no_rows(resp_store):
    assert resp_store.execute("MATCH (n) RETURN n", read_only=True) == []


def test_a_bad_query_raises_query_error_and_the_store_keeps_answering(store):
    with pytest.raises(QueryError):
        store.execute("MATCH (n RETURN n")
    assert store.execute("RETURN 1 AS one") == [{"one": 1}]


def test_atomic_batch_applies_every_statement(store):
    store.execute_atomic([("CREATE (:A {i: $i})", {"i": i}) for i in range(5)])
    assert store.execute("MATCH (a:A) RETURN sum(a.i) AS s")[0]["s"] == 10


def test_nodes_come_back_as_plain_dicts_with_labels(store):
    store.execute("CREATE (:Platform:Thing {name: $n, memory_total_mb: 512.0})", {"n": "onboard"})
    node = store.execute("MATCH (p:Platform) RETURN p", read_only=True)[0]["p"]
    assert node["name"] == "onboard" and node["memory_total_mb"] == 512.0
    assert set(node["_labels"]) == {"Platform", "Thing"}


def test_non_finite_numbers_are_refused_before_reaching_the_store(store):
    with pytest.raises(QueryError, match="finite"):
        store.execute("RETURN $x AS x", {"x": float("nan")})


def test_lexical_read_only_check_ignores_words_inside_strings():
    assert_read_only("MATCH (n) WHERE n.name = 'CREATE SET DELETE' RETURN n")
    assert_read_only("MATCH (n) RETURN n.set AS load, {create: 1} AS m")
    with pytest.raises(ReadOnlyViolation, match="MERGE"):
        assert_read_only("MATCH (n) merge (m:X) RETURN n")
    with pytest.raises(ReadOnlyViolation, match="CALL"):
        assert_read_only("CALL db.idx.fulltext.drop('x')")


@pytest.mark.parametrize("url, kind", [
    ("embedded:/tmp/x", "embedded"), ("falkordb://h:1234", "falkordb"),
    ("memgraph://h:7687", "memgraph"), ("bolt://h:7687", "bolt"),
])
def test_store_urls_name_their_backend(url, kind):
    assert parse_store_url(url).kind == kind


@pytest.mark.parametrize("url", ["mysql://h:1", "falkordb://", "falkordb://h:notaport",
                                 "falkordb://h:6379/quad1.import-partial.0a1b2c3d4e5f"])
def test_bad_store_urls_fail_with_the_url_named(url):
    with pytest.raises(ConfigError, match="store URL"):
        parse_store_url(url)


def test_a_second_process_finds_the_running_embedded_store_instead_of_starting_another(tmp_path):
    first = open_store(f"embedded:{tmp_path}")
    first.setup()
    try:
        first.execute("CREATE (:Mark {n: 7})")
        code = (
            "from kgadapt.knowledge.store import open_store\n"
            f"s = open_store('embedded:{tmp_path}'); s.setup()\n"
            "assert not s.server.owned\n"
            "print(s.execute('MATCH (m:Mark) RETURN m.n AS n')[0]['n'])\n"
            "s.shutdown()\n"
        )
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == "7"
        assert first.execute("RETURN 1 AS one") == [{"one": 1}]  # still running: the second did not stop it
    finally:
        first.shutdown()


def test_acknowledged_writes_survive_kill_9_of_the_embedded_store(tmp_path):
    store = open_store(f"embedded:{tmp_path}")
    store.setup()
    acknowledged = 0
    for i in range(200):
        store.execute("CREATE (:W {i: $i})", {"i": i})
        acknowledged += 1
    pid = store.server.address.pid
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    store.server._process = None  # it is dead; do not try to stop it
    # The next query finds no server, starts a new one from the same directory (AOF replay).
    count = store.execute("MATCH (w:W) RETURN count(w) AS c")[0]["c"]
    store.shutdown()
    assert count == acknowledged


def test_the_embedded_store_stops_when_its_owner_is_killed(tmp_path):
    code = (
        "import time\nfrom kgadapt.knowledge.store import open_store\n"
        f"s = open_store('embedded:{tmp_path}'); s.setup()\n"
        "print(s.server.address.pid, flush=True)\ntime.sleep(60)\n"
    )
    owner = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    server_pid = int(owner.stdout.readline())
    owner.kill()
    owner.wait()
    import psutil

    try:
        psutil.Process(server_pid).wait(timeout=10)
    except psutil.NoSuchProcess:
        pass
    assert not psutil.pid_exists(server_pid) or psutil.Process(server_pid).status() == psutil.STATUS_ZOMBIE


def test_the_read_only_guard_reads_each_statement_text_once_and_still_refuses_writes():
    read_only_verdicts.cache_clear()
    text = "MATCH (p:Platform {name: $name}) RETURN p.name AS name"
    for _ in range(3):
        assert_read_only(text)
    assert (read_only_verdicts.cache_info().misses, read_only_verdicts.cache_info().hits) == (1, 2)
    write = "MATCH (p:Platform) SET p.online = false"
    for _ in range(2):  # the kept verdict is the refusal
        with pytest.raises(ReadOnlyViolation, match="SET"):
            assert_read_only(write)
    long_write = "MATCH (n) RETURN n //" + "x" * 9000 + "\nCREATE (m)"
    for _ in range(2):  # too long to keep: checked every time, never kept
        with pytest.raises(ReadOnlyViolation, match="CREATE"):
            assert_read_only(long_write)
    assert read_only_verdicts.cache_info().currsize == 2
