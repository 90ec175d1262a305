"""Request/reply over Zenoh: one way to ask, one way to answer, one way to let go.

Asking::

    rows = call(session, key, messages.encode(QueryRequest(params=params)), decode_rows, timeout=2.0)
    details = gather(session, key, payload, decode, timeout=5.0)   # every queryable that matches
    pending = ask(session, key, payload, timeout=2.0, every_reply=True)   # replies as they come
    for reply in pending.replies(): ...

:func:`call` returns the first reply decoded, :func:`gather` every reply once
all matching queryables have finished. Errors are typed, never ``None`` and
never a text to compare: :class:`~kgadapt.shared.errors.RemoteError` carries the far
side's ``reply_err`` text, :class:`~kgadapt.shared.errors.NoResponder` says nobody
serves the key (the query ended without a reply),
:class:`~kgadapt.shared.errors.RequestTimeout` that the deadline passed; Zenoh's own
failures (closed session, bad key) become :class:`~kgadapt.shared.errors.TransportError`.
Zenoh's own query timeout is ``timeout + GRACE``: anything arriving after our
deadline, Zenoh's "Timeout" error reply included, counts as no reply, judged
by the clock. ``resend_for``: a query that ends at once without a reply
reached nobody (a session opened a moment ago may not know the queryables
yet), so it is sent again for up to that many seconds.

Answering::

    server = Server("knowledge service", workers=2, max_pending=1000)
    server.setup()
    server.serve(session, key, handler, what="query")     # handler(Request) -> Reply
    ...
    server.shutdown()

The Zenoh callback only queues the query (a full queue is answered "busy" at
once); ``workers`` threads call the handler. Whatever happens, the query gets
exactly one answer and is then dropped (which ends the asker's ``get``): the
handler's :class:`Reply`, or ``reply_err`` with the text of the
:class:`~kgadapt.shared.errors.KgadaptError` it raised (a refusal, naming what is
wrong), or ``reply_err("internal error ...")`` for any other exception (a
bug: logged, and the server keeps serving). Queries still queued at
shutdown are answered "<name> is shutting down".

Declarations: a part keeps its publishers, subscribers, tokens and servers
on one :class:`contextlib.ExitStack`; :func:`declared` puts a Zenoh entity
on it so that closing the stack undeclares it, quietly (the session may be
closed already).
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, NamedTuple, Protocol, TypeVar, cast

import zenoh

from kgadapt.shared.errors import ConfigError, KgadaptError, NoResponder, RemoteError, RequestTimeout, TransportError

log = logging.getLogger(__name__)

T = TypeVar("T")

# Zenoh's own query timeout is ours plus this, so that its end (and its "Timeout" error reply) comes after
# our deadline: a reply is judged late by the clock, never by its text.
GRACE = 0.05
RESEND_PAUSE = 0.05  # between sends of a query that reached nobody (at most)
# The first pause: a session opened a moment ago learns the queryables within a few ms (a query sent
# at once reached nobody, one sent 2 ms after the open was answered: measured with the knowledge service
# over a local router), so the pauses start short and double up to RESEND_PAUSE.
FIRST_RESEND_PAUSE = 0.002


def resend_pauses() -> Iterator[float]:
    """The pauses between sends of a query that reached nobody: short first, then RESEND_PAUSE."""
    pause = FIRST_RESEND_PAUSE
    while True:
        yield pause
        pause = min(pause * 2, RESEND_PAUSE)


class _Undeclarable(Protocol):
    def undeclare(self) -> Any: ...


E = TypeVar("E", bound=_Undeclarable)


def undeclare_quietly(entity: _Undeclarable) -> None:
    """Undeclare ``entity``; a failure (the session closed first) is only logged."""
    try:
        entity.undeclare()
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError and friends: nothing left to undeclare
        log.debug("undeclare %s: %s", type(entity).__name__, exc)


def declared(stack: contextlib.ExitStack, entity: E) -> E:
    """``entity``, to be undeclared quietly when ``stack`` closes."""
    stack.callback(undeclare_quietly, entity)
    return entity


class Request(NamedTuple):  # a NamedTuple, not a dataclass: one is made per query, in a few hundred ns
    """What a handler sees of a query (never the Zenoh query itself: replying is the server's)."""

    key: str  # the query's key expression (it may hold wildcards)
    payload: bytes | None
    parameters: dict[str, str]  # the selector's ``?name=value;...``
    received: float  # time.time() when the query arrived


class Reply(NamedTuple):
    """``payload`` on ``key``: a handler's answer (``key`` concrete, matching the query's), or one received."""

    key: str
    payload: bytes


# -- asking -----------------------------------------------------------------------


class Pending:
    """The replies of one query, as they arrive, until every queryable reached is done or the deadline passes."""

    def __init__(self, key: str, timeout: float, deadline: float, replies: zenoh.Handler[zenoh.Reply]) -> None:
        self.key = key
        self.timeout = timeout
        self.deadline = deadline  # time.monotonic() past which a reply is late
        self.finished = False  # Zenoh ended the query before the deadline: every queryable it reached is done
        self._replies = replies

    def replies(self) -> Iterator[Reply | RemoteError]:
        """Each reply: a :class:`Reply`, or a :class:`RemoteError` (not raised) for an error reply.

        Ends when Zenoh ends the query (``finished``) or with the first reply
        that comes after the deadline (which may be Zenoh's own "Timeout"
        error reply: it is never handed out).
        """
        if self.finished:
            return
        for item in self._replies:  # Zenoh's channel: no thread hop, unlike a callback
            if time.monotonic() > self.deadline:
                return
            if item.ok is not None:
                yield Reply(key=str(item.ok.key_expr), payload=item.ok.payload.to_bytes())
            elif item.err is not None:
                yield RemoteError(item.err.payload.to_bytes().decode("utf-8", "replace"))
        self.finished = time.monotonic() <= self.deadline


def ask(session: zenoh.Session, key: str, payload: bytes, *, timeout: float, every_reply: bool = False,
        attachment: bytes | None = None) -> Pending:
    """Send one query on ``key`` and return at once; read its replies from the :class:`Pending`.

    ``every_reply``: no consolidation (each queryable's reply, as soon as it
    comes, even two on one key); else Zenoh's default. ``attachment``: sent
    with the query (the knowledge service names the asker by it).
    """
    if not timeout > 0:
        raise TransportError(f"query on {key}: timeout {timeout!r} s must be more than 0")
    options: dict[str, Any] = {"consolidation": zenoh.ConsolidationMode.NONE} if every_reply else {}
    if attachment is not None:
        options["attachment"] = attachment
    deadline = time.monotonic() + timeout  # before Zenoh's timer starts
    try:
        # Zenoh's timeout a little after ours: what it sends when it expires comes after our deadline.
        handler = session.get(key, payload=payload, timeout=timeout + GRACE, **options)
    except zenoh.ZError as exc:
        raise TransportError(f"query on {key}: {exc}") from exc
    return Pending(key, timeout, deadline, handler)


def _exchange(session: zenoh.Session, key: str, payload: bytes, *, timeout: float, resend_for: float,
              first_only: bool, attachment: bytes | None = None) -> list[Reply | RemoteError]:
    """The replies to one request: the first (``first_only``) or all; NoResponder or RequestTimeout else."""
    if not timeout > 0:
        raise TransportError(f"query on {key}: timeout {timeout!r} s must be more than 0")
    start = time.monotonic()
    deadline = start + timeout
    pauses = resend_pauses()
    while True:
        pending = ask(session, key, payload, timeout=max(0.001, deadline - time.monotonic()), attachment=attachment)
        got: list[Reply | RemoteError] = []
        for reply in pending.replies():
            got.append(reply)
            if first_only:
                return got
        if not pending.finished:
            raise RequestTimeout(f"no reply on {key} within {timeout:g} s")
        if got:
            return got
        # Ended without a reply: nobody received the request, so sending it again is safe.
        pause = next(pauses)
        if time.monotonic() + pause >= min(deadline, start + resend_for):
            raise NoResponder(f"nobody answers on {key}")
        time.sleep(pause)


def _decoded(reply: Reply | RemoteError, decode: Callable[[bytes], T]) -> T:
    if isinstance(reply, RemoteError):
        raise reply
    return decode(reply.payload)


def call(session: zenoh.Session, key: str, payload: bytes, decode: Callable[[bytes], T], *, timeout: float,
         resend_for: float = 0.0, attachment: bytes | None = None) -> T:
    """The first reply to ``payload`` on ``key``, decoded.

    RemoteError (its text is the far side's), NoResponder, RequestTimeout,
    TransportError; whatever ``decode`` raises passes through.
    """
    return _decoded(_exchange(session, key, payload, timeout=timeout, resend_for=resend_for, first_only=True,
                              attachment=attachment)[0], decode)


def gather(session: zenoh.Session, key: str, payload: bytes, decode: Callable[[bytes], T], *, timeout: float,
           resend_for: float = 0.0) -> list[T]:
    """Every reply to ``payload`` on ``key`` (a key with wildcards reaches several queryables), decoded.

    Waits until every queryable reached has answered; RequestTimeout if one
    has not by ``timeout``, RemoteError if one answered with an error.
    NoResponder when nobody serves ``key``.
    """
    got = _exchange(session, key, payload, timeout=timeout, resend_for=resend_for, first_only=False)
    return [_decoded(reply, decode) for reply in got]


# -- answering --------------------------------------------------------------------


Handler = Callable[[Request], Reply]

_STOP = object()


@dataclass(frozen=True)
class _Queued:
    query: zenoh.Query
    handler: Handler
    what: str
    received: float


class Server:
    """Queryables answered by a pool of ``workers`` threads (see the module's docstring).

    ``name`` names the server in "busy" and "shutting down" replies and logs;
    ``prefix`` starts every error reply (e.g. ``"deployer onboard: "``).
    """

    def __init__(self, name: str, *, workers: int = 1, max_pending: int = 64, prefix: str = "",
                 pending: Any = None) -> None:
        """``pending``: the queue of waiting queries, if not a FIFO of ``max_pending`` (e.g. a
        :class:`~kgadapt.shared.fair_queue.FairQueue`): ``put_nowait`` (``queue.Full``), ``put``, ``get``,
        ``get_nowait`` (``queue.Empty``), ``qsize``; its items have the Zenoh query as ``query``."""
        if workers < 1 or max_pending < 1:
            raise ConfigError(f"{name}: workers {workers!r} and max_pending {max_pending!r} must be at least 1")
        self.name = name
        self.workers = workers
        self.prefix = prefix
        self._pending: queue.Queue[Any] = queue.Queue(maxsize=max_pending) if pending is None else pending
        self._threads: list[threading.Thread] = []
        self._queryables: list[zenoh.Queryable[None]] = []
        self._closing = threading.Event()
        self._stats_lock = threading.Lock()
        self._stats = {"answered": 0, "refused": 0, "failed": 0, "shed": 0}
        self._shed_logged = 0.0
        self._busy = 0

    # -- life cycle ---------------------------------------------------------------

    def setup(self) -> None:
        """Start the workers."""
        self._closing.clear()
        for i in range(self.workers):
            thread = threading.Thread(target=self._work, name=f"{self.name}-{i}".replace(" ", "-"), daemon=True)
            thread.start()
            self._threads.append(thread)

    def serve(self, session: zenoh.Session, key: str, handler: Handler, *, what: str = "") -> None:
        """Declare a queryable on ``key`` whose queries ``handler`` answers. ``what`` names them in messages."""
        label = what or key

        def on_query(query: zenoh.Query) -> None:
            # Zenoh callback: queue and return, nothing else.
            self._enqueue(_Queued(query, handler, label, time.time()))

        try:
            self._queryables.append(session.declare_queryable(key, on_query))
        except zenoh.ZError as exc:
            raise TransportError(f"{self.name}: cannot declare the queryable {key}: {exc}") from exc

    def undeclare(self) -> None:
        """Stop taking queries (those queued are still answered)."""
        while self._queryables:
            undeclare_quietly(self._queryables.pop())

    def shutdown(self) -> None:
        """Undeclare, answer what is still queued "shutting down", let the workers finish the queries they hold."""
        self.undeclare()
        self._closing.set()
        self._refuse_pending()
        for _ in self._threads:
            try:
                self._pending.put(_STOP, timeout=5)
            except queue.Full:
                log.warning("%s: worker queue stayed full at shutdown", self.name)
        for thread in self._threads:
            thread.join(timeout=30)
            if thread.is_alive():
                log.warning("%s: worker %s still busy at shutdown", self.name, thread.name)
        self._threads.clear()
        self._refuse_pending()  # anything queued between the first drain and the stop

    def __enter__(self) -> "Server":
        self.setup()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def pending(self) -> int:
        """Queries queued, not yet taken by a worker."""
        return self._pending.qsize()

    def busy(self) -> int:
        """Workers answering a query now."""
        with self._stats_lock:
            return self._busy

    def stats(self) -> dict[str, int]:
        """Queries ``answered``, ``refused`` (a KgadaptError), ``failed`` (a bug), ``shed`` (queue full)."""
        with self._stats_lock:
            return dict(self._stats)

    # -- internals ----------------------------------------------------------------

    def _count(self, what: str) -> None:
        with self._stats_lock:
            self._stats[what] += 1

    def _enqueue(self, item: _Queued) -> None:
        if self._closing.is_set():
            _finish(item.query, error=f"{self.name} is shutting down")
            return
        try:
            self._pending.put_nowait(item)
        except queue.Full:
            # Refused at once, so the asker need not wait out its timeout.
            self._count("shed")
            now = time.monotonic()
            if now - self._shed_logged >= 1.0:  # at most one warning a second in a flood
                self._shed_logged = now
                log.warning("%s: %s request shed: its queue is full", self.name, item.what)
            _finish(item.query, error=f"{self.name} busy: too many {item.what} requests pending; ask again later")

    def _refuse_pending(self) -> None:
        while True:
            try:
                item = self._pending.get_nowait()
            except queue.Empty:
                return
            if item is not _STOP:
                _finish(item.query, error=f"{self.name} is shutting down")

    def _work(self) -> None:
        while True:
            item = self._pending.get()
            if item is _STOP:
                return
            with self._stats_lock:
                self._busy += 1
            try:
                self._answer(item)
            finally:
                with self._stats_lock:
                    self._busy -= 1

    def _answer(self, item: _Queued) -> None:
        query = item.query
        try:
            request = Request(key=str(query.key_expr), payload=None if query.payload is None else query.payload.to_bytes(),
                              parameters=_parameters(query), received=item.received)
            reply = item.handler(request)
        except KgadaptError as exc:
            self._count("refused")
            log.info("%s: %s request on %s refused: %s", self.name, item.what, query.key_expr, exc)
            _finish(query, error=f"{self.prefix}{exc}")
            return
        except Exception as exc:  # a bug: answer it, log it, keep serving
            self._count("failed")
            log.exception("%s: %s request on %s failed", self.name, item.what, query.key_expr)
            _finish(query, error=f"{self.prefix}internal error answering {item.what} request: "
                                 f"{type(exc).__name__}: {exc}")
            return
        self._count("answered")
        _finish(query, reply=reply)


def serve(session: zenoh.Session, key: str, handler: Handler, *, name: str, workers: int = 1,
          max_pending: int = 64, prefix: str = "") -> Server:
    """A started :class:`Server` answering ``key`` alone (``shutdown()`` it, or use it as a context manager)."""
    server = Server(name, workers=workers, max_pending=max_pending, prefix=prefix)
    server.setup()
    try:
        server.serve(session, key, handler)
    except BaseException:
        server.shutdown()
        raise
    return server


def _parameters(query: zenoh.Query) -> dict[str, str]:
    try:
        parameters = query.parameters
        if parameters.is_empty():  # the common case, and much cheaper than iterating
            return {}
        # zenoh's stub says __iter__ returns a list; it is an iterator of (name, value) pairs.
        pairs = cast(Iterable[tuple[str, str]], parameters)
        return {str(k): str(v) for k, v in pairs}
    except Exception:  # noqa: BLE001 - a selector Zenoh cannot split: no parameters
        return {}


def _finish(query: zenoh.Query, *, reply: Reply | None = None, error: str | None = None) -> None:
    """Reply (or reply_err), then drop the query so the asker's get completes. The one place that does."""
    try:
        if reply is not None:
            query.reply(reply.key, reply.payload)
        else:
            query.reply_err(error or "refused")
    except Exception as exc:  # noqa: BLE001 - the asker may be gone; nothing to tell it
        log.debug("reply on %s failed: %s", query.key_expr, exc)
    finally:
        try:
            query.drop()
        except Exception as exc:  # noqa: BLE001 - already dropped
            log.debug("drop: %s", exc)
