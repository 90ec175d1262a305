"""The local process supervisor: start, watch, restart and stop child processes.

One :class:`Supervisor` per agent runs the detector processes of its host.
For each *instance* (a name unique among the live ones) it

- starts the program in its own session and process group, asked by the
  kernel to die with the agent (``PR_SET_PDEATHSIG``), so neither a crashed
  agent nor a detector's own children leave orphans behind;
- watches stdout for the readiness line of the one readiness protocol
  (:mod:`kgadapt.shared.readiness`) within a timeout;
- notices the exit and its return code, and restarts a crashed program with
  exponential back-off up to a limit (systemd's ``Restart=on-failure``);
- stops it like ros2 launch does: SIGINT, then SIGTERM, then SIGKILL, each
  after its own timeout, sent to the whole process group (the escalation of
  :mod:`kgadapt.shared.children`, which every other starter of children uses).

What happens is reported to listeners as :class:`ProcessEvent` values
(``started``, ``ready``, ``exited``, ``restarted``, ``stopped``, ``failed``).
Listeners run on the supervisor's threads: they must be quick and must not
call back into the supervisor.

With ``launcher`` the supervisor also runs the host's launcher
(deploy/launcher.py): a process that has imported the detector's code and
forks a detector on request, much faster than a new interpreter starts. The
supervisor then adopts those detectors as a child subreaper, so it waits for,
signals and restarts them exactly like the ones it started itself; a program
the launcher cannot run, or any start while the launcher is absent or
restarting, is started the plain way.

Threads: every fork happens on one long-lived *spawner* thread, because
``PR_SET_PDEATHSIG`` fires when the forking *thread* ends, not the process;
a child forked from a short-lived thread would be killed with it. Each run
then has a reader (stdout), a waiter (exit) and, until it is ready, a
watchdog thread.
"""

from __future__ import annotations

import collections
import ctypes
import logging
import os
import queue
import secrets
import shutil
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Literal

from kgadapt.deploy.launcher import ForkedProcess, LauncherClient, become_subreaper, pool_key
from kgadapt.shared import parent_death
from kgadapt.shared.children import StopPolicy, escalate
from kgadapt.shared.errors import ConfigError, DeploymentError, NotReady, ReadinessTimeout
from kgadapt.shared.keys import check_name
from kgadapt.shared.readiness import CONFIGURED_TOKEN, READY_TOKEN, ReadyWatch
from kgadapt.shared.states import FINAL_STATES, LIVE_STATES, SERVING_STATES, ProcessEventKind, ProcessState

log = logging.getLogger(__name__)

# How long an exit's report waits for the reader to take the rest of the child's output (its last lines,
# such as why it crashed, may still be in the pipe when the exit is seen). The whole process group is
# killed first, so end of file follows at once unless a process that left the group holds the pipe.
OUTPUT_DRAIN_S = 1.0

try:  # libc's signal(): Python's refuses in a child forked from a non-main thread
    _libc_signal: Callable[[int, None], object] | None = ctypes.CDLL(None, use_errno=True).signal
    _libc_signal.argtypes = [ctypes.c_int, ctypes.c_void_p]  # type: ignore[union-attr]  # the CDLL function just set
    _libc_signal.restype = ctypes.c_void_p  # type: ignore[union-attr]  # as above
except (OSError, AttributeError):  # pragma: no cover - not Linux
    _libc_signal = None


def _child_setup(parent_pid: int, death_signal: int) -> Callable[[], None]:
    """The preexec_fn: default SIGINT/SIGTERM, and ``death_signal`` when the spawner thread dies."""

    def setup() -> None:
        # An ignored signal stays ignored across exec: a supervisor started as a background
        # job of a shell (SIGINT ignored) would otherwise make every child deaf to our SIGINT.
        if _libc_signal is not None:
            _libc_signal(signal.SIGINT, None)  # None = SIG_DFL (0)
            _libc_signal(signal.SIGTERM, None)
        parent_death.tie_to_parent(parent_pid, death_signal)

    return setup


@dataclass(frozen=True, kw_only=True)
class RestartPolicy:
    """Restart a crashed process (non-zero exit or signal) with exponential back-off.

    A run that lasted ``stable_after`` seconds resets the count, so a detector
    that crashes once a day is not given up on after a week.
    """

    max_restarts: int = 3
    backoff_initial: float = 0.5
    backoff_factor: float = 2.0
    backoff_max: float = 10.0
    stable_after: float = 60.0

    def delay(self, attempt: int) -> float:
        """Seconds to wait before restart number ``attempt`` (1-based)."""
        return min(self.backoff_max, self.backoff_initial * self.backoff_factor ** (attempt - 1))


@dataclass(frozen=True, kw_only=True)
class ProcessSpec:
    """What to run for one instance. ``env`` is added to the agent's own environment."""

    instance: str
    argv: tuple[str, ...]
    env: tuple[tuple[str, str], ...] = ()
    cwd: str | None = None
    deployment: str = ""
    config: str = ""
    await_ready: bool = True  # False: ready as soon as it runs (a program that prints no readiness line)
    ready_timeout: float = 10.0
    restart: RestartPolicy = field(default_factory=RestartPolicy)
    stop: StopPolicy = field(default_factory=StopPolicy)

    def __post_init__(self) -> None:
        check_name(self.instance, "instance")
        if not self.argv or not all(isinstance(a, str) for a in self.argv):
            raise DeploymentError(f"instance {self.instance}: argv must be a non-empty list of strings")
        if self.ready_timeout <= 0:
            raise DeploymentError(f"instance {self.instance}: ready_timeout must be positive")


@dataclass(frozen=True, kw_only=True)
class ProcessEvent:
    """Something that happened to an instance (see the module docstring for the kinds)."""

    event: ProcessEventKind
    instance: str
    time: float
    run_id: str
    pid: int | None = None
    returncode: int | None = None
    detail: str | None = None
    deployment: str = ""
    config: str = ""


@dataclass(frozen=True, kw_only=True)
class ProcessInfo:
    """A snapshot of one instance, safe to hand out and to serialise."""

    instance: str
    deployment: str
    config: str
    state: ProcessState
    pid: int | None
    run_id: str
    restarts: int
    started_at: float | None
    ready_at: float | None
    ended_at: float | None
    returncode: int | None
    argv: tuple[str, ...]
    detail: str | None = None
    output: tuple[str, ...] = ()  # the last lines the current (or last) run printed
    via: str = ""  # how the current (or last) run was started: "launcher" (forked) or "exec"

    @property
    def live(self) -> bool:
        return self.state in LIVE_STATES


@dataclass(frozen=True, kw_only=True)
class SupervisorSettings:
    """``death_signal`` reaches the children when the agent dies without cleaning up.

    SIGKILL, not SIGTERM: a detector that ignores SIGTERM must not outlive its agent.
    """

    death_signal: int = signal.SIGKILL
    keep_finished: int = 50  # final instances remembered for list/status
    spawn_timeout: float = 10.0
    # How the parent-death signal is set: "preexec" calls prctl in a preexec_fn
    # (race-free: the child also checks its parent is still there), which makes
    # Python fork() the whole agent; "setpriv" execs util-linux's
    # ``setpriv --pdeathsig`` first, which lets Python use vfork. Measured here
    # (bench/deployer_bench.py): a few ms saved per start in a large agent.
    death_signal_via: Literal["preexec", "setpriv"] = "preexec"
    # Fork programs the host's launcher preloads (deploy/launcher.py) instead of starting a new interpreter.
    launcher: bool = False
    python: str = sys.executable  # the interpreter the launcher runs in; only "<python> -m ..." is forked

    def __post_init__(self) -> None:
        if self.death_signal_via not in ("preexec", "setpriv"):
            raise DeploymentError(f"death_signal_via {self.death_signal_via!r}: use 'preexec' or 'setpriv'")
        if not isinstance(self.launcher, bool):
            raise DeploymentError(f"launcher {self.launcher!r}: True or False (death_signal_via says how the "
                                  "parent-death signal is set)")


class _Run:
    """One execution of an instance's program."""

    def __init__(self, proc: subprocess.Popen[bytes] | ForkedProcess, run_id: str) -> None:
        self.proc = proc
        self.run_id = run_id
        self.via = ("pool" if proc.pooled else "launcher") if isinstance(proc, ForkedProcess) else "exec"
        self.pid = proc.pid
        self.started_at = time.time()
        self.ready_at: float | None = None
        self.ended_at: float | None = None
        self.returncode: int | None = None
        self.reaped = False  # once True the pid (and process group id) may be reused
        self.watch = ReadyWatch(run_id)  # its readiness line, and the last lines it printed
        self.done = threading.Event()
        self.output_read = threading.Event()  # the reader reached the end of the child's output
        self.not_ready_in_time = False


_Spawned = tuple["subprocess.Popen[bytes] | ForkedProcess", str]  # the process and its run id
# What the spawner thread is asked: a start, "launcher" (start the launcher again) or None (end).
# A start, a launcher to start, idle members to keep (``("pool", spec, size)``), or the end.
_SpawnItem = (tuple["ProcessSpec", "Future[_Spawned]"] | tuple[Literal["pool"], "ProcessSpec", int]
              | Literal["launcher"] | None)


class _Instance:
    def __init__(self, spec: ProcessSpec) -> None:
        self.spec = spec
        self.state: ProcessState = ProcessState.STARTING
        self.run: _Run | None = None
        self.restarts = 0  # since the last stable run
        self.total_restarts = 0
        self.stop_requested = False
        self.detail: str | None = None


class Supervisor:
    """Runs and watches the child processes of one host. ``setup()`` before use."""

    def __init__(self, settings: SupervisorSettings | None = None) -> None:
        self.settings = settings or SupervisorSettings()
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._instances: dict[str, _Instance] = {}
        self._finished: collections.deque[str] = collections.deque()
        self._listeners: list[Callable[[ProcessEvent], None]] = []
        self._spawn_queue: queue.Queue[_SpawnItem] = queue.Queue()
        self._spawner: threading.Thread | None = None
        self._closing = False
        self.launcher: LauncherClient | None = None

    # -- life cycle ---------------------------------------------------------------

    def setup(self) -> None:
        """Start the spawner thread. No child runs before this."""
        if self._spawner is not None:
            return
        if self.settings.death_signal_via == "setpriv" and not shutil.which("setpriv"):
            raise DeploymentError("death_signal_via 'setpriv' needs util-linux's setpriv on PATH")
        self._closing = False
        self._spawner = threading.Thread(target=self._spawn_loop, name="supervisor-spawner", daemon=True)
        self._spawner.start()
        if self.settings.launcher:
            try:
                become_subreaper()  # a forked detector is re-parented to us, so we can wait for it
            except DeploymentError as exc:
                log.warning("%s; detectors start the plain way", exc)
            else:
                parent = os.getpid()
                self.launcher = LauncherClient(
                    python=self.settings.python, death_signal=self.settings.death_signal,
                    preexec=lambda: _child_setup(parent, self.settings.death_signal),
                    schedule_restart=self._schedule_launcher)
                self._spawn_queue.put("launcher")

    def _schedule_launcher(self, delay: float) -> None:
        """Start the launcher again after ``delay`` seconds (on the spawner thread)."""
        def put() -> None:
            if not self._closing and self._spawner is not None:
                self._spawn_queue.put("launcher")

        timer = threading.Timer(delay, put)
        timer.daemon = True
        timer.start()

    def shutdown(self) -> None:
        """Stop every live instance (escalating as configured), then the spawner thread."""
        with self._lock:
            self._closing = True
            live = [name for name, inst in self._instances.items() if inst.state in LIVE_STATES]
        stoppers = [threading.Thread(target=self._stop_quietly, args=(name,), daemon=True) for name in live]
        for t in stoppers:
            t.start()
        for t in stoppers:
            t.join()
        if self.launcher is not None:
            self.launcher.shutdown()
        if self._spawner is not None:
            self._spawn_queue.put(None)
            self._spawner.join(timeout=5)
            self._spawner = None

    def add_listener(self, listener: Callable[[ProcessEvent], None]) -> None:
        """Call ``listener(event)`` for every event from now on (on supervisor threads)."""
        self._listeners.append(listener)

    # -- requests -----------------------------------------------------------------

    def start(self, spec: ProcessSpec, *, wait_ready: bool = True) -> ProcessInfo:
        """Start ``spec``; with ``wait_ready`` return once it is ready.

        Raises DeploymentError when the instance name is taken by a live one or
        the program cannot be started or gives up, ReadinessTimeout when it
        did not print the readiness line in time (it is then stopped).
        """
        with self._lock:
            if self._spawner is None or self._closing:
                raise DeploymentError("supervisor is not running (call setup() first)")
            old = self._instances.get(spec.instance)
            if old is not None and old.state in LIVE_STATES:
                raise DeploymentError(f"instance {spec.instance} is already running (pid {old.run.pid if old.run else '-'})")
            inst = _Instance(spec)
            self._instances[spec.instance] = inst
            if spec.instance in self._finished:
                self._finished.remove(spec.instance)
        try:
            self._launch(inst)
        except DeploymentError as exc:
            with self._lock:
                inst.state, inst.detail = ProcessState.FAILED, str(exc)
                self._remember_finished(spec.instance)
                self._changed.notify_all()
            self._emit(inst, ProcessEventKind.FAILED, detail=str(exc))
            raise
        if not wait_ready:
            return self._info(inst)
        return self.wait_ready(spec.instance)

    def wait_ready(self, instance: str, timeout: float | None = None) -> ProcessInfo:
        """Block until ``instance`` is ready; raise if it ends up stopped, exited or failed."""
        with self._lock:
            inst = self._get(instance)
            spec = inst.spec
            # Bounded even if every restart runs into its readiness timeout.
            if timeout is None:
                attempts = spec.restart.max_restarts + 1
                timeout = attempts * (spec.ready_timeout + spec.restart.backoff_max) + 5.0
            deadline = time.monotonic() + timeout
            while inst.state not in SERVING_STATES and inst.state not in FINAL_STATES:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ReadinessTimeout(f"instance {instance} not ready within {timeout:.1f} s")
                self._changed.wait(left)
            if inst.state in SERVING_STATES:
                return self._info(inst)
            run = inst.run
            if run is not None and run.not_ready_in_time:
                raise ReadinessTimeout(
                    f"instance {instance} did not print {READY_TOKEN} within {spec.ready_timeout:g} s; stopped it"
                )
            why = f": {inst.detail}" if inst.detail else ""
            raise DeploymentError(f"instance {instance} {inst.state} before it was ready{why}")

    def stop(self, instance: str) -> ProcessInfo:
        """Stop ``instance``: SIGINT, SIGTERM, SIGKILL with the spec's timeouts.

        Returns the final snapshot (with the return code). Stopping an instance
        that already ended returns its snapshot; an unknown one raises.
        """
        with self._lock:
            inst = self._get(instance)
            if inst.state not in FINAL_STATES:
                inst.stop_requested = True
                inst.state = ProcessState.STOPPING
                self._changed.notify_all()  # wakes a back-off wait
        while True:
            with self._lock:
                if inst.state in FINAL_STATES:
                    return self._info(inst)
                run = inst.run
            if run is not None and not run.done.is_set():
                self._escalate(inst, run)
            with self._lock:
                # The waiter (or back-off) thread sets the final state; a restart
                # launched meanwhile shows up as a new run and is stopped in turn.
                deadline = time.monotonic() + 5.0
                while inst.state not in FINAL_STATES and inst.run is run:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise DeploymentError(f"instance {instance} did not reach a final state after it exited")
                    self._changed.wait(left)

    def _escalate(self, inst: _Instance, run: _Run) -> None:
        if escalate(lambda sig: self._signal_group(run, sig), run.done.wait, inst.spec.stop,
                    what=f"instance {inst.spec.instance} (pid {run.pid})"):
            return
        raise DeploymentError(
            f"instance {inst.spec.instance} (pid {run.pid}) survived SIGKILL; is it stuck in the kernel?"
        )

    def status(self, instance: str) -> ProcessInfo:
        """The snapshot of one instance; DeploymentError if unknown."""
        with self._lock:
            return self._info(self._get(instance))

    def processes(self, *, include_finished: bool = True) -> list[ProcessInfo]:
        """Snapshots of all instances (live first, then recently finished)."""
        with self._lock:
            infos = [self._info(i) for i in self._instances.values()]
        if not include_finished:
            infos = [i for i in infos if i.live]
        return sorted(infos, key=lambda i: (not i.live, i.instance))

    # -- internals ----------------------------------------------------------------

    def _get(self, instance: str) -> _Instance:
        inst = self._instances.get(instance)
        if inst is None:
            raise DeploymentError(f"no instance {instance!r} on this host")
        return inst

    def _info(self, inst: _Instance) -> ProcessInfo:
        run = inst.run
        return ProcessInfo(
            instance=inst.spec.instance,
            deployment=inst.spec.deployment,
            config=inst.spec.config,
            state=inst.state,
            pid=run.pid if run else None,
            run_id=run.run_id if run else "",
            restarts=inst.total_restarts,
            started_at=run.started_at if run else None,
            ready_at=run.ready_at if run else None,
            ended_at=run.ended_at if run else None,
            returncode=run.returncode if run else None,
            argv=inst.spec.argv,
            detail=inst.detail,
            output=tuple(list(run.watch.tail)[-5:]) if run else (),
            via=run.via if run else "",
        )

    def _remember_finished(self, name: str) -> None:
        # Called with the lock held: forget the oldest final instances beyond the limit.
        if name not in self._finished:
            self._finished.append(name)
        while len(self._finished) > self.settings.keep_finished:
            old = self._finished.popleft()
            inst = self._instances.get(old)
            if inst is not None and inst.state in FINAL_STATES:
                del self._instances[old]

    def _emit(self, inst: _Instance, event: ProcessEventKind, **fields: Any) -> None:  # ProcessEvent's own fields
        run = inst.run
        ev = ProcessEvent(
            event=event,
            instance=inst.spec.instance,
            time=time.time(),
            run_id=run.run_id if run else "",
            pid=fields.pop("pid", run.pid if run else None),
            deployment=inst.spec.deployment,
            config=inst.spec.config,
            **fields,
        )
        log.debug("event %s", ev)
        for listener in list(self._listeners):
            try:
                listener(ev)
            except Exception:  # a listener's bug must not stop supervision
                log.exception("deployer event listener failed on %s", ev)

    def _launch(self, inst: _Instance, *, restart: bool = False) -> None:
        """Spawn one run of ``inst`` (on the spawner thread), report it, start its threads."""
        future: Future[_Spawned] = Future()
        self._spawn_queue.put((inst.spec, future))
        try:
            proc, run_id = future.result(timeout=self.settings.spawn_timeout)
        except OSError as exc:
            raise DeploymentError(f"cannot start instance {inst.spec.instance} ({inst.spec.argv[0]}): {exc}") from exc
        except TimeoutError as exc:  # concurrent.futures.TimeoutError is TimeoutError since 3.11
            raise DeploymentError(f"spawner did not start instance {inst.spec.instance} in time") from exc
        run = _Run(proc, run_id)
        with self._lock:
            inst.run = run
            if not inst.stop_requested:  # a stop that came during the spawn keeps its state
                inst.state = ProcessState.STARTING if inst.spec.await_ready else ProcessState.RUNNING
            if not inst.spec.await_ready:
                run.ready_at = run.started_at
                run.watch.mark_ready()
            self._changed.notify_all()
        # Reported before the reader thread can report "ready".
        self._emit(inst, ProcessEventKind.STARTED)
        if restart:
            self._emit(inst, ProcessEventKind.RESTARTED, detail=f"restart {inst.restarts} of {inst.spec.restart.max_restarts}")
        name = inst.spec.instance
        threading.Thread(target=self._read_output, args=(inst, run), name=f"out-{name}", daemon=True).start()
        threading.Thread(target=self._wait_exit, args=(inst, run), name=f"wait-{name}", daemon=True).start()
        if inst.spec.await_ready:
            threading.Thread(target=self._watch_readiness, args=(inst, run), name=f"ready-{name}", daemon=True).start()

    def _spawn_loop(self) -> None:
        parent = os.getpid()
        while True:
            item = self._spawn_queue.get()
            if item is None:
                return
            if isinstance(item, str):  # "launcher"
                if self.launcher is not None and not self._closing:
                    self.launcher.launch()
                continue
            if len(item) == 3:  # ("pool", spec, size)
                _, spec, size = item
                if self.launcher is not None and not self._closing:
                    self.launcher.fill(spec.argv, self.child_env(spec), spec.cwd, size)
                continue
            spec, future = item
            if not future.set_running_or_notify_cancel():
                continue
            try:
                env = self.child_env(spec)
                forked = self.launcher.fork(spec.argv, env, spec.cwd) if self.launcher is not None else None
                if forked is not None:
                    future.set_result((forked, f"{spec.instance}-{secrets.token_hex(4)}"))
                    continue
                argv = list(spec.argv)
                preexec: Callable[[], None] | None = _child_setup(parent, self.settings.death_signal)
                if self.settings.death_signal_via == "setpriv":
                    name = signal.Signals(self.settings.death_signal).name.removeprefix("SIG")
                    argv, preexec = [shutil.which("setpriv") or "setpriv", f"--pdeathsig={name}", "--", *argv], None
                proc = subprocess.Popen(
                    argv,
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.STDOUT,
                    cwd=spec.cwd,
                    env=env,
                    start_new_session=True,  # own group: our signals reach its children, a terminal's do not
                    preexec_fn=preexec,
                )
            except (OSError, ValueError, subprocess.SubprocessError) as exc:
                future.set_exception(exc if isinstance(exc, OSError) else OSError(str(exc)))
                continue
            future.set_result((proc, f"{spec.instance}-{secrets.token_hex(4)}"))

    @staticmethod
    def child_env(spec: ProcessSpec) -> dict[str, str]:
        """The environment a child of ``spec`` gets."""
        env = dict(os.environ)
        env["PYTHONUNBUFFERED"] = "1"  # a Python child's readiness line must not sit in a pipe buffer
        env.update(dict(spec.env))
        return env

    def keep_pool(self, spec: ProcessSpec, size: int) -> None:
        """Have the launcher keep ``size`` idle members for starts like ``spec`` (on the spawner thread)."""
        if self.launcher is not None and not self._closing:
            self._spawn_queue.put(("pool", spec, int(size)))

    def idle_for(self, spec: ProcessSpec) -> int:
        """The launcher's idle members that could take ``spec``."""
        return self.launcher.idle_for(spec.argv, self.child_env(spec)) if self.launcher is not None else 0

    def pool_key(self, spec: ProcessSpec) -> str | None:
        """What pool members for ``spec`` share with the starts they can take (deploy/launcher.py's
        ``pool_key``); None when the launcher does not fork ``spec`` (not ready, or not its program)."""
        if self.launcher is None or not self.launcher.runs(spec.argv):
            return None
        return pool_key(spec.argv, self.child_env(spec))

    def _read_output(self, inst: _Instance, run: _Run) -> None:
        try:
            self._read_lines(inst, run)
        finally:
            run.output_read.set()

    def _read_lines(self, inst: _Instance, run: _Run) -> None:
        child_log = logging.getLogger(f"{__name__}.{inst.spec.instance}")
        assert run.proc.stdout is not None
        for raw in run.proc.stdout:
            line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
            if run.watch.feed(line) is not None:  # the readiness line (also kept out of the tail)
                with self._lock:
                    run.ready_at = time.time()
                    is_current = inst.run is run and inst.state == ProcessState.STARTING
                    if is_current:
                        inst.state = ProcessState.READY
                        if inst.restarts and inst.detail:
                            inst.detail = None
                    self._changed.notify_all()
                if is_current:
                    self._emit(inst, ProcessEventKind.READY)
                continue
            if line.startswith(CONFIGURED_TOKEN + " ") and inst.spec.config:
                self._reconfigured(inst, line.split()[1:])
            child_log.debug("%s", line)
        run.proc.stdout.close()

    def _reconfigured(self, inst: _Instance, words: list[str]) -> None:
        """The child took another configuration in place: its record, and the argv of a
        restart, name the new one (a child only does so after the graph allowed it)."""
        if len(words) != 2:
            return
        config, deployment = words
        try:
            check_name(config, "configuration")
            check_name(deployment, "deployment")
        except ConfigError:
            return
        argv = list(inst.spec.argv)
        for i, word in enumerate(argv[:-1]):
            if word == "--config" and argv[i + 1] == inst.spec.config:
                argv[i + 1] = config
        with self._lock:
            inst.spec = replace(inst.spec, config=config, deployment=deployment, argv=tuple(argv))
        self._emit(inst, ProcessEventKind.RECONFIGURED)

    def _watch_readiness(self, inst: _Instance, run: _Run) -> None:
        try:
            run.watch.wait(inst.spec.ready_timeout)
            return
        except ReadinessTimeout:
            pass
        except NotReady:  # it exited: _wait_exit decides what follows
            return
        with self._lock:
            if inst.run is not run or inst.stop_requested or run.done.is_set() or run.watch.ready:
                return
            run.not_ready_in_time = True
            inst.stop_requested = True  # no restart: a program that cannot get ready will not by retrying
            inst.state = ProcessState.STOPPING
            inst.detail = f"not ready within {inst.spec.ready_timeout:g} s"
        tail = " | ".join(list(run.watch.tail)[-5:]) or "nothing"
        log.warning("instance %s (pid %s) not ready within %.1f s; stopping it; its last output: %s",
                    inst.spec.instance, run.pid, inst.spec.ready_timeout, tail)
        # SIGINT is skipped: a program that cannot get ready may well be deaf to it.
        escalate(lambda sig: self._signal_group(run, sig), run.done.wait, inst.spec.stop,
                 what=f"instance {inst.spec.instance} (pid {run.pid})", first=signal.SIGTERM)

    def _signal_group(self, run: _Run, sig: int) -> None:
        with self._lock:
            if run.reaped:  # the group id may belong to someone else by now
                return
            try:
                os.killpg(run.pid, sig)
            except ProcessLookupError:
                pass
            except PermissionError as exc:  # the child changed its uid; we cannot do more
                log.error("cannot signal process group %s: %s", run.pid, exc)

    def _wait_exit(self, inst: _Instance, run: _Run) -> None:
        # Wait without reaping: while the leader is a zombie its pid, and so its
        # process group id, cannot be reused, and killpg still hits its children.
        while True:
            try:
                os.waitid(os.P_PID, run.pid, os.WEXITED | os.WNOWAIT)
                break
            except ChildProcessError:
                break
            except InterruptedError:
                continue
        with self._lock:
            try:
                os.killpg(run.pid, signal.SIGKILL)  # leftovers of the group: no orphans
            except (ProcessLookupError, PermissionError):
                pass
            returncode = run.proc.wait()
            run.reaped = True
            run.returncode = returncode
            run.ended_at = time.time()
        run.output_read.wait(OUTPUT_DRAIN_S)  # its last lines (why it crashed) before the report
        run.done.set()
        run.watch.end(returncode)
        tail = "\n".join(list(run.watch.tail)[-5:]) or None
        self._emit(inst, ProcessEventKind.EXITED, returncode=returncode, detail=tail if returncode else None)
        self._after_exit(inst, run, returncode, tail)

    def _after_exit(self, inst: _Instance, run: _Run, returncode: int, tail: str | None) -> None:
        spec = inst.spec
        final: ProcessEventKind | None = None  # FAILED or STOPPED: the run was the instance's last
        with self._lock:
            if inst.run is not run:
                return
            if run.not_ready_in_time:
                inst.state = ProcessState.FAILED
                self._remember_finished(spec.instance)
                self._changed.notify_all()
                final = ProcessEventKind.FAILED
            elif inst.stop_requested:
                inst.state = ProcessState.STOPPED
                self._remember_finished(spec.instance)
                self._changed.notify_all()
                final = ProcessEventKind.STOPPED
            elif returncode == 0:
                inst.state = ProcessState.EXITED
                inst.detail = "exited by itself with status 0"
                self._remember_finished(spec.instance)
                self._changed.notify_all()
                return
            else:
                if (run.ended_at or time.time()) - run.started_at >= spec.restart.stable_after:
                    inst.restarts = 0
                if inst.restarts >= spec.restart.max_restarts or self._closing:
                    inst.state = ProcessState.FAILED
                    inst.detail = f"exited with status {returncode} after {inst.restarts} restarts" + (
                        f"; last output: {tail}" if tail else ""
                    )
                    self._remember_finished(spec.instance)
                    self._changed.notify_all()
                    final = ProcessEventKind.FAILED
                else:
                    inst.restarts += 1
                    inst.total_restarts += 1
                    inst.state = ProcessState.RESTARTING
                    inst.detail = f"exited with status {returncode}; restart {inst.restarts} of {spec.restart.max_restarts}"
                    self._changed.notify_all()
        if final == ProcessEventKind.FAILED:
            self._emit(inst, ProcessEventKind.FAILED, detail=inst.detail)
            return
        if final == ProcessEventKind.STOPPED:
            self._emit(inst, ProcessEventKind.STOPPED, returncode=returncode)
            return
        self._restart_after_backoff(inst)

    def _restart_after_backoff(self, inst: _Instance) -> None:
        delay = inst.spec.restart.delay(inst.restarts)
        deadline = time.monotonic() + delay
        with self._lock:
            while not inst.stop_requested and not self._closing:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._changed.wait(left)
            if inst.stop_requested or self._closing:
                inst.state = ProcessState.STOPPED
                self._remember_finished(inst.spec.instance)
                self._changed.notify_all()
                stopped = True
            else:
                stopped = False
        if stopped:
            self._emit(inst, ProcessEventKind.STOPPED)
            return
        try:
            self._launch(inst, restart=True)
        except DeploymentError as exc:
            with self._lock:
                inst.state, inst.detail = ProcessState.FAILED, str(exc)
                self._remember_finished(inst.spec.instance)
                self._changed.notify_all()
            self._emit(inst, ProcessEventKind.FAILED, detail=str(exc))

    def _stop_quietly(self, name: str) -> None:
        try:
            self.stop(name)
        except DeploymentError as exc:
            log.error("shutdown: %s", exc)
