"""Ask a robot's knowledge service over Zenoh.

>>> client = KnowledgeClient(session, "quad1")
>>> client.query("placement", {"feature": "MarkerDetection"})
[{'config': ..., 'platform': 'remote', ...}]

Every robot at once (one Zenoh get, one table with a robot column; see
knowledge/fleet.py)::

    FleetClient(session, FleetSettings(timeout=2.0)).ask("current_placement").rows()

Errors: :class:`RemoteError` when the service answers with an error reply
(its text names the problem), :class:`RequestTimeout` when nothing answers in
time, :class:`MessageError` when the reply itself is malformed.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Mapping

from kgadapt.knowledge.fleet import FleetAnswer, FleetClient, FleetSettings  # noqa: F401 (the fleet's client, re-exported)
from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.errors import RemoteError, RequestTimeout, TransportError

log = logging.getLogger(__name__)
_ASK_AGAIN_S = 0.2  # pause between asks while the service is not up or refuses (``wait_s``)


class KnowledgeClient:
    """Named queries, read-only Cypher and run-time writes on ``robot``'s knowledge service."""

    def __init__(self, session: Any, robot: str, *, timeout: float = 2.0, own: bool = False,
                 host: str | None = None) -> None:
        self.session = session
        self.robot = keys.check_name(robot, "robot name")
        # host: the host whose agent this is. Its writes go to knowledge/write/<host>/<verb>, where the
        # service accepts only what that host owns (None: the robot-wide write/<verb>, operators only).
        self.host = None if host is None else keys.check_name(host, "host name")
        self.timeout = timeout
        # own=True: the robot's own software asks on knowledge/own/query/*, served from the
        # primary store apart from other robots' questions (which the ACL keeps off that key).
        self.own = own
        self.last_elapsed_ms: float | None = None  # store time the service reported for the last request

    def query(self, name: str, params: Mapping[str, Any] | None = None, *, wait_s: float = 0.0) -> list[dict[str, Any]]:
        """Rows of named query ``name`` with ``params``.

        ``wait_s``: ask again for that long while no service answers or it refuses (it may be
        starting, or its store reloading after a restart), as a part's first read at start should.
        """
        payload = messages.encode(messages.QueryRequest(params=dict(params or {})))
        key_of = keys.knowledge_own_query if self.own else keys.knowledge_query
        key = key_of(self.robot, keys.check_name(name, "query name"))
        deadline = time.monotonic() + wait_s
        while True:
            try:
                return self._ask(key, payload, f"query {name!r}")
            except (TransportError, RemoteError) as exc:
                if time.monotonic() >= deadline:
                    raise
                log.info("%s; asking again", exc)
                time.sleep(_ASK_AGAIN_S)

    def cypher(self, text: str, params: Mapping[str, Any] | None = None) -> list[dict[str, Any]]:
        """Rows of a read-only Cypher statement (a write is refused by the service)."""
        payload = messages.encode(messages.CypherRequest(cypher=text, params=dict(params or {})))
        return self._ask(keys.knowledge_cypher(self.robot), payload, "cypher")

    def write(self, verb: str, params: Mapping[str, Any]) -> list[dict[str, Any]]:
        """Apply run-time write ``verb`` (see kgadapt.knowledge.runtime.WRITERS)."""
        payload = messages.encode(messages.WriteRequest(params=dict(params)))
        verb = keys.check_name(verb, "write verb")
        key = (keys.knowledge_write(self.robot, verb) if self.host is None
               else keys.knowledge_host_write(self.robot, self.host, verb))
        return self._ask(key, payload, f"write {verb!r}")

    def service_stats(self) -> dict[str, Any]:
        """The service's own counters (``knowledge/own/stats``): requests, statuses, refused hosts."""
        rows = self._ask(keys.knowledge_own_stats(self.robot), b"", "service stats")
        return rows[0] if rows else {}

    def _asker(self) -> bytes | None:
        """Who asks, for the service's per-asker bound on other robots' questions: this session's id."""
        try:
            return str(self.session.zid()).encode()
        except Exception:  # noqa: BLE001 - a session without an id (closed): the service counts it as "anonymous"
            return None

    def _ask(self, key: str, payload: bytes, what: str) -> list[dict[str, Any]]:
        try:
            # Sent again while nothing answers at once: just after open(), or while the service restarts.
            body = rpc.call(self.session, key, payload, lambda data: messages.decode_as(data, messages.Rows),
                            timeout=self.timeout, resend_for=self.timeout, attachment=self._asker())
        except RemoteError as exc:
            raise RemoteError(f"{what} refused by the knowledge service of {self.robot}: {exc}") from exc
        except RequestTimeout as exc:  # NoResponder (nothing serves the key) stays a NoResponder
            raise type(exc)(
                f"{what}: no answer from the knowledge service of robot {self.robot!r} on {key} "
                f"within {self.timeout:.1f} s (is `kgadapt knowledge serve` running and reachable?)"
            ) from exc
        self.last_elapsed_ms = body.elapsed_ms
        return body.rows
