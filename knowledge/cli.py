"""``kgadapt knowledge``: load models, ask named queries, run read-only Cypher, export and import a robot's knowledge.

Every subcommand takes ``--store URL`` (default ``$KGADAPT_STORE``, else the
embedded store in the user's data directory); ``--json`` where the output is
data. ``kgadapt knowledge serve`` is added by ``kgadapt.knowledge.service_cli`` through the
command registry (it needs Zenoh, and lives with the service's other commands).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from kgadapt.knowledge.schema import Graph
from kgadapt.knowledge.store import STORE_ENV, open_store, rows_as_table
from kgadapt.shared.errors import ConfigError

_STORE_HELP = f"graph store URL (default: ${STORE_ENV}, else the embedded store); e.g. embedded:DIR, falkordb://HOST:PORT, bolt://HOST:PORT"


def _store_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--store", metavar="URL", default=None, help=_STORE_HELP)


def register(subparsers: Any) -> Any:
    """Add ``kgadapt knowledge`` and its subcommands; returns them, for ``serve`` to join."""
    parser = subparsers.add_parser(
        "knowledge", help="load domain models, query the knowledge graph, export it",
        description="The robot's software knowledge: domain models in a graph, queried with Cypher.")
    sub = parser.add_subparsers(dest="knowledge_command", metavar="SUBCOMMAND")
    sub.required = True

    load = sub.add_parser("load", help="check and load model files or directories (all or nothing)",
                          description="Parse every model file (.rpsl .platform .service .deploy .features .site) under "
                                      "the given paths, check them all, then write them in one batch. Loading "
                                      "again replaces what the files said before; run-time facts are kept.")
    load.add_argument("paths", nargs="+", metavar="PATH", help="model file or directory (searched recursively)")
    load.add_argument("--check", action="store_true",
                      help="only parse and check; write nothing (with --store: names may come from models loaded there)")
    load.add_argument("--json", action="store_true", help="print the counts as JSON")
    _store_arg(load)
    load.set_defaults(func=_load)

    query = sub.add_parser("query", help="run a named query",
                           description="Run a named query (see 'kgadapt knowledge queries') with parameters.")
    query.add_argument("name", help="query name")
    query.add_argument("--param", "-p", action="append", default=[], metavar="KEY=VALUE",
                       help="a parameter (repeat for more); typed as the query declares")
    query.add_argument("--json", action="store_true", help="print the rows as JSON")
    _time_limit_arg(query)
    _store_arg(query)
    query.set_defaults(func=_query)

    listing = sub.add_parser("queries", help="list the named queries and their parameters")
    listing.add_argument("--json", action="store_true", help="print the list as JSON")
    _store_arg(listing)
    listing.set_defaults(func=_queries)

    cypher = sub.add_parser("cypher", help="run one read-only Cypher query",
                            description="Run one read-only Cypher query of the subset other robots may send "
                                        "(MATCH, OPTIONAL MATCH, WHERE, WITH, UNWIND, RETURN, ORDER BY, SKIP, LIMIT, "
                                        "UNION; no CALL, no LOAD CSV): anything else is refused before it reaches "
                                        "the store.")
    cypher.add_argument("text", metavar="QUERY", help="the Cypher text; values as $parameters")
    cypher.add_argument("--param", "-p", action="append", default=[], metavar="KEY=VALUE",
                        help="a parameter; the value is read as JSON when it parses, else as a string")
    cypher.add_argument("--json", action="store_true", help="print the rows as JSON")
    _time_limit_arg(cypher)
    _store_arg(cypher)
    cypher.set_defaults(func=_cypher)

    export = sub.add_parser("export", help="export the robot's knowledge as Graphviz dot or as Cypher statements",
                            description="Every part of the robot's knowledge: its graph and its fleet roster (on "
                                        "FalkorDB a graph beside it). dot: to look at (dot -Tsvg). cypher: "
                                        "statements that recreate it in an empty store (one per line): kgadapt "
                                        "knowledge import, or a console of e.g. a Memgraph server.")
    export.add_argument("--format", choices=("dot", "cypher"), default="dot", help="output format (default dot)")
    export.add_argument("--output", "-o", metavar="FILE", help="write here instead of standard output")
    _store_arg(export)
    export.set_defaults(func=_export)

    restore = sub.add_parser("import", help="recreate a robot's knowledge from a Cypher export, in an empty store",
                             description="Run a script of 'kgadapt knowledge export --format cypher' on an empty "
                                         "store, each part where that store keeps it (the fleet roster beside the "
                                         "robot's graph on FalkorDB, in it elsewhere); an export of an older "
                                         "version too. All or nothing: a statement the store refuses is named by "
                                         "its line and nothing stays; on FalkorDB (RESP) and Memgraph an import "
                                         "killed midway leaves the store as empty as it was (FalkorDB's Bolt "
                                         "listener: see docs/knowledge.md).")
    restore.add_argument("file", metavar="FILE", help="the exported script ('-': standard input)")
    restore.add_argument("--json", action="store_true", help="print the counts as JSON")
    _store_arg(restore)
    restore.set_defaults(func=_import)
    return sub  # kgadapt.knowledge.service_cli adds serve (the command registry, kgadapt/cli.py)


def _time_limit_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--time-limit", type=float, default=10.0, metavar="SECONDS",
                        help="hard limit: past it the query is stopped and the command fails saying so "
                             "(default 10; the paper's literal queries keep their own 1 s)")


def _run_bounded(store_url: str | None, cypher: str, params: dict[str, Any], limit_s: float,
                 graph: Graph = Graph.ROBOT) -> list[dict[str, Any]]:
    """Run a read-only query on ``graph`` of the robot's store so that it ends by ``limit_s``: on FalkorDB in a
    QuerySandbox, killed at the limit (killing this command alone would leave the store working on it);
    elsewhere with the store's timeout."""
    if limit_s <= 0:
        raise ConfigError(f"--time-limit {limit_s}: must be positive")
    with open_store(store_url) as robot_store:
        store = graph.store(robot_store)
        if not store.capabilities.sandbox:
            return store.execute(cypher, params, read_only=True, timeout_ms=int(limit_s * 1000))
        from kgadapt.knowledge.sandbox import QuerySandbox

        sandbox = QuerySandbox(store)
        sandbox.setup()
        try:
            return sandbox.execute(cypher, params, limit_s=limit_s)
        finally:
            sandbox.shutdown()


def _pairs(items: list[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--param {item!r}: write KEY=VALUE")
        if key in out:
            raise ConfigError(f"--param {key!r} given twice")
        out[key.strip()] = value
    return out


def _print_json(data: Any) -> None:
    print(json.dumps(data, indent=2, sort_keys=False, default=str))


def _load(args: argparse.Namespace) -> int:
    from kgadapt.knowledge.loader import check_models, load_models, report

    if args.check and args.store is None:  # nothing to compare with: names must be defined by these files
        result = report(check_models(args.paths))
    elif args.check:  # names may be defined by models already in that store, as a load into it would find them
        with open_store(args.store) as store:
            result = report(check_models(args.paths, store))
    else:
        with open_store(args.store) as store:
            result = load_models(store, args.paths)
    if args.json:
        _print_json({**result.as_dict(), "written": not args.check})
        return 0
    verb = "checked" if args.check else "loaded"
    print(f"{verb} {len(result.files)} model files")
    print(rows_as_table(result.rows()))
    return 0


def _query(args: argparse.Namespace) -> int:
    from kgadapt.knowledge.queries import check_params, coerce_params, get_query

    query = get_query(args.name)
    values = check_params(args.name, coerce_params(args.name, _pairs(args.param)))
    limit_s = args.time_limit
    if query.time_limit_ms is not None:
        limit_s = min(limit_s, query.time_limit_ms / 1000)
    rows = _run_bounded(args.store, query.text_for(values), values, limit_s, query.graph)
    reason = _why_empty(args.store, args.name, values) if not rows else ""
    _print_rows(rows, args.json, reason)
    return 0


def _why_empty(store_url: str | None, name: str | None, values: dict[str, Any], cypher: str = "") -> str:
    """Why the answer is empty (or NamedQueryError when the question names what is not there)."""
    from kgadapt.knowledge.empty_answers import explain_empty, roster_outside, store_is_empty
    from kgadapt.knowledge.queries import run_named

    with open_store(store_url) as store:
        where = f"store {store.url}"
        run = lambda n, p: run_named(store, n, p)  # noqa: E731
        if name is None:  # free Cypher: an empty store, or a roster kept beside the graph it read
            if store_is_empty(run):
                raise ConfigError(f"{where} holds no models: nothing is loaded there (kgadapt knowledge load "
                                  "knowledge/models; a mistyped --store opens a new, empty store)")
            return roster_outside(cypher) if store.capabilities.graphs else ""  # the roster is kept beside
        return explain_empty(name, values, run, where=where)


def _print_rows(rows: list[dict[str, Any]], as_json: bool, reason: str) -> None:
    if as_json:
        _print_json(rows)
        if reason:
            print(f"kgadapt: no rows: {reason}", file=sys.stderr)
    else:
        print(rows_as_table(rows) if rows or not reason else f"(no rows: {reason})")


def _queries(args: argparse.Namespace) -> int:
    from kgadapt.knowledge.queries import catalogue

    rows = catalogue()
    if args.json:
        _print_json(rows)
        return 0
    for row in rows:
        print(f"{row['name']}({row['params'] if row['params'] != '-' else ''})")
        print(f"    {row['description']}")
    return 0


def _cypher(args: argparse.Namespace) -> int:
    params: dict[str, Any] = {}
    for key, text in _pairs(args.param).items():
        try:
            params[key] = json.loads(text)
        except ValueError:
            params[key] = text
    from kgadapt.knowledge.cypher_guard import check_cypher

    rows = _run_bounded(args.store, check_cypher(args.text), params, args.time_limit)
    _print_rows(rows, args.json, _why_empty(args.store, None, params, args.text) if not rows else "")
    return 0


def _export(args: argparse.Namespace) -> int:
    from kgadapt.knowledge.export import export

    with open_store(args.store) as store:
        text = export(store, args.format)
    if args.output:
        try:
            Path(args.output).write_text(text)
        except OSError as exc:
            raise ConfigError(f"cannot write {args.output}: {exc.strerror or exc}") from exc
    else:
        sys.stdout.write(text)
    return 0


def _import(args: argparse.Namespace) -> int:
    from kgadapt.knowledge.export import node_counts, restore

    source = "<stdin>" if args.file == "-" else args.file
    try:
        script = sys.stdin.read() if args.file == "-" else Path(args.file).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise ConfigError(f"cannot read {source}: {reason}") from exc
    with open_store(args.store) as store:
        statements = restore(store, script, source=source)
        counts = node_counts(store)
    if args.json:
        _print_json({"statements": statements, "nodes": counts, "store": store.url})
    else:
        print(f"imported {source} into store {store.url}: {statements} statements; nodes "
              + ", ".join(f"{part} {count}" for part, count in counts.items()))
    return 0
