"""Bolt servers through the Neo4j Python driver: ``memgraph://``, ``bolt://`` and their TLS forms.

Memgraph documents the Neo4j Python driver as a supported client; it gives
what this backend needs through its public API alone: a per-query timeout
sent in the Bolt transaction metadata (``tx_timeout``, which Memgraph and
Neo4j enforce on the server), explicit transactions, TLS settings, typed
errors, and graph values (``neo4j.graph``) we turn into plain ones.

``bolt://`` also reaches FalkorDB started with ``BOLT_PORT``, which the tests
use as the Bolt server that runs here. It claims to be Neo4j but behaves
differently, and this backend finds that out by behaviour, never by error
text (:meth:`BoltStore.setup`): it pastes string parameters into the query
text, ignores ``tx_timeout``, has no explicit transactions, and may hang the
handshake that follows a disconnect, so one session is kept for every query.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from typing import Any, Callable, Mapping, Sequence

import neo4j
from neo4j import exceptions as neo4j_errors
from neo4j import graph as neo4j_graph

from kgadapt.knowledge.dialect import FALKORDB, NEO4J, Dialect, dialect_for_agent
from kgadapt.knowledge.params import check_params
from kgadapt.knowledge.store import Capabilities, GraphStore, Row, Statement, StoreSettings
from kgadapt.shared.errors import ConfigError, QueryError, ReadOnlyViolation, StoreTimeout, StoreUnavailable

log = logging.getLogger(__name__)

# A transient conflict (Memgraph: concurrent writes to one node) is retried
# this many times, after these pauses; then it is a QueryError.
TRANSIENT_RETRY_PAUSES = (0.02, 0.08, 0.25)
# Connection loss: the driver's error types that mean "no server", not "bad query".
_LOST = (neo4j_errors.ServiceUnavailable, neo4j_errors.SessionExpired, OSError)


class BoltStore(GraphStore):
    """Memgraph (``memgraph://``) or any Bolt server (``bolt://``) via the Neo4j Python driver."""

    def __init__(self, settings: StoreSettings) -> None:
        super().__init__(settings)
        self._driver: neo4j.Driver | None = None
        self._session: neo4j.Session | None = None
        self._lock = threading.RLock()
        self._splices_params = False
        # Known once connected: from the server's announced agent (dialect_for_agent), or FalkorDB's
        # listener found by behaviour. The URL's scheme chooses only the transport.
        self._dialect: Dialect = NEO4J
        self.server_agent: str | None = None

    # --- what this backend is -------------------------------------------------

    @property
    def dialect(self) -> Dialect:
        return self._dialect

    @property
    def capabilities(self) -> Capabilities:
        stand_in = self._splices_params  # FalkorDB's Bolt listener
        return Capabilities(
            transactions=not stand_in,
            timeouts=not stand_in,
            tls=True,
            read_only="check",
            thread_safe=True,  # every call holds self._lock around the one session
            sandbox=False,  # no DUMP/RESTORE over Bolt
        )

    # --- life cycle -----------------------------------------------------------

    def setup(self, *, timeout: float | None = None) -> None:
        timeout = timeout or self.settings.connect_timeout
        deadline = time.monotonic() + timeout
        while True:
            try:
                self._driver = self._make_driver(min(1.0, timeout))
                self._open_session()
                self.server_agent = self._announced_agent()
                self._splices_params = self._probe_parameter_splicing()
                self._dialect = FALKORDB if self._splices_params else dialect_for_agent(self.server_agent)
                log.info("Bolt server at %s announces itself as %r: %s dialect", self.settings.url,
                         self.server_agent, self._dialect.name)
                return
            except neo4j_errors.AuthError as exc:
                self._close_quietly()
                raise StoreUnavailable(f"Bolt server at {self.settings.url} refused the login: {exc}") from exc
            except (neo4j_errors.Neo4jError, neo4j_errors.DriverError, OSError) as exc:
                self._close_quietly()
                if time.monotonic() >= deadline:
                    raise StoreUnavailable(f"cannot reach Bolt server at {self.settings.url}: {_one_line(exc)}") from exc
                time.sleep(0.1)

    def _make_driver(self, connect_timeout: float) -> neo4j.Driver:
        """One driver; a short connection timeout so a dropped handshake fails fast and is retried."""
        s = self.settings
        auth = (s.username, s.password) if s.username else None
        kwargs: dict[str, Any] = {
            "connection_timeout": connect_timeout,
            "connection_acquisition_timeout": max(2.0, connect_timeout * 2),
            "max_transaction_retry_time": 0.0,
            "user_agent": "kgadapt",
        }
        scheme = "bolt"
        if s.tls == "verify" and s.ca_file:
            kwargs["encrypted"] = True
            kwargs["trusted_certificates"] = neo4j.TrustCustomCAs(s.ca_file)
        elif s.tls == "verify":
            scheme = "bolt+s"
        elif s.tls == "self-signed":
            scheme = "bolt+ssc"
        try:
            return neo4j.GraphDatabase.driver(f"{scheme}://{s.host}:{s.port}", auth=auth, **kwargs)
        except (neo4j_errors.ConfigurationError, ValueError) as exc:
            raise StoreUnavailable(f"cannot set up a Bolt driver for {s.url}: {exc}") from exc

    def _open_session(self) -> None:
        """Keep one session for every query.

        FalkorDB's Bolt listener may hang the handshake of the connection that
        follows a disconnect; one long-lived session keeps one connection.
        """
        if self._driver is None:
            raise StoreUnavailable("store is not set up; call setup() first")
        self._session = self._driver.session()

    def _announced_agent(self) -> str | None:
        """The agent the server announced in its HELLO reply, read from a first round trip on our session
        (the driver's public ResultSummary.server; on the one connection FalkorDB's listener needs)."""
        summary = self._current_session().run("RETURN 1 AS one").consume()
        agent = summary.server.agent
        return str(agent) if agent else None

    def _probe_parameter_splicing(self) -> bool:
        """True when the server pastes string parameters into the query text.

        Measured here: FalkorDB 4.16's Bolt listener does (the parameter
        ``"x' RETURN 1 AS p //"`` ran as code), while claiming to be Neo4j.
        On such a server we refuse strings with a quote or a backslash.
        """
        probe = "kg'\\probe"
        try:
            rows = self._fetch("RETURN $p AS p", {"p": probe}, None)
        except neo4j_errors.Neo4jError:
            return True
        spliced = not rows or rows[0].get("p") != probe
        if spliced:
            log.warning("Bolt server at %s splices parameters into query text; string parameters "
                        "with ' or \\ will be refused, and it cannot cut queries off at a timeout",
                        self.settings.url)
        return spliced

    def shutdown(self) -> None:
        """Close the session and the driver; never opens a connection to do so."""
        with self._lock:
            self._close_quietly()

    def _close_quietly(self) -> None:
        session, self._session = self._session, None
        driver, self._driver = self._driver, None
        for closer in (session, driver):
            if closer is None:
                continue
            try:
                closer.close()
            except (neo4j_errors.Neo4jError, neo4j_errors.DriverError, OSError):
                pass  # closing a dead connection: nothing to undo

    # --- queries --------------------------------------------------------------

    def _execute(self, cypher: str, params: Mapping[str, Any] | None, read_only: bool,
                 timeout_ms: int | None) -> list[Row]:
        clean = check_params(params)
        if self._splices_params:
            _refuse_quotes(clean)
        seconds = timeout_ms / 1000.0 if timeout_ms and self.capabilities.timeouts else None
        rows: list[Row] = self._with_errors(lambda: self._fetch(cypher, clean, seconds), timeout_ms)
        return rows

    def execute_atomic(self, statements: Sequence[Statement]) -> None:
        """One explicit transaction, rolled back on any error.

        FalkorDB's Bolt listener has no explicit transactions; there the
        statements run one by one after the importers' validation.
        """
        batch = [(cypher, check_params(params)) for cypher, params in statements]
        if self._splices_params:
            for _, params in batch:
                _refuse_quotes(params)
        if not self.capabilities.transactions:
            for cypher, params in batch:
                self._with_errors(functools.partial(self._fetch, cypher, params, None), None)
            return

        def run_batch() -> None:
            session = self._current_session()
            with session.begin_transaction() as tx:
                for cypher, params in batch:
                    tx.run(cypher, params).consume()
                tx.commit()

        self._with_errors(run_batch, None)

    def execute_script(self, statements: Sequence[tuple[str, str]]) -> None:
        """Run ``statements`` (each a label such as ``FILE:LINE`` and a statement without parameters) in one
        explicit transaction: all of them or, when one is refused or the connection is lost (the importer
        killed), none (the server rolls an unfinished transaction back). QueryError starting with the label of
        the statement refused. A server without explicit transactions (FalkorDB's Bolt listener) is refused:
        ConfigError, nothing run."""
        if not self.capabilities.transactions:
            raise ConfigError(f"store {self.settings.url}: this Bolt server has no explicit transactions")
        current = ["(commit)"]

        def run_all() -> None:
            session = self._current_session()
            with session.begin_transaction() as tx:
                for label, cypher in statements:
                    current[0] = label
                    tx.run(cypher).consume()
                current[0] = "(commit)"
                tx.commit()

        try:
            self._with_errors(run_all, None)
        except QueryError as exc:
            raise QueryError(f"{current[0]}: {exc}") from exc

    def _current_session(self) -> neo4j.Session:
        if self._session is None:
            # Reconnect on the call after a loss (the loss itself was reported).
            if self._driver is None:
                raise StoreUnavailable("store is not set up; call setup() first")
            self._open_session()
        assert self._session is not None
        return self._session

    def _fetch(self, cypher: str, params: dict[str, Any], timeout_s: float | None) -> list[Row]:
        session = self._current_session()
        result = session.run(neo4j.Query(cypher, timeout=timeout_s), params)
        return [{key: plain(record[key]) for key in record.keys()} for record in result]

    def _with_errors(self, work: Callable[[], Any], timeout_ms: int | None) -> Any:
        """Run ``work`` under the store lock; translate the driver's errors into ours."""
        with self._lock:
            if self._driver is None:
                raise StoreUnavailable("store is not set up; call setup() first")
            for attempt, pause in enumerate((*TRANSIENT_RETRY_PAUSES, None)):
                try:
                    return work()
                except neo4j_errors.TransientError as exc:
                    if _is_timeout(exc):
                        raise StoreTimeout(f"query cut off by the store at its {timeout_ms} ms limit: "
                                           f"{exc.message or exc}") from exc
                    if pause is None:
                        raise QueryError(f"store kept reporting a conflict after {attempt} retries: "
                                         f"{exc.message or exc}") from exc
                    log.info("transient store error (%s); retrying in %.0f ms", exc.code, pause * 1000)
                    time.sleep(pause)
                except _LOST as exc:
                    self._drop_session()
                    raise StoreUnavailable(f"lost Bolt server at {self.settings.url}: {_one_line(exc)}") from exc
                except neo4j_errors.Neo4jError as exc:
                    message = exc.message or str(exc) or type(exc).__name__
                    if _is_timeout(exc):
                        raise StoreTimeout(f"query cut off by the store at its {timeout_ms} ms limit: "
                                           f"{message}") from exc
                    if exc.code and "Forbidden" in exc.code and "ReadOnly" in exc.code:
                        raise ReadOnlyViolation(f"read-only query refused by the store: {message}") from exc
                    raise QueryError(f"store rejected the query: {message}") from exc
                except neo4j_errors.DriverError as exc:
                    self._drop_session()
                    raise StoreUnavailable(f"Bolt driver failed for {self.settings.url}: {exc}") from exc
        raise AssertionError("unreachable")

    def _drop_session(self) -> None:
        session, self._session = self._session, None
        if session is not None:
            try:
                session.close()
            except (neo4j_errors.Neo4jError, neo4j_errors.DriverError, OSError):
                pass


def _one_line(exc: BaseException) -> str:
    """The driver's messages span lines; a CLI error is one line."""
    return " ".join(str(exc).split()) or type(exc).__name__


def _is_timeout(exc: neo4j_errors.Neo4jError) -> bool:
    """The server's own timeout codes (Neo4j: TransactionTimedOut*; Memgraph reports it as a transient error)."""
    code = exc.code or ""
    return "TimedOut" in code or "Timeout" in code


def _refuse_quotes(params: Mapping[str, Any], where: str = "") -> None:
    for key, value in params.items():
        name = f"{where}{key}"
        if isinstance(value, str) and ("'" in value or "\\" in value):
            raise QueryError(
                f"parameter {name!r}: this Bolt server pastes parameters into query text, "
                "so values with ' or \\ are refused (use the RESP or Memgraph backend for such values)"
            )
        if isinstance(value, dict):
            _refuse_quotes(value, f"{name}.")
        if isinstance(value, list):
            _refuse_quotes({str(i): v for i, v in enumerate(value)}, f"{name}.")


def plain(value: Any) -> Any:
    """A driver value as plain Python, the same shapes as the RESP backend gives.

    A node is its properties plus ``_labels`` (sorted); a relationship its
    properties plus ``_type``; a path the list of its nodes. Lists and maps
    are converted all the way down; temporal values become ISO strings.
    """
    if isinstance(value, neo4j_graph.Node):
        return {**{k: plain(v) for k, v in value.items()}, "_labels": sorted(value.labels)}
    if isinstance(value, neo4j_graph.Relationship):
        return {**{k: plain(v) for k, v in value.items()}, "_type": value.type}
    if isinstance(value, neo4j_graph.Path):
        return [plain(node) for node in value.nodes]
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if hasattr(value, "iso_format"):  # neo4j.time Date, Time, DateTime, Duration
        return value.iso_format()
    return value
