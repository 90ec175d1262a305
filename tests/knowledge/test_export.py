"""Export: Cypher that recreates the graph elsewhere, and dot to look at it."""

from __future__ import annotations

import pytest

from kgadapt.knowledge import export as E
from kgadapt.knowledge import runtime as R
from kgadapt.knowledge.falkordb_store import FalkorDBStore
from kgadapt.knowledge.store import StoreSettings

from .conftest import counts, signature


@pytest.fixture
def empty_graph(resp_server):
    """A second, empty graph on the session's RESP server."""
    target = FalkorDBStore(StoreSettings(kind="falkordb", url="falkordb+unix://copy",
                                         unix_socket=resp_server.address.unix_socket, graph="export_copy"))
    target.setup()
    target.clear()
    yield target
    target.clear()
    target.shutdown()


def test_exported_cypher_recreates_the_graph_in_an_empty_store(known_store, empty_graph):
    R.update_platform(known_store, name="alpha", time=1.0, memory_free_mb=12.5, online=True)
    R.record_calibration(known_store, config="g_a", band="day", detection_rate=0.9, false_rate=0.0,
                         ms_per_frame=4.0, time=2.0)
    script = E.export(known_store, "cypher")
    nodes, edges = counts(known_store)
    assert E.import_script(empty_graph, script) == nodes + edges + 1
    assert counts(empty_graph) == (nodes, edges)
    assert signature(empty_graph) == signature(known_store)


TRICKY = ["it's", "back\\slash", 'say "hi"', "two\nlines", "tab\there", "\u2028sep", "ü€", "'}) DETACH DELETE n //"]


def test_exported_literals_are_escaped_so_tricky_strings_come_back_unchanged(resp_store):
    for i, value in enumerate(TRICKY):
        resp_store.execute("CREATE (:Probe:`odd label` {i: $i, v: $v, `odd key`: [$v, 1.5, true]})", {"i": i, "v": value})
    resp_store.execute("MATCH (a:Probe {i: 0}), (b:Probe {i: 1}) CREATE (a)-[:`ODD TYPE` {w: $w}]->(b)",
                       {"w": TRICKY[-1]})
    script = E.export(resp_store, "cypher")
    resp_store.clear()
    E.import_script(resp_store, script)
    rows = resp_store.execute("MATCH (p:Probe:`odd label`) RETURN p.i AS i, p.v AS v, p.`odd key` AS k ORDER BY i")
    assert [r["v"] for r in rows] == TRICKY
    assert all(r["k"] == [r["v"], 1.5, True] for r in rows)
    assert resp_store.execute("MATCH ()-[r:`ODD TYPE`]->() RETURN r.w AS w") == [{"w": TRICKY[-1]}]
    assert resp_store.execute("MATCH (n:KgadaptExport) RETURN count(n) AS c")[0]["c"] == 0


def test_literal_formats_each_value_type():
    assert [E.literal(v) for v in (None, True, 3, 2.0, 1e20, "a'b\\c", [1, "x"])] == [
        "null", "true", "3", "2.0", "1e20", "'a\\'b\\\\c'", "[1, 'x']"]
    assert E.name("Platform") == "Platform" and E.name("odd `name`") == "`odd ``name```"


def test_large_and_small_floats_are_written_without_a_plus_in_the_exponent(resp_store):
    # openCypher's grammar (and Memgraph's lexer) has no '+' in an exponent.
    # (FalkorDB's parser keeps 15 significant digits of a float literal, so
    # 1.2345678901234568e17 would come back as 1.23456789012346e17: not tested here.)
    values = [1e16, 1e300, -2.5e20, 1e-7, 1.5e17]
    assert all("+" not in E.literal(v) for v in values)
    resp_store.execute("CREATE (:Probe {v: $v})", {"v": values})
    script = E.export(resp_store, "cypher")
    resp_store.clear()
    E.import_script(resp_store, script)
    assert resp_store.execute("MATCH (p:Probe) RETURN p.v AS v") == [{"v": values}]


def test_dot_export_draws_every_node_and_relation(known_store):
    text = E.export(known_store, "dot")
    nodes, edges = counts(known_store)
    assert text.startswith("digraph kgadapt {") and text.rstrip().endswith("}")
    assert text.count("fillcolor=") == nodes
    assert text.count(" -> ") == edges
    assert '[label="PerceptionGraph\\ng_a"' in text
    assert '[label="EXECUTABLE_ON"]' in text
