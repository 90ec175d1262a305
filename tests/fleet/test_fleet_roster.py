"""The fleet roster: every knowledge service remembers the robots it heard on the fleet keys, so a robot that is
gone is listed as silent by a fleet question that names no robot, until an operator forgets it."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import subprocess
import sys
import time
from typing import Iterator

import pytest

from kgadapt.knowledge.fleet_roster import FleetRoster, Heard, RosterSettings, forget_robot
from kgadapt.knowledge.queries import run_named
from kgadapt.knowledge.runtime import run_write
from kgadapt.shared import messages
from kgadapt.shared.errors import MessageError, NamedQueryError
from kgadapt.shared.session import ZenohSettings, open_session
from tests.conftest import REPO, free_port
from tests.support import Child, wait_for


def kgadapt(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "kgadapt", *args], capture_output=True, text=True, timeout=timeout,
                          cwd=REPO)


def roster_of(store) -> dict[str, dict]:
    return {row["robot"]: row for row in run_named(store, "fleet_roster")}


def test_a_killed_robot_is_listed_as_silent_by_a_new_fleet_question_without_expect(tmp_path):
    prefix = f"r{os.getpid()}"
    robots = [f"{prefix}a", f"{prefix}b", f"{prefix}c"]
    endpoints = [f"tcp/127.0.0.1:{free_port()}" for _ in robots]
    children = []
    try:
        for i, robot in enumerate(robots):  # three robots' services, b and c linked to a's router
            args = ["knowledge", "serve", "--robot", robot, "--store", f"embedded:{tmp_path / robot}",
                    "--listen", endpoints[i]] + (["--connect", endpoints[0]] if i else [])
            children.append(Child.kgadapt(f"serve-{robot}", args, tmp_path))
        for child in children:
            child.wait_ready(60)
        a, b, c = robots
        session = open_session(ZenohSettings(mode="client", connect=(endpoints[0],)))
        try:
            from kgadapt.knowledge.client import KnowledgeClient

            client = KnowledgeClient(session, a, timeout=2.0)

            def a_remembers_all() -> bool:
                rows = {row["robot"]: row for row in client.query("fleet_roster")}
                return set(robots) <= set(rows) and rows
            roster = wait_for(a_remembers_all, 30, f"{a}'s roster to list {robots}")
        finally:
            session.close()
        assert roster[a]["heard"] == Heard.SELF.value and roster[a]["first_seen"] <= roster[a]["last_seen"]
        assert {roster[b]["heard"], roster[c]["heard"]} <= {Heard.ANSWER.value, Heard.ANNOUNCE.value}
        assert roster[c]["zid"]  # the robot's own Zenoh id, as it told it

        children[2].kill9()  # kill -9 of c's knowledge service
        done = kgadapt("ask", "--fleet", "platforms", "--robot", a, "--connect", endpoints[0], "--timeout", "2",
                       "--json")
        assert done.returncode == 3, done.stderr  # exit 3: some robot silent
        answer = json.loads(done.stdout)
        assert answer["silent"] == [c]
        assert set(answer["answered"]) >= {a, b}

        done = kgadapt("fleet", "--robot", a, "--connect", endpoints[0], "forget", c)
        assert done.returncode == 0, done.stderr
        done = kgadapt("ask", "--fleet", "platforms", "--robot", a, "--connect", endpoints[0], "--timeout", "2",
                       "--json")
        assert json.loads(done.stdout)["silent"] == [] and done.returncode == 0, done.stdout + done.stderr
    finally:
        for child in children:
            if child.process.poll() is None:
                child.stop()


def test_the_roster_is_bounded_and_forgets_on_request(resp_store, caplog):
    roster = FleetRoster(resp_store, RosterSettings(robot="me", cap=3))
    for robot in ("me", "r1", "r2"):
        assert roster.remember(robot, how=Heard.ANSWER, when=100.0, routers=["ab12"])
    with caplog.at_level(logging.WARNING, logger="kgadapt.knowledge.fleet_roster"):
        for k in range(5):  # full: a new robot is not recorded; a flood of them logs the 1st, 2nd and 4th
            assert not roster.remember(f"new{k}", how=Heard.ANNOUNCE, when=101.0)
    assert roster.refused == 5
    logged = [r.getMessage() for r in caplog.records if "fleet roster full" in r.getMessage()]
    assert len(logged) == 3 and "new0 not recorded" in logged[0] and "(4 turned away so far" in logged[2]
    assert roster.remember("r1", how=Heard.ANNOUNCE, when=200.0)  # a known one still is
    rows = roster_of(resp_store)
    assert set(rows) == {"me", "r1", "r2"}
    assert (rows["r1"]["first_seen"], rows["r1"]["last_seen"], rows["r1"]["heard"], rows["r1"]["routers"]) == (
        100.0, 200.0, "announce", ["ab12"])
    run_write(resp_store, "fleet_forget", {"robot": "r2"})
    assert set(roster_of(resp_store)) == {"me", "r1"}
    assert roster.remember("r3", how=Heard.ANNOUNCE)  # room again
    forget_robot(resp_store, robot="me'}) DETACH DELETE r //")  # a value, never code: removes nothing
    assert set(roster_of(resp_store)) == {"me", "r1", "r3"}
    with pytest.raises(NamedQueryError, match="'robot'"):
        forget_robot(resp_store, robot=7)


def test_a_roll_call_with_a_bad_announcement_is_refused_naming_it(resp_store):
    roster = FleetRoster(resp_store, RosterSettings(robot="me"))
    with pytest.raises(MessageError, match="router id"):
        roster.heard({"announce": "r1", "routers": "not-hex"})
    with pytest.raises(Exception, match="robot"):
        roster.heard({"announce": "r1/**"})
    assert roster_of(resp_store) == {}


def _dumps(store) -> int:
    """DUMP calls the store's server has served: each is a query sandbox copying a robot's graph."""
    return int(store.redis.info("commandstats").get("cmdstat_dump", {}).get("calls", 0))


def test_roll_calls_between_fleet_questions_copy_no_robots_graph_into_its_sandboxes(fleet):
    """Every roll call writes every robot's roster. Kept beside the robot's graph, not in it, none of that makes
    a sandbox copy the robot's graph again: idle robots answer the fleet's questions from the copies they have."""
    from kgadapt.knowledge.fleet import FleetClient, FleetSettings

    robots = sorted(fleet.robots)
    client = FleetClient(fleet.client("b"), FleetSettings(timeout=10.0, expect=tuple(robots), discover_hosts=False))
    for _ in range(4):  # each robot's public workers (two) have answered, so every sandbox holds a copy
        assert client.ask("current_placement").complete
    caller = fleet.services[robots[0]]
    store = fleet.stores[robots[0]]
    before = _dumps(store)
    for _ in range(5):
        when = time.time()
        assert set(caller.roster.roll_call()) == set(robots[1:])  # the others answered (and were remembered)
        answer = client.ask("current_placement")
        assert answer.complete and all(a.rows for a in answer.robots)
        for robot in robots[1:]:  # each heard the announcement and wrote its roster meanwhile
            rows = roster_of(fleet.stores[robot])
            assert rows[robots[0]]["last_seen"] >= when
    assert _dumps(store) - before == 0
    for robot in robots:  # and the robots' own graphs hold no roster
        assert fleet.stores[robot].execute("MATCH (r:FleetRobot) RETURN count(r) AS n")[0]["n"] == 0


def test_a_roster_kept_in_the_robots_graph_is_moved_beside_it(resp_store):
    """A roster an older version kept in the robot's graph is moved into the roster's own graph at open()."""
    resp_store.execute("CREATE (:FleetRobot {name: 'old', first_seen: 1.0, last_seen: 2.0, heard: 'answer', "
                       "routers: ['ab12']})")
    roster = FleetRoster(resp_store, RosterSettings(robot="me"))
    roster.open()
    try:
        assert roster.store is resp_store.sibling(f"{resp_store.settings.graph}.fleet_roster")
        assert roster.remember("me", how=Heard.SELF, when=3.0)
        rows = roster_of(resp_store)  # the named query, given the robot's store, reads the roster's graph
        assert set(rows) == {"old", "me"}
        assert (rows["old"]["first_seen"], rows["old"]["last_seen"], rows["old"]["routers"]) == (1.0, 2.0, ["ab12"])
        assert resp_store.execute("MATCH (r:FleetRobot) RETURN count(r) AS n")[0]["n"] == 0
    finally:
        roster.store.clear()
        roster.shutdown()


def test_fleet_roster_and_fleet_forget_run_on_the_robots_store_reach_the_roster_its_service_keeps(fleet):
    """The store API's named query and write verb, given a robot's store, reach the roster its knowledge service
    keeps beside the robot's graph: the robots the service heard, and a robot forgotten there is gone from
    the service's answers."""
    robots = sorted(fleet.robots)
    robot = robots[0]
    service, store = fleet.services[robot], fleet.stores[robot]
    # Its own robot at setup, the others from the roll calls at their setups (up to 1 s late each).
    wait_for(lambda: set(roster_of(store)) == set(robots), 15, f"{robot}'s roster, read on its store, to list {robots}")
    assert service.roster.remember("ghost", how=Heard.ANNOUNCE)

    def served() -> set[str]:
        return {row["robot"] for row in messages.decode(service.answer_named("fleet_roster", None, public=True),
                                                         "rows")["rows"]}

    assert "ghost" in served() and "ghost" in roster_of(store)
    run_write(store, "fleet_forget", {"robot": "ghost"})
    assert "ghost" not in served() and "ghost" not in roster_of(store)
    assert store.execute("MATCH (r:FleetRobot) RETURN count(r) AS n")[0]["n"] == 0  # nothing in the robot's graph


def test_a_service_that_keeps_no_roster_refuses_fleet_roster_naming_why(resp_store):
    """Its roster's graph is not kept up to date: an error saying so, never a list that looks like an answer."""
    from kgadapt.knowledge.service import KnowledgeService, ServiceSettings

    service = KnowledgeService(resp_store, ServiceSettings(robot="me", roster=False, lock=False, sandbox=False))
    for public in (False, True):
        with pytest.raises(NamedQueryError, match="keeps no fleet roster"):
            service.answer_named("fleet_roster", None, public=public)


@contextlib.contextmanager
def served_robot_that_heard_a_visitor(tmp_path, robot: str) -> Iterator[tuple[str, str]]:
    """``kgadapt knowledge serve`` of ``robot`` on a new embedded store with the shipped models, after a roll call
    of robot ``visitor`` reached it (so its roster remembers it): (store URL, endpoint); stopped after."""
    from kgadapt.knowledge.client import KnowledgeClient

    endpoint, store = f"tcp/127.0.0.1:{free_port()}", f"embedded:{tmp_path / 'store'}"
    done = kgadapt("knowledge", "load", str(REPO / "knowledge" / "models"), "--store", store)
    assert done.returncode == 0, done.stderr
    child = Child.kgadapt("serve", ["knowledge", "serve", "--robot", robot, "--store", store, "--listen", endpoint],
                          tmp_path)
    try:
        child.wait_ready(60)
        session = open_session(ZenohSettings(mode="client", connect=(endpoint,)))
        try:  # a roll call of another robot: the service remembers it
            KnowledgeClient(session, robot, timeout=5.0).query("fleet_roster", {"announce": "visitor"}, wait_s=10.0)
        finally:
            session.close()
        yield store, endpoint
    finally:
        if child.process.poll() is None:
            child.stop()


def listed(store: str) -> list[dict]:
    """``kgadapt knowledge query fleet_roster --store STORE --json``: the roster's rows."""
    done = kgadapt("knowledge", "query", "fleet_roster", "--store", store, "--json")
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_kgadapt_knowledge_query_on_a_served_store_lists_the_robots_its_service_heard(tmp_path):
    """``kgadapt knowledge query fleet_roster --store`` beside a running ``kgadapt knowledge serve``: the robots
    the service heard (itself, and a robot that announced itself in a roll call), and after ``kgadapt fleet
    forget`` not that one. Free Cypher about FleetRobot nodes, which reads the robot's graph, says where they are."""
    robot = f"k{os.getpid()}"
    with served_robot_that_heard_a_visitor(tmp_path, robot) as (store, endpoint):
        assert {row["robot"] for row in listed(store)} == {robot, "visitor"}
        done = kgadapt("fleet", "--robot", robot, "--connect", endpoint, "forget", "visitor")
        assert done.returncode == 0, done.stderr
        assert {row["robot"] for row in listed(store)} == {robot}
        for asked in (["knowledge", "cypher", "--store", store], ["ask", "--robot", robot, "--connect", endpoint,
                                                                  "--cypher"]):
            done = kgadapt(*asked, "MATCH (r:FleetRobot) RETURN r.name AS name")
            assert done.returncode == 0 and "ask the named query fleet_roster" in done.stdout, done.stdout + done.stderr


def test_a_served_robot_exported_and_imported_into_a_fresh_store_keeps_the_robots_its_service_heard(tmp_path):
    """``kgadapt knowledge export --format cypher`` of a robot whose ``kgadapt knowledge serve`` heard another
    robot, then ``kgadapt knowledge import`` into a new embedded store: ``fleet_roster`` there lists both (the
    roster is kept beside the robot's graph on FalkorDB, and an export once held the robot's graph alone)."""
    robot = f"x{os.getpid()}"
    with served_robot_that_heard_a_visitor(tmp_path, robot) as (store, _):
        pass
    heard = listed(store)
    assert {row["robot"] for row in heard} == {robot, "visitor"}
    backup, fresh = tmp_path / "robot.cypher", f"embedded:{tmp_path / 'fresh'}"
    done = kgadapt("knowledge", "export", "--format", "cypher", "-o", str(backup), "--store", store)
    assert done.returncode == 0, done.stderr
    done = kgadapt("knowledge", "import", str(backup), "--store", fresh, "--json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["nodes"]["fleet_roster"] == 2
    assert listed(fresh) == heard
    for asked in ("platforms", "detector_configs"):  # the robot's own graph came along too
        rows = [kgadapt("knowledge", "query", asked, "--store", where, "--json").stdout for where in (store, fresh)]
        assert rows[0] == rows[1] and json.loads(rows[0])
    done = kgadapt("knowledge", "import", str(backup), "--store", fresh)  # the same again: refused, nothing doubled
    assert done.returncode != 0 and "is not empty" in done.stderr, done.stdout + done.stderr
    assert listed(fresh) == heard
