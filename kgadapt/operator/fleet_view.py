"""``kgadapt fleet``: every robot on the network at a glance, live.

One row per robot: whether its knowledge service answers, its online hosts,
the running detector configuration and its host, the illumination band that
configuration is made for, the last adaptation decision and its age.

Where it comes from, all read-only:

- fleet questions (knowledge/fleet.py), all four sent together each refresh:
  ``current_placement``, ``platforms``, ``decisions`` (the newest) and
  ``detector_configs`` (for the band of the running configuration);
- what the robots publish, when the network lets it through (a robot's own
  router does not, for other robots: see docs/fleet.md): host liveliness
  tokens on ``kgadapt/*/host/*/alive`` and decisions as they happen on
  ``kgadapt/*/adaptation/events``. Either makes the view refresh at once.

It declares no queryable, publishes nothing and sends no write.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any

from kgadapt.shared import keys, messages, rpc

CLEAR = "\x1b[H\x1b[2J"


@dataclass(frozen=True, kw_only=True)
class FleetViewSettings:
    """How the fleet view asks and refreshes."""

    timeout: float = 1.5  # per refresh, for every robot's answers
    interval: float = 2.0  # seconds between refreshes when nothing happens
    expect: tuple[str, ...] = ()  # robots to list even when they never answered
    roster: str | None = None  # also list the robots this robot's fleet roster remembers
    subscribe: bool = True  # also listen to host liveliness and adaptation events


@dataclass(frozen=True, kw_only=True)
class RobotStatus:
    """One robot as the view shows it."""

    robot: str
    answering: bool
    hosts_online: tuple[str, ...] = ()
    config: str | None = None
    host: str | None = None
    band: str | None = None
    decision_time: float | None = None
    decision_trigger: str | None = None
    decision_choice: str | None = None  # config@host
    decision_outcome: str | None = None

    def decision_age_s(self, now: float) -> float | None:
        return None if self.decision_time is None else max(0.0, now - self.decision_time)


class FleetView:
    """The fleet's state. ``setup()`` subscribes, ``snapshot()`` asks, ``shutdown()`` undeclares."""

    def __init__(self, session: Any, settings: FleetViewSettings = FleetViewSettings()) -> None:
        from kgadapt.knowledge.fleet import FleetClient, FleetSettings

        self.session = session
        self.settings = settings
        self.fleet = FleetClient(session, FleetSettings(timeout=settings.timeout, expect=settings.expect,
                                                          roster=settings.roster))
        self.changed = threading.Event()  # set by a liveliness change or an adaptation event
        self._lock = threading.Lock()
        self._alive: dict[str, set[str]] = {}  # robot -> hosts with a live token
        self._events: dict[str, messages.AdaptationEvent] = {}  # robot -> newest adaptation event
        self._stack = contextlib.ExitStack()

    def setup(self) -> None:
        """Subscribe to host liveliness (with history) and adaptation events of every robot."""
        if not self.settings.subscribe:
            return
        with contextlib.ExitStack() as stack:
            rpc.declared(stack, self.session.liveliness().declare_subscriber(
                f"{keys.PREFIX}/*/host/*/alive", self._on_alive, history=True))
            rpc.declared(stack, self.session.declare_subscriber(f"{keys.PREFIX}/*/adaptation/events", self._on_event))
            self._stack = stack.pop_all()

    def shutdown(self) -> None:
        self._stack.close()

    # Zenoh callbacks: record and signal, nothing else.
    def _on_alive(self, sample: Any) -> None:
        import zenoh

        parts = str(sample.key_expr).split("/")
        if len(parts) != 5:
            return
        robot, host = parts[1], parts[3]
        with self._lock:
            hosts = self._alive.setdefault(robot, set())
            if sample.kind == zenoh.SampleKind.PUT:
                hosts.add(host)
            else:
                hosts.discard(host)
        self.changed.set()

    def _on_event(self, sample: Any) -> None:
        from kgadapt.shared.errors import MessageError

        robot = str(sample.key_expr).split("/")[1]
        try:
            event = messages.decode_as(sample.payload.to_bytes(), messages.AdaptationEvent)
        except MessageError:
            return  # not ours to judge; the robot's own tools log it
        with self._lock:
            previous = self._events.get(robot)
            if previous is None or event.time >= previous.time:
                self._events[robot] = event
        self.changed.set()

    def snapshot(self) -> list[RobotStatus]:
        """Ask the fleet (four named queries in one round trip) and merge what was published."""
        self.changed.clear()
        placement, platforms, decisions, configs = self.fleet.ask_many([
            ("current_placement", None), ("platforms", None), ("decisions", {"limit": 1}),
            ("detector_configs", None)])
        with self._lock:
            alive = {r: set(h) for r, h in self._alive.items()}
            events = dict(self._events)
        robots = set(placement.answered) | set(r.robot for r in placement.robots) | set(alive) | set(events)
        out = []
        for robot in sorted(robots):
            p = placement.answer_of(robot)
            answering = robot in placement.answered
            place = p.rows[0] if p is not None and p.rows else {}
            plat = platforms.answer_of(robot)
            online = set(alive.get(robot, set()))
            if plat is not None:
                online |= {row["platform"] for row in plat.rows if row.get("online")}
            bands = {row.get("config"): row.get("band") for row in (configs.answer_of(robot) or _NONE).rows}
            dec = decisions.answer_of(robot)
            last = dec.rows[0] if dec is not None and dec.rows else {}
            d_time, d_trigger = last.get("time"), last.get("trigger")
            d_choice = _choice(last.get("config"), last.get("host"))
            d_outcome = last.get("outcome")
            event = events.get(robot)
            if event is not None and (d_time is None or event.time > d_time):
                detail = event.decision or messages.Decision()
                d_time, d_trigger = event.time, event.trigger
                d_choice, d_outcome = _choice(detail.config, detail.host), event.outcome
            config = place.get("config")
            out.append(RobotStatus(
                robot=robot, answering=answering, hosts_online=tuple(sorted(online)), config=config,
                host=place.get("host"), band=bands.get(config), decision_time=d_time, decision_trigger=d_trigger,
                decision_choice=d_choice, decision_outcome=d_outcome))
        return out

    def __enter__(self) -> "FleetView":
        self.setup()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


class _NoAnswer:
    rows: tuple[dict[str, Any], ...] = ()


_NONE = _NoAnswer()


def _choice(config: str | None, host: str | None) -> str | None:
    return None if config is None else f"{config}@{host or '?'}"


def render(robots: list[RobotStatus], now: float | None = None) -> str:
    """The view as a plain text table."""
    from kgadapt.knowledge.store import rows_as_table

    now = time.time() if now is None else now
    rows = []
    for r in robots:
        age = r.decision_age_s(now)
        rows.append({
            "robot": r.robot, "knowledge": "answers" if r.answering else "SILENT",
            "hosts online": ", ".join(r.hosts_online) or "-", "config": r.config, "on": r.host, "band": r.band,
            "last decision": (f"{r.decision_trigger} -> {r.decision_choice or 'no change'}"
                              if r.decision_trigger else None),
            "age": _age(age),
        })
    silent = sum(1 for r in robots if not r.answering)
    head = f"{len(robots)} robots, {len(robots) - silent} answering, {silent} silent  ({time.strftime('%H:%M:%S')})"
    return head + "\n" + (rows_as_table(rows) if rows else "(no robot seen yet)")


def as_json(robots: list[RobotStatus], now: float | None = None) -> list[dict[str, Any]]:
    now = time.time() if now is None else now
    return [{**asdict(r), "hosts_online": list(r.hosts_online), "decision_age_s": r.decision_age_s(now)}
            for r in robots]


def _age(seconds: float | None) -> str | None:
    if seconds is None:
        return None
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def register(subparsers: Any) -> None:
    """Add ``kgadapt fleet``."""
    from kgadapt.shared.session import add_arguments as add_zenoh_arguments

    p = subparsers.add_parser(
        "fleet",
        help="every robot on the network: hosts, running configuration, band, last decision (live)",
        description="Show every robot of the fleet, refreshing: online hosts, the running detector "
        "configuration and its host, the band it is made for, the last decision and its age. Read-only: asks "
        "the robots' knowledge services and listens to what they publish. Connects as a Zenoh client to "
        "tcp/127.0.0.1:7447 unless told otherwise.",
    )
    p.add_argument("--once", action="store_true", help="print the fleet once and exit")
    p.add_argument("--json", action="store_true", help="print JSON (one document; with --once, or one per refresh)")
    p.add_argument("--interval", type=float, default=2.0, help="seconds between refreshes (default 2)")
    p.add_argument("--timeout", type=float, default=1.5, help="seconds to wait for the robots' answers (default 1.5)")
    p.add_argument("--expect", action="append", default=[], metavar="ROBOT",
                   help="a robot to list even when it does not answer (repeatable)")
    p.add_argument("--robot", default=keys.DEFAULT_ROBOT,
                   help=f"the robot whose fleet roster lists the robots to expect, and whose roster `forget` "
                   f"changes (default {keys.DEFAULT_ROBOT})")
    add_zenoh_arguments(p)
    p.set_defaults(func=run)
    sub = p.add_subparsers(dest="fleet_command", metavar="[forget ROBOT]")
    forget = sub.add_parser(
        "forget", help="remove a robot from the fleet roster of --robot's knowledge service",
        description="Remove ROBOT from the fleet roster that --robot's knowledge service keeps (the robots it "
        "has heard answer or announce), so fleet questions stop listing it as silent. A robot that answers or "
        "announces again is remembered again. An operator's write: needs write access to that service.")
    forget.add_argument("forget_robot", metavar="ROBOT", help="the robot to forget")
    forget.set_defaults(func=run_forget)


def run_forget(args: argparse.Namespace) -> int:
    """``kgadapt fleet forget ROBOT``: the write verb ``fleet_forget`` on --robot's knowledge service."""
    from kgadapt.knowledge.client import KnowledgeClient
    from kgadapt.shared.session import DEFAULT_ENDPOINT, open_session, settings_from_args

    robot = keys.check_name(args.forget_robot, "robot name")  # before any network
    zenoh = settings_from_args(args).with_defaults(mode="client", connect=[DEFAULT_ENDPOINT])
    session = open_session(zenoh)
    try:
        KnowledgeClient(session, args.robot, timeout=args.timeout).write("fleet_forget", {"robot": robot})
    finally:
        session.close()
    print(f"{args.robot} no longer remembers {robot}")
    return 0


def run(args: argparse.Namespace) -> int:
    from kgadapt.shared.errors import ConfigError
    from kgadapt.shared.session import DEFAULT_ENDPOINT, open_session, settings_from_args

    if not args.interval > 0 or not args.timeout > 0:
        raise ConfigError("--interval and --timeout: more than 0 s")
    settings = FleetViewSettings(timeout=args.timeout, interval=args.interval, expect=tuple(args.expect),
                                 roster=args.robot)
    zenoh = settings_from_args(args).with_defaults(mode="client", connect=[DEFAULT_ENDPOINT])
    session = open_session(zenoh)
    try:
        with FleetView(session, settings) as view:
            while True:
                robots = view.snapshot()
                if args.json:
                    print(json.dumps(as_json(robots), default=str), flush=True)
                else:
                    print(("" if args.once or not sys.stdout.isatty() else CLEAR) + render(robots), flush=True)
                if args.once:
                    return 0 if all(r.answering for r in robots) else 3
                view.changed.wait(args.interval)  # refresh at once when a robot publishes something
    finally:
        session.close()
