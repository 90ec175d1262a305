"""Fixtures of the fleet tests: several robots' knowledge services on two linked Zenoh routers.

``fleet`` (one per module): routers ``a`` and ``b`` (``b`` connects to ``a``),
robots ``<p>q1`` and ``<p>q2`` served on router ``a``, ``<p>q3`` on router ``b``,
each with its own graph on the session's FalkorDB server, loaded with the
shipped models and seeded by bench/fleet_bench.py's :func:`seed_robot` (a
running detector and the decision behind it). ``<p>`` is unique to the run
so that nothing else on the machine answers as one of them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import pytest

from kgadapt.bench.fleet_bench import seed_robot
from kgadapt.knowledge.falkordb_store import FalkorDBStore
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.knowledge.store import StoreSettings
from kgadapt.shared import keys
from kgadapt.shared.session import ZenohSettings, open_session
from tests.conftest import free_port
from tests.support import wait_for

FAST_OPEN = {"scouting/delay": 0}


@dataclass
class Fleet:
    endpoints: dict[str, str]  # router name -> endpoint
    routers: dict[str, Any]  # router name -> session
    robots: dict[str, dict[str, Any]]  # robot -> what was seeded (config, band, host, decision, router)
    services: dict[str, KnowledgeService]
    stores: dict[str, Any]
    opened: list[Any] = field(default_factory=list)

    def client(self, router: str = "b") -> Any:
        """A Zenoh client session of router ``router`` (closed with the fleet)."""
        session = open_session(ZenohSettings(mode="client", connect=(self.endpoints[router],), extra=FAST_OPEN))
        self.opened.append(session)
        return session

    def stop_service(self, robot: str) -> None:
        self.services.pop(robot).shutdown()


def _store(resp_server: Any, graph: str) -> FalkorDBStore:
    socket = resp_server.address.unix_socket
    store = FalkorDBStore(StoreSettings(kind="falkordb", url=f"falkordb+unix://{socket}", unix_socket=socket,
                                        graph=graph))
    store.setup()
    return store


def wait_until_all_answer(session: Any, robots: list[str], timeout: float = 10.0) -> None:
    """Declarations take a moment to cross the routers: wait until every robot answers a probe."""
    def answered() -> bool:
        got = set()
        for reply in session.get(f"{keys.PREFIX}/*/knowledge/query/platforms", timeout=1):
            if reply.ok is not None:
                got.add(str(reply.ok.key_expr).split("/")[1])
        return set(robots) <= got

    wait_for(answered, timeout, f"answers from {robots}")


@pytest.fixture(scope="module")
def fleet(resp_server):
    prefix = f"f{os.getpid()}"
    endpoints = {"a": f"tcp/127.0.0.1:{free_port()}", "b": f"tcp/127.0.0.1:{free_port()}"}
    routers = {"a": open_session(ZenohSettings(mode="router", listen=(endpoints["a"],), extra=FAST_OPEN))}
    routers["b"] = open_session(ZenohSettings(mode="router", listen=(endpoints["b"],), connect=(endpoints["a"],),
                                              extra=FAST_OPEN))
    placement = {f"{prefix}q1": "a", f"{prefix}q2": "a", f"{prefix}q3": "b"}
    fleet = Fleet(endpoints=endpoints, routers=routers, robots={}, services={}, stores={})
    try:
        for i, (robot, router) in enumerate(placement.items()):
            store = _store(resp_server, robot)
            fleet.stores[robot] = store
            fleet.robots[robot] = {**seed_robot(store, robot, i), "router": router}
            service = KnowledgeService(store, ServiceSettings(robot=robot, mark_offline_at_start=False))
            service.setup(routers[router])
            fleet.services[robot] = service
        wait_until_all_answer(fleet.client("b"), list(placement))
        yield fleet
    finally:
        for session in fleet.opened:
            session.close()
        for service in fleet.services.values():
            service.shutdown()
        for router in reversed(list(routers.values())):
            router.close()
        for store in fleet.stores.values():
            store.clear()
            store.shutdown()
