"""The knowledge service: the graph store, reachable over Zenoh.

It owns the store and serves, under ``kgadapt/<robot>/knowledge/``:

===========================  ====================================  ==========================
key                          request                               reply
===========================  ====================================  ==========================
``query/<name>``             ``query_request {params}``            ``rows {rows, elapsed_ms}``
``own/query/<name>``         ``query_request {params}``            ``rows`` (the robot's own software)
``cypher``                   ``cypher_request {cypher, params}``   ``rows`` (read-only subset only)
``write/<verb>``             ``write_request {params}``            ``rows {rows: []}`` (operators)
``write/<host>/<verb>``      ``write_request {params}``            ``rows {rows: []}`` (host's own)
``own/stats``                (none)                                ``rows`` (one row: counters)
===========================  ====================================  ==========================

``<name>`` is any of ``kgadapt.knowledge.queries.QUERIES``, ``<verb>`` any of
``kgadapt.knowledge.runtime.WRITERS``. A named query may also be asked without a
payload, its parameters in the selector (``query/placement?feature=MarkerDetection``),
which is handy from Zenoh's own tools. Every problem (malformed, truncated,
wrong-typed or oversized payload, unknown query or verb, missing or ill-typed
parameter, a write sent as Cypher, a store error) is answered with
``query.reply_err(text)`` naming it.

Two doors, two paths. ``own/query/*`` (the robot's own agents, manager and
detectors; the shipped ACL keeps other robots off it) and the write verbs
are served by their own workers from the primary store. ``query/*`` and
``cypher`` (anyone allowed to read, other robots included) are checked by
other workers and answered by a
:class:`~kgadapt.knowledge.public_worker.PublicWorker` each: a child process
at nice 19 that runs them on a :class:`~kgadapt.knowledge.sandbox.QuerySandbox`
(a copy of the graph in a separate, lower-priority FalkorDB server, as fresh
as the primary) and reads and encodes their answers there, so that neither
takes the service's interpreter or a core from the robot's own requests.
Waiting questions are kept per asker (:class:`~kgadapt.shared.fair_queue.FairQueue`,
the asker named by its query's attachment): at most ``max_pending_per_asker``
each, ``max_pending_public`` in all, the askers served in turn.
Each of those questions has a hard time limit (``public_time_limit_ms``,
or a literal paper query's own shorter one): past it the answer is
abandoned and the sandbox server killed, so the work stops. Free Cypher must
parse in the subset of :mod:`kgadapt.knowledge.cypher_guard`. Their workers wait
(before a question runs, before its answer is encoded) while one of the robot's
own requests is being answered (:class:`OwnFirst`): parsing and encoding a large
answer would otherwise take the interpreter from it. A flood of questions
thus costs other robots their answers, never the robot its own. One service
per store: :class:`~kgadapt.knowledge.service_lock.ServiceLock`.

Write verbs sit on their own key (``knowledge/write/**``) so that Zenoh access
control can keep them from other robots while the queries stay open; with
``writes=False`` (``kgadapt knowledge serve --read-only``) they are not
declared at all. A host's agent writes on ``write/<host>/<verb>``, which the
shipped ACL opens to that host's certificate only, and the service accepts
there only what that host owns (:func:`check_owner`): its own platform, its
own processes (by ``host``, or by the ``run_id`` of a profile it started), and
on the ``manager_host`` the decisions and the flight state. ``write/<verb>``
(any verb, about anything) is for operators and the service's own identity.
Every write's figures must be plausible (``kgadapt.knowledge.runtime``'s bounds).

It also keeps each ``Platform``'s run-time figures current: host statuses
(``host/<host>/status``) update free memory, CPU load and ``last_seen``
(the service's receive time, so hosts' clocks need not agree), and host
liveliness (``host/<host>/alive``, subscribed with history) sets ``online``.
A status never sets ``online``: only the token does, so a late status cannot
revive a host whose token is gone. Only the models add hosts: a status, a
token or a write naming a host no ``Platform`` of the models names is refused
(logged once per host, counted as ``unknown_host_refused``, the names in
``own/stats`` and ``kgadapt status``), and a decision's ``time`` is the
service's receive time, not the sender's clock. At setup every platform is first marked
offline; the liveliness history then marks the live ones online again.

Threads: Zenoh callbacks only put work on queues. Request workers (two
:class:`kgadapt.shared.rpc.Server` pools: ``workers`` for the robot's own requests,
``public_workers`` for other robots') answer queries; one status worker applies host statuses and
liveliness changes. Statuses have no callback: Zenoh keeps them in a ring of
``max_pending_statuses`` (the oldest dropped first when it is full), and the status worker takes
them all every ``status_batch_s`` (a Python callback per status cost the
services more than everything they then did with it). A liveliness change
comes by callback, which first moves the statuses received before it onto the
queue, so the worker sees both in the order they arrived, and ends the wait at
once. A status's receive time is when it is taken (at most ``status_batch_s``
after it arrived, or a second after a spell with no status at all; the order of
receive times is the order of arrival). The newest of each host is written
in one ``UNWIND`` store call per batch, each host's figures checked as a
single write checks them; the profiles' memory StatusTrust needs is read for
the batch in one call too. A status within the deadband of what the graph holds
of its host waits (``status_deadband_mb``, ``status_deadband_load``): the waiting
ones are written together at most ``status_refresh_s`` later, checked again
against the profiles read then.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import zenoh

from kgadapt.knowledge import queries, runtime
from kgadapt.knowledge import schema as S
from kgadapt.knowledge.cypher_guard import CypherLimits, check_cypher
from kgadapt.knowledge.fleet import ROSTER_QUERY
from kgadapt.knowledge.fleet_roster import FleetRoster, RosterSettings
from kgadapt.knowledge.params import check_params
from kgadapt.knowledge.service_lock import ServiceLock
from kgadapt.knowledge.store import GraphStore
from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.errors import (
    ConfigError,
    KgadaptError,
    MessageError,
    NamedQueryError,
    QueryError,
    QueryTimeLimit,
    TransportError,
    UnknownHost,
)
from kgadapt.shared.fair_queue import FairQueue
from kgadapt.shared.hostmonitor import StatusTrust, TrustSettings, check_status

log = logging.getLogger(__name__)

_STOP = object()
_MAX_LIVELINESS_DUE = 100  # per host: a flapping token while the store is away
_MAX_REFUSED_HOSTS = 256  # names of refused hosts remembered (and logged); past that only counted
_UNKNOWN_RECHECK_S = 10.0  # a refused host is looked up again this often (the models may be reloaded)
_QUIET_TAKES = 4  # status takes that found nothing before the ring is taken every _QUIET_TAKE_S
_QUIET_TAKE_S = 1.0


def _next_tick(now: float, period: float) -> float:
    """When a take ``period`` after the last one is due: the next multiple of ``period`` on the monotonic
    clock. Services that take on this shared grid wake together and run one after another on warm
    caches; a take alone costs several times one among others (docs/fleet.md). A period over a second
    gains nothing from company and is kept whole."""
    if period > _QUIET_TAKE_S:
        return now + period
    return (now // period + 1) * period


@dataclass(frozen=True, kw_only=True)
class ServiceSettings:
    """How the knowledge service serves."""

    robot: str = keys.DEFAULT_ROBOT
    writes: bool = True  # declare knowledge/write/<verb>; False = --read-only
    workers: int = 2  # request worker threads (a slow Cypher query then blocks only one)
    query_timeout_ms: int = 5000  # named queries (FalkorDB honours it late for reads)
    max_pending_requests: int = 1000
    # Statuses waiting in Zenoh's ring for the status worker (when it is full the oldest go first: only each
    # host's newest is written), and events on its queue.
    max_pending_statuses: int = 10000
    # A liveliness change the store could not take (e.g. it was restarting) is tried again this often,
    # in order with the host's later changes; the profiles of a lost host must end even then.
    liveliness_retry_s: float = 1.0
    mark_offline_at_start: bool = True
    # Other robots' questions (query/*, cypher): own workers, a copy of the graph, hard limits.
    public_workers: int = 2
    public_time_limit_ms: int = 1000
    max_pending_public: int = 32
    # Each asker (named by its query's attachment; none: "anonymous") has at most this many questions
    # waiting, and the askers waiting take turns: one asker's flood fills only its own line.
    max_pending_per_asker: int = 8
    # Other robots' questions run in child processes (PublicWorker, one per public worker) at this added
    # niceness, not in the service's: reading and encoding their answers no longer takes the interpreter
    # or a core from the robot's own requests. False: in this process (from its own sandboxes).
    public_process: bool = True
    public_nice: int = 19
    # Other robots' questions wait, before they run and before their answer is encoded, while the robot's
    # own requests are being answered (at most this long each time): on 2 cores their parsing and encoding
    # otherwise takes the interpreter from the robot's own. 0: no waiting.
    own_first_wait_s: float = 1.0
    sandbox: bool = True  # serve them from a QuerySandbox when the store is FalkorDB
    lock: bool = True  # refuse to start beside another service on the same store
    # The host whose agent runs the adaptation manager and the flight bridge: the one that may write
    # decisions and the flight state on its write/<host>/<verb> key.
    manager_host: str = "onboard"
    # Host statuses wait at most status_batch_s for others and are written together, the newest per
    # host, at most status_batch_max events a batch, in one store call (liveliness changes never wait).
    # The window bounds how far the graph's figures lag the statuses: the adaptation manager checks
    # placements against the statuses it hears itself, so only the placement query's first cut and
    # operators' views wait for it. Hosts publish at their own phases, so 0.02 s held about one status
    # of a robot's 10 hosts at 2 Hz: two store calls a status, costing more than the status itself.
    status_batch_s: float = 0.25
    status_batch_max: int = 1000
    # A status whose figures are within the deadband of what the graph holds (free and total memory
    # within status_deadband_mb, load within status_deadband_load points, the same cores) waits; every
    # waiting host's newest status is written together at least every status_refresh_s. Placement
    # decides on tens to hundreds of MiB, and a host's free memory moves by a few MiB between
    # statuses: writing each costs a store call per batch, 2 Hz x hosts (0: write every status).
    # The refresh only makes figures already within the deadband exact (and moves last_seen; a loss
    # records the last status heard): at 2 s its reads and writes were a fifth of the fan-in's CPU.
    status_deadband_mb: float = 16.0
    status_deadband_load: float = 10.0
    status_refresh_s: float = 10.0
    # The fleet roster (knowledge/fleet_roster.py): robots heard on the fleet keys, at most roster_cap; roll
    # calls at setup and 5 s later, then every roster_interval_s (0: no more). roster=False: none kept.
    roster: bool = True
    roster_cap: int = 1000
    roster_interval_s: float = 600.0

    def __post_init__(self) -> None:
        keys.check_name(self.robot, "robot name")
        if self.workers < 1 or self.public_workers < 1:
            raise ConfigError(f"workers {self.workers!r}, public_workers {self.public_workers!r}: at least 1 each")
        keys.check_name(self.manager_host, "manager host")
        if self.public_time_limit_ms < 1:
            raise ConfigError(f"public_time_limit_ms {self.public_time_limit_ms!r}: at least 1")
        if min(self.status_deadband_mb, self.status_deadband_load, self.status_refresh_s) < 0:
            raise ConfigError(f"status_deadband_mb {self.status_deadband_mb!r}, status_deadband_load "
                              f"{self.status_deadband_load!r}, status_refresh_s {self.status_refresh_s!r}: "
                              "none below 0")


class KnowledgeService:
    """Serve one store over Zenoh. ``setup(session)`` declares, ``shutdown()`` undeclares.

    The store and the session belong to the caller: the service neither opens
    nor closes them.
    """

    def __init__(self, store: GraphStore, settings: ServiceSettings = ServiceSettings()) -> None:
        self.store = store
        self.settings = settings
        # The robot's own requests (own/query/*, writes) and other robots' questions (query/*, cypher):
        # two pools, so a flood of the second never delays the first.
        self._own = rpc.Server("knowledge service", workers=settings.workers, max_pending=settings.max_pending_requests)
        self._public = rpc.Server("knowledge service", workers=settings.public_workers,
                                  max_pending=settings.max_pending_public,
                                  pending=FairQueue(maxsize=settings.max_pending_public,
                                                    per_asker=settings.max_pending_per_asker, asker_of=asker_of))
        self.own_first = OwnFirst(max_wait_s=settings.own_first_wait_s)
        # Liveliness changes (and the statuses taken before each) for the status worker. A SimpleQueue: its
        # timed get() is C, and the worker waits on it about four times a second (docs/fleet.md, issue 32);
        # its bound is kept by the one producer, _on_alive, under _take_lock.
        self._events: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._event_thread: threading.Thread | None = None
        # The status subscriber (its samples wait in Zenoh's ring until taken), and the lock that keeps a
        # liveliness change behind the statuses received before it: taking statuses and queueing a change
        # each hold it.
        self._status_sub: Any = None
        self._take_lock = threading.Lock()
        # Per host, its liveliness changes not yet in the store, oldest first (only the status worker touches it).
        self._liveliness_due: dict[str, list[tuple[bool, float, float | None]]] = {}
        # Per host (status worker only): the figures last written, the newest admitted status within the
        # deadband of them (not written yet), the profiles' memory last read; when waiting ones are written.
        self._written: dict[str, messages.HostStatus] = {}
        self._waiting: dict[str, tuple[messages.HostStatus, float]] = {}
        self._held: dict[str, float] = {}
        self._refresh_at = 0.0
        self._retry_at = 0.0  # when the liveliness changes the store refused are tried again
        self._stack = contextlib.ExitStack()
        self._stats_lock = threading.Lock()
        self._stats: collections.Counter[str] = collections.Counter()
        self._last_drop = ""
        self._drop_log = _RateLimitedLog(log, per_second=10)
        # Statuses contradicting what is known are refused here too (the graph never holds them). Those of
        # a host without a token are still recorded: the placement query takes only online platforms.
        self._trust = StatusTrust(TrustSettings(require_alive=False))
        self._store_lock = _store_lock(store)
        self._writers: Mapping[str, Callable[..., Any]] = dict(runtime.WRITERS) if settings.writes else {}
        self._lock = ServiceLock(store) if settings.lock else None
        # kgadapt.knowledge.sandbox.QuerySandbox (public_process=False) or PublicWorker, one per public
        # worker thread: a kill costs only its own question
        self.sandboxes: list[Any] = []
        self.public_processes: list[Any] = []
        self._sandbox_pool: queue.Queue[Any] = queue.Queue()
        # Kept where the store keeps it (schema.Graph.FLEET_ROSTER: beside the robot's graph on FalkorDB).
        self.roster = (FleetRoster(store, RosterSettings(robot=settings.robot, cap=settings.roster_cap,
                                                         interval_s=settings.roster_interval_s))
                       if settings.roster else None)
        # Hosts of the models seen so far, and when each refused one was last looked up (status worker only);
        # the refused names, for stats (under _stats_lock).
        self._known_hosts: set[str] = set()
        self._unknown_checked: dict[str, float] = {}
        self._refused_hosts: list[str] = []

    # -- life cycle ---------------------------------------------------------

    def setup(self, session: Any) -> None:
        """Start the workers and declare the queryables and subscribers on ``session``."""
        robot = self.settings.robot
        with contextlib.ExitStack() as stack:  # closed at once if anything fails; else kept for shutdown()
            if self._lock is not None:
                self._lock.acquire()  # before anything is written: a second service changes nothing
                stack.callback(self._lock.release)
            if self.settings.sandbox and self.store.dialect.name == "falkordb" and self.store.capabilities.timeouts:
                # A FalkorDB over RESP (the Bolt listener has no DUMP/RESTORE to copy from).
                from kgadapt.knowledge.public_worker import PublicWorker, PublicWorkerSettings
                from kgadapt.knowledge.sandbox import QuerySandbox

                stack.callback(self.sandboxes.clear)
                stack.callback(self.public_processes.clear)
                for _ in range(self.settings.public_workers):
                    if self.settings.public_process:
                        worker = PublicWorker(self.store, PublicWorkerSettings(nice=self.settings.public_nice))
                        self.public_processes.append(worker)
                        stack.callback(worker.shutdown)
                        worker.start()  # the children start side by side, then are waited for
                    else:
                        sandbox = QuerySandbox(self.store)
                        self.sandboxes.append(sandbox)
                        stack.callback(sandbox.shutdown)
                        sandbox.setup()
                        self._sandbox_pool.put(sandbox)
                for worker in self.public_processes:
                    worker.wait_ready()
                    self._sandbox_pool.put(worker)
            if self.settings.mark_offline_at_start:
                self._mark_all_offline()
            if self.roster is not None:  # where the roster is, before a roll call can reach the queryables
                stack.callback(self.roster.shutdown)
                self.roster.open()
            stack.enter_context(self._own)
            stack.enter_context(self._public)
            self._event_thread = threading.Thread(target=self._event_loop, name="knowledge-status", daemon=True)
            self._event_thread.start()
            stack.callback(self._stop_event_worker)
            # Subscribers first: declarations reach others in order, so whoever
            # sees the queryables also sees that statuses are listened to.
            try:
                rpc.declared(stack, session.liveliness().declare_subscriber(keys.host_alive(robot, "*"), self._on_alive,
                                                                            history=True))
                self._status_sub = rpc.declared(stack, session.declare_subscriber(
                    keys.host_status(robot, "*"), zenoh.handlers.RingChannel(self.settings.max_pending_statuses)))
                # Forgotten (under the take-lock) before it is undeclared: a take from the ring while
                # zenoh-python undeclares it raises "Already mutably borrowed" (seen at a test's shutdown).
                stack.callback(self._forget_status_sub)
            except zenoh.ZError as exc:
                raise TransportError(f"knowledge service of {robot}: cannot subscribe to host statuses: {exc}") from exc
            stack.callback(self._own.undeclare)
            stack.callback(self._public.undeclare)
            if self.settings.writes:
                self._own.serve(session, keys.knowledge_write(robot, "*"), self._handler("write"), what="write")
                self._own.serve(session, keys.knowledge_host_write(robot, "*", "*"), self._handler("write"), what="write")
            self._public.serve(session, keys.knowledge_cypher(robot), self._handler("cypher"), what="cypher")
            self._public.serve(session, keys.knowledge_query(robot, "*"), self._handler("query"), what="query")
            self._own.serve(session, keys.knowledge_own_query(robot, "*"), self._handler("own"), what="own")
            if self.roster is not None:  # after the queryables: whoever hears the roll call can ask back
                self.roster.setup(session)
            self._own.serve(session, keys.knowledge_own_stats(robot), self._handler("stats"), what="stats")
            self._stack = stack.pop_all()
        log.info(
            "knowledge service for robot %s: %d named queries, cypher (read-only subset), %s; "
            "other robots' questions from %s, %d ms hard limit",
            robot, len(queries.QUERIES),
            f"write verbs {', '.join(sorted(self._writers))}" if self.settings.writes else "no write verbs (read-only)",
            f"{len(self.sandboxes)} sandbox copies" if self.sandboxes else "the store itself",
            self.settings.public_time_limit_ms,
        )
        if not self.sandboxes and not self.store.capabilities.timeouts:
            log.warning("the store %s cannot stop a query at a time limit: free Cypher and the literal paper "
                        "queries from other robots will be refused", self.store.url)

    def shutdown(self) -> None:
        """Undeclare everything and stop the workers (requests still queued get an error reply)."""
        self._stack.close()

    def stats(self) -> dict[str, Any]:
        """Counters: requests answered/refused/failed/shed, statuses applied/dropped, the last drop reason."""
        with self._stats_lock:
            counts: collections.Counter[str] = collections.Counter(self._stats)
            last_drop = self._last_drop
            refused = list(self._refused_hosts)
        for server in (self._own, self._public):
            counts.update({f"requests_{what}": n for what, n in server.stats().items() if n})
        restarts = sum(worker.restarts for worker in self.public_processes)
        if restarts:  # a public worker process found dead and started afresh
            counts["public_worker_restarts"] = restarts
        if self.roster is not None and self.roster.refused:  # new robots turned away by a full roster
            counts["roster_full_refused"] = self.roster.refused
        return {**counts, "last_drop": last_drop, "unknown_hosts": refused}

    # -- request handling, Zenoh-free (tests call these directly) -----------

    def answer_named(self, name: str, payload: bytes | None, selector_params: Mapping[str, str] | None = None,
                     *, public: bool = False) -> bytes:
        """A ``rows`` reply for named query ``name``; raise KgadaptError naming the problem.

        ``public``: asked on the door open to other robots, so it runs in the
        sandbox under the hard limit. The literal paper queries always do.
        """
        if name not in queries.QUERIES:
            raise NamedQueryError(f"unknown named query {name!r}; known: {', '.join(sorted(queries.QUERIES))}")
        if payload:
            request = messages.decode_as(payload, messages.QueryRequest)
            params = check_params(request.params or {}, what=f"query {name!r}", error=MessageError)
        elif selector_params:
            params = queries.coerce_params(name, dict(selector_params))
        else:
            params = {}
        query = queries.QUERIES[name]
        if query.graph is S.Graph.FLEET_ROSTER:
            if self.roster is None:  # its graph is not kept up to date: no answer rather than a stale one
                raise NamedQueryError(f"query {name!r}: the knowledge service of {self.settings.robot} keeps no "
                                      "fleet roster (ServiceSettings.roster is off)")
            if name == ROSTER_QUERY:  # a roll call announces its asker
                self._heard_roll_call(queries.check_params(name, params))
        if query.graph is not S.Graph.ROBOT:
            # Not in the robot's graph that sandboxes copy: run_named runs it where it is kept. The roster
            # is bounded (its cap): it needs no sandbox's time limit either.
            start = time.perf_counter()
            with self._store_lock:
                rows = queries.run_named(self.store, name, params, timeout_ms=self.settings.query_timeout_ms)
            return rows_reply(rows, (time.perf_counter() - start) * 1000, f"query {name!r}")
        start = time.perf_counter()
        if public or query.time_limit_ms is not None:
            limit_ms = min(self.settings.public_time_limit_ms, query.time_limit_ms or self.settings.public_time_limit_ms)
            values = queries.check_params(name, params)
            text = query.text_for(values)
            if "LIMIT" not in text.rstrip().splitlines()[-1].upper():
                # Rows are parsed here, under the GIL the robot's own requests need too:
                # fig4_literal's 21,344 rows cost them tens of ms. Same bound as free Cypher.
                text = f"{text.rstrip()}\nLIMIT {CypherLimits().max_rows}"
            # A named query's text has no clock or random number: on an unchanged copy, the same answer.
            if self.public_processes:
                return self._run_in_public_process(text, values, limit_ms, f"query {name!r}", cacheable=True)
            rows = self._run_untrusted(text, values, limit_ms, f"query {name!r}", cacheable=True)
            self.own_first.wait_turn()  # encoding a large answer holds the interpreter too
        else:
            with self._store_lock:
                rows = queries.run_named(self.store, name, params, timeout_ms=self.settings.query_timeout_ms)
        return rows_reply(rows, (time.perf_counter() - start) * 1000, f"query {name!r}")

    def _heard_roll_call(self, values: Mapping[str, Any]) -> None:
        """Another robot's roll call announced it: remember it (a bad name is refused, naming it)."""
        assert self.roster is not None
        try:
            with self._store_lock:
                self.roster.heard(values)
        except (ConfigError, MessageError) as exc:
            raise MessageError(f"query {ROSTER_QUERY!r}: {exc}") from exc
        except KgadaptError as exc:  # the store refused it: the question is still answered
            self._count("roster_not_recorded")
            log.warning("fleet roster: %s not recorded: %s", values.get("announce"), exc)

    def answer_cypher(self, payload: bytes | None) -> bytes:
        """A ``rows`` reply for read-only Cypher; a write is refused with ReadOnlyViolation."""
        if not payload:
            raise MessageError("cypher_request has no payload")
        request = messages.decode_as(payload, messages.CypherRequest)
        text = check_cypher(request.cypher)  # before anything reaches a store
        params = check_params(request.params or {}, what="cypher", error=MessageError)
        if self.public_processes:
            return self._run_in_public_process(text, params, self.settings.public_time_limit_ms, "cypher")
        start = time.perf_counter()
        rows = self._run_untrusted(text, params, self.settings.public_time_limit_ms, "cypher")
        self.own_first.wait_turn()
        return rows_reply(rows, (time.perf_counter() - start) * 1000, "cypher")

    def _run_in_public_process(self, text: str, params: Mapping[str, Any], limit_ms: int, what: str, *,
                               cacheable: bool = False) -> bytes:
        """The encoded reply, from a lower-priority child process (read, encoded there)."""
        self.own_first.wait_turn()
        worker = self._sandbox_pool.get()  # as many as public workers: never waits
        try:
            return bytes(worker.execute(text, params, limit_ms=limit_ms, what=what, cacheable=cacheable))
        except QueryTimeLimit:
            self._count("time_limits_hit")
            raise
        finally:
            self._sandbox_pool.put(worker)

    def _run_untrusted(self, text: str, params: Mapping[str, Any], limit_ms: int, what: str, *,
                       cacheable: bool = False) -> list[dict[str, Any]]:
        """In the sandbox when there is one (killed past the limit), else on the store with its timeout."""
        self.own_first.wait_turn()
        try:
            if self.sandboxes:
                sandbox = self._sandbox_pool.get()  # as many as public workers: never waits
                try:
                    return sandbox.execute(text, params, limit_s=limit_ms / 1000, cacheable=cacheable)
                finally:
                    self._sandbox_pool.put(sandbox)
            if not self.store.capabilities.timeouts:
                # Nothing could cut it off: refuse rather than pretend (said at start-up too).
                self._count("refused_no_time_limit")
                raise QueryError(f"{what}: the store {self.store.url} cannot stop a query at a time limit, so "
                                 "questions from outside the robot that need one are refused; ask a named query")
            with self._store_lock:
                return self.store.execute(text, params, read_only=True, timeout_ms=limit_ms)
        except QueryTimeLimit as exc:
            self._count("time_limits_hit")
            raise QueryTimeLimit(f"{what}: {exc}") from exc

    def answer_write(self, verb: str, payload: bytes | None, *, host: str | None = None,
                     received: float | None = None) -> bytes:
        """Apply write verb ``verb``; an empty ``rows`` reply, or KgadaptError naming the problem.

        ``host``: asked on ``write/<host>/<verb>``, so only what ``host`` owns is accepted.
        ``received``: when the request arrived (stamped on process samples).
        """
        if not self.settings.writes:
            raise NamedQueryError("this knowledge service is read-only: no write verbs")
        if verb not in self._writers:
            raise NamedQueryError(f"unknown write verb {verb!r}; known: {', '.join(sorted(self._writers))}")
        if not payload:
            raise MessageError(f"write_request for {verb!r} has no payload")
        request = messages.decode_as(payload, messages.WriteRequest)
        params = check_params(request.params, what=f"write verb {verb!r}", error=MessageError)
        if verb == "process_sample":  # ours, not the sender's: a late sample must not reopen a lost host's profile
            params["received"] = time.time() if received is None else received
        elif verb == "decision" and "time" in params:  # ours too: a sender's clock cannot date one ahead
            params["time"] = time.time() if received is None else received
        start = time.perf_counter()
        try:
            with self._store_lock:
                if host is not None:
                    check_owner(self.store, verb, params, host=host, manager_host=self.settings.manager_host)
                # checks names, types and bounds, naming them; each verb writes where its part is kept
                runtime.run_write(self.store, verb, params)
        except UnknownHost as exc:
            self._refuse_host(exc.host, f"write {verb!r}")
            raise
        return rows_reply([], (time.perf_counter() - start) * 1000, f"write verb {verb!r}")

    # -- Zenoh: requests through rpc.Server, events queued ---------------------------

    def _handler(self, kind: str) -> rpc.Handler:
        return lambda request: self._serve(kind, request)

    def _serve(self, kind: str, request: rpc.Request) -> rpc.Reply:
        """The reply to one request (on a server's worker); a KgadaptError is answered with its text."""
        if kind in ("query", "cypher"):
            return self._answer(kind, request)
        with self.own_first.serving():  # the robot's own: other robots' questions wait meanwhile
            return self._answer(kind, request)

    def _answer(self, kind: str, request: rpc.Request) -> rpc.Reply:
        robot = self.settings.robot
        key, payload = request.key, request.payload
        if kind in ("query", "own"):
            name = keys.last_chunk(key)
            params = {k: v for k, v in request.parameters.items() if not k.startswith("_")}
            body = self.answer_named(name, payload, params, public=kind == "query")
            reply_key = (keys.knowledge_query if kind == "query" else keys.knowledge_own_query)(robot, name)
        elif kind == "cypher":
            body = self.answer_cypher(payload)
            reply_key = keys.knowledge_cypher(robot)
        elif kind == "stats":
            body = rows_reply([self.stats()], 0.0, "service stats")
            reply_key = keys.knowledge_own_stats(robot)
        else:
            verb = keys.last_chunk(key)
            if key.split("/")[-3] == "write":  # write/<host>/<verb>: a host's own
                host = _host_of(key)
                body = self.answer_write(verb, payload, host=host, received=request.received)
                reply_key = keys.knowledge_host_write(robot, host, verb)
            else:
                body = self.answer_write(verb, payload, received=request.received)
                reply_key = keys.knowledge_write(robot, verb)
        return rpc.Reply(key=reply_key, payload=body)

    def _on_alive(self, sample: Any) -> None:
        online = sample.kind == zenoh.SampleKind.PUT
        with self._take_lock:  # the statuses received before the change go first
            for event in self._received_statuses():
                self._enqueue_event(event)
            self._enqueue_event(("alive", str(sample.key_expr), online, time.time()))

    def _forget_status_sub(self) -> None:
        with self._take_lock:
            self._status_sub = None

    def _received_statuses(self, limit: int | None = None) -> list[tuple[Any, ...]]:
        """The statuses waiting in Zenoh's ring, oldest first, at most ``limit``, stamped now (caller holds
        _take_lock)."""
        sub = self._status_sub
        if sub is None:
            return []
        now = time.time()
        events: list[tuple[Any, ...]] = []
        try:
            while (limit is None or len(events) < limit) and (sample := sub.try_recv()) is not None:
                events.append(("status", str(sample.key_expr), sample.payload.to_bytes(), now))
        except zenoh.ZError:  # undeclared at shutdown: nothing more comes
            pass
        return events

    def _take_events(self, first: Any) -> list[Any]:
        """``first`` (None: nothing), then the queued events and the statuses received since, in order of
        arrival, at most ``status_batch_max`` (the rest wait in order for the next batch)."""
        batch = [] if first is None else [first]
        with self._take_lock:
            while not self._events.empty():  # this thread alone takes from the queue
                batch.append(self._events.get_nowait())
            batch.extend(self._received_statuses(max(0, self.settings.status_batch_max - len(batch))))
        return batch

    def _enqueue_event(self, event: tuple[Any, ...]) -> None:
        """Queue ``event`` for the status worker, or drop it when max_pending_statuses wait (caller holds
        _take_lock)."""
        if self._events.qsize() >= self.settings.max_pending_statuses:
            self._drop(f"{event[0]} on {event[1]}: {self.settings.max_pending_statuses} events pending")
            return
        self._events.put(event)

    # -- the status worker -------------------------------------------------------------

    def _stop_event_worker(self) -> None:
        self._events.put(_STOP)  # beyond the bound: the worker ends after what waits before it
        if self._event_thread is not None:
            self._event_thread.join(timeout=10)
            self._event_thread = None

    def _event_loop(self) -> None:
        # Statuses gather in Zenoh's ring for status_batch_s, to be written together in one store call;
        # a liveliness change (queued by its callback) wakes the worker at once and is never delayed.
        # When no status has come for _QUIET_TAKES takes (no host publishes: hosts send at 2 Hz), the ring
        # is taken every _QUIET_TAKE_S until a status or a liveliness change comes (a hundred quiet services
        # taking it every 0.25 s cost about 3 % of a core).
        due = _next_tick(time.monotonic(), self.settings.status_batch_s)
        empty_takes = 0
        while True:
            try:
                first = self._events.get(timeout=max(0.0, min(due, self._event_due()) - time.monotonic()))
            except queue.Empty:
                first = None
            now = time.monotonic()
            if first is None and now < due:  # a liveliness retry or a refresh, not yet the statuses' turn
                self._act_on_time()
                continue
            try:
                batch = self._take_events(first)
            except Exception:  # the worker must outlive a failed take too
                log.exception("status worker: could not take the waiting statuses")
                batch = [] if first is None else [first]
            empty_takes = 0 if batch else empty_takes + 1
            if now >= due:
                quiet = empty_takes >= _QUIET_TAKES
                due = _next_tick(now, max(self.settings.status_batch_s, _QUIET_TAKE_S) if quiet
                                 else self.settings.status_batch_s)
            elif first is not None:  # a liveliness change: its host's statuses follow
                due = min(due, _next_tick(now, self.settings.status_batch_s))
            stop = _STOP in batch
            if stop:
                batch = batch[:batch.index(_STOP)]
            try:
                if batch:
                    self._apply_events(batch)
                else:
                    self._act_on_time()
            except Exception:  # the worker must outlive one bad batch
                log.exception("status worker: unexpected failure")
            if stop:
                return

    def _event_due(self) -> float:
        """When the status worker must act without an event: a liveliness retry or waiting statuses due."""
        dues = [float("inf")]
        if self._liveliness_due:
            dues.append(self._retry_at)
        if self._waiting:
            dues.append(self._refresh_at)
        return min(dues)

    def _act_on_time(self) -> None:
        """Without new events: retry the liveliness changes the store refused, write the waiting statuses, when due."""
        if self._liveliness_due and time.monotonic() >= self._retry_at:
            self._apply_liveliness()
        self._refresh_waiting()

    def _apply_events(self, batch: list[tuple[Any, ...]]) -> None:
        statuses: dict[str, tuple[messages.HostStatus, float]] = {}
        decoded: list[tuple[str, str, str, Any, float]] = []
        for kind, key, value, received in batch:
            try:
                host = _host_of(key)
                if not self._admit_host(host, kind):
                    continue
                decoded.append((kind, key, host, self._check_status(host, value) if kind == "status" else value,
                                received))
            except KgadaptError as exc:
                self._drop(f"{kind} on {key}: {exc}")
        # What the open profiles of the hosts whose statuses are written now hold, read in one store call;
        # a status within the deadband is checked against the figure last read (at most status_refresh_s old)
        # and checked again, against a fresh one, before it is written.
        due = {host for kind, _, host, body, _ in decoded if kind == "status" and self._changed(host, body)}
        self._held.update(self._held_by_processes(sorted(due)))
        for kind, key, host, value, received in decoded:
            try:
                if kind == "status":
                    body = self._trust.admit(host, value, received=received, used_mb=self._held.get(host, 0.0))
                    if host in due:
                        statuses[host] = (body, received)
                        self._waiting.pop(host, None)
                    else:
                        if not self._waiting:
                            self._refresh_at = time.monotonic() + self.settings.status_refresh_s
                        self._waiting[host] = (body, received)
                else:
                    # A new life's first status is written at once; a lost one's waiting status never, but the
                    # loss records when it was heard (last_seen).
                    unwritten = [pending[1] for pending in (statuses.pop(host, None), self._waiting.pop(host, None))
                                 if pending is not None]
                    heard = max(unwritten) if unwritten and not value else None
                    # Every change, in order: a loss and a return in one batch still end the lost life's profiles.
                    self._liveliness_due.setdefault(host, []).append((value, received, heard))
                    self._trust.alive(host, value)
                    self._written.pop(host, None)
            except KgadaptError as exc:
                self._drop(f"{kind} on {key}: {exc}")
        self._count("events_received", len(batch))
        self._apply_liveliness()
        if statuses:
            self._apply_statuses(statuses)
        self._refresh_waiting()

    def _changed(self, host: str, body: messages.HostStatus) -> bool:
        """Whether ``body`` differs from what the graph holds of ``host`` by more than the deadband."""
        s, last = self.settings, self._written.get(host)
        if last is None or body.cpu_cores != last.cpu_cores:
            return True
        return (abs(float(body.memory_free_mb) - float(last.memory_free_mb)) > s.status_deadband_mb
                or abs(float(body.memory_total_mb) - float(last.memory_total_mb)) > s.status_deadband_mb
                or abs(float(body.cpu_load) - float(last.cpu_load)) > s.status_deadband_load)

    def _refresh_waiting(self) -> None:
        """Write every waiting status together once status_refresh_s has passed since the first waited,
        each checked again against its host's profiles read now."""
        if not self._waiting or time.monotonic() < self._refresh_at:
            return
        waiting, self._waiting = self._waiting, {}
        self._held.update(self._held_by_processes(sorted(waiting)))
        statuses: dict[str, tuple[messages.HostStatus, float]] = {}
        for host, (body, received) in waiting.items():
            try:
                self._trust.check_held(host, body, used_mb=self._held.get(host, 0.0))
                statuses[host] = (body, received)
            except KgadaptError as exc:
                self._drop(f"status on {host}: {exc}")
        if statuses:
            self._apply_statuses(statuses)

    def _apply_statuses(self, statuses: Mapping[str, tuple[messages.HostStatus, float]]) -> None:
        """The newest status of each host, all written in one store call."""
        figures = [{"name": host, "time": received, "memory_total_mb": float(body.memory_total_mb),
                    "memory_free_mb": float(body.memory_free_mb), "cpu_load": float(body.cpu_load),
                    "cpu_cores": body.cpu_cores}
                   for host, (body, received) in statuses.items()]
        try:
            with self._store_lock:
                refused = runtime.update_platforms(self.store, figures)
        except KgadaptError as exc:
            for host in statuses:
                self._drop(f"status of host {host}: store refused it: {exc}")
            return
        for host, (body, _) in statuses.items():
            if host not in refused:
                self._written[host] = body
        for host, why in refused.items():
            if isinstance(why, UnknownHost):
                self._refuse_host(host, "status")
            else:
                self._drop(f"status of host {host}: store refused it: {why}")
        self._count("status_writes")
        self._count("status_applied", len(statuses) - len(refused))

    def _apply_liveliness(self) -> None:
        """Write the hosts' liveliness changes, oldest first; what the store refuses waits for the next try."""
        for host in list(self._liveliness_due):
            due = self._liveliness_due[host]
            while due:
                online, received, heard = due[0]
                try:
                    with self._store_lock:
                        runtime.set_platform_liveliness(self.store, name=host, online=online, time=received, heard=heard)
                        if not online:
                            # Its processes are beyond reach: the profiles they opened before the loss end
                            # with the token. One that outlived a partition reopens with its next sample.
                            runtime.close_host_profiles(self.store, name=host, time=received)
                except UnknownHost:
                    self._refuse_host(host, "alive")
                    due.clear()
                    break
                except KgadaptError as exc:
                    self._count("liveliness_retried")
                    self._retry_at = time.monotonic() + self.settings.liveliness_retry_s
                    log.warning("liveliness of host %s (%s): the store refused it, trying again: %s",
                                host, "online" if online else "offline", exc)
                    break
                due.pop(0)
                self._count("liveliness_applied")
                if not online:
                    self._count("profile closing_applied")
                log.info("host %s is %s", host, "online" if online else "offline")
            if len(due) > _MAX_LIVELINESS_DUE:
                # A token flapping while the store is away: the newest loss ends every profile the
                # earlier ones would have, and the newest change says where the host is now.
                losses = [change for change in due if not change[0]]
                due[:] = sorted(set(losses[-1:] + due[-1:]), key=lambda change: change[1])
            if not due:
                del self._liveliness_due[host]

    def _admit_host(self, host: str, what: str) -> bool:
        """Whether a Platform of the models is named ``host`` (status worker); a refusal is counted."""
        if host in self._known_hosts:
            return True
        now = time.monotonic()
        checked = self._unknown_checked.get(host)
        if checked is None or now - checked >= _UNKNOWN_RECHECK_S:
            try:
                with self._store_lock:
                    known = runtime.is_known_host(self.store, host)
            except KgadaptError:
                return True  # the store is away: its writer refuses an unknown host itself
            if known:
                self._known_hosts.add(host)
                self._unknown_checked.pop(host, None)
                return True
            if len(self._unknown_checked) >= _MAX_REFUSED_HOSTS:
                self._unknown_checked.pop(next(iter(self._unknown_checked)))
            self._unknown_checked[host] = now
        self._refuse_host(host, what)
        return False

    def _refuse_host(self, host: str, what: str) -> None:
        """Count a refusal of a host no model names; log it the first time that host is refused."""
        with self._stats_lock:
            self._stats["unknown_host_refused"] += 1
            first = host not in self._refused_hosts and len(self._refused_hosts) < _MAX_REFUSED_HOSTS
            if first:
                self._refused_hosts.append(host)
        if first:
            log.warning("refused host %r (%s): no Platform of the models names it, and only the models add hosts; "
                        "further refusals of it are counted, not logged", host, what)

    def _check_status(self, host: str, payload: bytes) -> messages.HostStatus:
        return check_status(host, messages.decode_as(payload, messages.HostStatus))

    def _held_by_processes(self, hosts: list[str]) -> dict[str, float]:
        if not hosts:
            return {}
        try:
            with self._store_lock:
                return runtime.held_by_processes_of(self.store, hosts)
        except KgadaptError as exc:  # e.g. the store restarting: the statuses are still applied
            log.debug("no profile figures for %s: %s", ", ".join(hosts), exc)
            return {}

    def _mark_all_offline(self) -> None:
        now = time.time()
        with self._store_lock:
            # A graph never written to has no rows (every backend answers such a read with none).
            for row in queries.run_named(self.store, "platforms", {}):
                if row.get("online"):
                    runtime.set_platform_online(self.store, name=row["platform"], online=False, time=now)

    # -- bookkeeping --------------------------------------------------------

    def _count(self, what: str, n: int = 1) -> None:
        if n:
            with self._stats_lock:
                self._stats[what] += n

    def _drop(self, reason: str) -> None:
        with self._stats_lock:
            self._stats["events_dropped"] += 1
            self._last_drop = reason
        self._drop_log.warning("dropped %s", reason)


# -- ownership of writes ----------------------------------------------------

# The parameter naming the host a write is about, for the verbs a host writes about itself.
_HOST_PARAM = {"platform": "name", "platform_online": "name", "process_start": "host"}
_RUN_VERBS = ("process_sample", "process_end", "process_reconfigured")  # about a profile, by run_id
_MANAGER_VERBS = ("decision", "flight_state", "live_rate")  # the adaptation manager's and the flight bridge's


def check_owner(store: GraphStore, verb: str, params: Mapping[str, Any], *, host: str, manager_host: str) -> None:
    """Refuse (NamedQueryError naming the parameter) a write on ``write/<host>/<verb>`` about anything
    ``host`` does not own. A process profile belongs to the host its ``process_start`` named."""
    where = f"write {verb!r} from host {host!r}"
    if verb in _HOST_PARAM:
        named = params.get(_HOST_PARAM[verb])
        if named != host:
            raise NamedQueryError(f"{where}: parameter {_HOST_PARAM[verb]!r} is {named!r}; "
                                  f"a host writes only about itself")
    if verb in _RUN_VERBS or verb == "process_start":
        run_id = params.get("run_id")
        if not isinstance(run_id, str):
            return  # the writer names the missing or ill-typed parameter
        rows = store.execute(f"MATCH (r:{S.PROCESS_PROFILE} {{name: $run_id}}) RETURN r.host AS host LIMIT 1",
                             {"run_id": run_id})
        owner = rows[0]["host"] if rows else None
        if verb == "process_start":
            if rows and owner != host:
                raise NamedQueryError(f"{where}: parameter 'run_id' {run_id!r} is a process of host {owner!r}")
        elif owner != host:
            raise NamedQueryError(f"{where}: parameter 'run_id' {run_id!r} is "
                                  + ("no process this host started" if not rows
                                     else f"a process of host {owner!r}"))
        return
    if verb in _MANAGER_VERBS:
        if host != manager_host:
            raise NamedQueryError(f"{where}: only the adaptation manager's host {manager_host!r} writes {verb!r}")
        return
    if verb not in _HOST_PARAM:
        raise NamedQueryError(f"{where}: {verb!r} is no host's to write (operators write it on "
                              f"knowledge/write/{verb})")


# -- helpers ----------------------------------------------------------------


def rows_reply(rows: list[dict[str, Any]], elapsed_ms: float, what: str) -> bytes:
    """The encoded ``rows`` reply; MessageError naming ``what`` if a value cannot be sent."""
    try:
        return messages.encode(messages.Rows(rows=rows, elapsed_ms=round(elapsed_ms, 4)))
    except MessageError as exc:
        raise MessageError(f"{what}: the answer cannot be sent: {exc}") from exc
    except (TypeError, ValueError, OverflowError) as exc:  # msgpack cannot pack a store value
        raise MessageError(f"{what}: the answer holds a value that cannot be sent: {exc}") from exc


def _host_or_none(key: str) -> str | None:
    try:
        return _host_of(key)
    except MessageError:
        return None  # refused, naming it, when the status itself is read


def _host_of(key: str) -> str:
    try:
        return keys.check_name(keys.last_chunk(key, 2), "host name")
    except ConfigError as exc:
        raise MessageError(str(exc)) from exc


def _store_lock(store: GraphStore) -> Any:
    """Every backend is safe to call from several threads (FalkorDB's client has a connection
    pool; the Bolt backend serializes its one session itself), so no lock of ours is needed."""
    return contextlib.nullcontext()


def asker_of(item: Any) -> str:
    """Who asked a queued question: its attachment (at most 64 bytes), else "anonymous".

    Zenoh tells a queryable nothing of the asker (the router knows its certificate, the queryable
    does not), so an asker is what it says it is: the per-asker bound keeps one asker's flood from
    another's share, and the whole queue's bound holds against one that names itself anew each time."""
    try:
        attachment = item.query.attachment
    except AttributeError:
        return ""
    if attachment is None:
        return "anonymous"
    return "asker:" + attachment.to_bytes()[:64].decode("utf-8", "replace")


class OwnFirst:
    """The robot's own requests first: other robots' questions wait while one is being answered.

    Python runs one thread at a time: a public worker parsing a 1,000-row answer from its sandbox
    (tens of ms) makes the robot's own request wait for the interpreter at every step. The public
    workers therefore wait at their steps (before a question runs, before its answer is encoded)
    until no own request is being answered, at most ``max_wait_s`` each time, so a steady stream
    of the robot's own requests slows other robots' answers but never stops them.
    """

    def __init__(self, *, max_wait_s: float) -> None:
        self.max_wait_s = max_wait_s
        self._serving = 0
        self._waiting = 0
        self._idle = threading.Condition()
        self._mine = threading.local()  # set on a thread answering an own request: it never waits

    @contextlib.contextmanager
    def serving(self) -> Any:
        with self._idle:
            self._serving += 1
        self._mine.own = True
        try:
            yield
        finally:
            self._mine.own = False
            with self._idle:
                self._serving -= 1
                if not self._serving:
                    self._idle.notify_all()

    @property
    def waiting(self) -> int:
        """Public steps waiting for their turn now."""
        with self._idle:
            return self._waiting

    def wait_turn(self) -> None:
        if self.max_wait_s > 0 and not getattr(self._mine, "own", False):
            with self._idle:
                self._waiting += 1
                try:
                    self._idle.wait_for(lambda: not self._serving, timeout=self.max_wait_s)
                finally:
                    self._waiting -= 1


class _RateLimitedLog:
    """At most ``per_second`` warnings a second; the rest are counted and summarized."""

    def __init__(self, logger: logging.Logger, *, per_second: int) -> None:
        self.logger = logger
        self.per_second = per_second
        self._window = 0.0
        self._count = 0
        self._suppressed = 0
        self._lock = threading.Lock()

    def warning(self, fmt: str, *args: Any) -> None:
        with self._lock:
            now = time.monotonic()
            if now - self._window >= 1.0:
                if self._suppressed:
                    self.logger.warning("(%d similar messages suppressed)", self._suppressed)
                self._window, self._count, self._suppressed = now, 0, 0
            self._count += 1
            if self._count > self.per_second:
                self._suppressed += 1
                return
        self.logger.warning(fmt, *args)
