"""Load domain models into the graph: parse every file, check everything, then write once.

``load_models(store, paths)`` is all or nothing: every file is parsed by the
importer its extension names, every reference is resolved (across the files
of this load, then against models already in the store), and only then is the
whole graph change sent as one ``execute_atomic`` batch of parameterised
statements made from fixed templates (labels and relation types come from
``knowledge/schema.py``, values travel as parameters).

Reloading is idempotent. Nodes are MERGEd on their primary label and name and
carry ``model_file`` and ``model_keys`` (the properties their model set);
relations carry ``model_file``. A reload replaces what the reloaded files said
before: their relations are deleted and written again, nodes they no longer
define are deleted, properties a model no longer sets are removed (the old
``model_keys`` say which), and when a directory is loaded, whatever came from
a file under it that no longer exists goes too. Run-time knowledge survives a
reload: properties written at run time onto model nodes (a platform's live
figures, the flight state) are not among ``model_keys`` and are left alone;
process profiles, decisions and calibration relations are never touched.
"""

from __future__ import annotations

import logging
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.importers import IMPORTERS, parse_file
from kgadapt.knowledge.importers.model import EdgeSpec, NodeSpec, ParsedModel, Ref
from kgadapt.knowledge.importers.rpsl import COMPONENT_KINDS
from kgadapt.knowledge.store import GraphStore, Statement
from kgadapt.shared.errors import ModelError

log = logging.getLogger(__name__)

# Labels whose nodes come from model files (the ones a reload may delete).
MODEL_LABELS = (S.FEATURE, S.ILLUMINATION_BAND, S.PERCEPTION_GRAPH, S.COMPONENT, S.PORT, S.DEPLOYMENT, S.PLATFORM,
                S.SITE, S.MARKER)
# Sub-labels a node may lose when its model changes kind.
_SUBLABELS = {S.COMPONENT: COMPONENT_KINDS, S.DEPLOYMENT: (S.SYSTEMD_SERVICE_FILE, S.DEPLOYMENT_FILE)}
MODEL_KEYS = "model_keys"  # node property: the keys its model set (so a reload knows what to remove)


@dataclass(frozen=True)
class LoadReport:
    """What a load wrote: files, nodes per label (every label a node carries) and relations per type."""

    files: tuple[str, ...]
    labels: dict[str, int] = field(default_factory=dict)
    relations: dict[str, int] = field(default_factory=dict)
    statements: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {"files": list(self.files), "labels": dict(self.labels), "relations": dict(self.relations)}

    def rows(self) -> list[dict[str, Any]]:
        """One row per label and relation type, for a table."""
        return ([{"kind": "label", "name": k, "count": v} for k, v in sorted(self.labels.items())]
                + [{"kind": "relation", "name": k, "count": v} for k, v in sorted(self.relations.items())])


@dataclass
class ResolvedModels:
    """Every model of one load, checked, with each relation's end labels known."""

    models: list[ParsedModel]
    roots: list[str]  # directories loaded (their stale files are swept)
    nodes: dict[tuple[str, str], NodeSpec]
    edges: list[tuple[EdgeSpec, str, str]]  # (edge, source label, target label)

    @property
    def files(self) -> list[str]:
        return [m.path for m in self.models]


def collect_files(paths: Iterable[Path | str]) -> tuple[list[Path], list[Path]]:
    """The model files named by ``paths`` (directories searched recursively) and the directories."""
    files: list[Path] = []
    roots: list[Path] = []
    for raw in paths:
        path = Path(raw).absolute()
        if path.is_dir():
            found = sorted(p for p in path.rglob("*") if p.is_file() and p.suffix in IMPORTERS)
            if not found:
                raise ModelError(str(path), None, f"no model files here (looked for {', '.join(IMPORTERS)})")
            roots.append(Path(os.path.normpath(path)))  # as the files are: "../m" must find what came from "m"
            files.extend(found)
        elif path.is_file():
            files.append(path)
        else:
            raise ModelError(str(raw), None, "no such file or directory")
    unique = list(dict.fromkeys(Path(os.path.normpath(f)) for f in files))
    return unique, roots


def check_models(paths: Sequence[Path | str], store: GraphStore | None = None) -> ResolvedModels:
    """Parse and check every model file; nothing is written. ``store`` resolves names defined earlier."""
    files, roots = collect_files(paths)
    models = [parse_file(f) for f in files]
    nodes: dict[tuple[str, str], NodeSpec] = {}
    for model in models:
        for node in model.nodes:
            key = (node.label, node.name)
            if key in nodes:
                first = nodes[key].origin
                raise node.origin.error(f"duplicate {node.label} name {node.name!r} "
                                        f"(first defined at {first.path}:{first.line})")
            nodes[key] = node
    file_names = [m.path for m in models]
    in_store = _names_in_store(store, models, nodes, file_names, [str(r) for r in roots])
    edges: list[tuple[EdgeSpec, str, str]] = []
    seen: dict[tuple[Any, ...], EdgeSpec] = {}
    for model in models:
        for edge in model.edges:
            source = _resolve(edge.source, edge, nodes, in_store)
            target = _resolve(edge.target, edge, nodes, in_store)
            if edge.check is not None:
                problem = edge.check(nodes.get((source, edge.source.name)), nodes.get((target, edge.target.name)))
                if problem:
                    raise edge.origin.error(problem)
            identity = (edge.type, source, edge.source.name, target, edge.target.name, tuple(sorted(edge.key.items())))
            if identity in seen:
                first = seen[identity].origin
                raise edge.origin.error(f"{edge.type} from {edge.source.name!r} to {edge.target.name!r} "
                                        f"stated twice (first at {first.path}:{first.line})")
            seen[identity] = edge
            edges.append((edge, source, target))
    return ResolvedModels(models=models, roots=[str(r) for r in roots], nodes=nodes, edges=edges)


def _names_in_store(store: GraphStore | None, models: list[ParsedModel], nodes: dict[tuple[str, str], NodeSpec],
                    files: list[str], roots: list[str]) -> set[tuple[str, str]]:
    """(label, name) of model-defined nodes in the store that this load refers to and will keep."""
    if store is None:
        return set()
    wanted: dict[str, set[str]] = {}
    for model in models:
        for edge in model.edges:
            for ref in (edge.source, edge.target):
                if not any((label, ref.name) in nodes for label in ref.labels):
                    for label in ref.labels:
                        wanted.setdefault(label, set()).add(ref.name)
    found: set[tuple[str, str]] = set()
    for label, names in wanted.items():
        rows = store.execute(  # no rows from a graph never written to (GraphStore.execute)
            f"MATCH (n:{label}) WHERE n.name IN $names AND n.model_file IS NOT NULL "
            "AND NOT n.model_file IN $files RETURN n.name AS name, n.model_file AS file",
            {"names": sorted(names), "files": files}, read_only=True)
        for row in rows:
            if not any(str(row["file"]).startswith(root + os.sep) for root in roots):  # swept by this load
                found.add((label, row["name"]))
    return found


def _resolve(ref: Ref, edge: EdgeSpec, nodes: dict[tuple[str, str], NodeSpec], in_store: set[tuple[str, str]]) -> str:
    here = [label for label in ref.labels if (label, ref.name) in nodes]
    if not here:
        here = [label for label in ref.labels if (label, ref.name) in in_store]
    if len(here) == 1:
        return here[0]
    if not here:
        raise edge.origin.error(f"unknown {ref.describe()}: no model defines it")
    raise edge.origin.error(f"{ref.describe()} is ambiguous: both a {' and a '.join(here)} have that name")


def plan(resolved: ResolvedModels, previous_keys: Mapping[tuple[str, str], Sequence[str]] | None = None,
         ) -> list[Statement]:
    """The statements that make the store hold exactly what the models say (run-time facts kept).

    ``previous_keys`` maps (label, name) to the ``model_keys`` a node had before this load.
    """
    previous_keys = previous_keys or {}
    files = resolved.files
    statements: list[Statement] = []
    for label in MODEL_LABELS:
        keep = sorted(name for (lab, name) in resolved.nodes if lab == label)
        statements.append((
            f"MATCH (n:{label}) WHERE n.model_file IN $files AND NOT n.name IN $keep DETACH DELETE n",
            {"files": files, "keep": keep}))
        for root in resolved.roots:
            statements.append((
                f"MATCH (n:{label}) WHERE n.model_file STARTS WITH $prefix AND NOT n.name IN $keep DETACH DELETE n",
                {"prefix": root + os.sep, "keep": keep}))
    statements.append(("MATCH ()-[r]->() WHERE r.model_file IN $files DELETE r", {"files": files}))
    for root in resolved.roots:
        statements.append(("MATCH ()-[r]->() WHERE r.model_file STARTS WITH $prefix DELETE r",
                           {"prefix": root + os.sep}))
    for key, node in resolved.nodes.items():
        statements.append(_upsert(node, previous_keys.get(key, ())))
    for edge, source, target in resolved.edges:
        keys = ", ".join(f"{k}: $key_{k}" for k in edge.key)
        for k in edge.key:
            assert k.isidentifier(), k  # key names come from importer code, never from model text
        statements.append((
            f"MATCH (a:{source} {{name: $source}}), (b:{target} {{name: $target}}) "
            f"MERGE (a)-[r:{edge.type}{' {' + keys + '}' if keys else ''}]->(b) SET r.model_file = $file",
            {"source": edge.source.name, "target": edge.target.name, "file": edge.origin.path,
             **{f"key_{k}": v for k, v in edge.key.items()}}))
    return statements


def _upsert(node: NodeSpec, previous: Sequence[str]) -> Statement:
    props = {**node.props, "model_file": node.origin.path}
    # += keeps what run-time writers put on the node; keys the model set before and
    # no longer sets are set to null, which removes them.
    gone = {k: None for k in previous if k not in props and k != MODEL_KEYS}
    props = {**gone, **props, MODEL_KEYS: sorted(props)}
    labels = "".join(f":{label}" for label in node.extra_labels)
    set_labels = f" SET n{labels}" if labels else ""
    drop = [label for label in _SUBLABELS.get(node.label, ()) if label not in node.extra_labels]
    remove = f" REMOVE n{''.join(':' + label for label in drop)}" if drop else ""
    return f"MERGE (n:{node.label} {{name: $name}}) SET n += $props{set_labels}{remove}", {
        "name": node.name, "props": props}


def previous_model_keys(store: GraphStore, resolved: ResolvedModels) -> dict[tuple[str, str], list[str]]:
    """The ``model_keys`` the store's nodes carry now, for the nodes this load writes."""
    wanted: dict[str, list[str]] = {}
    for label, name in resolved.nodes:
        wanted.setdefault(label, []).append(name)
    found: dict[tuple[str, str], list[str]] = {}
    for label, names in wanted.items():
        rows = store.execute(f"MATCH (n:{label}) WHERE n.name IN $names AND n.{MODEL_KEYS} IS NOT NULL "
                             f"RETURN n.name AS name, n.{MODEL_KEYS} AS keys", {"names": sorted(names)},
                             read_only=True)
        for row in rows:
            found[(label, row["name"])] = list(row["keys"] or [])
    return found


def report(resolved: ResolvedModels, statements: int = 0) -> LoadReport:
    labels: Counter[str] = Counter()
    for node in resolved.nodes.values():
        labels[node.label] += 1
        for label in node.extra_labels:
            labels[label] += 1
    relations = Counter(edge.type for edge, _, _ in resolved.edges)
    return LoadReport(files=tuple(resolved.files), labels=dict(labels), relations=dict(relations),
                      statements=statements)


def load_models(store: GraphStore, paths: Sequence[Path | str]) -> LoadReport:
    """Check every model under ``paths``, then write them all in one atomic batch.

    A setup step of the store (GraphStore.prepare): each answer bounded, and the whole load run once more
    on a restarted server if a fresh embedded one never answers. Safe to run twice: the batch is atomic
    and it MERGEs.
    """
    return store.prepare(lambda bounded: _load(bounded, paths))


def _load(store: GraphStore, paths: Sequence[Path | str]) -> LoadReport:
    resolved = check_models(paths, store)
    statements = plan(resolved, previous_model_keys(store, resolved))
    S.ensure_indexes(store)
    store.execute_atomic(statements)
    store.compact()
    log.info("loaded %d model files in %d statements", len(resolved.models), len(statements))
    return report(resolved, len(statements))
