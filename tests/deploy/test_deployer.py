"""The deployer over Zenoh: what runs comes from the knowledge store, nothing else."""

from __future__ import annotations

import os
import signal
import sys
import time

import psutil
import pytest

from kgadapt.deploy.client import DeployerClient
from kgadapt.shared import keys, messages
from kgadapt.shared.errors import ConfigError, DeploymentError, RequestTimeout
from tests.deploy.conftest import CONFIG, ROBOT, Collector, add_deployment, wait_for_deployers
from tests.support import Child

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def alive(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def wait_until(predicate, timeout: float = 10.0, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError(f"{what} not met within {timeout} s")


def raw_request(session, host: str, verb: str, payload: bytes):
    replies = list(session.get(keys.deployer_verb(ROBOT, host, verb), payload=payload, timeout=5))
    assert len(replies) == 1
    return replies[0]


def test_a_deployment_from_the_store_starts_on_request_reports_events_and_stops(hosts, client_session):
    events = Collector(client_session, keys.deployer_events(ROBOT, "onboard"), "deploy_event")
    client = DeployerClient(client_session, ROBOT)
    info = client.start("onboard", "echo", CONFIG, instance="det1")
    assert info.state == "ready" and info.host == "onboard" and alive(info.pid)
    # Placeholders were filled by the deployer from its own knowledge.
    assert info.argv[:3] == [sys.executable, "-m", "kgadapt.sim.echo_detector"]
    assert info.argv[info.argv.index("--host") + 1] == "onboard"
    assert info.argv[info.argv.index("--instance") + 1] == "det1"
    assert [p.instance for p in client.processes("*")] == ["det1"]
    final = client.stop("onboard", "det1")
    assert final.state == "stopped" and final.returncode is not None and not alive(info.pid)
    events.wait_for(lambda e: e["event"] == "stopped")
    kinds = [e["event"] for _, e in events.items]
    assert kinds == ["started", "ready", "exited", "stopped"]
    assert all(e["instance"] == "det1" and e["deployment"] == "echo" for _, e in events.items)
    events.close()


def test_an_unknown_deployment_is_refused_and_nothing_runs(hosts, client_session):
    client = DeployerClient(client_session, ROBOT)
    with pytest.raises(DeploymentError, match="'no_such_deployment' is not in the knowledge store"):
        client.start("onboard", "no_such_deployment", CONFIG)
    assert client.processes("*") == []


def test_a_deployment_for_another_host_is_refused_and_nothing_runs(hosts, client_session):
    client = DeployerClient(client_session, ROBOT)
    with pytest.raises(DeploymentError, match="not executable on host onboard .only on remote"):
        client.start("onboard", "echo_remote_only", CONFIG)
    assert client.processes("*") == []


def test_a_configuration_the_deployment_does_not_deploy_is_refused(hosts, client_session):
    client = DeployerClient(client_session, ROBOT)
    with pytest.raises(DeploymentError, match="does not deploy configuration marker_detection_dark"):
        client.start("onboard", "echo", "marker_detection_dark")
    assert client.processes("*") == []


@pytest.mark.parametrize("field", ["command", "executable", "arguments", "environment"])
def test_a_start_request_carrying_a_command_line_is_refused_and_nothing_runs(hosts, client_session, tmp_path, field):
    marker = tmp_path / "pwned"
    evil = f"touch {marker}" if field in ("command", "executable") else ["-c", f"open({str(marker)!r}, 'w')"]
    payload = messages.encode("deploy_request", {"deployment": "echo", "config": CONFIG, field: evil})
    reply = raw_request(client_session, "onboard", "start", payload)
    body = messages.decode(reply.ok.payload.to_bytes(), "deploy_reply")
    assert body["ok"] is False
    assert repr(field) in body["detail"]["error"] and "knowledge store" in body["detail"]["error"]
    assert DeployerClient(client_session, ROBOT).processes("*") == []
    assert not marker.exists()


def test_a_malformed_request_gets_an_error_reply_and_the_deployer_keeps_serving(hosts, client_session):
    reply = raw_request(client_session, "onboard", "start", b"\xc1 not msgpack")
    assert reply.ok is None and "not valid msgpack" in reply.err.payload.to_string()
    reply = raw_request(client_session, "onboard", "stop", messages.encode("deploy_request", {"instance": "../x"}))
    assert "bad instance" in messages.decode(reply.ok.payload.to_bytes(), "deploy_reply")["detail"]["error"]
    assert DeployerClient(client_session, ROBOT).processes("onboard") == []


def test_a_refusal_the_deployer_names_as_a_config_error_is_raised_as_one(hosts, client_session):
    with pytest.raises(ConfigError, match="bad instance"):
        DeployerClient(client_session, ROBOT).stop("onboard", "../x")


def test_a_hosts_list_stays_within_the_message_bound_whatever_its_children_printed():
    # One child that printed one 300,000-character line made every list and status of its host fail to encode
    # (deploy_reply is bounded at 256 KiB) for as long as it was kept: 50 ended instances and the live ones.
    from kgadapt.deploy.deployer import DETAIL_CHARS, ONE_DETAIL_CHARS, ONE_LINE_CHARS, OUTPUT_LINE_CHARS, _detail
    from kgadapt.deploy.supervisor import ProcessInfo
    from kgadapt.shared.states import ProcessState

    loud = [ProcessInfo(instance=f"det{i}", deployment="echo", config=CONFIG, state=ProcessState.EXITED, pid=None,
                        run_id=f"r{i}", restarts=0, started_at=1.0, ready_at=None, ended_at=2.0, returncode=1,
                        argv=(sys.executable, "-m", "kgadapt.onboard.perception.detector", "--instance", f"det{i}"),
                        detail="y" * 300_000, output=tuple("x" * 300_000 for _ in range(5))) for i in range(60)]
    body = messages.DeployReply(ok=True, detail=messages.DeployDetail(
        host="onboard", processes=[_detail(info, "onboard", messages.ProcessDetail) for info in loud]))
    encoded = messages.encode(body)  # raised MessageError past the bound before
    shown = messages.decode_as(encoded, messages.DeployReply).detail.processes[0]
    assert all(len(line) == OUTPUT_LINE_CHARS and line.startswith("xxx") for line in shown.output)
    assert len(shown.detail) == DETAIL_CHARS and shown.detail.endswith("yyy")
    # One instance's reply keeps more of each line, still within the bound.
    one = _detail(loud[0], "onboard", messages.DeployDetail)
    messages.encode(messages.DeployReply(ok=True, detail=one))
    assert all(len(line) == ONE_LINE_CHARS for line in one.output) and len(one.detail) == ONE_DETAIL_CHARS


def test_a_placeholder_outside_the_contract_is_refused_naming_it(graph, hosts, client_session):
    add_deployment(graph, "leaky", platforms=["onboard"], deploys=[CONFIG], arguments=["-c", "print('{home}')"])
    with pytest.raises(DeploymentError, match=r"placeholder \{home\} is not allowed"):
        DeployerClient(client_session, ROBOT).start("onboard", "leaky", CONFIG)


def test_the_process_profile_reaches_the_graph_start_then_memory_then_exit(graph, hosts, client_session):
    client = DeployerClient(client_session, ROBOT)
    info = client.start("onboard", "echo", CONFIG, instance="profiled")
    run = info.run_id

    def profile():
        rows = graph.execute(
            "MATCH (r:ProcessProfile {name: $run})-[:RAN_ON]->(p:Platform), (r)-[:PROFILE_OF]->(d:Deployment) "
            "RETURN r AS r, p.name AS platform, d.name AS deployment", {"run": run})
        return rows[0] if rows else None

    row = wait_until(profile, what="process_start in the graph")
    assert row["platform"] == "onboard" and row["deployment"] == "echo"
    assert row["r"]["pid"] == info.pid and abs(row["r"]["start_time"] - info.started_at) < 1.0
    # The first sample comes right after exec, when little is mapped; a Python with Zenoh soon has MiBs.
    row = wait_until(lambda: (p := profile()) and (p["r"].get("rss_mb_max") or 0) > 5 and p, what="memory figures")
    assert row["r"]["rss_mb_max"] < 2000 and 0 < row["r"]["rss_mb_mean"] <= row["r"]["rss_mb_max"]
    assert row["r"]["rss_mb_last"] > 0 and row["r"]["cpu_percent_mean"] >= 0
    assert row["r"].get("end_time") is None
    client.stop("onboard", "profiled")
    row = wait_until(lambda: (p := profile()) and p["r"].get("end_time") and p, what="exit status")
    assert row["r"]["exit_status"] == client.status("onboard", "profiled").returncode
    assert row["r"]["end_time"] >= row["r"]["start_time"]


def test_killing_an_agent_with_sigkill_leaves_no_detector_running(knowledge, endpoint, test_session, tmp_path):
    agent = Child([sys.executable, "-m", "kgadapt", "deploy", "serve", "--robot", ROBOT, "--host", "onboard",
                   "--connect", endpoint], "agent", tmp_path)
    try:
        agent.wait_ready()
        assert "agent ready" in agent.output[0]  # the line for people comes first
        wait_for_deployers(test_session, ["onboard"])
        info = DeployerClient(test_session, ROBOT).start("onboard", "echo", CONFIG)
        assert alive(info.pid)
        os.kill(agent.pid, signal.SIGKILL)
        agent.process.wait()
        wait_until(lambda: not alive(info.pid), timeout=5.0, what="detector gone after kill -9 of its agent")
    finally:
        agent.stop()


def test_raced_starts_pass_only_while_the_declared_memory_fits_the_budget(graph, knowledge, endpoint, test_session):
    from concurrent.futures import ThreadPoolExecutor

    from tests.deploy.conftest import DeployerHost

    # A configuration that declares 300 MiB; the host measures plenty free, as it does while the
    # detectors it has just started have not yet taken their memory.
    graph.execute("MATCH (g:PerceptionGraph {name: $c}) MERGE (x:Component {name: 'heavy'}) "
                  "SET x.memory_demand_mb = 300 MERGE (g)-[:CONTAINS]->(x)", {"c": CONFIG})
    host = DeployerHost(endpoint, "onboard", memory={"free_memory": lambda: 10_000.0, "budget": lambda: 700.0})
    try:
        wait_for_deployers(test_session, ["onboard"])
        client = DeployerClient(test_session, ROBOT)

        def start(i: int):
            try:
                return client.start("onboard", "echo", CONFIG, instance=f"heavy{i}")
            except DeploymentError as exc:
                return exc

        with ThreadPoolExecutor(3) as pool:
            outcomes = list(pool.map(start, range(3)))
        started = [o for o in outcomes if isinstance(o, messages.DeployDetail)]
        refused = [str(o) for o in outcomes if isinstance(o, DeploymentError)]
        assert len(started) == 2 and len(refused) == 1, outcomes  # 2 x 300 fit 700; a third would not
        assert ("it declares 300 MiB and host onboard's 2 process(es) already declare 600 MiB" in refused[0]
                and "900 MiB would exceed its memory budget of 700 MiB" in refused[0]), refused
        # A stop gives the declared memory back.
        client.stop("onboard", str(started[0].instance))
        again = client.start("onboard", "echo", CONFIG, instance="heavy3")
        assert again.state == "ready"
    finally:
        host.close()


def test_a_start_beside_a_running_process_asks_the_graph_for_its_configuration_once(graph, knowledge, endpoint,
                                                                                    test_session):
    """Issue 32: a change as a new process waits for the deployer's questions to the graph. Its admission
    counts the new configuration's memory from the row it carries to the start, and the running process's
    from its own admission: one question for the configuration, none for what already runs."""
    from tests.deploy.conftest import CONFIG_DUSK, DeployerHost

    for config, mb in ((CONFIG, 100), (CONFIG_DUSK, 200)):
        graph.execute("MATCH (g:PerceptionGraph {name: $c}) MERGE (x:Component {name: $x}) "
                      "SET x.memory_demand_mb = $mb MERGE (g)-[:CONTAINS]->(x)", {"c": config, "x": f"{config}_x", "mb": mb})
    asks: list[str] = []
    host = DeployerHost(endpoint, "onboard", asks=asks, memory={"free_memory": lambda: 10_000.0, "budget": lambda: 350.0})
    try:
        wait_for_deployers(test_session, ["onboard"])
        client = DeployerClient(test_session, ROBOT)
        client.start("onboard", "echo", CONFIG, instance="day1")
        before = len(asks)
        client.start("onboard", "echo", CONFIG_DUSK, instance="dusk1")
        assert sorted(asks[before:]) == ["deployment", "detector_config"], asks[before:]  # asked side by side
        # The figures still count: 100 + 200 held, a third 100 would pass 350.
        with pytest.raises(DeploymentError, match="300 MiB would exceed|already declare 300 MiB"):
            client.start("onboard", "echo", CONFIG, instance="day2")
        # A stopped process is no longer counted: its figure goes with it.
        client.stop("onboard", "dusk1")
        assert client.start("onboard", "echo", CONFIG, instance="day3").state == "ready"
    finally:
        host.close()


def test_a_client_told_not_to_resend_gives_up_at_once_on_a_host_without_a_deployer(client_session):
    # The adaptation manager's probe of the running detector: no deployer answering means its host just
    # went, which liveliness reports. Sent again for its whole timeout, the probe once held the host's loss
    # in the manager's queue for 480 ms (issue 32).
    probe = DeployerClient(client_session, ROBOT, timeout=60.0, resend_for=0.0)
    started = time.monotonic()
    with pytest.raises(RequestTimeout, match="no deployer on host gone"):
        probe.status("gone", "det1")
    assert time.monotonic() - started < 30.0  # sent once: the default sends it again for the whole 60 s
