"""Agents say what is wrong and what they do at the default log level.

An agent whose router is not there says so every few seconds, says when it
reaches it, and exits with status 1 when told to give up; Ctrl-C stops it
saying what it stopped.
"""

from __future__ import annotations

import signal
import subprocess
import sys

from kgadapt.operator.cluster import free_tcp_port
from tests.support import Child


def test_an_agent_without_its_router_says_so_until_it_comes_then_stops_on_ctrl_c_saying_what(tmp_path):
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    agent = Child([sys.executable, "-m", "kgadapt", "remote", "--connect", endpoint, "--memory-budget", "1G"],
                  "remote", tmp_path)  # no --log-level: the default must talk
    service = None
    try:
        agent.wait_for_line("remote agent ready")
        def stderr() -> str:
            return agent.stderr_path.read_text()

        from tests.support import wait_for

        wait_for(lambda: f"cannot reach the router at {endpoint}" in stderr(), 20, "the agent to say it is alone")
        service = Child([sys.executable, "-m", "kgadapt", "knowledge", "serve", "--store",
                         f"embedded:{tmp_path / 'store'}", "--listen", endpoint], "service", tmp_path)
        service.wait_for_line("knowledge service ready")
        wait_for(lambda: f"reached {endpoint} again" in stderr(), 20, "the agent to say it reached the router")
        agent.process.send_signal(signal.SIGINT)
        assert agent.process.wait(20) == 0
        said = stderr()
        assert "stopped deployer" in said and "stopped host monitor" in said and "stopped everything in" in said
    finally:
        for child in (agent, service):
            if child is not None and child.process.poll() is None:
                child.process.send_signal(signal.SIGINT)
                child.process.wait(20)


def test_an_agent_told_to_give_up_exits_1_naming_the_endpoint():
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    result = subprocess.run([sys.executable, "-m", "kgadapt", "remote", "--connect", endpoint, "--give-up-after", "2"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 1
    assert f"no router reached at {endpoint} within 2 s" in result.stderr.splitlines()[-1]
