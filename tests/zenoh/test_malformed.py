"""Every queryable and subscriber of the fabric fed malformed input: error replies or logged drops, never a crash.

Payloads come from hypothesis: random bytes, truncated valid messages,
valid messages with one field of the wrong type, wrong kind or version, and
oversized payloads. After each run the service must still answer a good
request.
"""

from __future__ import annotations

from typing import Any

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from zenoh import CongestionControl

from kgadapt.shared import keys, messages
from kgadapt.shared.hostmonitor import HostMonitor, HostMonitorSettings, squeeze_key
from tests.security import fuzz
from tests.zenoh.conftest import platform_row, wait_for

BLOCK = CongestionControl.BLOCK

FUZZ = settings(
    max_examples=40, deadline=None, derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

GOOD = {
    "query_request": {"params": {"feature": "MarkerDetection"}},
    "cypher_request": {"cypher": "RETURN $x AS x", "params": {"x": 1}},
    "write_request": {"params": {"name": "fuzzhost", "time": 1.0, "memory_free_mb": 10.0}},
    "squeeze_request": {"reserve_mb": 10.0},
    "host_status": {"host": "fuzzhost", "time": 1.0, "memory_total_mb": 100.0, "memory_free_mb": 50.0, "cpu_load": 1.0},
}

# A value of each plain type; "wrong" picks one whose type the field does not take.
ANY_VALUE = st.one_of(
    st.integers(-(2**63), 2**63 - 1), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=20),
    st.binary(max_size=20), st.lists(st.integers(), max_size=3), st.dictionaries(st.text(max_size=5), st.integers(), max_size=3),
    st.booleans(),
)


def packed(body: dict[str, Any]) -> bytes:
    return msgpack.packb(body, use_bin_type=True)


def wire(kind: str) -> dict[str, Any]:
    return {"kind": kind, "v": fuzz.version(kind), **GOOD[kind]}


def wrong_typed(kind: str) -> st.SearchStrategy[bytes]:
    """A valid ``kind`` message with one schema field replaced by a value of a type it does not take."""
    fields = fuzz.wire_fields(kind)

    def replace(pair: tuple[str, Any]) -> bytes:
        name, value = pair
        return packed({**wire(kind), name: value})

    def fits(pair: tuple[str, Any]) -> bool:
        name, value = pair
        types = fields[name].types
        return isinstance(value, bool) and bool not in types or not isinstance(value, types)

    return st.tuples(st.sampled_from(sorted(fields)), ANY_VALUE).filter(fits).map(replace)


def truncated(kind: str) -> st.SearchStrategy[bytes]:
    data = packed(wire(kind))
    return st.integers(1, len(data) - 1).map(lambda n: data[:n])


def wrong_envelope(kind: str) -> st.SearchStrategy[bytes]:
    return st.one_of(
        st.sampled_from(sorted(set(messages.KINDS) - {kind})).map(lambda other: packed({**wire(kind), "kind": other})),
        st.integers(2, 99).map(lambda v: packed({**wire(kind), "v": v})),
        st.just(packed([wire(kind)])),
        st.just(packed("just a string")),
        st.just(packed({1: 2})),
    )


def oversized(kind: str) -> st.SearchStrategy[bytes]:
    limit = fuzz.max_size(kind)
    return st.one_of(
        st.integers(limit + 1, limit + 4096).map(lambda n: b"\x00" * n),
        st.integers(limit + 1, limit + 4096).map(lambda n: packed({**wire(kind), "padding": "x" * n})),
    )


def malformed(kind: str) -> st.SearchStrategy[bytes]:
    return st.one_of(
        st.binary(min_size=1, max_size=300), truncated(kind), wrong_typed(kind), wrong_envelope(kind), oversized(kind),
    )


def ask_raw(session: Any, key: str, payload: bytes) -> tuple[str, str]:
    replies = list(session.get(key, payload=payload, timeout=3))
    assert len(replies) == 1, f"expected one reply on {key}, got {len(replies)}"
    reply = replies[0]
    if reply.ok is not None:
        return "ok", ""
    return "err", reply.err.payload.to_bytes().decode("utf-8", "replace")


@pytest.mark.parametrize("target,kind", [
    ("query/placement", "query_request"),
    ("cypher", "cypher_request"),
    ("write/platform", "write_request"),
])
def test_every_knowledge_queryable_answers_malformed_payloads_with_an_error_reply(
    zenoh_pair, client, robot, target, kind, resp_store
):
    _, session = zenoh_pair
    key = f"{keys.robot_root(robot)}/knowledge/{target}"

    @FUZZ
    @given(payload=malformed(kind))
    def check(payload: bytes) -> None:
        outcome, text = ask_raw(session, key, payload)
        assert outcome == "err", f"payload {payload[:60]!r} was accepted"
        assert text and text != "Timeout"

    check()
    assert ask_raw(session, key, packed(wire(kind)))[0] == "ok"  # still serving
    assert resp_store.execute("MATCH (p:Platform {name: 'fuzzhost'}) RETURN count(p) AS n")[0]["n"] == 1


@pytest.mark.parametrize("params", [
    {"feature": b"bytes"},
    {"feature": msgpack.ExtType(5, b"ext")},
    {"feature": [1, [2, [3]]]},
    {"feature": {"nested": "map"}},
    {"feature": 2**64 - 1},
])
def test_a_named_query_refuses_parameter_values_that_are_no_graph_values(zenoh_pair, client, robot, params):
    _, session = zenoh_pair
    payload = packed({"kind": "query_request", "v": 1, "params": params})
    outcome, text = ask_raw(session, keys.knowledge_query(robot, "placement"), payload)
    assert outcome == "err" and "feature" in text


def test_the_squeeze_queryable_answers_malformed_payloads_with_an_error_reply(zenoh_pair, robot):
    server, session = zenoh_pair
    monitor = HostMonitor(HostMonitorSettings(robot=robot, host="fuzzhost", memory_budget_mb=1000))
    monitor.setup(server)
    key = squeeze_key(robot, "fuzzhost")
    try:
        wait_for(lambda: list(session.get(key, timeout=1)), 5, "the squeeze queryable to be known")
        @FUZZ
        @given(payload=st.one_of(malformed("squeeze_request"), st.floats(max_value=-0.001).map(
            lambda v: packed({"kind": "squeeze_request", "v": 1, "reserve_mb": v}))))
        def check(payload: bytes) -> None:
            outcome, text = ask_raw(session, key, payload)
            assert outcome == "err", f"payload {payload[:60]!r} was accepted"
            assert text

        check()
        assert ask_raw(session, key, packed(wire("squeeze_request")))[0] == "ok"
    finally:
        monitor.shutdown()


def test_the_status_subscriber_drops_malformed_statuses_with_a_reason_and_keeps_applying_good_ones(
    zenoh_pair, client, service, robot
):
    _, session = zenoh_pair
    key = keys.host_status(robot, "fuzzhost")
    bad_values = st.sampled_from([
        {"memory_free_mb": -1.0}, {"cpu_load": -5}, {"cpu_cores": 0}, {"host": "otherhost"}, {"host": "bad host"},
        {"memory_total_mb": float("inf")},
    ]).map(lambda change: packed({**wire("host_status"), **change}))

    @FUZZ
    @given(payload=st.one_of(malformed("host_status"), bad_values))
    def check(payload: bytes) -> None:
        before = service.stats().get("events_dropped", 0)
        session.put(key, payload, congestion_control=BLOCK)  # Zenoh's default drops a large one under load
        wait_for(lambda: service.stats().get("events_dropped", 0) > before, 3, f"the drop of {payload[:60]!r}")
        assert service.stats()["last_drop"].startswith(f"status on {key}")

    check()
    assert platform_row(client, "fuzzhost")["memory_free_mb"] is None  # nothing malformed reached the graph
    session.put(key, messages.encode("host_status", {**GOOD["host_status"], "memory_free_mb": 42.0}),
                congestion_control=BLOCK)
    wait_for(lambda: (platform_row(client, "fuzzhost") or {}).get("memory_free_mb") == 42.0, 3, "the good status")


def test_the_liveliness_subscriber_drops_tokens_with_bad_host_names(zenoh_pair, client, service, robot):
    _, session = zenoh_pair
    chunks = st.one_of(
        st.text(alphabet="abc.:+@~é", min_size=1, max_size=10).filter(lambda t: not t.isalpha() or "é" in t),
        st.integers(65, 200).map(lambda n: "h" * n),
    )

    @FUZZ
    @given(chunk=chunks)
    def check(chunk: str) -> None:
        before = service.stats().get("events_dropped", 0)
        try:
            token = session.liveliness().declare_token(f"{keys.robot_root(robot)}/host/{chunk}/alive")
        except Exception:
            return  # Zenoh itself refuses that key: nothing reaches the service
        wait_for(lambda: service.stats().get("events_dropped", 0) > before, 3, f"the drop of token {chunk!r}")
        token.undeclare()
        wait_for(lambda: service.stats().get("events_dropped", 0) > before + 1, 3, f"the drop of {chunk!r}'s end")

    check()
    token = session.liveliness().declare_token(keys.host_alive(robot, "goodhost"))
    try:
        wait_for(lambda: (platform_row(client, "goodhost") or {}).get("online") is True, 3, "the good token")
    finally:
        token.undeclare()
    online = [row["platform"] for row in client.query("platforms", {}) if row["online"] is not None]
    assert online == ["goodhost"]  # no token with a bad name reached the graph


def test_a_flood_of_statuses_is_coalesced_to_the_newest_per_host(zenoh_pair, client, service, robot):
    _, session = zenoh_pair
    # BLOCK: every one of the 1000 must arrive (with Zenoh's default, a loaded machine dropped some).
    publishers = {h: session.declare_publisher(keys.host_status(robot, h), congestion_control=BLOCK)
                  for h in ("h1", "h2")}
    for i in range(500):
        for host, pub in publishers.items():
            pub.put(messages.encode("host_status", {**GOOD["host_status"], "host": host, "memory_total_mb": 1000.0,
                                                    "memory_free_mb": float(i)}))
    for host in publishers:
        wait_for(lambda h=host: (platform_row(client, h) or {}).get("memory_free_mb") == 499.0, 30, f"{host}'s last status")
    stats = service.stats()
    assert stats["events_received"] == 1000
    assert stats["status_applied"] < 1000  # the worker wrote only the newest of what piled up
    for pub in publishers.values():
        pub.undeclare()
