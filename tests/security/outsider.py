"""An outsider's client, written only from docs/CONTRACTS.md: zenoh-python and msgpack, nothing of kgadapt.

The attack tests use it for what another robot (or anyone the router lets
in) can send: named queries and Cypher on the documented keys, with the
documented message shapes. It imports no project code on purpose, so a
change in our own client cannot hide a hole.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import msgpack
import zenoh


@dataclass(frozen=True)
class Answer:
    """What came back: ``ok`` rows, an ``err`` text, or ``none`` (no reply in time)."""

    kind: str  # "ok" | "err" | "none"
    rows: list[dict[str, Any]] | None
    error: str
    seconds: float


class Outsider:
    def __init__(self, session: zenoh.Session, robot: str) -> None:
        self.session = session
        self.robot = robot

    def cypher(self, text: str, params: dict[str, Any] | None = None, *, timeout: float = 5.0) -> Answer:
        body = {"kind": "cypher_request", "v": 1, "cypher": text, "params": params or {}}
        return self._get(f"kgadapt/{self.robot}/knowledge/cypher", msgpack.packb(body), timeout)

    def query(self, name: str, params: dict[str, Any] | None = None, *, timeout: float = 5.0) -> Answer:
        body = {"kind": "query_request", "v": 1, "params": params or {}}
        return self._get(f"kgadapt/{self.robot}/knowledge/query/{name}", msgpack.packb(body), timeout)

    def raw(self, key: str, payload: bytes, *, timeout: float = 5.0) -> Answer:
        return self._get(key, payload, timeout)

    def _get(self, key: str, payload: bytes, timeout: float) -> Answer:
        started = time.perf_counter()
        for reply in self.session.get(key, payload=payload, timeout=timeout):
            elapsed = time.perf_counter() - started
            if reply.ok is not None:
                body = msgpack.unpackb(reply.ok.payload.to_bytes(), raw=False)
                return Answer("ok", body.get("rows"), "", elapsed)
            text = reply.err.payload.to_bytes().decode("utf-8", "replace")
            return Answer("none" if text == "Timeout" else "err", None, text, elapsed)
        return Answer("none", None, "", time.perf_counter() - started)
