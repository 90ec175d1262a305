"""Fixtures of the knowledge tests: a known model set (tests/knowledge/known_models) and helpers."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from kgadapt.knowledge.loader import load_models
from kgadapt.knowledge.store import GraphStore

KNOWN = Path(__file__).resolve().parent / "known_models"
SHIPPED = Path(__file__).resolve().parents[2] / "knowledge" / "models"


@pytest.fixture
def known_dir(tmp_path: Path) -> Path:
    """A private copy of the known models (tests may edit it)."""
    target = tmp_path / "models"
    shutil.copytree(KNOWN, target)
    return target


@pytest.fixture
def known_store(store: GraphStore, known_dir: Path) -> GraphStore:
    """Every backend, holding the known models."""
    load_models(store, [known_dir])
    return store


def counts(store: GraphStore) -> tuple[int, int]:
    """(nodes, relations) in the graph."""
    nodes = store.execute("MATCH (n) RETURN count(n) AS c", read_only=True)[0]["c"]
    edges = store.execute("MATCH ()-[r]->() RETURN count(r) AS c", read_only=True)[0]["c"]
    return nodes, edges


def signature(store: GraphStore) -> list[tuple]:
    """The whole graph as sorted tuples (labels, properties; relation type, ends, properties): ids left out."""
    nodes = store.execute("MATCH (n) RETURN labels(n) AS l, properties(n) AS p", read_only=True)
    edges = store.execute(
        "MATCH (a)-[r]->(b) RETURN type(r) AS t, a.name AS a, b.name AS b, properties(r) AS p", read_only=True)
    out = [("node", tuple(sorted(n["l"])), tuple(sorted((k, repr(v)) for k, v in n["p"].items()))) for n in nodes]
    out += [("edge", e["t"], e["a"], e["b"], tuple(sorted((k, repr(v)) for k, v in e["p"].items()))) for e in edges]
    return sorted(out)
