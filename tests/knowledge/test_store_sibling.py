"""GraphStore.sibling: another graph on the server a store reaches, and schema.Graph, which says in which of a
robot's graphs a part of its knowledge is kept (the fleet roster beside the robot's graph on FalkorDB)."""

from __future__ import annotations

import os

import pytest

from kgadapt.knowledge.falkordb_store import FalkorDBStore
from kgadapt.knowledge.fleet_roster import FleetRoster, Heard, RosterSettings, forget_robot
from kgadapt.knowledge.queries import run_named
from kgadapt.knowledge.schema import Graph
from kgadapt.knowledge.store import StoreSettings, open_store
from kgadapt.shared.errors import ConfigError, StoreUnavailable
from kgadapt.shared.proc_stat import state_of


def _store_on(server, graph: str) -> FalkorDBStore:
    sock = server.address.unix_socket
    return FalkorDBStore(StoreSettings(kind="falkordb", url=f"falkordb+unix://{sock}", unix_socket=sock, graph=graph))


def _count(store, label: str) -> int:
    return store.execute(f"MATCH (n:{label}) RETURN count(n) AS n")[0]["n"]


def test_a_sibling_is_another_graph_on_the_same_server_kept_until_its_store_shuts_down(resp_server):
    graph = f"sib{os.getpid()}"
    store = _store_on(resp_server, graph)
    with pytest.raises(StoreUnavailable, match="not set up"):
        store.sibling(f"{graph}.other")
    store.setup()
    try:
        other = store.sibling(f"{graph}.other")
        assert store.sibling(f"{graph}.other") is other and store.sibling(graph) is store
        other.execute("CREATE (:Probe {v: 1})")
        assert (_count(other, "Probe"), _count(store, "Probe")) == (1, 0)
        assert store.redis.exists(f"{graph}.other") == 1  # a key of the same server
        other.clear()
    finally:
        store.shutdown()
    with pytest.raises(StoreUnavailable):  # closed with its store
        other.execute("RETURN 1 AS one")


def test_a_sibling_of_an_embedded_store_shares_its_server_and_leaves_stopping_it_to_the_store(tmp_path):
    """The sibling reaches the same server: a server gone is started again by whichever is asked first, the
    other finds it, nothing is lost, and the store's shutdown leaves no server running."""
    store = open_store(f"embedded:{tmp_path}")
    store.setup()
    try:
        other = store.sibling("kgadapt.other")
        other.execute("CREATE (:Probe {v: 1})")
        store.execute("CREATE (:Own {v: 1})")
        first = store.server.address.pid
        store.server.kill()
        assert _count(other, "Probe") == 1  # reconnected: another server started on the same data
        second = store.server.address.pid
        assert second != first and _count(store, "Own") == 1 and store.server.address.pid == second
    finally:
        store.shutdown()
    assert not os.path.exists(f"/proc/{second}") or state_of(second) == "Z"


def test_fleet_roster_and_fleet_forget_on_the_robots_store_reach_the_roster_on_every_backend(store):
    """Where the store holds several graphs (FalkorDB over RESP) the roster is beside the robot's graph; on a
    store of one graph (Bolt: Memgraph, Neo4j, FalkorDB's Bolt listener) it is in it. Either way what the
    roster remembers is what fleet_roster lists and fleet_forget removes, given the robot's store."""
    roster = FleetRoster(store, RosterSettings(robot="me"))
    roster.open()
    beside = store.capabilities.graphs
    assert (roster.store is not store) == beside
    if not beside:
        with pytest.raises(ConfigError, match="one graph only"):
            store.sibling("kgadapt.fleet_roster")
    try:
        assert roster.remember("quad2", how=Heard.ANSWER, when=1.0, routers=["ab12"])
        rows = run_named(store, "fleet_roster")
        assert [(r["robot"], r["heard"], r["routers"]) for r in rows] == [("quad2", "answer", ["ab12"])]
        assert _count(store, "FleetRobot") == (0 if beside else 1)
        forget_robot(store, robot="quad2")
        assert run_named(store, "fleet_roster") == []
    finally:
        if beside:
            roster.store.clear()


def test_a_sibling_given_as_a_robots_store_is_refused_naming_its_graph(resp_store):
    """A robot's named queries asked of the roster's graph would be looked for where they never are."""
    roster_store = Graph.FLEET_ROSTER.store(resp_store)
    assert roster_store is not resp_store
    for name in ("fleet_roster", "platforms"):
        with pytest.raises(ConfigError, match=r"\.fleet_roster'.*give the robot's store"):
            run_named(roster_store, name)


def _robot_on(server, graph: str, *, heard: str) -> tuple[FalkorDBStore, FleetRoster]:
    store = _store_on(server, graph)
    store.setup()
    store.execute("CREATE (:Platform {name: $name})", {"name": f"{graph}-host"})
    roster = FleetRoster(store, RosterSettings(robot="me"))
    roster.open()
    roster.remember(heard, how=Heard.ANSWER, when=1.0)
    return store, roster


def test_clearing_a_robots_store_clears_its_roster_beside_it_and_no_other_robots_graphs(resp_server):
    """A robot's knowledge cleared leaves nothing of it on the server, its roster's graph included; another
    robot's graph and roster on the same server (one whose name starts like it too) and a graph that is no
    part of a robot's knowledge stay as they were. A roster's store cleared clears the roster alone."""
    base = f"clr{os.getpid()}"
    robot, robot_roster = _robot_on(resp_server, base, heard="quad2")
    other, other_roster = _robot_on(resp_server, f"{base}x", heard="quad9")
    unrelated = robot.sibling(f"{base}.notes")
    unrelated.execute("CREATE (:Note {v: 1})")
    try:
        assert robot.redis.exists(base, f"{base}.fleet_roster", f"{base}x", f"{base}x.fleet_roster") == 4
        robot.clear()
        assert robot.redis.exists(base, f"{base}.fleet_roster") == 0
        assert run_named(robot, "fleet_roster") == [] and _count(robot, "Platform") == 0
        assert [r["robot"] for r in run_named(other, "fleet_roster")] == ["quad9"]
        assert _count(other, "Platform") == 1 and _count(unrelated, "Note") == 1

        assert robot_roster.remember("quad3", how=Heard.ANNOUNCE)  # the cleared roster is written again
        robot.execute("CREATE (:Platform {name: 'again'})")
        robot_roster.store.clear()
        assert run_named(robot, "fleet_roster") == [] and _count(robot, "Platform") == 1
    finally:
        unrelated.clear()
        for store in (robot, other):
            store.clear()
            store.shutdown()


def test_clearing_a_robots_store_leaves_no_roster_on_every_backend(store):
    roster = FleetRoster(store, RosterSettings(robot="me"))
    roster.open()
    roster.remember("quad2", how=Heard.ANSWER)
    store.execute("CREATE (:Platform {name: 'onboard'})")
    store.clear()
    assert run_named(store, "fleet_roster") == []
    assert store.execute("MATCH (n) RETURN count(n) AS n")[0]["n"] == 0
