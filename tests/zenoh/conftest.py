"""Fixtures of the Zenoh fabric tests: loopback sessions, an in-process service, child processes."""

from __future__ import annotations

import itertools
import os
import sys
import time

import pytest

from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.schema import ensure_indexes
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.shared import keys
from kgadapt.shared.session import ZenohSettings, open_session
from tests.conftest import free_port
from tests.support import Child, wait_for  # noqa: F401 (the tests import wait_for from here)

_robots = itertools.count()


def platform_row(client: KnowledgeClient, name: str) -> dict | None:
    for row in client.query("platforms", {}):
        if row["platform"] == name:
            return row
    return None


@pytest.fixture
def robot() -> str:
    """A robot name of its own, so tests never see each other's keys."""
    return f"r{os.getpid()}x{next(_robots)}"


@pytest.fixture(scope="module")
def zenoh_pair():
    """Two peer sessions on loopback: (server side listening, client side connected to it)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
    client = open_session(ZenohSettings(mode="peer", connect=(endpoint,)))
    # The first get may race the connection being set up; wait until the link is there.
    deadline = time.monotonic() + 5
    while not list(client.info.peers_zid()) and time.monotonic() < deadline:
        time.sleep(0.01)
    yield server, client
    client.close()
    server.close()


# The hosts these tests' statuses and tokens name, as Platforms of their models: only the models add hosts.
MODEL_HOSTS = ("fuzzhost", "goodhost", "h1", "h2", "onboard", "remote")


@pytest.fixture
def service(resp_store, zenoh_pair, robot):
    """An in-process knowledge service on the test's own graph (its platforms: MODEL_HOSTS) and robot name."""
    server, _ = zenoh_pair
    ensure_indexes(resp_store)  # as `kgadapt knowledge serve` does; it also creates the graph
    resp_store.execute("UNWIND $names AS name MERGE (:Platform {name: name})", {"names": list(MODEL_HOSTS)})
    svc = KnowledgeService(resp_store, ServiceSettings(robot=robot))
    svc.setup(server)
    yield svc
    svc.shutdown()


def wait_until_serving(session, robot: str, *, writes: bool = True, timeout: float = 5.0) -> None:
    """Wait until the service's queryables are known on ``session``'s side.

    A declaration takes a moment to reach another peer; a get sent before
    that finds no queryable and gets no reply at all.
    """
    probes = [keys.knowledge_query(robot, "platforms"), keys.knowledge_cypher(robot)]
    if writes:
        probes.append(keys.knowledge_write(robot, "probe"))  # an unknown verb: any reply will do
    for key in probes:
        wait_for(lambda: list(session.get(key, timeout=1)), timeout, f"a reply on {key}")


@pytest.fixture
def client(zenoh_pair, robot, service) -> KnowledgeClient:
    _, session = zenoh_pair
    wait_until_serving(session, robot, writes=service.settings.writes)
    return KnowledgeClient(session, robot, timeout=3.0)


@pytest.fixture
def children(tmp_path):
    """Start ``kgadapt`` children; every one still running is stopped at teardown, also on failure."""
    started: list[Child] = []

    def start(name: str, *args: str) -> Child:
        child = Child([sys.executable, "-m", "kgadapt", "--log-level", "INFO", *args], name, tmp_path)
        started.append(child)
        return child

    yield start
    for child in reversed(started):
        child.stop()
