"""Shared fixtures: real FalkorDB servers (RESP and Bolt), Memgraph when given.

``store`` runs a test against every backend that is available here: the
embedded FalkorDB over RESP and FalkorDB over Bolt always, Memgraph when
``KGADAPT_MEMGRAPH_URL`` is set (skipped with that reason otherwise). Each
test gets an empty graph.
"""

from __future__ import annotations

import itertools
import os
import sys
from pathlib import Path

import pytest

from kgadapt.knowledge.embedded import EmbeddedServer
from kgadapt.knowledge.falkordb_store import FalkorDBStore
from kgadapt.knowledge.store import GraphStore, StoreSettings, open_store
from kgadapt.operator.cluster import free_tcp_port

REPO = Path(__file__).resolve().parent.parent
_graph_numbers = itertools.count()


def free_port() -> int:
    """A TCP port on loopback that was free a moment ago (below 32768, which FalkorDB's Bolt port needs too)."""
    return free_tcp_port()


@pytest.fixture(scope="session")
def resp_server(tmp_path_factory: pytest.TempPathFactory):
    """One embedded FalkorDB (unix socket, AOF fsync always) for the test session."""
    server = EmbeddedServer(tmp_path_factory.mktemp("falkordb-resp"))
    server.ensure()
    yield server
    server.stop()


@pytest.fixture(scope="session")
def bolt_server(tmp_path_factory: pytest.TempPathFactory):
    """FalkorDB with its Bolt listener on a free loopback port (no AOF: see knowledge/embedded.py)."""
    server = EmbeddedServer(tmp_path_factory.mktemp("falkordb-bolt"), bolt_port=free_port(), append_only=False)
    server.ensure()
    yield server
    server.stop()


@pytest.fixture
def resp_store(resp_server: EmbeddedServer):
    """An empty graph of its own on the session's RESP server."""
    settings = StoreSettings(
        kind="falkordb",
        url=f"falkordb+unix://{resp_server.address.unix_socket}",
        unix_socket=resp_server.address.unix_socket,
        graph=f"test{next(_graph_numbers)}",
    )
    store = FalkorDBStore(settings)
    store.setup()
    yield store
    store.clear()
    store.shutdown()


@pytest.fixture(scope="session")
def _bolt_store_session(bolt_server: EmbeddedServer):
    store = open_store(f"bolt://127.0.0.1:{bolt_server.bolt_port}")
    store.setup(timeout=15)
    yield store
    store.shutdown()


@pytest.fixture
def bolt_store(_bolt_store_session: GraphStore):
    """The Bolt server's one graph, emptied before the test."""
    _bolt_store_session.execute("MATCH (n) DETACH DELETE n")
    return _bolt_store_session


@pytest.fixture
def memgraph_store():
    url = os.environ.get("KGADAPT_MEMGRAPH_URL")
    if not url:
        pytest.skip("Memgraph tests need KGADAPT_MEMGRAPH_URL (no Memgraph server can be installed here)")
    store = open_store(url)
    store.setup()
    store.execute("MATCH (n) DETACH DELETE n")
    yield store
    store.shutdown()


@pytest.fixture(params=["resp", "bolt", "memgraph"])
def store(request: pytest.FixtureRequest) -> GraphStore:
    """Every available backend, one after the other, each with an empty graph."""
    return request.getfixturevalue(f"{request.param}_store")


@pytest.fixture
def kgadapt_cmd():
    """The command line that runs ``kgadapt`` from this checkout's environment."""
    return [sys.executable, "-m", "kgadapt"]
