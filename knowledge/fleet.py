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
knowledge service has heard answer or announce, see :class:`FleetRoster`),
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
import random
import threading
import time
from dataclasses import dataclass
from typing import Any, Mapping

from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.errors import ConfigError, MessageError, RemoteError, TransportError

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
            robot = _robot_of(key, name)
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
            robots.extend(r["robot"] for r in rows if isinstance(r, dict) and _is_name(str(r.get("robot"))))
        return robots

    @staticmethod
    def _hosts_robots(handler: Any) -> list[str]:
        robots = []
        for reply in handler:
            if reply.ok is not None:
                robot = str(reply.ok.key_expr).split("/")[1]
                if _is_name(robot):
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


def _robot_of(key: str, name: str) -> str | None:
    """``<robot>`` of ``kgadapt/<robot>/knowledge/query/<name>``, or None for any other key."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != keys.PREFIX or parts[2:] != ["knowledge", "query", name]:
        return None
    return parts[1] if _is_name(parts[1]) else None


def _is_name(text: str) -> bool:
    try:
        keys.check_name(text)
    except ConfigError:
        return False
    return True


# -- the fleet roster: the robots a knowledge service has heard -------------------------------------------------

ROSTER_QUERY = "fleet_roster"
_MAX_ROUTERS = 16  # a robot's routers as announced: more is no robot of ours
_ZID_CHARS = frozenset("0123456789abcdef")


class Heard(enum.Enum):
    """How a knowledge service came to know a robot of its roster."""

    SELF = "self"  # the service's own robot
    ANSWER = "answer"  # it answered this service's roll call
    ANNOUNCE = "announce"  # it announced itself in its own roll call


@dataclass(frozen=True, kw_only=True)
class RosterSettings:
    """How a knowledge service keeps its fleet roster."""

    robot: str  # the service's own robot
    cap: int = 1000  # robots remembered at most; a new one past it is not recorded (the known ones stay)
    # A roll call (a fleet question for every robot's roster, announcing this robot) at setup and at these
    # delays after it (a router link takes a moment), then every interval_s; 0: only those first ones.
    # A robot that starts later announces itself to those already up, so the first calls are few.
    first_calls_s: tuple[float, ...] = (0.0, 5.0)
    interval_s: float = 600.0
    timeout_s: float = 2.0
    jitter_s: float = 1.0  # each roll call up to this much later: services started together do not call together
    # Where the roster is kept is the store's to say, not a setting: schema.Graph.FLEET_ROSTER (beside the
    # robot's graph on FalkorDB over RESP), so whoever runs fleet_roster or fleet_forget on the robot's store
    # reaches the same roster.

    def __post_init__(self) -> None:
        keys.check_name(self.robot, "robot name")
        if self.cap < 1:
            raise ConfigError(f"roster cap {self.cap!r}: at least 1")
        if self.interval_s < 0 or not self.timeout_s > 0:
            raise ConfigError(f"roster interval {self.interval_s!r} s, timeout {self.timeout_s!r} s: "
                              "interval at least 0, timeout more than 0")


def check_routers(text: str | None, what: str) -> list[str] | None:
    """Zenoh router ids from a comma-separated text (lower-case hex, at most 16); MessageError naming ``what``."""
    if text is None:
        return None
    routers = [zid for zid in text.split(",") if zid]
    if len(routers) > _MAX_ROUTERS:
        raise MessageError(f"{what}: {len(routers)} routers, at most {_MAX_ROUTERS}")
    for zid in routers:
        if len(zid) > 32 or not set(zid) <= _ZID_CHARS:
            raise MessageError(f"{what}: router id {zid[:40]!r} is not a Zenoh id (hex, at most 32 digits)")
    return routers


def forget_robot(store: Any, *, robot: str) -> None:
    """Write verb ``fleet_forget`` (operators): remove ``robot`` from the fleet roster (``kgadapt fleet forget``)
    of the robot whose store is ``store``, wherever the store keeps it (schema.Graph.FLEET_ROSTER).

    A robot that answers or announces again is remembered again.
    """
    from kgadapt.knowledge import schema as S
    from kgadapt.shared.errors import NamedQueryError

    # Any text is a value, never code: one that names no remembered robot removes nothing.
    if not isinstance(robot, str) or not robot:
        raise NamedQueryError(f"write 'fleet_forget': parameter 'robot' must be a robot's name, not {robot!r}")
    S.Graph.FLEET_ROSTER.store(store).execute(f"MATCH (r:{S.FLEET_ROBOT} {{name: $robot}}) DELETE r",
                                              {"robot": robot})


class FleetRoster:
    """The robots a knowledge service has heard answer or announce on the fleet keys, kept in its store.

    ``store`` is the robot's store; the roster is where that store keeps it (:attr:`store`, see
    ``schema.Graph.FLEET_ROSTER``: a graph of its own beside the robot's on FalkorDB over RESP, the robot's
    graph elsewhere), the same place the named query ``fleet_roster`` and the write verb ``fleet_forget``
    reach on that store. ``open()`` connects there and moves any roster an older version kept in the
    robot's graph. ``setup(session)`` (opening first if need be) records the service's own robot and starts
    the roll calls (a thread of its own: a roll call waits on replies); ``shutdown()`` stops them (the
    roster's graph closes with the robot's store). Only what arrives on the fleet keys is recorded: answers
    to the roll call (the robot from the reply's key) and other robots' roll calls (the ``announce``
    parameter, see :meth:`heard`). Bounded by ``cap``.
    """

    def __init__(self, store: Any, settings: RosterSettings) -> None:
        self.primary = store
        self.settings = settings
        self._opened = False
        self._session: Any = None
        self._zid: str | None = None
        self._routers: list[str] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.refused = 0  # robots not recorded because the roster was full

    @property
    def store(self) -> Any:
        """Where the roster is (connected at first use: the robot's store keeps it)."""
        from kgadapt.knowledge.schema import Graph

        return Graph.FLEET_ROSTER.store(self.primary)

    def open(self) -> None:
        """Connect to where the roster is kept and move there a roster kept in the robot's graph (once)."""
        if self._opened:
            return
        if self.store is not self.primary:
            _move_roster(self.primary, self.store)
        self._opened = True

    def setup(self, session: Any) -> None:
        self.open()
        self._session = session
        self._zid, self._routers = _zenoh_ids(session)
        self.remember(self.settings.robot, how=Heard.SELF, zid=self._zid, routers=self._routers)
        self._stop.clear()
        self._thread = threading.Thread(target=self._roll_calls, name="fleet-roster", daemon=True)
        self._thread.start()

    def shutdown(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.settings.timeout_s + 5)
            self._thread = None

    def remember(self, robot: str, *, how: Heard, when: float | None = None, zid: str | None = None,
                 routers: list[str] | None = None) -> bool:
        """Record that ``robot`` was heard (now, or at ``when``); False when the roster is full and it is new."""
        from kgadapt.knowledge import schema as S

        keys.check_name(robot, "robot name")
        params = {"name": robot, "time": time.time() if when is None else float(when), "heard": how.value,
                  "zid": zid, "routers": routers}
        # A robot heard before, the common case: one statement.
        rows = self.store.execute(
            f"MATCH (r:{S.FLEET_ROBOT} {{name: $name}}) SET r.last_seen = $time, r.heard = $heard, "
            "r.zid = coalesce($zid, r.zid), r.routers = coalesce($routers, r.routers) RETURN count(r) AS n", params)
        if rows and rows[0]["n"]:
            return True
        count = self.store.execute(f"MATCH (r:{S.FLEET_ROBOT}) RETURN count(r) AS n")
        if count and count[0]["n"] >= self.settings.cap:
            self.refused += 1
            return False
        self.store.execute(
            f"MERGE (r:{S.FLEET_ROBOT} {{name: $name}}) ON CREATE SET r.first_seen = $time "
            "SET r.last_seen = $time, r.heard = $heard, r.zid = $zid, r.routers = $routers", params)
        return True

    def heard(self, params: Mapping[str, Any]) -> None:
        """A roll call of another robot arrived (the checked parameters of a ``fleet_roster`` question)."""
        robot = params.get("announce")
        if robot is None or robot == self.settings.robot:
            return
        what = f"roll call of {robot}"
        zid = check_routers(params.get("zid"), what)
        if zid is not None and len(zid) != 1:
            raise MessageError(f"{what}: zid {params.get('zid')!r} is not one Zenoh id")
        self.remember(keys.check_name(robot, "announcing robot"), how=Heard.ANNOUNCE,
                      zid=zid[0] if zid else None, routers=check_routers(params.get("routers"), what))

    def roll_call(self) -> list[str]:
        """Ask every robot's roster, announcing this robot; remember those that answer. Their names."""
        announce = {"announce": self.settings.robot, **({"zid": self._zid} if self._zid else {}),
                    **({"routers": ",".join(self._routers)} if self._routers else {})}
        payload = messages.encode(messages.QueryRequest(params=announce))
        pending = rpc.ask(self._session, f"{keys.PREFIX}/*/knowledge/query/{ROSTER_QUERY}", payload,
                          timeout=self.settings.timeout_s, every_reply=True)
        heard = []
        for reply in pending.replies():
            if isinstance(reply, RemoteError):
                continue  # an older robot without a roster: not attributable (see the module doc)
            robot = _robot_of(reply.key, ROSTER_QUERY)
            if robot is None or robot == self.settings.robot:
                continue
            try:
                rows = messages.decode_as(reply.payload, messages.Rows).rows
            except MessageError:
                continue
            own = next((r for r in rows if isinstance(r, dict) and r.get("robot") == robot), {})
            zid = own.get("zid") if isinstance(own.get("zid"), str) else None
            routers = own.get("routers")
            try:
                routers = check_routers(",".join(routers), f"roster of {robot}") if isinstance(routers, list) \
                    and all(isinstance(z, str) for z in routers) else None
            except MessageError:
                routers = None
            if self.remember(robot, how=Heard.ANSWER, zid=zid, routers=routers):
                heard.append(robot)
        return heard

    def _roll_calls(self) -> None:
        import logging

        log = logging.getLogger(__name__)
        start = time.monotonic()
        delays = list(self.settings.first_calls_s)
        while not self._stop.is_set():
            if delays:
                wait = max(0.0, start + delays.pop(0) - time.monotonic())
            elif self.settings.interval_s > 0:
                wait = self.settings.interval_s
            else:
                return
            wait += random.uniform(0.0, self.settings.jitter_s)
            if self._stop.wait(wait):
                return
            try:
                self._zid, self._routers = _zenoh_ids(self._session)
                self.remember(self.settings.robot, how=Heard.SELF, zid=self._zid, routers=self._routers)
                heard = self.roll_call()
                log.debug("fleet roll call of %s: %d robots answered", self.settings.robot, len(heard))
            except Exception as exc:  # noqa: BLE001 - a store away or the session closing: the next roll call tries again
                log.warning("fleet roll call of %s: %s", self.settings.robot, exc)


def _move_roster(primary: Any, roster: Any) -> None:
    """Move a roster kept in the robot's graph (before it had a graph of its own) into the roster's graph."""
    from kgadapt.knowledge import schema as S

    # Read only: a MATCH ... DELETE that finds nothing still counts as a write to the robot's graph.
    rows = primary.execute(f"MATCH (r:{S.FLEET_ROBOT}) RETURN r.name AS name, r.first_seen AS first_seen, "
                           "r.last_seen AS last_seen, r.heard AS heard, r.zid AS zid, r.routers AS routers",
                           read_only=True)
    if not rows:
        return
    roster.execute(
        f"UNWIND $rows AS row MERGE (r:{S.FLEET_ROBOT} {{name: row.name}}) "
        "ON CREATE SET r.first_seen = row.first_seen, r.last_seen = row.last_seen, r.heard = row.heard, "
        "r.zid = row.zid, r.routers = row.routers", {"rows": rows})
    primary.execute(f"MATCH (r:{S.FLEET_ROBOT}) DELETE r")


def _zenoh_ids(session: Any) -> tuple[str | None, list[str]]:
    """The session's own Zenoh id and its routers' (a router-mode session: the routers linked to it)."""
    try:
        info = session.info
        return str(info.zid()), sorted(str(z) for z in info.routers_zid())[:_MAX_ROUTERS]
    except Exception:  # noqa: BLE001 - zenoh.ZError: the session is closing
        return None, []
