"""Starting and stopping a child process of ours: one way, for every part that has children.

:class:`ChildProcess` starts a program in its own session (so its group, and
with it anything it forks, can be signalled at once and a terminal's Ctrl-C
reaches only us), reads its stdout on a thread (into a log file and a
:class:`~kgadapt.shared.readiness.ReadyWatch`), waits for its readiness line
(:meth:`ChildProcess.wait_ready`) and stops it the way ros2 launch does:
SIGINT, then SIGTERM, then SIGKILL, each after its own bounded wait
(:func:`escalate`, which the deployer's supervisor uses too).
"""

from __future__ import annotations

import functools
import logging
import os
import queue
import signal
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Callable, Mapping, Sequence

from kgadapt.shared import parent_death
from kgadapt.shared.errors import DeploymentError
from kgadapt.shared.readiness import Payload, ReadyWatch

log = logging.getLogger(__name__)

_ESCALATION = (signal.SIGINT, signal.SIGTERM, signal.SIGKILL)


@dataclass(frozen=True, kw_only=True)
class StopPolicy:
    """Escalation timeouts in seconds: SIGINT, wait, SIGTERM, wait, SIGKILL, wait."""

    sigint_timeout: float = 3.0
    sigterm_timeout: float = 3.0
    sigkill_timeout: float = 5.0

    def steps(self, first: int = signal.SIGINT) -> list[tuple[signal.Signals, float]]:
        """The (signal, wait) steps from ``first`` on (SIGTERM first skips SIGINT)."""
        waits = (self.sigint_timeout, self.sigterm_timeout, self.sigkill_timeout)
        if first not in _ESCALATION:
            raise DeploymentError(f"stop signal {first!r}: use SIGINT, SIGTERM or SIGKILL")
        start = _ESCALATION.index(signal.Signals(first))
        return list(zip(_ESCALATION[start:], waits[start:], strict=True))


# ChildProcess.stop()'s default: an agent stops its own detectors first (up to ~6 s with theirs at 3 s).
AGENT_STOP = StopPolicy(sigint_timeout=10.0, sigterm_timeout=5.0)


def escalate(send: Callable[[int], None], ended: Callable[[float], bool], policy: StopPolicy, *,
             what: str, first: int = signal.SIGINT) -> bool:
    """Signal with ``send`` step by step until ``ended(wait)`` says the process is gone; False if it survived SIGKILL."""
    for sig, wait in policy.steps(first):
        send(sig)
        if ended(wait):
            return True
        log.info("%s still running %.1f s after %s", what, wait, sig.name)
    return False


def stop_process(process: subprocess.Popen[Any], policy: StopPolicy, *, what: str, first: int = signal.SIGINT,
                 group: bool = True) -> int:
    """Stop a child with :func:`escalate` (its process group with ``group``); its exit status.

    DeploymentError if it survived SIGKILL.
    """

    def send(sig: int) -> None:
        if process.poll() is not None:
            return
        try:
            if group:
                os.killpg(process.pid, sig)
            else:
                process.send_signal(sig)
        except ProcessLookupError:
            pass

    def ended(wait: float) -> bool:
        try:
            process.wait(wait)
        except subprocess.TimeoutExpired:
            return False
        return True

    if process.poll() is None and not escalate(send, ended, policy, what=what, first=first):
        raise DeploymentError(f"{what} survived SIGKILL; is it stuck in the kernel?")
    return process.returncode


class ChildProcess:
    """One child process of ours, started at construction, with its output read on a thread.

    ``log``: a file that gets the child's stderr and, with ``log_stdout``, a copy
    of every stdout line too (``append`` keeps what it held). Without ``log``
    stderr is inherited. ``env`` replaces the environment (None: ours).
    ``on_line`` is called (on the reader thread) with every stdout line, then
    with None when the output ends: for children that speak more than readiness.
    ``death_signal`` reaches the child when we die without stopping it (a ``kill -9`` of a test run or a
    bench left their robots running); only for a child started on the main thread, because the kernel
    sends it when the *thread* that started the child ends. None: the child outlives us.
    """

    def __init__(self, argv: Sequence[str], *, name: str, env: Mapping[str, str] | None = None,
                 cwd: str | Path | None = None, log: Path | None = None, log_stdout: bool = True,
                 append: bool = False, stdin: int | IO[Any] | None = subprocess.DEVNULL, keep: int = 50,
                 on_line: Callable[[str | None], None] | None = None,
                 death_signal: int | None = signal.SIGTERM) -> None:
        self.name = name
        self.argv = tuple(argv)
        self.log_path = log
        self.watch = ReadyWatch(name, keep=keep, output=self.last_output)
        self.lines: queue.Queue[str] = queue.Queue()  # every stdout line, for wait_for_line
        self.output: list[str] = []  # every stdout line, with its newline
        self._eof = threading.Event()
        self._on_line = on_line
        self._log: IO[str] | None = open(log, "a" if append else "w") if log is not None else None
        self._log_stdout = log_stdout and self._log is not None
        tie = None  # a preexec_fn
        if death_signal is not None and threading.current_thread() is threading.main_thread():
            tie = functools.partial(parent_death.tie_to_parent, os.getpid(), death_signal)
        try:
            self.process = subprocess.Popen(
                list(argv), stdout=subprocess.PIPE, stderr=self._log, stdin=stdin, text=True, errors="replace", cwd=cwd,
                env=dict(env) if env is not None else None, start_new_session=True, preexec_fn=tie)
        except (OSError, ValueError, subprocess.SubprocessError) as exc:
            if self._log is not None:
                self._log.close()
            raise DeploymentError(f"cannot start {name} ({argv[0] if argv else '(no program)'}): {exc}") from exc
        threading.Thread(target=self._read, name=f"{name}-stdout", daemon=True).start()
        threading.Thread(target=self._reap, name=f"{name}-wait", daemon=True).start()

    @property
    def pid(self) -> int:
        return self.process.pid

    def _read(self) -> None:
        assert self.process.stdout is not None
        try:
            for line in self.process.stdout:
                self.output.append(line)
                self.lines.put(line)
                self.watch.feed(line)
                if self._log_stdout and self._log is not None:
                    self._log.write(line)
                    self._log.flush()
                if self._on_line is not None:
                    self._on_line(line)
        except (OSError, ValueError):  # the pipe closed under us while stopping
            pass
        finally:
            self._eof.set()
            if self._on_line is not None:
                self._on_line(None)

    def _reap(self) -> None:
        returncode = self.process.wait()
        # Lines still in the pipe count: the readiness line may be the last thing it printed.
        # Bounded, since a grandchild may hold the pipe open after the child itself is gone.
        self._eof.wait(2.0)
        self.watch.end(returncode)
        if self._log is not None and self._eof.is_set():
            self._log.close()

    # -- readiness --------------------------------------------------------------------

    def wait_ready(self, timeout: float) -> Payload:
        """The child's readiness payload; NotReady (exited) or ReadinessTimeout, naming it and its last lines."""
        return self.watch.wait(timeout)

    def wait_for_line(self, text: str, timeout: float = 30.0) -> str:
        """The next stdout line containing ``text`` (human lines, not readiness; lines are consumed)."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise DeploymentError(f"{self.name}: no line with {text!r} within {timeout:g} s; "
                                      f"last output:\n{self.last_output()}")
            try:
                line = self.lines.get(timeout=min(left, 0.2))
            except queue.Empty:
                if self.watch.ended:
                    raise DeploymentError(f"{self.name} exited with status {self.watch.returncode}; "
                                          f"last output:\n{self.last_output()}") from None
                continue
            if text in line:
                return line

    def last_output(self) -> str:
        """What errors show: the log's last lines, or stdout's and then stderr's."""
        if self.log_path is None or self._log_stdout:
            return self.tail()
        return f"{self.watch.last_lines()}\nstderr ({self.log_path}):\n{self.tail()}"

    def tail(self, n: int = 15) -> str:
        """The last ``n`` lines of its log (stdout lines when there is no log)."""
        if self.log_path is None:
            return "".join(self.output[-n:]).rstrip("\n") or "(no output)"
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return "(no log)"

    # -- stopping ---------------------------------------------------------------------

    def alive(self) -> bool:
        return self.process.poll() is None

    def wait(self, timeout: float | None = None) -> int:
        """Its exit status once it has exited by itself and its output is read (TimeoutExpired after ``timeout``)."""
        returncode = self.process.wait(timeout)
        self._eof.wait(2.0)
        return returncode

    def send_signal(self, sig: int) -> None:
        """Send ``sig`` to the child's whole process group (nothing if it is gone)."""
        if self.process.poll() is not None:
            return
        try:
            os.killpg(self.process.pid, sig)
        except ProcessLookupError:
            pass

    def stop(self, policy: StopPolicy | None = None, *, first: int = signal.SIGINT) -> int:
        """SIGINT, SIGTERM, SIGKILL (from ``first`` on) to its group, each with a bounded wait; the exit status."""
        returncode = stop_process(self.process, policy or AGENT_STOP, what=f"{self.name} (pid {self.pid})", first=first)
        self._eof.wait(2.0)
        if self._log is not None and not self._log.closed and self._eof.is_set():
            self._log.close()
        return returncode

    def __enter__(self) -> "ChildProcess":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
