"""Limits that hold for those the router lets in, on the deployed configuration.

The robot as shipped (``conftest.Network``): ``kgadapt knowledge serve`` on
the shipped router configuration over the shipped models, the onboard agent
with a 700 MiB budget on the shipped onboard configuration, its detectors with
their own certificate, every certificate made by ``kgadapt certs``.

- The deployer's own checks, met by this robot's operator (whom access control
  lets command deployers): the memory budget under raced starts, names that
  try to leave their key chunk, fields that say how to run, wildcard keys,
  deployments the graph does not know. Deployer requests are sent as an
  outsider would, msgpack from docs/CONTRACTS.md.
- Per-identity scoping seen from the receiving side: what the remote agent's
  certificate writes for the onboard host and what a detector's certificate
  puts as a host status or a flight state never reaches the graph or the
  onboard agent's identity, while the same from the entitled identity does.
"""

from __future__ import annotations

import re
from typing import Any

import msgpack
import psutil
import pytest

from kgadapt.deploy.client import DeployerClient
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.shared import keys, messages
from kgadapt.shared.errors import DeploymentError, RemoteError, RequestTimeout
from kgadapt.shared.states import LIVE_STATES
from tests.security.conftest import OTHER_ROBOT, ROBOT, dropped_kind, wait_for
from tests.security.test_access import OPERATOR, concurrently, write_params

DARK = "marker_detection_dark"
BUDGET_MB = 700.0  # the onboard agent's --memory-budget in Network


def deployer_request(session: Any, key: str, body: dict[str, Any]) -> tuple[str, Any]:
    """("ok", the deploy_reply map) or ("err", the error text) or ("none", None), as an outsider reads them."""
    payload = msgpack.packb({"kind": "deploy_request", "v": 1, **body})
    for reply in session.get(key, payload=payload, timeout=5):
        if reply.ok is not None:
            return "ok", msgpack.unpackb(reply.ok.payload.to_bytes(), raw=False)
        return "err", reply.err.payload.to_bytes().decode("utf-8", "replace")
    return "none", None


def live_instances(deployers: DeployerClient) -> dict[str, str]:
    return {p.instance: p.config for p in deployers.processes("onboard") if p.state in LIVE_STATES}


# -- item: the memory budget ---------------------------------------------------------------------------


def test_three_concurrent_starts_over_the_budget_as_the_operator_pass_only_as_far_as_the_budget_holds(session_as):
    operator_session = session_as(OPERATOR)
    deployers = DeployerClient(operator_session, ROBOT, timeout=10.0, start_timeout=30.0)
    knowledge = KnowledgeClient(operator_session, ROBOT, timeout=3.0, own=True)
    demand = knowledge.query("detector_config", {"config": DARK})[0]["memory_demand_mb"]
    assert 3 * demand > BUDGET_MB  # three of them would not fit: 3 x 324 MiB on 700 MiB
    before = live_instances(deployers)
    outcomes = concurrently({f"dark{i}": (lambda i=i: deployers.start(
        "onboard", "detector_dark", DARK, instance=f"dark{i}", wait_ready=False)) for i in range(3)})
    started = [name for name, outcome in outcomes.items() if isinstance(outcome, messages.DeployDetail)]
    try:
        refused = [str(outcome) for outcome in outcomes.values() if isinstance(outcome, DeploymentError)]
        assert len(started) + len(refused) == 3, outcomes
        assert started, outcomes  # what fits still starts: the checks refuse by the figures
        # Before: all three were accepted, 972 MiB declared on a 700 MiB budget.
        assert len(started) * demand <= BUDGET_MB, outcomes
        for text in refused:  # each refusal names the figures it was refused by
            assert re.search(rf"start of {DARK} refused: it (declares|needs) {demand:.0f} MiB", text), text
            assert re.search(r"memory budget of 700 MiB|\d+ MiB free within its memory budget", text), text
        live = live_instances(deployers)
        assert not set(live) & set(outcomes) - set(started)  # a refused start left nothing running
        assert sum(demand for config in live.values() if config == DARK) <= BUDGET_MB
    finally:
        for name in started:
            deployers.stop("onboard", name)
    assert live_instances(deployers) == before


# -- item: the deployer's own checks, as the operator ---------------------------------------------------


def test_the_deployers_own_checks_hold_for_the_operator_on_the_deployed_configuration(network, session_as):
    operator = session_as(OPERATOR)
    start_key = keys.deployer_verb(ROBOT, "onboard", "start")
    marker = network.work / "deployer-pwned"
    good = {"deployment": "detector_day", "config": "marker_detection_day", "wait_ready": False}

    def refused(key: str, body: dict[str, Any], reason: str) -> None:
        kind, answer = deployer_request(operator, key, body)
        text = answer if kind == "err" else (answer or {}).get("detail", {}).get("error", "")
        assert kind == "err" or (kind == "ok" and answer["ok"] is False), (body, kind, answer)
        assert re.search(reason, text), (body, text)

    # Names that try to leave their key chunk or the deployments directory.
    for field, value in [("deployment", "../../../bin/sh"), ("deployment", "detector_day/../../x"),
                         ("config", "../marker_detection_day"), ("config", ".."), ("instance", "../../tmp/x"),
                         ("instance", "a/b"), ("deployment", "detector_day\x00")]:
        refused(start_key, {**good, field: value}, re.escape(repr(value)))
    refused(keys.deployer_verb(ROBOT, "onboard", "stop"), {"instance": "../x"}, re.escape(repr("../x")))
    refused(keys.deployer_verb(ROBOT, "onboard", "status"), {"instance": "*"}, re.escape(repr("*")))
    # Fields that would say how to run: refused, naming the field.
    for field, value in [("command", f"touch {marker}"), ("executable", "/bin/sh"),
                         ("arguments", ["-c", f"touch {marker}"]), ("environment", [f"LD_PRELOAD={marker}"]),
                         ("cwd", "/"), ("argv", ["/bin/sh"])]:
        refused(start_key, {**good, field: value}, f"{field!r} not accepted")
    # Wildcard keys: a change names exactly one host. As deployed, the router already drops them (the
    # onboard identity serves only its own host/onboard/**, which a wider key is not included in); where
    # a wildcard does reach a deployer (the open set-up, test_host_protection.py) it refuses it itself.
    for key in (f"kgadapt/{ROBOT}/host/*/deployer/start", f"kgadapt/{ROBOT}/host/**/start",
                f"kgadapt/{ROBOT}/host/$*board/deployer/start", f"kgadapt/{ROBOT}/host/*/deployer/stop"):
        kind, answer = deployer_request(operator, key, good if key.endswith("start") else {"instance": "x"})
        assert kind == "none" or (kind == "err" and "exactly one host" in answer), (key, kind, answer)
    # Deployments the graph does not know, or not for this host or configuration.
    refused(start_key, {**good, "deployment": "no_such_deployment"}, "'no_such_deployment' is not in the knowledge store")
    refused(start_key, {**good, "deployment": "detector_hd", "config": "marker_detection_hd"},
            r"not executable on host onboard \(only on remote\)")
    refused(start_key, {**good, "config": "marker_detection_dark"}, "does not deploy configuration marker_detection_dark")
    # Nothing ran, and the same deployer starts what is allowed for the same operator.
    deployers = DeployerClient(operator, ROBOT, timeout=5.0, start_timeout=30.0)
    assert live_instances(deployers) == {}
    assert not marker.exists()
    kind, answer = deployer_request(operator, start_key, {**good, "instance": "allowed"})
    assert kind == "ok" and answer["ok"] is True, answer
    deployers.stop("onboard", "allowed")


# -- item: per-identity scoping, seen by the receivers ---------------------------------------------------


def _graph_of_onboard(operator: KnowledgeClient) -> dict[str, Any]:
    """What the forged writes would change: onboard's online state and figures, profiles, decisions, flight."""
    platform = operator.cypher("MATCH (p:Platform {name: 'onboard'}) RETURN p.online AS online, "
                               "p.cpu_cores AS cores")
    names = operator.cypher("MATCH (n) WHERE (n:ProcessProfile OR n:AdaptationDecision) AND (n.name ENDS WITH "
                            "'-onboard' OR n.name ENDS WITH '-remote') RETURN n.name AS name")
    flight = operator.cypher("MATCH (c:FlightControl) RETURN c.mode AS mode")
    return {"platform": platform, "names": sorted(r["name"] for r in names), "flight": flight}


def test_the_remote_agents_certificate_cannot_write_for_the_onboard_host_as_the_graph_sees_it(session_as):
    remote_session = session_as(f"{ROBOT}-remote")
    operator = KnowledgeClient(session_as(OPERATOR), ROBOT, timeout=3.0)
    forged = {
        "platform": {"name": "onboard", "time": 9.0, "memory_total_mb": 700.0, "memory_free_mb": 1.0, "cpu_cores": 77},
        "platform_online": {"name": "onboard", "online": False, "time": 9.0},
        "process_start": {**write_params("process_start"), "run_id": "forged-by-remote", "host": "onboard"},
        "decision": {**write_params("decision"), "name": "forged-by-remote", "host": "onboard"},
        "flight_state": {**write_params("flight_state"), "mode": "FORGED_BY_REMOTE"},
    }
    # Online (liveliness, at once) and its first status written (batched): the agent's own figures, this
    # machine's cores, replace the model's; only then does nothing but a forged write change the graph.
    wait_for(lambda: (_graph_of_onboard(operator)["platform"] or [{}])[0] == {"online": True,
                                                                             "cores": psutil.cpu_count()}, 10,
             "the onboard host online in the graph, with its own status's figures")
    before = _graph_of_onboard(operator)
    # On the onboard host's write key: dropped by the router (asked all at once: each waits its timeout).
    on_onboard_key = KnowledgeClient(remote_session, ROBOT, timeout=1.0, host="onboard")
    outcomes = concurrently({verb: (lambda v=verb: on_onboard_key.write(v, forged[v])) for verb in forged})
    assert {verb: dropped_kind(o) for verb, o in outcomes.items()} == dict.fromkeys(forged, RequestTimeout)
    # On its own key: the service refuses everything about the onboard host.
    own_key = KnowledgeClient(remote_session, ROBOT, timeout=3.0, host="remote")
    for verb, params in forged.items():
        with pytest.raises(RemoteError):
            own_key.write(verb, params)
    assert _graph_of_onboard(operator) == before
    # The same writes from the onboard host's own certificate are taken: the graph would have shown them.
    onboard = KnowledgeClient(session_as(f"{ROBOT}-onboard"), ROBOT, timeout=3.0, host="onboard")
    onboard.write("process_start", {**forged["process_start"], "run_id": "by-onboard"})
    onboard.write("decision", {**forged["decision"], "name": "by-onboard"})
    assert {"by-onboard"} <= set(_graph_of_onboard(operator)["names"])


def test_a_detectors_certificate_cannot_put_a_status_or_a_flight_state_as_their_receivers_see_it(session_as):
    detector = session_as(f"{ROBOT}-onboard-detector")
    operator_session = session_as(OPERATOR)
    operator = KnowledgeClient(operator_session, ROBOT, timeout=3.0)
    # The flight state's receiver: the onboard agent's identity (its adaptation manager listens with it).
    onboard = session_as(f"{ROBOT}-onboard")
    heard: list[bytes] = []
    subscriber = onboard.declare_subscriber(keys.flight_state(ROBOT), lambda s: heard.append(s.payload.to_bytes()))
    # The status's receiver: the knowledge service. A status carrying cpu_cores leaves them on the platform
    # until another status carries them, so a forged one would leave a trace the later ones cannot hide.
    status = {"host": "remote", "time": 1.0, "memory_total_mb": 4096.0, "memory_free_mb": 2000.0, "cpu_load": 0.0}
    forged_status = messages.encode("host_status", {**status, "cpu_cores": 77})
    forged_flight = messages.encode("flight_state", {"time": 1.0, "link": True, "mode": "FORGED_BY_DETECTOR"})
    control_flight = messages.encode("flight_state", {"time": 1.0, "link": True, "mode": "BY_OPERATOR"})
    remote_row = lambda: next(iter(operator.cypher(  # noqa: E731
        "MATCH (p:Platform {name: 'remote'}) RETURN p.memory_free_mb AS free, p.cpu_cores AS cores")), {})
    try:
        # The route from the operator to the onboard agent's new subscription first: a put made before the
        # router knows the subscription reaches no one, and would be counted as lost below.
        def operator_heard() -> bool:
            operator_session.put(keys.flight_state(ROBOT), control_flight)
            return control_flight in heard

        wait_for(operator_heard, 5, "a route from the operator's flight state to the onboard agent")
        heard.clear()
        for free in (2100.0, 2200.0, 2300.0):  # each beyond the service's deadband (16 MiB): written at once
            # Forged first, then the entitled sender's; each control waited for where it is received.
            detector.put(keys.host_status(ROBOT, "remote"), forged_status)
            detector.put(keys.flight_state(ROBOT), forged_flight)
            operator_session.put(keys.host_status(ROBOT, "remote"),
                                 messages.encode("host_status", {**status, "memory_free_mb": free}))
            operator_session.put(keys.flight_state(ROBOT), control_flight)
            wait_for(lambda f=free: remote_row().get("free") == f, 5, f"the operator's status ({free} MiB free)")
        wait_for(lambda: heard.count(control_flight) >= 3, 5, "the operator's flight states at the onboard agent")
        assert remote_row().get("cores") != 77  # no forged status was ever applied (the model says 8)
        assert forged_flight not in heard
        # The same status from the operator leaves exactly that trace.
        operator_session.put(keys.host_status(ROBOT, "remote"), forged_status)
        wait_for(lambda: remote_row().get("cores") == 77, 5, "the operator's status with cpu_cores")
    finally:
        subscriber.undeclare()


# -- calibration figures: the operator's (and the service's) to write, nobody else's ------------------------


def test_only_the_operator_writes_calibration_figures_on_the_shipped_configuration(session_as):
    """Calibration ranks the detector configurations, so a forged figure would misplace the detector. The
    calibration command writes into the store on the knowledge host; over Zenoh only the operator's
    certificate (and the service's own) may write them, on the robot-wide key: every host's, every
    detector's and another robot's certificate is dropped by the router there and refused by the service on
    its host's own key, whatever the source it names."""
    operator = KnowledgeClient(session_as(OPERATOR), ROBOT, timeout=3.0)
    figures = {**write_params("calibration"), "detection_rate": 0.01, "source": "forged"}
    count = "MATCH ()-[c:CALIBRATED {source: $source}]->() RETURN count(c) AS n"
    attempts: dict[str, Any] = {}
    for cn, host in [(f"{ROBOT}-onboard", "onboard"), (f"{ROBOT}-remote", "remote"),
                     (f"{ROBOT}-onboard-detector", "onboard"), (f"{ROBOT}-remote-detector", "remote"),
                     (f"{OTHER_ROBOT}-onboard", "onboard")]:
        session = session_as(cn)
        for source in ("forged", "synthetic"):
            params = {**figures, "source": source}
            attempts[f"{cn} robot-wide {source}"] = (lambda s=session, p=params: KnowledgeClient(
                s, ROBOT, timeout=1.0).write("calibration", p))
            attempts[f"{cn} on {host}'s key {source}"] = (lambda s=session, h=host, p=params: KnowledgeClient(
                s, ROBOT, timeout=1.0, host=h).write("calibration", p))
    synthetic_before = operator.cypher(
        "MATCH (g)-[c:CALIBRATED {source: 'synthetic'}]->(b) RETURN g.name AS g, b.name AS b, "
        "c.detection_rate AS rate ORDER BY g, b")
    outcomes = concurrently(attempts)  # a dropped request waits its timeout: all at once
    for what, outcome in outcomes.items():
        if "key" in what and ("-onboard on onboard" in what or "-remote on remote" in what) \
                and "detector" not in what and OTHER_ROBOT not in what:
            # The host's own key reaches the service, which refuses calibration there, naming why.
            assert isinstance(outcome, RemoteError) and "no host's to write" in str(outcome), (what, outcome)
        else:
            assert isinstance(outcome, RequestTimeout), (what, outcome)  # dropped at the router
    assert operator.cypher(count, {"source": "forged"}) == [{"n": 0}]
    assert operator.cypher(
        "MATCH (g)-[c:CALIBRATED {source: 'synthetic'}]->(b) RETURN g.name AS g, b.name AS b, "
        "c.detection_rate AS rate ORDER BY g, b") == synthetic_before
    # The operator's own write is taken: the refusals above are the identities', not a broken verb.
    assert operator.write("calibration", {**figures, "source": "by-operator"}) == []
    assert operator.cypher(count, {"source": "by-operator"}) == [{"n": 1}]
