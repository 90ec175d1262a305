"""The wire contract as an outsider sees it: a client written only from the documents, against the real robot.

One robot for the module: the knowledge service (embedded FalkorDB, the
Zenoh router), a remote agent, a stand-in flight controller and the onboard
agent with a synthetic camera, the flight bridge and the adaptation manager;
all real processes started as a user would (`kgadapt ...`). The client
(tests/contract/outsider_client.py) encodes requests by hand and decodes
what the robot publishes and answers with plain msgpack, and every payload
must have exactly the fields and types docs/CONTRACTS.md lists.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from typing import Any, Iterator

import msgpack
import pytest
import zenoh

from tests.conftest import REPO, free_port
from tests.contract.outsider_client import Heard, Outsider, encode, shape_problems
from tests.support import Child, wait_for

ONBOARD, REMOTE = "onboard", "remote"
INSTANCE = "contract1"  # the detector this test starts itself, on the remote host


def assert_shape(kind: str, body: Any, size: int | None = None) -> None:
    problems = shape_problems(kind, body, size)
    assert not problems, f"{kind} differs from docs/CONTRACTS.md: {problems}"


def ok_rows(reply: Any) -> list[dict[str, Any]]:
    """The rows of a ``rows`` reply, after checking it is one."""
    assert reply.ok, f"error reply: {reply.error}"
    assert_shape("rows", reply.body, reply.size)
    return reply.body["rows"]


def refused(reply: Any, *names: str) -> str:
    """The text of an error reply, after checking it names each of ``names``."""
    assert not reply.ok, f"expected an error reply, got {str(reply.body)[:500]}"
    for name in names:
        assert name in reply.error, f"the error does not name {name!r}: {reply.error}"
    return reply.error


def open_client(endpoint: str) -> zenoh.Session:
    """A Zenoh client of the router, as docs/zenoh.md says outsiders reach the robot."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


class Robot:
    def __init__(self, name: str, client: Outsider, heard: dict[str, Heard]) -> None:
        self.name = name
        self.client = client
        self.heard = heard


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    base = tmp_path_factory.mktemp("contract")
    store = f"embedded:{base / 'store'}"
    loaded = subprocess.run([sys.executable, "-m", "kgadapt", "knowledge", "load", "--store", store,
                             str(REPO / "knowledge" / "models")], cwd=REPO, capture_output=True, text=True,
                            timeout=120)
    assert loaded.returncode == 0, loaded.stderr
    name = f"c{free_port()}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    children: list[Child] = []
    session = None
    heard: dict[str, Heard] = {}
    try:
        service = Child.kgadapt("service", ["knowledge", "serve", "--store", store, "--robot", name,
                                            "--listen", endpoint], base)
        children.append(service)
        service.wait_ready(60)
        session = open_client(endpoint)
        client = Outsider(session, name)
        # Listen before the agents start: the adaptation manager's startup decision is published once.
        for what, keyexpr in [("status", "host/*/status"), ("deploy_events", "host/*/deployer/events"),
                              ("adaptation", "adaptation/events"), ("flight", "flight/state"),
                              ("frame", "camera/*/frame"), ("illumination", "camera/*/illumination"),
                              ("markers", "detector/*/markers")]:
            heard[what] = client.listen(keyexpr)
        # Calibrations, as an operator writes them (write verb `calibration`): the planner ranks by them.
        now = time.time()
        for row in ok_rows(client.query("detector_configs")):
            for band in ("day", "dusk", "dark"):
                rate = 0.99 if band == row["band"] else 0.5
                assert ok_rows(client.write("calibration", {
                    "config": row["config"], "band": band, "detection_rate": rate, "ms_per_frame": 10.0,
                    "time": now, "false_per_frame": 0.0})) == []
        fc_port = free_port()
        remote = Child.kgadapt("remote", ["remote", "--robot", name, "--host", REMOTE, "--memory-budget", "2G",
                                          "--connect", endpoint], base)
        children.append(remote)
        fake_fc = Child.kgadapt("fake-fc", ["flight", "fake-fc", "--url", f"udpout:127.0.0.1:{fc_port}", "--armed"],
                                base)
        children.append(fake_fc)
        onboard = Child.kgadapt("onboard", ["onboard", "--robot", name, "--host", ONBOARD, "--memory-budget", "700M",
                                            "--camera-source", "synthetic", "--fc", f"udpin:127.0.0.1:{fc_port}",
                                            "--adapt", "--connect", endpoint], base)
        children.append(onboard)
        for child in (remote, fake_fc, onboard):
            child.wait_ready(60)
        yield Robot(name, client, heard)
    finally:
        for h in heard.values():
            h.close()
        if session is not None:
            session.close()
        for child in reversed(children):
            child.stop()


# --- what the robot publishes ----------------------------------------------------------------------------------------

def test_host_statuses_have_the_documented_fields(robot: Robot) -> None:
    for host in (ONBOARD, REMOTE):
        key, body, size = robot.heard["status"].wait(
            lambda k, b, host=host: k == robot.client.key("host", host, "status"), 30, f"a status of {host}")
        assert_shape("host_status", body, size)
        assert body["host"] == host
        assert 0 <= body["memory_free_mb"] <= body["memory_total_mb"]
        assert body["cpu_load"] >= 0


def test_host_liveliness_tokens(robot: Robot) -> None:
    expected = {robot.client.key("host", h, "alive") for h in (ONBOARD, REMOTE)}
    # A token reaches the router a moment after its agent declared it (seen: onboard's missing once).
    wait_for(lambda: robot.client.tokens("host/*/alive") == expected, 10, "both hosts' tokens")


def test_camera_frames_and_illumination(robot: Robot) -> None:
    key, frame, size = robot.heard["frame"].wait(lambda k, b: True, 30, "a camera frame")
    assert_shape("frame", frame, size)
    assert key == robot.client.key("camera", frame["camera"], "frame")
    assert frame["jpeg"][:2] == b"\xff\xd8", "jpeg is not a JPEG"
    key, light, size = robot.heard["illumination"].wait(lambda k, b: True, 30, "an illumination reading")
    assert_shape("illumination", light, size)
    assert key == robot.client.key("camera", light["camera"], "illumination")


def test_flight_state(robot: Robot) -> None:
    key, state, size = robot.heard["flight"].wait(lambda k, b: b.get("link") is True, 30, "a flight state with link")
    assert_shape("flight_state", state, size)
    assert state["armed"] is True  # the stand-in autopilot was started --armed


def test_the_startup_decision_is_published_and_recorded(robot: Robot) -> None:
    key, event, size = robot.heard["adaptation"].wait(
        lambda k, b: (b.get("decision") or {}).get("trigger_kind") == "startup", 60, "the startup decision")
    assert_shape("adaptation_event", event, size)
    assert event["trigger"].startswith("startup")
    decision = event["decision"]
    # The manager's detector detects: its detections carry its instance on the key and in the body.
    mkey, detections, msize = robot.heard["markers"].wait(
        lambda k, b: b.get("instance") == decision.get("instance"), 60, "the startup detector's detections")
    assert_shape("detections", detections, msize)
    assert mkey == robot.client.key("detector", detections["instance"], "markers")
    assert len(detections["corners"]) == len(detections["ids"]) == len(detections["clean"])
    rows = ok_rows(robot.client.query("decisions", {"limit": 5}))
    assert any(r.get("name") == decision["name"] for r in rows), rows
    # docs/fleet.md: current_placement names the configuration, its host and the decision.
    placed = ok_rows(robot.client.query("current_placement"))
    assert [(r["config"], r["host"], r["decision"]) for r in placed] == [
        (decision["config"], decision["host"], decision["name"])]


# --- the knowledge service -------------------------------------------------------------------------------------------

DOCUMENTED_COLUMNS = {  # docs/CONTRACTS.md, "Named queries"
    "placement": ("config", "deployment", "platform", "demand_mb", "free_mb"),
    "detector_configs": ("config", "band", "min_level", "max_level", "memory_demand_mb", "detection_rate",
                         "false_per_frame", "false_per_reported", "ms_per_frame", "calibrated_at"),
    "config_ranking": ("config", "detection_rate", "false_per_frame", "false_per_reported", "ms_per_frame",
                       "memory_demand_mb", "suited_for", "score"),
    "detector_config": ("config", "dictionary", "config_json", "memory_demand_mb", "deployment"),
    "deployment": ("name", "kind", "executable", "arguments", "environment", "platforms", "deploys"),
    "platforms": ("platform", "memory_total_mb", "memory_free_mb", "cpu_load", "online", "online_since",
                  "last_seen", "cpu_cores", "cpu_capacity"),
    "flight_control": ("name", "mode", "armed", "landed_state", "link", "last_seen"),
    "process_profile": ("run_id", "instance", "host", "rss_mb_last", "rss_mb_mean", "rss_mb_max",
                        "cpu_percent_mean"),
    "camera_intrinsics": ("camera", "fx", "fy", "cx", "cy"),
}


def test_named_queries_answer_the_documented_columns(robot: Robot) -> None:
    c = robot.client
    asked = {
        "placement": {"config": "marker_detection_day"},
        "detector_configs": {},
        "config_ranking": {"band": "day"},
        "detector_config": {"config": "marker_detection_day"},
        "deployment": {"name": "detector_day"},
        "platforms": {},
        "flight_control": {},
        "camera_intrinsics": {"camera": "camera"},
    }
    differ = {}
    for name, params in asked.items():
        rows = ok_rows(c.query(name, params))
        assert rows, f"{name} {params}: no rows"
        differ.update({name: tuple(row) for row in rows if tuple(row) != DOCUMENTED_COLUMNS[name]})
    assert not differ, f"columns other than documented: {differ}"
    online = {r["platform"]: r["online"] for r in ok_rows(c.query("platforms"))}
    assert online[ONBOARD] is True and online[REMOTE] is True
    ranking = ok_rows(c.query("config_ranking", {"band": "day"}))
    assert ranking[0]["config"] == "marker_detection_day"
    deployment = ok_rows(c.query("deployment", {"name": "detector_day"}))[0]
    assert REMOTE in deployment["platforms"] and "marker_detection_day" in deployment["deploys"]
    assert ok_rows(c.query("detector_config", {"config": "no_such_config"})) == []  # "empty when unknown"
    assert ok_rows(c.query("process_profile", {"run_id": "no-such-run"})) == []
    # The others the docs list (docs/knowledge.md, "Named queries") answer too.
    for name, params in {"feature_deployments": {"platform": REMOTE}, "deployable_components": {},
                         "camera_resolutions": {}, "low_memory_components": {"threshold_mb": 100.0},
                         "cpu_overload": {"platform": ONBOARD}, "decisions": {}, "current_placement": {},
                         "in_place_change": {"from": "detector_day", "to": "detector_dusk", "host": REMOTE}}.items():
        ok_rows(c.query(name, params))
    # The robot's own lane answers the same.
    assert ok_rows(c.query("platforms", own=True))


def test_the_papers_literal_queries_are_bounded(robot: Robot) -> None:
    """fig4_literal has 21,344 rows on the shipped models (docs/knowledge.md): through the service, on
    either door, it answers its first 1,000 (the LIMIT every sandboxed question gets) or stops at 1 s."""
    for own in (False, True):
        reply = robot.client.query("fig4_literal", {"platform": REMOTE}, own=own)
        if reply.ok:
            assert len(ok_rows(reply)) == 1000
        else:
            refused(reply, "time limit")


def test_a_named_query_in_the_selector(robot: Robot) -> None:
    rows = ok_rows(robot.client.query_selector("placement", config="marker_detection_day"))
    assert rows and {r["config"] for r in rows} == {"marker_detection_day"}
    rows = ok_rows(robot.client.query_selector("decisions", limit="1"))  # converted to the declared int
    assert len(rows) <= 1


def test_named_query_refusals_name_the_problem(robot: Robot) -> None:
    c = robot.client
    refused(c.query("no_such_query"), "no_such_query")
    refused(c.query("detector_config", {}), "config")
    refused(c.query("placement", {"bogus": 1}), "bogus")
    refused(c.query("decisions", {"limit": "many"}), "limit")
    refused(c.query_selector("decisions", limit="many"), "limit")


def test_cypher_lane(robot: Robot) -> None:
    c = robot.client
    rows = ok_rows(c.cypher("MATCH (p:Platform) WHERE p.name = $n RETURN p.name AS name", {"n": REMOTE}))
    assert rows == [{"name": REMOTE}]
    # A RETURN without LIMIT gets LIMIT 1000 (docs/knowledge.md).
    assert len(ok_rows(c.cypher("UNWIND $xs AS x RETURN x", {"xs": list(range(1500))}))) == 1000
    refused(c.cypher("CREATE (n:Platform {name: 'x'}) RETURN n"), "CREATE")
    refused(c.cypher("CALL db.labels()"), "CALL")
    refused(c.cypher("LOAD CSV FROM 'file:///etc/passwd' AS l RETURN l"), "LOAD")
    refused(c.cypher("UNWIND range(1, 10) AS x RETURN x"), "range")
    refused(c.cypher("MATCH (n) RETURN n LIMIT 5000"), "LIMIT")
    refused(c.cypher("RETURN 1 AS x // " + "y" * 4000))  # over 4,000 characters
    # Written in the graph, not in Cypher: nothing was created.
    assert ok_rows(c.cypher("MATCH (n:Platform {name: 'x'}) RETURN count(n) AS n")) == [{"n": 0}]


def test_malformed_requests_name_the_field(robot: Robot) -> None:
    c = robot.client
    cypher_key = c.key("knowledge", "cypher")
    query_key = c.key("knowledge", "query", "platforms")
    assert not c.get_one(query_key, b"\xc1").ok  # not msgpack
    assert not c.get_one(query_key, msgpack.packb([1, 2])).ok  # not a map
    refused(c.get_one(query_key, msgpack.packb({"v": 1, "params": {}})), "kind")
    refused(c.get_one(query_key, encode("cypher_request", cypher="RETURN 1")), "kind")
    refused(c.get_one(query_key, msgpack.packb({"kind": "query_request", "v": 2, "params": {}})), "v")
    refused(c.get_one(cypher_key, encode("cypher_request", params={})), "cypher")
    refused(c.get_one(cypher_key, encode("cypher_request", cypher=42)), "cypher")
    refused(c.get_one(cypher_key, encode("cypher_request", cypher=b"RETURN 1")), "cypher")  # a str is no bytes
    refused(c.get_one(cypher_key, encode("cypher_request", cypher="RETURN 1", params=[1])), "params")
    refused(c.get_one(cypher_key, encode("cypher_request", cypher="RETURN 1 // " + "y" * 17000)), "cypher")
    refused(c.get_one(query_key, encode("query_request", params={f"p{i}": i for i in range(65)})), "params")
    over = c.get_one(query_key, encode("query_request", params={"x": "y" * 300000}))
    assert not over.ok
    # A field the receiver does not know is kept (ignored); a nil optional field is an absent one.
    assert ok_rows(c.get_one(query_key, encode("query_request", params={}, newer_field=[1, 2])))
    assert ok_rows(c.get_one(query_key, encode("query_request", params=None)))
    assert ok_rows(c.get_one(query_key, encode("query_request")))


def test_writes_and_what_a_host_may_write(robot: Robot) -> None:
    c = robot.client
    now = time.time()
    ghost = {"name": "contract_ghost", "time": now, "memory_total_mb": 1000.0, "memory_free_mb": 400.0,
             "cpu_load": 10.0}
    # Only the models add hosts: a write about a host no Platform names is refused, naming it.
    refused(c.write("platform", ghost), "contract_ghost")
    assert "contract_ghost" not in {r["platform"] for r in ok_rows(c.query("platforms"))}
    assert ok_rows(c.write("platform", {**ghost, "name": REMOTE, "memory_total_mb": 2048.0})) == []
    refused(c.write("platform", {**ghost, "memory_free_mb": 2000.0}), "memory_free_mb")
    refused(c.write("platform", {**ghost, "cpu_load": -1.0}), "cpu_load")
    refused(c.write("platform", {**ghost, "surprise": 1}), "surprise")
    refused(c.write("no_such_verb", {}), "no_such_verb")
    refused(c.get_one(c.key("knowledge", "write", "platform"), encode("write_request")), "params")
    # On a host's own key only what that host owns (docs/CONTRACTS.md, check_owner).
    refused(c.write("platform", {**ghost, "name": ONBOARD}, host=REMOTE), "name")
    refused(c.write("calibration", {"config": "marker_detection_day", "band": "day", "detection_rate": 0.9,
                                    "ms_per_frame": 5.0, "time": now}, host=REMOTE))
    refused(c.write("process_start", {"run_id": "contract-run-1", "instance": "x", "deployment": "detector_day",
                                      "config": "marker_detection_day", "host": ONBOARD, "pid": 4242,
                                      "start_time": now}, host=REMOTE), "host")
    refused(c.write("decision", {"name": "contract-decision", "time": now, "trigger": "startup",
                                 "inputs_json": "{}", "query": "placement", "config": "marker_detection_day",
                                 "host": REMOTE, "duration_ms": 1.0, "outcome": "x"}, host=REMOTE))
    assert ok_rows(c.write("platform", {**ghost, "name": REMOTE, "memory_total_mb": 2048.0,
                                       "memory_free_mb": 2000.0}, host=REMOTE)) == []


def test_squeeze_answers_the_new_status(robot: Robot) -> None:
    c = robot.client
    reply = c.squeeze(REMOTE, 100)
    assert reply.ok, reply.error
    assert_shape("host_status", reply.body, reply.size)
    assert reply.body["host"] == REMOTE and reply.body["reserved_mb"] == 100
    reply = c.squeeze(REMOTE, 0)
    assert reply.ok and reply.body["reserved_mb"] == 0
    refused(c.squeeze(REMOTE, -5), "reserve_mb")
    assert "number" in refused(c.squeeze(REMOTE, True), "reserve_mb")  # a bool is no number
    refused(c.squeeze(REMOTE, "lots"), "reserve_mb")
    refused(c.squeeze(REMOTE, math.nan), "reserve_mb")


def test_no_responder_means_no_reply(robot: Robot) -> None:
    replies = robot.client.get_all(f"kgadapt/{robot.name}x/knowledge/query/platforms",
                                   encode("query_request", params={}), timeout=2.0)
    assert replies == []


# --- the deployers and a detector ------------------------------------------------------------------------------------

def deploy_reply(replies: list[Any]) -> dict[str, Any]:
    assert len(replies) == 1, replies
    assert replies[0].ok, replies[0].error
    assert_shape("deploy_reply", replies[0].body, replies[0].size)
    return replies[0].body


def test_deployer_lifecycle_and_detector_requests(robot: Robot) -> None:
    c = robot.client
    events = robot.heard["deploy_events"]
    listed = c.deployer("*", "list", timeout=10.0)
    assert len(listed) == 2 and all(r.ok for r in listed), listed
    for r in listed:
        assert_shape("deploy_reply", r.body, r.size)
        assert r.body["ok"] is True and {"host", "processes"} <= set(r.body["detail"]) <= {"host", "processes", "launcher"}
    assert {r.body["detail"]["host"] for r in listed} == {ONBOARD, REMOTE}

    started = deploy_reply(c.deployer(REMOTE, "start", deployment="detector_day", config="marker_detection_day",
                                      instance=INSTANCE))
    assert started["ok"] is True, started
    detail = started["detail"]
    assert detail["instance"] == INSTANCE and detail["host"] == REMOTE
    assert detail["state"] in ("ready", "running") and detail["pid"] > 0
    for kind in ("started", "ready"):
        key, event, size = events.wait(lambda k, b, kind=kind: b.get("instance") == INSTANCE and b["event"] == kind,
                                       30, f"the {kind} event")
        assert key == c.key("host", REMOTE, "deployer", "events")
        assert_shape("deploy_event", event, size)
        assert event["run_id"] == detail["run_id"]
    assert c.key("detector", INSTANCE, "alive") in c.tokens(f"detector/{INSTANCE}/alive")
    key, detections, size = robot.heard["markers"].wait(lambda k, b: b.get("instance") == INSTANCE, 30,
                                                        "detections of our detector")
    assert_shape("detections", detections, size)
    assert detections["host"] == REMOTE and detections["config"] == "marker_detection_day"

    status = deploy_reply(c.deployer(REMOTE, "status", instance=INSTANCE))
    assert status["ok"] is True and status["detail"]["run_id"] == detail["run_id"]
    # Its profile, written by the deployer through the knowledge service.
    profile = wait_for(lambda: ok_rows(c.query("process_profile", {"run_id": detail["run_id"]})), 15,
                       "the run's process profile")
    assert tuple(profile[0]) == DOCUMENTED_COLUMNS["process_profile"]
    assert profile[0]["instance"] == INSTANCE and profile[0]["host"] == REMOTE
    # Only the host that started a run writes its samples.
    refused(c.write("process_sample", {"run_id": detail["run_id"], "rss_mb_last": 50.0, "rss_mb_mean": 50.0,
                                       "rss_mb_max": 50.0, "cpu_percent_mean": 5.0}, host=ONBOARD), "run_id")
    assert len(status["detail"]["output"]) <= 5  # its last output lines

    # In place: the graph allows detector_day -> detector_dusk on this host.
    assert ok_rows(c.query("in_place_change", {"from": "detector_day", "to": "detector_dusk", "host": REMOTE}))
    reply = c.configure(REMOTE, INSTANCE, "marker_detection_dusk")
    assert reply.ok, reply.error
    assert_shape("configure_reply", reply.body, reply.size)
    assert reply.body["instance"] == INSTANCE and reply.body["config"] == "marker_detection_dusk"
    assert reply.body["previous"] == "marker_detection_day" and reply.body["deployment"] == "detector_dusk"
    key, event, size = events.wait(lambda k, b: b.get("instance") == INSTANCE and b["event"] == "reconfigured", 30,
                                   "the reconfigured event")
    assert_shape("deploy_event", event, size)
    refused(c.configure(REMOTE, INSTANCE, "no_such_config"), "no_such_config")

    reply = c.activity(REMOTE, INSTANCE, False)
    assert reply.ok, reply.error
    assert_shape("activity_reply", reply.body, reply.size)
    assert reply.body == {**reply.body, "instance": INSTANCE, "active": False}
    reply = c.activity(REMOTE, INSTANCE, True)
    assert reply.ok and reply.body["active"] is True

    # A crash: exited with the signal as a negative return code, then restarted with the configuration
    # it took in place.
    os.kill(detail["pid"], signal.SIGKILL)
    key, event, size = events.wait(lambda k, b: b.get("run_id") == detail["run_id"] and b["event"] == "exited", 30,
                                   "the killed run's exit")
    assert event["returncode"] == -signal.SIGKILL
    key, event, size = events.wait(lambda k, b: b.get("instance") == INSTANCE and b["event"] == "restarted", 30,
                                   "the restart")
    assert_shape("deploy_event", event, size)
    assert (event["deployment"], event["config"]) == ("detector_dusk", "marker_detection_dusk")
    assert event["run_id"] != detail["run_id"]
    events.wait(lambda k, b: b.get("run_id") == event["run_id"] and b["event"] == "ready", 30, "the new run's ready")

    # Every verb refuses a field beyond its own.
    body = deploy_reply(c.deployer(REMOTE, "stop", instance=INSTANCE, config="marker_detection_day"))
    assert body["ok"] is False and "config" in body["detail"]["error"], body
    stopped = deploy_reply(c.deployer(REMOTE, "stop", instance=INSTANCE))
    assert stopped["ok"] is True and "returncode" in stopped["detail"], stopped
    key, event, size = events.wait(lambda k, b: b.get("instance") == INSTANCE and b["event"] == "stopped", 30,
                                   "the stopped event")
    assert_shape("deploy_event", event, size)
    for _, event, size in events.snapshot():
        assert_shape("deploy_event", event, size)


def test_deployer_refusals(robot: Robot) -> None:
    c = robot.client
    # A request names what to run, never how.
    replies = c.deployer(REMOTE, "start", timeout=10.0,
                         **{"deployment": "detector_day", "config": "marker_detection_day", "command": "/bin/sh"})
    assert len(replies) == 1
    text = replies[0].error if not replies[0].ok else json.dumps(replies[0].body)
    assert "command" in text and (not replies[0].ok or replies[0].body["ok"] is False), text
    # Unknown deployment: ok false with {error, error_type, host}.
    body = deploy_reply(c.deployer(REMOTE, "start", timeout=10.0, deployment="no_such_deployment",
                                   config="marker_detection_day"))
    assert body["ok"] is False
    assert {"error", "error_type", "host"} <= set(body["detail"]) and "no_such_deployment" in body["detail"]["error"]
    # A configuration its deployment does not deploy.
    body = deploy_reply(c.deployer(REMOTE, "start", timeout=10.0, deployment="detector_day",
                                   config="marker_detection_dark"))
    assert body["ok"] is False and "marker_detection_dark" in body["detail"]["error"]
    # A start on a key with wildcards names no one host.
    replies = c.deployer("*", "start", timeout=10.0, deployment="detector_day", config="marker_detection_day")
    assert replies and all(not r.ok or r.body["ok"] is False for r in replies), replies
    # Not a deploy_request at all.
    replies = c.get_all(c.key("host", REMOTE, "deployer", "status"), encode("squeeze_request", reserve_mb=1))
    assert len(replies) == 1 and not replies[0].ok and "kind" in replies[0].error, replies
    replies = c.get_all(c.key("host", REMOTE, "deployer", "start"),
                        encode("deploy_request", deployment="detector_day", config="x/y"))
    assert len(replies) == 1 and (not replies[0].ok or replies[0].body["ok"] is False), replies
    # Status of an unknown instance.
    replies = c.deployer(REMOTE, "status", timeout=10.0, instance="no_such_instance")
    assert len(replies) == 1
    text = replies[0].error if not replies[0].ok else json.dumps(replies[0].body)
    assert "no_such_instance" in text, text


def test_everything_heard_has_the_documented_shape(robot: Robot) -> None:
    """Last: every message the robot published while the module ran, checked against the docs."""
    kinds = {"status": "host_status", "deploy_events": "deploy_event", "adaptation": "adaptation_event",
             "flight": "flight_state", "frame": "frame", "illumination": "illumination", "markers": "detections"}
    for what, kind in kinds.items():
        items = robot.heard[what].snapshot()
        assert items, f"nothing heard on {what}"
        problems = {p for _, body, size in items for p in shape_problems(kind, body, size)}
        assert not problems, f"{kind}: {sorted(problems)[:20]}"

