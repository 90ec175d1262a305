"""What every importer produces: node and edge specifications, not Cypher.

An importer reads one model file and returns a :class:`ParsedModel`: the nodes
it defines (primary label from ``knowledge/schema.py``, a name, properties)
and the relations it asserts, each with the file and line it came from. Names
in relations are references; the loader resolves them across every file of a
load (and the models already in the store), so that one model may name what
another defines, as the paper's domain models do.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

from kgadapt.shared.errors import ModelError


@dataclass(frozen=True)
class Origin:
    """Where in a model file something was written."""

    path: str
    line: int

    def error(self, message: str) -> ModelError:
        """A :class:`ModelError` pointing here."""
        return ModelError(self.path, self.line, message)


@dataclass
class NodeSpec:
    """One node a model defines. ``label`` is its primary label (names are unique within it)."""

    label: str
    name: str
    props: dict[str, Any]
    origin: Origin
    extra_labels: tuple[str, ...] = ()


@dataclass(frozen=True)
class Ref:
    """A reference by name to a node of one of ``labels`` (``what`` says what kind of thing, for people)."""

    labels: tuple[str, ...]
    name: str
    what: str
    shown: str | None = None  # how to name it in a message, when "WHAT 'NAME'" would not read well

    def describe(self) -> str:
        return self.shown or f"{self.what} {self.name!r}"


# Called with the two resolved node specs (None when the node lives only in the
# store); returns what is wrong, or None.
EdgeCheck = Callable[["NodeSpec | None", "NodeSpec | None"], "str | None"]


@dataclass
class EdgeSpec:
    """One relation a model asserts. ``key`` properties take part in its identity."""

    type: str
    source: Ref
    target: Ref
    origin: Origin
    key: dict[str, Any] = field(default_factory=dict)
    check: EdgeCheck | None = None


@dataclass
class ParsedModel:
    """The nodes and relations of one model file."""

    path: str
    notation: str
    nodes: list[NodeSpec] = field(default_factory=list)
    edges: list[EdgeSpec] = field(default_factory=list)
