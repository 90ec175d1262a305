"""Fleet questions and the fleet view over real Zenoh: three robots' knowledge services on two linked routers."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from kgadapt.bench.fleet_bench import seed_robot
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.fleet import FleetClient, FleetSettings, RobotState
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.operator.fleet_view import FleetView, FleetViewSettings, render
from kgadapt.shared import keys, messages
from kgadapt.shared.errors import ConfigError
from tests.conftest import REPO
from tests.fleet.conftest import _store, wait_until_all_answer
from tests.support import wait_for


def kgadapt(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "kgadapt", *args], capture_output=True, text=True, timeout=timeout,
                          cwd=REPO)


def ours(rows, fleet):
    return [r for r in rows if r["robot"] in fleet.robots]


def test_one_question_reaches_every_robot_across_both_routers_and_labels_each_row(fleet):
    answer = FleetClient(fleet.client("b"), FleetSettings(timeout=3.0)).ask("current_placement")
    rows = {r["robot"]: r for r in ours(answer.rows(), fleet)}
    assert set(rows) == set(fleet.robots)  # q1 and q2 live behind router a, the client is on router b
    for robot, seeded in fleet.robots.items():
        assert list(rows[robot])[0] == "robot"
        assert (rows[robot]["config"], rows[robot]["host"], rows[robot]["decision"]) == (
            seeded["config"], seeded["host"], seeded["decision"])
    assert set(fleet.robots) <= set(answer.answered)


def test_a_robot_expected_but_not_answering_is_listed_as_silent_not_left_out(fleet):
    client = FleetClient(fleet.client("a"), FleetSettings(timeout=0.5, expect=("ghost",)))
    answer = client.ask("platforms")
    assert "ghost" in answer.silent and not answer.complete
    assert answer.answer_of("ghost").state is RobotState.SILENT
    assert set(fleet.robots) <= set(answer.answered)
    assert "no answer within the timeout from: ghost" in answer.table()
    platforms = {(r["robot"], r["platform"]) for r in ours(answer.rows(), fleet)}
    assert platforms == {(robot, host) for robot in fleet.robots for host in ("onboard", "remote")}


def test_a_robot_that_answered_before_and_stops_is_then_listed_as_silent(fleet, resp_server):
    robot = next(iter(fleet.robots))[:-2] + "q9"
    store = _store(resp_server, robot)
    service = KnowledgeService(store, ServiceSettings(robot=robot, mark_offline_at_start=False))
    try:
        seed_robot(store, robot, 7)
        service.setup(fleet.routers["a"])
        session = fleet.client("b")
        wait_until_all_answer(session, [robot])
        client = FleetClient(session, FleetSettings(timeout=1.0))
        assert robot in client.ask("current_placement").answered
        service.shutdown()
        answer = client.ask("current_placement", timeout=0.5)
        assert robot in answer.silent and set(fleet.robots) <= set(answer.answered)
    finally:
        service.shutdown()
        store.clear()
        store.shutdown()


def test_a_query_the_robots_refuse_is_reported_with_their_reason(fleet):
    client = FleetClient(fleet.client("b"), FleetSettings(timeout=2.0, expect=tuple(fleet.robots)))
    answer = client.ask("placement", {"feature": 5})  # a number where the query wants text
    assert set(fleet.robots) <= set(answer.silent)
    assert len(answer.refusals) >= len(fleet.robots)
    assert all("feature" in text for text in answer.refusals)
    with pytest.raises(ConfigError):
        client.ask("kgadapt/**")  # a query name is one key chunk: no wildcard, no other key


def test_ask_fleet_prints_one_table_with_a_robot_column_and_the_silent_robots(fleet):
    done = kgadapt("ask", "--fleet", "current_placement", "--connect", fleet.endpoints["b"], "--timeout", "2",
                   "--expect", "ghost")
    assert done.returncode == 3, done.stderr  # not everyone answered
    header = done.stdout.splitlines()[0].split()
    assert header[:3] == ["robot", "instance", "config"]
    for robot, seeded in fleet.robots.items():
        line = next(line for line in done.stdout.splitlines() if line.startswith(robot + " "))
        assert seeded["config"] in line and seeded["host"] in line
    assert "no answer within the timeout from: ghost" in done.stdout
    as_json = kgadapt("ask", "--fleet", "detector_configs", "--connect", fleet.endpoints["a"], "--json")
    assert as_json.returncode == 0, as_json.stderr
    rows = ours(json.loads(as_json.stdout)["rows"], fleet)
    assert {r["robot"] for r in rows} == set(fleet.robots)
    assert {(r["config"], r["band"]) for r in rows} >= {("marker_detection_dark", "dark")}


def test_fleet_once_shows_every_robots_configuration_band_hosts_and_last_decision(fleet):
    done = kgadapt("fleet", "--once", "--json", "--connect", fleet.endpoints["b"], "--timeout", "2")
    assert done.returncode == 0, done.stderr
    shown = {r["robot"]: r for r in json.loads(done.stdout) if r["robot"] in fleet.robots}
    assert set(shown) == set(fleet.robots)
    for robot, seeded in fleet.robots.items():
        r = shown[robot]
        assert (r["config"], r["host"], r["band"]) == (seeded["config"], seeded["host"], seeded["band"])
        assert r["answering"] and r["hosts_online"] == ["onboard", "remote"]
        assert r["decision_choice"] == f"{seeded['config']}@{seeded['host']}"
        assert 0 <= r["decision_age_s"] < 600
    text = kgadapt("fleet", "--once", "--connect", fleet.endpoints["a"])
    assert text.returncode == 0, text.stderr
    assert "robot" in text.stdout.splitlines()[1] and all(robot in text.stdout for robot in fleet.robots)


def test_the_view_refreshes_on_what_robots_publish_and_writes_nothing(fleet):
    robot = next(iter(fleet.robots))
    watcher = fleet.client("b")
    robot_side = fleet.client("a")  # the robot's own agents publish through its router
    # A host of the models going offline first, to come online below (only the models add hosts).
    KnowledgeClient(robot_side, robot, timeout=3.0).write("platform_online",
                                                          {"name": "remote", "online": False, "time": time.time()})
    before = {r: _decisions_and_runs(store) for r, store in fleet.stores.items()}
    with FleetView(watcher, FleetViewSettings(timeout=2.0)) as view:
        first = {r.robot: r for r in view.snapshot()}
        assert first[robot].decision_trigger.startswith("band_changed")
        assert "remote" not in first[robot].hosts_online
        token = robot_side.liveliness().declare_token(keys.host_alive(robot, "remote"))
        try:
            assert view.changed.wait(5), "no refresh signal for a host coming online"
            wait_for(lambda: "remote" in {r.robot: r for r in view.snapshot()}[robot].hosts_online, 5,
                     "the new host among the online hosts")
            view.changed.clear()
            event = {"time": time.time(), "trigger": "memory_short(host=onboard)", "outcome": "migrated",
                     "decision": {"config": "marker_detection_dusk", "host": "remote"}}
            robot_side.put(keys.adaptation_events(robot), messages.encode("adaptation_event", event))
            assert view.changed.wait(5), "no refresh signal for an adaptation event"
            now = {r.robot: r for r in view.snapshot()}[robot]
            assert now.decision_trigger == "memory_short(host=onboard)"
            assert now.decision_choice == "marker_detection_dusk@remote"
            assert "memory_short(host=onboard) -> marker_detection_dusk@remote" in render(list({robot: now}.values()))
        finally:
            token.undeclare()
    # The view asked (named queries only) and wrote nothing: no robot's decisions or runs changed.
    assert {r: _decisions_and_runs(store) for r, store in fleet.stores.items()} == before


def _decisions_and_runs(store) -> tuple[int, int]:
    rows = store.execute("MATCH (a:AdaptationDecision) WITH count(a) AS a MATCH (r:ProcessProfile) "
                         "RETURN a, count(r) AS r", read_only=True)
    return rows[0]["a"], rows[0]["r"]


def test_a_peer_that_asks_right_after_opening_still_gets_every_robot(fleet):
    from kgadapt.shared.session import ZenohSettings, open_session

    peer = open_session(ZenohSettings(mode="peer", connect=(fleet.endpoints["a"],), extra={"scouting/delay": 0}))
    try:
        answer = FleetClient(peer, FleetSettings(timeout=3.0, expect=tuple(fleet.robots))).ask("current_placement")
        assert set(fleet.robots) <= set(answer.answered), answer.table()
    finally:
        peer.close()


def test_bad_fleet_requests_are_refused_naming_the_problem_before_any_network():
    bad_name = kgadapt("ask", "--fleet", "kgadapt/**", "--connect", "tcp/127.0.0.1:9")
    assert bad_name.returncode == 1 and "query name 'kgadapt/**'" in bad_name.stderr
    bad_robot = kgadapt("ask", "--fleet", "platforms", "--expect", "a*b", "--connect", "tcp/127.0.0.1:9")
    assert bad_robot.returncode == 1 and "robot name 'a*b'" in bad_robot.stderr
    both = kgadapt("fleet", "--once", "--interval", "0")
    assert both.returncode == 1 and "--interval" in both.stderr
