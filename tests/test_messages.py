"""The wire contract as types (kgadapt.shared.messages): every kind round-trips, what a receiver refuses is
refused naming the field, unknown fields are kept, and docs/CONTRACTS.md's table is the types'."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import msgpack
import pytest

from kgadapt.shared import messages
from kgadapt.shared.errors import MessageError
from kgadapt.shared.states import Change, ProcessEventKind, ProcessState, TriggerKind

DOCS = Path(__file__).resolve().parents[1] / "docs"

# One valid body of each kind, optional fields included where they are typed more than "any".
GOOD: dict[str, dict[str, Any]] = {
    "host_status": {"host": "onboard", "time": 1.0, "memory_total_mb": 4000.0, "memory_free_mb": 1000, "cpu_load": 12.5,
                    "cpu_cores": 4, "budget_mb": 3000.0},
    "squeeze_request": {"reserve_mb": 10.0},
    "frame": {"camera": "cam0", "seq": 1, "time": 1.0, "width": 4, "height": 4, "jpeg": b"\xff\xd8", "truth": []},
    "illumination": {"camera": "cam0", "seq": 1, "time": 1.0, "mean": 1, "p5": 1, "p50": 1, "p95": 1, "smoothed": 1.0,
                     "source": "frame", "markers": 2},
    "detections": {"instance": "det1", "config": "marker_detection_day", "host": "onboard", "seq": 3, "frame_time": 1.0,
                   "time": 1.1, "ids": [7], "corners": [[[0, 0], [1, 0], [1, 1], [0, 1]]], "processing_ms": 4.0,
                   "clean": [True]},
    "reflex": {"instance": "det1", "host": "onboard", "config": "marker_detection_dark", "previous": "marker_detection_day",
               "deployment": "detector_dark", "band": "dark", "from_band": "day", "evidence": "light", "level": 5.2,
               "seq": 3, "frame_time": 1.0, "time": 1.03, "count": 1, "again": True, "frames": 300, "hedged": 12,
               "hedge_ms": 80.5},
    "query_request": {"params": {"config": "marker_detection_day"}},
    "cypher_request": {"cypher": "RETURN $x AS x", "params": {"x": 1}},
    "rows": {"rows": [{"x": 1}], "elapsed_ms": 0.5},
    "write_request": {"params": {"name": "onboard", "time": 1.0}},
    "deploy_request": {"deployment": "detector_day", "config": "marker_detection_day", "wait_ready": False,
                       "ready_timeout": 5},
    "resolved_config": {"config": "marker_detection_day", "config_json": "{}", "dictionary": "DICT_4X4_50",
                        "deployment": "detector_day", "memory_demand_mb": 120.0, "resolved_at": 1.0,
                        "digest": "0123abcd"},
    "configure_request": {"config": "marker_detection_dusk"},
    "configure_reply": {"instance": "det1", "config": "marker_detection_dusk", "previous": "marker_detection_day",
                        "deployment": "detector_dusk", "first_seq": 12, "check_ms": 1.0, "build_ms": 2.0},
    "activity_request": {"active": True},
    "activity_reply": {"instance": "det1", "active": False, "processed": 10},
    "deploy_reply": {"ok": True, "detail": {"host": "onboard", "processes": [
        {"instance": "det1", "state": "running", "pid": 42, "argv": ["python", "-m", "x"], "started_at": 1.0}],
        "launcher": {"pid": 41, "ready": True}}},
    "deploy_event": {"event": "started", "host": "onboard", "instance": "det1", "time": 1.0, "pid": 42,
                     "run_id": "r1"},
    "flight_state": {"time": 1.0, "link": True, "armed": True, "mode": "LOITER", "attitude": [0.0, 0.1, 0.2],
                     "heard": {"HEARTBEAT": 1.0}},
    "adaptation_event": {"time": 1.0, "trigger": "band_changed(dusk)", "outcome": "done", "decision": {
        "name": "quad1-decision-1", "trigger_kind": "band_changed", "change": "migrate", "config": "marker_detection_dusk",
        "host": "remote", "latency_ms": 120.5, "frames_lost": 0, "trigger_time": 0.5}},
}


def test_every_kind_has_a_good_example():
    assert set(GOOD) == set(messages.KINDS)


@pytest.mark.parametrize("kind", sorted(GOOD))
def test_every_kind_round_trips_as_a_map_and_as_its_struct(kind):
    payload = messages.encode(kind, GOOD[kind])
    raw = msgpack.unpackb(payload, raw=False)
    assert raw == {"kind": kind, "v": 1, **GOOD[kind]}  # the same map an outsider writes from the docs
    assert messages.decode(payload, kind) == raw
    struct = messages.decode_as(payload, messages.KINDS[kind])
    assert type(struct) is messages.KINDS[kind] and struct.v == 1
    assert messages.decode_any(payload) == struct
    again = messages.encode(struct)  # the Struct packs to a message that decodes to the same Struct
    assert messages.decode_as(again, messages.KINDS[kind]) == struct
    assert msgpack.unpackb(again, raw=False)["kind"] == kind


def test_typed_access_gives_the_enums_and_nested_structs():
    event = messages.decode_as(messages.encode("adaptation_event", GOOD["adaptation_event"]), messages.AdaptationEvent)
    assert event.decision is not None and event.decision.trigger_kind is TriggerKind.BAND_CHANGED
    assert event.decision.change is Change.MIGRATE
    reply = messages.decode_as(messages.encode("deploy_reply", GOOD["deploy_reply"]), messages.DeployReply)
    assert reply.detail is not None and reply.detail.processes is not None
    assert reply.detail.processes[0].state is ProcessState.RUNNING
    assert messages.decode_as(messages.encode("deploy_event", GOOD["deploy_event"]),
                              messages.DeployEvent).event is ProcessEventKind.STARTED
    status = messages.decode_as(messages.encode("host_status", GOOD["host_status"]), messages.HostStatus)
    assert status.memory_free_mb == 1000.0 and isinstance(status.memory_free_mb, float)  # an int is a number


def test_a_struct_is_frozen_and_keyword_only():
    status = messages.SqueezeRequest(reserve_mb=1.0)
    with pytest.raises(AttributeError):
        status.reserve_mb = 2.0  # type: ignore[misc]
    with pytest.raises(TypeError):
        messages.SqueezeRequest(1.0)  # type: ignore[misc]


def _wire(kind: str, **changes: Any) -> bytes:
    return msgpack.packb({"kind": kind, "v": 1, **GOOD[kind], **changes}, use_bin_type=True)


@pytest.mark.parametrize(("kind", "changes", "named"), [
    ("deploy_event", {"event": "exploded"}, "'event'"),
    ("adaptation_event", {"decision": {"trigger_kind": "boredom"}}, "'decision.trigger_kind'"),
    ("adaptation_event", {"decision": {"change": "ready"}}, "'decision.change'"),  # another enum's value
    ("deploy_reply", {"detail": {"state": "sleeping"}}, "'detail.state'"),
    ("deploy_reply", {"detail": {"processes": [{"state": "running"}, {"state": "zombie"}]}},
     "'detail.processes[1].state'"),
])
def test_a_value_outside_its_enum_is_refused_naming_the_field(kind, changes, named):
    with pytest.raises(MessageError, match=r"enum value") as info:
        messages.decode(_wire(kind, **changes), kind)
    assert named in str(info.value) and kind in str(info.value)
    with pytest.raises(MessageError):  # nor can we send one
        messages.encode(kind, {**GOOD[kind], **changes})


@pytest.mark.parametrize(("kind", "changes", "text"), [
    ("host_status", {"memory_free_mb": "lots"}, r"host_status field 'memory_free_mb': Expected `number`, got `str`"),
    ("host_status", {"cpu_load": True}, r"'cpu_load': Expected `number`, got `bool`"),  # a bool is no number
    ("host_status", {"cpu_cores": 4.0}, r"'cpu_cores': Expected `int \| null`, got `float`"),
    ("frame", {"jpeg": "/9j/"}, r"'jpeg': Expected `bytes`, got `str`"),  # a str is not taken as base64
    ("host_status", {"time": math.nan}, r"'time': must be a finite number"),
    ("host_status", {"budget_mb": -math.inf}, r"'budget_mb': must be a finite number"),
    ("host_status", {"host": "h" * 65}, r"'host': Expected `str` of length <= 64"),
    ("flight_state", {"attitude": [0, 0, 0, 0]}, r"'attitude': Expected `array` of length <= 3"),
    ("adaptation_event", {"decision": {"latency_ms": "slow"}}, r"'decision.latency_ms'"),
    ("deploy_reply", {"detail": {"processes": [{"argv": ["a", 1]}]}}, r"'detail.processes\[0\].argv\[1\]'"),
    ("host_status", {"host": None}, r"'host': Expected `str`, got `null`"),
])
def test_a_value_of_the_wrong_type_is_refused_naming_the_field(kind, changes, text):
    with pytest.raises(MessageError, match=text):
        messages.decode(_wire(kind, **changes), kind)


def test_a_missing_field_is_named():
    body = {k: v for k, v in GOOD["host_status"].items() if k != "cpu_load"}
    with pytest.raises(MessageError, match=r"^host_status message lacks field 'cpu_load'$"):
        messages.decode(msgpack.packb({"kind": "host_status", "v": 1, **body}), "host_status")
    with pytest.raises(MessageError, match=r"lacks field 'cpu_load'"):
        messages.encode("host_status", body)


@pytest.mark.parametrize(("payload", "text"), [
    (msgpack.packb({"kind": "telepathy", "v": 1}), r"expected a host_status message, got kind 'telepathy'"),
    (msgpack.packb({"v": 1, **GOOD["host_status"]}), r"expected a host_status message, got kind None"),
    (msgpack.packb({"kind": "host_status", "v": 2, **GOOD["host_status"]}), r"has version 2; this receiver reads version 1"),
    (msgpack.packb({"kind": "host_status", **GOOD["host_status"]}), r"has version None"),
    (msgpack.packb([1, 2]), r"host_status message is not a map but list"),
    (b"\xc1", r"host_status message is not valid msgpack"),
    (msgpack.packb({"kind": "host_status", "v": 1, **GOOD["host_status"]})[:-3], r"not valid msgpack"),
    (msgpack.packb({1: 2, "kind": "host_status", "v": 1, **GOOD["host_status"]}), r"map key that is not a string"),
    (b"\x00" * (messages.MAX_SMALL + 1), r"host_status message of 262145 bytes exceeds 262144"),
])
def test_a_bad_envelope_is_refused_saying_what_is_wrong(payload, text):
    with pytest.raises(MessageError, match=text):
        messages.decode(payload, "host_status")


def test_an_unknown_kind_is_refused():
    with pytest.raises(MessageError, match=r"unknown message kind 'telepathy'"):
        messages.decode(msgpack.packb({"kind": "telepathy", "v": 1}), "telepathy")
    with pytest.raises(MessageError, match=r"unknown message kind 'telepathy'"):
        messages.decode_any(msgpack.packb({"kind": "telepathy", "v": 1}))
    with pytest.raises(MessageError, match=r"unknown message kind 'telepathy'"):
        messages.encode("telepathy", {})
    with pytest.raises(MessageError, match=r"no kind"):
        messages.decode_any(msgpack.packb({"v": 1}))


def test_an_unknown_field_is_kept_in_the_map_and_ignored_by_the_struct():
    payload = _wire("host_status", gpu_load=3.5, note={"from": "a newer sender"})
    body = messages.decode(payload, "host_status")
    assert body["gpu_load"] == 3.5 and body["note"] == {"from": "a newer sender"}
    assert messages.decode_as(payload, messages.HostStatus).memory_total_mb == 4000.0
    # and sent: a body may carry fields its kind does not list
    sent = msgpack.unpackb(messages.encode("flight_state", {**GOOD["flight_state"], "firmware": "4.5.7"}))
    assert sent["firmware"] == "4.5.7"


def test_an_absent_optional_field_and_a_nil_one_are_the_same():
    payload = _wire("deploy_event", pid=None, returncode=None)
    assert messages.decode_as(payload, messages.DeployEvent).pid is None
    assert messages.decode(payload, "deploy_event")["pid"] is None


def test_sending_checks_size_and_what_msgpack_cannot_carry():
    with pytest.raises(MessageError, match=r"frame message of \d+ bytes exceeds 8388608"):
        messages.encode("frame", {**GOOD["frame"], "jpeg": b"x" * messages.MAX_PAYLOAD})
    with pytest.raises(MessageError, match=r"cannot be packed"):
        messages.encode("rows", {"rows": [{"x": object()}]})
    import numpy as np

    sent = messages.decode(messages.encode("illumination", {**GOOD["illumination"], "mean": np.float64(3.5)}),
                           "illumination")
    assert sent["mean"] == 3.5 and type(sent["mean"]) is float  # a float subclass goes as a float


def test_the_fuzzers_view_of_a_kind_comes_from_its_struct():
    from tests.security import fuzz

    fields = fuzz.wire_fields("detections")
    assert fuzz.version("detections") == 1 and fuzz.max_size("detections") == messages.MAX_SMALL
    assert fields["seq"].types == (int,) and fields["seq"].required
    assert fields["time"].types == (int, float)
    assert fields["clean"].types == (list,) and not fields["clean"].required
    assert "v" not in fields and "kind" not in fields


def test_contracts_message_table_is_generated_from_the_types():
    text = (DOCS / "CONTRACTS.md").read_text()
    start, end = text.index(messages.BEGIN), text.index(messages.END) + len(messages.END)
    assert text[start:end] == messages.contract_table(), (
        "docs/CONTRACTS.md is out of date: run `python -m kgadapt.shared.messages docs/CONTRACTS.md`")


def test_a_body_may_repeat_its_kind_and_version_but_not_name_others():
    received = messages.decode(messages.encode("squeeze_request", {"reserve_mb": 1.0}), "squeeze_request")
    assert messages.decode(messages.encode("squeeze_request", received), "squeeze_request") == received  # relayed as is
    with pytest.raises(MessageError, match="names kind 'host_status'"):
        messages.encode("squeeze_request", {**received, "kind": "host_status"})
    with pytest.raises(MessageError, match="version 2"):
        messages.encode("squeeze_request", {**received, "v": 2})
    with pytest.raises(MessageError, match="squeeze_request message has version 2"):
        messages.encode(messages.SqueezeRequest(v=2, reserve_mb=1.0))
