"""How each store spells what Cypher leaves to the implementation: index statements.

Every query of ``knowledge/queries.py`` stays in the subset that FalkorDB,
Memgraph and Neo4j all accept; only index creation and listing differ, and
the backend (not an error message) chooses the dialect:

==========  ==========================================  ==================================
store       create an index                             list indexes
==========  ==========================================  ==================================
FalkorDB    ``CREATE INDEX FOR (n:L) ON (n.p)``         ``CALL db.indexes()``
Memgraph    ``CREATE INDEX ON :L(p)`` (2.x and 3.x)     ``SHOW INDEX INFO``
Neo4j 5     ``CREATE INDEX IF NOT EXISTS FOR …``        ``SHOW INDEXES``
==========  ==========================================  ==================================

Memgraph accepts ``CREATE INDEX FOR …`` only from 3.10, and has neither
``db.indexes()`` nor ``dbms.components()``; its own form works on every
2.x and 3.x release. Neo4j before 4.0 knew only ``CREATE INDEX ON :L(p)``.

Which dialect a Bolt server speaks comes from what it says it is, the agent
of its HELLO reply (:func:`dialect_for_agent`), never from the URL: the
scheme (``bolt://``, ``memgraph://``, their TLS forms) only chooses the
transport. Memgraph announces ``Neo4j/v5.11.0 compatible graph database
server - Memgraph``; Neo4j ``Neo4j/5.26.0``. FalkorDB's Bolt listener
claims to be Neo4j and is found by behaviour instead (knowledge/bolt_store.py).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Iterable

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def _checked(name: str) -> str:
    if not _NAME.match(name):
        raise ValueError(f"index name part {name!r}: use letters, digits and _")
    return name


@dataclass(frozen=True, kw_only=True)
class Dialect:
    """One store's index statements."""

    name: str
    create_form: str  # format string with {label} and {prop}
    list_statement: str

    def create_index(self, label: str, prop: str) -> str:
        return self.create_form.format(label=_checked(label), prop=_checked(prop))

    def indexed(self, rows: Iterable[dict[str, Any]]) -> set[tuple[str, str]]:
        """(label, property) pairs of single-property label indexes in the list statement's rows."""
        found: set[tuple[str, str]] = set()
        for row in rows:
            label = row.get("label")
            props = row.get("property", row.get("properties"))
            if isinstance(label, list):  # Neo4j: labelsOrTypes
                label = label[0] if len(label) == 1 else None
            if isinstance(props, str):
                props = [props]
            if isinstance(label, str) and isinstance(props, list) and len(props) == 1:
                found.add((label, str(props[0])))
        return found


FALKORDB = Dialect(
    name="falkordb",
    create_form="CREATE INDEX FOR (n:{label}) ON (n.{prop})",
    list_statement="CALL db.indexes() YIELD label, properties RETURN label, properties",
)
MEMGRAPH = Dialect(
    name="memgraph",
    create_form="CREATE INDEX ON :{label}({prop})",
    list_statement="SHOW INDEX INFO",
)
NEO4J_3 = Dialect(
    name="neo4j3",
    create_form="CREATE INDEX ON :{label}({prop})",
    list_statement="CALL db.indexes() YIELD tokenNames AS label, properties RETURN label, properties",
)
NEO4J = Dialect(
    name="neo4j",
    create_form="CREATE INDEX IF NOT EXISTS FOR (n:{label}) ON (n.{prop})",
    list_statement="SHOW INDEXES YIELD labelsOrTypes AS label, properties RETURN label, properties",
)


_NEO4J_VERSION = re.compile(r"^neo4j/v?(\d+)", re.IGNORECASE)


def dialect_for_agent(agent: str | None) -> Dialect:
    """The dialect of a Bolt server that announced itself as ``agent`` (its HELLO reply's ``server``).

    Memgraph names itself after the Neo4j version it is compatible with
    (``Neo4j/v5.11.0 compatible graph database server - Memgraph``): the name
    decides, not the version. Neo4j's own agent is ``Neo4j/<version>``; before
    4.0 it had only the ``ON :L(p)`` form. Anything else speaks Neo4j's current
    Cypher as far as we know.
    """
    text = (agent or "").strip()
    if "memgraph" in text.lower():
        return MEMGRAPH
    match = _NEO4J_VERSION.match(text)
    if match and int(match.group(1)) < 4:
        return NEO4J_3
    return NEO4J
