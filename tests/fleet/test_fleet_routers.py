"""Two robots, each with its own router on the shipped configuration, in separate network namespaces.

quad1's and quad2's knowledge services (``kgadapt knowledge serve``, the
routers) run in namespaces of their own, with TLS and access control from
deploy/zenoh/router.json5 (quad2's is the same file with the robot names
swapped, as its comment says to do); quad2's router dials quad1's. From
quad2's namespace, as quad2's operator and quad2's onboard software (Zenoh
clients of quad2's router): a fleet question reaches both robots through the
router-to-router link, while every attempt to write quad1's knowledge, to
reach its Cypher or its deployer, gets nothing.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from kgadapt.bench.fleet_bench import seed_robot
from kgadapt.knowledge.store import open_store
from tests.conftest import REPO
from tests.support import Child, host_network

ZENOH_DIR = REPO / "deploy" / "zenoh"
SHIPPED_TLS_DIR = "/etc/kgadapt/tls"
PORT = 7447

_PROBE = r"""
import json, sys, time
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.fleet import FleetClient, FleetSettings
from kgadapt.shared import messages
from kgadapt.shared.errors import RequestTimeout
from kgadapt.shared.session import ZenohSettings, open_session
operator_cfg, onboard_cfg = sys.argv[1], sys.argv[2]
out = {}
operator = open_session(ZenohSettings(config_file=operator_cfg))
fleet = FleetClient(operator, FleetSettings(timeout=3.0, expect=("quad1", "quad2", "quad3"), discover_hosts=False))
deadline = time.monotonic() + 15
while True:  # the routers' link and declarations take a moment after start
    answer = fleet.ask("current_placement")
    if {"quad1", "quad2"} <= set(answer.answered) or time.monotonic() > deadline:
        break
out["fleet"] = answer.as_json()
# The roll calls crossed the router link too: quad2's roster remembers quad1 (heard on the fleet keys only).
own = KnowledgeClient(operator, "quad2", timeout=3.0)
deadline = time.monotonic() + 20
while True:
    roster = {r["robot"]: r["heard"] for r in own.query("fleet_roster")}
    if "quad1" in roster or time.monotonic() > deadline:
        break
    time.sleep(0.5)
out["roster_quad2"] = roster
from kgadapt.operator.fleet_view import FleetView, FleetViewSettings, as_json
with FleetView(operator, FleetViewSettings(timeout=3.0)) as view:  # its subscriptions are denied: it asks
    out["view"] = as_json(view.snapshot())
def refused(call):
    try:
        call()
    except RequestTimeout:
        return True
    return False
decision = {"name": "forged", "time": 1.0, "trigger": "forged", "config": "marker_detection_dark", "host": "remote"}
onboard = open_session(ZenohSettings(config_file=onboard_cfg))
out["write_as_quad2_onboard"] = refused(lambda: KnowledgeClient(onboard, "quad1", timeout=1.5).write("decision", decision))
out["write_as_quad2_operator"] = refused(lambda: KnowledgeClient(operator, "quad1", timeout=1.5).write("decision", decision))
out["cypher_of_quad1"] = refused(
    lambda: KnowledgeClient(operator, "quad1", timeout=1.5).cypher("MATCH (n) RETURN count(n) AS n"))
payload = messages.encode("write_request", {"params": decision})
out["wildcard_write_replies"] = [
    r.ok is not None for r in operator.get("kgadapt/*/knowledge/write/decision", payload=payload, timeout=1.5)]
out["deployer_replies"] = [
    r.ok is not None for r in operator.get("kgadapt/quad1/host/*/deployer/list",
                                           payload=messages.encode("deploy_request", {}), timeout=1.5)]
out["own_write"] = not refused(
    lambda: KnowledgeClient(operator, "quad2", timeout=3).write("decision", {**decision, "name": "quad2-own"}))
print(json.dumps(out), flush=True)
"""


def config_for(robot: str, name: str, tls: Path, out: Path, **changes: object) -> Path:
    """A shipped configuration written for ``robot`` (names swapped), its TLS files in ``tls``, plus ``changes``."""
    import zenoh

    text = (ZENOH_DIR / name).read_text().replace(SHIPPED_TLS_DIR, str(tls))
    if robot != "quad1":  # the file is written for quad1, with quad2 among the others: swap them
        text = text.replace("quad1", "@@").replace(robot, "quad1").replace("@@", robot)
    source = out / f"{robot}-{len(list(out.iterdir()))}-{name}"
    source.write_text(text)
    config = zenoh.Config.from_file(str(source))
    for key, value in {"scouting/delay": 0, **changes}.items():
        config.insert_json5(key, json.dumps(value))
    path = source.with_suffix(".json")
    path.write_text(str(config))
    return path


@pytest.fixture
def network():
    with host_network(("quad1", "quad2"), "10.213.19") as net:
        yield net


def kgadapt(*args: str) -> None:
    done = subprocess.run([sys.executable, "-m", "kgadapt", *args], capture_output=True, text=True, cwd=REPO,
                          timeout=60)
    assert done.returncode == 0, done.stderr


def test_a_fleet_question_crosses_the_router_link_and_nothing_writes_the_other_robot(network, tmp_path):
    tls, work = tmp_path / "tls", tmp_path / "work"
    work.mkdir()
    addr = {robot: network.address(robot) for robot in ("quad1", "quad2")}
    kgadapt("certs", str(tls), "--robot", "quad1", "--router-address", addr["quad1"])
    kgadapt("certs", str(tls), "--robot", "quad2", "--router-address", addr["quad2"], "--use-ca")
    stores = {}
    for i, robot in enumerate(("quad1", "quad2")):
        stores[robot] = f"embedded:{tmp_path / robot}"
        store = open_store(stores[robot])
        store.setup()
        try:
            seed_robot(store, robot, i)
        finally:
            store.shutdown()
    routers = {}
    for robot, dial in (("quad1", []), ("quad2", [f"tls/{addr['quad1']}:{PORT}"])):
        config = config_for(robot, "router.json5", tls, work, **{
            "listen/endpoints": [f"tls/{addr[robot]}:{PORT}"], "connect/endpoints": dial})
        argv = network.run_in(robot, [sys.executable, "-m", "kgadapt", "--log-level", "INFO", "knowledge", "serve",
                                      "--robot", robot, "--store", stores[robot], "--zenoh-config", str(config)])
        routers[robot] = Child(argv, f"serve-{robot}", work)
    try:
        for child in routers.values():
            child.wait_ready()

        def client(cn: str) -> Path:
            return config_for("quad2", "onboard.json5", tls, work, **{
                "connect/endpoints": [f"tls/{addr['quad2']}:{PORT}"],
                "transport/link/tls/connect_certificate": str(tls / f"{cn}.pem"),
                "transport/link/tls/connect_private_key": str(tls / f"{cn}-key.pem")})

        probe = subprocess.run(
            network.run_in("quad2", [sys.executable, "-c", _PROBE, str(client("quad2-operator")),
                                     str(client("quad2-onboard"))]),
            capture_output=True, text=True, cwd=REPO, timeout=90, env={**os.environ, "PYTHONPATH": str(REPO)})
        assert probe.returncode == 0, probe.stderr
        out = json.loads(probe.stdout.strip().splitlines()[-1])
    finally:
        for child in routers.values():
            child.stop()
    fleet = out["fleet"]
    by_robot = {r["robot"]: r for r in fleet["rows"]}
    assert set(by_robot) == {"quad1", "quad2"}, fleet  # quad1 answered through quad2's router and the link
    assert by_robot["quad1"]["config"] == "marker_detection_day" and by_robot["quad2"]["config"] == "marker_detection_dusk"
    assert fleet["silent"] == ["quad3"]  # expected, not on the network: listed, not left out
    assert out["roster_quad2"] == {"quad2": "self", "quad1": out["roster_quad2"].get("quad1")}
    assert out["roster_quad2"]["quad1"] in ("answer", "announce")  # the roll calls crossed on the shipped ACL
    view = {r["robot"]: r for r in out["view"]}
    assert set(view) == {"quad1", "quad2"} and all(r["answering"] for r in view.values())
    assert (view["quad1"]["config"], view["quad1"]["band"]) == ("marker_detection_day", "day")
    assert view["quad1"]["hosts_online"] == []  # seeded online, but quad1's service marked them offline at start
    assert out["write_as_quad2_onboard"] and out["write_as_quad2_operator"] and out["cypher_of_quad1"]
    assert out["wildcard_write_replies"] == []  # a wildcard write reaches no robot, not even quad2's own
    assert out["deployer_replies"] == []
    assert out["own_write"]  # the refusals above are the ACL's doing: writes to one's own robot work
    store = open_store(stores["quad1"])
    store.setup()
    try:
        decisions = store.execute("MATCH (a:AdaptationDecision) RETURN a.name AS name", read_only=True)
    finally:
        store.shutdown()
    assert [d["name"] for d in decisions] == ["quad1-decision-1"]  # nothing forged reached quad1's graph


def test_the_shipped_router_opens_only_named_queries_to_the_fleet():
    import zenoh

    acl = json.loads(zenoh.Config.from_file(str(ZENOH_DIR / "router.json5")).get_json("access_control"))
    rules = {r["id"]: r for r in acl["rules"]}
    others = next(p for p in acl["policies"] if "other-robots" in p["subjects"])
    for rule_id in others["rules"]:
        rule = rules[rule_id]
        assert rule["permission"] == "allow"
        assert set(rule["messages"]) <= {"query", "reply", "declare_queryable"}, rule_id
        for key in rule["key_exprs"]:
            assert key.endswith("/knowledge/query/*") or key == "kgadapt/quad1/knowledge/cypher", (rule_id, key)
    # Nobody else may declare a queryable in this robot's namespace (it could answer our own questions).
    for rule_id in others["rules"]:
        rule = rules[rule_id]
        if "declare_queryable" in rule["messages"] and "ingress" in rule["flows"]:
            assert not any(k.startswith("kgadapt/quad1/") or k.startswith("kgadapt/*") for k in rule["key_exprs"])
