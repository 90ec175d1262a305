"""Commands to the autopilot that are acknowledged: COMMAND_LONG out, COMMAND_ACK back, bounded retries.

MAVLink's command protocol: the sender repeats a COMMAND_LONG (with
``confirmation`` counting the repeats) until a COMMAND_ACK for that command
comes back. :class:`CommandSender` does that on a thread of its own, so the
link's reader and ticker never wait: ``submit()`` returns a
:class:`PendingCommand` at once; ``result(timeout)`` waits for the outcome.

Outcomes (:class:`CommandOutcome`): ``ACCEPTED``; a refusal the autopilot
stated (``DENIED``, ``FAILED``, ``UNSUPPORTED``, or ``TEMPORARILY_REJECTED``
once the retries are spent) — kept in :attr:`CommandSender.refusals` and
logged as a warning; ``NO_ACK`` when no acknowledgement came after every attempt.
``IN_PROGRESS`` extends the wait without a resend. Every acknowledgement that
rejects a command is logged at INFO when it comes and counted
(``counters["rejected"]``, ``on_rejected``), so a rejection whose retry is
accepted still shows.
"""

from __future__ import annotations

import enum
import logging
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

from pymavlink.dialects.v20 import common as mavlink2

from kgadapt.shared.errors import FlightLinkError

log = logging.getLogger(__name__)


class CommandOutcome(enum.Enum):
    ACCEPTED = "accepted"
    TEMPORARILY_REJECTED = "temporarily_rejected"
    DENIED = "denied"
    UNSUPPORTED = "unsupported"
    FAILED = "failed"
    CANCELLED = "cancelled"
    NO_ACK = "no_ack"

    @property
    def refused(self) -> bool:
        return self is not CommandOutcome.ACCEPTED


_RESULTS = {
    mavlink2.MAV_RESULT_ACCEPTED: CommandOutcome.ACCEPTED,
    mavlink2.MAV_RESULT_TEMPORARILY_REJECTED: CommandOutcome.TEMPORARILY_REJECTED,
    mavlink2.MAV_RESULT_DENIED: CommandOutcome.DENIED,
    mavlink2.MAV_RESULT_UNSUPPORTED: CommandOutcome.UNSUPPORTED,
    mavlink2.MAV_RESULT_FAILED: CommandOutcome.FAILED,
    getattr(mavlink2, "MAV_RESULT_CANCELLED", 6): CommandOutcome.CANCELLED,
}


def command_name(command: int) -> str:
    entry = mavlink2.enums["MAV_CMD"].get(command)
    return entry.name.removeprefix("MAV_CMD_") if entry is not None else str(command)


@dataclass(frozen=True, kw_only=True)
class CommandSettings:
    """How long to wait for an acknowledgement and how often to try."""

    first_wait_s: float = 0.5  # wait before the first resend ...
    backoff: float = 2.0  # ... then 1, 2 s: four attempts cover 7.5 s
    attempts: int = 4
    in_progress_wait_s: float = 5.0  # how long an IN_PROGRESS ack holds off a resend
    refusals_kept: int = 20

    def __post_init__(self) -> None:
        if self.first_wait_s <= 0 or self.backoff < 1 or self.attempts < 1:
            raise FlightLinkError("command retry settings: first_wait_s > 0, backoff >= 1, attempts >= 1")


@dataclass(frozen=True)
class Refusal:
    time: float  # epoch seconds
    command: str  # e.g. "SET_MESSAGE_INTERVAL"
    label: str  # what it was for, e.g. "ATTITUDE at 10 Hz"
    outcome: CommandOutcome

    def __str__(self) -> str:
        return f"{self.command}({self.label}): {self.outcome.value}"


class PendingCommand:
    """One command on its way; ``result(timeout)`` blocks until its outcome is known."""

    def __init__(self, command: int, params: tuple[float, ...], target: tuple[int, int], label: str) -> None:
        self.command = command
        self.params = params
        self.target = target
        self.label = label
        self.attempts = 0
        self.outcome: CommandOutcome | None = None
        self._done = threading.Event()
        self._ack: int | None = None
        self._acked = threading.Event()

    def result(self, timeout: float | None = None) -> CommandOutcome:
        if not self._done.wait(timeout):
            raise FlightLinkError(f"command {command_name(self.command)} ({self.label}) still pending")
        return self.outcome  # type: ignore[return-value]  # set before _done is

    @property
    def done(self) -> bool:
        return self._done.is_set()


SendFn = Callable[[object], None]


class CommandSender:
    """Sends COMMAND_LONGs one after the other, each until acknowledged or out of attempts."""

    def __init__(self, settings: CommandSettings, *, encoder: Callable[[], mavlink2.MAVLink | None], send: SendFn,
                 on_refusal: Callable[[Refusal], None] | None = None,
                 on_rejected: Callable[[], None] | None = None,
                 alive: Callable[[], bool] = lambda: True) -> None:
        self.settings = settings
        self._alive = alive  # False while the link is down: no point waiting for acks then
        # The same command twice in the queue is sent once: (command, params, target) -> the one queued.
        self._queued: dict[tuple[int, tuple[float, ...], tuple[int, int]], PendingCommand] = {}
        self._encoder = encoder  # returns the link's MAVLink object (None while closed)
        self._send = send
        self._on_refusal = on_refusal
        self._on_rejected = on_rejected  # every rejecting acknowledgement, final or not
        self._queue: queue.SimpleQueue[PendingCommand | None] = queue.SimpleQueue()
        self._current: PendingCommand | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.refusals: deque[Refusal] = deque(maxlen=settings.refusals_kept)
        self.counters = {"sent": 0, "resent": 0, "accepted": 0, "refused": 0, "no_ack": 0, "rejected": 0}

    def setup(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="mavlink-commands", daemon=True)
        self._thread.start()

    def shutdown(self) -> None:
        self._stop.set()
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def submit(self, command: int, params: tuple[float, ...], target: tuple[int, int], *,
               label: str = "") -> PendingCommand:
        if len(params) > 7:
            raise FlightLinkError(f"command {command_name(command)} takes at most 7 parameters")
        full = tuple(float(p) for p in params) + (0.0,) * (7 - len(params))
        key = (command, full, target)
        with self._lock:
            queued = self._queued.get(key)
            if queued is not None and not queued.done:
                return queued
            pending = PendingCommand(command, full, target, label)
            self._queued[key] = pending
        self._queue.put(pending)
        return pending

    def on_ack(self, message: mavlink2.MAVLink_command_ack_message) -> None:
        """A COMMAND_ACK from the autopilot (called on the reader thread: only signals)."""
        with self._lock:
            current = self._current
        if current is not None and message.command == current.command:
            current._ack = message.result
            current._acked.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            pending = self._queue.get()
            if pending is None:
                continue
            with self._lock:
                self._current = pending
            try:
                outcome = self._drive(pending)
            finally:
                with self._lock:
                    self._current = None
                    self._queued.pop((pending.command, pending.params, pending.target), None)
            self._finish(pending, outcome)

    def _drive(self, pending: PendingCommand) -> CommandOutcome:
        s = self.settings
        wait = s.first_wait_s
        last = CommandOutcome.NO_ACK
        for attempt in range(s.attempts):
            if self._stop.is_set() or not self._alive():
                return CommandOutcome.NO_ACK
            pending._acked.clear()
            pending.attempts = attempt + 1
            mav = self._encoder()
            if mav is None:
                return CommandOutcome.NO_ACK
            try:
                self._send(mav.command_long_encode(
                    pending.target[0], pending.target[1], pending.command, min(attempt, 255), *pending.params))
                self.counters["sent" if attempt == 0 else "resent"] += 1
            except FlightLinkError as exc:
                log.debug("command %s not sent: %s", command_name(pending.command), exc)
            deadline = time.monotonic() + wait
            while True:
                if not pending._acked.wait(max(0.0, deadline - time.monotonic())):
                    break  # no ack in time: resend
                result = pending._ack
                pending._acked.clear()
                if result == mavlink2.MAV_RESULT_IN_PROGRESS:
                    deadline = time.monotonic() + s.in_progress_wait_s
                    continue
                last = _RESULTS.get(result, CommandOutcome.FAILED)
                if last is not CommandOutcome.ACCEPTED:
                    self._rejected(pending, last, retry_in=wait if last is CommandOutcome.TEMPORARILY_REJECTED
                                   and attempt + 1 < s.attempts else None)
                if last is CommandOutcome.TEMPORARILY_REJECTED:
                    break  # try again after the back-off
                return last
            if last is CommandOutcome.TEMPORARILY_REJECTED:
                self._stop.wait(wait)
            wait *= s.backoff
        return last

    def _rejected(self, pending: PendingCommand, outcome: CommandOutcome, *, retry_in: float | None) -> None:
        self.counters["rejected"] += 1
        what = f"{command_name(pending.command)}({pending.label})"
        if retry_in is not None:
            log.info("autopilot rejected %s: %s (attempt %d); trying again in %.1f s", what, outcome.value,
                     pending.attempts, retry_in)
        else:
            log.info("autopilot rejected %s: %s (attempt %d)", what, outcome.value, pending.attempts)
        if self._on_rejected is not None:
            try:
                self._on_rejected()
            except Exception:  # a listener's bug must not stop the command thread
                log.exception("command rejection listener failed")

    def _finish(self, pending: PendingCommand, outcome: CommandOutcome) -> None:
        pending.outcome = outcome
        name = command_name(pending.command)
        if outcome is CommandOutcome.ACCEPTED:
            self.counters["accepted"] += 1
        else:
            self.counters["no_ack" if outcome is CommandOutcome.NO_ACK else "refused"] += 1
            refusal = Refusal(time.time(), name, pending.label, outcome)
            self.refusals.append(refusal)
            spent = " (retries spent)" if outcome in (CommandOutcome.TEMPORARILY_REJECTED, CommandOutcome.NO_ACK) else ""
            log.warning("autopilot did not accept %s after %d attempt(s)%s", refusal, pending.attempts, spent)
            if self._on_refusal is not None:
                try:
                    self._on_refusal(refusal)
                except Exception:  # a listener's bug must not stop the command thread
                    log.exception("command refusal listener failed")
        pending._done.set()
