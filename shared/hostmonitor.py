"""The host monitor: an agent part that publishes this host's memory and CPU.

What it publishes (``host_status`` on ``kgadapt/<robot>/host/<host>/status``)::

    memory_total_mb   the budget when one is given, else the machine's total memory
    memory_free_mb    budget - our process tree's RSS - reservation   (with a budget)
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
import logging
import os
import queue
import re
import threading
import time
from dataclasses import dataclass
from typing import Any

import psutil

from shared import keys, messages
from shared.errors import ConfigError, MessageError, RemoteError, RequestTimeout

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


def check_status(host: str, body: dict[str, Any]) -> dict[str, Any]:
    """``body`` (a decoded ``host_status`` received on host ``host``'s key) if it is plausible, else MessageError.

    One rule for everyone who acts on statuses (the knowledge service, the
    adaptation manager): the body names the host of its key, no figure is
    negative, free memory is within the total, a host has at least one core.
    """
    if body["host"] != host:
        raise MessageError(f"host_status on the key of host {host!r} names host {body['host']!r}")
    for name in ("memory_total_mb", "memory_free_mb", "cpu_load"):
        if body[name] < 0:
            raise MessageError(f"host_status field {name!r} is negative ({body[name]})")
    if body["memory_free_mb"] > body["memory_total_mb"]:
        raise MessageError(f"host_status of {host}: {body['memory_free_mb']} MiB free of {body['memory_total_mb']} MiB total")
    cores = body.get("cpu_cores")
    if cores is not None and cores < 1:
        raise MessageError(f"host_status field 'cpu_cores' must be at least 1, got {cores}")
    return body


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
        self._requests: queue.Queue[Any] = queue.Queue(maxsize=64)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._publisher: Any = None
        self._queryable: Any = None
        self._me: psutil.Process | None = None  # looked up on first use: __init__ does no I/O
        self._last: dict[str, Any] | None = None
        self.published = 0

    # -- measurements -------------------------------------------------------

    def ours_mb(self) -> float:
        """RSS of this process and all its descendants, in MiB."""
        if self._me is None:
            self._me = psutil.Process(os.getpid())
        total = 0
        try:
            procs = [self._me, *self._me.children(recursive=True)]
        except psutil.Error:
            procs = [self._me]
        for proc in procs:
            try:
                total += proc.memory_info().rss
            except psutil.Error:  # a child may exit between listing and reading
                continue
        return total / MIB

    def free_mb(self) -> float:
        """Free memory now, as ``sample()`` would publish it (for the deployer's start check)."""
        s = self.settings
        if s.memory_budget_mb is not None:
            return max(0.0, s.memory_budget_mb - self.ours_mb() - self._reserved_mb)
        return max(0.0, psutil.virtual_memory().available / MIB - self._reserved_mb)

    def sample(self) -> dict[str, Any]:
        """One ``host_status`` body measured now."""
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
        body: dict[str, Any] = {
            "host": s.host,
            "time": time.time(),
            "memory_total_mb": round(total, 1),
            "memory_free_mb": round(max(0.0, free), 1),
            "cpu_load": round(cpu_load, 1),
            "cpu_cores": cores,
            "ours_mb": round(ours, 1),
            "reserved_mb": round(self._reserved_mb, 1),
        }
        if s.memory_budget_mb is not None:
            body["budget_mb"] = s.memory_budget_mb
        return body

    # -- part life cycle ----------------------------------------------------

    def setup(self, session: Any) -> None:
        """Declare the status publisher and the squeeze queryable; start sampling."""
        s = self.settings
        psutil.cpu_percent(interval=None)  # prime: the first call always says 0.0
        self._publisher = session.declare_publisher(keys.host_status(s.robot, s.host))
        self._queryable = session.declare_queryable(squeeze_key(s.robot, s.host), self._on_squeeze)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"hostmonitor-{s.host}", daemon=True)
        self._thread.start()
        budget = f"budget {s.memory_budget_mb:.0f} MiB" if s.memory_budget_mb else "no budget (machine memory)"
        log.info("host monitor for %s: publishing status at %.1f Hz, %s", s.host, s.rate_hz, budget)

    def shutdown(self) -> None:
        """Stop sampling and undeclare."""
        self._stop.set()
        try:
            self._requests.put_nowait(None)  # wake the sampler now rather than after one interval
        except queue.Full:
            pass
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        for entity in (self._queryable, self._publisher):
            if entity is not None:
                try:
                    entity.undeclare()
                except Exception as exc:  # the session may already be closed
                    log.debug("undeclare failed: %s", exc)
        self._queryable = self._publisher = None
        self._drain_requests()

    # -- internals ----------------------------------------------------------

    def _on_squeeze(self, query: Any) -> None:
        # Zenoh callback: no Zenoh calls here, only hand the query to the sampler thread.
        try:
            self._requests.put_nowait(query)
        except queue.Full:
            log.warning("squeeze dropped: too many pending squeeze requests")

    def _run(self) -> None:
        period = 1.0 / self.settings.rate_hz
        next_due = 0.0
        while not self._stop.is_set():
            try:
                query = self._requests.get(timeout=self.settings.sample_interval)
            except queue.Empty:
                query = None
            if self._stop.is_set():
                break
            try:
                if query is not None:
                    self._answer_squeeze(query)
                    next_due = time.monotonic() + period
                    continue
                body = self.sample()
                now = time.monotonic()
                if now >= next_due or self._moved(body):
                    self._publish(body)
                    next_due = now + period
            except Exception:  # the monitor must outlive one bad sample
                log.exception("host monitor: sample or publish failed")

    def _moved(self, body: dict[str, Any]) -> bool:
        last = self._last
        if last is None:
            return True
        return (
            abs(body["memory_free_mb"] - last["memory_free_mb"]) >= self.settings.memory_change_mb
            or abs(body["cpu_load"] - last["cpu_load"]) >= self.settings.cpu_change
        )

    def _publish(self, body: dict[str, Any]) -> None:
        self._publisher.put(messages.encode("host_status", body))
        self._last = body
        self.published += 1

    def _answer_squeeze(self, query: Any) -> None:
        try:
            try:
                payload = query.payload
                if payload is None:
                    raise MessageError("squeeze_request has no payload")
                request = messages.decode(payload.to_bytes(), "squeeze_request")
                reserve = float(request["reserve_mb"])
                if reserve < 0:
                    raise MessageError(f"squeeze_request field 'reserve_mb' must not be negative, got {reserve}")
            except MessageError as exc:
                log.warning("squeeze refused: %s", exc)
                query.reply_err(str(exc))
                return
            self._reserved_mb = reserve
            body = self.sample()
            self._publish(body)
            log.info("squeeze: reserving %.0f MiB on %s, free now %.0f MiB", reserve, body["host"], body["memory_free_mb"])
            query.reply(squeeze_key(self.settings.robot, self.settings.host), messages.encode("host_status", body))
        finally:
            query.drop()

    def _drain_requests(self) -> None:
        while True:
            try:
                query = self._requests.get_nowait()
            except queue.Empty:
                return
            if query is not None:
                query.drop()


def squeeze(session: Any, robot: str, host: str, reserve_mb: float, *, timeout: float = 2.0) -> dict[str, Any]:
    """Ask ``host``'s monitor to reserve ``reserve_mb`` MiB; return the status it then published."""
    key = squeeze_key(robot, host)
    payload = messages.encode("squeeze_request", {"reserve_mb": float(reserve_mb)})
    for reply in session.get(key, payload=payload, timeout=timeout):
        if reply.ok is not None:
            return messages.decode(reply.ok.payload.to_bytes(), "host_status")
        text = reply.err.payload.to_bytes().decode("utf-8", "replace")
        if text == "Timeout":
            raise RequestTimeout(f"squeeze on {key}: no answer within {timeout} s")
        raise RemoteError(f"squeeze on {key}: {text}")
    raise RequestTimeout(f"squeeze on {key}: no host monitor answered within {timeout} s (is the agent of {host!r} running?)")


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
