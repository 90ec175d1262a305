"""Ask every robot's knowledge service at once: one Zenoh ``get`` on ``kgadapt/*/knowledge/query/<name>``.

>>> fleet = FleetClient(session, FleetSettings(timeout=2.0, expect=("quad1", "quad2")))
>>> answer = fleet.ask("current_placement")
>>> answer.rows()          # every row, each with its robot first
[{'robot': 'quad1', 'instance': ..., 'config': 'marker_detection_day', 'host': 'onboard', ...}, ...]
>>> answer.silent          # robots expected that did not answer in time
('quad2',)
>>> print(answer.table())

Each robot's knowledge service answers on its own key, so a reply names its
robot. Which robots were expected comes from four places: ``expect`` (the
fleet you know of), the fleet roster of robot ``roster`` (the robots its
knowledge service has heard answer or announce, see
:class:`~kgadapt.knowledge.fleet_roster.FleetRoster`),
robots whose hosts show a liveliness token on ``kgadapt/*/host/*/alive``
(another robot's router may not let those through, see docs/fleet.md) and
robots that answered this client before; the roster and the tokens are asked
in parallel with the question. A robot expected and not answering within the
timeout is listed as silent, never left out.

An error reply (a robot that does not know the query, or refuses a
parameter) carries no key in Zenoh, so it cannot be pinned on a robot: its
text is kept in ``refusals``, and the robot shows as silent.

Fleet questions are named queries only: they reach ``knowledge/query/*``
and nothing else, and the shipped router configurations let other robots
reach exactly that (deploy/zenoh/router.json5).
"""

from __future__ import annotations

import enum
import threading
import time
from dataclasses import dataclass
from typing import Any, Mapping

from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.errors import ConfigError, MessageError, RemoteError, TransportError

ROSTER_QUERY = "fleet_roster"  # the named query of every robot's fleet roster (knowledge/fleet_roster.py)

ROBOT_COLUMN = "robot"


class RobotState(enum.Enum):
    """How a robot took a fleet question."""

    ANSWERED = "answered"
    SILENT = "silent"  # expected, but no answer within the timeout (or an error reply, see module doc)


@dataclass(frozen=True, kw_only=True)
class FleetSettings:
    """How to ask the fleet."""

    timeout: float = 2.0  # seconds to wait for every robot's answer
    expect: tuple[str, ...] = ()  # robots that should answer (listed as silent when they do not)
    discover_hosts: bool = True  # also expect robots whose hosts' liveliness tokens are visible
    # Also expect the robots this robot's knowledge service remembers (its fleet roster), asked in
    # the same round trip; None: none.
    roster: str | None = None

    def __post_init__(self) -> None:
        if not self.timeout > 0:
            raise ConfigError(f"fleet timeout {self.timeout!r}: must be more than 0 s")
        for robot in self.expect:
            keys.check_name(robot, "robot name")
        if self.roster is not None:
            keys.check_name(self.roster, "robot name (whose roster)")


@dataclass(frozen=True, kw_only=True)
class RobotAnswer:
    """One robot's part of a fleet answer."""

    robot: str
    state: RobotState
    rows: tuple[dict[str, Any], ...] = ()
    store_ms: float | None = None  # store time its service reported
    arrived_ms: float | None = None  # from sending the question to its reply arriving


@dataclass(frozen=True, kw_only=True)
class FleetAnswer:
    """The answers of the whole fleet to one named query."""

    query: str
    params: Mapping[str, Any]
    robots: tuple[RobotAnswer, ...]  # sorted by robot name
    refusals: tuple[str, ...] = ()  # texts of error replies (not attributable to a robot)
    malformed: tuple[str, ...] = ()  # replies that could not be read, and why
    wall_ms: float = 0.0  # from sending the question to the last reply (or the timeout)

    @property
    def answered(self) -> tuple[str, ...]:
        return tuple(a.robot for a in self.robots if a.state is RobotState.ANSWERED)

    @property
    def silent(self) -> tuple[str, ...]:
        return tuple(a.robot for a in self.robots if a.state is RobotState.SILENT)

    @property
    def complete(self) -> bool:
        return not self.silent

    def answer_of(self, robot: str) -> RobotAnswer | None:
        return next((a for a in self.robots if a.robot == robot), None)

    def rows(self) -> list[dict[str, Any]]:
        """Every robot's rows, each with ``robot`` first."""
        out: list[dict[str, Any]] = []
        for answer in self.robots:
            out.extend({ROBOT_COLUMN: answer.robot, **row} for row in answer.rows)
        return out

    def as_json(self) -> dict[str, Any]:
        return {
            "query": self.query, "params": dict(self.params), "rows": self.rows(),
            "answered": list(self.answered), "silent": list(self.silent),
            "refusals": list(self.refusals), "malformed": list(self.malformed), "wall_ms": round(self.wall_ms, 2),
        }

    def table(self) -> str:
        """One table with a robot column; then a line per silent robot and per refusal."""
        from kgadapt.knowledge.store import rows_as_table

        lines = [rows_as_table(self.rows())] if self.rows() else []
        answered_empty = [a.robot for a in self.robots if a.state is RobotState.ANSWERED and not a.rows]
        if answered_empty:
            lines.append(f"no rows from: {', '.join(answered_empty)}")
        if self.silent:
            lines.append(f"no answer within the timeout from: {', '.join(self.silent)}")
        for text in self.refusals:
            lines.append(f"refused by a robot: {text}")
        for text in self.malformed:
            lines.append(f"unreadable reply: {text}")
        lines.append(f"{len(self.answered)} of {len(self.robots)} robots answered in {self.wall_ms:.0f} ms")
        return "\n".join(lines)


class FleetClient:
    """Named queries asked of every robot's knowledge service at once.

    Thread-safe: the fleet view asks several questions at once from one client.
    """

    def __init__(self, session: Any, settings: FleetSettings = FleetSettings()) -> None:
        self.session = session
        self.settings = settings
        self._lock = threading.Lock()
        self._known: set[str] = set(settings.expect)  # robots that answered before (or were expected)

    @property
    def known(self) -> tuple[str, ...]:
        with self._lock:
            return tuple(sorted(self._known))

    def ask(self, name: str, params: Mapping[str, Any] | None = None, *, timeout: float | None = None) -> FleetAnswer:
        """Ask named query ``name`` of every robot; wait until all answered or ``timeout`` passed."""
        return self.ask_many([(name, params)], timeout=timeout)[0]

    def ask_many(
        self, questions: list[tuple[str, Mapping[str, Any] | None]], *, timeout: float | None = None
    ) -> list[FleetAnswer]:
        """Several named queries sent together (one round trip, not one per question)."""
        timeout = self.settings.timeout if timeout is None else timeout
        if not timeout > 0:
            raise ConfigError(f"fleet timeout {timeout!r}: must be more than 0 s")
        checked = []
        for name, params in questions:
            checked.append((keys.check_name(name, "query name"), dict(params or {}),
                            messages.encode(messages.QueryRequest(params=dict(params or {})))))
        start = time.perf_counter()
        deadline = time.monotonic() + timeout
        try:
            hosts = None
            if self.settings.discover_hosts:
                hosts = self.session.liveliness().get(f"{keys.PREFIX}/*/host/*/alive", timeout=timeout)
            roster = None
            if self.settings.roster is not None:
                roster = rpc.ask(self.session, keys.knowledge_query(self.settings.roster, ROSTER_QUERY),
                                 messages.encode(messages.QueryRequest(params={})), timeout=timeout)
            pending = [(name, params, payload, self._send(name, payload, timeout)) for name, params, payload in checked]
            answers = [self._collect(name, params, replies, start) for name, params, _, replies in pending]
            # No reply at all, at once: no queryable was known yet (a session just opened, in peer
            # mode). Nobody received the question, so asking again is safe; until the timeout.
            while time.monotonic() + 0.05 < deadline:
                empty = [i for i, a in enumerate(answers) if not (a.robots or a.refusals or a.malformed)]
                if not empty:
                    break
                time.sleep(0.05)
                for i in empty:
                    name, params, payload, _ = pending[i]
                    replies = self._send(name, payload, max(0.05, deadline - time.monotonic()))
                    answers[i] = self._collect(name, params, replies, start)
        except Exception as exc:  # zenoh.ZError: session closed
            raise TransportError(f"fleet question: {exc}") from exc
        expected = set(self._hosts_robots(hosts)) if hosts is not None else set()
        if roster is not None:
            expected.update(self._roster_robots(roster))
        with self._lock:
            for answer in answers:
                self._known.update(answer.answered)
            self._known.update(expected)
            known = set(self._known)
        return [_with_silent(answer, known) for answer in answers]

    def _send(self, name: str, payload: bytes, timeout: float) -> rpc.Pending:
        return rpc.ask(self.session, f"{keys.PREFIX}/*/knowledge/query/{name}", payload, timeout=timeout,
                       every_reply=True)

    def _collect(self, name: str, params: dict[str, Any], pending: rpc.Pending, start: float) -> FleetAnswer:
        robots: dict[str, RobotAnswer] = {}
        refusals: list[str] = []
        malformed: list[str] = []
        for reply in pending.replies():  # ends when every queryable has finalized, or at the timeout
            arrived = (time.perf_counter() - start) * 1000
            if isinstance(reply, RemoteError):
                refusals.append(str(reply))
                continue
            key = reply.key
            robot = robot_of(key, name)
            if robot is None:
                malformed.append(f"reply on {key}: not a knowledge/query/{name} key")
                continue
            try:
                body = messages.decode_as(reply.payload, messages.Rows)
            except MessageError as exc:
                malformed.append(f"{robot}: {exc}")
                continue
            rows = tuple(r for r in body.rows if isinstance(r, dict))
            if robot in robots:  # two services claim one robot: keep both sets of rows, say so
                malformed.append(f"{robot}: answered more than once")
                rows = robots[robot].rows + rows
            robots[robot] = RobotAnswer(robot=robot, state=RobotState.ANSWERED, rows=rows,
                                        store_ms=body.elapsed_ms, arrived_ms=arrived)
        wall = (time.perf_counter() - start) * 1000
        return FleetAnswer(query=name, params=params, robots=tuple(robots[r] for r in sorted(robots)),
                           refusals=tuple(refusals), malformed=tuple(malformed), wall_ms=wall)

    @staticmethod
    def _roster_robots(pending: rpc.Pending) -> list[str]:
        """The robots a fleet roster lists (none when the robot asked for it does not answer)."""
        robots: list[str] = []
        for reply in pending.replies():
            if isinstance(reply, RemoteError):
                continue
            try:
                rows = messages.decode_as(reply.payload, messages.Rows).rows
            except MessageError:
                continue
            robots.extend(r["robot"] for r in rows if isinstance(r, dict) and is_name(str(r.get("robot"))))
        return robots

    @staticmethod
    def _hosts_robots(handler: Any) -> list[str]:
        robots = []
        for reply in handler:
            if reply.ok is not None:
                robot = str(reply.ok.key_expr).split("/")[1]
                if is_name(robot):
                    robots.append(robot)
        return robots


def _with_silent(answer: FleetAnswer, known: set[str]) -> FleetAnswer:
    missing = sorted(known - set(answer.answered))
    if not missing:
        return answer
    robots = list(answer.robots) + [RobotAnswer(robot=r, state=RobotState.SILENT) for r in missing]
    robots.sort(key=lambda a: a.robot)
    return FleetAnswer(query=answer.query, params=answer.params, robots=tuple(robots), refusals=answer.refusals,
                       malformed=answer.malformed, wall_ms=answer.wall_ms)


def robot_of(key: str, name: str) -> str | None:
    """``<robot>`` of ``kgadapt/<robot>/knowledge/query/<name>``, or None for any other key."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != keys.PREFIX or parts[2:] != ["knowledge", "query", name]:
        return None
    return parts[1] if is_name(parts[1]) else None


def is_name(text: str) -> bool:
    """True when ``text`` is a valid robot name (a reply's key or a roster's row may carry anything)."""
    try:
        keys.check_name(text)
    except ConfigError:
        return False
    return True

