"""The shipped Zenoh configurations: they load, and their TLS and access control do what they say.

The second part runs the real thing with throwaway certificates: the router
configuration with the knowledge service in it, the onboard host's
configuration for a deployer and the detector it starts, and sessions with
the certificates of an operator, another robot, a stranger of the same CA
and someone from another CA.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
import zenoh

from kgadapt.deploy.client import DeployerClient
from kgadapt.deploy.deployer import Deployer, DeployerSettings
from kgadapt.knowledge import schema as S
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.shared.errors import RequestTimeout, TransportError
from kgadapt.shared.session import HOST_LEASE_MS, ROUTER_LEASE_MS, ZenohSettings, build_config, open_session
from tests.conftest import free_port
from tests.deploy.conftest import CONFIG, FAST_OPEN, add_deployment
from tests.deploy.pki import TestCA

ZENOH_DIR = Path(__file__).resolve().parents[2] / "deploy" / "zenoh"
SHIPPED = sorted(ZENOH_DIR.glob("*.json5"))
ROBOT = "quad1"  # the robot the shipped configurations are written for


def test_the_router_and_both_host_configurations_are_shipped():
    assert {p.name for p in SHIPPED} >= {"router.json5", "onboard.json5", "remote.json5"}


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_each_shipped_configuration_loads_with_tls_and_the_lease_of_its_kind(path):
    # Hosts 1 s: the router drops a host's link after the host's lease. The router's own is longer
    # (fewer keep-alives on every host link) and is what session.py gives a router whose file sets none.
    config = zenoh.Config.from_file(str(path))
    tls = json.loads(config.get_json("transport/link/tls"))
    assert tls["enable_mtls"] is True and tls["root_ca_certificate"]
    lease = json.loads(config.get_json("transport/link/tx/lease"))
    assert lease == (ROUTER_LEASE_MS if path.name == "router.json5" else HOST_LEASE_MS)
    assert json.loads(build_config(ZenohSettings(config_file=str(path))).get_json("transport/link/tx/lease")) == lease
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    endpoints = json.loads(config.get_json("listen/endpoints" if path.name == "router.json5" else "connect/endpoints"))
    assert endpoints and all(e.startswith("tls/") for e in endpoints)


def test_the_router_configuration_denies_by_default_and_keeps_writes_to_this_robot():
    acl = json.loads(zenoh.Config.from_file(str(ZENOH_DIR / "router.json5")).get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    read_only = rules["knowledge-read-only"]
    assert set(read_only["messages"]) == {"query", "reply"}
    assert not any("write" in k or "deployer" in k for k in read_only["key_exprs"])


def config_file(tmp: Path, name: str, **changes: object) -> str:
    """A shipped configuration with some keys changed, written as JSON for a session or a child."""
    config = zenoh.Config.from_file(str(ZENOH_DIR / name))
    for key, value in changes.items():
        config.insert_json5(key.replace(".", "/"), json.dumps(value))
    path = tmp / f"{name}-{len(list(tmp.iterdir()))}.json"
    path.write_text(str(config))
    return str(path)


@pytest.fixture
def secured(tmp_path, resp_store):
    """Router + knowledge service + onboard deployer, all on the shipped configurations with test certificates."""
    ca = TestCA(tmp_path / "ca")
    port = free_port()
    endpoint = f"tls/localhost:{port}"
    S.ensure_indexes(resp_store)
    add_deployment(resp_store, "echo", platforms=["onboard"], deploys=[CONFIG])

    def client_config(cn: str, *, authority: TestCA = ca, **changes: object) -> str:
        cert, key = authority.issue(cn)
        return config_file(tmp_path, "onboard.json5", **{
            "connect.endpoints": [endpoint], "transport.link.tls.root_ca_certificate": str(ca.path),
            "transport.link.tls.connect_certificate": str(cert), "transport.link.tls.connect_private_key": str(key),
            **changes})

    router_cert, router_key = ca.issue("quad1-knowledge")
    router_config = config_file(tmp_path, "router.json5", **{
        "listen.endpoints": [f"tls/127.0.0.1:{port}"], "transport.link.tls.root_ca_certificate": str(ca.path),
        "transport.link.tls.listen_certificate": str(router_cert), "transport.link.tls.listen_private_key": str(router_key)})
    router = open_session(ZenohSettings(config_file=router_config, extra=FAST_OPEN))
    service = KnowledgeService(resp_store, ServiceSettings(robot=ROBOT))
    service.setup(router)
    onboard_config = client_config("quad1-onboard")
    agent = open_session(ZenohSettings(config_file=onboard_config, extra=FAST_OPEN))
    deployer = Deployer(DeployerSettings(robot=ROBOT, host="onboard", connect=endpoint, zenoh_config=onboard_config,
                                         ready_timeout=10.0, sample_interval=0.2))
    deployer.setup(agent)
    opened = []

    def session_as(cn: str, **kw: object):
        session = open_session(ZenohSettings(config_file=client_config(cn, **kw), extra=FAST_OPEN))
        opened.append(session)
        return session

    yield session_as
    for session in opened:
        session.close()
    deployer.shutdown()
    agent.close()
    service.shutdown()
    router.close()


def test_this_robots_operator_starts_a_detector_that_itself_connects_over_tls(secured):
    operator = secured("quad1-operator")
    client = DeployerClient(operator, ROBOT, timeout=3.0)
    info = client.start("onboard", "echo", CONFIG, instance="secure1")
    assert info.state == "ready"  # the echo detector opened its session with the host's certificate
    assert client.stop("onboard", "secure1").state == "stopped"


def test_another_robot_may_ask_named_queries_but_cannot_start_a_process_or_write(secured):
    other = secured("quad2-onboard")
    knowledge = KnowledgeClient(other, ROBOT, timeout=1.0)
    assert knowledge.query("deployment", {"name": "echo"})[0]["platforms"] == ["onboard"]
    with pytest.raises(RequestTimeout):
        DeployerClient(other, ROBOT, timeout=1.0).start("onboard", "echo", CONFIG, instance="intruder")
    with pytest.raises(RequestTimeout):
        knowledge.write("process_end", {"run_id": "forged", "end_time": 1.0, "exit_status": 0})
    operator = DeployerClient(secured("quad1-operator"), ROBOT, timeout=3.0)
    assert operator.processes("onboard") == []  # nothing ran


def test_a_certificate_the_policies_do_not_name_gets_nothing_at_all(secured):
    stranger = secured("mallory")
    with pytest.raises(RequestTimeout):
        KnowledgeClient(stranger, ROBOT, timeout=1.0).query("deployment", {"name": "echo"})


def test_a_certificate_from_another_authority_cannot_connect(secured, tmp_path):
    foreign = TestCA(tmp_path / "foreign", name="someone else's CA")
    with pytest.raises(TransportError):
        secured("quad1-onboard", authority=foreign, **{"connect.exit_on_failure": True, "connect.timeout_ms": 1000})


@pytest.mark.skipif(not shutil.which("openssl"), reason="openssl is not installed")
def test_the_shipped_certificate_script_makes_certificates_the_shipped_configurations_accept(tmp_path):
    script = ZENOH_DIR.parent / "tls" / "make-certs.sh"
    tls = tmp_path / "tls"
    subprocess.run(["bash", str(script), str(tls), ROBOT, "localhost"], check=True, capture_output=True, timeout=60)
    port = free_port()
    router = open_session(ZenohSettings(extra=FAST_OPEN, config_file=config_file(tmp_path, "router.json5", **{
        "listen.endpoints": [f"tls/127.0.0.1:{port}"], "transport.link.tls.root_ca_certificate": str(tls / "ca.pem"),
        "transport.link.tls.listen_certificate": str(tls / "quad1-knowledge.pem"),
        "transport.link.tls.listen_private_key": str(tls / "quad1-knowledge-key.pem")})))
    queryable = router.declare_queryable("kgadapt/quad1/host/onboard/deployer/list", lambda q: q.reply(q.key_expr, b"here"))
    operator = open_session(ZenohSettings(config_file=config_file(tmp_path, "onboard.json5", **{
        "connect.endpoints": [f"tls/localhost:{port}"], "connect.exit_on_failure": True, "connect.timeout_ms": 2000,
        "transport.link.tls.root_ca_certificate": str(tls / "ca.pem"),
        "transport.link.tls.connect_certificate": str(tls / "quad1-operator.pem"),
        "transport.link.tls.connect_private_key": str(tls / "quad1-operator-key.pem")})))
    try:
        replies = list(operator.get("kgadapt/quad1/host/onboard/deployer/list", timeout=2))
        assert [r.ok.payload.to_bytes() for r in replies] == [b"here"]
    finally:
        operator.close()
        queryable.undeclare()
        router.close()
