"""The fleet roster: the robots a knowledge service has heard on the fleet keys (docs/fleet.md).

Kept where the robot's store keeps it (:class:`kgadapt.knowledge.schema.Graph` ``FLEET_ROSTER``: a graph
of its own beside the robot's on FalkorDB over RESP, the robot's graph elsewhere), and reached only
through the robot's store: :class:`FleetRoster` writes there, the named query ``fleet_roster`` reads
there (the catalogue declares its graph), the write verb ``fleet_forget`` (:func:`forget_robot`)
deletes there. Whoever asks (the service's queryables, ``kgadapt ask``, ``kgadapt knowledge query
--store``, the store API) gets the same roster.
"""

from __future__ import annotations

import enum
import logging
import random
import threading
import time
from dataclasses import dataclass
from typing import Any, Mapping

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.fleet import ROSTER_QUERY, robot_of
from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.errors import ConfigError, MessageError, NamedQueryError, RemoteError

log = logging.getLogger(__name__)

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
        return S.Graph.FLEET_ROSTER.store(self.primary)

    def open(self) -> None:
        """Connect to where the roster is kept and move there a roster kept in the robot's graph (once)."""
        if self._opened:
            return
        if self.store is not self.primary:
            move_roster(self.primary, self.store)
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
            if self.refused & (self.refused - 1) == 0:  # the 1st, 2nd, 4th, 8th...: a flood of names logs little
                log.warning("fleet roster full (%d robots): %s not recorded (%d turned away so far; "
                            "kgadapt fleet forget makes room)", self.settings.cap, robot, self.refused)
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
            robot = robot_of(reply.key, ROSTER_QUERY)
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


def move_roster(primary: Any, roster: Any) -> None:
    """Move a roster kept in the robot's graph (before it had a graph of its own) into the roster's graph: at a
    service's setup, and after an import of an export of that time (knowledge/export.py). A robot in both keeps
    what the roster's graph says of it."""
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
