"""Export the knowledge graph: Graphviz ``dot`` to look at, or Cypher to recreate it elsewhere.

The Cypher export is the one place kgadapt writes values as literals: it is a
script for another store (e.g. a Memgraph server) fed by a console, where
parameters are not available. Every string is escaped (``\\``, ``'``, newline,
carriage return, tab) and every name that is not a plain identifier is back-quoted, so
the script recreates exactly the nodes, labels, properties and relations read.
One statement per line, each ending in ``;``; ``//`` lines are comments.
"""

from __future__ import annotations

import re
from typing import Any, Iterator

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.params import cypher_literal as literal
from kgadapt.knowledge.store import GraphStore
from kgadapt.shared.errors import ConfigError

FORMATS = ("dot", "cypher")
# A temporary label and key that tie relations to the nodes created by the same script.
EXPORT_LABEL = "KgadaptExport"
EXPORT_KEY = "export_id"
_IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_PRIMARY = (S.FEATURE, S.ILLUMINATION_BAND, S.PERCEPTION_GRAPH, S.COMPONENT, S.PORT, S.DEPLOYMENT,
            S.PLATFORM, S.PROCESS_PROFILE, S.ADAPTATION_DECISION, S.SITE, S.MARKER)
_COLOURS = {S.FEATURE: "#f4d03f", S.ILLUMINATION_BAND: "#f9e79f", S.PERCEPTION_GRAPH: "#5dade2",
            S.COMPONENT: "#aed6f1", S.PORT: "#eaeded", S.DEPLOYMENT: "#82e0aa", S.PLATFORM: "#f5b041",
            S.PROCESS_PROFILE: "#d7bde2", S.ADAPTATION_DECISION: "#f1948a", S.SITE: "#a3e4d7",
            S.MARKER: "#d0ece7"}


def snapshot(store: GraphStore) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Every node (id, labels, props) and relation (source, target, type, props), in id order."""
    nodes = store.execute("MATCH (n) RETURN id(n) AS id, labels(n) AS labels, properties(n) AS props "
                          "ORDER BY id", read_only=True)
    edges = store.execute("MATCH (a)-[r]->(b) RETURN id(r) AS id, id(a) AS source, id(b) AS target, "
                          "type(r) AS type, properties(r) AS props ORDER BY id", read_only=True)
    return nodes, edges


def export(store: GraphStore, fmt: str) -> str:
    """The whole graph in format ``fmt`` ("dot" or "cypher")."""
    if fmt not in FORMATS:
        raise ConfigError(f"export format {fmt!r}: use one of {', '.join(FORMATS)}")
    nodes, edges = snapshot(store)
    return to_dot(nodes, edges) if fmt == "dot" else to_cypher(nodes, edges)


# --- Cypher ---------------------------------------------------------------

def name(text: str) -> str:
    """A label, relation type or property key, back-quoted unless it is a plain identifier."""
    if _IDENT.match(text):
        return text
    return "`" + text.replace("`", "``") + "`"


def _map(props: dict[str, Any]) -> str:
    items = [f"{name(k)}: {literal(v)}" for k, v in props.items() if v is not None]
    return "{" + ", ".join(items) + "}"


def to_cypher(nodes: list[dict[str, Any]], edges: list[dict[str, Any]]) -> str:
    """Statements that recreate the graph in an empty store (one per line)."""
    lines = [f"// kgadapt knowledge export: {len(nodes)} nodes, {len(edges)} relations.",
             "// Run on an empty graph, one statement per line.",
             ]
    for node in nodes:
        labels = "".join(":" + name(label) for label in node["labels"]) + f":{EXPORT_LABEL}"
        props = {EXPORT_KEY: node["id"], **(node["props"] or {})}
        lines.append(f"CREATE ({labels} {_map(props)});")
    for edge in edges:
        props = edge["props"] or {}
        body = f" {_map(props)}" if props else ""
        lines.append(
            f"MATCH (a:{EXPORT_LABEL} {{{EXPORT_KEY}: {edge['source']}}}), "
            f"(b:{EXPORT_LABEL} {{{EXPORT_KEY}: {edge['target']}}}) "
            f"CREATE (a)-[:{name(edge['type'])}{body}]->(b);")
    lines.append(f"MATCH (n:{EXPORT_LABEL}) REMOVE n:{EXPORT_LABEL} REMOVE n.{EXPORT_KEY};")
    return "\n".join(lines) + "\n"


def statements(script: str) -> Iterator[str]:
    """The statements of an exported script (comments and blank lines skipped)."""
    for line in script.split("\n"):
        line = line.strip()
        if line and not line.startswith("//"):
            yield line[:-1] if line.endswith(";") else line


def import_script(store: GraphStore, script: str) -> int:
    """Run an exported script against ``store``; return the number of statements."""
    count = 0
    for statement in statements(script):
        store.execute(statement)
        count += 1
    return count


# --- dot ------------------------------------------------------------------

def _dot_text(text: str) -> str:
    return text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def to_dot(nodes: list[dict[str, Any]], edges: list[dict[str, Any]]) -> str:
    """A Graphviz digraph: one box per node (its main label and name), one arrow per relation."""
    out = ["digraph kgadapt {", "  rankdir=LR;",
           '  node [shape=box, style="rounded,filled", fontname="Helvetica", fontsize=10];',
           '  edge [fontname="Helvetica", fontsize=8];']
    for node in nodes:
        labels = node["labels"] or []
        primary = next((label for label in _PRIMARY if label in labels), labels[0] if labels else "")
        props = node["props"] or {}
        title = str(props.get("name", node["id"]))
        colour = _COLOURS.get(primary, "#ffffff")
        out.append(f'  n{node["id"]} [label="{_dot_text(primary)}\\n{_dot_text(title)}", fillcolor="{colour}"];')
    for edge in edges:
        out.append(f'  n{edge["source"]} -> n{edge["target"]} [label="{_dot_text(edge["type"])}"];')
    out.append("}")
    return "\n".join(out) + "\n"
