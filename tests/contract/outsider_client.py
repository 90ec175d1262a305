"""A client of kgadapt's wire contract written only from the documents: zenoh-python and msgpack, nothing of kgadapt.

Everything here is transcribed from docs/CONTRACTS.md (the "Message kinds" and
"States and kinds" tables, the knowledge service's keys), docs/zenoh.md (the
key table), docs/deploy.md ("Wire contract"), docs/perception.md (frames,
illumination, detections, a detector's configure and activity keys),
docs/flight.md (`flight/state`) and docs/fleet.md (`adaptation/events`). It
imports no project code on purpose: if the messages' layout changes without
the documents, this client and its test notice.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import msgpack
import zenoh

# --- the documented schema -------------------------------------------------------------------------------------------
# A type is one of: "number" (float or int, finite, not bool), "int", "bool", ("str", limit|None),
# ("bytes", limit), ("list", limit|None, item type|None), ("map", limit|None), ("enum", name), ("struct", name).

NUMBER, INT, BOOL = "number", "int", "bool"


def S(limit: int | None = None) -> tuple[Any, ...]:
    return ("str", limit)


def L(limit: int | None = None, item: Any = None) -> tuple[Any, ...]:
    return ("list", limit, item)


def M(limit: int | None = None) -> tuple[Any, ...]:
    return ("map", limit)


ENUMS: dict[str, frozenset[str]] = {
    "ProcessState": frozenset("starting ready running restarting stopping stopped exited failed".split()),
    "ProcessEventKind": frozenset("started ready exited restarted stopped failed reconfigured".split()),
    "TriggerKind": frozenset(
        "startup band_changed memory_short host_lost host_back rate_collapsed detector_gone standby".split()),
    "Change": frozenset("reconfigure migrate standby standby_start standby_stopped".split()),
}


@dataclass(frozen=True)
class Kind:
    v: int
    max_bytes: int
    required: dict[str, Any]
    optional: dict[str, Any]


K256 = 262144
M8 = 8388608
KINDS: dict[str, Kind] = {
    "host_status": Kind(1, K256,
                        {"host": S(64), "time": NUMBER, "memory_total_mb": NUMBER, "memory_free_mb": NUMBER,
                         "cpu_load": NUMBER},
                        {"cpu_cores": INT, "budget_mb": NUMBER, "ours_mb": NUMBER, "reserved_mb": NUMBER,
                         "origin": S(32), "seq": INT}),
    "squeeze_request": Kind(1, K256, {"reserve_mb": NUMBER}, {}),
    "frame": Kind(1, M8,
                  {"camera": S(64), "seq": INT, "time": NUMBER, "width": INT, "height": INT,
                   "jpeg": ("bytes", 8388608)},
                  {"truth": L(1024), "level": NUMBER, "sent": NUMBER}),
    "illumination": Kind(1, K256,
                         {"camera": S(64), "seq": INT, "time": NUMBER, "mean": NUMBER, "p5": NUMBER, "p50": NUMBER,
                          "p95": NUMBER, "smoothed": NUMBER},
                         {"level": NUMBER, "frame_level": NUMBER, "marker_level": NUMBER, "source": S(64),
                          "usable": NUMBER, "saturated": NUMBER, "black": NUMBER, "markers": INT}),
    "detections": Kind(1, K256,
                       {"instance": S(64), "config": S(64), "host": S(64), "seq": INT, "frame_time": NUMBER,
                        "time": NUMBER, "ids": L(1024), "corners": L(1024), "processing_ms": NUMBER},
                       {"camera": S(64), "received": NUMBER, "decode_ms": NUMBER, "dropped": INT,
                        "frame_sent": NUMBER, "clean": L(1024)}),
    "query_request": Kind(1, K256, {}, {"params": M(64)}),
    "cypher_request": Kind(1, K256, {"cypher": S(16384)}, {"params": M(64)}),
    "rows": Kind(1, M8, {"rows": L(100000, M())}, {"elapsed_ms": NUMBER}),
    "write_request": Kind(1, K256, {"params": M(64)}, {}),
    "deploy_request": Kind(1, K256, {},
                           {"deployment": S(64), "config": S(64), "instance": S(64), "wait_ready": BOOL,
                            "ready_timeout": NUMBER, "idle": BOOL}),
    "configure_request": Kind(1, K256, {"config": S(64)}, {}),
    "configure_reply": Kind(1, K256,
                            {"instance": S(64), "config": S(64), "previous": S(64), "deployment": S(64),
                             "check_ms": NUMBER, "build_ms": NUMBER},
                            {"first_seq": INT, "first_frame_ms": NUMBER}),
    "activity_request": Kind(1, K256, {"active": BOOL}, {}),
    "activity_reply": Kind(1, K256, {"instance": S(64), "active": BOOL, "processed": INT}, {}),
    "deploy_reply": Kind(1, K256, {"ok": BOOL}, {"detail": ("struct", "DeployDetail")}),
    "deploy_event": Kind(1, K256,
                         {"event": ("enum", "ProcessEventKind"), "host": S(64), "instance": S(64), "time": NUMBER},
                         {"pid": INT, "returncode": INT, "detail": S(4096), "run_id": S(128), "deployment": S(64),
                          "config": S(64)}),
    "flight_state": Kind(1, K256, {"time": NUMBER, "link": BOOL},
                         {"armed": BOOL, "mode": S(64), "landed_state": S(32), "battery_pct": NUMBER,
                          "battery_v": NUMBER, "onboard_load": NUMBER, "event": S(32), "alt_rel_m": NUMBER,
                          "alt_amsl_m": NUMBER, "lat_deg": NUMBER, "lon_deg": NUMBER, "attitude": L(3),
                          "rates": L(3), "position_ned": L(3), "velocity_ned": L(3), "rangefinder_m": NUMBER,
                          "home": L(3), "heard": M(16), "boot_ms": INT, "reboots": INT, "missing": L(16),
                          "refused": L(16), "system_id": INT, "autopilot": S(32), "last_heartbeat": NUMBER}),
    "adaptation_event": Kind(1, K256, {"time": NUMBER, "trigger": S(256)},
                             {"decision": ("struct", "Decision"), "outcome": S(256)}),
}

_PROCESS_FIELDS: dict[str, Any] = {
    "instance": S(), "host": S(), "deployment": S(), "config": S(), "state": ("enum", "ProcessState"),
    "pid": INT, "run_id": S(), "restarts": INT, "started_at": NUMBER, "ready_at": NUMBER, "ended_at": NUMBER,
    "returncode": INT, "argv": L(None, S()), "detail": S(), "output": L(None, S()), "via": S(),
}
STRUCTS: dict[str, dict[str, Any]] = {  # nested maps: every field optional
    "DeployDetail": {**_PROCESS_FIELDS, "processes": L(None, ("struct", "ProcessDetail")),
                     "launcher": ("struct", "Launcher"), "error": S(), "error_type": S(64)},
    "ProcessDetail": dict(_PROCESS_FIELDS),
    "Launcher": {"pid": INT, "ready": BOOL},
    "Decision": {"name": S(), "trigger_kind": ("enum", "TriggerKind"), "trigger_time": NUMBER,
                 "change": ("enum", "Change"), "config": S(), "host": S(), "instance": S(),
                 "previous_instance": S(), "latency_ms": NUMBER, "frames_lost": INT},
}


def _type_problem(where: str, value: Any, spec: Any) -> list[str]:
    """What is wrong with ``value`` against the documented type ``spec`` (empty when nothing)."""
    if value is None:  # "an absent optional field and a nil one mean the same": callers skip None of optionals
        return [f"{where}: nil"]
    if spec == NUMBER:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return [f"{where}: {type(value).__name__} is no number"]
        if isinstance(value, float) and not math.isfinite(value):
            return [f"{where}: {value} is not finite"]
        return []
    if spec == INT:
        ok = isinstance(value, int) and not isinstance(value, bool)
        return [] if ok else [f"{where}: {type(value).__name__} is no int"]
    if spec == BOOL:
        return [] if isinstance(value, bool) else [f"{where}: {type(value).__name__} is no bool"]
    tag = spec[0]
    if tag == "str":
        if not isinstance(value, str):
            return [f"{where}: {type(value).__name__} is no str"]
        return [f"{where}: {len(value)} characters over {spec[1]}"] if spec[1] and len(value) > spec[1] else []
    if tag == "bytes":
        if not isinstance(value, bytes):
            return [f"{where}: {type(value).__name__} is no bytes"]
        return [f"{where}: {len(value)} bytes over {spec[1]}"] if len(value) > spec[1] else []
    if tag == "list":
        if not isinstance(value, list):
            return [f"{where}: {type(value).__name__} is no list"]
        out = [f"{where}: {len(value)} items over {spec[1]}"] if spec[1] and len(value) > spec[1] else []
        if spec[2] is not None:
            for i, item in enumerate(value):
                out += _type_problem(f"{where}[{i}]", item, spec[2])
        return out
    if tag == "map":
        if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
            return [f"{where}: {type(value).__name__} is no map of str keys"]
        return [f"{where}: {len(value)} entries over {spec[1]}"] if spec[1] and len(value) > spec[1] else []
    if tag == "enum":
        if not isinstance(value, str) or value not in ENUMS[spec[1]]:
            return [f"{where}: {value!r} is not a {spec[1]}"]
        return []
    if tag == "struct":
        if not isinstance(value, dict):
            return [f"{where}: {type(value).__name__} is no {spec[1]} map"]
        return _fields_problems(where, value, {}, STRUCTS[spec[1]])
    raise ValueError(f"unknown type spec {spec!r}")


def _fields_problems(where: str, body: dict[str, Any], required: dict[str, Any],
                     optional: dict[str, Any]) -> list[str]:
    out = []
    for name, spec in required.items():
        if name not in body:
            out.append(f"{where}.{name}: missing")
        else:
            out += _type_problem(f"{where}.{name}", body[name], spec)
    for name, value in body.items():
        if name in required:
            continue
        if name not in optional:
            out.append(f"{where}.{name}: not documented")
        elif value is not None:
            out += _type_problem(f"{where}.{name}", value, optional[name])
    return out


def shape_problems(kind: str, body: Any, payload_size: int | None = None) -> list[str]:
    """Every difference between ``body`` (a decoded payload) and the documented ``kind``: empty when it fits exactly."""
    if not isinstance(body, dict):
        return [f"{kind}: payload is a {type(body).__name__}, not a map"]
    spec = KINDS[kind]
    out = []
    if body.get("kind") != kind:
        out.append(f"{kind}.kind: {body.get('kind')!r}")
    if body.get("v") != spec.v or isinstance(body.get("v"), bool):
        out.append(f"{kind}.v: {body.get('v')!r}, documented {spec.v}")
    if payload_size is not None and payload_size > spec.max_bytes:
        out.append(f"{kind}: {payload_size} bytes over {spec.max_bytes}")
    fields = {k: v for k, v in body.items() if k not in ("kind", "v")}
    return out + _fields_problems(kind, fields, spec.required, spec.optional)


def encode(kind: str, **fields: Any) -> bytes:
    """A payload as the docs describe it: a msgpack map ``{"kind", "v", ...fields}``."""
    return msgpack.packb({"kind": kind, "v": KINDS[kind].v, **fields}, use_bin_type=True)


def decode(payload: bytes) -> Any:
    return msgpack.unpackb(payload, raw=False)


# --- asking ----------------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Reply:
    """One reply: ``ok`` with ``body`` (decoded) and its ``size``, or not ``ok`` with the ``error`` text."""

    ok: bool
    body: Any = None
    error: str = ""
    size: int = 0


class Outsider:
    """Asks and listens on the documented keys of robot ``robot`` through one Zenoh session."""

    def __init__(self, session: zenoh.Session, robot: str) -> None:
        self.session = session
        self.robot = robot

    def key(self, *chunks: str) -> str:
        return "/".join(("kgadapt", self.robot, *chunks))

    def get_all(self, key: str, payload: bytes | None, timeout: float = 10.0) -> list[Reply]:
        """Every reply to one get on ``key`` (a selector may carry ``?name=value`` parameters)."""
        out = []
        for reply in self.session.get(key, payload=payload, timeout=timeout):
            if reply.ok is not None:
                raw = reply.ok.payload.to_bytes()
                out.append(Reply(True, body=decode(raw), size=len(raw)))
            else:
                out.append(Reply(False, error=reply.err.payload.to_bytes().decode("utf-8", "replace")))
        return out

    def get_one(self, key: str, payload: bytes | None, timeout: float = 10.0) -> Reply:
        replies = self.get_all(key, payload, timeout)
        if len(replies) != 1:
            raise AssertionError(f"{key}: {len(replies)} replies, documented exactly one: {replies}")
        return replies[0]

    # knowledge service
    def query(self, name: str, params: dict[str, Any] | None = None, *, own: bool = False) -> Reply:
        lane = ("knowledge", "own", "query", name) if own else ("knowledge", "query", name)
        return self.get_one(self.key(*lane), encode("query_request", params=params or {}))

    def query_selector(self, name: str, **params: str) -> Reply:
        selector = self.key("knowledge", "query", name)
        if params:
            selector += "?" + ";".join(f"{k}={v}" for k, v in params.items())
        return self.get_one(selector, None)

    def cypher(self, text: str, params: dict[str, Any] | None = None) -> Reply:
        return self.get_one(self.key("knowledge", "cypher"), encode("cypher_request", cypher=text, params=params or {}))

    def write(self, verb: str, params: dict[str, Any], *, host: str | None = None) -> Reply:
        chunks = ("knowledge", "write", host, verb) if host else ("knowledge", "write", verb)
        return self.get_one(self.key(*chunks), encode("write_request", params=params))

    # host monitor
    def squeeze(self, host: str, reserve_mb: Any) -> Reply:
        return self.get_one(self.key("host", host, "squeeze"), encode("squeeze_request", reserve_mb=reserve_mb))

    # deployer
    def deployer(self, host: str, verb: str, timeout: float = 60.0, **fields: Any) -> list[Reply]:
        return self.get_all(self.key("host", host, "deployer", verb), encode("deploy_request", **fields), timeout)

    # a running detector
    def configure(self, host: str, instance: str, config: str) -> Reply:
        return self.get_answered(self.key("host", host, "detector", instance, "configure"),
                                 encode("configure_request", config=config), timeout=30.0)

    def activity(self, host: str, instance: str, active: bool) -> Reply:
        return self.get_answered(self.key("host", host, "detector", instance, "activity"),
                                 encode("activity_request", active=active))

    def get_answered(self, key: str, payload: bytes, timeout: float = 10.0) -> Reply:
        """``get_one``, asking again while nothing answers: a detector's queryable may reach this session
        a moment after its deployer reported it ready (docs/perception.md, "Idle or active")."""
        deadline = time.monotonic() + timeout
        while True:
            replies = self.get_all(key, payload, max(0.1, deadline - time.monotonic()))
            if replies or time.monotonic() >= deadline:
                break
            time.sleep(0.05)
        if len(replies) != 1:
            raise AssertionError(f"{key}: {len(replies)} replies, documented exactly one: {replies}")
        return replies[0]

    def tokens(self, keyexpr: str, timeout: float = 5.0) -> set[str]:
        """The keys of the liveliness tokens alive under ``keyexpr`` now."""
        return {str(reply.ok.key_expr) for reply in self.session.liveliness().get(self.key(keyexpr), timeout=timeout)
                if reply.ok is not None}

    def listen(self, keyexpr: str) -> "Heard":
        heard = Heard()
        heard.subscriber = self.session.declare_subscriber(self.key(keyexpr), heard.add)
        return heard


class Heard:
    """What a subscriber heard: (key, body or None when not msgpack, payload size), in order of arrival."""

    def __init__(self) -> None:
        self.items: list[tuple[str, Any, int]] = []
        self.subscriber: Any = None
        self._changed = threading.Condition()

    def add(self, sample: zenoh.Sample) -> None:  # Zenoh callback: decode and append, nothing that blocks
        raw = sample.payload.to_bytes()
        try:
            body = decode(raw)
        except Exception:
            body = None
        with self._changed:
            self.items.append((str(sample.key_expr), body, len(raw)))
            self._changed.notify_all()

    def wait(self, predicate: Callable[[str, Any], bool], timeout: float, what: str) -> tuple[str, Any, int]:
        """The first item for which ``predicate(key, body)`` holds, waiting up to ``timeout`` s for it."""
        deadline = time.monotonic() + timeout
        with self._changed:
            seen = 0
            while True:
                for item in self.items[seen:]:
                    if item[1] is not None and predicate(item[0], item[1]):
                        return item
                seen = len(self.items)
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"timed out after {timeout} s waiting for {what}; heard {len(self.items)} "
                                         f"messages, the last on {[k for k, _, _ in self.items[-3:]]}")
                self._changed.wait(left)

    def snapshot(self) -> list[tuple[str, Any, int]]:
        with self._changed:
            return list(self.items)

    def close(self) -> None:
        if self.subscriber is not None:
            self.subscriber.undeclare()
