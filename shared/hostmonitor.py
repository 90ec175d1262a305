"""The host monitor: an agent part that publishes this host's memory and CPU.

What it publishes (``host_status`` on ``kgadapt/<robot>/host/<host>/status``)::

    memory_total_mb   the budget when one is given, else the machine's total memory
    memory_free_mb    budget - our process tree's RSS - reservation   (with a budget; the launcher's
                      idle pool members left out: they yield to a start)
                      the machine's available memory - reservation    (without)
    cpu_load          machine CPU load in percent of one core (2 busy cores = 200)
    cpu_cores         logical CPUs
    budget_mb, ours_mb, reserved_mb   the figures free memory was computed from

It samples every ``sample_interval`` seconds, publishes every ``1 / rate_hz``
seconds, and publishes at once when free memory or CPU load moved by more
than a threshold since the last publication, or when a squeeze changes the
reservation.

The memory budget is how two agents on one machine behave as two different
hosts: each declares what it gives to our processes and counts only its own
process tree (itself and its children) against it.

Squeeze: the queryable ``kgadapt/<robot>/host/<host>/squeeze`` takes a
``squeeze_request {reserve_mb}`` and sets an extra reservation subtracted from
free memory (0 lifts it); it answers with the ``host_status`` just published.
Tests and the demo use it to make a host "run out" of memory on cue
(:func:`squeeze` here, ``kgadapt squeeze`` on the command line).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import re
import secrets
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Collection

import msgspec
import psutil

from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.errors import ConfigError, MessageError, NoResponder, RemoteError, RequestTimeout
from kgadapt.shared.process_tree import ProcessTree

log = logging.getLogger(__name__)

MIB = 1024 * 1024
_SIZE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([kmgt]?)(?:i?b)?\s*$", re.IGNORECASE)
_UNIT_MIB = {"": 1.0, "k": 1 / 1024, "m": 1.0, "g": 1024.0, "t": 1024.0 * 1024.0}


def parse_size_mb(text: str, *, allow_zero: bool = False) -> float:
    """``"512M"``, ``"2G"``, ``"1.5GiB"``, ``"300"`` (MiB) -> MiB; raise ConfigError otherwise."""
    match = _SIZE.match(str(text))
    if not match:
        raise ConfigError(f"memory size {text!r}: use a number with an optional unit K, M, G or T (e.g. 512M, 2G)")
    value = float(match.group(1)) * _UNIT_MIB[match.group(2).lower()]
    if value == 0 and not allow_zero:
        raise ConfigError(f"memory size {text!r} must be more than zero")
    return value


def check_status(host: str, body: messages.HostStatus) -> messages.HostStatus:
    """``body`` (a decoded ``host_status`` received on host ``host``'s key) if it is plausible, else MessageError.

    One rule for everyone who acts on statuses (the knowledge service, the
    adaptation manager): the body names the host of its key, no figure is
    negative, free memory is within the total, a host has at least one core.
    """
    if body.host != host:
        raise MessageError(f"host_status on the key of host {host!r} names host {body.host!r}")
    for name, value in (("memory_total_mb", body.memory_total_mb), ("memory_free_mb", body.memory_free_mb),
                        ("cpu_load", body.cpu_load)):
        if value < 0:
            raise MessageError(f"host_status field {name!r} is negative ({value})")
    if body.memory_free_mb > body.memory_total_mb:
        raise MessageError(f"host_status of {host}: {body.memory_free_mb} MiB free of {body.memory_total_mb} MiB total")
    cores = body.cpu_cores
    if cores is not None and cores < 1:
        raise MessageError(f"host_status field 'cpu_cores' must be at least 1, got {cores}")
    return body


@dataclass(frozen=True, kw_only=True)
class TrustSettings:
    """How much a consumer of statuses believes them (see :class:`StatusTrust`)."""

    window_s: float = 2.5  # a figure counts when every accepted status of this window agrees with it
    min_statuses: int = 2  # ... and the window holds at least this many (else the last this many of stale_s)
    stale_s: float = 5.0  # a status this much older than the host's newest accepted one is refused
    total_slack: float = 0.05  # a total this much above the host's first total since its token came up is refused
    profile_slack: float = 0.25  # free memory may overlap its processes' recorded RSS this much (shared pages)
    require_alive: bool = True  # refuse statuses of a host whose liveliness token is absent
    new_source_s: float = 5.0  # statuses of a host from a new sender count once it alone has spoken this long
    contest_s: float = 15.0  # after two senders interleave on one host, none of its statuses count this long
    max_statuses: int = 128  # kept per host at most: a monitor sends 2 a second, 10 at most when its figures jump

    def __post_init__(self) -> None:
        if not self.window_s > 0 or self.min_statuses < 1 or not self.stale_s > 0:
            raise ConfigError(f"status trust: window {self.window_s!r} s, {self.min_statuses!r} statuses and "
                              f"staleness {self.stale_s!r} s must all be positive")
        if self.max_statuses < self.min_statuses:
            raise ConfigError(f"status trust: max_statuses {self.max_statuses!r} is below min_statuses "
                              f"{self.min_statuses!r}")


@dataclass
class _HostTrust:
    alive: bool = False
    total_mb: float | None = None  # the first total since the token came up: a host's total does not grow
    newest: float | None = None  # the newest accepted status's own time
    # (received, free) of accepted statuses, oldest first. Bounded by count as well as by age: a sender that
    # floods its host's key costs each admit the same as one that keeps to its rate.
    recent: deque[tuple[float, float]] = field(default_factory=deque)
    source: str | None = None  # the sender whose statuses count (its ``origin``; "" for a sender without one)
    seq: int | None = None  # that sender's last sequence number
    current_heard: float = 0.0  # when that sender last spoke
    candidate: str | None = None  # another sender, on probation
    candidate_since: float = 0.0
    contested_until: float = 0.0
    frozen: list[float] = field(default_factory=list)  # the window's figures when the contest began


class StatusTrust:
    """What one consumer (knowledge service, adaptation manager) believes of each host's statuses.

    A host status is only a claim: a bug, a stale clock or a process holding
    this robot's certificate can say anything on a host's key. :meth:`admit`
    refuses (MessageError) a status that contradicts what is known: besides
    :func:`check_status`, a status of a host without a liveliness token, a
    status far older than the host's newest, a total above the host's total,
    free memory that the RSS of the host's own running processes (their
    profiles) shows as used, a sequence number that does not grow (or is left
    out under the origin of a sender that numbers its statuses). A status
    from another sender than the host's current one (each monitor sends its
    random ``origin`` and a ``seq``) counts only once that sender alone has
    spoken for ``new_source_s`` (a restarted monitor); if the current sender
    speaks again meanwhile, two senders interleave, and for ``contest_s`` the
    host's figures stay what they were before (none of its statuses counts): a
    forger beside a real monitor holds the detector where it is, whichever of
    them lags. And no single status decides: :meth:`confirmed_free`
    is the least free memory of the last ``window_s`` (so one roomy forgery
    between real statuses is outvoted), :meth:`roomiest` the most (so one
    "full" forgery is), each only with ``min_statuses`` statuses in the window.
    Not thread-safe: one worker owns it.
    """

    def __init__(self, settings: TrustSettings = TrustSettings()) -> None:
        self.settings = settings
        self._hosts: dict[str, _HostTrust] = {}
        self.refused = 0

    def alive(self, host: str, alive: bool) -> None:
        """The host's liveliness token came (a new session: its figures start afresh) or went."""
        record = self._host(host)
        if alive and not record.alive:
            self._hosts[host] = self._record(alive=True)
        else:
            record.alive = alive
            if not alive:
                record.recent.clear()

    def admit(self, host: str, body: messages.HostStatus, *, received: float,
              used_mb: float = 0.0) -> messages.HostStatus:
        """``body`` if it is believable, else MessageError saying why (counted in ``refused``).

        ``used_mb``: what the host's running processes are recorded to hold (their profiles' RSS).
        """
        s = self.settings
        try:
            check_status(host, body)
            record = self._host(host)
            if s.require_alive and not record.alive:
                raise MessageError(f"host_status of {host}: the host has no liveliness token")
            stamp = float(body.time)
            if record.newest is not None and stamp < record.newest - s.stale_s:
                raise MessageError(f"host_status of {host}: measured {record.newest - stamp:.1f} s before its "
                                   f"newest status (stale or replayed)")
            total, free = float(body.memory_total_mb), float(body.memory_free_mb)
            if record.total_mb is not None and total > record.total_mb * (1 + s.total_slack):
                raise MessageError(f"host_status of {host}: total {total:.0f} MiB above the host's "
                                   f"{record.total_mb:.0f} MiB")
            self._check_used(host, record, body, used_mb)
            self._check_sender(host, record, body, received)
        except MessageError:
            self.refused += 1
            raise
        if record.total_mb is None:
            record.total_mb = total
        record.newest = stamp if record.newest is None else max(record.newest, stamp)
        recent, oldest = record.recent, received - max(s.window_s, s.stale_s)
        while recent and recent[0][0] <= oldest:
            recent.popleft()
        recent.append((received, free))  # the deque's maxlen drops the oldest of a flood
        return body

    def check_held(self, host: str, body: messages.HostStatus, *, used_mb: float) -> None:
        """Raise MessageError (counted in ``refused``) when ``body``, admitted before, claims more free
        memory than the host's running processes, recorded to hold ``used_mb``, leave."""
        try:
            self._check_used(host, self._host(host), body, used_mb)
        except MessageError:
            self.refused += 1
            raise

    def _record(self, *, alive: bool = False) -> _HostTrust:
        return _HostTrust(alive=alive, recent=deque(maxlen=self.settings.max_statuses))

    def _host(self, host: str) -> _HostTrust:
        """The host's record, made on first use (without building one per call when it exists)."""
        record = self._hosts.get(host)
        if record is None:
            record = self._hosts[host] = self._record()
        return record

    def _check_used(self, host: str, record: _HostTrust, body: messages.HostStatus, used_mb: float) -> None:
        total, free = float(body.memory_total_mb), float(body.memory_free_mb)
        known_total = total if record.total_mb is None else record.total_mb
        if used_mb > 0 and free > known_total - used_mb * (1 - self.settings.profile_slack):
            raise MessageError(f"host_status of {host}: {free:.0f} MiB free of {known_total:.0f} MiB, but its "
                               f"running processes hold {used_mb:.0f} MiB")

    def _check_sender(self, host: str, record: _HostTrust, body: messages.HostStatus, received: float) -> None:
        """Raise MessageError unless this status's sender is the host's current one (or takes over)."""
        s = self.settings
        origin = body.origin or ""
        seq = body.seq
        if not isinstance(origin, str) or (seq is not None and (not isinstance(seq, int) or isinstance(seq, bool))):
            raise MessageError(f"host_status of {host}: origin must be a string and seq an integer")
        if record.source is None or (record.candidate == origin and received - record.candidate_since >= s.new_source_s
                                     and record.current_heard < record.candidate_since):
            if record.source is not None:
                log.warning("host %s: statuses now come from sender %r (the last one was silent for %.1f s)",
                            host, origin, received - record.current_heard)
                record.recent.clear()  # the old sender's figures are not this one's
            record.source, record.seq, record.candidate = origin, None, None
        if origin == record.source:
            if seq is None and record.seq is not None:
                # A monitor numbers every status: one without a number under a numbering sender's origin is
                # another sender that copied the (public) origin.
                self._contest(record, received)
                raise MessageError(f"host_status of {host}: no seq from sender {origin!r}, which numbers its "
                                   "statuses (a second sender with its origin)")
            if seq is not None and record.seq is not None and seq <= record.seq:
                self._contest(record, received)
                raise MessageError(f"host_status of {host}: seq {seq} not after {record.seq} from sender "
                                   f"{origin!r} (replayed, or a second sender with its origin)")
            if record.candidate is not None:
                # The current sender is alive beside the new one: two senders on one key.
                self._contest(record, received)
                log.warning("host %s: two senders of its statuses (%r and %r); none counts for %.0f s",
                            host, record.source, record.candidate, s.contest_s)
                record.candidate = None
            record.current_heard = received
            if seq is not None:
                record.seq = seq
            return
        if record.candidate != origin:
            record.candidate, record.candidate_since = origin, received
        raise MessageError(f"host_status of {host}: from sender {origin!r}, not the host's {record.source!r}: "
                           f"counted once it alone has spoken for {s.new_source_s:g} s")

    def _contest(self, record: _HostTrust, now: float) -> None:
        """Hold the host's figures as they were: a forger must not make the drone's own host unconfirmed
        (no target: the detector would go remote) any more than move it with false figures."""
        if now >= record.contested_until:
            record.frozen = self._frees(record, now) or []
        record.contested_until = now + self.settings.contest_s

    def _window(self, host: str, now: float) -> list[float] | None:
        record = self._hosts.get(host)
        if record is None or (self.settings.require_alive and not record.alive):
            return None
        if now < record.contested_until:
            return record.frozen or None
        return self._frees(record, now)

    def _frees(self, record: _HostTrust, now: float) -> list[float] | None:
        s = self.settings
        frees = [f for t, f in record.recent if t > now - s.window_s]
        if len(frees) < s.min_statuses:
            # Statuses come late on a loaded machine: then the last ``min_statuses`` of the last
            # ``stale_s`` seconds. Still never one status alone.
            late = [f for t, f in record.recent if t > now - s.stale_s]
            frees = late[-s.min_statuses:]
        return frees if len(frees) >= s.min_statuses else None

    def confirmed_free(self, host: str, now: float) -> float | None:
        """The least free memory the host's statuses of the window show; None: not confirmed."""
        frees = self._window(host, now)
        return min(frees) if frees else None

    def roomiest(self, host: str, now: float) -> float | None:
        """The most free memory the host's statuses of the window show (a shortage must hold in all); None: not confirmed."""
        frees = self._window(host, now)
        return max(frees) if frees else None


def squeeze_key(robot: str, host: str) -> str:
    """The squeeze queryable of one host.

    Built here because shared/keys.py has no entry for it yet (asked for in the
    Zenoh fabric report); it follows the same rules: names are checked chunks.
    """
    return f"{keys.robot_root(robot)}/host/{keys.check_name(host, 'host')}/squeeze"


@dataclass(frozen=True, kw_only=True)
class HostMonitorSettings:
    """How the host monitor samples and publishes."""

    robot: str
    host: str
    rate_hz: float = 2.0
    memory_budget_mb: float | None = None
    sample_interval: float = 0.1
    memory_change_mb: float = 32.0  # publish at once when free memory moves this much
    cpu_change: float = 50.0  # ... or CPU load moves this many percent of one core

    def __post_init__(self) -> None:
        keys.check_name(self.robot, "robot name")
        keys.check_name(self.host, "host name")
        if not self.rate_hz > 0:
            raise ConfigError(f"status rate {self.rate_hz!r} Hz must be more than zero")
        if self.memory_budget_mb is not None and not self.memory_budget_mb > 0:
            raise ConfigError(f"memory budget {self.memory_budget_mb!r} MiB must be more than zero")
        if not self.sample_interval > 0:
            raise ConfigError(f"sample interval {self.sample_interval!r} s must be more than zero")


class HostMonitor:
    """Agent part: samples memory and CPU with psutil and publishes ``host_status``."""

    name = "host monitor"

    def __init__(self, settings: HostMonitorSettings) -> None:
        self.settings = settings
        self._reserved_mb = 0.0
        self._lock = threading.Lock()  # sampling and publishing: the sampler thread and the squeeze worker
        self._next_due = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._publisher: Any = None
        self._stack = contextlib.ExitStack()
        self._tree: ProcessTree | None = None  # looked up on first use: __init__ does no I/O
        self._last: messages.HostStatus | None = None
        self.published = 0
        # Who sends (random per monitor life) and in which order: consumers tell a second sender on this
        # host's key (a forger, a replay) from this monitor by them (StatusTrust).
        self.origin = secrets.token_hex(4)
        # Pids of processes of ours that give their memory back when a start needs it (the launcher's idle
        # pool members: a start takes one, or the pool is made smaller): left out of ``ours_mb``, so free
        # memory is what a start can have. Set by the agent once its deployer exists.
        self.yielding: Callable[[], Collection[int]] | None = None

    # -- measurements -------------------------------------------------------

    def ours_mb(self, *, exact: bool = False) -> float:
        """RSS of this process and all its descendants, in MiB (but the ``yielding`` ones). ``exact``: walk every
        process of the machine rather than read the tree's own children lists (shared/process_tree.py)."""
        if self._tree is None:
            self._tree = ProcessTree(os.getpid())
        left_out = set(self.yielding()) if self.yielding is not None else set()
        return self._tree.rss_bytes(left_out=left_out, exact=exact) / MIB

    def free_mb(self) -> float:
        """Free memory now, as ``sample()`` would publish it (for the deployer's start check)."""
        s = self.settings
        if s.memory_budget_mb is not None:
            # A start is decided on it: the exact reading (about 1 ms), not the sampler's quick one.
            return max(0.0, s.memory_budget_mb - self.ours_mb(exact=True) - self._reserved_mb)
        available: float = psutil.virtual_memory().available
        return max(0.0, available / MIB - self._reserved_mb)

    def budget_mb(self) -> float:
        """What this host gives our processes in all: the budget, else the machine's memory (the deployer
        fits the memory the graph declares for its processes into it)."""
        if self.settings.memory_budget_mb is not None:
            return self.settings.memory_budget_mb
        total: float = psutil.virtual_memory().total
        return total / MIB

    def sample(self) -> messages.HostStatus:
        """One ``host_status`` measured now (its sender's ``origin`` and ``seq`` are set when it is published)."""
        s = self.settings
        cores = psutil.cpu_count() or 1
        cpu_load = psutil.cpu_percent(interval=None) * cores
        ours = self.ours_mb()
        if s.memory_budget_mb is not None:
            total = s.memory_budget_mb
            free = s.memory_budget_mb - ours - self._reserved_mb
        else:
            vm = psutil.virtual_memory()
            total = vm.total / MIB
            free = vm.available / MIB - self._reserved_mb
        return messages.HostStatus(
            host=s.host, time=time.time(), memory_total_mb=round(total, 1), memory_free_mb=round(max(0.0, free), 1),
            cpu_load=round(cpu_load, 1), cpu_cores=cores, ours_mb=round(ours, 1),
            reserved_mb=round(self._reserved_mb, 1), budget_mb=s.memory_budget_mb,
        )

    # -- part life cycle ----------------------------------------------------

    def setup(self, session: Any) -> None:
        """Declare the status publisher and the squeeze queryable; start sampling."""
        s = self.settings
        psutil.cpu_percent(interval=None)  # prime: the first call always says 0.0
        with contextlib.ExitStack() as stack:
            self._publisher = rpc.declared(stack, session.declare_publisher(keys.host_status(s.robot, s.host)))
            server = stack.enter_context(rpc.Server(f"host monitor {s.host}", workers=1, max_pending=64))
            server.serve(session, squeeze_key(s.robot, s.host), self._answer_squeeze, what="squeeze")
            stack.callback(server.undeclare)
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"hostmonitor-{s.host}", daemon=True)
            self._thread.start()
            stack.callback(self._stop_sampling)
            self._stack = stack.pop_all()
        budget = f"budget {s.memory_budget_mb:.0f} MiB" if s.memory_budget_mb else "no budget (machine memory)"
        log.info("host monitor for %s: publishing status at %.1f Hz, %s", s.host, s.rate_hz, budget)

    def shutdown(self) -> None:
        """Stop sampling and undeclare."""
        self._stack.close()
        self._publisher = None

    # -- internals ----------------------------------------------------------

    def _stop_sampling(self) -> None:
        self._stop.set()  # wakes the sampler now rather than after one interval
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def _run(self) -> None:
        period = 1.0 / self.settings.rate_hz
        while not self._stop.wait(self.settings.sample_interval):
            try:
                with self._lock:  # a squeeze publishes too
                    body = self.sample()
                    now = time.monotonic()
                    if now >= self._next_due or self._moved(body):
                        self._publish(body)
                        self._next_due = now + period
            except Exception:  # the monitor must outlive one bad sample
                log.exception("host monitor: sample or publish failed")

    def _moved(self, body: messages.HostStatus) -> bool:
        last = self._last
        if last is None:
            return True
        return bool(
            abs(body.memory_free_mb - last.memory_free_mb) >= self.settings.memory_change_mb
            or abs(body.cpu_load - last.cpu_load) >= self.settings.cpu_change
        )

    def _publish(self, body: messages.HostStatus) -> messages.HostStatus:
        sent = msgspec.structs.replace(body, origin=self.origin, seq=self.published)
        self._publisher.put(messages.encode(sent))
        self._last = sent
        self.published += 1
        return sent

    def _answer_squeeze(self, request: rpc.Request) -> rpc.Reply:
        # On the squeeze server's worker; a MessageError is answered with reply_err naming the field.
        if request.payload is None:
            raise MessageError("squeeze_request has no payload")
        reserve = messages.decode_as(request.payload, messages.SqueezeRequest).reserve_mb
        if reserve < 0:
            raise MessageError(f"squeeze_request field 'reserve_mb' must not be negative, got {reserve}")
        with self._lock:
            self._reserved_mb = reserve
            status = self._publish(self.sample())
            self._next_due = time.monotonic() + 1.0 / self.settings.rate_hz
        log.info("squeeze: reserving %.0f MiB on %s, free now %.0f MiB", reserve, status.host, status.memory_free_mb)
        return rpc.Reply(key=squeeze_key(self.settings.robot, self.settings.host),
                         payload=messages.encode(status))


def squeeze(session: Any, robot: str, host: str, reserve_mb: float, *, timeout: float = 2.0) -> messages.HostStatus:
    """Ask ``host``'s monitor to reserve ``reserve_mb`` MiB; return the status it then published."""
    key = squeeze_key(robot, host)
    payload = messages.encode(messages.SqueezeRequest(reserve_mb=float(reserve_mb)))
    try:
        return rpc.call(session, key, payload, lambda data: messages.decode_as(data, messages.HostStatus), timeout=timeout)
    except RemoteError as exc:
        raise RemoteError(f"squeeze on {key}: {exc}") from exc
    except NoResponder as exc:
        raise NoResponder(f"squeeze on {key}: no host monitor answered within {timeout} s "
                          f"(is the agent of {host!r} running?)") from exc
    except RequestTimeout as exc:
        raise RequestTimeout(f"squeeze on {key}: no answer within {timeout} s") from exc


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--memory-budget`` and ``--status-rate`` for agent commands."""
    group = parser.add_argument_group("host monitor")
    group.add_argument(
        "--memory-budget", metavar="SIZE",
        help="memory this host gives to our processes, e.g. 512M or 2G (default: the machine's free memory)",
    )
    group.add_argument("--status-rate", type=float, default=2.0, metavar="HZ", help="status publication rate (default 2)")


def settings_from_args(args: argparse.Namespace, *, robot: str, host: str) -> HostMonitorSettings:
    budget = parse_size_mb(args.memory_budget) if getattr(args, "memory_budget", None) else None
    return HostMonitorSettings(robot=robot, host=host, rate_hz=args.status_rate, memory_budget_mb=budget)
