"""Bolt servers through gqlalchemy: ``memgraph://`` (Memgraph) and ``bolt://`` (Neo4j class).

``bolt://`` also reaches FalkorDB started with ``BOLT_PORT``, which the tests use
as a stand-in Bolt server (DESIGN.md section 7 lists its sharp edges: the first
handshake after a disconnect may be dropped, so ``setup()`` retries it).
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any, Mapping, Sequence

from knowledge.store import GraphStore, Row, Statement, StoreSettings, assert_read_only
from shared.errors import QueryError, ReadOnlyViolation, StoreUnavailable

log = logging.getLogger(__name__)


class BoltStore(GraphStore):
    """Memgraph (``memgraph://``) or any Bolt server (``bolt://``) via gqlalchemy."""

    def __init__(self, settings: StoreSettings) -> None:
        super().__init__(settings)
        self._db: Any = None
        self._session: Any = None
        self._splices_params = False

    def setup(self, *, timeout: float | None = None) -> None:
        import gqlalchemy

        timeout = timeout or self.settings.connect_timeout
        s = self.settings
        if s.kind == "memgraph":
            self._db = gqlalchemy.Memgraph(host=s.host, port=s.port, username=s.username, password=s.password)
        else:
            self._db = gqlalchemy.Neo4j(host=s.host, port=s.port, username=s.username, password=s.password)
            self._shorten_connect_timeout(min(1.0, timeout))
        deadline = time.monotonic() + timeout
        while True:
            try:
                self._open_session()
                self._fetch("RETURN 1 AS one", {})
                self._splices_params = self._probe_parameter_splicing()
                return
            except Exception as exc:  # each driver has its own errors; all mean "not reachable"
                if time.monotonic() >= deadline:
                    self._db = None
                    raise StoreUnavailable(f"cannot reach Bolt server at {s.url}: {exc}") from exc
                time.sleep(0.1)

    def _shorten_connect_timeout(self, seconds: float) -> None:
        """Give gqlalchemy's neo4j driver a short connection timeout.

        Measured with FalkorDB's Bolt listener: after a client disconnects, the
        next handshake hangs until the driver's default 30 s timeout (twice).
        With a short timeout that attempt fails fast and the retry connects.
        """
        import neo4j

        conn = self._db._get_cached_connection()
        old = getattr(conn, "_connection", None)
        if old is None:
            return
        s = self.settings
        conn._connection = neo4j.GraphDatabase.driver(
            f"bolt://{s.host}:{s.port}", auth=(s.username, s.password), encrypted=False,
            connection_timeout=seconds, connection_acquisition_timeout=seconds * 2,
        )
        old.close()

    def _open_session(self) -> None:
        """Neo4j class: keep one Bolt session for every query.

        gqlalchemy opens a session per query; FalkorDB's Bolt listener drops
        the connection handed back to the pool, so we hold our own session.
        """
        self._session = None
        if self.settings.kind == "bolt":
            driver = self._db._get_cached_connection()._connection
            self._session = driver.session()

    def _probe_parameter_splicing(self) -> bool:
        """True when the server pastes string parameters into the query text.

        Measured here: FalkorDB 4.16's Bolt listener does (the parameter
        ``"x' RETURN 1 AS p //"`` ran as code), while claiming to be Neo4j.
        On such a server we refuse strings with a quote or a backslash.
        """
        probe = "kg'\\probe"
        try:
            rows = self._fetch("RETURN $p AS p", {"p": probe})
        except Exception:
            return True
        spliced = not rows or rows[0].get("p") != probe
        if spliced:
            log.warning("Bolt server at %s splices parameters into query text; "
                        "string parameters with ' or \\ will be refused", self.settings.url)
        return spliced

    def _fetch(self, cypher: str, params: dict[str, Any]) -> list[Row]:
        if self._session is None:
            return [{k: _plain(v) for k, v in row.items()} for row in self._db.execute_and_fetch(cypher, params)]
        from gqlalchemy.connection import _convert_neo4j_value

        result = self._session.run(cypher, params)
        keys = result.keys()
        return [{k: _plain(_convert_neo4j_value(record[k])) for k in keys} for record in result]

    def shutdown(self) -> None:
        session, self._session = getattr(self, "_session", None), None
        if session is not None:
            try:
                session.close()
            except Exception:  # best effort
                pass
        db, self._db = self._db, None
        if db is None:
            return
        try:
            conn = db._get_cached_connection()
            inner = getattr(conn, "_connection", None)
            if inner is not None and hasattr(inner, "close"):
                inner.close()
        except Exception:  # closing is best effort
            pass

    def execute(
        self,
        cypher: str,
        params: Mapping[str, Any] | None = None,
        *,
        read_only: bool = False,
        timeout_ms: int | None = None,
    ) -> list[Row]:
        if read_only:
            assert_read_only(cypher)
        if self._db is None:
            raise StoreUnavailable("store is not set up; call setup() first")
        clean = _check_params(params)
        if self._splices_params:
            _refuse_quotes(clean)
        try:
            try:
                return self._fetch(cypher, clean)
            except Exception as exc:
                if type(exc).__name__ not in ("ServiceUnavailable", "SessionExpired") or self._session is None:
                    raise
                log.warning("Bolt connection dropped (%s); opening a new session", exc)
                self._open_session()
                return self._fetch(cypher, clean)
        except (ConnectionError, OSError) as exc:
            raise StoreUnavailable(f"lost Bolt server at {self.settings.url}: {exc}") from exc
        except Exception as exc:  # neo4j.exceptions / mgclient.DatabaseError
            message = str(exc) or type(exc).__name__
            if "read" in message.lower() and "only" in message.lower():
                raise ReadOnlyViolation(message) from exc
            raise QueryError(f"store rejected the query: {message}") from exc

    def execute_atomic(self, statements: Sequence[Statement]) -> None:
        """One explicit transaction where the driver offers it.

        Memgraph (mgclient) and Neo4j roll back on error. FalkorDB's Bolt
        listener has no explicit transactions; there the statements run one by
        one after the importers' validation.
        """
        if self._db is None:
            raise StoreUnavailable("store is not set up; call setup() first")
        conn = self._db._get_cached_connection()
        inner = getattr(conn, "_connection", None)
        if self._splices_params:
            for _, params in statements:
                _refuse_quotes(params or {})
        try:
            if self.settings.kind == "memgraph" and inner is not None and hasattr(inner, "autocommit"):
                inner.autocommit = False
                try:
                    cursor = inner.cursor()
                    for cypher, params in statements:
                        cursor.execute(cypher, _check_params(params) or {})
                        cursor.fetchall()
                    inner.commit()
                except Exception:
                    inner.rollback()
                    raise
                finally:
                    inner.autocommit = True
                return
            if inner is not None and hasattr(inner, "session") and not self._is_falkordb():
                with inner.session() as session:
                    with session.begin_transaction() as tx:
                        for cypher, params in statements:
                            tx.run(cypher, _check_params(params) or {}).consume()
                        tx.commit()
                return
            for cypher, params in statements:
                self.execute(cypher, params)
        except (QueryError, StoreUnavailable):
            raise
        except Exception as exc:
            raise QueryError(f"store rejected the batch: {exc}") from exc

    def _is_falkordb(self) -> bool:
        # FalkorDB's Bolt listener serves one graph named "falkordb" and has no transactions.
        cached = getattr(self, "_falkordb", None)
        if cached is None:
            try:
                rows = list(self._db.execute_and_fetch("CALL dbms.components() YIELD name RETURN name"))
                cached = any("falkor" in str(r.get("name", "")).lower() for r in rows)
            except Exception:
                cached = True  # no dbms.components(): not Neo4j; run statements one by one
            self._falkordb = cached
        return cached


def _check_params(params: Mapping[str, Any] | None) -> dict[str, Any]:
    clean = dict(params or {})
    for key, value in clean.items():
        _check_value(key, value)
    return clean


def _check_value(key: str, value: Any) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise QueryError(f"parameter {key!r}: {value} is not a finite number")
    if isinstance(value, str) and "\x00" in value:
        # FalkorDB's Bolt listener cuts strings at NUL; no store here should keep half a value.
        raise QueryError(f"parameter {key!r}: a NUL character is not allowed in a string")
    if isinstance(value, (list, tuple)):
        for item in value:
            _check_value(key, item)
    if isinstance(value, dict):
        for item in value.values():
            _check_value(key, item)


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


def _plain(value: Any) -> Any:
    labels = getattr(value, "_labels", None)
    if labels is not None:
        props = getattr(value, "_properties", None) or {
            k: v for k, v in value.__dict__.items() if not k.startswith("_")
        }
        return {**props, "_labels": sorted(labels)}
    rel_type = getattr(value, "_type", None)
    if rel_type is not None and hasattr(value, "_start_node_id"):
        props = getattr(value, "_properties", None) or {}
        return {**props, "_type": rel_type}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value
