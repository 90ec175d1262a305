"""Wire messages: msgpack maps with a kind and a schema version, checked on receipt.

Every payload is a map ``{"kind": KIND, "v": VERSION, ...fields}``. Each kind is a
frozen, keyword-only :class:`msgspec.Struct` below (the union :data:`Message` is
tagged on ``kind``); process states, process events, triggers and changes are the
enums of :mod:`kgadapt.shared.states`, so an unknown value is refused naming its
field. ``encode`` checks what we send as a receiver would; ``decode`` checks what we
receive and raises :class:`MessageError` naming the problem (not msgpack, not a map,
wrong kind, unknown version, missing or ill-typed field with its path, a number that
is not finite, oversized) so that a queryable can answer with an error reply and a
subscriber can log a drop and go on.

Runtime code sends Structs (``encode(HostStatus(...))``) and receives them
(:func:`decode_as`, :func:`decode_any`): no wire message is a map inside the project
(tests/test_typed_messages.py scans for it). ``encode(kind, body)`` and ``decode`` (the
map as sent) are for tests and tools that write or read the wire as an outsider does.

Fields not in a Struct are kept, not refused: a newer sender may add optional
fields without breaking older receivers (the Struct of :func:`decode_as` ignores
them; :func:`decode_with_unknown` names them for a receiver that refuses them). A
new *required* field or a changed meaning needs a new version.

docs/CONTRACTS.md, section "Message kinds", is generated from these types
(``python -m kgadapt.shared.messages docs/CONTRACTS.md``); tests/test_messages.py
checks that it is up to date.
"""

from __future__ import annotations

import functools
import re
import sys
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, ClassVar, TypeVar, Union

import msgspec
from msgspec import Meta, Struct

from kgadapt.shared.errors import MessageError
from kgadapt.shared.states import Change, ProcessEventKind, ProcessState, ReflexEvidence, TriggerKind

MAX_PAYLOAD = 8 * 1024 * 1024  # a 1080p JPEG is well under this
MAX_SMALL = 256 * 1024  # everything that is not a frame

# Field types. A number is a float on the wire or an int (taken as a float), never a bool,
# NaN or an infinity: the bounds below refuse NaN and the infinities.
_LARGEST = 1.7976931348623157e308
Number = Annotated[float, Meta(ge=-_LARGEST, le=_LARGEST)]
Name = Annotated[str, Meta(max_length=64)]  # a host, instance, configuration or camera name
Str32 = Annotated[str, Meta(max_length=32)]
Str128 = Annotated[str, Meta(max_length=128)]
Str256 = Annotated[str, Meta(max_length=256)]
Str4096 = Annotated[str, Meta(max_length=4096)]
Params = Annotated[dict[str, Any], Meta(max_length=64)]  # named-query, Cypher or write parameters
Triple = Annotated[list[Any], Meta(max_length=3)]
Items = Annotated[list[Any], Meta(max_length=1024)]  # one entry per marker


def _version(number: int) -> Any:
    """A kind's version ``v``: a default from a factory, which ``omit_defaults`` never leaves out."""
    return msgspec.field(default_factory=lambda: number)


class Message(Struct, frozen=True, kw_only=True, tag_field="kind", omit_defaults=True):
    """What every kind has: its schema version ``v`` (the tag ``kind`` is the Struct's).

    An unset optional field is left out, as the first senders' maps left it out (a receiver reads an
    absent field and a nil one alike); ``kind`` and ``v`` are always sent.
    """

    MAX_SIZE: ClassVar[int] = MAX_SMALL
    v: int = _version(1)


class HostStatus(Message, tag="host_status", frozen=True, kw_only=True):
    host: Name
    time: Number
    memory_total_mb: Number
    memory_free_mb: Number
    cpu_load: Number  # percent of one core: 2 busy cores = 200
    cpu_cores: int | None = None
    budget_mb: Number | None = None
    ours_mb: Number | None = None
    reserved_mb: Number | None = None
    # The sender: random per monitor life, and a number that grows with each status (StatusTrust
    # tells a second sender on a host's key by them).
    origin: Str32 | None = None
    seq: int | None = None


class SqueezeRequest(Message, tag="squeeze_request", frozen=True, kw_only=True):
    reserve_mb: Number  # >= 0; 0 lifts the reservation (checked by the host monitor)


class Frame(Message, tag="frame", frozen=True, kw_only=True):
    MAX_SIZE: ClassVar[int] = MAX_PAYLOAD
    camera: Name
    seq: int
    time: Number
    width: int
    height: int
    jpeg: Annotated[bytes, Meta(max_length=MAX_PAYLOAD)]
    truth: Items | None = None
    level: Number | None = None
    sent: Number | None = None  # publication time (capture "time" is before encoding)


class Illumination(Message, tag="illumination", frozen=True, kw_only=True):
    camera: Name
    seq: int
    time: Number
    mean: Number
    p5: Number
    p50: Number
    p95: Number
    smoothed: Number
    # from kgadapt.onboard.perception.illumination.estimate_light: the robust level the band is read from
    # (smoothed is its EMA), and what it used
    level: Number | None = None
    frame_level: Number | None = None
    marker_level: Number | None = None
    source: Name | None = None
    usable: Number | None = None
    saturated: Number | None = None
    black: Number | None = None
    markers: int | None = None


class Detections(Message, tag="detections", frozen=True, kw_only=True):
    instance: Name
    config: Name
    host: Name
    seq: int
    frame_time: Number
    time: Number
    ids: Items
    corners: Items
    processing_ms: Number
    # from kgadapt.onboard.perception.detector: when the frame arrived, JPEG decode time, stale frames dropped so
    # far, and the camera's publication time of the frame (transport = received - frame_sent)
    camera: Name | None = None
    received: Number | None = None
    decode_ms: Number | None = None
    dropped: int | None = None
    frame_sent: Number | None = None
    clean: Items | None = None  # per marker, whether its cells read clean (kgadapt.onboard.perception.markers.cells_are_clean)
    # Per marker, a pose its detector measured itself ([x, y, z] m or {"tvec": [x, y, z]}; docs/flight.md), which
    # the flight bridge sends as the target's position (the detectors of this project measure none).
    poses: Items | None = None


class Reflex(Message, tag="reflex", frozen=True, kw_only=True):
    """A running detector switched configuration on its own, between two frames (kgadapt.onboard.perception.reflex),
    or (``config`` nil) found the light in a band nothing it may take in place is for."""

    instance: Name
    host: Name
    config: Name | None = None  # what it runs from frame ``seq`` on
    previous: Name  # what it ran before
    deployment: Name | None = None  # the deployment ``config`` belongs to
    elsewhere: Name | None = None  # config nil: the band's best, which needs another process
    band: Name
    from_band: Name | None = None
    evidence: ReflexEvidence
    level: Number | None = None  # the frame's light estimate
    seq: int  # the first frame of the camera processed with ``config``
    frame_time: Number  # its capture time
    time: Number
    count: int  # the detector's reflexes so far (a receiver acts once per count)
    # The last reflex is put again about once a second (``again``), so a receiver that lost it (stopped,
    # its link dropped) still gets it; with the detector's hedging so far: frames processed, frames on
    # which it also ran a second configuration, and the ms that cost in all.
    again: bool | None = None
    frames: int | None = None
    hedged: int | None = None
    hedge_ms: Number | None = None


class QueryRequest(Message, tag="query_request", frozen=True, kw_only=True):
    params: Params | None = None


class CypherRequest(Message, tag="cypher_request", frozen=True, kw_only=True):
    cypher: Annotated[str, Meta(max_length=16384)]
    params: Params | None = None


class Rows(Message, tag="rows", frozen=True, kw_only=True):
    MAX_SIZE: ClassVar[int] = MAX_PAYLOAD
    rows: Annotated[list[dict[str, Any]], Meta(max_length=100_000)]
    elapsed_ms: Number | None = None  # time in the store


class WriteRequest(Message, tag="write_request", frozen=True, kw_only=True):
    params: Params


class DeployRequest(Message, tag="deploy_request", frozen=True, kw_only=True):
    """Which fields a verb takes is the deployer's to say (it refuses the others, naming them)."""

    deployment: Name | None = None
    config: Name | None = None
    instance: Name | None = None
    wait_ready: bool | None = None  # absent: true
    ready_timeout: Number | None = None  # seconds
    # absent: false. start: true starts a detector idle (a warm standby); list: true also names the
    # launcher's idle pool members (``Launcher.idle_members``).
    idle: bool | None = None


class ResolvedConfig(Message, tag="resolved_config", frozen=True, kw_only=True):
    """The configuration a deployer resolved from the graph (named query ``detector_config``) for a start,
    handed to the started detector so that it does not ask for it again. The graph stays the source: a
    detector takes it only for the configuration it was started with, and asks the graph for any other."""

    config: Name
    config_json: Annotated[str, Meta(max_length=65536)]
    dictionary: Str128 | None = None
    deployment: Name | None = None
    memory_demand_mb: Number | None = None
    # Which answer of the graph it is: the deployer's clock when it asked, and a digest of the row
    # (the store keeps no version number; a changed row has another digest).
    resolved_at: Number
    digest: Str128


class Launcher(Struct, frozen=True, kw_only=True, omit_defaults=True):
    """A deployer's launcher (the forking helper its detectors start from)."""

    pid: int | None = None
    ready: bool | None = None
    # The pids of its idle pool members (forked ahead of starts; deploy/launcher.py), so that whoever
    # looks for stray detector processes can tell them from orphans; only for a list request with idle.
    idle_members: Annotated[list[int], Meta(max_length=64)] | None = None


class ProcessDetail(Struct, frozen=True, kw_only=True, omit_defaults=True):
    """One supervised process as a deployer reports it (``kgadapt.deploy.supervisor.ProcessInfo``)."""

    instance: str | None = None
    host: str | None = None
    deployment: str | None = None
    config: str | None = None
    state: ProcessState | None = None
    pid: int | None = None
    run_id: str | None = None
    restarts: int | None = None
    started_at: Number | None = None
    ready_at: Number | None = None
    ended_at: Number | None = None
    returncode: int | None = None
    argv: list[str] | None = None
    detail: str | None = None
    output: list[str] | None = None  # the last lines the current (or last) run printed
    via: str | None = None  # "launcher" (forked) or "exec"


class DeployDetail(ProcessDetail, frozen=True, kw_only=True, omit_defaults=True):
    """``detail`` of a ``deploy_reply``: one process (start, stop, status), the host's list, or a refusal."""

    processes: list[ProcessDetail] | None = None  # list
    launcher: Launcher | None = None  # list
    error: str | None = None  # a refusal (ok false): what was wrong
    error_type: Annotated[str, Meta(max_length=64)] | None = None  # its class in kgadapt.shared.errors


class DeployReply(Message, tag="deploy_reply", frozen=True, kw_only=True):
    ok: bool
    detail: DeployDetail | None = None


class ConfigureRequest(Message, tag="configure_request", frozen=True, kw_only=True):
    """In-place reconfiguration of a running detector (kgadapt.onboard.perception.detector)."""

    config: Name


class ConfigureReply(Message, tag="configure_reply", frozen=True, kw_only=True):
    instance: Name
    config: Name
    previous: Name
    deployment: Name
    first_seq: int | None = None  # the first frame processed with the new configuration
    check_ms: Number
    build_ms: Number
    first_frame_ms: Number | None = None


class ActivityRequest(Message, tag="activity_request", frozen=True, kw_only=True):
    """A detector's idle/active switch: an idle detector takes no frames and publishes nothing."""

    active: bool


class ActivityReply(Message, tag="activity_reply", frozen=True, kw_only=True):
    instance: Name
    active: bool
    processed: int


class DeployEvent(Message, tag="deploy_event", frozen=True, kw_only=True):
    event: ProcessEventKind
    host: Name
    instance: Name
    time: Number
    pid: int | None = None
    returncode: int | None = None  # negative: a signal
    detail: Str4096 | None = None
    run_id: Str128 | None = None
    deployment: Name | None = None
    config: Name | None = None


class FlightState(Message, tag="flight_state", frozen=True, kw_only=True):
    """The flight controller's state from the MAVLink bridge; an absent figure is unknown (not heard in time)."""

    time: Number
    link: bool
    armed: bool | None = None
    mode: Name | None = None
    landed_state: Str32 | None = None
    battery_pct: Number | None = None
    battery_v: Number | None = None
    onboard_load: Number | None = None
    event: Str32 | None = None  # link_up, link_lost, link_restored, autopilot_rebooted
    alt_rel_m: Number | None = None
    alt_amsl_m: Number | None = None
    lat_deg: Number | None = None
    lon_deg: Number | None = None
    attitude: Triple | None = None
    rates: Triple | None = None
    position_ned: Triple | None = None
    velocity_ned: Triple | None = None
    rangefinder_m: Number | None = None
    home: Triple | None = None
    heard: Annotated[dict[str, Any], Meta(max_length=16)] | None = None
    boot_ms: int | None = None
    reboots: int | None = None
    missing: Annotated[list[Any], Meta(max_length=16)] | None = None
    refused: Annotated[list[Any], Meta(max_length=16)] | None = None
    # COMMAND_ACKs that rejected a command since the link started, a rejection later retried and
    # accepted included (TEMPORARILY_REJECTED): a refusal stays visible after its retry succeeds. Absent: none.
    rejected: int | None = None
    # True while the landing targets sent carry angles only (no marker size known, no rangefinder
    # distance): ArduPilot cannot place such a target without its own rangefinder. Absent otherwise.
    angles_only: bool | None = None
    # Which autopilot the state is of (the bridge follows the first it hears): its MAVLink system id,
    # its kind (ardupilot, px4, generic, else the MAV_AUTOPILOT number) and its last HEARTBEAT, epoch s.
    system_id: int | None = None
    autopilot: Str32 | None = None
    last_heartbeat: Number | None = None


class Decision(Struct, frozen=True, kw_only=True, omit_defaults=True):
    """``decision`` of an ``adaptation_event``: what the adaptation manager chose and how it went."""

    name: str | None = None  # the Decision node's name in the graph
    trigger_kind: TriggerKind | None = None
    trigger_time: Number | None = None
    change: Change | None = None
    config: str | None = None
    host: str | None = None
    instance: str | None = None
    previous_instance: str | None = None
    latency_ms: Number | None = None
    frames_lost: int | None = None


class AdaptationEvent(Message, tag="adaptation_event", frozen=True, kw_only=True):
    time: Number
    trigger: Str256
    decision: Decision | None = None
    outcome: Str256 | None = None


# The tagged union of every kind: msgspec picks the Struct by ``kind``.
AnyMessage = Union[
    HostStatus, SqueezeRequest, Frame, Illumination, Detections, Reflex, QueryRequest, CypherRequest, Rows, WriteRequest,
    DeployRequest, ResolvedConfig, ConfigureRequest, ConfigureReply, ActivityRequest, ActivityReply, DeployReply, DeployEvent,
    FlightState, AdaptationEvent,
]
KINDS: dict[str, type[Message]] = {str(t.__struct_config__.tag): t for t in typing.get_args(AnyMessage)}

M = TypeVar("M", bound=Message)

_RAW = msgspec.msgpack.Decoder()
_ENCODER = msgspec.msgpack.Encoder(enc_hook=lambda obj: _plain(obj))


def _plain(obj: object) -> object:
    # float subclasses (numpy.float64) go as floats, as msgpack-python sent them.
    if isinstance(obj, float):
        return float(obj)
    raise TypeError(f"cannot send a {type(obj).__name__}")


# What encode checks its payload with: the Struct's own decoder, one typed pass.


@functools.cache
def _decoder(cls: type[Message]) -> msgspec.msgpack.Decoder[Any]:
    # Made on first use: building all 18 at import cost a new detector process ~50 ms before it was ready.
    return msgspec.msgpack.Decoder(cls)


def kind_of(cls: type[Message]) -> str:
    return str(cls.__struct_config__.tag)


@functools.cache
def version_of(cls: type[Message]) -> int:
    # v is the first field of every kind; looked up once, on first use (resolving the annotations costs).
    return int(msgspec.structs.fields(cls)[0].default_factory())


def encode(message: Message | str, body: Mapping[str, Any] | None = None) -> bytes:
    """Pack a message: a Struct, or ``body`` as a ``kind`` message; checked as a receiver checks it.

    A ``body`` map may carry fields the Struct does not know: they are sent. The map form is for tests and
    tools that write the wire as an outsider does; runtime code builds the Struct.
    """
    what: Message | dict[str, Any]
    if isinstance(message, Message):
        cls, what = type(message), message
        if message.v != version_of(cls):
            raise MessageError(f"a {kind_of(cls)} message has version {message.v}; this sender writes {version_of(cls)}")
    else:
        cls = _kind(message)
        version = version_of(cls)
        if body and (body.get("kind", message) != message or body.get("v", version) != version):
            raise MessageError(f"a {message} body names kind {body.get('kind')!r}, version {body.get('v')!r}")
        what = {"kind": message, "v": version, **(body or {})}
    kind = kind_of(cls)
    try:
        payload = _ENCODER.encode(what)
    except (TypeError, ValueError, OverflowError) as exc:
        raise MessageError(f"{kind} message cannot be packed: {exc}") from exc
    if len(payload) > cls.MAX_SIZE:
        raise MessageError(f"{kind} message of {len(payload)} bytes exceeds {cls.MAX_SIZE}")
    try:
        # Kind and version are ours, so the receiver's field checks suffice: one typed pass.
        _decoder(cls).decode(payload)
    except msgspec.ValidationError as exc:
        raise MessageError(_explain(kind, exc)) from exc
    return payload


def decode(payload: bytes | bytearray | memoryview, kind: str) -> dict[str, Any]:
    """Unpack and check a ``kind`` message; its map as sent (unknown fields kept). MessageError says what is wrong.

    For tests and tools that look at the wire as an outsider does; runtime code receives a Struct.
    """
    return _load(payload, _kind(kind))[0]


def decode_as(payload: bytes | bytearray | memoryview, cls: type[M]) -> M:
    """Unpack and check a message of the kind ``cls``; MessageError says what is wrong."""
    message = _load(payload, cls)[1]
    assert isinstance(message, cls)
    return message


def decode_with_unknown(payload: bytes | bytearray | memoryview, cls: type[M]) -> tuple[M, tuple[str, ...]]:
    """:func:`decode_as`, and the names of the fields ``cls`` does not know (sorted), for a receiver that
    refuses them (the deployer: a request names what to run, never how)."""
    raw, message = _load(payload, cls)
    assert isinstance(message, cls)
    return message, tuple(sorted(set(raw) - {"kind"} - set(cls.__struct_fields__)))


def decode_any(payload: bytes | bytearray | memoryview) -> Message:
    """Unpack and check a message of whichever kind it says it is."""
    try:
        kind = _RAW.decode(payload).get("kind")
    except (msgspec.MsgspecError, AttributeError, RecursionError) as exc:
        raise MessageError(f"message is not a valid msgpack map: {exc}") from exc
    if not isinstance(kind, str):
        raise MessageError(f"message has no kind but {kind!r}")
    return _load(payload, _kind(kind))[1]


def _kind(kind: str) -> type[Message]:
    try:
        return KINDS[kind]
    except KeyError:
        raise MessageError(f"unknown message kind {kind!r}") from None


def _load(payload: bytes | bytearray | memoryview, cls: type[Message]) -> tuple[dict[str, Any], Message]:
    kind, version = kind_of(cls), version_of(cls)
    if len(payload) > cls.MAX_SIZE:
        raise MessageError(f"{kind} message of {len(payload)} bytes exceeds {cls.MAX_SIZE}")
    try:
        raw = _RAW.decode(payload)
    except (msgspec.MsgspecError, RecursionError) as exc:
        raise MessageError(f"{kind} message is not valid msgpack: {exc}") from exc
    if not isinstance(raw, dict):
        raise MessageError(f"{kind} message is not a map but {type(raw).__name__}")
    if raw.get("kind") != kind:
        raise MessageError(f"expected a {kind} message, got kind {raw.get('kind')!r}")
    if raw.get("v") != version:
        raise MessageError(f"{kind} message has version {raw.get('v')!r}; this receiver reads version {version}")
    try:
        # bytes stay bytes: a str is not taken as base64 for one.
        message = msgspec.convert(raw, cls, builtin_types=(bytes,))
    except msgspec.ValidationError as exc:
        raise MessageError(_explain(kind, exc)) from exc
    return raw, message


_WHERE = re.compile(r"^(?P<what>.*?)(?: - at `(?P<path>[^`]*)`)?$", re.S)
_MISSING = re.compile(r"^Object missing required field `(?P<name>[^`]+)`$")


def _explain(kind: str, exc: msgspec.ValidationError) -> str:
    """msgspec's complaint as ours: the field's path without ``$.``, "finite" for NaN and infinities, "number"."""
    text = str(exc)
    if " - at `key` in `" in text:
        where = text.rsplit(" - at `key` in `", 1)[1].rstrip("`")
        where = "" if where == "$" else f" in {where.removeprefix('$.')!r}"
        return f"{kind} message has a map key that is not a string{where}"
    match = _WHERE.match(text)
    what, path = (match.group("what"), match.group("path") or "$") if match else (text, "$")
    field = path[2:] if path.startswith("$.") else path.removeprefix("$")
    missing = _MISSING.match(what)
    if missing:
        name = f"{field}.{missing.group('name')}" if field else missing.group("name")
        return f"{kind} message lacks field {name!r}"
    if repr(_LARGEST) in what:
        what = "must be a finite number"
    # A Number is a float in msgspec's words but takes an int too: say "number", as docs/CONTRACTS.md does.
    what = what.replace("Expected `float", "Expected `number")
    if not field:
        return f"{kind} message: {what}"
    return f"{kind} field {field!r}: {what}"


# -- the contract's table, read from the Structs ----------------------------------------------------------


def _words(t: Any) -> str:
    """One msgspec type in the words of docs/CONTRACTS.md."""
    from msgspec import inspect as mi

    if isinstance(t, mi.UnionType):
        return " or ".join(_words(p) for p in t.types if not isinstance(p, mi.NoneType))
    limit = f" ≤ {t.max_length}" if getattr(t, "max_length", None) else ""
    if isinstance(t, mi.FloatType):
        return "number"
    if isinstance(t, mi.IntType):
        return "int"
    if isinstance(t, mi.BoolType):
        return "bool"
    if isinstance(t, mi.StrType):
        return "str" + limit
    if isinstance(t, mi.BytesType):
        return "bytes" + limit
    if isinstance(t, (mi.EnumType, mi.StructType)):
        return f"`{t.cls.__name__}`"
    if isinstance(t, mi.ListType):
        item = "" if isinstance(t.item_type, mi.AnyType) else f" of {_words(t.item_type)}"
        return "list" + item + limit
    if isinstance(t, mi.DictType):
        return "map" + limit
    if isinstance(t, mi.LiteralType):
        return " or ".join(map(repr, t.values))
    return "any"


def _cells(cls: type[Struct]) -> str:
    """The "fields | optional fields" cells of a Struct (a kind's version ``v`` left out)."""
    from msgspec import inspect as mi

    info = mi.type_info(cls)
    assert isinstance(info, mi.StructType)
    fields = [f for f in info.fields if not (f.name == "v" and issubclass(cls, Message))]
    required = [f"`{f.name}` ({_words(f.type)})" for f in fields if f.required]
    optional = [f"`{f.name}` ({_words(f.type)})" for f in fields if not f.required]
    return ", ".join(required) + (" | " if required else "— | ") + (", ".join(optional) or "—")


NESTED: tuple[type[Struct], ...] = (DeployDetail, ProcessDetail, Launcher, Decision)
ENUMS = (ProcessState, ProcessEventKind, TriggerKind, Change)

BEGIN = "<!-- message kinds: generated by `python -m kgadapt.shared.messages docs/CONTRACTS.md` -->"
END = "<!-- end of message kinds -->"


def contract_table() -> str:
    """The "Message kinds" tables of docs/CONTRACTS.md, from the Structs above."""
    lines = [BEGIN, "", "| kind | v | max bytes | fields | optional fields |", "|---|---|---|---|---|"]
    for kind, cls in KINDS.items():
        lines.append(f"| `{kind}` | {version_of(cls)} | {cls.MAX_SIZE} | {_cells(cls)} |")
    lines += ["", "Nested maps:", "", "| map | fields | optional fields |", "|---|---|---|"]
    for nested in NESTED:
        lines.append(f"| `{nested.__name__}` | {_cells(nested)} |")
    lines += ["", END]
    return "\n".join(lines)


def update_doc(path: Path) -> bool:
    """Rewrite the generated section of ``path``; True when it changed."""
    text = path.read_text()
    start, end = text.index(BEGIN), text.index(END) + len(END)
    new = text[:start] + contract_table() + text[end:]
    if new != text:
        path.write_text(new)
    return new != text


if __name__ == "__main__":
    for name in sys.argv[1:] or ["docs/CONTRACTS.md"]:
        print(f"{name}: {'updated' if update_doc(Path(name)) else 'up to date'}")
