"""``kgadapt knowledge``: load models, ask named queries, run read-only Cypher, export the graph.

Every subcommand takes ``--store URL`` (default ``$KGADAPT_STORE``, else the
embedded store in the user's data directory); ``--json`` where the output is
data. ``kgadapt knowledge serve`` is added by ``knowledge.service_cli`` when
that module exists.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path
from typing import Any

from knowledge.store import STORE_ENV, open_store, rows_as_table
from shared.errors import ConfigError

_STORE_HELP = f"graph store URL (default: ${STORE_ENV}, else the embedded store); e.g. embedded:DIR, falkordb://HOST:PORT, bolt://HOST:PORT"


def _store_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--store", metavar="URL", default=None, help=_STORE_HELP)


def register(subparsers: Any) -> None:
    """Add ``kgadapt knowledge`` and its subcommands."""
    parser = subparsers.add_parser(
        "knowledge", help="load domain models, query the knowledge graph, export it",
        description="The robot's software knowledge: domain models in a graph, queried with Cypher.")
    sub = parser.add_subparsers(dest="knowledge_command", metavar="SUBCOMMAND")
    sub.required = True

    load = sub.add_parser("load", help="check and load model files or directories (all or nothing)",
                          description="Parse every model file (.rpsl .platform .service .deploy .features) under "
                                      "the given paths, check them all, then write them in one batch. Loading "
                                      "again replaces what the files said before; run-time facts are kept.")
    load.add_argument("paths", nargs="+", metavar="PATH", help="model file or directory (searched recursively)")
    load.add_argument("--check", action="store_true", help="only parse and check; write nothing")
    load.add_argument("--json", action="store_true", help="print the counts as JSON")
    _store_arg(load)
    load.set_defaults(func=_load)

    query = sub.add_parser("query", help="run a named query",
                           description="Run a named query (see 'kgadapt knowledge queries') with parameters.")
    query.add_argument("name", help="query name")
    query.add_argument("--param", "-p", action="append", default=[], metavar="KEY=VALUE",
                       help="a parameter (repeat for more); typed as the query declares")
    query.add_argument("--json", action="store_true", help="print the rows as JSON")
    _store_arg(query)
    query.set_defaults(func=_query)

    listing = sub.add_parser("queries", help="list the named queries and their parameters")
    listing.add_argument("--json", action="store_true", help="print the list as JSON")
    _store_arg(listing)
    listing.set_defaults(func=_queries)

    cypher = sub.add_parser("cypher", help="run one read-only Cypher query",
                            description="Run one Cypher query read-only: a query that writes is refused.")
    cypher.add_argument("text", metavar="QUERY", help="the Cypher text; values as $parameters")
    cypher.add_argument("--param", "-p", action="append", default=[], metavar="KEY=VALUE",
                        help="a parameter; the value is read as JSON when it parses, else as a string")
    cypher.add_argument("--json", action="store_true", help="print the rows as JSON")
    _store_arg(cypher)
    cypher.set_defaults(func=_cypher)

    export = sub.add_parser("export", help="export the graph as Graphviz dot or as Cypher statements",
                            description="dot: to look at (dot -Tsvg). cypher: statements that recreate the graph "
                                        "in an empty store, e.g. a Memgraph server (one per line).")
    export.add_argument("--format", choices=("dot", "cypher"), default="dot", help="output format (default dot)")
    export.add_argument("--output", "-o", metavar="FILE", help="write here instead of standard output")
    _store_arg(export)
    export.set_defaults(func=_export)

    try:
        service_cli = importlib.import_module("knowledge.service_cli")
    except ModuleNotFoundError as exc:
        if exc.name != "knowledge.service_cli":
            raise
    else:
        hook = getattr(service_cli, "register_knowledge", None)
        if hook is not None:
            hook(sub)


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
    from knowledge.loader import check_models, load_models, report

    if args.check:
        result = report(check_models(args.paths))
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
    from knowledge.queries import coerce_params, run_named

    params = coerce_params(args.name, _pairs(args.param))
    with open_store(args.store) as store:
        rows = run_named(store, args.name, params)
    if args.json:
        _print_json(rows)
    else:
        print(rows_as_table(rows))
    return 0


def _queries(args: argparse.Namespace) -> int:
    from knowledge.queries import catalogue

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
    with open_store(args.store) as store:
        rows = store.execute(args.text, params, read_only=True)
    if args.json:
        _print_json(rows)
    else:
        print(rows_as_table(rows))
    return 0


def _export(args: argparse.Namespace) -> int:
    from knowledge.export import export

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
