"""A router's own lease is longer than its hosts': a cut-off host is still found within the host's lease,
and an idle host gets a quarter of the keep-alives it sends.

Real processes on real links: a router (``ZenohSettings(mode="router")``, as the knowledge service opens
it) in one network namespace and a host's client in another, joined by a bridge whose port for the router
is taken down to cut the two apart.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from kgadapt.operator.cluster import HostNetwork
from kgadapt.shared.children import ChildProcess
from kgadapt.shared.session import HOST_LEASE_MS, ROUTER_LEASE_MS
from tests.conftest import REPO
from tests.support import host_network

pytestmark = pytest.mark.netns

PORT = 7447

_ROUTER = r"""
import json, sys, time
from kgadapt.shared.readiness import announce_ready
from kgadapt.shared.session import ZenohSettings, open_session
session = open_session(ZenohSettings(mode="router", listen=(sys.argv[1],)))
def changed(sample):  # Zenoh's callback: print and return
    print(json.dumps({"kind": str(sample.kind), "key": str(sample.key_expr), "time": time.time()}), flush=True)
sub = session.liveliness().declare_subscriber("leasetest/**", changed, history=True)
announce_ready(role="router")
sys.stdin.read()
"""

_HOST = r"""
import sys
from kgadapt.shared.readiness import announce_ready
from kgadapt.shared.session import ZenohSettings, open_session
session = open_session(ZenohSettings(mode="client", connect=(sys.argv[1],)))
token = session.liveliness().declare_token("leasetest/host")
announce_ready(role="host")
sys.stdin.read()
"""


@pytest.fixture
def network():
    with host_network(("router", "host"), "10.213.23") as net:
        yield net


def _bytes(network: HostNetwork, endpoint: str) -> tuple[int, int]:
    """(sent, received) payload bytes of the host's TCP connection to ``endpoint`` (ss, in its namespace)."""
    out = subprocess.run(network.run_in("host", ["ss", "-tinH", "state", "established", "dst", endpoint]),
                         capture_output=True, text=True, timeout=10, check=True).stdout
    fields = dict(f.split(":", 1) for f in out.split() if f.startswith(("bytes_sent:", "bytes_received:")))
    assert fields, f"no connection to {endpoint} in the host's namespace:\n{out}"
    return int(fields["bytes_sent"]), int(fields["bytes_received"])


def test_a_router_finds_a_cut_off_host_within_the_hosts_lease_and_sends_it_a_quarter_of_the_keep_alives(network):
    assert ROUTER_LEASE_MS >= 2 * HOST_LEASE_MS  # what this test tells apart
    address = network.address("router")
    endpoint = f"tcp/{address}:{PORT}"
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    router = ChildProcess(network.run_in("router", [sys.executable, "-c", _ROUTER, endpoint]), name="router",
                          cwd=REPO, env=env, stdin=subprocess.PIPE)
    host = None
    try:
        router.wait_ready(30.0)
        host = ChildProcess(network.run_in("host", [sys.executable, "-c", _HOST, endpoint]), name="host", cwd=REPO,
                            env=env, stdin=subprocess.PIPE)
        host.wait_ready(30.0)
        assert "PUT" in json.loads(router.wait_for_line('"leasetest/host"', 10.0))["kind"].upper()

        # Idle both ways: each side sends only keep-alives, one every own lease / 4.
        sent0, received0 = _bytes(network, f"{address}:{PORT}")
        time.sleep(6.0)  # a window to count the keep-alives in, not a wait for an event
        sent1, received1 = _bytes(network, f"{address}:{PORT}")
        sent, received = sent1 - sent0, received1 - received0
        assert sent > 0, "the host sent no keep-alive in 6 s"
        # The router's keep-alives are a quarter of the host's (4 s against 1 s), each of the same size; at
        # equal leases they would be as many. Half is the line between the two.
        assert received <= sent / 2, (sent, received)

        cut = network.cut("router")  # the router's cable: the host can no longer reach it, nor it the host
        gone = json.loads(router.wait_for_line('"leasetest/host"', ROUTER_LEASE_MS / 1000 + 10))
        assert "DELETE" in gone["kind"].upper()
        # Zenoh drops a link after the *other* side's lease: the host's 1 s, not the router's own 4 s.
        assert gone["time"] - cut < ROUTER_LEASE_MS / 1000, gone["time"] - cut
    finally:
        # Killed: each holds a link to the other that the cut left dead, and Zenoh's close waits for a dead
        # TCP link (a 10 s SO_LINGER).
        for child in (host, router):
            if child is not None:
                child.stop(first=signal.SIGKILL)
