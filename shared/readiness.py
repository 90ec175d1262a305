"""The one readiness protocol of kgadapt's processes.

A process of ours says it is ready with one call, :func:`announce_ready`, which

- sends ``READY=1`` (and a ``STATUS=`` line) to ``$NOTIFY_SOCKET`` when it is
  set: systemd's ``Type=notify`` (sd_notify(3), see :mod:`.notifier`);
- writes one line on stdout: the token :data:`READY_TOKEN`, a space and a JSON
  object (the *payload*, always with the process's ``pid``), for example
  ``KGADAPT_READY {"pid":4711,"role":"onboard","robot":"quad1"}``.

Whoever starts a child of ours (the deployer's supervisor, the robot harness,
tests, benchmarks) waits on that line with :class:`ReadyWatch`: it is fed the
child's output lines, and :meth:`ReadyWatch.wait` returns the payload or
raises :class:`NotReady` (the child exited first) or :class:`ReadinessTimeout`,
naming the child and its last output lines. A bare token line (no payload) is
ready too, with an empty payload: programs that are not Python can print it.

Human-readable lines ("onboard agent ready: ...") are for people; machines
wait on this protocol only. This module is the one place that spells the token.
"""

from __future__ import annotations

import collections
import json
import os
import sys
import threading
from typing import Any, Callable, TextIO

from kgadapt.shared.errors import NotReady, ReadinessTimeout
from kgadapt.shared.notifier import ServiceNotifier

READY_TOKEN = "KGADAPT_READY"
# "<token> <config> <deployment>": a detector took another configuration in place (deploy/supervisor.py).
CONFIGURED_TOKEN = "KGADAPT_CONFIGURED"
# Set to "1" in a started process's environment: start idle (a detector's warm standby does no detection
# work and publishes nothing until it is activated). Its deployer sets it for a start request with idle.
START_IDLE_ENV = "KGADAPT_START_IDLE"
# A started detector's configuration as its deployer resolved it from the graph (a ``resolved_config``
# message, base64): the detector takes it instead of asking the knowledge service again.
RESOLVED_CONFIG_ENV = "KGADAPT_RESOLVED_CONFIG"
# An idle pool member's environment only (deploy/launcher.py): the deployments, comma-separated, whose starts
# it may take on its host, so it prepares each one's reflex table while it waits.
POOL_DEPLOYMENTS_ENV = "KGADAPT_POOL_DEPLOYMENTS"

Payload = dict[str, Any]

# Lines a child tells its parent on stdout are written whole, one write() each, under this lock: print()
# writes the text and its newline separately, so another thread's line could land between them (a
# detector's reflex recorded a swap while it announced itself ready, and the parent never saw the
# readiness line: it began in the middle of the other).
_STDOUT_LINES = threading.Lock()


def say_line(text: str, out: TextIO | None = None) -> None:
    """Write ``text`` and its newline to stdout (or ``out``) in one write, whole, and flush (a pipe would
    hold the line back)."""
    stream = out or sys.stdout
    with _STDOUT_LINES:
        stream.write(text + "\n")
        stream.flush()


def announce_configured(config: str, deployment: str, *, out: TextIO | None = None) -> None:
    """Tell the parent (the deployer's supervisor) that this detector took ``config`` of ``deployment``."""
    say_line(f"{CONFIGURED_TOKEN} {config} {deployment}", out)


def ready_line(**payload: Any) -> str:
    """The readiness line for ``payload`` (this process's pid added)."""
    return _line({"pid": os.getpid(), **payload})


def _line(fields: Payload) -> str:
    return f"{READY_TOKEN} {json.dumps(fields, separators=(',', ':'), default=str)}"


def announce_ready(*, status: str = "", notifier: ServiceNotifier | None = None, out: TextIO | None = None,
                   **payload: Any) -> Payload:
    """Tell systemd (when it started us) and our parent (stdout) that this process is ready.

    ``status`` is the human summary systemd shows; ``payload`` are small JSON
    values for the parent. Returns the payload sent, pid included.
    """
    fields: Payload = {"pid": os.getpid(), **payload}
    (notifier or ServiceNotifier()).ready(status=status)
    say_line(_line(fields), out)
    return fields


def parse_ready(line: str) -> Payload | None:
    """The payload if ``line`` is a readiness line, else None.

    A token followed by anything but a JSON object is not a readiness line (and
    so is never mistaken for one).
    """
    text = line.strip()
    if text == READY_TOKEN:
        return {}
    if not text.startswith(READY_TOKEN + " "):
        return None
    try:
        payload = json.loads(text[len(READY_TOKEN) + 1:])
    except ValueError:
        return None
    return payload if isinstance(payload, dict) else None


class ReadyWatch:
    """Watches one child's output for its readiness line; keeps its last lines for error messages.

    Feed it every line the child prints (:meth:`feed`, from the thread that reads
    its stdout) and tell it when the child has ended (:meth:`end`, after the
    last line was fed). :meth:`wait` may be called from any thread. ``output``
    describes the child's last output for errors (default: its last stdout
    lines), e.g. from a log file that also has its stderr.
    """

    def __init__(self, name: str, *, keep: int = 20, output: Callable[[], str] | None = None) -> None:
        self.name = name
        self._output = output
        self.payload: Payload | None = None
        self.returncode: int | None = None
        self.ended = False
        self.tail: collections.deque[str] = collections.deque(maxlen=keep)
        self._cond = threading.Condition()

    @property
    def ready(self) -> bool:
        return self.payload is not None

    def feed(self, line: str) -> Payload | None:
        """Take one output line; returns the payload when this line made the child ready."""
        payload = parse_ready(line) if self.payload is None else None
        with self._cond:
            if payload is None:
                self.tail.append(line.rstrip("\r\n"))
                return None
            self.payload = payload
            self._cond.notify_all()
        return payload

    def mark_ready(self, payload: Payload | None = None) -> None:
        """Ready without a line (a program that is not expected to print one)."""
        with self._cond:
            if self.payload is None:
                self.payload = dict(payload or {})
                self._cond.notify_all()

    def end(self, returncode: int | None) -> None:
        with self._cond:
            self.ended, self.returncode = True, returncode
            self._cond.notify_all()

    def last_lines(self, n: int = 10) -> str:
        with self._cond:
            lines = list(self.tail)[-n:]
        return "\n".join(lines) if lines else "(no output)"

    def wait(self, timeout: float) -> Payload:
        """The payload, once the child is ready; NotReady if it ended first, ReadinessTimeout after ``timeout`` s."""
        with self._cond:
            self._cond.wait_for(lambda: self.payload is not None or self.ended, timeout)
            payload, ended, returncode = self.payload, self.ended, self.returncode
        if payload is not None:
            return payload
        output = self._output() if self._output is not None else self.last_lines()
        if ended:
            raise NotReady(f"{self.name} exited with status {returncode} before it printed {READY_TOKEN}; "
                           f"last output:\n{output}")
        raise ReadinessTimeout(f"{self.name} did not print {READY_TOKEN} within {timeout:g} s; last output:\n{output}")
