"""Deployers protect their host: one host per change request, and no start beyond the memory budget.

A real knowledge service and a real remote agent (budget 300 MiB) on
loopback; requests are sent as an outsider would, from CONTRACTS.md.
"""

from __future__ import annotations

import msgpack
import pytest

from kgadapt.deploy.client import DeployerClient
from kgadapt.shared.errors import DeploymentError
from tests.security.outsider import Outsider

DARK = "marker_detection_dark"  # 324 MiB declared: more than a 300 MiB budget can hold
DAY = "marker_detection_day"


def _start(config: str, deployment: str) -> bytes:
    return msgpack.packb({"kind": "deploy_request", "v": 1, "deployment": deployment, "config": config,
                          "wait_ready": True})


def test_a_wildcard_start_reaches_no_host(loopback_robot):
    robot = loopback_robot(remote_budget="2G")
    outsider = Outsider(robot["session"](), robot["robot"])
    # The deployer answers before the wildcards are tried: a query the router routes to no one yet proves nothing.
    DeployerClient(robot["session"](), robot["robot"]).wait_for(["remote"], timeout=10.0)
    for key in (f"kgadapt/{robot['robot']}/host/*/deployer/start", f"kgadapt/{robot['robot']}/host/**/start",
                f"kgadapt/{robot['robot']}/host/$*ote/deployer/start"):
        answer = outsider.raw(key, _start(DAY, "detector_day"), timeout=10)
        assert answer.kind == "err" and "exactly one host" in answer.error, (key, answer)
    stop = outsider.raw(f"kgadapt/{robot['robot']}/host/*/deployer/stop",
                        msgpack.packb({"kind": "deploy_request", "v": 1, "instance": "x"}), timeout=10)
    assert stop.kind == "err" and "exactly one host" in stop.error
    assert DeployerClient(robot["session"](), robot["robot"]).processes("*") == []  # nothing started anywhere


def test_a_start_beyond_the_hosts_memory_budget_is_refused_with_that_reason(loopback_robot):
    robot = loopback_robot(remote_budget="300M")
    deployers = DeployerClient(robot["session"](), robot["robot"])
    with pytest.raises(DeploymentError, match=r"declares 324 MiB and host remote's 0 process\(es\) already declare "
                                              r"0 MiB \(none\): 324 MiB would exceed its memory budget of 300 MiB"):
        deployers.start("remote", "detector_dark", DARK)
    assert deployers.processes("remote") == []
    # What fits still starts: the check refuses by the figures, not by the request.
    started = deployers.start("remote", "detector_day", DAY)
    assert started.state in ("ready", "running")
    deployers.stop("remote", started.instance)


def _listening(pid: int) -> set[str]:
    import psutil

    return {c.laddr.ip for c in psutil.Process(pid).net_connections(kind="inet") if c.status == psutil.CONN_LISTEN}


def test_agents_and_detectors_listen_on_loopback_only(loopback_robot):
    robot = loopback_robot(remote_budget="2G")
    deployers = DeployerClient(robot["session"](), robot["robot"])
    started = deployers.start("remote", "detector_day", DAY)
    try:
        agent = _listening(robot["agent"].process.pid)
        detector = _listening(int(started.pid))
        assert agent and agent <= {"127.0.0.1"}, agent  # the agent's router listens, but only there
        assert detector == set(), detector  # a detector is a client of that router: it listens on nothing
    finally:
        deployers.stop("remote", started.instance)


def test_a_second_knowledge_service_on_the_same_store_refuses_to_start_and_changes_nothing(loopback_robot, tmp_path):
    import subprocess
    import sys

    from kgadapt.knowledge.client import KnowledgeClient
    from tests.conftest import REPO, free_port
    from tests.support import wait_for

    robot = loopback_robot(remote_budget="2G")
    own = KnowledgeClient(robot["session"](), robot["robot"], timeout=2.0, own=True)
    online = lambda: {r["platform"] for r in own.query("platforms", {}) if r["online"]}  # noqa: E731
    wait_for(lambda: "remote" in online(), 10, "the remote host online")
    second = subprocess.run(
        [sys.executable, "-m", "kgadapt", "knowledge", "serve", "--store", f"embedded:{robot['store_dir']}",
         "--robot", robot["robot"], "--listen", f"tcp/127.0.0.1:{free_port()}"],
        capture_output=True, text=True, timeout=60, cwd=REPO,
    )
    assert second.returncode != 0
    assert "another knowledge service already serves the store" in second.stderr, second.stderr
    # Before, the second service marked every platform offline and placement answered nothing.
    assert "remote" in online()
    assert own.query("placement", {"config": DAY})
