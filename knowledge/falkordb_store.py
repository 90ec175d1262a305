"""FalkorDB over RESP: the embedded default and ``falkordb://`` servers.

Parameters travel in FalkorDB's ``CYPHER name=value ...`` prefix of the query
text, built here (:func:`params_header`) for single statements and MULTI/EXEC
batches alike, after :func:`kgadapt.knowledge.params.check_params`; the falkordb
client is used only through its public ``query``/``ro_query``/``connection``.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import Any, Callable, Mapping, Sequence, TypeVar

import redis
from falkordb import FalkorDB
from falkordb.edge import Edge
from falkordb.node import Node
from falkordb.path import Path as GraphPath

from kgadapt.knowledge.dialect import FALKORDB, Dialect
from kgadapt.knowledge.embedded import EmbeddedServer
from kgadapt.knowledge.params import check_params, cypher_literal
from kgadapt.knowledge.store import Capabilities, GraphStore, Row, Statement, StoreSettings
from kgadapt.shared.errors import ConfigError, QueryError, QueryTimeLimit, ReadOnlyViolation, StoreTimeout, StoreUnavailable

log = logging.getLogger(__name__)
T = TypeVar("T")
_LOADING_POLL_S = 0.1  # how often a query asks again while a restarted server reads its AOF


class FalkorDBStore(GraphStore):
    """A FalkorDB graph, embedded (started by us) or already running."""

    def __init__(self, settings: StoreSettings, *, server: EmbeddedServer | None = None) -> None:
        super().__init__(settings)
        self.server = server
        self._db: FalkorDB | None = None
        self._graph: Any = None
        # A second client whose every answer is bounded by settings.setup_timeout, used by the thread in prepare().
        self._setup_db: FalkorDB | None = None
        self._setup_graph: Any = None
        self._preparing = threading.local()
        self._reconnect_lock = threading.RLock()  # _reopen() may meet a lost connection and reconnect
        # Other graphs on the same server (sibling()), kept until shutdown(). A sibling shares this store's
        # embedded server object: whichever of them first finds the server gone starts another (both then
        # reach it), and only this store stops it.
        self._siblings: dict[str, FalkorDBStore] = {}
        self._siblings_lock = threading.Lock()
        self._stops_server = True

    def setup(self, *, timeout: float | None = None) -> None:
        self.prepare(lambda store: self._open(timeout))

    def _open(self, timeout: float | None) -> None:
        if self._connect(timeout):
            # A freshly started server's first statement, bounded: twice in CI one never answered it (every
            # thread of the server waiting on a lock). prepare() kills such a server and starts another.
            _first_answer(self)

    def _connect(self, timeout: float | None) -> bool:
        """Connect (starting the embedded server if none runs); True when this call started it."""
        timeout = timeout or self.settings.connect_timeout
        started = False
        if self.settings.kind == "embedded":
            if self.server is None:
                if self.settings.data_dir is None:
                    raise StoreUnavailable(f"store {self.settings.url}: an embedded store needs a data directory")
                self.server = EmbeddedServer(self.settings.data_dir, start_timeout=timeout)
            starts = self.server.starts
            address = self.server.ensure()
            started = self.server.starts > starts
            kwargs: dict[str, Any] = {"unix_socket_path": address.unix_socket}
        elif self.settings.unix_socket:
            kwargs = {"unix_socket_path": self.settings.unix_socket}
        else:
            kwargs = {"host": self.settings.host, "port": self.settings.port}
        if self.settings.password:
            kwargs["password"] = self.settings.password
        if self.settings.username:
            kwargs["username"] = self.settings.username
        loading_since = time.monotonic()
        while True:
            try:
                # The bounded client first: FalkorDB() itself asks the server (INFO), then PING. The ordinary
                # client is made once the server has answered.
                limit = self._setup_limit()
                setup_db = FalkorDB(socket_connect_timeout=timeout, socket_timeout=limit, **kwargs)
                setup_db.connection.ping()
                # One client where the ordinary limit is the setup limit (sandboxes, the public worker): a
                # FalkorDB() costs a connection and two INFOs (about 1 ms).
                db = setup_db if self.settings.socket_timeout == limit else FalkorDB(
                    socket_connect_timeout=timeout, socket_timeout=self.settings.socket_timeout, **kwargs)
                break
            except redis.BusyLoadingError as exc:
                self._wait_while_loading(loading_since, timeout, exc)
            except redis.TimeoutError as exc:
                raise self._no_setup_answer("connecting: INFO, PING", exc) from exc
            except (redis.RedisError, OSError) as exc:
                raise StoreUnavailable(f"cannot reach FalkorDB at {self.settings.url}: {exc}") from exc
        # Other threads keep using the old clients until the new ones are whole.
        self._setup_graph = setup_db.select_graph(self.settings.graph)
        self._setup_db = setup_db
        self._graph = db.select_graph(self.settings.graph)
        self._db = db
        return started

    def _setup_limit(self) -> float:
        limit = self.settings.setup_timeout
        return limit if self.settings.socket_timeout is None else min(limit, self.settings.socket_timeout)

    def prepare(self, steps: Callable[[GraphStore], T]) -> T:
        """``steps(self)`` with every answer bounded by ``settings.setup_timeout``.

        An embedded server that does not answer in time and is ours to end (we started it, or it answers
        no PING) is killed and another started on the same data; the steps then run once more. Otherwise,
        or if the new server does not answer either, StoreUnavailable naming what each server was doing:
        its pid, state and its threads' wait channels.
        """
        if getattr(self._preparing, "on", False):
            return steps(self)  # the outer prepare() bounds these and retries
        self._preparing.on = True
        try:
            try:
                return steps(self)
            except _NoSetupAnswer as exc:
                first = exc
            if not self._end_hung(first):
                raise StoreUnavailable(str(first)) from first
            log.error("%s; killed it, starting another on the same data", first)
            try:
                self._reopen()
                return steps(self)
            except _NoSetupAnswer as exc:
                self._end_hung(exc)
                raise StoreUnavailable(f"{exc}; killed it too, as the server before it, which had "
                                       f"not answered either ({first.server})") from exc
        finally:
            self._preparing.on = False
            setup_db = self._setup_db
            if setup_db is not None and setup_db is not self._db:  # keep no idle connection once set up
                setup_db.connection.connection_pool.disconnect(inuse_connections=False)

    def _preparing_now(self) -> bool:
        return bool(getattr(self._preparing, "on", False))

    def _no_setup_answer(self, what: str, exc: Exception) -> "_NoSetupAnswer":
        server = "not ours to see"
        if self.settings.kind == "embedded" and self.server is not None:
            server = self.server.describe() + f", answers PING: {'yes' if self.server.answers() else 'no'}"
        return _NoSetupAnswer(f"FalkorDB at {self.settings.url} gave no answer to a setup statement "
                              f"({what[:80]}) within {self._setup_limit():g} s: server {server}", server=server)

    def _end_hung(self, exc: "_NoSetupAnswer") -> bool:
        """Kill the embedded server that did not answer a setup statement; False when it is not ours to
        kill (not embedded, or another process's server that still answers PING)."""
        server = self.server
        if self.settings.kind != "embedded" or server is None or (not server.owned and server.answers()):
            return False
        server.kill()
        return True

    def _reopen(self) -> None:
        with self._reconnect_lock:
            old, old_setup = self._db, self._setup_db
            self._open(None)  # nothing answers at the old address now: ensure() starts another server
            _close_replaced((old, old_setup), keep=(self._db, self._setup_db))

    def sibling(self, graph: str) -> GraphStore:
        """The store of graph ``graph`` on this store's server: connected at the first call, then kept (see
        GraphStore.sibling). It reaches the server as this store does (an embedded one: the same server
        object, so a restart by either is found by both) with the same limits."""
        if graph == self.settings.graph:
            return self
        with self._siblings_lock:
            found = self._siblings.get(graph)
            if found is not None:
                return found
            if self._db is None:
                raise StoreUnavailable(f"store {self.settings.url} is not set up; call setup() before "
                                       f"reaching graph {graph!r} beside it")
            store = FalkorDBStore(dataclasses.replace(self.settings, graph=graph), server=self.server)
            store._stops_server = False
            store.setup()
            self._siblings[graph] = store
            return store

    def graph_names(self) -> list[str]:
        """Every graph on this store's server (GRAPH.LIST)."""
        client: Any = self.redis  # redis-py's execute_command is untyped
        try:
            names = client.execute_command("GRAPH.LIST")
        except redis.RedisError as exc:
            raise StoreUnavailable(f"FalkorDB at {self.settings.url}: cannot list its graphs: {exc}") from exc
        return sorted(n.decode() if isinstance(n, bytes) else str(n) for n in names)

    def drop_graph(self, graph: str) -> None:
        """Delete graph ``graph`` on this store's server (none there: nothing to do) and close its sibling
        store if one is kept; never this store's own graph (clear() does that)."""
        if graph == self.settings.graph:
            raise ConfigError(f"store {self.settings.url}: drop_graph is for graphs beside {graph!r}; use clear()")
        with self._siblings_lock:
            sibling = self._siblings.pop(graph, None)
        if sibling is not None:
            sibling.shutdown()  # a sibling never stops the server
        try:
            self.redis.delete(graph)  # a graph is a key: DEL frees it as GRAPH.DELETE does
        except redis.RedisError as exc:
            raise StoreUnavailable(f"FalkorDB at {self.settings.url}: cannot delete graph {graph!r}: {exc}") from exc

    def swap_in(self, moves: Mapping[str, str], *, marker: str, check: Callable[[], None]) -> None:
        """Put staged graphs in place as one step: for each ``staged -> target`` of ``moves``, delete the
        staged graph's nodes labelled ``marker`` and RENAME it to ``target`` (replacing an empty one), all in
        one MULTI/EXEC, so a reader sees every target as it was or every staged graph in its place, never a mix.

        Every graph named is WATCHed first, then ``check()`` runs (it reads the targets and raises if they
        may not be replaced) and each staged graph must still hold its ``marker`` node (it was not deleted,
        and begun again by someone else, while it was being written). A write to any of them after the WATCH
        aborts the EXEC: ConfigError, nothing moved. The staged graphs' sibling stores are closed after the
        move and the stores of the targets select their graph again (the client caches a graph's schema)."""
        keys = [*moves, *moves.values()]
        pipe: Any = self.redis.pipeline(transaction=True)  # its watch and execute_command are untyped
        try:
            pipe.watch(*keys)
            check()
            for staged in moves:
                if not pipe.exists(staged) or pipe.execute_command(
                        "GRAPH.RO_QUERY", staged, f"MATCH (m:{marker}) RETURN count(m)")[1] != [[1]]:
                    raise ConfigError(f"store {self.settings.url}: staged graph {staged!r} was deleted (and "
                                      "begun again) by someone else while this import ran (another import into "
                                      "the same store?): nothing imported")
            pipe.multi()
            for staged, target in moves.items():
                pipe.execute_command("GRAPH.QUERY", staged, f"MATCH (m:{marker}) DELETE m")
                pipe.rename(staged, target)
            replies = pipe.execute(raise_on_error=False)
        except redis.WatchError as exc:
            raise ConfigError(f"store {self.settings.url}: graphs {', '.join(moves.values())} changed while the "
                              "import was being put in place: nothing imported") from exc
        except redis.ResponseError as exc:
            raise QueryError(f"store {self.settings.url}: putting the import in place failed: {exc}") from exc
        except (redis.RedisError, OSError) as exc:
            raise StoreUnavailable(f"lost FalkorDB at {self.settings.url} while putting the import in place: "
                                   f"{exc}") from exc
        finally:
            pipe.reset()
        failed = [reply for reply in replies if isinstance(reply, Exception)]
        if failed:  # not seen: each command was checked above, inside the WATCH
            raise QueryError(f"store {self.settings.url}: putting the import in place: {failed[0]}")
        for staged in moves:
            self.drop_graph(staged)  # gone by its name already: closes its sibling store
        with self._siblings_lock:
            stores = [self, *self._siblings.values()]
        for store in stores:
            if store.settings.graph in moves.values():
                store._select_again()

    def _select_again(self) -> None:
        with self._reconnect_lock:
            if self._db is not None:
                self._graph = self._db.select_graph(self.settings.graph)
            if self._setup_db is not None:
                self._setup_graph = self._setup_db.select_graph(self.settings.graph)

    def shutdown(self) -> None:
        with self._siblings_lock:
            siblings, self._siblings = list(self._siblings.values()), {}
        for sibling in siblings:
            sibling.shutdown()
        for db in {id(db): db for db in (self._db, self._setup_db)}.values():
            if db is not None:
                try:
                    db.connection.close()
                except redis.RedisError:
                    pass
        self._db = self._setup_db = None
        self._graph = self._setup_graph = None
        if self.server is not None and self._stops_server:
            self.server.stop()

    @property
    def dialect(self) -> Dialect:
        return FALKORDB

    @property
    def capabilities(self) -> Capabilities:
        # MULTI/EXEC batches; GRAPH.QUERY's TIMEOUT; GRAPH.RO_QUERY refuses writes. No TLS on
        # the unix socket of the embedded store. redis-py's connection pool serves many threads;
        # DUMP/RESTORE copies the graph into a QuerySandbox; a graph is a key, many on one server.
        return Capabilities(transactions=True, timeouts=True, tls=False, read_only="store",
                            thread_safe=True, sandbox=True, graphs=True)

    @property
    def redis(self) -> redis.Redis:
        """The underlying redis client (for admin commands such as ``GRAPH.CONFIG``)."""
        if self._db is None:
            raise StoreUnavailable("store is not set up; call setup() first")
        db = self._setup_db if self._preparing_now() and self._setup_db is not None else self._db
        client: redis.Redis = db.connection
        return client

    def _execute(self, cypher: str, params: Mapping[str, Any] | None, read_only: bool,
                 timeout_ms: int | None) -> list[Row]:
        result = self._run(params_header(params) + cypher, read_only, timeout_ms)
        if result is None:
            return []
        columns = [name for _, name in result.header] if result.header else []
        return [{c: _plain(v) for c, v in zip(columns, row, strict=True)} for row in result.result_set]

    def _run(self, query: str, read_only: bool, timeout_ms: int | None) -> Any:
        if self._graph is None:
            raise StoreUnavailable("store is not set up; call setup() first")
        loading_since: float | None = None
        reconnected = False
        while True:
            graph = self._setup_graph if self._preparing_now() else self._graph
            try:
                if read_only:
                    return graph.ro_query(query, timeout=timeout_ms)
                return graph.query(query, timeout=timeout_ms)
            except redis.BusyLoadingError as exc:
                loading_since = loading_since or time.monotonic()
                self._wait_while_loading(loading_since, self.settings.connect_timeout, exc)
            except redis.ResponseError as exc:
                message = str(exc)
                if read_only and "empty key" in message:
                    return None  # FalkorDB: a read on a graph never written to; no rows
                if "read-only" in message:
                    raise ReadOnlyViolation(f"read-only query refused by the store: {message}") from exc
                if "timed out" in message:  # GRAPH.QUERY ... TIMEOUT: "Query timed out"
                    raise StoreTimeout(f"store rejected the query: {message}") from exc
                raise QueryError(f"store rejected the query: {message}") from exc
            except redis.TimeoutError as exc:
                if self._preparing_now():
                    raise self._no_setup_answer(query, exc) from exc
                # The socket timeout is the hard limit: the answer is abandoned (redis-py drops
                # the connection); the server may still be working on it.
                limit = self.settings.socket_timeout
                restarted = self._restart_if_hung(self._graph)
                raise QueryTimeLimit(
                    f"query abandoned: no answer within the hard limit of {limit if limit is not None else '?'} s"
                    + ("; the embedded server answered no PING either and was restarted" if restarted else "")
                ) from exc
            except (redis.ConnectionError, OSError) as exc:
                # The embedded server may have been restarted by another of our
                # processes; find (or start) it again, once.
                if reconnected or self.settings.kind != "embedded":
                    raise StoreUnavailable(f"lost FalkorDB at {self.settings.url}: {exc}") from exc
                log.warning("lost the embedded store (%s); reconnecting", exc)
                self._reconnect(self._graph)
                reconnected = True

    def _wait_while_loading(self, since: float, limit_s: float, exc: Exception) -> None:
        """A restarted server answers LOADING until its AOF is read (20 s seen on a loaded machine):
        wait a moment, or give up once it has been loading for ``limit_s``."""
        if time.monotonic() - since >= limit_s:
            raise StoreUnavailable(f"FalkorDB at {self.settings.url} still loading its data after {limit_s:g} s: "
                                   f"{exc}") from exc
        time.sleep(_LOADING_POLL_S)

    def _restart_if_hung(self, failed_graph: Any) -> bool:
        """After a query hit the hard limit: if the embedded server answers no PING, it is hung, not busy
        (FalkorDB runs queries on worker threads, so PING answers beside a long one); restart it.

        Without this every later query would time out too until someone restarted the server by hand.
        """
        if self.settings.kind != "embedded" or self.server is None or self.server.answers():
            return False
        try:
            self._reconnect(failed_graph)  # ensure() kills the hung server before it starts another
        except StoreUnavailable as exc:
            log.error("could not restart the hung embedded store: %s", exc)
            return False
        return True

    def _reconnect(self, failed_graph: Any) -> None:
        """Reconnect once for all threads: whoever comes second finds it done."""
        with self._reconnect_lock:
            if self._graph is not failed_graph and self._graph is not None:
                return  # another thread already reconnected
            old, old_setup = self._db, self._setup_db
            self.setup()  # replaces the clients only when it succeeds
            _close_replaced((old, old_setup), keep=(self._db, self._setup_db))

    def execute_atomic(self, statements: Sequence[Statement]) -> None:
        """MULTI/EXEC: the batch runs in isolation and in one AOF write.

        Redis does not roll back a transaction whose command fails at run
        time, so callers validate before writing (the importers do); an
        error in any reply is raised.
        """
        if self._graph is None or self._db is None:
            raise StoreUnavailable("store is not set up; call setup() first")
        preparing = self._preparing_now()
        db = self._setup_db if preparing and self._setup_db is not None else self._db
        pipe = db.connection.pipeline(transaction=True)
        batch = [params_header(params) + cypher for cypher, params in statements]  # all checked before any is sent
        for query in batch:
            pipe.execute_command("GRAPH.QUERY", self.settings.graph, query, "--compact")
        try:
            replies = pipe.execute(raise_on_error=False)
        except redis.TimeoutError as exc:
            if preparing:
                raise self._no_setup_answer(f"a batch of {len(batch)} statements", exc) from exc
            graph = self._graph
            restarted = self._restart_if_hung(graph)
            raise StoreUnavailable(f"lost FalkorDB at {self.settings.url}: {exc}"
                                   + ("; it answered no PING and was restarted" if restarted else "")) from exc
        except (redis.ConnectionError, OSError) as exc:
            raise StoreUnavailable(f"lost FalkorDB at {self.settings.url}: {exc}") from exc
        except redis.RedisError as exc:
            raise QueryError(f"store rejected the batch: {exc}") from exc
        for (cypher, _), reply in zip(statements, replies, strict=True):
            if isinstance(reply, Exception):
                raise QueryError(f"store rejected a statement of the batch ({cypher[:60]}...): {reply}")

    def compact(self, *, timeout: float = 30.0) -> None:
        """Rewrite the append-only file as a snapshot (BGREWRITEAOF) and wait for it.

        A restart then loads the graph from the snapshot instead of replaying the model load's index
        creations and MULTI/EXEC of writes through FalkorDB's query path. FalkorDB 4.16 yields to the
        event loop in that replay, where a command arriving aborts the server ('!server.in_exec'), and a
        restart under load was once seen to hang there for more than 10 s. A rewrite that fails or does
        not end in time loses nothing (the append-only file stays whole): it is logged, not raised.
        """
        client = self.redis
        try:
            if not int(client.info("persistence").get("aof_enabled", 0)):
                return  # no append-only file: nothing is replayed at a restart
            client.bgrewriteaof()
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                state = client.info("persistence")
                if not int(state.get("aof_rewrite_in_progress", 0)) and not int(state.get("aof_rewrite_scheduled", 0)):
                    if state.get("aof_last_bgrewrite_status") != "ok":
                        log.warning("FalkorDB at %s: rewriting the append-only file failed (%s); it stays as it was",
                                    self.settings.url, state.get("aof_last_bgrewrite_status"))
                    return
                time.sleep(0.01)  # the rewrite runs in a forked child: nothing to wait on but INFO
            log.warning("FalkorDB at %s: the append-only file rewrite did not end within %.0f s",
                        self.settings.url, timeout)
        except redis.RedisError as exc:
            log.warning("FalkorDB at %s: cannot rewrite the append-only file: %s", self.settings.url, exc)

    def clear(self) -> None:
        """Delete this graph and, when it is a robot's, the graphs that hold the rest of that robot's knowledge
        beside it (schema.Graph: its fleet roster). Other graphs on the server are left as they are; a
        sibling's clear deletes its own graph alone."""
        self._delete_graph()
        from kgadapt.knowledge.schema import Graph, is_beside  # the schema knows the store, not the other way round

        if is_beside(self.settings.graph):
            return
        for part in Graph:
            if part is not Graph.ROBOT and self.redis.exists(part.beside(self.settings.graph)):
                part.store(self).clear()  # the sibling's own graph alone

    def _delete_graph(self) -> None:
        if self._graph is None or self._db is None:
            raise StoreUnavailable("store is not set up; call setup() first")
        try:
            self._graph.delete()
        except redis.ResponseError:
            pass  # no such graph yet
        self._graph = self._db.select_graph(self.settings.graph)


class _NoSetupAnswer(StoreUnavailable):
    """A setup statement had no answer within the setup limit (prepare() turns it into StoreUnavailable)."""

    def __init__(self, message: str, *, server: str) -> None:
        super().__init__(message)
        self.server = server


def _close_replaced(clients: Sequence[FalkorDB | None], *, keep: Sequence[FalkorDB | None]) -> None:
    for client in clients:
        if client is not None and all(client is not kept for kept in keep):
            try:
                client.connection.close()
            except redis.RedisError:
                pass


def _first_answer(store: GraphStore) -> None:
    store.ping()  # GRAPH.RO_QUERY: answered by the module even before the graph exists


def params_header(params: Mapping[str, Any] | None) -> str:
    """FalkorDB's parameter prefix ``CYPHER a=1 b='x' `` for ``params`` ("" when there are none).

    Values are written by :func:`kgadapt.knowledge.params.cypher_literal`, as an export script writes them.
    """
    clean = check_params(params)
    if not clean:
        return ""
    return "CYPHER " + "".join([f"{name}={cypher_literal(value, name=name)} " for name, value in clean.items()])


def _plain(value: Any) -> Any:
    """Store values as plain Python: nodes and edges become dicts."""
    if isinstance(value, Node):
        return {**value.properties, "_labels": sorted(value.labels or [])}
    if isinstance(value, Edge):
        return {**value.properties, "_type": value.relation}
    if isinstance(value, GraphPath):
        return [_plain(n) for n in value.nodes()]
    if isinstance(value, list):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value
