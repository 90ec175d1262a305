"""Fixtures for deployer tests over Zenoh: a knowledge service, a graph of deployments, deployers.

Everything real: the knowledge service on the session's embedded FalkorDB
(an empty graph per test), a Zenoh router on a free loopback port, deployers
as peers, and the stand-in detector ``kgadapt.sim.echo_detector`` as the program
the deployments run.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from typing import Any, Iterator

import pytest

from kgadapt.deploy.client import DeployerClient
from kgadapt.deploy.deployer import Deployer, DeployerSettings
from kgadapt.deploy.supervisor import RestartPolicy, StopPolicy
from kgadapt.knowledge import schema as S
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.fleet import ROSTER_QUERY
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.shared import keys, messages
from kgadapt.shared.session import ZenohSettings, open_session
from tests.conftest import free_port

ROBOT = "testbot"
CONFIG = "marker_detection_day"
CONFIG_DUSK = "marker_detection_dusk"
# Measured: open() of a router, and of a peer that finds others, waits scouting/delay (500 ms by
# default) for scouted peers. The tests wait for what they need (wait_for_deployers) instead.
FAST_OPEN = {"scouting/delay": 0}
ECHO = ["-m", "kgadapt.sim.echo_detector", "--robot", "{robot}", "--host", "{host}", "--instance", "{instance}",
        "--config", "{config}", "--connect", "{connect}"]
# The echo detector's arguments, run by a program that hangs before readiness when --host is remote.
ECHO_HANGS_ON_REMOTE = [
    "-c", "import sys, threading\n"
          "if sys.argv[sys.argv.index('--host') + 1] == 'remote':\n"
          "    threading.Event().wait()\n"
          "from kgadapt.sim.echo_detector import main\n"
          "sys.exit(main(sys.argv[1:]))",
    *ECHO[2:]]


def add_deployment(store: Any, name: str, *, platforms: list[str], deploys: list[str], executable: str = "{python}",
                   arguments: list[str] | None = None, environment: list[str] | None = None) -> None:
    """A Deployment node with its EXECUTABLE_ON and DEPLOYS relations (nodes merged by name)."""
    store.execute(
        f"MERGE (d:{S.DEPLOYMENT} {{name: $name}}) "
        "SET d.kind = 'DeploymentFile', d.executable = $executable, d.arguments = $arguments, d.environment = $environment",
        {"name": name, "executable": executable, "arguments": list(arguments if arguments is not None else ECHO),
         "environment": list(environment or [])},
    )
    for platform in platforms:
        store.execute(
            f"MATCH (d:{S.DEPLOYMENT} {{name: $name}}) MERGE (p:{S.PLATFORM} {{name: $platform}}) "
            f"MERGE (d)-[:{S.EXECUTABLE_ON}]->(p)", {"name": name, "platform": platform})
    for config in deploys:
        store.execute(
            f"MATCH (d:{S.DEPLOYMENT} {{name: $name}}) MERGE (g:{S.PERCEPTION_GRAPH} {{name: $config}}) "
            f"MERGE (d)-[:{S.DEPLOYS}]->(g)", {"name": name, "config": config})


@pytest.fixture
def graph(resp_store):
    """Deployments of the echo detector: on both hosts, on the remote only, and one that hangs on the remote."""
    S.ensure_indexes(resp_store)
    add_deployment(resp_store, "echo", platforms=["onboard", "remote"], deploys=[CONFIG, CONFIG_DUSK])
    add_deployment(resp_store, "echo_remote_only", platforms=["remote"], deploys=[CONFIG])
    add_deployment(resp_store, "echo_hangs_on_remote", platforms=["onboard", "remote"], deploys=[CONFIG],
                   arguments=ECHO_HANGS_ON_REMOTE)
    return resp_store


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def knowledge(graph, endpoint) -> Iterator[KnowledgeService]:
    """The knowledge service in a router session listening on ``endpoint``."""
    session = open_session(ZenohSettings(mode="router", listen=(endpoint,), extra=FAST_OPEN))
    service = KnowledgeService(graph, ServiceSettings(robot=ROBOT))
    service.setup(session)
    yield service
    service.shutdown()
    session.close()


def not_roll_calls(asked: list[str]) -> list[str]:
    """The named queries in ``asked`` but the knowledge service's own fleet roll calls: it asks every robot's
    service for its roster, its own included, about 0.5 and 5.5 s after its setup (knowledge/fleet_roster.py),
    so a test that counts what a detector asks of the service can meet one."""
    return [name for name in asked if name != ROSTER_QUERY]


def peer_session(endpoint: str) -> Any:
    return open_session(ZenohSettings(mode="peer", connect=(endpoint,), extra=FAST_OPEN))


class AskLog:
    """A knowledge client that notes the name of every named query put through it."""

    def __init__(self, client: Any, names: list[str]) -> None:
        self.client, self.names = client, names

    def query(self, name: str, *args: Any, **kwargs: Any) -> Any:
        self.names.append(name)  # before asking: the service never counts a question this log has not
        return self.client.query(name, *args, **kwargs)

    def __getattr__(self, attr: str) -> Any:
        return getattr(self.client, attr)


class DeployerHost:
    """A deployer in its own peer session, as an agent would run it."""

    def __init__(self, endpoint: str, host: str, *, memory: dict[str, Any] | None = None,
                 asks: list[str] | None = None, **changes: Any) -> None:
        """``asks``: every named query the deployer puts to the knowledge service is appended to it."""
        settings = DeployerSettings(
            robot=ROBOT, host=host, connect=endpoint, ready_timeout=10.0,
            restart=RestartPolicy(max_restarts=1, backoff_initial=0.05),
            stop=StopPolicy(sigint_timeout=2.0, sigterm_timeout=2.0), sample_interval=0.2,
        )
        # The launcher costs an interpreter's imports per deployer; the echo tests do not need it.
        settings = replace(settings, **{"launcher": False, **changes})
        self.session = peer_session(endpoint)
        knowledge = None
        if asks is not None:
            knowledge = AskLog(KnowledgeClient(self.session, ROBOT, timeout=settings.knowledge_timeout, own=True,
                                               host=host), asks)
        # memory: free_memory and budget callables
        self.deployer = Deployer(settings, knowledge=knowledge, **(memory or {}))
        self.deployer.setup(self.session)

    def close(self) -> None:
        self.deployer.shutdown()
        self.session.close()


@pytest.fixture
def launcher() -> bool:
    """Whether the ``hosts`` deployers run a launcher; a test module overrides this fixture."""
    return False


@pytest.fixture
def hosts(knowledge, endpoint, launcher) -> Iterator[dict[str, DeployerHost]]:
    """Deployers for the hosts ``onboard`` and ``remote``, both on this machine."""
    made = {name: DeployerHost(endpoint, name, launcher=launcher) for name in ("onboard", "remote")}
    yield made
    for host in made.values():
        host.close()


@pytest.fixture
def test_session(knowledge, endpoint) -> Iterator[Any]:
    """A session for the test itself (the side that asks the deployers)."""
    session = peer_session(endpoint)
    yield session
    session.close()


@pytest.fixture
def client_session(test_session, hosts) -> Any:
    """The test's session, once it sees both deployers of ``hosts``."""
    wait_for_deployers(test_session, list(hosts))
    return test_session


def wait_for_deployers(session: Any, names: list[str], timeout: float = 10.0) -> None:
    """Declarations travel asynchronously: wait until every named deployer answers ``list``."""
    DeployerClient(session, ROBOT).wait_for(names, timeout)


class Collector:
    """Decoded messages of one kind arriving on a key, in order, with their arrival time."""

    def __init__(self, session: Any, key: str, kind: str) -> None:
        self.kind = kind
        self.items: list[tuple[float, dict]] = []
        self._cv = threading.Condition()
        self._sub = session.declare_subscriber(key, self._on)

    def _on(self, sample: Any) -> None:
        body = messages.decode(sample.payload.to_bytes(), self.kind)
        with self._cv:
            self.items.append((time.perf_counter(), body))
            self._cv.notify_all()

    def wait_for(self, predicate, timeout: float = 10.0) -> tuple[float, dict]:
        with self._cv:
            found: list = []

            def check() -> bool:
                found[:] = [item for item in self.items if predicate(item[1])]
                return bool(found)

            assert self._cv.wait_for(check, timeout), f"nothing matching among {len(self.items)}, last: {self.items[-3:]}"
            return found[0]

    def close(self) -> None:
        self._sub.undeclare()


class FrameSource:
    """Publishes small camera frames at ``fps`` until closed (the echo detector answers each)."""

    def __init__(self, session: Any, fps: float = 30.0, *, robot: str = ROBOT, jpeg: bytes = b"\xff\xd8",
                 size: tuple[int, int] = (8, 8)) -> None:
        self.publisher = session.declare_publisher(keys.camera_frame(robot, "cam0"))
        self.jpeg, self.size = jpeg, size
        self.fps = fps
        self.seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period = 1.0 / self.fps
        next_at = time.perf_counter()
        while not self._stop.is_set():
            self.seq += 1
            self.publisher.put(messages.encode("frame", {
                "camera": "cam0", "seq": self.seq, "time": time.time(), "width": self.size[0], "height": self.size[1],
                "jpeg": self.jpeg,
            }))
            next_at += period
            self._stop.wait(max(0.0, next_at - time.perf_counter()))

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.publisher.undeclare()
