"""Mutual TLS and access control of the shipped configurations, with certificates made by ``kgadapt certs``.

Real processes on loopback: ``kgadapt knowledge serve`` on the shipped
router configuration (the one place rules are enforced) over an embedded
store holding the shipped models, and ``kgadapt onboard`` (host monitor with
its squeeze queryable, deployer, liveliness) on the shipped onboard
configuration as a client of it. The test's own sessions use the shipped
onboard configuration with another certificate each: this robot's operator,
another robot of the fleet (``quad2-onboard``, listed as one of the
``other-robots``), a stranger of our CA, someone of another CA, and nobody.

Every refusal is paired with the same request from this robot's operator
succeeding, so a refusal cannot pass merely because something is not up.
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable

import pytest

from kgadapt.deploy.client import DeployerClient
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.runtime import WRITERS
from kgadapt.onboard.perception.detector import set_active
from kgadapt.shared import keys, messages
from kgadapt.shared.errors import RemoteError, RequestTimeout, TransportError
from kgadapt.shared.hostmonitor import squeeze
from kgadapt.shared.session import ZenohSettings, open_session
from tests.conftest import free_port
from tests.security.conftest import FAST_OPEN, OTHER_ROBOT, ROBOT, SHELL_WORDS, dropped_kind, shipped_config, wait_for

OPERATOR = f"{ROBOT}-operator"
OTHER = f"{OTHER_ROBOT}-onboard"
STRANGER = "mallory-operator"  # signed by our CA, named by no policy
FAIL_FAST = {"connect/exit_on_failure": True, "connect/timeout_ms": 1000}

def graph_snapshot(knowledge: KnowledgeClient) -> tuple[Any, ...]:
    """Everything but the live figures of platforms (the onboard agent keeps updating those) and of the
    fleet roster (the service's roll calls move its robots' last_seen): of both, the names."""
    nodes = knowledge.cypher("MATCH (n) WHERE NOT n:Platform AND NOT n:FleetRobot "
                             "RETURN labels(n) AS l, properties(n) AS p")
    platforms = knowledge.cypher("MATCH (p) WHERE p:Platform OR p:FleetRobot "
                                 "RETURN labels(p) AS l, p.name AS name ORDER BY name")
    relations = knowledge.cypher("MATCH (a)-[r]->(b) RETURN a.name AS a, type(r) AS t, properties(r) AS p, "
                                 "b.name AS b")
    key = lambda row: repr(sorted(row.items()))  # noqa: E731
    return sorted(nodes, key=key), platforms, sorted(relations, key=key)


def write_params(verb: str) -> dict[str, Any]:
    """Valid parameters for each write verb, so that only the identity decides."""
    return {
        "platform": {"name": "remote", "time": 1.0, "memory_free_mb": 1.0},
        "platform_online": {"name": "onboard", "online": False, "time": 1.0},
        "process_start": {"run_id": "forged-run", "instance": "forged", "deployment": "detector_day",
                          "config": "marker_detection_day", "host": "onboard", "pid": 1, "start_time": 1.0},
        "process_sample": {"run_id": "forged-run", "rss_mb_last": 1.0, "rss_mb_mean": 1.0, "rss_mb_max": 1.0,
                           "cpu_percent_mean": 1.0},
        "process_end": {"run_id": "forged-run", "end_time": 2.0, "exit_status": 0},
        "process_reconfigured": {"run_id": "forged-run", "config": "marker_detection_dark",
                                 "deployment": "detector_dark", "time": 2.0},
        "calibration": {"config": "marker_detection_day", "band": "dark", "detection_rate": 1.0, "false_rate": 0.0,
                        "ms_per_frame": 1.0, "time": 1.0},
        "decision": {"name": "forged-decision", "time": 1.0, "trigger": "forged"},
        "live_rate": {"config": "marker_detection_day", "band": "dark", "detection_rate": 0.0, "frames": 40,
                      "frames_expected": 30, "frames_seen": 0, "since": 1.0, "time": 2.0},
        "flight_state": {"name": "flight_control", "time": 1.0, "link": True, "mode": "FORGED"},
        "fleet_forget": {"robot": "quad1"},
    }[verb]


def concurrently(calls: dict[str, Callable[[], Any]]) -> dict[str, Any]:
    """Run the calls in parallel; each one's result or the exception it raised."""
    def outcome(call: Callable[[], Any]) -> Any:
        try:
            return call()
        except Exception as exc:
            return exc

    with ThreadPoolExecutor(len(calls)) as pool:
        futures = {name: pool.submit(outcome, call) for name, call in calls.items()}
        return {name: future.result() for name, future in futures.items()}


def reply_payloads(session: Any, key: str, payload: bytes | None = None) -> list[bytes]:
    return [(r.ok.payload if r.ok is not None else r.err.payload).to_bytes()
            for r in session.get(key, payload=payload, timeout=2)]


# -- who may connect ----------------------------------------------------------------------------------


def test_a_peer_without_a_client_certificate_cannot_connect(session_as):
    with pytest.raises(TransportError):
        session_as(OPERATOR, **{"transport/link/tls/connect_certificate": None,
                                "transport/link/tls/connect_private_key": None, **FAIL_FAST})
    assert session_as(OPERATOR, **FAIL_FAST)  # the same configuration with the certificate connects


def test_plain_tcp_to_the_tls_port_is_refused(network):
    with pytest.raises(TransportError):
        open_session(ZenohSettings(mode="client", connect=(f"tcp/127.0.0.1:{network.port}",)))


def test_a_certificate_from_another_ca_cannot_connect_even_with_this_robots_operator_name(session_as):
    with pytest.raises(TransportError):
        session_as(OPERATOR, foreign=True, **FAIL_FAST)


def test_a_router_with_a_certificate_of_our_ca_for_another_name_is_not_trusted(network, pki, tmp_path):
    # Another robot's host certificate is signed by our CA but not valid for the name the hosts dial.
    port = free_port()
    cert, key = pki.pair(OTHER)
    impostor = open_session(ZenohSettings(config_file=str(shipped_config("router.json5", pki.tls, tmp_path, **{
        "listen/endpoints": [f"tls/127.0.0.1:{port}"], "transport/link/tls/listen_certificate": str(cert),
        "transport/link/tls/listen_private_key": str(key), **FAST_OPEN}))))
    try:
        with pytest.raises(TransportError):
            open_session(ZenohSettings(config_file=str(network.config(
                OPERATOR, **{"connect/endpoints": [f"tls/localhost:{port}"], **FAIL_FAST}))))
    finally:
        impostor.close()


# -- what another robot may do ------------------------------------------------------------------------


def test_another_robot_may_ask_named_queries_and_read_only_cypher(session_as):
    knowledge = KnowledgeClient(session_as(OTHER), ROBOT, timeout=2.0)
    assert knowledge.query("deployment", {"name": "detector_hd"})[0]["platforms"] == ["remote"]
    assert knowledge.cypher("MATCH (f:Feature {name: $f}) RETURN f.name AS f", {"f": "MarkerDetection"}) == [
        {"f": "MarkerDetection"}]


def test_another_robot_cannot_start_list_or_stop_processes_nor_squeeze_a_host(session_as):
    other = DeployerClient(session_as(OTHER), ROBOT, timeout=1.0)
    operator_session = session_as(OPERATOR)
    operator = DeployerClient(operator_session, ROBOT, timeout=3.0)
    outcomes = concurrently({
        "start": lambda: other.start("onboard", "detector_day", "marker_detection_day", instance="intruder",
                                     wait_ready=False),
        "stop": lambda: other.stop("onboard", "anything"),
        "squeeze": lambda: squeeze(other.session, ROBOT, "onboard", 600.0, timeout=1.0),
    })
    assert {what: dropped_kind(outcome) for what, outcome in outcomes.items()} == dict.fromkeys(outcomes, RequestTimeout)
    list_key, empty = keys.deployer_verb(ROBOT, "onboard", "list"), messages.encode("deploy_request", {})
    assert reply_payloads(other.session, list_key, empty) == []  # not even an answer
    assert len(reply_payloads(operator_session, list_key, empty)) == 1  # while the deployer answers this robot
    assert operator.processes("onboard") == []  # and nothing was started
    squeezed = squeeze(operator_session, ROBOT, "onboard", 0.0, timeout=3.0)  # the queryable is there too
    assert squeezed.host == "onboard" and (squeezed.reserved_mb or 0.0) == 0.0


def test_another_robot_cannot_write_knowledge_with_any_verb_this_robots_operator_may_use(session_as):
    other = KnowledgeClient(session_as(OTHER), ROBOT, timeout=1.0)
    operator = KnowledgeClient(session_as(OPERATOR), ROBOT, timeout=3.0)
    before = graph_snapshot(operator)
    # A denied request is dropped at the router: the asker waits its whole timeout, so ask all at once.
    outcomes = concurrently({verb: (lambda v=verb: other.write(v, write_params(v))) for verb in WRITERS})
    assert {verb: dropped_kind(outcome) for verb, outcome in outcomes.items()} == {verb: RequestTimeout for verb in WRITERS}
    assert graph_snapshot(operator) == before
    for verb in WRITERS:
        assert operator.write(verb, write_params(verb)) == [], verb  # the same write from this robot is applied
    assert graph_snapshot(operator) != before


def test_another_robots_read_only_cypher_cannot_write(session_as):
    other = KnowledgeClient(session_as(OTHER), ROBOT, timeout=2.0)
    before = graph_snapshot(other)
    for text in ["CREATE (:Platform {name: 'forged'})", "MATCH (n) DETACH DELETE n",
                 "MATCH (d:Deployment) SET d.executable = '/bin/sh'",
                 "LOAD CSV FROM 'file:///etc/passwd' AS row RETURN row",
                 "CALL db.idx.fulltext.drop('Deployment')",
                 "MATCH (n) RETURN n UNION MATCH (m) DETACH DELETE m RETURN m AS n"]:
        with pytest.raises(RemoteError, match="read-only"):
            other.cypher(text)
    assert graph_snapshot(other) == before


def test_another_robot_cannot_put_statuses_or_liveliness_into_the_graph(session_as):
    other = session_as(OTHER)
    operator_session = session_as(OPERATOR)
    operator = KnowledgeClient(operator_session, ROBOT, timeout=3.0)
    # For a host of the models that has no agent up here: a forged status would leave its cpu_cores
    # (later statuses without them keep them), a forged token would set it online.
    status = {"host": "remote", "time": 1.0, "memory_total_mb": 100.0, "memory_free_mb": 1.0, "cpu_load": 0.0}
    other.put(keys.host_status(ROBOT, "remote"), messages.encode("host_status", {**status, "cpu_cores": 55}))
    token = other.liveliness().declare_token(keys.host_alive(ROBOT, "remote"))
    try:
        operator_session.put(keys.host_status(ROBOT, "remote"),
                             messages.encode("host_status", {**status, "memory_free_mb": 2.0}))
        row = lambda: next(r for r in operator.query("platforms", {}) if r["platform"] == "remote")  # noqa: E731
        wait_for(lambda: row()["memory_free_mb"] == 2.0, 5, "the operator's status to reach the graph")
        assert row()["cpu_cores"] != 55 and row()["online"] is not True
    finally:
        token.undeclare()


def test_another_robot_can_neither_read_this_robots_data_nor_answer_its_queries(session_as):
    other = session_as(OTHER)
    operator = session_as(OPERATOR)
    agent = session_as(f"{ROBOT}-onboard")
    seen_by_other: list[str] = []
    seen_by_agent: list[str] = []
    spy = other.declare_subscriber(f"kgadapt/{ROBOT}/**", lambda s: seen_by_other.append(str(s.key_expr)))
    own = agent.declare_subscriber(keys.camera_frame(ROBOT, "cam0"), lambda s: seen_by_agent.append(str(s.key_expr)))
    forged = other.declare_queryable(keys.knowledge_query(ROBOT, "placement"),
                                     lambda q: q.reply(q.key_expr, b"forged answer"))
    try:
        wait_for(lambda: (operator.put(keys.camera_frame(ROBOT, "cam0"), b"frame"), seen_by_agent)[1], 5,
                 "a frame to reach this robot's own subscriber")
        answers = reply_payloads(operator, keys.knowledge_query(ROBOT, "placement"))
    finally:
        for entity in (spy, own, forged):
            entity.undeclare()
    assert seen_by_other == []
    assert len(answers) == 1 and b"forged" not in answers[0]
    assert messages.decode(answers[0], "rows")["rows"] is not None  # the knowledge service's own answer


def test_wildcard_requests_of_another_robot_reach_no_queryable(session_as):
    other = session_as(OTHER)
    payload = messages.encode("deploy_request", {"deployment": "detector_day", "config": "marker_detection_day"})
    for selector in [f"kgadapt/{ROBOT}/**", "kgadapt/**", "**", f"kgadapt/{ROBOT}/knowledge/**",
                     f"kgadapt/{ROBOT}/knowledge/*/*", f"kgadapt/{ROBOT}/host/*/deployer/start"]:
        assert reply_payloads(other, selector, payload) == [], selector
    assert DeployerClient(session_as(OPERATOR), ROBOT, timeout=3.0).processes("onboard") == []


def test_a_certificate_of_our_ca_that_no_policy_names_gets_nothing(session_as):
    stranger = session_as(STRANGER)
    with pytest.raises(RequestTimeout):
        KnowledgeClient(stranger, ROBOT, timeout=1.0).query("platforms", {})
    assert reply_payloads(stranger, keys.deployer_verb(ROBOT, "onboard", "list"),
                          messages.encode("deploy_request", {})) == []


# -- what this robot's own hosts may do: each only its own ------------------------------------------


def test_a_hosts_certificate_publishes_only_its_own_status_liveliness_and_detections(session_as):
    remote = session_as(f"{ROBOT}-remote")  # the remote agent's identity, inherited by its detectors
    watcher = session_as(OPERATOR)
    seen: list[str] = []
    forged_seen: list[str] = []  # the onboard agent's own status travels meanwhile: only the forged one counts
    alive: list[str] = []

    def on_sample(sample: Any) -> None:
        seen.append(str(sample.key_expr))
        if b"forged" in sample.payload.to_bytes() or sample.payload.to_bytes() == forged_status:
            forged_seen.append(str(sample.key_expr))

    subscriber = watcher.declare_subscriber(f"kgadapt/{ROBOT}/**", on_sample)
    tokens = watcher.liveliness().declare_subscriber(keys.host_alive(ROBOT, "*"),
                                                    lambda s: alive.append(str(s.key_expr)))
    status = {"time": 1.0, "memory_total_mb": 700.0, "memory_free_mb": 0.0, "cpu_load": 0.0}
    forged_status = messages.encode("host_status", {"host": "onboard", **status})
    forged_token = remote.liveliness().declare_token(keys.host_alive(ROBOT, "ghost"))
    onboard_token = remote.liveliness().declare_token(keys.host_alive(ROBOT, "onboard_twin"))
    try:
        for_onboard = keys.host_status(ROBOT, "onboard")
        own = keys.host_status(ROBOT, "remote")
        flight = keys.flight_state(ROBOT)
        wait_for(lambda: (remote.put(own, messages.encode("host_status", {"host": "remote", **status})),
                          own in seen)[1], 5, "the remote host's own status to be delivered")
        real_token = remote.liveliness().declare_token(keys.host_alive(ROBOT, "remote"))
        wait_for(lambda: keys.host_alive(ROBOT, "remote") in alive, 5, "the remote host's own token")
        real_token.undeclare()
        remote.put(for_onboard, forged_status)
        remote.put(flight, messages.encode("flight_state", {"time": 1.0, "link": True, "landed_state": "LANDING"}))
        remote.put(keys.adaptation_events(ROBOT), b"forged")
        remote.put(keys.camera_frame(ROBOT, "cam0"), b"forged frame")
        detections = keys.detector_markers(ROBOT, "on_remote")
        wait_for(lambda: (remote.put(detections, b"x"), detections in seen)[1], 5, "a remote detector's detections")
    finally:
        for entity in (subscriber, tokens, forged_token, onboard_token):
            entity.undeclare()
    assert for_onboard not in forged_seen and flight not in seen
    assert keys.adaptation_events(ROBOT) not in seen and keys.camera_frame(ROBOT, "cam0") not in seen
    assert not {keys.host_alive(ROBOT, "ghost"), keys.host_alive(ROBOT, "onboard_twin")} & set(alive)


def test_a_remote_hosts_certificate_cannot_command_deployers(session_as):
    remote = DeployerClient(session_as(f"{ROBOT}-remote"), ROBOT, timeout=1.0)
    with pytest.raises(RequestTimeout):
        remote.start("onboard", "detector_day", "marker_detection_day", instance="from_remote", wait_ready=False)
    onboard = DeployerClient(session_as(f"{ROBOT}-onboard"), ROBOT, timeout=3.0)  # the manager's identity may
    assert onboard.processes("onboard") == []


# -- what the deployer runs ---------------------------------------------------------------------------


def test_commands_from_the_models_run_without_a_shell_and_their_words_arrive_verbatim(network, session_as):
    operator = DeployerClient(session_as(OPERATOR), ROBOT, timeout=3.0, start_timeout=20.0)
    info = operator.start("onboard", "shell_probe", "marker_detection_day", instance="shellprobe")
    try:
        assert info.state == "ready"
        argv, probe = wait_for(lambda: next(
            (json.loads(line) for line in operator.status("onboard", "shellprobe").output
             if line.startswith("[[")), None), 5, "the probe's own report of its arguments")
    finally:
        operator.stop("onboard", "shellprobe")
    marker = str(network.marker)
    assert argv == [w.format(m=marker) for w in SHELL_WORDS]
    assert probe == f"$(touch {marker})"
    assert not network.marker.exists()


# -- write verbs: each host only about itself, only plausible figures ----------------------------------


def test_a_hosts_write_verbs_act_only_on_what_that_host_owns(session_as):
    remote_session = session_as(f"{ROBOT}-remote")
    remote = KnowledgeClient(remote_session, ROBOT, timeout=3.0, host="remote")
    onboard = KnowledgeClient(session_as(f"{ROBOT}-onboard"), ROBOT, timeout=3.0, host="onboard")
    operator = KnowledgeClient(session_as(OPERATOR), ROBOT, timeout=3.0)
    operator.write("platform_online", {"name": "onboard", "online": True, "time": 5.0})  # (an earlier test's write)
    # Keys the remote certificate may not ask on at all: dropped by the router, so asked at once.
    dropped = concurrently({
        "onboard's key": lambda: KnowledgeClient(remote_session, ROBOT, timeout=1.0, host="onboard").write(
            "platform_online", {"name": "onboard", "online": False, "time": 1.0}),
        "robot-wide key": lambda: KnowledgeClient(remote_session, ROBOT, timeout=1.0).write(
            "platform_online", {"name": "onboard", "online": False, "time": 1.0}),
    })
    assert {what: dropped_kind(outcome) for what, outcome in dropped.items()} == dict.fromkeys(dropped, RequestTimeout)
    # On its own key, the service refuses what is not the remote host's, naming the parameter.
    assert remote.write("platform", {"name": "remote", "time": 2.0, "memory_total_mb": 2048.0,
                                     "memory_free_mb": 1000.0}) == []
    for verb, params, reason in [
        ("platform", {"name": "onboard", "time": 2.0, "memory_free_mb": 0.0}, "'name' is 'onboard'"),
        ("platform_online", {"name": "onboard", "online": False, "time": 2.0}, "'name' is 'onboard'"),
        ("process_start", {**write_params("process_start"), "run_id": "remote-run", "host": "onboard"},
         "'host' is 'onboard'"),
        ("decision", write_params("decision"), "only the adaptation manager's host 'onboard'"),
        ("flight_state", {**write_params("flight_state"), "landed_state": "LANDING"},
         "only the adaptation manager's host"),
        ("calibration", {**write_params("calibration"), "detection_rate": 0.0}, "no host's to write"),
        ("live_rate", write_params("live_rate"), "only the adaptation manager's host"),
    ]:
        with pytest.raises(RemoteError, match=reason):
            remote.write(verb, params)
    # A process belongs to the host that started it: nobody else may sample, end or take its profile.
    onboard_run = {**write_params("process_start"), "run_id": "onboard-run", "host": "onboard"}
    assert onboard.write("process_start", onboard_run) == []
    for verb, params in [
        ("process_sample", {**write_params("process_sample"), "run_id": "onboard-run", "rss_mb_last": 60000.0}),
        ("process_end", {**write_params("process_end"), "run_id": "onboard-run"}),
        ("process_start", {**onboard_run, "host": "remote"}),
        ("process_sample", {**write_params("process_sample"), "run_id": "nobody-started-this"}),
    ]:
        with pytest.raises(RemoteError, match="'run_id'"):
            remote.write(verb, params)
    assert onboard.write("process_sample", {**write_params("process_sample"), "run_id": "onboard-run"}) == []
    assert onboard.write("decision", {**write_params("decision"), "name": "onboard-decision"}) == []
    profile = operator.cypher("MATCH (r:ProcessProfile {name: 'onboard-run'}) RETURN r.host AS host, "
                              "r.rss_mb_last AS rss, r.end_time AS ended")
    assert profile == [{"host": "onboard", "rss": 1.0, "ended": None}]
    platforms = {r["platform"]: r for r in operator.query("platforms", {})}
    assert platforms["onboard"]["online"] is True  # the forged platform_online never reached it


def test_implausible_figures_are_refused_naming_the_field(session_as):
    onboard = KnowledgeClient(session_as(f"{ROBOT}-onboard"), ROBOT, timeout=3.0, host="onboard")
    operator = KnowledgeClient(session_as(OPERATOR), ROBOT, timeout=3.0)
    assert onboard.write("process_start", {**write_params("process_start"), "run_id": "plausible-run",
                                           "host": "onboard"}) == []
    for client, verb, params, field in [
        (onboard, "platform", {"name": "onboard", "time": 3.0, "memory_free_mb": 1e12}, "memory_free_mb"),
        (onboard, "platform", {"name": "onboard", "time": 3.0, "memory_free_mb": -100000.0}, "memory_free_mb"),
        (onboard, "platform", {"name": "onboard", "time": 3.0, "memory_total_mb": 700.0, "memory_free_mb": 800.0},
         "memory_free_mb"),
        (onboard, "platform", {"name": "onboard", "time": 3.0, "cpu_load": -1.0}, "cpu_load"),
        (onboard, "process_sample", {**write_params("process_sample"), "run_id": "plausible-run",
                                     "rss_mb_last": 1e12}, "rss_mb_last"),
        (onboard, "flight_state", {**write_params("flight_state"), "battery_pct": 250.0}, "battery_pct"),
        (operator, "calibration", {**write_params("calibration"), "detection_rate": 1.5}, "detection_rate"),
        (operator, "platform", {"name": "forged_host", "time": 3.0, "memory_free_mb": 1e12}, "memory_free_mb"),
    ]:
        with pytest.raises(RemoteError, match=field):
            client.write(verb, params)
    rows = operator.cypher("MATCH (p:Platform) WHERE p.memory_free_mb > 1e9 OR p.memory_free_mb < 0 "
                           "RETURN p.name AS name")
    assert rows == []


# -- detectors: their own identity, none of their host's rights -----------------------------------------


def test_a_detector_runs_with_its_own_identity(network, session_as):
    operator_session = session_as(OPERATOR)
    operator = DeployerClient(operator_session, ROBOT, timeout=3.0, start_timeout=30.0)
    alive: list[str] = []
    tokens = operator_session.liveliness().declare_subscriber(keys.detector_alive(ROBOT, "*"),
                                                             lambda s: alive.append(str(s.key_expr)))
    try:
        # Ready means it read its configuration from the knowledge service through the router.
        info = operator.start("onboard", "detector_dusk", "marker_detection_dusk", instance="own_identity")
        try:
            assert info.state == "ready"
            if info.via == "exec":  # a forked or pooled detector's /proc environ is the launcher's (test_launcher)
                environ = Path(f"/proc/{info['pid']}/environ").read_bytes().split(b"\0")
                assert f"KGADAPT_ZENOH_CONFIG={network.detector_config}".encode() in environ
            wait_for(lambda: keys.detector_alive(ROBOT, "own_identity") in alive, 5, "the detector's token")
            # Its reconfiguration queryable, declared with its own identity, answers the operator.
            configure = keys.detector_configure(ROBOT, "onboard", "own_identity")
            assert len(reply_payloads(operator_session, configure, b"not a request")) == 1
            # Its idle/active switch (the warm standby's): the manager's identity may, the remote host's may not.
            assert set_active(session_as(f"{ROBOT}-onboard"), ROBOT, "onboard", "own_identity", False,
                              timeout=5.0).active is False
            with pytest.raises(RequestTimeout):
                set_active(session_as(f"{ROBOT}-remote"), ROBOT, "onboard", "own_identity", True, timeout=1.0)
        finally:
            operator.stop("onboard", "own_identity")
    finally:
        tokens.undeclare()


def test_a_detectors_certificate_cannot_start_write_or_speak_for_its_host(session_as):
    detector = session_as(f"{ROBOT}-onboard-detector")
    watcher = session_as(OPERATOR)
    seen: list[tuple[str, bytes]] = []
    alive: list[str] = []
    subscriber = watcher.declare_subscriber(f"kgadapt/{ROBOT}/**",
                                            lambda s: seen.append((str(s.key_expr), s.payload.to_bytes())))
    tokens = watcher.liveliness().declare_subscriber(f"kgadapt/{ROBOT}/**", lambda s: alive.append(str(s.key_expr)))
    host_token = detector.liveliness().declare_token(keys.host_alive(ROBOT, "detector_ghost"))
    other_side = detector.declare_queryable(keys.detector_configure(ROBOT, "remote", "forged"),
                                            lambda q: q.reply(q.key_expr, b"forged"))
    deny = dict(timeout=1.0)
    try:
        # What it may: its configuration, its detections, its liveliness.
        rows = KnowledgeClient(detector, ROBOT, timeout=3.0, own=True).query(
            "detector_config", {"config": "marker_detection_day"})
        assert rows and rows[0]["config"] == "marker_detection_day"
        own = keys.detector_markers(ROBOT, "det_a")
        wait_for(lambda: (detector.put(own, b"detections"), any(k == own for k, _ in seen))[1], 5,
                 "the detector's own detections")
        token = detector.liveliness().declare_token(keys.detector_alive(ROBOT, "det_a"))
        wait_for(lambda: keys.detector_alive(ROBOT, "det_a") in alive, 5, "the detector's own token")
        token.undeclare()
        # What it may not: nothing answers, nothing is delivered.
        status = messages.encode("host_status", {"host": "onboard", "time": 1.0, "memory_total_mb": 700.0,
                                                 "memory_free_mb": 0.0, "cpu_load": 0.0})
        detector.put(keys.host_status(ROBOT, "onboard"), status)
        detector.put(keys.flight_state(ROBOT), messages.encode("flight_state", {
            "time": 1.0, "link": True, "landed_state": "LANDING"}))
        detector.put(keys.adaptation_events(ROBOT), b"forged")
        deployer = DeployerClient(detector, ROBOT, **deny)
        outcomes = concurrently({
            "start": lambda: deployer.start("onboard", "detector_day", "marker_detection_day", instance="by_det",
                                            wait_ready=False),
            "squeeze": lambda: squeeze(detector, ROBOT, "onboard", 600.0, timeout=1.0),
            "own write": lambda: KnowledgeClient(detector, ROBOT, host="onboard", **deny).write(
                "platform_online", {"name": "onboard", "online": False, "time": 9.0}),
            "robot-wide write": lambda: KnowledgeClient(detector, ROBOT, **deny).write(
                "decision", write_params("decision")),
            "cypher": lambda: KnowledgeClient(detector, ROBOT, **deny).cypher("RETURN 1 AS one"),
        })
        assert {what: dropped_kind(outcome) for what, outcome in outcomes.items()} == dict.fromkeys(outcomes, RequestTimeout)
        forged_configure = reply_payloads(watcher, keys.detector_configure(ROBOT, "remote", "forged"))
        wait_for(lambda: (watcher.put(keys.adaptation_events(ROBOT), b"marker"),
                          any(p == b"marker" for _, p in seen))[1], 5, "the watcher's own put to come back")
    finally:
        for entity in (subscriber, tokens, host_token, other_side):
            entity.undeclare()
    assert (keys.host_status(ROBOT, "onboard"), status) not in seen
    assert keys.flight_state(ROBOT) not in {k for k, _ in seen}
    assert (keys.adaptation_events(ROBOT), b"forged") not in seen
    assert b"forged" not in forged_configure
    assert keys.host_alive(ROBOT, "detector_ghost") not in alive
    assert "by_det" not in {p.instance for p in DeployerClient(watcher, ROBOT, timeout=3.0).processes("onboard")}
