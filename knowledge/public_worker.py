"""Other robots' questions, answered in a separate process of lower priority.

The knowledge service answers the robot's own requests in its own process.
A question from outside (``query/*``, ``cypher``) is checked there (names,
parameters, the Cypher subset: cheap), then handed to a
:class:`PublicWorker`: a child process (``python -m
kgadapt.knowledge.public_worker``) at nice ``nice`` (19 by default, Linux's
lowest weight but SCHED_IDLE; it starts at the service's priority, so a
loaded machine does not hold up the service's start, and lowers every thread
of its own before the first question) that owns a
:class:`~kgadapt.knowledge.sandbox.QuerySandbox` (the copy of the graph, in
a FalkorDB server of its own) and does everything that grows with the
answer: the query, reading its rows, encoding the ``rows`` reply. The service
gets the encoded reply back through a pipe and sends it as it is.

Why a process: Python runs one thread at a time, so reading and encoding a
1,000-row answer (about 80 ms of CPU) in the service's process took the
interpreter from the robot's own requests, whatever their threads' priority.
In another process, at a lower priority, that work takes a core only when
the robot's own processes leave it.

The child touches the primary store only to copy the graph (``DUMP``, about
1 ms on the primary, when it has been written to since the last copy); it
never holds it while a question runs. Protocol on its stdin/stdout: frames of
a 4-byte big-endian length and a msgpack map: first the settings
(``{"store": {...}, "nice": n}``, answered ``{"ready": true}`` or
``{"error": ...}``), then requests ``{"cypher", "params", "limit_ms",
"what", "cacheable"}`` each answered ``{"ok": <rows reply bytes>}`` or ``{"error": kind,
"text": ...}``, one at a time, in order.

One worker holds one question at a time. If no answer has come by the
question's deadline (its time limit, the sandbox's grace, and ``slack_s``
for a child that waited for the CPU), the question is answered "not
answered in time" and the child keeps the question's answer owed: the next
question first waits for it (up to its own deadline), so a starved child
never has more than one question in hand.
"""

from __future__ import annotations

import faulthandler
import logging
import os
import select
import signal
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import IO, Any, Mapping

import msgpack

from kgadapt.knowledge.sandbox import SandboxSettings
from kgadapt.shared.errors import ConfigError, KgadaptError, MessageError, QueryError, QueryTimeLimit, StoreUnavailable
from kgadapt.shared.proc_stat import state_of

log = logging.getLogger(__name__)

_HEADER = struct.Struct(">I")
_MAX_FRAME = 64 * 1024 * 1024
_SANDBOX_GRACE_S = SandboxSettings().grace_s  # the sandbox's own wait past a limit before it kills its server
# Errors the child reports by kind; the service raises the same kind, so the asker reads the same text.
_ERRORS: dict[str, type[KgadaptError]] = {"time_limit": QueryTimeLimit, "query": QueryError,
                                          "unavailable": StoreUnavailable, "message": MessageError}


@dataclass(frozen=True, kw_only=True)
class PublicWorkerSettings:
    """How the lower-priority worker runs."""

    nice: int = 19  # added to the child's niceness (0: same priority as the service)
    start_timeout_s: float = 30.0
    slack_s: float = 2.0  # beyond a question's limit and the sandbox's grace, for a child waiting for the CPU

    def __post_init__(self) -> None:
        if not 0 <= self.nice <= 19:
            raise ConfigError(f"nice {self.nice!r}: between 0 and 19")


class _NoStart(StoreUnavailable):
    """The child ended or stayed silent before saying it was ready (not a refusal of its own)."""


class PublicWorker:
    """One child process answering read-only questions from a sandboxed copy of ``store``'s graph.

    ``__init__`` does no I/O; ``setup()`` starts the child and waits (bounded)
    for its sandbox; ``shutdown()`` stops it. Thread-safe: one question at a time.
    """

    def __init__(self, store: Any, settings: PublicWorkerSettings = PublicWorkerSettings()) -> None:
        if not store.capabilities.sandbox:
            raise ConfigError(f"store {store.url}: only FalkorDB over RESP can be copied for a public worker")
        self.store = store
        self.settings = settings
        self.restarts = 0
        self._lock = threading.Lock()
        self._child: subprocess.Popen[bytes] | None = None
        self._owed = 0  # answers the child still owes for questions given up on
        self._hello: dict[str, Any] = {}

    @property
    def pid(self) -> int | None:
        return self._child.pid if self._child is not None else None

    def setup(self) -> None:
        self.start()
        self.wait_ready()

    def start(self) -> None:
        """Start the child without waiting for it (several start side by side; then :meth:`wait_ready`)."""
        with self._lock:
            self._spawn()

    def wait_ready(self) -> None:
        """Wait (bounded) for the child's sandbox; a child that ended or stayed silent is started once more.

        A start that failed for its own reasons (the store refused the copy) is not retried. One that
        crashed or hung says so in a warning and gets one more process: the robot's own knowledge
        service should not fail its start because one helper process did.
        """
        with self._lock:
            try:
                self._await_ready()
            except _NoStart as exc:
                log.warning("public worker: %s; starting another", exc)
                self.restarts += 1
                self._start()

    def shutdown(self) -> None:
        with self._lock:
            self._stop()

    def execute(self, cypher: str, params: Mapping[str, Any], *, limit_ms: int, what: str,
                cacheable: bool = False) -> bytes:
        """The encoded ``rows`` reply to a read-only question; KgadaptError naming what went wrong.

        ``cacheable``: see :meth:`kgadapt.knowledge.sandbox.QuerySandbox.execute`.
        """
        wait_s = limit_ms / 1000 + _SANDBOX_GRACE_S + self.settings.slack_s
        with self._lock:
            if self._child is None or self._child.poll() is not None:
                self._restart("the worker process was gone")
            assert self._child is not None
            deadline = time.monotonic() + wait_s  # after a restart: the question's time is its own
            while self._owed:  # a question given up on earlier: its answer comes first
                if self._read(deadline) is None:
                    raise QueryTimeLimit(f"{what}: not answered: the worker for other robots' questions is "
                                         "still busy with an earlier one")
                self._owed -= 1
            self._write({"cypher": cypher, "params": dict(params), "limit_ms": limit_ms, "what": what,
                         "cacheable": cacheable})
            answer = self._read(deadline)
            if answer is None:
                self._owed += 1
                raise QueryTimeLimit(f"{what}: not answered within {wait_s:.1f} s "
                                     "(the worker for other robots' questions runs at a lower priority than the "
                                     "robot's own)")
        if "ok" in answer:
            return bytes(answer["ok"])
        raise _ERRORS.get(answer.get("error", ""), QueryError)(str(answer.get("text", "failed")))

    # -- internals ----------------------------------------------------------------

    def _start(self) -> None:
        self._spawn()
        self._await_ready()

    def _spawn(self) -> None:
        settings = self.store.settings
        kwargs = self.store.redis.connection_pool.connection_kwargs  # where the primary is, as connected
        store = {"graph": settings.graph, "unix_socket": kwargs.get("path"), "host": kwargs.get("host"),
                 "port": kwargs.get("port"), "username": settings.username, "password": settings.password,
                 "url": settings.url}
        child = subprocess.Popen([sys.executable, "-m", "kgadapt.knowledge.public_worker"], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, close_fds=True)
        self._child, self._owed = child, 0
        self._hello = {"store": store, "nice": self.settings.nice}

    def _await_ready(self) -> None:
        try:
            self._write(self._hello)
            ready = self._read(time.monotonic() + self.settings.start_timeout_s)
        except KgadaptError:
            ready = None
        if ready is not None and ready.get("ready"):
            return
        if ready is not None:
            self._stop()
            raise StoreUnavailable(f"the worker for other robots' questions did not start: {ready.get('text', 'refused')}")
        why = self._silence()
        self._stop()
        raise _NoStart(f"the worker for other robots' questions did not start: {why}")

    def _silence(self) -> str:
        """Why the child sent nothing: how it ended, or what state it is in after the start's wait."""
        assert self._child is not None
        try:
            code = self._child.wait(timeout=1.0)  # a child whose pipe ended is about to be reaped
        except subprocess.TimeoutExpired:
            code = None
        if code is not None:
            return (f"it was killed by signal {signal.Signals(-code).name}" if code < 0
                    else f"it ended with status {code}")
        try:
            state = state_of(self._child.pid)
        except OSError:
            state = "?"
        return (f"no answer in {self.settings.start_timeout_s:g} s from pid {self._child.pid} "
                f"(state {state}{', stopped by a signal' if state in ('T', 't') else ''})")

    def _restart(self, why: str) -> None:
        log.warning("public worker: %s; starting a new one", why)
        self.restarts += 1
        self._stop()
        self._start()

    def _stop(self) -> None:
        child, self._child = self._child, None
        if child is None:
            return
        assert child.stdin is not None and child.stdout is not None
        try:
            child.stdin.close()  # the child ends at the end of its input, stopping its sandbox
        except OSError:
            pass
        try:
            child.wait(timeout=10)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait(timeout=5)
        child.stdout.close()

    def _write(self, body: Mapping[str, Any]) -> None:
        assert self._child is not None and self._child.stdin is not None
        try:
            data = msgpack.packb(body, use_bin_type=True)
        except (TypeError, ValueError, OverflowError) as exc:
            raise MessageError(f"a question for the public worker cannot be sent: {exc}") from exc
        try:
            _send_packed(self._child.stdin, data)
        except (OSError, ValueError) as exc:
            raise StoreUnavailable(f"the worker for other robots' questions is gone: {exc}") from exc

    def _read(self, deadline: float) -> dict[str, Any] | None:
        """The child's next frame, or None if it has not come by ``deadline``."""
        assert self._child is not None and self._child.stdout is not None
        fd = self._child.stdout.fileno()
        data = b""
        need = _HEADER.size
        length: int | None = None
        while True:
            while len(data) < need:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not select.select([fd], [], [], remaining)[0]:
                    if data:  # half a frame: the stream is out of step; start afresh
                        self._restart("a reply was cut short")
                    return None
                chunk = os.read(fd, max(65536, need - len(data)))
                if not chunk:
                    raise StoreUnavailable("the worker for other robots' questions ended")
                data += chunk
            if length is None:
                (length,) = _HEADER.unpack_from(data)
                if length > _MAX_FRAME:
                    raise StoreUnavailable(f"the worker sent a frame of {length} bytes")
                need = _HEADER.size + length
                continue
            body = msgpack.unpackb(data[_HEADER.size:need], raw=False)
            assert len(data) == need, "one frame in flight at a time"
            return dict(body)


def _send(out: IO[bytes], body: Mapping[str, Any]) -> None:
    _send_packed(out, msgpack.packb(body, use_bin_type=True))


def _send_packed(out: IO[bytes], data: bytes) -> None:
    out.write(_HEADER.pack(len(data)) + data)
    out.flush()


def _receive(inp: IO[bytes]) -> dict[str, Any] | None:
    header = inp.read(_HEADER.size)
    if len(header) < _HEADER.size:
        return None
    (length,) = _HEADER.unpack(header)
    data = inp.read(length)
    if len(data) < length:
        return None
    return dict(msgpack.unpackb(data, raw=False))


# -- the child ------------------------------------------------------------------


def _answer(sandbox: Any, request: Mapping[str, Any]) -> dict[str, Any]:
    from kgadapt.knowledge.service import rows_reply

    what = str(request.get("what", "query"))
    start = time.perf_counter()
    try:
        rows = sandbox.execute(request["cypher"], request.get("params") or {}, limit_s=request["limit_ms"] / 1000,
                               cacheable=bool(request.get("cacheable")))
        return {"ok": rows_reply(rows, (time.perf_counter() - start) * 1000, what)}
    except QueryTimeLimit as exc:
        return {"error": "time_limit", "text": f"{what}: {exc}"}
    except StoreUnavailable as exc:
        return {"error": "unavailable", "text": f"{what}: {exc}"}
    except MessageError as exc:
        return {"error": "message", "text": str(exc)}
    except KgadaptError as exc:
        return {"error": "query", "text": f"{what}: {exc}"}


def _lower_priority(nice: int) -> None:
    for tid in os.listdir("/proc/self/task"):
        try:
            current = os.getpriority(os.PRIO_PROCESS, int(tid))
            os.setpriority(os.PRIO_PROCESS, int(tid), min(19, current + nice))
        except OSError as exc:
            log.debug("cannot lower the priority of public worker thread %s: %s", tid, exc)


def main() -> int:
    faulthandler.enable()  # a crash in a C extension says where on stderr instead of ending silently
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing but frames on the pipe
    first = _receive(inp)
    if first is None:
        return 1
    from kgadapt.knowledge.falkordb_store import FalkorDBStore
    from kgadapt.knowledge.sandbox import QuerySandbox
    from kgadapt.knowledge.service import rows_reply  # noqa: F401 (imported now, not at the first question)
    from kgadapt.knowledge.store import StoreSettings

    where = first["store"]
    source = FalkorDBStore(StoreSettings(kind="falkordb", url=where["url"], unix_socket=where["unix_socket"],
                                         host=where["host"], port=where["port"], graph=where["graph"],
                                         username=where["username"] or "", password=where["password"] or "",
                                         connect_timeout=10.0, socket_timeout=10.0))
    sandbox = QuerySandbox(source)
    try:
        source.setup()
        sandbox.setup()
    except KgadaptError as exc:
        _send(out, {"error": "unavailable", "text": str(exc)})
        return 1
    # Started at the service's priority (a loaded machine would otherwise hold up the service's start),
    # lowered before the first question: every thread, since Linux schedules threads, not processes.
    _lower_priority(int(first.get("nice", 19)))
    try:
        _send(out, {"ready": True})
        while (request := _receive(inp)) is not None:
            _send(out, _answer(sandbox, request))
    except (BrokenPipeError, KeyboardInterrupt):
        pass
    finally:
        sandbox.shutdown()
        source.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
