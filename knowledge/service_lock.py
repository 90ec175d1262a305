"""One knowledge service per store.

A second service on the same store would mark every platform offline at
start and then fight the first over platform state. The first service holds
this lock; a second one refuses to start, naming the holder.

- Embedded store: an ``flock`` on ``service.lock`` in the store's directory.
  The kernel releases it when the holder dies, so a restarted service (after
  ``kill -9``) takes it at once.
- ``falkordb://`` server: a lease key in the server (``SET NX PX``), renewed
  by a thread every third of its life, on a connection of its own. The lease
  names its holder's process (pid, start time, pid namespace, boot), so a
  service started on the same machine after its predecessor died (``kill -9``
  and restart) takes the lease at once. A holder elsewhere that dies leaves
  it for at most ``lease_s``; a new service waits that long before refusing.
- Other stores (Bolt): no lock; the docs say to run one service per store.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import socket
import threading
import time
import uuid
from typing import Any

from kgadapt.knowledge.store import GraphStore
from kgadapt.shared.errors import ConfigError, StoreError
from kgadapt.shared.proc_stat import START_TIME, STATE, stat_fields

log = logging.getLogger(__name__)

# Compare-and-renew and compare-and-delete, each one script so nothing runs between the check and the
# act (a lease run out between a GET and a PEXPIRE would extend the next holder's). The client may
# answer strings or bytes (FalkorDB's decodes them); the script compares inside the server.
_RENEW = ("local held = redis.call('GET', KEYS[1]) "
          "if held == ARGV[1] then return redis.call('PEXPIRE', KEYS[1], ARGV[2]) end "
          "if not held then return redis.call('SET', KEYS[1], ARGV[1], 'NX', 'PX', ARGV[2]) and 1 or 0 end "
          "return -1")
_RELEASE = "if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end return 0"


class ServiceLockHeld(StoreError):
    """Another knowledge service already serves this store."""


class ServiceLock:
    """``acquire()`` takes the store's service lock or raises ServiceLockHeld; ``release()`` gives it back."""

    def __init__(self, store: GraphStore, *, lease_s: float = 9.0) -> None:
        if lease_s <= 0:
            raise ConfigError(f"lease_s {lease_s!r}: must be positive")
        self.store = store
        # 9 s, renewed every 3 s: a hundred services renewing once a second cost 0.7-0.9 % of a core
        # (docs/fleet.md), and only a successor on another machine waits the lease out.
        self.lease_s = lease_s
        self._process = _this_process()
        self.holder = json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "id": uuid.uuid4().hex[:8],
                                  **self._process})
        self._file: Any = None
        self._stop = threading.Event()
        self._renewer: threading.Thread | None = None
        # The renewal's own connection to the server and its command, packed once (see renew()).
        self._line: Any = None
        self._line_pool: Any = None
        self._renewal: Any = None
        self._line_lock = threading.Lock()

    @property
    def key(self) -> str:
        return f"kgadapt:knowledge-service:{self.store.settings.graph}"

    def acquire(self) -> None:
        settings = self.store.settings
        if settings.kind == "embedded" and settings.data_dir is not None:
            self._acquire_file(settings.data_dir / "service.lock")
        elif settings.kind == "falkordb":
            self._acquire_lease()
        else:
            log.info("store %s: no service lock for this kind of store; run one service per store", settings.url)

    def release(self) -> None:
        self._stop.set()
        if self._renewer is not None:
            self._renewer.join(timeout=5)
            self._renewer = None
            try:
                redis = self.store.redis  # type: ignore[attr-defined]  # a lease only on FalkorDB: its redis client
                redis.eval(_RELEASE, 1, self.key, self.holder)
            except Exception as exc:  # noqa: BLE001 - the store may be gone; the lease then runs out by itself
                log.debug("service lease not released: %s", exc)
            self._close_line()
        if self._file is not None:
            try:
                fcntl.flock(self._file, fcntl.LOCK_UN)
            finally:
                self._file.close()
                self._file = None

    # -- embedded: a file lock ----------------------------------------------

    def _acquire_file(self, path: Any) -> None:
        handle = open(path, "a+")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            held_by = handle.read().strip() or "unknown"
            handle.close()
            raise ServiceLockHeld(
                f"another knowledge service already serves the store {self.store.url} ({held_by}); "
                "refusing to start a second one"
            ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(self.holder)
        handle.flush()
        self._file = handle

    # -- falkordb server: a lease ---------------------------------------------

    def _acquire_lease(self) -> None:
        redis = self.store.redis  # type: ignore[attr-defined]  # a lease only on FalkorDB: its redis client
        ttl_ms = int(self.lease_s * 1000)
        deadline = time.monotonic() + self.lease_s + 0.5
        while True:
            if redis.set(self.key, self.holder, nx=True, px=ttl_ms):
                break
            held_by = redis.get(self.key)
            if isinstance(held_by, bytes):
                held_by = held_by.decode(errors="replace")
            # Compare-and-delete: only the lease of the process found gone, not one taken meanwhile.
            if held_by and self._ended(held_by) and redis.eval(_RELEASE, 1, self.key, held_by):
                log.info("took the knowledge service lease of %s, which has ended", held_by)
                continue
            if time.monotonic() >= deadline:
                raise ServiceLockHeld(
                    f"another knowledge service already serves the store {self.store.url} "
                    f"({held_by or 'unknown'}); refusing to start a second one"
                )
            time.sleep(0.1)
        self._renewer = threading.Thread(target=self._renew, name="knowledge-service-lease", daemon=True)
        self._renewer.start()

    def _ended(self, held_by: str) -> bool:
        """Whether the lease ``held_by`` names a process of this machine and pid namespace that has ended
        (no such pid, another process under it, or a zombie). A holder elsewhere, or one that did not name
        its process, is never taken for ended."""
        try:
            other = json.loads(held_by)
        except ValueError:
            return False
        if not isinstance(other, dict) or not self._process:
            return False
        if other.get("boot") != self._process["boot"] or other.get("pidns") != self._process["pidns"]:
            return False
        pid, start = other.get("pid"), other.get("start")
        if not isinstance(pid, int) or not isinstance(start, int):
            return False
        now = _process_of(pid)
        return now is None or now[0] in ("Z", "X") or now[1] not in (start, -1)

    def renew(self) -> bool:
        """Extend the lease for another ``lease_s`` (taken again if it ran out); False when another holds it.

        Sent on a connection of its own with the command packed once: a renewal comes once a second, when
        redis-py's code is out of the CPU's caches, and its way through the client (pool, retry, command
        packing) then cost about 290 us of CPU against 90 us for this (a hundred services renew 100 times
        a second in ``kgadapt bench fleet``; docs/fleet.md). The connection comes from the client's pool,
        with its address, credentials and timeouts.
        """
        pool = self.store.redis.connection_pool  # type: ignore[attr-defined]  # a lease only on FalkorDB
        with self._line_lock:
            if self._line is None or self._line_pool is not pool:  # first, or the store's client replaced
                self._close_line_locked()
                self._line, self._line_pool = pool.make_connection(), pool
                self._renewal = self._line.pack_command("EVAL", _RENEW, 1, self.key, self.holder,
                                                        int(self.lease_s * 1000))
            try:
                self._line.send_packed_command(self._renewal, check_health=False)
                answer = self._line.read_response()
            except BaseException:
                self._close_line_locked()  # an answer half read must not be taken for the next renewal's
                raise
        return int(answer) >= 0

    def _close_line(self) -> None:
        with self._line_lock:
            self._close_line_locked()

    def _close_line_locked(self) -> None:
        if self._line is not None:
            try:
                self._line.disconnect()
            except Exception as exc:  # noqa: BLE001 - closing a connection to a server that may be gone
                log.debug("service lease connection not closed cleanly: %s", exc)
        self._line = self._line_pool = self._renewal = None

    def _renew(self) -> None:
        period = self.lease_s / 3
        # On a grid of the monotonic clock: the leases of the services of one process are renewed together,
        # on warm caches (as the status workers take, knowledge/service.py).
        while not self._stop.wait(period - time.monotonic() % period):
            try:
                if not self.renew():
                    log.error("the knowledge service lease on %s is held by another service", self.store.url)
            except Exception as exc:  # noqa: BLE001 - any redis error: renewed again a third of a lease later
                log.warning("cannot renew the knowledge service lease: %s", exc)


def _process_of(pid: int) -> tuple[str, int] | None:
    """The state and start time (clock ticks after boot) of process ``pid`` from /proc; None: no such process;
    start time -1: a process /proc does not show."""
    try:
        fields = stat_fields(pid)
    except (FileNotFoundError, ProcessLookupError):
        # /proc mounted with hidepid hides other users' processes: only the kernel's answer says it is gone.
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:
            pass
        return "?", -1  # alive, its start time unknown: not taken for ended
    return fields[STATE].decode(), int(fields[START_TIME])


def _this_process() -> dict[str, Any]:
    """What tells this process from any other that held a lease: its start time, its pid namespace and the
    machine's boot. Empty where /proc does not tell them (a lease then only ever runs out)."""
    try:
        with open("/proc/sys/kernel/random/boot_id", encoding="ascii") as handle:
            boot = handle.read().strip()
        pidns = os.readlink("/proc/self/ns/pid")
        mine = _process_of(os.getpid())
    except OSError:
        return {}
    return {} if mine is None else {"start": mine[1], "pidns": pidns, "boot": boot}
