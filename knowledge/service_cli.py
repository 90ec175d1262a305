"""``kgadapt knowledge serve`` (the knowledge service) and ``kgadapt ask`` (its client).

``serve`` owns the store: it opens it (starting the embedded FalkorDB when the
store is ``embedded:``), opens Zenoh as a router listening on
``tcp/127.0.0.1:7447`` unless told otherwise, serves until SIGINT or SIGTERM,
then undeclares everything and stops the store if it started it.

``ask`` asks any robot's service over Zenoh and prints the rows::

    kgadapt ask placement --param feature=MarkerDetection
    kgadapt ask --robot quad2 --cypher 'MATCH (p:Platform) RETURN p.name AS name' --json
    kgadapt ask --fleet current_placement --expect quad1 --expect quad2   # every robot (knowledge/fleet.py)
    kgadapt ask --fleet platforms --robot quad2   # robots quad2's roster remembers are listed, silent if gone
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from typing import Any

from kgadapt.shared.keys import DEFAULT_ROBOT


def register(subparsers: Any) -> None:
    """Add ``kgadapt ask``."""
    from kgadapt.shared.session import add_arguments as add_zenoh_arguments

    ask = subparsers.add_parser(
        "ask",
        help="ask a robot's knowledge service over Zenoh",
        description="Run a named query (or read-only Cypher) on a robot's knowledge service over Zenoh "
        "and print the rows. Connects as a Zenoh client to tcp/127.0.0.1:7447 unless told otherwise.",
    )
    ask.add_argument("query", nargs="?", metavar="QUERY", help="named query (see `kgadapt knowledge queries`)")
    ask.add_argument("--param", "-p", action="append", default=[], metavar="KEY=VALUE", help="query parameter (repeatable)")
    ask.add_argument("--cypher", metavar="TEXT", help="read-only Cypher instead of a named query")
    ask.add_argument("--robot", default=DEFAULT_ROBOT,
                     help=f"whose knowledge to ask (default {DEFAULT_ROBOT}); with --fleet, the robot whose fleet "
                     "roster names the robots to expect (those its knowledge service has heard)")
    ask.add_argument("--fleet", metavar="QUERY",
                     help="ask named query QUERY of every robot at once; one table with a robot column")
    ask.add_argument("--expect", action="append", default=[], metavar="ROBOT",
                     help="with --fleet: a robot that should answer, listed as silent if it does not (repeatable)")
    ask.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the answer (default 3)")
    ask.add_argument("--json", action="store_true", help="print rows as JSON")
    add_zenoh_arguments(ask)
    ask.set_defaults(func=run_ask)


def register_knowledge(knowledge_subparsers: Any) -> None:
    """Add ``kgadapt knowledge serve`` (registered under ``knowledge`` in pyproject.toml's command registry)."""
    from kgadapt.shared.session import add_arguments as add_zenoh_arguments

    serve = knowledge_subparsers.add_parser(
        "serve",
        help="serve the knowledge graph over Zenoh",
        description="Own the graph store and serve it over Zenoh: named queries, read-only Cypher, "
        "run-time writes, and platform status from the hosts' monitors and liveliness. "
        "Opens Zenoh as a router on tcp/127.0.0.1:7447 unless told otherwise.",
    )
    serve.add_argument("--store", metavar="URL", help="graph store URL (default $KGADAPT_STORE or embedded:)")
    serve.add_argument("--robot", default=DEFAULT_ROBOT, help=f"robot name, the key namespace (default {DEFAULT_ROBOT})")
    serve.add_argument(
        "--read-only", action="store_true",
        help="do not declare the write verbs (knowledge/write/*); queries and Cypher stay available",
    )
    serve.add_argument("--workers", type=int, default=2, help="request worker threads (default 2)")
    add_zenoh_arguments(serve)
    serve.set_defaults(func=run_serve)


def run_serve(args: argparse.Namespace) -> int:
    import logging

    from kgadapt.shared.allocator import cap_arenas

    cap_arenas()  # before Zenoh's threads: a long-running router's RSS creeps with glibc's default arenas

    from kgadapt.knowledge.schema import ensure_indexes
    from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
    from kgadapt.knowledge.store import open_store
    from kgadapt.shared.agent import StopSignals
    from kgadapt.shared.notifier import ServiceNotifier
    from kgadapt.shared.readiness import announce_ready
    from kgadapt.shared.session import DEFAULT_ENDPOINT, SERVICE_RUNTIME, open_session, settings_from_args

    log = logging.getLogger("kgadapt.knowledge.service")
    settings = ServiceSettings(robot=args.robot, writes=not args.read_only, workers=args.workers)
    zenoh = settings_from_args(args).with_defaults(mode="router", listen=[DEFAULT_ENDPOINT])
    zenoh = dataclasses.replace(zenoh, runtime=SERVICE_RUNTIME)  # the status fan-in's receive path (session.py)
    with StopSignals() as stop:
        # The robot's own path is bounded too: a query unanswered for 10 s is abandoned.
        store = open_store(args.store, socket_timeout=10.0)
        store.setup()
        try:
            ensure_indexes(store)
            session = open_session(zenoh)
            try:
                service = KnowledgeService(store, settings)
                service.setup(session)
                notifier = ServiceNotifier()
                try:
                    line = (
                        f"knowledge service ready: robot {settings.robot}, store {store.url}, "
                        f"zenoh {zenoh.mode} listen {list(zenoh.listen)} connect {list(zenoh.connect)}, "
                        f"writes {'on' if settings.writes else 'off'}"
                    )
                    print(line, flush=True)  # for people; machines wait on the readiness line
                    announce_ready(status=line, notifier=notifier, role="knowledge service", robot=settings.robot,
                                   listen=list(zenoh.listen))
                    stop.wait(tick=notifier.watchdog)
                    log.info("signal %s: stopping the knowledge service", stop.received)
                finally:
                    notifier.stopping()
                    service.shutdown()
            finally:
                session.close()
        finally:
            store.shutdown()
    return 0


def run_ask(args: argparse.Namespace) -> int:
    from kgadapt.knowledge.client import KnowledgeClient
    from kgadapt.knowledge.store import rows_as_table
    from kgadapt.shared.errors import ConfigError
    from kgadapt.shared.session import DEFAULT_ENDPOINT, open_session, settings_from_args

    if args.fleet:
        return _run_fleet_ask(args)
    if args.expect:
        raise ConfigError("--expect goes with --fleet QUERY")
    if bool(args.query) == bool(args.cypher):
        raise ConfigError("give either a named QUERY or --cypher TEXT (not both, not neither)")
    raw = _parse_params(args.param)
    if args.query:
        from kgadapt.knowledge.queries import QUERIES, coerce_params

        # A query this checkout does not know is sent as text: the far side judges it.
        params: dict[str, Any] = coerce_params(args.query, raw) if args.query in QUERIES else dict(raw)
    else:
        params = {k: _guess_value(v) for k, v in raw.items()}
    zenoh = settings_from_args(args).with_defaults(mode="client", connect=[DEFAULT_ENDPOINT])
    session = open_session(zenoh)
    try:
        client = KnowledgeClient(session, args.robot, timeout=args.timeout)
        rows = client.query(args.query, params) if args.query else client.cypher(args.cypher, params)
        reason = _why_empty(client, args.query, params, args.cypher or "") if not rows else ""
    finally:
        session.close()
    if args.json:
        print(json.dumps(rows, default=str))
        if reason:
            print(f"kgadapt: no rows: {reason}", file=sys.stderr)
    else:
        print(rows_as_table(rows) if rows or not reason else f"(no rows: {reason})")
    return 0


def _why_empty(client: Any, query: str | None, params: dict[str, Any], cypher: str = "") -> str:
    """Why the service answered nothing (knowledge/empty_answers.py), asked over the same Zenoh session."""
    from kgadapt.knowledge.empty_answers import explain_empty, roster_outside, store_is_empty
    from kgadapt.knowledge.queries import QUERIES, check_params

    where = f"the knowledge service of robot {client.robot}"
    if query is None or query not in QUERIES:  # free Cypher, or a query this checkout does not know
        if store_is_empty(client.query):
            return f"{where} holds no models: nothing is loaded there"
        return roster_outside(cypher)  # a likely reason, said as such: the service's backend is not known here
    return explain_empty(query, check_params(query, params), client.query, where=where)


def _run_fleet_ask(args: argparse.Namespace) -> int:
    """``ask --fleet QUERY``: one question to every robot (knowledge/fleet.py); exit 3 when some were silent."""
    from kgadapt.knowledge.fleet import FleetClient, FleetSettings
    from kgadapt.knowledge.queries import QUERIES, coerce_params
    from kgadapt.shared.errors import ConfigError
    from kgadapt.shared.session import DEFAULT_ENDPOINT, open_session, settings_from_args

    if args.query or args.cypher:
        raise ConfigError("--fleet QUERY asks a named query of every robot: give no other QUERY and no --cypher")
    from kgadapt.shared.keys import check_name

    check_name(args.fleet, "query name")  # before any network: a name is one key chunk, no wildcard
    raw = _parse_params(args.param)
    params: dict[str, Any] = coerce_params(args.fleet, raw) if args.fleet in QUERIES else dict(raw)
    settings = FleetSettings(timeout=args.timeout, expect=tuple(args.expect), roster=args.robot)
    zenoh = settings_from_args(args).with_defaults(mode="client", connect=[DEFAULT_ENDPOINT])
    session = open_session(zenoh)
    try:
        answer = FleetClient(session, settings).ask(args.fleet, params)
    finally:
        session.close()
    if args.json:
        print(json.dumps(answer.as_json(), default=str))
    else:
        print(answer.table())
    return 0 if answer.complete and not answer.refusals else 3


def _parse_params(items: list[str]) -> dict[str, str]:
    from kgadapt.shared.errors import ConfigError

    params: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--param {item!r}: use KEY=VALUE")
        params[key] = value
    return params


def _guess_value(text: str) -> Any:
    """Cypher parameters from the command line: JSON when it parses (numbers, true, lists), else text."""
    try:
        return json.loads(text)
    except ValueError:
        return text
