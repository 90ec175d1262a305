"""One contract for every backend: dialects, values, errors, timeouts and TLS.

The Bolt server that runs here is FalkorDB's Bolt listener; the Bolt
backend is driven through the Neo4j Python driver exactly as it drives
Memgraph (``memgraph://`` takes the same code path, with the Memgraph
dialect). TLS is checked with a real TLS terminator in front of that
listener, so the driver's certificate checks run for real.
"""

from __future__ import annotations

import socket
import ssl
import threading
from pathlib import Path

import pytest
from neo4j import exceptions as neo4j_errors

from kgadapt.knowledge import queries as Q
from kgadapt.knowledge import runtime as R
from kgadapt.knowledge.bolt_store import BoltStore
from kgadapt.knowledge.dialect import FALKORDB, MEMGRAPH, NEO4J, NEO4J_3, dialect_for_agent
from kgadapt.knowledge.embedded import EmbeddedServer
from kgadapt.knowledge.fleet_roster import FleetRoster, Heard, RosterSettings
from kgadapt.knowledge.loader import load_models
from kgadapt.knowledge.schema import INDEXED_NAMES, ensure_indexes
from kgadapt.knowledge.store import open_store, parse_store_url
from kgadapt.shared.errors import ConfigError, QueryError, StoreUnavailable
from tests.conftest import free_port
from tests.deploy.pki import TestCA
from tests.knowledge.bolt_double import MEMGRAPH_AGENT, NEO4J_AGENT, BoltDouble
from tests.support import wait_for

SHIPPED = Path(__file__).resolve().parents[2] / "knowledge" / "models"


# --- dialects ----------------------------------------------------------------------

def test_each_dialect_spells_index_creation_in_its_stores_own_form():
    assert MEMGRAPH.create_index("Platform", "name") == "CREATE INDEX ON :Platform(name)"
    assert FALKORDB.create_index("Platform", "name") == "CREATE INDEX FOR (n:Platform) ON (n.name)"
    assert NEO4J.create_index("Platform", "name") == "CREATE INDEX IF NOT EXISTS FOR (n:Platform) ON (n.name)"
    assert MEMGRAPH.list_statement == "SHOW INDEX INFO"
    for dialect in (MEMGRAPH, FALKORDB, NEO4J):
        with pytest.raises(ValueError, match="Platform\\)"):
            dialect.create_index("Platform)", "name")
        assert "CALL db.indexes" not in dialect.list_statement or dialect is FALKORDB


def test_each_dialect_reads_its_stores_index_listing():
    memgraph_2 = [{"index type": "label+property", "label": "Platform", "property": "name", "count": 3},
                  {"index type": "label", "label": "Feature", "property": None, "count": 1}]
    memgraph_3 = [{"index type": "label+property", "label": "Platform", "property": ["name"], "count": 3},
                  {"index type": "label+property", "label": "Port", "property": ["name", "key"], "count": 0}]
    neo4j = [{"label": ["Platform"], "properties": ["name"]}, {"label": None, "properties": None}]
    falkordb = [{"label": "Platform", "properties": ["name"]}]
    assert MEMGRAPH.indexed(memgraph_2) == {("Platform", "name")}
    assert MEMGRAPH.indexed(memgraph_3) == {("Platform", "name")}
    assert NEO4J.indexed(neo4j) == {("Platform", "name")}
    assert FALKORDB.indexed(falkordb) == {("Platform", "name")}


def test_indexes_are_created_once_in_the_backends_dialect(store):
    store.execute("CREATE (:Probe {name: 'x'})")
    ensure_indexes(store)
    ensure_indexes(store)  # idempotent: nothing raised, nothing doubled
    listed = store.dialect.indexed(store.execute(store.dialect.list_statement))
    assert {(label, "name") for label in INDEXED_NAMES} <= listed


def test_the_bolt_backend_finds_falkordbs_listener_by_its_behaviour(bolt_store):
    # It claims to be Neo4j; it pastes parameters into the text and ignores tx_timeout.
    assert bolt_store.dialect is FALKORDB
    assert bolt_store.capabilities.timeouts is False
    assert bolt_store.capabilities.transactions is False


# --- the same answers from every backend ----------------------------------------------

EXAMPLES = {
    "feature_deployments": {"platform": "remote"},
    "placement": {},
    "deployable_components": {},
    "camera_resolutions": {},
    "low_memory_components": {"threshold_mb": 500.0},
    "cpu_overload": {"platform": "onboard"},
    "detector_configs": {},
    "config_ranking": {"band": "day"},
    "config_robustness": {"band": "dark"},
    "live_rates": {"band": "dark"},
    "reflex_table": {"deployment": "detector_day", "host": "onboard"},
    "detector_config": {"config": "marker_detection_dark"},
    "in_place_change": {"from": "detector_day", "to": "detector_dark", "host": "onboard"},
    "deployment": {"name": "marker_detection_dark_onboard"},
    "platforms": {},
    "process_profile": {"run_id": "r1"},
    "camera_intrinsics": {"camera": "camera"},
    "site_markers": {"site": "demo-hall"},
    "flight_control": {},
    "decisions": {"limit": 5},
    "current_placement": {},
    "fleet_roster": {},
    "fig4_literal": {"platform": "remote"},
    "fig5_literal": {},
}


def _robot_state(store) -> None:
    """The shipped models plus what a running robot writes."""
    load_models(store, [SHIPPED])
    for host, free in (("onboard", 480.0), ("remote", 3000.0)):
        R.update_platform(store, name=host, time=100.0, memory_free_mb=free, cpu_load=12.5)
        R.set_platform_online(store, name=host, online=True, time=100.0)
    FleetRoster(store, RosterSettings(robot="quad1")).remember("quad2", how=Heard.ANSWER, when=2.0, routers=["ab12"])
    R.record_calibration(store, config="marker_detection_dark", band="dark", detection_rate=0.9,
                         false_rate=0.01, ms_per_frame=7.5, time=50.0)
    R.record_live_rate(store, config="marker_detection_dark", band="dark", detection_rate=0.75, frames=90,
                       frames_expected=60, frames_seen=50, since=95.0, time=100.0, run_id="r1", host="onboard")
    R.record_process_start(store, run_id="r1", instance="i1", deployment="marker_detection_dark_onboard",
                           config="marker_detection_dark", host="onboard", pid=42, start_time=101.0)
    R.record_process_sample(store, run_id="r1", rss_mb_last=120.0, rss_mb_mean=110.0, rss_mb_max=130.0,
                            cpu_percent_mean=30.0)
    R.record_decision(store, name="d1", time=100.5, trigger="startup", config="marker_detection_dark",
                      host="onboard", outcome="started")


def _canonical(rows):
    return sorted(repr(sorted(row.items())) for row in rows)


def test_every_named_query_gives_the_same_rows_on_every_backend_here(resp_store, bolt_store):
    assert set(EXAMPLES) == set(Q.QUERIES), "give every named query an example here"
    _robot_state(resp_store)
    _robot_state(bolt_store)
    non_empty = 0
    for name, params in EXAMPLES.items():
        resp_rows = Q.run_named(resp_store, name, params)
        bolt_rows = Q.run_named(bolt_store, name, params)
        assert _canonical(resp_rows) == _canonical(bolt_rows), name
        non_empty += bool(resp_rows)
    assert non_empty >= len(EXAMPLES) - 2  # the comparison is over real answers, not empty lists


def test_nodes_relationships_and_paths_nested_anywhere_come_back_as_the_same_plain_values(resp_store, bolt_store):
    query = ("MATCH p = (a:A)-[r:R]->(b:B) "
             "RETURN a, r, p, collect(b) AS bs, {rel: r, nodes: [a, b], deep: [[{n: b}]]} AS m")
    answers = []
    for store in (resp_store, bolt_store):
        store.execute("CREATE (:A:Extra {x: 1})-[:R {w: 2.5}]->(:B {y: 'three'})")
        answers.append(store.execute(query, read_only=True))
    assert answers[0] == answers[1]
    row, = answers[1]
    assert row["a"] == {"x": 1, "_labels": ["A", "Extra"]}
    assert row["r"] == {"w": 2.5, "_type": "R"}
    assert row["p"] == [{"x": 1, "_labels": ["A", "Extra"]}, {"y": "three", "_labels": ["B"]}]
    assert row["m"]["deep"] == [[{"n": {"y": "three", "_labels": ["B"]}}]]


# --- errors ------------------------------------------------------------------------

@pytest.fixture
def own_bolt_server(tmp_path):
    server = EmbeddedServer(tmp_path / "bolt", bolt_port=free_port(), append_only=False)
    server.ensure()
    yield server
    server.stop()


def test_a_refused_query_is_a_query_error_and_the_store_keeps_working(bolt_store):
    with pytest.raises(QueryError, match="store rejected the query"):
        bolt_store.execute("RETURN nosuchfunction(1) AS x")
    assert bolt_store.execute("RETURN 2 AS two") == [{"two": 2}]


def test_a_lost_server_is_store_unavailable_and_a_later_call_reconnects(tmp_path):
    port = free_port()
    server = EmbeddedServer(tmp_path / "bolt", bolt_port=port, append_only=False)
    server.ensure()
    store = open_store(f"bolt://127.0.0.1:{port}")
    try:
        store.setup(timeout=15)
        assert store.execute("RETURN 1 AS one") == [{"one": 1}]
        server.stop()
        with pytest.raises(StoreUnavailable, match="lost Bolt server"):
            store.execute("RETURN 1 AS one")
        server = EmbeddedServer(tmp_path / "bolt", bolt_port=port, append_only=False)
        server.ensure()

        def answers() -> bool:
            try:
                return store.execute("RETURN 1 AS one") == [{"one": 1}]
            except StoreUnavailable:
                return False  # FalkorDB's listener may drop the first handshake after a restart

        wait_for(answers, timeout=30, what="the Bolt store to reconnect")
    finally:
        store.shutdown()
        server.stop()


def test_shutdown_after_the_server_died_returns_at_once(tmp_path):
    port = free_port()
    server = EmbeddedServer(tmp_path / "bolt", bolt_port=port, append_only=False)
    server.ensure()
    store = open_store(f"bolt://127.0.0.1:{port}")
    store.setup(timeout=15)
    server.stop()
    done = threading.Event()
    threading.Thread(target=lambda: (store.shutdown(), done.set()), daemon=True).start()
    # Closing never opens a new connection; 5 s is far above what closing a socket takes.
    assert done.wait(5.0), "shutdown() blocked on a dead server"


def test_an_unreachable_server_is_store_unavailable_naming_the_url():
    store = open_store(f"memgraph://127.0.0.1:{free_port()}")
    with pytest.raises(StoreUnavailable, match=r"cannot reach Bolt server at memgraph://127\.0\.0\.1"):
        store.setup(timeout=1.0)


def test_a_transient_conflict_is_retried_a_bounded_number_of_times(bolt_store, monkeypatch):
    monkeypatch.setattr("kgadapt.knowledge.bolt_store.TRANSIENT_RETRY_PAUSES", (0.0, 0.0))
    calls = []

    def conflicting(fail_times):
        def work():
            calls.append(1)
            if len(calls) <= fail_times:
                raise neo4j_errors.TransientError("Cannot resolve conflicting transactions.")
            return "done"
        return work

    assert bolt_store._with_errors(conflicting(2), None) == "done" and len(calls) == 3
    calls.clear()
    with pytest.raises(QueryError, match="conflict after 2 retries"):
        bolt_store._with_errors(conflicting(5), None)
    assert len(calls) == 3


# --- TLS ---------------------------------------------------------------------------

class TlsTerminator:
    """A TLS listener that forwards each connection to a plain TCP port (as Memgraph's --bolt-cert-file does)."""

    def __init__(self, cert: Path, key: Path, target_port: int) -> None:
        self.context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        self.context.load_cert_chain(cert, key)
        self.target_port = target_port
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.sockets: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                raw, _ = self.listener.accept()
            except OSError:
                return
            try:
                tls = self.context.wrap_socket(raw, server_side=True)
            except (ssl.SSLError, OSError):
                raw.close()  # a client that refused our certificate
                continue
            upstream = socket.create_connection(("127.0.0.1", self.target_port))
            self.sockets += [tls, upstream]
            for a, b in ((tls, upstream), (upstream, tls)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(source: socket.socket, sink: socket.socket) -> None:
        try:
            while data := source.recv(65536):
                sink.sendall(data)
        except OSError:
            pass
        finally:
            for s in (source, sink):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def close(self) -> None:
        self.listener.close()
        for s in self.sockets:
            s.close()


@pytest.fixture
def tls_bolt(tmp_path, own_bolt_server):
    ca = TestCA(tmp_path / "pki")
    cert, key = ca.issue("store")
    terminator = TlsTerminator(cert, key, own_bolt_server.bolt_port)
    yield ca, terminator
    terminator.close()


@pytest.mark.parametrize("scheme", ["bolt+s", "memgraph+s"])
def test_tls_with_our_own_ca_connects_and_answers(tls_bolt, scheme):
    ca, terminator = tls_bolt
    store = open_store(f"{scheme}://localhost:{terminator.port}?ca={ca.path}")
    store.setup(timeout=15)
    try:
        assert store.capabilities.tls
        assert store.execute("RETURN $v AS v", {"v": 7}) == [{"v": 7}]
    finally:
        store.shutdown()


def test_tls_refuses_a_server_whose_certificate_our_ca_did_not_sign(tls_bolt, tmp_path):
    _, terminator = tls_bolt
    stranger = TestCA(tmp_path / "other", name="someone else's CA")
    store = open_store(f"bolt+s://localhost:{terminator.port}?ca={stranger.path}")
    with pytest.raises(StoreUnavailable, match="cannot reach Bolt server"):
        store.setup(timeout=1.5)


def test_ssc_accepts_a_self_signed_certificate_and_plain_bolt_cannot_talk_to_tls(tls_bolt):
    _, terminator = tls_bolt
    store = open_store(f"bolt+ssc://localhost:{terminator.port}")
    store.setup(timeout=15)
    try:
        assert store.execute("RETURN 1 AS one") == [{"one": 1}]
    finally:
        store.shutdown()
    with pytest.raises(StoreUnavailable):
        open_store(f"bolt://localhost:{terminator.port}").setup(timeout=1.5)


def test_store_urls_with_tls_are_parsed_and_bad_ones_named(tmp_path):
    ca = tmp_path / "ca.pem"
    ca.write_text("x")
    s = parse_store_url(f"memgraph+s://h:7688?ca={ca}")
    assert (s.kind, s.tls, s.ca_file, s.port) == ("memgraph", "verify", str(ca), 7688)
    assert parse_store_url("bolt+ssc://h").tls == "self-signed"
    assert parse_store_url("bolt://h").tls == ""
    for bad, named in (("falkordb+s://h", "falkordb\\+s"), ("memgraph+x://h", "memgraph\\+x"),
                       ("bolt://h?ca=/x", "needs a \\+s"), (f"bolt+s://h?ca={tmp_path}/none.pem", "none.pem"),
                       ("bolt+s://h?cert=1", "cert")):
        with pytest.raises(ConfigError, match=named):
            parse_store_url(bad)


def test_the_environments_ca_serves_verifying_urls_and_leaves_the_others_alone(tmp_path, monkeypatch):
    # $KGADAPT_STORE_CA in a unit's environment file must not turn every other store URL into an error.
    ca = tmp_path / "ca.pem"
    ca.write_text("x")
    monkeypatch.setenv("KGADAPT_STORE_CA", str(ca))
    assert parse_store_url("memgraph+s://h").ca_file == str(ca)
    for url, tls in (("memgraph+ssc://h", "self-signed"), ("memgraph://h", ""), ("bolt://h", ""),
                     ("falkordb://h", "")):
        settings = parse_store_url(url)
        assert (settings.tls, settings.ca_file) == (tls, None), url
    with pytest.raises(ConfigError, match="needs a \\+s"):
        parse_store_url(f"bolt://h?ca={ca}")  # asked for in the URL itself: still refused


def test_the_bolt_backend_is_the_driver_for_both_schemes():
    assert isinstance(open_store("memgraph://h:7687"), BoltStore)
    assert isinstance(open_store("bolt://h:7687"), BoltStore)


# --- the dialect from what the server announces, not from the URL ------------------

def test_the_dialect_follows_the_announced_agent_and_version():
    assert dialect_for_agent(MEMGRAPH_AGENT) is MEMGRAPH
    assert dialect_for_agent("Neo4j/v4.4.0 compatible graph database server - memgraph") is MEMGRAPH
    assert dialect_for_agent(NEO4J_AGENT) is NEO4J
    assert dialect_for_agent("Neo4j/4.4.12") is NEO4J
    assert dialect_for_agent("Neo4j/3.5.35") is NEO4J_3
    assert NEO4J_3.create_index("Platform", "name") == "CREATE INDEX ON :Platform(name)"
    assert dialect_for_agent(None) is NEO4J


@pytest.fixture(params=[MEMGRAPH_AGENT, NEO4J_AGENT], ids=["memgraph", "neo4j"])
def announcing_server(request):
    server = BoltDouble(request.param)
    server.setup()
    yield server
    server.shutdown()


@pytest.mark.parametrize("scheme", ["bolt", "memgraph"])
def test_a_bolt_servers_dialect_comes_from_its_announced_agent_whatever_the_scheme(announcing_server, scheme):
    store = open_store(f"{scheme}://127.0.0.1:{announcing_server.port}")
    store.setup(timeout=10)
    try:
        expected = MEMGRAPH if announcing_server.memgraph else NEO4J
        assert store.server_agent == announcing_server.agent
        assert store.dialect is expected
        ensure_indexes(store)  # the server refuses the other dialect's statements, as the real one does
        assert announcing_server.indexes == {(label, "name") for label in INDEXED_NAMES}
        ensure_indexes(store)  # listed in the server's own form: nothing created twice
        creates = [s for s in announcing_server.statements if s.startswith("CREATE INDEX")]
        assert len(creates) == len(INDEXED_NAMES)
        assert all(s == expected.create_index(label, "name") for s, label in zip(creates, INDEXED_NAMES))
    finally:
        store.shutdown()


def test_memgraph_over_tls_with_a_bolt_scheme_gets_the_memgraph_dialect(tmp_path):
    server = BoltDouble(MEMGRAPH_AGENT)
    server.setup()
    ca = TestCA(tmp_path / "pki")
    cert, key = ca.issue("store")
    terminator = TlsTerminator(cert, key, server.port)
    store = open_store(f"bolt+ssc://localhost:{terminator.port}")
    try:
        store.setup(timeout=10)
        assert store.dialect is MEMGRAPH
        ensure_indexes(store)
        assert ("Platform", "name") in server.indexes
    finally:
        store.shutdown()
        terminator.close()
        server.shutdown()


def test_a_store_that_cannot_stop_a_query_gets_no_free_cypher_from_other_robots(bolt_store, resp_store):
    """FalkorDB's Bolt listener ignores tx_timeout: the service refuses rather than pretends."""
    from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
    from kgadapt.shared import messages

    request = messages.encode("cypher_request", {"cypher": "MATCH (n) RETURN count(n) AS c", "params": {}})
    bolt_service = KnowledgeService(bolt_store, ServiceSettings(robot="quad1", lock=False))
    with pytest.raises(QueryError, match="cannot stop a query at a time limit"):
        bolt_service.answer_cypher(request)
    with pytest.raises(QueryError, match="cannot stop a query at a time limit"):
        bolt_service.answer_named("fig5_literal", None, public=True)
    # Its own named queries still run there, and a store that honours timeouts answers free Cypher.
    assert messages.decode(bolt_service.answer_named("platforms", None), "rows")["rows"] == []
    resp_store.execute("CREATE (:Probe)")
    resp_service = KnowledgeService(resp_store, ServiceSettings(robot="quad1", lock=False, sandbox=False))
    assert messages.decode(resp_service.answer_cypher(request), "rows")["rows"] == [{"c": 1}]
