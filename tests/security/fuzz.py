"""Hypothesis strategies for malformed wire messages of any kind (the Structs of shared/messages.py).

``malformed(kind, good)`` draws payloads no receiver may accept: random
bytes, a valid message cut short, one field of a wrong type, a field
missing, the wrong kind or version, not a map, non-string map keys, and
(rarely) a payload over the kind's size limit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import msgpack
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from msgspec import inspect as mi

from kgadapt.shared import messages

FUZZ = settings(
    max_examples=60, deadline=None, derandomize=True, database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

@dataclass(frozen=True)
class WireField:
    """One field of a kind as a receiver takes it: the Python types msgpack gives for it, whether it must be there."""

    types: tuple[type, ...]
    required: bool


def _types(t: Any) -> tuple[type, ...]:
    if isinstance(t, mi.UnionType):
        return tuple(x for part in t.types if not isinstance(part, mi.NoneType) for x in _types(part))
    if isinstance(t, mi.FloatType):
        return (int, float)
    simple = {mi.IntType: int, mi.BoolType: bool, mi.StrType: str, mi.BytesType: bytes, mi.EnumType: str,
              mi.ListType: list, mi.DictType: dict, mi.StructType: dict}
    return next(((v,) for k, v in simple.items() if isinstance(t, k)), (object,))


def wire_fields(kind: str) -> dict[str, WireField]:
    """Every field of ``kind`` but its version ``v``, read from its Struct."""
    info = mi.type_info(messages.KINDS[kind])
    assert isinstance(info, mi.StructType)
    return {f.name: WireField(_types(f.type), f.required) for f in info.fields if f.name != "v"}


def version(kind: str) -> int:
    return messages.version_of(messages.KINDS[kind])


def max_size(kind: str) -> int:
    return messages.KINDS[kind].MAX_SIZE


# A value of each plain type msgpack carries; wrong_typed picks one the field does not take.
ANY_VALUE = st.one_of(
    st.integers(-(2**63), 2**64 - 1), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=20),
    st.binary(max_size=20), st.lists(st.integers(), max_size=3), st.none(),
    st.dictionaries(st.text(max_size=5), st.integers(), max_size=3), st.booleans(),
)


def packed(body: Any) -> bytes:
    return msgpack.packb(body, use_bin_type=True)


def wire(kind: str, good: Mapping[str, Any]) -> dict[str, Any]:
    """``good`` as a complete ``kind`` message (checked, so the strategies start from a valid one)."""
    message = {"kind": kind, "v": version(kind), **good}
    messages.decode(packed(message), kind)
    return message


def truncated(kind: str, good: Mapping[str, Any]) -> st.SearchStrategy[bytes]:
    data = packed(wire(kind, good))
    return st.integers(1, len(data) - 1).map(lambda n: data[:n])


def wrong_typed(kind: str, good: Mapping[str, Any]) -> st.SearchStrategy[bytes]:
    fields = wire_fields(kind)

    def refused(pair: tuple[str, Any]) -> bool:
        name, value = pair
        field = fields[name]
        if value is None:
            return field.required
        if isinstance(value, bool):
            return bool not in field.types
        return not isinstance(value, field.types) or (isinstance(value, float) and value != value)

    return (st.tuples(st.sampled_from(sorted(fields)), ANY_VALUE).filter(refused)
            .map(lambda pair: packed({**wire(kind, good), pair[0]: pair[1]})))


def missing_field(kind: str, good: Mapping[str, Any]) -> st.SearchStrategy[bytes]:
    required = sorted(name for name, field in wire_fields(kind).items() if field.required)
    return st.sampled_from(required).map(lambda name: packed({k: v for k, v in wire(kind, good).items() if k != name}))


def wrong_envelope(kind: str, good: Mapping[str, Any]) -> st.SearchStrategy[bytes]:
    message = wire(kind, good)
    return st.one_of(
        st.sampled_from(sorted(set(messages.KINDS) - {kind})).map(lambda other: packed({**message, "kind": other})),
        st.integers(2, 99).map(lambda v: packed({**message, "v": v})),
        st.just(packed({k: v for k, v in message.items() if k != "kind"})),
        st.just(packed([message])),
        st.just(packed("just a string")),
        st.just(packed({1: 2, **message})),
        st.just(b""),
    )


def oversized(kind: str) -> st.SearchStrategy[bytes]:
    return st.just(b"\x00" * (max_size(kind) + 1))


def malformed(kind: str, good: Mapping[str, Any]) -> st.SearchStrategy[bytes]:
    """Payloads a receiver of ``kind`` must refuse (``good`` is one valid body it would accept)."""
    return st.one_of(
        st.binary(min_size=1, max_size=200), truncated(kind, good), wrong_typed(kind, good),
        missing_field(kind, good), wrong_envelope(kind, good), oversized(kind),
    )
