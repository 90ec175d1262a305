"""The agent skeleton: one Zenoh session, a liveliness token, and a list of parts.

An agent (``kgadapt onboard``, ``kgadapt remote``) is a host's resident
process. What it does lives in *parts*: objects with ``setup(session)`` and
``shutdown()`` (the host monitor now; camera, MAVLink bridge, deployer and
adaptation manager later). The agent opens the session, sets the parts up in
order, and only then declares ``kgadapt/<robot>/host/<host>/alive``, so that a
host seen alive is a host ready to serve. Shutdown goes the other way: token
first (everyone sees the host leave), parts in reverse order, session last.

The session's lease (shared/session.py, 1000 ms) is what makes a hung or
cut-off agent disappear from everyone's liveliness view within about a
second; a killed one disappears at once (its sockets close).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Protocol

from kgadapt.shared import keys, rpc
from kgadapt.shared.errors import KgadaptError, TransportError
from kgadapt.shared.session import DEFAULT_ENDPOINT, ZenohSettings, open_session
from kgadapt.shared.session import add_arguments as add_zenoh_arguments
from kgadapt.shared.session import settings_from_args as zenoh_settings_from_args

log = logging.getLogger(__name__)

DEFAULT_ROBOT = keys.DEFAULT_ROBOT  # kept here: deploy/deployer.py, onboard/ import it from kgadapt.shared.agent


class Part(Protocol):
    """Something an agent runs. ``__init__`` does no I/O."""

    name: str

    def setup(self, session: Any) -> None:
        """Declare what the part needs on ``session`` and start its threads; raise on failure."""

    def shutdown(self) -> None:
        """Undo ``setup``; must not raise, must be safe after a failed or partial setup."""


@dataclass(frozen=True, kw_only=True)
class AgentSettings:
    """Who the agent is and how it reaches the others."""

    robot: str = DEFAULT_ROBOT
    host: str
    role: str  # "onboard" | "remote": what the logs call it
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    give_up_s: float | None = None  # exit after this long without reaching the router (None: keep trying)

    def __post_init__(self) -> None:
        keys.check_name(self.robot, "robot name")
        keys.check_name(self.host, "host name")


class ConnectionWatch:
    """Says, every ``every_s``, when the session reaches no router and no peer, and when it does again.

    A peer session opens even when its router is not there (``kgadapt remote --connect`` to a
    port nobody listens on used to print "ready" and wait forever, silently). With ``give_up_s``
    the agent is told to stop after that long unreachable (``on_give_up``).
    """

    def __init__(self, *, what: str, endpoints: Iterable[str], every_s: float = 5.0, grace_s: float = 2.0,
                 give_up_s: float | None = None, on_give_up: Callable[[], None] | None = None) -> None:
        self.what, self.endpoints = what, list(endpoints)
        self.every_s, self.grace_s, self.give_up_s, self.on_give_up = every_s, grace_s, give_up_s, on_give_up
        self.unreachable_s = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def setup(self, session: Any) -> None:
        self._thread = threading.Thread(target=self._run, args=(session,), name="connection-watch", daemon=True)
        self._thread.start()

    def _connected(self, session: Any) -> bool:
        try:
            return bool(list(session.info.routers_zid()) or list(session.info.peers_zid()))
        except Exception:  # noqa: BLE001 - session closing
            return True

    def _run(self, session: Any) -> None:
        import time

        lost_at: float | None = None
        said_at = 0.0
        while not self._stop.wait(0.25):
            now = time.monotonic()
            if self._connected(session):
                if lost_at is not None and now - lost_at >= self.grace_s:
                    log.warning("%s: reached %s again", self.what, ", ".join(self.endpoints) or "the network")
                lost_at, self.unreachable_s = None, 0.0
                continue
            lost_at = now if lost_at is None else lost_at
            self.unreachable_s = now - lost_at
            if self.unreachable_s >= self.grace_s and now - said_at >= self.every_s:
                said_at = now
                log.warning("%s: cannot reach the router at %s for %.0f s (is `kgadapt knowledge serve` running "
                            "there?); still trying", self.what, ", ".join(self.endpoints) or "(none configured)",
                            self.unreachable_s)
            if self.give_up_s is not None and self.unreachable_s >= self.give_up_s and self.on_give_up is not None:
                log.error("%s: giving up after %.0f s without the router (--give-up-after)", self.what, self.unreachable_s)
                self.on_give_up()
                return

    def shutdown(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None


class Agent:
    """A host's agent: session, liveliness token and parts."""

    def __init__(self, settings: AgentSettings, parts: Iterable[Part] = ()) -> None:
        self.settings = settings
        self.parts: list[Part] = list(parts)
        self.session: Any = None
        self._token: Any = None
        self._ready: list[Part] = []
        self._watch: ConnectionWatch | None = None
        self.gave_up = threading.Event()

    def _give_up(self) -> None:
        self.gave_up.set()
        os.kill(os.getpid(), signal.SIGTERM)  # the main thread's StopSignals ends the agent as on a stop

    def add(self, part: Part) -> None:
        """Add a part before ``setup()``."""
        if self.session is not None:
            raise KgadaptError(f"cannot add part {part.name!r}: agent {self.settings.host} is already set up")
        self.parts.append(part)

    def setup(self) -> None:
        """Open the session, set the parts up, then declare the liveliness token.

        On failure everything already set up is undone and the error raised.
        """
        s = self.settings
        self.session = open_session(s.zenoh)
        # Started before the parts: a part waiting for the knowledge service is then not silent.
        self._watch = ConnectionWatch(what=f"{s.role} agent {s.host} of robot {s.robot}", endpoints=s.zenoh.connect,
                                      give_up_s=s.give_up_s, on_give_up=self._give_up)
        self._watch.setup(self.session)
        try:
            for part in self.parts:
                log.info("%s agent %s: setting up %s", s.role, s.host, part.name)
                part.setup(self.session)
                self._ready.append(part)
            self._token = self.session.liveliness().declare_token(keys.host_alive(s.robot, s.host))
        except BaseException:
            self.shutdown()
            raise
        log.info("%s agent %s of robot %s is alive with %d part(s)", s.role, s.host, s.robot, len(self._ready))

    def healthy(self) -> bool:
        """Every part set up reports healthy (a part without ``healthy()`` counts as healthy)."""
        if self.session is None:
            return False
        return all(getattr(part, "healthy", lambda: True)() for part in list(self._ready))

    def shutdown(self) -> None:
        """Drop the token, shut the parts down in reverse order, close the session."""
        if self._token is not None:
            rpc.undeclare_quietly(self._token)
            self._token = None
        if self._watch is not None:
            self._watch.shutdown()
            self._watch = None
        while self._ready:
            part = self._ready.pop()
            t0 = time.monotonic()
            try:
                part.shutdown()
            except Exception:  # one part's failure must not keep the others running
                log.exception("%s agent %s: shutting down %s failed", self.settings.role, self.settings.host, part.name)
            else:
                log.info("%s agent %s: stopped %s in %.2f s", self.settings.role, self.settings.host, part.name,
                         time.monotonic() - t0)
        if self.session is not None:
            try:
                self.session.close()
            except Exception as exc:  # noqa: BLE001 - stopping: the session may be closed already
                log.debug("session close failed: %s", exc)
            self.session = None
            log.info("%s agent %s stopped", self.settings.role, self.settings.host)


class StopSignals:
    """Turn SIGINT and SIGTERM into an event for the main thread (restored on exit)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.event = threading.Event()
        self.received: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> "StopSignals":
        for sig in self.SIGNALS:
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def _handle(self, signum: int, _frame: Any) -> None:
        self.received = signum
        self.event.set()

    def wait(self, tick: Callable[[], None] | None = None) -> None:
        """Wait for a signal, calling ``tick`` about twice a second meanwhile (the watchdog)."""
        # A timed wait keeps the main thread responsive to signals on every Python.
        while not self.event.wait(0.5):
            if tick is not None:
                tick()


def add_agent_arguments(parser: argparse.ArgumentParser, *, default_host: str, give_up: bool = True) -> None:
    """``--robot``, ``--host`` and the Zenoh flags of an agent command; ``give_up``: and ``--give-up-after``, for a
    command that keeps trying to reach the router (an agent), not one that asks once (squeeze)."""
    parser.add_argument("--robot", default=DEFAULT_ROBOT, help=f"robot name, the key namespace (default {DEFAULT_ROBOT})")
    parser.add_argument("--host", default=default_host,
                        help=f"this host's name, as the models call its Platform (default {default_host})")
    if give_up:
        parser.add_argument("--give-up-after", type=float, default=None, metavar="S",
                            help="exit (status 1) after S seconds without reaching the router (default: keep "
                                 "trying, saying so every 5 s)")
    add_zenoh_arguments(parser)


def agent_settings_from_args(args: argparse.Namespace, *, role: str) -> AgentSettings:
    """Agents are peers connecting to the knowledge service's router unless told otherwise."""
    zenoh = zenoh_settings_from_args(args).with_defaults(mode="peer", connect=[DEFAULT_ENDPOINT])
    return AgentSettings(robot=args.robot, host=args.host, role=role, zenoh=zenoh,
                         give_up_s=getattr(args, "give_up_after", None))


def run_agent(agent: Agent, *, announce: Callable[[str], None] | None = None) -> int:
    """Set up, announce readiness (stdout and systemd), wait for SIGINT/SIGTERM, shut down.

    Under systemd (``Type=notify``) the watchdog is fed only while every part
    is healthy, so a hung or broken agent is restarted, not only a dead one.
    """
    from kgadapt.shared.allocator import cap_arenas
    from kgadapt.shared.notifier import ServiceNotifier
    from kgadapt.shared.readiness import announce_ready

    cap_arenas()  # before the agent's threads (shared/allocator.py)
    s = agent.settings
    notifier = ServiceNotifier()
    with StopSignals() as stop:
        agent.setup()
        try:
            line = (
                f"{s.role} agent ready: robot {s.robot}, host {s.host}, "
                f"zenoh {s.zenoh.mode} connect {list(s.zenoh.connect)}"
            )
            (announce or _print_flush)(line)  # for people; machines wait on the readiness line
            announce_ready(status=line, notifier=notifier, role=s.role, robot=s.robot, host=s.host)

            def tick() -> None:
                if agent.healthy():
                    notifier.watchdog()

            stop.wait(tick=tick)
            log.info("%s agent %s: signal %s, stopping", s.role, s.host, stop.received)
        finally:
            t0 = time.monotonic()
            notifier.stopping()
            agent.shutdown()
            log.info("%s agent %s stopped everything in %.2f s", s.role, s.host, time.monotonic() - t0)
    if agent.gave_up.is_set():
        raise TransportError(f"{s.role} agent {s.host} of robot {s.robot}: no router reached at "
                             f"{', '.join(s.zenoh.connect) or '(none configured)'} within {s.give_up_s:g} s")
    return 0


def _print_flush(line: str) -> None:
    print(line, flush=True)
    sys.stdout.flush()
