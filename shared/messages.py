"""Wire messages: msgpack maps with a kind and a schema version, checked on receipt.

Every payload is a map ``{"kind": KIND, "v": VERSION, ...fields}``. ``encode``
checks what we send; ``decode`` checks what we receive and raises
:class:`MessageError` naming the problem (not msgpack, not a map, wrong kind,
unknown version, missing or ill-typed field, oversized) so that a queryable
can answer with an error reply and a subscriber can log a drop and go on.

Fields not in the schema are kept, not refused: a newer sender may add
optional fields without breaking older receivers. A new *required* field or a
changed meaning needs a new version.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import msgpack

from kgadapt.shared.errors import MessageError

MAX_PAYLOAD = 8 * 1024 * 1024  # a 1080p JPEG is well under this
MAX_SMALL = 256 * 1024  # everything that is not a frame

NUMBER = (int, float)


@dataclass(frozen=True)
class Field:
    types: tuple[type, ...]
    required: bool = True
    max_len: int | None = None  # strings, bytes, lists, maps


@dataclass(frozen=True)
class Schema:
    kind: str
    version: int
    fields: Mapping[str, Field]
    max_size: int = MAX_SMALL


def _f(*types: type, required: bool = True, max_len: int | None = None) -> Field:
    return Field(types, required, max_len)


_NAME = _f(str, max_len=64)
_OPT_NAME = _f(str, required=False, max_len=64)
_TIME = _f(*NUMBER)

SCHEMAS: dict[str, Schema] = {
    s.kind: s
    for s in [
        Schema("host_status", 1, {
            "host": _NAME, "time": _TIME,
            "memory_total_mb": _f(*NUMBER), "memory_free_mb": _f(*NUMBER), "cpu_load": _f(*NUMBER),
            "cpu_cores": _f(int, required=False), "budget_mb": _f(*NUMBER, required=False),
            "ours_mb": _f(*NUMBER, required=False), "reserved_mb": _f(*NUMBER, required=False),
        }),
        Schema("squeeze_request", 1, {"reserve_mb": _f(*NUMBER)}),
        Schema("frame", 1, {
            "camera": _NAME, "seq": _f(int), "time": _TIME,
            "width": _f(int), "height": _f(int), "jpeg": _f(bytes, max_len=MAX_PAYLOAD),
            "truth": _f(list, required=False, max_len=1024),
            "level": _f(*NUMBER, required=False),
            "sent": _f(*NUMBER, required=False),  # publication time (capture "time" is before encoding)
        }, max_size=MAX_PAYLOAD),
        Schema("illumination", 1, {
            "camera": _NAME, "seq": _f(int), "time": _TIME,
            "mean": _f(*NUMBER), "p5": _f(*NUMBER), "p50": _f(*NUMBER), "p95": _f(*NUMBER),
            "smoothed": _f(*NUMBER),
            # optional, from kgadapt.onboard.illumination.estimate_light: the robust level the band is read
            # from (smoothed is its EMA), and what it used
            "level": _f(*NUMBER, required=False), "frame_level": _f(*NUMBER, required=False),
            "marker_level": _f(*NUMBER, required=False), "source": _OPT_NAME,
            "usable": _f(*NUMBER, required=False), "saturated": _f(*NUMBER, required=False),
            "black": _f(*NUMBER, required=False), "markers": _f(int, required=False),
        }),
        Schema("detections", 1, {
            "instance": _NAME, "config": _NAME, "host": _NAME, "seq": _f(int),
            "frame_time": _TIME, "time": _TIME,
            "ids": _f(list, max_len=1024), "corners": _f(list, max_len=1024),
            "processing_ms": _f(*NUMBER),
            # optional, from kgadapt.onboard.detector: when the frame arrived, JPEG decode time, stale frames
            # dropped so far, and the camera's publication time of the frame (transport = received - frame_sent)
            "camera": _OPT_NAME, "received": _f(*NUMBER, required=False), "decode_ms": _f(*NUMBER, required=False),
            "dropped": _f(int, required=False), "frame_sent": _f(*NUMBER, required=False),
            # optional: per marker, whether its cells read clean (kgadapt.onboard.markers.cells_are_clean)
            "clean": _f(list, required=False, max_len=1024),
        }),
        Schema("query_request", 1, {"params": _f(dict, required=False, max_len=64)}),
        Schema("cypher_request", 1, {
            "cypher": _f(str, max_len=16384), "params": _f(dict, required=False, max_len=64),
        }),
        Schema("rows", 1, {"rows": _f(list, max_len=100_000), "elapsed_ms": _f(*NUMBER, required=False)},
               max_size=MAX_PAYLOAD),
        Schema("write_request", 1, {"params": _f(dict, max_len=64)}),
        Schema("deploy_request", 1, {
            "deployment": _f(str, required=False, max_len=64), "config": _f(str, required=False, max_len=64),
            "instance": _f(str, required=False, max_len=64),
            "wait_ready": _f(bool, required=False), "ready_timeout": _f(*NUMBER, required=False),
        }),
        # In-place reconfiguration of a running detector (kgadapt.onboard.detector): ask, and what it did.
        Schema("configure_request", 1, {"config": _NAME}),
        Schema("configure_reply", 1, {
            "instance": _NAME, "config": _NAME, "previous": _NAME, "deployment": _f(str, max_len=64),
            "first_seq": _f(int, required=False), "check_ms": _f(*NUMBER), "build_ms": _f(*NUMBER),
            "first_frame_ms": _f(*NUMBER, required=False),
        }),
        # A detector's idle/active switch (kgadapt.onboard.detector): an idle detector takes no frames and publishes nothing.
        Schema("activity_request", 1, {"active": _f(bool)}),
        Schema("activity_reply", 1, {"instance": _NAME, "active": _f(bool), "processed": _f(int)}),
        Schema("deploy_reply", 1, {"ok": _f(bool), "detail": _f(dict, required=False)}),
        Schema("deploy_event", 1, {
            "event": _f(str, max_len=32), "host": _NAME, "instance": _NAME, "time": _TIME,
            "pid": _f(int, required=False), "returncode": _f(int, required=False),
            "detail": _f(str, required=False, max_len=4096),
            "run_id": _f(str, required=False, max_len=128), "deployment": _f(str, required=False, max_len=64),
            "config": _f(str, required=False, max_len=64),
        }),
        Schema("flight_state", 1, {
            "time": _TIME, "link": _f(bool), "armed": _f(bool, required=False),
            "mode": _f(str, required=False, max_len=64), "landed_state": _f(str, required=False, max_len=32),
            "battery_pct": _f(*NUMBER, required=False), "battery_v": _f(*NUMBER, required=False),
            "onboard_load": _f(*NUMBER, required=False),
            "event": _f(str, required=False, max_len=32),  # link_up, link_lost, link_restored, autopilot_rebooted
            # optional (issue 12): absent = unknown, i.e. not heard within its stream's timeout
            "alt_rel_m": _f(*NUMBER, required=False), "alt_amsl_m": _f(*NUMBER, required=False),
            "lat_deg": _f(*NUMBER, required=False), "lon_deg": _f(*NUMBER, required=False),
            "attitude": _f(list, required=False, max_len=3), "rates": _f(list, required=False, max_len=3),
            "position_ned": _f(list, required=False, max_len=3), "velocity_ned": _f(list, required=False, max_len=3),
            "rangefinder_m": _f(*NUMBER, required=False), "home": _f(list, required=False, max_len=3),
            "heard": _f(dict, required=False, max_len=16), "boot_ms": _f(int, required=False),
            "reboots": _f(int, required=False), "missing": _f(list, required=False, max_len=16),
            "refused": _f(list, required=False, max_len=16),
        }),
        Schema("adaptation_event", 1, {
            "time": _TIME, "trigger": _f(str, max_len=256), "decision": _f(dict, required=False),
            "outcome": _f(str, required=False, max_len=256),
        }),
    ]
}


def encode(kind: str, body: Mapping[str, Any]) -> bytes:
    """Pack ``body`` as a ``kind`` message, checking it against the schema first."""
    schema = _schema(kind)
    message = {"kind": kind, "v": schema.version, **body}
    _check(schema, message)
    payload: bytes = msgpack.packb(message, use_bin_type=True)
    if len(payload) > schema.max_size:
        raise MessageError(f"{kind} message of {len(payload)} bytes exceeds {schema.max_size}")
    return payload


def decode(payload: bytes | bytearray | memoryview, kind: str) -> dict[str, Any]:
    """Unpack and check a ``kind`` message; raise MessageError saying what is wrong."""
    schema = _schema(kind)
    data = bytes(payload)
    if len(data) > schema.max_size:
        raise MessageError(f"{kind} message of {len(data)} bytes exceeds {schema.max_size}")
    try:
        # The size was checked above; msgpack's unpackb() takes no max_buffer_size.
        message = msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises several unrelated types
        raise MessageError(f"{kind} message is not valid msgpack: {exc}") from exc
    if not isinstance(message, dict):
        raise MessageError(f"{kind} message is not a map but {type(message).__name__}")
    if message.get("kind") != kind:
        raise MessageError(f"expected a {kind} message, got kind {message.get('kind')!r}")
    if message.get("v") != schema.version:
        raise MessageError(f"{kind} message has version {message.get('v')!r}; this receiver reads version {schema.version}")
    _check(schema, message)
    return message


def _schema(kind: str) -> Schema:
    try:
        return SCHEMAS[kind]
    except KeyError:
        raise MessageError(f"unknown message kind {kind!r}") from None


def _check(schema: Schema, message: Mapping[str, Any]) -> None:
    for name, field in schema.fields.items():
        if name not in message or message[name] is None:
            if field.required:
                raise MessageError(f"{schema.kind} message lacks field {name!r}")
            continue
        value = message[name]
        # bool is an int in Python; a number field must not accept True.
        if isinstance(value, bool) and bool not in field.types:
            raise MessageError(f"{schema.kind} field {name!r} must be {_names(field.types)}, not bool")
        if not isinstance(value, field.types):
            raise MessageError(
                f"{schema.kind} field {name!r} must be {_names(field.types)}, not {type(value).__name__}"
            )
        if isinstance(value, float) and not math.isfinite(value):
            raise MessageError(f"{schema.kind} field {name!r} is not a finite number")
        if field.max_len is not None and hasattr(value, "__len__") and len(value) > field.max_len:
            raise MessageError(f"{schema.kind} field {name!r} is too long ({len(value)} > {field.max_len})")


def _names(types: tuple[type, ...]) -> str:
    return " or ".join(t.__name__ for t in types)
