"""Export: Cypher that recreates the graph elsewhere, and dot to look at it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest
import redis

from kgadapt.knowledge import export as E
from kgadapt.knowledge import runtime as R
from kgadapt.knowledge.embedded import EmbeddedServer
from kgadapt.knowledge.falkordb_store import FalkorDBStore
from kgadapt.knowledge.fleet_roster import FleetRoster, Heard, RosterSettings
from kgadapt.knowledge.loader import load_models
from kgadapt.knowledge.queries import run_named
from kgadapt.knowledge.store import StoreSettings, open_store
from kgadapt.shared.errors import ConfigError, QueryError
from tests.conftest import REPO
from tests.support import wait_for

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


def _robots_graph(store) -> list[tuple]:
    """The signature of the robot's own knowledge, the roster left out (where it is depends on the backend)."""
    return [entry for entry in signature(store) if entry[0] != "node" or "FleetRobot" not in entry[1]]


@pytest.mark.parametrize("source, target", [("resp", "resp"), ("resp", "bolt"), ("bolt", "resp"), ("bolt", "bolt")])
def test_an_export_restores_the_robots_fleet_roster_in_a_fresh_store_of_either_backend(request, known_dir, source,
                                                                                        target):
    """What the robot's roster heard comes back from its export, wherever either store keeps the roster (FalkorDB
    over RESP: a graph beside the robot's; Bolt: in it)."""
    origin = request.getfixturevalue(f"{source}_store")
    load_models(origin, [known_dir])
    roster = FleetRoster(origin, RosterSettings(robot="me"))
    roster.open()
    roster.remember("me", how=Heard.SELF, when=1.0, zid="aa01", routers=["bb02"])
    roster.remember("quad2", how=Heard.ANSWER, when=2.0, zid="cc03", routers=["bb02", "dd04"])
    roster.remember("quad3", how=Heard.ANNOUNCE, when=3.0)
    heard, robots_graph = run_named(origin, "fleet_roster"), _robots_graph(origin)
    assert len(heard) == 3
    script = E.export(origin, "cypher")
    assert "// kgadapt graph fleet_roster: 3 nodes, 0 relations" in script

    fresh = request.getfixturevalue("empty_graph" if target == "resp" else "bolt_store")
    if fresh is origin:
        fresh.clear()
        assert run_named(fresh, "fleet_roster") == []
    E.restore(fresh, script)
    assert run_named(fresh, "fleet_roster") == heard
    assert _robots_graph(fresh) == robots_graph
    in_graph = fresh.execute("MATCH (r:FleetRobot) RETURN count(r) AS n")[0]["n"]
    assert in_graph == (0 if fresh.capabilities.graphs else 3)
    assert fresh.execute("MATCH (n:KgadaptExport) RETURN count(n) AS n")[0]["n"] == 0


OLDER_EXPORT = """// kgadapt knowledge export: 2 nodes, 0 relations.
// Run on an empty graph, one statement per line.
CREATE (:Platform:KgadaptExport {export_id: 0, name: 'onboard', memory_total_mb: 1024});
CREATE (:FleetRobot:KgadaptExport {export_id: 1, name: 'quad2', first_seen: 1.0, last_seen: 2.0, heard: 'answer', \
routers: ['ab12']});
MATCH (n:KgadaptExport) REMOVE n:KgadaptExport REMOVE n.export_id;
""".replace("\\\n", "")


def test_an_export_of_an_older_version_imports_with_its_roster_where_the_store_keeps_it(empty_graph):
    """Before the roster had a graph of its own an export had no parts, the roster in the robot's graph."""
    assert E.restore(empty_graph, OLDER_EXPORT) == 3
    assert [(r["robot"], r["heard"], r["routers"]) for r in run_named(empty_graph, "fleet_roster")] == [
        ("quad2", "answer", ["ab12"])]
    assert empty_graph.execute("MATCH (n) RETURN labels(n) AS l, n.name AS name") == [
        {"l": ["Platform"], "name": "onboard"}]


def test_an_import_refused_midway_names_the_line_and_leaves_the_store_empty(resp_store):
    script = E.to_cypher([E.Part(E.S.Graph.ROBOT, [], []),
                          E.Part(E.S.Graph.FLEET_ROSTER, [{"id": 0, "labels": ["FleetRobot"], "props": {"name": "q"}}],
                                 [])])
    broken = script + "CREATE (:Platform {name: 'x', oops: });\n"
    with pytest.raises(QueryError, match=r"^backup\.cypher:7: store rejected"):
        E.restore(resp_store, broken, source="backup.cypher")
    assert E.node_counts(resp_store) == {"robot": 0, "fleet_roster": 0}
    assert [g for g in resp_store.graph_names() if g.startswith(resp_store.settings.graph)] == []  # none staged
    with pytest.raises(ConfigError, match=r"backup\.cypher:4: unknown part 'wings'"):
        E.restore(resp_store, script.replace("graph fleet_roster", "graph wings"), source="backup.cypher")
    assert E.node_counts(resp_store) == {"robot": 0, "fleet_roster": 0}  # nothing run, not even the parts before

    E.restore(resp_store, script)
    assert [g for g in resp_store.graph_names() if g.startswith(resp_store.settings.graph)] == [
        resp_store.settings.graph, f"{resp_store.settings.graph}.fleet_roster"]
    with pytest.raises(ConfigError, match=r"is not empty \(1 nodes in its fleet_roster\)"):
        E.restore(resp_store, script)
    assert run_named(resp_store, "fleet_roster")[0]["robot"] == "q"


# --- an importer killed midway ------------------------------------------------

def _large_export(nodes: int) -> str:
    """An export of ``nodes`` platforms in a chain and a roster of three: large enough that an importer is
    caught midway."""
    robot = [{"id": i, "labels": ["Platform"], "props": {"name": f"p{i}", "memory_total_mb": 1024 + i}}
             for i in range(nodes)]
    chain = [{"source": i, "target": i + 1, "type": "NEXT", "props": {"w": i}} for i in range(nodes - 1)]
    roster = [{"id": i, "labels": ["FleetRobot"], "props": {"name": f"quad{i}", "heard": "answer"}} for i in range(3)]
    return E.to_cypher([E.Part(E.S.Graph.ROBOT, robot, chain), E.Part(E.S.Graph.FLEET_ROSTER, roster, [])])


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "KGADAPT_STORE"}
    return subprocess.run([sys.executable, "-m", "kgadapt", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=120)


def _graphs(socket: str) -> dict[str, int]:
    """Every graph on the server at ``socket`` and its node count, read through FalkorDB's own commands."""
    client = redis.Redis(unix_socket_path=socket, decode_responses=True)
    try:
        return {name: client.execute_command("GRAPH.RO_QUERY", name, "MATCH (n) RETURN count(n)")[1][0][0]
                for name in client.execute_command("GRAPH.LIST")}
    finally:
        client.close()


def _written(socket: str) -> int:
    """Nodes in the largest robot's graph on the server, staged or not (0 while the server is not up yet)."""
    try:
        graphs = _graphs(socket)
    except (redis.ConnectionError, FileNotFoundError):
        return 0
    return max((count for name, count in graphs.items() if not name.endswith(".fleet_roster")), default=0)


@pytest.mark.parametrize("server", ["kept", "dies_with_importer"])
def test_an_importer_killed_midway_leaves_the_store_as_empty_as_before_and_the_next_import_succeeds(
        tmp_path, server):
    """kill -9 of ``kgadapt knowledge import`` once it has written part of a large export: every reader finds the
    store empty (the CLI, the store API, FalkorDB's GRAPH.LIST: no robot graph, no roster graph), and the next
    import puts all of it in place and deletes what the killed one left. ``kept``: the store's server runs on
    (it was started by someone else); ``dies_with_importer``: the importer started it, so it dies too (as at a
    power loss) and the next reader starts it again from its append-only file."""
    nodes = 2000
    script = tmp_path / "large.cypher"
    script.write_text(_large_export(nodes))
    data = tmp_path / "store"
    url = f"embedded:{data}"
    owner = None
    if server == "kept":
        owner = EmbeddedServer(data)
        owner.ensure()
    try:
        env = {k: v for k, v in os.environ.items() if k != "KGADAPT_STORE"}
        importer = subprocess.Popen([sys.executable, "-m", "kgadapt", "knowledge", "import", str(script),
                                     "--store", url], cwd=REPO, env=env, stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True)
        try:
            socket = wait_for(lambda: json.loads(EmbeddedServer(data).info_path.read_text())["unix_socket"]
                              if EmbeddedServer(data).info_path.exists() else None, 30, "the store's server")
            wait_for(lambda: _written(socket) >= nodes // 4 or importer.poll() is not None, 60,
                     "a quarter of the import written")
            importer.kill()
        finally:
            importer.kill()
            out, err = importer.communicate(timeout=30)
        assert importer.returncode == -signal.SIGKILL, (out, err)  # killed midway, not finished

        if server == "kept":  # the killed import's staged graphs are there, named as such, the robot's are not
            left = _graphs(socket)
            assert "kgadapt" not in left and "kgadapt.fleet_roster" not in left
            assert left and all(E.STAGED_MARK in name for name in left)
            # ... and none of them can be opened as a robot's knowledge by naming it (before any connection).
            staging = sorted(left)[0]
            opened = _cli("knowledge", "cypher", "MATCH (n) RETURN count(n) AS n", "--store",
                          f"falkordb://127.0.0.1:1/{staging}", "--json")
            assert opened.returncode != 0 and f"graph {staging!r} is an import's staging graph" in opened.stderr, opened
        for read in (_cli("knowledge", "cypher", "MATCH (n) RETURN count(n) AS n", "--store", url, "--json"),
                     _cli("knowledge", "query", "fleet_roster", "--store", url, "--json")):
            assert read.returncode == 1 and "holds no models: nothing is loaded there" in read.stderr, read
        with open_store(url) as store:
            assert E.node_counts(store) == {"robot": 0, "fleet_roster": 0}

        again = _cli("knowledge", "import", str(script), "--store", url, "--json")
        assert again.returncode == 0, again.stderr
        assert json.loads(again.stdout)["nodes"] == {"robot": nodes, "fleet_roster": 3}
        with open_store(url) as store:
            assert E.node_counts(store) == {"robot": nodes, "fleet_roster": 3}
            assert store.execute("MATCH ()-[r:NEXT]->() RETURN count(r) AS n")[0]["n"] == nodes - 1
            assert store.execute(f"MATCH (n:{E.STAGED_LABEL}) RETURN count(n) AS n")[0]["n"] == 0
            assert sorted(store.graph_names()) == ["kgadapt", "kgadapt.fleet_roster"]  # the staged ones deleted
    finally:
        if owner is not None:
            owner.stop()


# --- putting staged graphs in place (FalkorDB over RESP) --------------------

def _stage(store: FalkorDBStore, token: str = "t1") -> dict[str, str]:
    """A staged robot graph (with an index, a relation and the mark) and roster beside ``store``'s: the moves."""
    graph = store.settings.graph
    robot, roster = E.staged_name(graph, token), E.staged_name(graph, token) + ".fleet_roster"
    for name in (robot, roster):
        store.sibling(name).execute(f"CREATE (:{E.STAGED_LABEL} {{token: $t}})", {"t": token})
    store.sibling(robot).execute("CREATE INDEX FOR (p:Platform) ON (p.name)")
    store.sibling(robot).execute("CREATE (:Platform {name: 'onboard'})-[:HOSTS]->(:Site {name: 'lab'})")
    store.sibling(roster).execute("CREATE (:FleetRobot {name: 'quad2'})")
    return {robot: graph, roster: f"{graph}.fleet_roster"}


def test_staged_graphs_renamed_into_place_answer_under_their_new_names_with_their_indexes(resp_store):
    """RENAME of a FalkorDB graph key, checked through FalkorDB's own commands: GRAPH.QUERY reaches the graph
    by its new name, its index is there and used, and the old names are gone."""
    moves = _stage(resp_store)
    resp_store.swap_in(moves, marker=E.STAGED_LABEL, check=lambda: None)
    raw = resp_store.redis
    assert raw.execute_command("GRAPH.QUERY", resp_store.settings.graph,
                               "MATCH (p:Platform)-[:HOSTS]->(s) RETURN p.name, s.name")[1] == [["onboard", "lab"]]
    indexes = resp_store.execute("CALL db.indexes() YIELD label, properties RETURN label, properties")
    assert indexes == [{"label": "Platform", "properties": ["name"]}]
    # FalkorDB builds an index in the background and the planner uses it once it is operational. Asked at
    # once, the plan was once (a loaded fresh-clone run) without the index scan; that the index was still
    # being built then is the likely cause, not shown: the plan is printed should it fail again.
    wait_for(lambda: resp_store.execute("CALL db.indexes() YIELD status RETURN status") == [{"status": "OPERATIONAL"}],
             10, "the renamed graph's index operational")
    plan = raw.execute_command("GRAPH.EXPLAIN", resp_store.settings.graph, "MATCH (p:Platform {name: 'x'}) RETURN p")
    assert any("Index Scan" in str(step) for step in plan), plan
    assert resp_store.execute(f"MATCH (n:{E.STAGED_LABEL}) RETURN count(n) AS n")[0]["n"] == 0
    assert run_named(resp_store, "fleet_roster")[0]["robot"] == "quad2"  # the roster's store selected it again
    assert not any(E.STAGED_MARK in name for name in resp_store.graph_names())


def test_a_target_written_while_staged_graphs_are_put_in_place_refuses_and_moves_nothing(resp_store):
    moves = _stage(resp_store)
    with pytest.raises(ConfigError, match="changed while the import was being put in place: nothing imported"):
        resp_store.swap_in(moves, marker=E.STAGED_LABEL,
                           check=lambda: resp_store.execute("CREATE (:Platform {name: 'meanwhile'})"))
    assert resp_store.execute("MATCH (n) RETURN n.name AS name") == [{"name": "meanwhile"}]
    assert all(name in resp_store.graph_names() for name in moves)  # nothing renamed


def test_a_staged_graph_begun_again_by_someone_else_is_not_put_in_place(resp_store):
    """Another import's clean-up deleted this one's staged graph midway and the rest of its statements made a new
    one: it lacks the mark and is refused, so the tail of an import never stands for all of it."""
    moves = _stage(resp_store)
    robot = next(iter(moves))
    resp_store.drop_graph(robot)
    resp_store.sibling(robot).execute("CREATE (:Platform {name: 'tail'})")
    with pytest.raises(ConfigError, match=f"staged graph '{robot}' was deleted"):
        resp_store.swap_in(moves, marker=E.STAGED_LABEL, check=lambda: None)
    assert E.node_counts(resp_store) == {"robot": 0, "fleet_roster": 0}


def test_an_import_deletes_the_staged_graphs_a_killed_import_left_and_no_other_graph(resp_store, resp_server):
    moves = _stage(resp_store, token="dead")
    other = FalkorDBStore(StoreSettings(kind="falkordb", url="falkordb+unix://other",
                                        unix_socket=resp_server.address.unix_socket,
                                        graph=resp_store.settings.graph + "x.import-partial.live"))
    other.setup()
    try:
        other.execute("CREATE (:Platform {name: 'another robot'})")
        E.restore(resp_store, OLDER_EXPORT)
        names = resp_store.graph_names()
        assert not any(name in names for name in moves) and other.settings.graph in names
        assert E.node_counts(resp_store) == {"robot": 1, "fleet_roster": 1}
    finally:
        other.clear()
        other.shutdown()


def test_a_bolt_server_without_transactions_is_not_given_a_script_to_run_as_one(bolt_store):
    with pytest.raises(ConfigError, match="no explicit transactions"):
        bolt_store.execute_script([("x.cypher:1", "CREATE (:Platform {name: 'a'})")])
    assert bolt_store.execute("MATCH (n) RETURN count(n) AS n")[0]["n"] == 0


def test_an_import_into_memgraph_refused_midway_leaves_nothing_and_names_the_line(memgraph_store):
    script = E.to_cypher([E.Part(E.S.Graph.ROBOT, [{"id": 0, "labels": ["Platform"], "props": {"name": "a"}}], [])])
    with pytest.raises(QueryError, match=r"^backup\.cypher:6: "):
        E.restore(memgraph_store, script + "CREATE (:Platform {name: 'x', oops: });\n", source="backup.cypher")
    assert memgraph_store.execute("MATCH (n) RETURN count(n) AS n")[0]["n"] == 0
    assert E.restore(memgraph_store, script) == 2
