"""The per-host launcher: a process that has imported the detector's code and forks detectors on request.

A detector started the plain way is a new Python interpreter that imports
OpenCV, NumPy, Zenoh and the project's code before it can open its session:
hundreds of milliseconds on a small computer. The launcher pays that once.
Its agent's :class:`~kgadapt.deploy.supervisor.Supervisor` starts it
(``python -m kgadapt.deploy.launcher --fd N``) and talks to it over a private unix
socket pair (``SOCK_SEQPACKET``, one JSON message each way per request), never
over Zenoh: the launcher stays single-threaded and opens no session, so every
fork copies one thread and no runtime. The forked detector opens its own
Zenoh session, exactly as a plain-started one does.

What runs stays decided by the deployer: the launcher only takes an argv the
deployer resolved from the graph, and only ``<python> -m <module> ...`` for a
module it preloaded (:data:`RUNNABLE`); anything else the supervisor starts
the plain way.

Supervision is unchanged because the detector is the *agent's* child, not the
launcher's: the launcher forks an intermediate process that forks the
detector and exits at once; the orphaned detector is re-parented to the agent,
which declared itself a child subreaper (``PR_SET_CHILD_SUBREAPER``). Only
then does the detector ask for its parent-death signal (re-parenting would
fire it), check that its parent is the agent, start its own session and
process group, take the standard streams the agent sent (``SCM_RIGHTS``:
stdin, and the pipe whose other end the supervisor reads for the
readiness line), take the environment and working directory of the request
and run the module as ``__main__``. The agent waits for it, signals its group
and restarts it like any other child.

Warm pool: the agent may also ask the launcher to keep idle members for a
start it expects (``{"pool": N, ...}`` with the argv and environment of such a
start; fewer than it has: the extra ones are ended). A member is forked the same way but stops before the module's work:
it takes the environment, opens its Zenoh session (the module's
``pool_session(args)``) and waits on a socket of its own. A fork request whose
argv and environment match a member's, but for the ``--instance`` and
``--config`` values and the per-start variables (:data:`PER_START_ENV`;
:func:`pool_key`), is handed to an idle member instead of a new fork: it
takes the descriptors, environment and argv and tells its intermediate process
to exit, so it is re-parented to the agent as a forked detector is; the
launcher replies with its pid once that process has exited (status 0: the
member took the start). Meanwhile the member runs the module's
``main(args, session=..., adoption=...)`` with the session it already has: the
module does its own setup while the re-parenting happens, and calls
``adoption()`` before it says it is ready, which checks that its parent is
the agent and takes the agent's parent-death signal (until then the lifeline
below holds). A member's intermediate process stays until the start (so a
member is the launcher's grandchild while idle: it dies with the launcher).

An idle member must also die with the agent, at once, as a forked detector
does. Its parent-death signal cannot give that: it fires when its intermediate
process ends, which follows the launcher's death, which follows the agent's:
three processes torn down one after another, so for a while after ``kill -9``
of the agent an idle member is an orphan (and were the launcher to die before
an intermediate process asked for its signal, one would never end). So the
agent holds the write end of a *lifeline* pipe no other process holds (the
launcher gets the read end: ``--lifeline FD``), and each member (and its
intermediate process) opens that pipe anew, as its own open file (the signal's owner belongs to the open file, which
a fork shares), and asks the kernel to send it SIGKILL when the pipe's last
writer closes (``O_ASYNC`` with ``F_SETSIG``): the kernel closes a dying
process's files before its parent can reap it, as it sends the parent-death
signal. A member drops its lifeline once it has been adopted by the agent and
has its parent-death signal instead (at ``adoption()``). A member killed with
its agent before it has run its first lines (it is named idle once forked)
ends one death later: the first of them finds its intermediate process gone.

Protocol (JSON, one message per datagram)::

    launcher -> agent   {"ready": true, "pid": P, "python": EXE, "runnable": [modules]}   once, after the imports
    agent -> launcher   {"argv": [...], "env": {...}, "cwd": str|null, "parent": AGENT_PID, "death_signal": N}
                        + two descriptors: stdin, stdout (stderr goes to stdout)
    launcher -> agent   {"pid": DETECTOR_PID, "pooled": bool, "idle": IDLE_LEFT, "members": [PIDS], "middles": [PIDS]}
                        or {"error": "..."}
    agent -> launcher   {"pool": N, "argv": [...], "env": {...}, "cwd": ..., "parent": ..., "death_signal": N}
    launcher -> agent   {"idle": IDLE_MEMBERS_FOR_THAT_START, "members": [PIDS], "middles": [PIDS]} or {"error": "..."}

``members``: the pids of the idle members for that kind of start, so the agent can say which
processes under its launcher are idle members (its ``list`` reply) and tools can tell them from orphans.
``middles``: their intermediate processes. Both give their memory back when a start takes a member (the
intermediate process then ends), so the agent's host monitor leaves both out of measured use.

The launcher exits when the agent closes its end of the socket (or dies).
"""

from __future__ import annotations

import argparse
import fcntl
import importlib
import io
import json
import logging
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from typing import Any, Callable, NoReturn, Sequence

from kgadapt.shared import parent_death, proc_stat
from kgadapt.shared.errors import DeploymentError

log = logging.getLogger(__name__)

# Modules a launcher may run with ``-m``; PRELOAD is what it imports first (the heavy parts). Runtime
# detectors only: the tests' echo detector (kgadapt.sim) is started the plain way, as any program.
RUNNABLE = ("kgadapt.onboard.perception.detector",)
# The reflex module (with the light estimate and the live ranking it uses: 25 ms of imports) too: a
# forked detector arms its reflex table on a thread after ready, and an import there would hold the
# frame worker at the import lock.
PRELOAD = ("numpy", "cv2", "zenoh", "kgadapt.onboard.perception.markers", "kgadapt.knowledge.client", "kgadapt.shared.session",
           "kgadapt.shared.agent", "kgadapt.onboard.perception.reflex", *RUNNABLE)
_MAX_MESSAGE = 1 << 20
# What differs between two starts a pool member can take: these flags' values and these variables.
PER_START_ARGS = ("--instance", "--config")
# (KGADAPT_POOL_DEPLOYMENTS is a member's own: what it prepares for, never a start's.)
PER_START_ENV = ("KGADAPT_START_IDLE", "KGADAPT_RESOLVED_CONFIG", "KGADAPT_POOL_DEPLOYMENTS")
MAX_POOL = 8  # idle members per kind of start, whatever the agent asks
# The launcher's argv carries this much room: a forked detector writes its own command line there,
# so ps, psutil and the tools that find detectors by their command line see it as a plain-started one.
TITLE_ROOM = 2048


def become_subreaper() -> None:
    """Make this process adopt its orphaned descendants (a forked detector). DeploymentError if it cannot."""
    try:
        parent_death.become_subreaper()
    except OSError as exc:
        raise DeploymentError(f"the launcher needs Linux prctl(PR_SET_CHILD_SUBREAPER): {exc}") from exc


def runnable_module(argv: Sequence[str], python: str, modules: Sequence[str]) -> str | None:
    """The module of ``argv`` when it is ``<python> -m <module> ...`` with a module the launcher runs, else None."""
    if len(argv) < 3 or argv[1] != "-m" or argv[2] not in modules:
        return None
    # The same path as given needs no look at the file system (resolving both cost 0.2 ms a start).
    if argv[0] != python and os.path.realpath(argv[0]) != os.path.realpath(python):
        return None
    return argv[2]


def pool_key(argv: Sequence[str], env: dict[str, str]) -> str:
    """What a pool member must share with a start to take it: the argv without the per-start flags'
    values and the environment without the per-start variables."""
    kept: list[str] = []
    skip = False
    for arg in argv:
        if skip:
            skip = False
        elif arg in PER_START_ARGS:
            skip = True
        else:
            kept.append(arg)
    return json.dumps([kept, sorted((k, v) for k, v in env.items() if k not in PER_START_ENV)])


# -- the launcher process ---------------------------------------------------------------


class _Member:
    """An idle pool member as the launcher holds it."""

    def __init__(self, pid: int, middle: int, sock: socket.socket) -> None:
        self.pid, self.middle, self.sock = pid, middle, sock


def _threads() -> int:
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:  # pragma: no cover - no procfs: trust threading
        return threading.active_count()


def serve(sock: socket.socket, *, runnable: Sequence[str] = RUNNABLE, lifeline: int | None = None) -> int:
    """Answer fork requests on ``sock`` until the agent closes it; the launcher's main loop. ``lifeline``:
    the read end of the agent's lifeline pipe (pool members die when its writer closes); None: members
    die with the launcher only."""
    hello = {"ready": True, "pid": os.getpid(), "python": sys.executable, "runnable": list(runnable)}
    sock.send(json.dumps(hello).encode())
    pool: dict[str, list[_Member]] = {}
    while True:
        try:
            data, fds, _flags, _addr = socket.recv_fds(sock, _MAX_MESSAGE, 4)
        except InterruptedError:
            continue
        except OSError as exc:
            log.debug("launcher: socket closed: %s", exc)
            return 0
        if not data:
            for fd in fds:
                os.close(fd)
            return 0  # the agent closed its end or died
        try:
            _reap_members(pool)
            reply = _fork_request(data, fds, runnable, sock, pool, lifeline)
        except DeploymentError as exc:
            reply = {"error": str(exc)}
        finally:
            for fd in fds:
                os.close(fd)
        try:
            sock.send(json.dumps(reply).encode())
        except OSError:
            return 0


def _reap_members(pool: dict[str, list[_Member]]) -> None:
    """Forget members that died idle (their intermediate process ends with them) and reap those."""
    for key, members in list(pool.items()):
        for m in list(members):
            try:
                done, _ = os.waitpid(m.middle, os.WNOHANG)
            except ChildProcessError:
                done = m.middle
            if done:
                members.remove(m)
                m.sock.close()
        if not members:
            del pool[key]


def _fork_request(data: bytes, fds: list[int], runnable: Sequence[str], sock: socket.socket,
                  pool: dict[str, list[_Member]] | None = None, lifeline: int | None = None) -> dict[str, Any]:
    pool = {} if pool is None else pool
    try:
        request = json.loads(data)
        argv = [str(a) for a in request["argv"]]
        env = {str(k): str(v) for k, v in dict(request["env"]).items()}
        cwd = request.get("cwd")
        parent = int(request["parent"])
        death_signal = int(request["death_signal"])
        size = None if request.get("pool") is None else max(0, min(int(request["pool"]), MAX_POOL))
    except (ValueError, KeyError, TypeError) as exc:
        raise DeploymentError(f"malformed fork request: {exc}") from exc
    module = runnable_module(argv, sys.executable, runnable)
    if module is None:
        raise DeploymentError(f"the launcher runs only {sys.executable} -m one of {', '.join(runnable)}; not {argv[:3]}")
    key = pool_key(argv, env)
    if size is not None:
        if not hasattr(importlib.import_module(module), "pool_session"):
            raise DeploymentError(f"{module} cannot wait in a pool (it has no pool_session)")
        members = pool.setdefault(key, [])
        while len(members) > size:  # fewer asked (the memory budget has less room now): the newest end
            _end_member(members.pop())
        while len(members) < size:
            members.append(_fork_member(module, argv, env, cwd, sock, lifeline))
        return _pool_reply(members)
    if len(fds) != 2:
        raise DeploymentError(f"a fork request carries stdin and stdout, not {len(fds)} descriptors")
    members = pool.get(key) or []
    while members:
        member = members.pop(0)
        if _hand_over(member, data, fds):
            return {"pid": member.pid, "pooled": True, **_pool_reply(members)}
    return {**_fork_detector(module, argv, env, cwd, parent, death_signal, fds, sock), "pooled": False,
            **_pool_reply([])}


def _pool_reply(members: Sequence[_Member]) -> dict[str, Any]:
    return {"idle": len(members), "members": [m.pid for m in members], "middles": [m.middle for m in members]}


def _end_member(member: _Member) -> None:
    """End an idle member (it may still be opening its session) and reap its intermediate process."""
    member.sock.close()
    try:
        os.kill(member.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    try:
        os.waitpid(member.middle, 0)  # it exits as its member does (end of file on their pipe)
    except ChildProcessError:
        pass


def _hand_over(member: _Member, data: bytes, fds: list[int]) -> bool:
    """Give ``member`` the start request and its descriptors; True once it is the agent's: its
    intermediate process ended because the member took the start (status 0), and the kernel re-parents
    a process's children before its parent can reap it. False: the member had died."""
    try:
        socket.send_fds(member.sock, [data], fds)  # queued: the member reads it though we close at once
    except OSError:  # it died (its end closed): its intermediate process ends with it
        pass
    finally:
        member.sock.close()
    try:
        _, status = os.waitpid(member.middle, 0)  # it exits when the member says so (or died with it)
    except ChildProcessError:
        return False
    return os.waitstatus_to_exitcode(status) == 0


def _fork_member(module: str, argv: list[str], env: dict[str, str], cwd: str | None, sock: socket.socket,
                 lifeline: int | None = None) -> _Member:
    """Fork an idle pool member for starts like ``argv``; it opens its session on its own time."""
    if _threads() != 1:
        raise DeploymentError(f"the launcher has {_threads()} threads; it forks only single-threaded")
    sys.stdout.flush()
    sys.stderr.flush()
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    r, w = os.pipe()
    launcher = os.getpid()
    middle = os.fork()
    if middle == 0:  # the intermediate process: fork the member, say its pid, exit when it is taken
        code = 1
        try:
            # Dies with the launcher, and so its member; at once if the launcher died before the request.
            if not parent_death.tie_to_parent(launcher, signal.SIGKILL):
                os._exit(1)  # not reached: the signal is SIGKILL
            if lifeline is not None:  # ... and with the agent, at once
                lifeline = _hold_lifeline(lifeline)
            me = os.getpid()
            os.close(r)
            ours.close()
            sock.close()
            release_r, release_w = os.pipe()
            pid = os.fork()
            if pid == 0:
                os.close(release_r)
                _pool_member(me, module, argv, env, cwd, theirs, release_w, lifeline)
            os.close(release_w)
            theirs.close()
            os.write(w, str(pid).encode())
            # 0: the member took a start (it wrote); 1: it died (end of file).
            code = 0 if os.read(release_r, 1) == b"x" else 1
        finally:
            os._exit(code)
    os.close(w)
    theirs.close()
    try:
        text = os.read(r, 32)
    finally:
        os.close(r)
    if not text:
        ours.close()
        os.waitpid(middle, 0)
        raise DeploymentError("the launcher could not fork a pool member")
    return _Member(int(text), middle, ours)


def _pool_member(middle: int, module: str, argv: list[str], env: dict[str, str], cwd: str | None,
                 member_sock: socket.socket, release: int, lifeline: int | None = None) -> None:
    """In a pool member: open the session, wait for a start, become it. Never returns."""

    def run() -> int:
        nonlocal argv
        kept = (member_sock.fileno(), release) if lifeline is None else (member_sock.fileno(), release, lifeline)
        _close_fds_but(*kept)  # the launcher's sockets, other members' ones
        # Idle, it dies with its intermediate process; at once if that has ended already.
        if not parent_death.tie_to_parent(middle, signal.SIGKILL):
            os._exit(1)  # not reached: the signal is SIGKILL
        own_line = None if lifeline is None else _hold_lifeline(lifeline)  # ... and with the agent, at once
        os.setsid()
        devnull = os.open(os.devnull, os.O_RDWR)
        os.dup2(devnull, 0)
        os.close(devnull)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        _enter(env, cwd, [*argv[:3], "(pooled)"])
        logging.root.handlers.clear()
        runner = importlib.import_module(module)
        session = runner.pool_session(argv[3:])
        data, fds, _flags, _addr = socket.recv_fds(member_sock, _MAX_MESSAGE, 4)
        if not data or len(fds) != 2:
            os._exit(0)  # the launcher closed the pool
        request = json.loads(data)
        argv = [str(a) for a in request["argv"]]
        parent, death_signal = int(request["parent"]), int(request["death_signal"])
        _take_stdio(fds)
        os.close(fds[0])
        os.close(fds[1])
        _enter({str(k): str(v) for k, v in dict(request["env"]).items()}, request.get("cwd"), argv)
        _line_buffered()
        parent_death.set_death_signal(0)  # not when the intermediate process ends now
        member_sock.close()
        # The intermediate process exits, this one is re-parented to the agent and the launcher names it
        # to the agent, while the module does its own setup. Before it says it is ready, the module
        # checks its adoption and takes the agent's parent-death signal; until then the lifeline holds.
        os.write(release, b"x")
        os.close(release)

        def adoption() -> None:
            _await_adoption(middle, parent, death_signal)
            if own_line is not None:  # adopted, with the agent's parent-death signal: the lifeline's work is done
                os.close(own_line)

        return _run_module(module, argv, session=session, adoption=adoption)

    _end_with(run)


def _fork_detector(module: str, argv: list[str], env: dict[str, str], cwd: str | None, parent: int,
                   death_signal: int, fds: list[int], sock: socket.socket) -> dict[str, Any]:
    if _threads() != 1:  # a fork copies one thread: locks held by others would stay locked in the child
        raise DeploymentError(f"the launcher has {_threads()} threads; it forks only single-threaded")
    sys.stdout.flush()
    sys.stderr.flush()
    r, w = os.pipe()
    middle = os.fork()
    if middle == 0:  # the intermediate process: fork the detector, say its pid, exit so it is re-parented
        code = 1
        try:
            me = os.getpid()
            pid = os.fork()
            if pid == 0:
                _detector_child(me, parent, death_signal, fds, module, argv, env, cwd, (r, w, sock.fileno()))
            os.write(w, str(pid).encode())
            code = 0
        finally:
            os._exit(code)
    os.close(w)
    _, status = os.waitpid(middle, 0)
    try:
        text = os.read(r, 32) if os.waitstatus_to_exitcode(status) == 0 else b""
    finally:
        os.close(r)
    if not text:
        raise DeploymentError("the launcher could not fork a detector")
    return {"pid": int(text)}


def _detector_child(middle: int, parent: int, death_signal: int, fds: list[int], module: str, argv: list[str],
                    env: dict[str, str], cwd: str | None, close: tuple[int, ...]) -> None:
    """In the forked detector: become the agent's supervised child, then run ``module`` as ``__main__``. Never returns."""

    def run() -> int:
        for fd in close:
            os.close(fd)
        _await_adoption(middle, parent, death_signal)
        os.setsid()  # own session and process group: the supervisor signals the group
        _take_stdio(fds)
        _close_fds_but()
        signal.signal(signal.SIGINT, signal.default_int_handler)  # as a fresh interpreter has them
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        _enter(env, cwd, argv)
        logging.root.handlers.clear()  # the detector configures its own logging
        _line_buffered()
        return _run_module(module, argv)

    _end_with(run)


# -- what both kinds of forked child do (a pool member, a detector forked on request) ------------------------


def _end_with(run: Callable[[], int]) -> NoReturn:
    """Run a forked child's body and end the process with its exit code, whatever happens."""
    code = 1
    try:
        code = run()
    except BaseException:  # noqa: BLE001 - whatever happens, this process must end here
        import traceback

        traceback.print_exc()
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)


def _await_adoption(middle: int, parent: int, death_signal: int) -> None:
    """Wait until the intermediate process has exited and ``parent`` (the agent, our subreaper) is our parent."""
    deadline = time.monotonic() + 5.0
    while os.getppid() == middle:  # the intermediate process exits right after the fork
        if time.monotonic() > deadline:
            os._exit(1)
        time.sleep(0.0002)
    # After the re-parenting: set before, the intermediate's exit would already have fired it. Not tied: the
    # agent died, or is not our subreaper, and nobody would supervise us.
    if not parent_death.tie_to_parent(parent, death_signal):
        os._exit(1)


def _hold_lifeline(lifeline: int) -> int:
    """Have the kernel SIGKILL this process when the lifeline pipe's last writer (the agent) closes it;
    ends the process at once if that has happened already. Returns this process's own descriptor of it."""
    # An open file of our own: the signal goes to the owner of the open file, one per open, shared by forks.
    own = os.open(f"/proc/self/fd/{lifeline}", os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    os.close(lifeline)
    fcntl.fcntl(own, fcntl.F_SETOWN, os.getpid())
    fcntl.fcntl(own, fcntl.F_SETSIG, signal.SIGKILL)
    fcntl.fcntl(own, fcntl.F_SETFL, fcntl.fcntl(own, fcntl.F_GETFL) | os.O_ASYNC)
    if select.select([own], [], [], 0)[0]:  # end of file already (nothing is ever written): the agent is gone
        os.kill(os.getpid(), signal.SIGKILL)
        os._exit(1)
    return own


def _close_fds_but(*keep: int) -> None:
    """Close every descriptor above stderr except ``keep``."""
    for name in os.listdir("/proc/self/fd"):
        fd = int(name)
        if fd > 2 and fd not in keep:
            try:
                os.close(fd)
            except OSError:
                pass


def _take_stdio(fds: Sequence[int]) -> None:
    """Make the agent's (stdin, stdout) pair this process's stdin, stdout and stderr."""
    stdin, stdout = fds
    os.dup2(stdin, 0)
    os.dup2(stdout, 1)
    os.dup2(stdout, 2)


def _enter(env: dict[str, str], cwd: str | None, title: Sequence[str]) -> None:
    """Take the start's environment, working directory and command line."""
    os.environ.clear()
    os.environ.update(env)
    if cwd:
        os.chdir(cwd)
    set_title(title)


def _line_buffered() -> None:
    # As stdout is after the dup2 onto the agent's pipe; a test may have replaced it.
    if isinstance(sys.stdout, io.TextIOWrapper):
        sys.stdout.reconfigure(line_buffering=True)


def set_title(argv: Sequence[str]) -> bool:
    """Show ``argv`` as this process's command line (/proc/PID/cmdline), within the room of its own argv.

    Written over the original argv area (what setproctitle does): the kernel reads an area whose
    last byte is not NUL up to its first NUL, and psutil splits such a title at the spaces. False
    when it does not fit or the area cannot be written.
    """
    try:
        fields = proc_stat.stat_fields()
        start, end = int(fields[proc_stat.ARG_START]), int(fields[proc_stat.ARG_END])
        title = " ".join(argv).encode()
        if len(title) + 2 > end - start:
            return False
        data = title + b"\0" + b" " * (end - start - len(title) - 1)
        with open("/proc/self/mem", "r+b", buffering=0) as mem:
            mem.seek(start)
            mem.write(data)
        return True
    except (OSError, ValueError, IndexError):
        return False


def _run_module(module: str, argv: list[str], *, session: Any = None, adoption: Callable[[], None] | None = None) -> int:
    """Run ``module``'s ``main(args)`` as ``python -m module args`` would (a pool member's with its session,
    and ``adoption``, which the module calls before it says it is ready).

    Its preloaded copy is used as it is: running it again as ``__main__`` (runpy) would execute a
    second copy beside the imported one, which Python warns about in the detector's output.
    """
    sys.argv = [argv[0], *argv[3:]]
    try:
        runner = importlib.import_module(module)
        code = runner.main(sys.argv[1:]) if session is None else \
            runner.main(sys.argv[1:], session=session, adoption=adoption)
    except SystemExit as exc:
        if exc.code is None:
            return 0
        if isinstance(exc.code, int):
            return exc.code
        print(exc.code, file=sys.stderr)
        return 1
    return code if isinstance(code, int) else 0


def preload(modules: Sequence[str], runnable: Sequence[str]) -> None:
    """Import ``modules``, then call each ``runnable`` module's ``prefork()`` if it has one: what every
    start of it would otherwise do first in the fork (the detector builds its argument parser and reads a
    made-up carried configuration), done once before any fork. A prefork starts no thread."""
    for name in modules:
        importlib.import_module(name)
    for name in runnable:
        prepare = getattr(importlib.import_module(name), "prefork", None)
        if callable(prepare):
            prepare()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kgadapt.deploy.launcher",
                                     description="Fork detectors for the agent that started this (see deploy/launcher.py).")
    parser.add_argument("--fd", type=int, required=True, help="descriptor of the socket to the agent")
    parser.add_argument("--title-room", default="", help="room for the forked detectors' command lines")
    parser.add_argument("--lifeline", type=int, help="descriptor of the read end of the agent's lifeline pipe "
                        "(idle pool members die when the agent closes its end)")
    args = parser.parse_args(argv)
    set_title([sys.executable, "-m", "kgadapt.deploy.launcher", "--fd", str(args.fd)])
    # OpenBLAS starts a thread pool at import; the launcher must stay single-threaded to fork safely, so a
    # value from the agent's environment (kgadapt.env) does not hold here: it made every launcher exit.
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    sock = socket.socket(fileno=args.fd)
    preload(PRELOAD, RUNNABLE)
    if _threads() != 1:
        print(f"kgadapt.deploy.launcher: error: {_threads()} threads after the imports; cannot fork safely", file=sys.stderr)
        return 1
    import gc

    # The imported objects go to the permanent generation: a child's collections then neither walk
    # them (a full one in a detector cost frames at a reconfiguration) nor write to their pages (copy-on-write).
    gc.collect()
    gc.freeze()
    try:
        return serve(sock, lifeline=args.lifeline)
    finally:
        sock.close()


# -- the agent's side ------------------------------------------------------------------


class ForkedProcess:
    """A detector forked by the launcher, as the supervisor sees it (the parts of ``subprocess.Popen`` it uses)."""

    def __init__(self, pid: int, stdout: Any, *, pooled: bool = False) -> None:
        self.pid = pid
        self.stdout = stdout
        self.pooled = pooled  # an idle pool member took the start
        self.returncode: int | None = None

    def wait(self) -> int:
        if self.returncode is None:
            while True:
                try:
                    _, status = os.waitpid(self.pid, 0)
                    break
                except InterruptedError:
                    continue
            self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode


class LauncherClient:
    """The agent's end: starts the launcher, forks through it, notices its death and starts it again.

    ``launch`` and ``fork`` are called on the supervisor's spawner thread (the
    launcher gets its parent-death signal from that thread). ``fork`` returns
    None whenever the launcher cannot do it (not ready yet, dead, refused);
    the caller then starts the program the plain way.
    """

    def __init__(self, *, python: str, death_signal: int, preexec: Callable[[], Callable[[], None]],
                 schedule_restart: Callable[[float], None], hello_timeout: float = 60.0,
                 reply_timeout: float = 5.0, restart_delay: float = 0.5) -> None:
        self.python = python
        self.death_signal = death_signal
        self._preexec = preexec
        self._schedule_restart = schedule_restart
        self.hello_timeout = hello_timeout
        self.reply_timeout = reply_timeout
        self.restart_delay = restart_delay
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._proc: subprocess.Popen[bytes] | None = None
        self._sock: socket.socket | None = None
        # The write end of each live launcher's lifeline pipe (this process alone holds it: O_CLOEXEC, and
        # never passed on); its pool members die when it closes, with this process or with their launcher.
        self._lifelines: dict[int, int] = {}
        self._runnable: tuple[str, ...] = ()
        self._ready = False
        self._closing = False
        self.starts = 0  # launcher processes started so far
        self.idle: dict[str, int] = {}  # idle pool members by pool_key, as the launcher last said
        self._members: dict[str, list[int]] = {}  # their pids, by pool_key, as the launcher last said
        self._middles: dict[str, list[int]] = {}  # ... and their intermediate processes' pids

    @property
    def pid(self) -> int | None:
        with self._lock:
            return self._proc.pid if self._proc is not None else None

    @property
    def ready(self) -> bool:
        with self._lock:
            return self._ready

    def wait_ready(self, timeout: float) -> bool:
        """True once a launcher is ready to fork (within ``timeout`` seconds)."""
        with self._changed:
            return self._changed.wait_for(lambda: self._ready or self._closing, timeout) and self._ready

    def launch(self) -> None:
        """Start a launcher process (on the spawner thread); its greeting is awaited on another thread."""
        with self._lock:
            if self._closing or self._proc is not None:
                return
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        line_r, line_w = os.pipe2(os.O_CLOEXEC)
        env = dict(os.environ)
        env["PYTHONUNBUFFERED"] = "1"
        try:
            proc = subprocess.Popen(
                [self.python, "-m", "kgadapt.deploy.launcher", "--fd", str(theirs.fileno()), "--lifeline", str(line_r),
                 "--title-room", "." * TITLE_ROOM],
                stdin=subprocess.DEVNULL, pass_fds=(theirs.fileno(), line_r), env=env, start_new_session=True,
                preexec_fn=self._preexec(),
            )
        except (OSError, subprocess.SubprocessError) as exc:
            ours.close()
            os.close(line_w)
            log.warning("cannot start the launcher (%s); detectors start the plain way", exc)
            self._schedule_restart(self.restart_delay * 10)
            return
        finally:
            theirs.close()
            os.close(line_r)
        with self._lock:
            self._proc, self._sock, self._ready = proc, ours, False
            self._lifelines[proc.pid] = line_w
            self.starts += 1
            self.idle, self._members, self._middles = {}, {}, {}  # a new launcher has no pool
        threading.Thread(target=self._await_hello, args=(proc, ours), name="launcher-hello", daemon=True).start()
        threading.Thread(target=self._watch, args=(proc,), name="launcher-wait", daemon=True).start()

    def _await_hello(self, proc: subprocess.Popen[bytes], sock: socket.socket) -> None:
        sock.settimeout(self.hello_timeout)
        try:
            hello = json.loads(sock.recv(_MAX_MESSAGE) or b"{}")
        except (OSError, ValueError) as exc:
            log.warning("launcher (pid %s) did not greet: %s", proc.pid, exc)
            hello = {}
        with self._lock:
            if self._proc is not proc:
                return
            if hello.get("ready") and hello.get("python"):
                self._runnable = tuple(hello.get("runnable") or ())
                self._ready = True
                self._changed.notify_all()
                log.info("launcher ready (pid %s): forks %s", proc.pid, ", ".join(self._runnable))
                return
        self._kill(proc)

    def _watch(self, proc: subprocess.Popen[bytes]) -> None:
        code = proc.wait()
        self._cut_lifeline(proc.pid)  # its idle members, should any outlive it, end now
        with self._lock:
            if self._proc is not proc:
                return
            self._proc, self._ready = None, False
            sock, self._sock = self._sock, None
            closing = self._closing
            self._changed.notify_all()
        if sock is not None:
            sock.close()
        if closing:
            return
        log.warning("launcher (pid %s) ended with status %s; starting another, plain starts meanwhile", proc.pid, code)
        self._schedule_restart(self.restart_delay)

    def _cut_lifeline(self, pid: int) -> None:
        with self._lock:
            line = self._lifelines.pop(pid, None)
        if line is not None:
            os.close(line)

    def _kill(self, proc: subprocess.Popen[bytes]) -> None:
        try:
            proc.kill()  # its watcher thread notices the exit and starts another
        except OSError:
            pass

    def fork(self, argv: Sequence[str], env: dict[str, str], cwd: str | None) -> ForkedProcess | None:
        """Fork ``argv`` through the launcher; None when it cannot (the caller starts it the plain way)."""
        with self._lock:
            if not self._ready or self._sock is None or self._proc is None:
                return None
            if runnable_module(argv, self.python, self._runnable) is None:
                return None
            sock, proc = self._sock, self._proc
            stdin = os.open(os.devnull, os.O_RDONLY | os.O_CLOEXEC)
            r, w = os.pipe2(os.O_CLOEXEC)
            request = {"argv": list(argv), "env": env, "cwd": cwd, "parent": os.getpid(),
                       "death_signal": int(self.death_signal)}
            try:
                sock.settimeout(self.reply_timeout)
                socket.send_fds(sock, [json.dumps(request).encode()], [stdin, w])
                reply = json.loads(sock.recv(_MAX_MESSAGE) or b"{}")
            except (OSError, ValueError) as exc:
                reply = {"error": f"no answer: {exc}"}
                self._ready = False
                dead = True
            else:
                dead = not reply
            finally:
                os.close(stdin)
                os.close(w)
        pid = reply.get("pid") if isinstance(reply, dict) else None
        if isinstance(pid, int):
            with self._lock:
                self._note_pool(pool_key(argv, env), reply)
        if not isinstance(pid, int):
            os.close(r)
            log.warning("launcher (pid %s) did not fork %s: %s", proc.pid, argv[2] if len(argv) > 2 else argv,
                        reply.get("error") if isinstance(reply, dict) else reply)
            if dead:
                self._kill(proc)
            return None
        return ForkedProcess(pid, os.fdopen(r, "rb"), pooled=bool(reply.get("pooled")))

    def fill(self, argv: Sequence[str], env: dict[str, str], cwd: str | None, size: int) -> int | None:
        """Have ``size`` idle members wait for starts like ``argv`` (fewer than there are: the extra ones
        end); the number idle now, None when the launcher cannot."""
        with self._lock:
            if not self._ready or self._sock is None:
                return None
            if runnable_module(argv, self.python, self._runnable) is None:
                return None
            request = {"pool": int(size), "argv": list(argv), "env": env, "cwd": cwd, "parent": os.getpid(),
                       "death_signal": int(self.death_signal)}
            try:
                self._sock.settimeout(self.reply_timeout)
                self._sock.send(json.dumps(request).encode())
                reply = json.loads(self._sock.recv(_MAX_MESSAGE) or b"{}")
            except (OSError, ValueError) as exc:
                log.warning("launcher: no answer to a pool request: %s", exc)
                return None
            idle = reply.get("idle") if isinstance(reply, dict) else None
            if not isinstance(idle, int):
                log.info("launcher: pool refused: %s", reply.get("error") if isinstance(reply, dict) else reply)
                return None
            self._note_pool(pool_key(argv, env), reply)
            return idle

    def _note_pool(self, key: str, reply: dict[str, Any]) -> None:
        """What the launcher said of the idle members for ``key`` (caller holds the lock)."""
        self.idle[key] = int(reply.get("idle") or 0)
        for name, into in (("members", self._members), ("middles", self._middles)):
            pids = reply.get(name)
            into[key] = [int(p) for p in pids if isinstance(p, int)] if isinstance(pids, list) else []

    def idle_pids(self) -> list[int]:
        """The pids of every idle pool member, as the launcher last said (none while it is not ready)."""
        with self._lock:
            return sorted(p for pids in self._members.values() for p in pids) if self._ready else []

    def yielding_pids(self) -> list[int]:
        """The pids of the processes that hold idle members: the members and their intermediate processes
        (a start takes a member and its intermediate process ends), as the launcher last said."""
        with self._lock:
            if not self._ready:
                return []
            return sorted(p for table in (self._members, self._middles) for pids in table.values() for p in pids)

    def runs(self, argv: Sequence[str]) -> bool:
        """Whether the ready launcher forks ``argv`` (so could keep pool members for it)."""
        with self._lock:
            return self._ready and runnable_module(argv, self.python, self._runnable) is not None

    def idle_for(self, argv: Sequence[str], env: dict[str, str]) -> int:
        """Idle members that could take a start of ``argv`` with ``env``."""
        with self._lock:
            return self.idle.get(pool_key(argv, env), 0) if self._ready else 0

    def shutdown(self) -> None:
        """Close the socket (the launcher exits on it) and wait for the launcher; forked detectors are not touched."""
        with self._lock:
            self._closing = True
            proc, sock = self._proc, self._sock
            self._sock, self._ready = None, False
            self._changed.notify_all()
        if sock is not None:
            sock.close()
        if proc is not None:
            try:
                proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            self._cut_lifeline(proc.pid)


if __name__ == "__main__":
    sys.exit(main())
