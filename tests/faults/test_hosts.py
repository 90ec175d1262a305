"""The test hosts themselves: namespaces on a bridge, reachable from each other only, cut and healed, removed."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from kgadapt.operator.cluster import HostNetwork, NetworkSettings
from tests.faults.conftest import our_namespaces

pytestmark = pytest.mark.netns

PROBE = """
import socket, sys
s = socket.socket(); s.settimeout(1.0)
try:
    s.connect((sys.argv[1], 9)); print("open")
except ConnectionRefusedError: print("reachable")
except OSError as exc: print("unreachable")
"""


def reach(network: HostNetwork, src: str, address: str) -> str:
    """From ``src``'s namespace, try TCP port 9 of ``address``: reachable (refused), open, or unreachable."""
    argv = network.run_in(src, [sys.executable, "-c", PROBE, address])
    return subprocess.run(argv, capture_output=True, text=True, timeout=10).stdout.strip()


def test_hosts_reach_each_other_over_the_bridge_not_from_outside_and_a_cut_isolates_one(needs_namespaces):
    network = HostNetwork(NetworkSettings())
    try:
        network.setup()
        assert len(our_namespaces(network)) == 4
        onboard, remote = network.address("onboard"), network.address("remote")
        assert reach(network, "remote", onboard) == "reachable"
        assert reach(network, "robot2", remote) == "reachable"
        # Nothing of it is in this namespace: no address of our subnet, no link of our bridge.
        here = subprocess.run(["ip", "-o", "addr"], capture_output=True, text=True).stdout
        links = subprocess.run(["ip", "-o", "link"], capture_output=True, text=True).stdout
        assert f" {network.settings.subnet}." not in here and network.port("remote") not in links
        network.cut("remote")
        assert reach(network, "robot2", remote) == "unreachable"
        assert reach(network, "robot2", onboard) == "reachable"  # only the remote host's cable is pulled
        network.heal("remote")
        assert reach(network, "robot2", remote) == "reachable"
    finally:
        network.shutdown()
    assert our_namespaces(network) == []


def test_removing_the_hosts_ends_what_still_runs_in_them(needs_namespaces):
    network = HostNetwork(NetworkSettings())
    try:
        network.setup()
        sleeper = subprocess.Popen(network.run_in("remote", ["sleep", "60"]))
        deadline = time.monotonic() + 5  # ip enters the namespace after the fork
        while sleeper.pid not in network.pids("remote") and time.monotonic() < deadline:
            time.sleep(0.01)
        assert sleeper.pid in network.pids("remote")
    finally:
        network.shutdown()
    assert sleeper.wait(5) == -9
    assert our_namespaces(network) == []


def test_a_host_name_that_cannot_name_an_interface_is_refused():
    with pytest.raises(Exception, match="at most 12 letters and digits"):
        NetworkSettings(hosts=("onboard", "a-very-long-host-name"))
