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
2.x and 3.x release.
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
NEO4J = Dialect(
    name="neo4j",
    create_form="CREATE INDEX IF NOT EXISTS FOR (n:{label}) ON (n.{prop})",
    list_statement="SHOW INDEXES YIELD labelsOrTypes AS label, properties RETURN label, properties",
)
