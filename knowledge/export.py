"""Export a robot's knowledge: Graphviz ``dot`` to look at, or Cypher to recreate it elsewhere.

A robot's knowledge is in one or more graphs (:class:`kgadapt.knowledge.schema.Graph`: on FalkorDB over RESP
its fleet roster has a graph of its own beside the robot's); an export holds every part, each under a line
``// kgadapt graph PART: ...`` (``robot``, ``fleet_roster``), so that :func:`import_script` (``kgadapt
knowledge import``) puts each part where the store it restores into keeps it. A console fed the whole
script puts every part in one graph, where a store of one graph (Memgraph, Neo4j) keeps them all. A script
without such lines (written before the roster had a graph of its own) is the robot's graph; a roster found
in it is moved where the store keeps the roster.

The Cypher export is the one place kgadapt writes values as literals: it is a
script for another store (e.g. a Memgraph server) fed by a console, where
parameters are not available. Every string is escaped (``\\``, ``'``, newline,
carriage return, tab) and every name that is not a plain identifier is back-quoted, so
the script recreates exactly the nodes, labels, properties and relations read.
One statement per line, each ending in ``;``; ``//`` lines are comments.
"""

from __future__ import annotations

import logging
import re
import secrets
from typing import Any, Iterator, NamedTuple

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.params import cypher_literal as literal
from kgadapt.knowledge.store import STAGED_MARK, GraphStore
from kgadapt.shared.errors import ConfigError, KgadaptError, QueryError, StoreUnavailable

log = logging.getLogger(__name__)
FORMATS = ("dot", "cypher")
# A temporary label and key that tie relations to the nodes created by the same part of a script.
EXPORT_LABEL = "KgadaptExport"
EXPORT_KEY = "export_id"
# A staged import's graphs (FalkorDB over RESP): <robot graph>.import-partial.<token>[.fleet_roster], each holding
# one node of this label until it is put in place.
STAGED_LABEL = "KgadaptImport"
PART_LINE = "// kgadapt graph "  # then the part's name (schema.Graph, lower case), ":" and its counts
_IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_PRIMARY = (S.FEATURE, S.ILLUMINATION_BAND, S.PERCEPTION_GRAPH, S.COMPONENT, S.PORT, S.DEPLOYMENT,
            S.PLATFORM, S.PROCESS_PROFILE, S.ADAPTATION_DECISION, S.SITE, S.MARKER, S.FLEET_ROBOT)
_COLOURS = {S.FEATURE: "#f4d03f", S.ILLUMINATION_BAND: "#f9e79f", S.PERCEPTION_GRAPH: "#5dade2",
            S.COMPONENT: "#aed6f1", S.PORT: "#eaeded", S.DEPLOYMENT: "#82e0aa", S.PLATFORM: "#f5b041",
            S.PROCESS_PROFILE: "#d7bde2", S.ADAPTATION_DECISION: "#f1948a", S.SITE: "#a3e4d7",
            S.MARKER: "#d0ece7", S.FLEET_ROBOT: "#cacfd2"}


class Part(NamedTuple):
    """One part of a robot's knowledge as read: which part, its nodes and its relations."""

    graph: S.Graph
    nodes: list[dict[str, Any]]
    edges: list[dict[str, Any]]


def part_name(part: S.Graph) -> str:
    return part.name.lower()


def snapshot(store: GraphStore, part: S.Graph = S.Graph.ROBOT) -> Part:
    """Every node (id, labels, props) and relation (source, target, type, props) of ``part`` of the robot whose
    store is ``store``, in id order: the graph that holds it, or, where that graph holds other parts too (a
    store of one graph), its nodes told apart by label."""
    graph = part.store(store)
    nodes = graph.execute(f"MATCH (n) {_where(part, store, 'n')} RETURN id(n) AS id, labels(n) AS labels, "
                          "properties(n) AS props ORDER BY id", read_only=True)
    edges = graph.execute(f"MATCH (a)-[r]->(b) {_where(part, store, 'a', 'b')} RETURN id(r) AS id, "
                          "id(a) AS source, id(b) AS target, type(r) AS type, properties(r) AS props ORDER BY id",
                          read_only=True)
    return Part(part, nodes, edges)


def _where(part: S.Graph, store: GraphStore, *variables: str) -> str:
    """``WHERE`` the nodes bound to ``variables`` are of ``part``, or "" where its graph holds it alone (labels
    are the schema's names, never values)."""
    graph = part.store(store)
    others = [other for other in S.Graph if other is not part and other.store(store) is graph]
    if not others:
        return ""
    if part.labels:
        return "WHERE " + " AND ".join("(" + " OR ".join(f"{var}:{name(label)}" for label in part.labels) + ")"
                                       for var in variables)
    kept = [label for other in others for label in other.labels]  # the robot's part: whatever no other holds
    return "WHERE " + " AND ".join("NOT (" + " OR ".join(f"{var}:{name(label)}" for label in kept) + ")"
                                   for var in variables)


def export(store: GraphStore, fmt: str) -> str:
    """Every part of the robot's knowledge whose store is ``store``, in format ``fmt`` ("dot" or "cypher")."""
    if fmt not in FORMATS:
        raise ConfigError(f"export format {fmt!r}: use one of {', '.join(FORMATS)}")
    parts = [snapshot(store, part) for part in S.Graph]
    return to_dot(parts) if fmt == "dot" else to_cypher(parts)


# --- Cypher ---------------------------------------------------------------

def name(text: str) -> str:
    """A label, relation type or property key, back-quoted unless it is a plain identifier."""
    if _IDENT.match(text):
        return text
    return "`" + text.replace("`", "``") + "`"


def _map(props: dict[str, Any]) -> str:
    items = [f"{name(k)}: {literal(v)}" for k, v in props.items() if v is not None]
    return "{" + ", ".join(items) + "}"


def to_cypher(parts: list[Part]) -> str:
    """Statements that recreate the parts in an empty store (one per line), each part under its line."""
    nodes, edges = sum(len(p.nodes) for p in parts), sum(len(p.edges) for p in parts)
    lines = [f"// kgadapt knowledge export: {nodes} nodes, {edges} relations.",
             "// Run on an empty store, one statement per line: kgadapt knowledge import puts each part in the "
             "graph its store keeps it in; a console fed it all puts every part in one graph.",
             ]
    for part in parts:
        lines.append(f"{PART_LINE}{part_name(part.graph)}: {len(part.nodes)} nodes, {len(part.edges)} relations")
        lines.extend(_statements(part))
    return "\n".join(lines) + "\n"


def _statements(part: Part) -> list[str]:
    lines = []
    for node in part.nodes:
        labels = "".join(":" + name(label) for label in node["labels"]) + f":{EXPORT_LABEL}"
        props = {EXPORT_KEY: node["id"], **(node["props"] or {})}
        lines.append(f"CREATE ({labels} {_map(props)});")
    for edge in part.edges:
        props = edge["props"] or {}
        body = f" {_map(props)}" if props else ""
        lines.append(
            f"MATCH (a:{EXPORT_LABEL} {{{EXPORT_KEY}: {edge['source']}}}), "
            f"(b:{EXPORT_LABEL} {{{EXPORT_KEY}: {edge['target']}}}) "
            f"CREATE (a)-[:{name(edge['type'])}{body}]->(b);")
    if part.nodes:  # each part's ids are its graph's: a part's temporary keys are gone before the next part's
        lines.append(f"MATCH (n:{EXPORT_LABEL}) REMOVE n:{EXPORT_LABEL} REMOVE n.{EXPORT_KEY};")
    return lines


def statements(script: str, source: str = "script") -> Iterator[tuple[S.Graph, int, str]]:
    """The statements of an exported script: (the part they belong to, line number, statement), comments
    and blank lines skipped. ConfigError naming ``source`` and the line for a part this version does not know."""
    part = S.Graph.ROBOT  # a script without part lines: the robot's graph
    parts = {part_name(graph): graph for graph in S.Graph}
    for number, line in enumerate(script.split("\n"), 1):
        line = line.strip()
        if line.startswith(PART_LINE):
            named = line[len(PART_LINE):].partition(":")[0].strip()
            if named not in parts:
                raise ConfigError(f"{source}:{number}: unknown part {named!r} of a robot's knowledge "
                                  f"(known: {', '.join(parts)})")
            part = parts[named]
        elif line and not line.startswith("//"):
            yield part, number, line[:-1] if line.endswith(";") else line


def import_script(store: GraphStore, script: str, *, source: str = "script") -> int:
    """Run an exported script against the robot's store ``store``, each part in the graph that store keeps it
    in; a roster found in the robot's graph (a script of an older version) is then moved where the store keeps
    it. The number of statements; QueryError naming ``source`` and the line of a statement the store refused."""
    return _run(store, list(statements(script, source)), source)  # a script naming an unknown part: nothing run


def _run(store: GraphStore, planned: list[tuple[S.Graph, int, str]], source: str) -> int:
    """:func:`import_script` of statements already read (:func:`statements`)."""
    from kgadapt.knowledge.fleet_roster import move_roster

    for part, number, statement in planned:
        try:
            part.store(store).execute(statement)
        except QueryError as exc:
            raise QueryError(f"{source}:{number}: {exc}") from exc
    roster = S.Graph.FLEET_ROSTER.store(store)
    if roster is not store:
        move_roster(store, roster)
    return len(planned)


def restore(store: GraphStore, script: str, *, source: str = "script") -> int:
    """:func:`import_script` into a store that holds nothing of a robot yet (ConfigError naming what it holds),
    all or nothing as every reader of the store sees it; the number of statements run.

    FalkorDB over RESP (``capabilities.graphs``): the script runs into staged graphs beside the robot's
    (:func:`staged_name`), which one MULTI/EXEC then renames into place, so a refused statement, or an importer
    killed midway, leaves the store's graphs untouched; staged graphs left by a killed import are deleted by the
    next import. A store with transactions (Memgraph, Neo4j): one transaction. FalkorDB's Bolt listener has
    none: statement by statement, a refused one empties the store again, and an importer killed midway leaves
    part of the import (the next import names what the store holds)."""
    planned = list(statements(script, source))  # a script naming an unknown part: nothing run
    _refuse_unless_empty(store)
    if store.capabilities.graphs:
        return _staged(store, planned, source)
    if store.capabilities.transactions:
        return _in_one_transaction(store, planned, source)
    try:
        return _run(store, planned, source)
    except BaseException as exc:
        try:
            store.clear()  # it was empty: nothing half-written stays
        except KgadaptError as again:
            raise StoreUnavailable(f"{exc}; emptying store {store.url} again failed too ({again}): it holds part "
                                   "of the import") from exc
        raise


def _refuse_unless_empty(store: GraphStore) -> None:
    held = {part: count for part, count in node_counts(store).items() if count}
    if held:
        what = ", ".join(f"{count} nodes in its {part}" for part, count in held.items())
        raise ConfigError(f"store {store.url} is not empty ({what}): import into an empty store, e.g. "
                          "--store embedded:NEW_DIR")


def staged_name(graph: str, token: str) -> str:
    """The graph an import into the robot's graph ``graph`` is written to before it is put in place: never a
    robot's graph by name, and its parts beside it (``<staged>.fleet_roster``) start with it too."""
    return f"{graph}{STAGED_MARK}{token}"


def _staged(store: GraphStore, planned: list[tuple[S.Graph, int, str]], source: str) -> int:
    from kgadapt.knowledge.falkordb_store import FalkorDBStore

    if not isinstance(store, FalkorDBStore):  # capabilities.graphs: FalkorDB over RESP is the one such backend
        raise ConfigError(f"store {store.url}: staged imports need FalkorDB over RESP")
    robot_graph = store.settings.graph
    for left in store.graph_names():  # a killed import's: never anyone's knowledge
        if left.startswith(robot_graph + STAGED_MARK):
            store.drop_graph(left)
    token = secrets.token_hex(6)
    staged = store.sibling(staged_name(robot_graph, token))
    moves = {part: part.store(staged) for part in S.Graph}
    try:
        for graph in moves.values():  # the mark that this import wrote it, checked as it is put in place
            graph.execute(f"CREATE (:{STAGED_LABEL} {{token: $token}})", {"token": token})
        count = _run(staged, planned, source)
        store.swap_in({graph.settings.graph: part.beside(robot_graph) for part, graph in moves.items()},
                      marker=STAGED_LABEL, check=lambda: _refuse_unless_empty(store))
        return count
    except BaseException:
        try:
            for graph in moves.values():
                store.drop_graph(graph.settings.graph)
        except KgadaptError as again:  # the next import deletes them
            log.warning("store %s: cannot delete the staged graphs of a failed import: %s", store.url, again)
        raise


def _in_one_transaction(store: GraphStore, planned: list[tuple[S.Graph, int, str]], source: str) -> int:
    from kgadapt.knowledge.bolt_store import BoltStore

    if not isinstance(store, BoltStore) or any(part.store(store) is not store for part, _, _ in planned):
        raise ConfigError(f"store {store.url}: an import in one transaction needs a Bolt store of one graph")
    store.execute_script([(f"{source}:{number}", statement) for _, number, statement in planned])
    return len(planned)


def node_counts(store: GraphStore) -> dict[str, int]:
    """How many nodes each part of the robot's knowledge holds, by part name."""
    counts = {}
    for part in S.Graph:
        rows = part.store(store).execute(f"MATCH (n) {_where(part, store, 'n')} RETURN count(n) AS n",
                                         read_only=True)
        counts[part_name(part)] = int(rows[0]["n"]) if rows else 0
    return counts


# --- dot ------------------------------------------------------------------

def _dot_text(text: str) -> str:
    return text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def to_dot(parts: list[Part]) -> str:
    """A Graphviz digraph: one box per node (its main label and name), one arrow per relation."""
    out = ["digraph kgadapt {", "  rankdir=LR;",
           '  node [shape=box, style="rounded,filled", fontname="Helvetica", fontsize=10];',
           '  edge [fontname="Helvetica", fontsize=8];']
    for part in parts:
        # Ids are per graph: the parts kept beside the robot's graph get their own prefix.
        prefix = "n" if part.graph is S.Graph.ROBOT else f"{part_name(part.graph)}_n"
        for node in part.nodes:
            labels = node["labels"] or []
            primary = next((label for label in _PRIMARY if label in labels), labels[0] if labels else "")
            props = node["props"] or {}
            title = str(props.get("name", node["id"]))
            colour = _COLOURS.get(primary, "#ffffff")
            out.append(f'  {prefix}{node["id"]} [label="{_dot_text(primary)}\\n{_dot_text(title)}", '
                       f'fillcolor="{colour}"];')
        for edge in part.edges:
            out.append(f'  {prefix}{edge["source"]} -> {prefix}{edge["target"]} [label="{_dot_text(edge["type"])}"];')
    out.append("}")
    return "\n".join(out) + "\n"
