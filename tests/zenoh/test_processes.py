"""The fabric as real processes on loopback: knowledge service, onboard and remote agents, `kgadapt ask`."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import psutil
import pytest

from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.loader import load_models
from kgadapt.knowledge.store import open_store
from kgadapt.shared.hostmonitor import squeeze
from kgadapt.shared.session import ZenohSettings, open_session
from tests.conftest import REPO, free_port
from tests.zenoh.conftest import platform_row, wait_for

MODELS = REPO / "knowledge" / "models"
DARK = "marker_detection_dark"  # the hungriest configuration of the shipped models


@pytest.fixture
def fabric(tmp_path, children, robot):
    """A knowledge service on the shipped models, with a client session; agents are started by the test."""
    store_dir = tmp_path / "store"
    store = open_store(f"embedded:{store_dir}")
    store.setup()
    try:
        load_models(store, [MODELS])
    finally:
        store.shutdown()  # ours: stops the server; the service starts it again from the AOF
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    service = children("service", "knowledge", "serve", "--store", f"embedded:{store_dir}",
                       "--robot", robot, "--listen", endpoint)
    service.wait_ready()
    session = open_session(ZenohSettings(mode="client", connect=(endpoint,)))
    client = KnowledgeClient(session, robot, timeout=3.0)

    def agent(role: str, host: str, budget: str):
        child = children(f"{role}-{host}", role, "--robot", robot, "--host", host,
                         "--memory-budget", budget, "--connect", endpoint)
        child.wait_ready()
        return child

    yield {"endpoint": endpoint, "service": service, "session": session, "client": client,
           "agent": agent, "store_dir": store_dir}
    session.close()


def online_with_figures(client: KnowledgeClient, host: str) -> dict | None:
    row = platform_row(client, host)
    return row if row and row["online"] is True and row["memory_free_mb"] is not None else None


def ask(endpoint: str, robot: str, *args: str) -> list[dict]:
    result = subprocess.run(
        [sys.executable, "-m", "kgadapt", "ask", "--robot", robot, "--connect", endpoint, "--json", *args],
        cwd=REPO, capture_output=True, text=True, timeout=30,
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def test_free_memory_in_the_graph_follows_a_squeezed_host_within_a_second_and_ask_sees_the_placement(fabric, robot):
    client = fabric["client"]
    fabric["agent"]("onboard", "onboard", "300M")
    fabric["agent"]("remote", "remote", "2G")
    remote = wait_for(lambda: online_with_figures(client, "remote"), 5, "remote online with figures")
    onboard = wait_for(lambda: online_with_figures(client, "onboard"), 5, "onboard online with figures")
    assert remote["memory_total_mb"] == 2048.0 and 1500 < remote["memory_free_mb"] < 2048
    assert onboard["memory_total_mb"] == 300.0 and onboard["memory_free_mb"] < 300

    rows = ask(fabric["endpoint"], robot, "placement", "--param", f"config={DARK}")
    assert [row["platform"] for row in rows] == ["remote"]  # onboard's budget is below the demand
    demand = rows[0]["demand_mb"]

    status = squeeze(fabric["session"], robot, "remote", 2048 - demand + 50)
    assert status.memory_free_mb < demand
    # The next status carries it (a few ms; `kgadapt bench zenoh`): the bound only separates it from never.
    wait_for(lambda: platform_row(client, "remote")["memory_free_mb"] < demand, 8.0, "the squeeze in the graph")
    assert ask(fabric["endpoint"], robot, "placement", "--param", f"config={DARK}") == []

    released = subprocess.run(  # the command-line way, as the demo does it
        [sys.executable, "-m", "kgadapt", "squeeze", "--robot", robot, "--host", "remote",
         "--connect", fabric["endpoint"], "--json", "0"], cwd=REPO, capture_output=True, text=True, timeout=30)
    assert released.returncode == 0, released.stderr
    assert json.loads(released.stdout)["reserved_mb"] == 0
    wait_for(lambda: platform_row(client, "remote")["memory_free_mb"] > demand, 1.0, "the release in the graph")


def test_ask_prints_a_table_and_fails_with_one_line_naming_an_unknown_query(fabric, robot):
    base = [sys.executable, "-m", "kgadapt", "ask", "--robot", robot, "--connect", fabric["endpoint"]]
    table = subprocess.run([*base, "detector_configs"], cwd=REPO, capture_output=True, text=True, timeout=30)
    assert table.returncode == 0, table.stderr
    assert table.stdout.splitlines()[0].split()[:2] == ["config", "band"]
    assert DARK in table.stdout
    bad = subprocess.run([*base, "no_such_query"], cwd=REPO, capture_output=True, text=True, timeout=30)
    assert bad.returncode == 1
    assert bad.stderr.count("\n") == 1 and "no_such_query" in bad.stderr
    write = subprocess.run([*base, "--cypher", "MATCH (p:Platform) DELETE p"], cwd=REPO, capture_output=True,
                           text=True, timeout=30)
    assert write.returncode == 1 and "read-only" in write.stderr


def test_a_killed_agent_is_marked_offline_and_online_again_when_restarted(fabric):
    client = fabric["client"]
    remote = fabric["agent"]("remote", "remote", "1G")
    wait_for(lambda: online_with_figures(client, "remote"), 5, "remote online")
    remote.kill9()
    # Its socket closes: well within one 1 s lease on a quiet machine; the bound only separates it from never.
    wait_for(lambda: platform_row(client, "remote")["online"] is False, 8.0, "remote offline after kill -9")

    fabric["agent"]("remote", "remote", "1G")
    wait_for(lambda: online_with_figures(client, "remote"), 5, "remote online after restart")


def test_a_hung_agent_is_marked_offline_after_about_one_lease_and_online_again_when_it_resumes(fabric):
    client = fabric["client"]
    remote = fabric["agent"]("remote", "remote", "1G")
    wait_for(lambda: online_with_figures(client, "remote"), 5, "remote online")
    remote.process.send_signal(signal.SIGSTOP)  # hung: its socket stays open, only the lease can tell
    try:
        stopped_at = time.monotonic()
        wait_for(lambda: platform_row(client, "remote")["online"] is False, 9.0, "remote offline while hung")
        # The 1000 ms lease, not Zenoh's default 10 s: the upper bound leaves room for a loaded machine.
        assert 0.5 < time.monotonic() - stopped_at < 9.0
    finally:
        remote.process.send_signal(signal.SIGCONT)
    wait_for(lambda: platform_row(client, "remote")["online"] is True, 10, "remote online after it resumed")


def test_sigterm_stops_agent_and_service_cleanly_and_the_service_stops_its_store(fabric):
    client = fabric["client"]
    onboard = fabric["agent"]("onboard", "onboard", "500M")
    wait_for(lambda: online_with_figures(client, "onboard"), 5, "onboard online")
    assert onboard.stop() == 0
    wait_for(lambda: platform_row(client, "onboard")["online"] is False, 2.0, "onboard offline after SIGTERM")

    store_pid = json.loads((fabric["store_dir"] / "server.json").read_text())["pid"]
    assert psutil.pid_exists(store_pid)
    assert fabric["service"].stop() == 0
    wait_for(lambda: not psutil.pid_exists(store_pid) or psutil.Process(store_pid).status() == psutil.STATUS_ZOMBIE,
             5, "the store server to stop")
    assert not (fabric["store_dir"] / "server.json").exists()
