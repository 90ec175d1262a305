"""The named states and kinds (kgadapt.shared.states): the values docs/CONTRACTS.md and docs/deploy.md list,
and the plain strings they are on the wire."""

from __future__ import annotations

import json
import re
from enum import StrEnum
from pathlib import Path

import pytest

from kgadapt.shared import messages
from kgadapt.shared.states import (
    ENDED_EVENTS,
    FINAL_STATES,
    KEPT_STATES,
    LIVE_STATES,
    SERVING_STATES,
    URGENT_TRIGGERS,
    Change,
    ProcessEventKind,
    ProcessState,
    ReflexEvidence,
    TriggerKind,
)

DOCS = Path(__file__).resolve().parents[1] / "docs"
ENUMS: dict[str, type[StrEnum]] = {"ProcessState": ProcessState, "ProcessEventKind": ProcessEventKind,
                                   "TriggerKind": TriggerKind, "Change": Change, "ReflexEvidence": ReflexEvidence}


def _contract_table() -> dict[str, list[str]]:
    """``enum name -> values`` from the table of the section "States and kinds" of docs/CONTRACTS.md."""
    text = (DOCS / "CONTRACTS.md").read_text()
    section = text.split("## States and kinds", 1)[1].split("\n## ", 1)[0]
    table: dict[str, list[str]] = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 3 and re.fullmatch(r"`\w+`", cells[0]):
            table[cells[0].strip("`")] = re.findall(r"`([^`]+)`", cells[2])
    return table


def test_contracts_lists_every_enum_with_exactly_its_values_in_order():
    table = _contract_table()
    assert set(table) == set(ENUMS), table
    for name, enum in ENUMS.items():
        assert table[name] == [m.value for m in enum], name


def _deploy_wire_contract_item(head: str) -> str:
    """The list item of docs/deploy.md's "Wire contract" that starts with ``head``, its lines joined."""
    text = (DOCS / "deploy.md").read_text().split("## Wire contract", 1)[1].split("\n## ", 1)[0]
    start = text.index(head)
    end = text.find("\n- ", start)
    return " ".join(text[start:end if end >= 0 else None].split())


def test_deploy_wire_contract_lists_the_live_and_final_states_and_the_events():
    line = _deploy_wire_contract_item("States:")
    live, final = re.findall(r"`([^`]+)` \((live|final)\)", line)
    assert live[1] == "live" and final[1] == "final", line
    assert live[0].split(", ") == [s.value for s in ProcessState if s in LIVE_STATES]
    assert final[0].split(", ") == [s.value for s in ProcessState if s in FINAL_STATES]
    named = re.findall(r"`(\w+)`", _deploy_wire_contract_item("Events:"))
    assert list(dict.fromkeys(named)) == [e.value for e in ProcessEventKind]  # in order of first mention


def test_the_sets_partition_the_states_as_documented():
    assert LIVE_STATES | FINAL_STATES == set(ProcessState) and not LIVE_STATES & FINAL_STATES
    assert KEPT_STATES == LIVE_STATES - {ProcessState.STOPPING}
    assert SERVING_STATES == {"ready", "running"} and SERVING_STATES < KEPT_STATES
    assert URGENT_TRIGGERS == {"startup", "host_lost"}
    assert ENDED_EVENTS == {"exited", "stopped", "failed"}


MEMBERS = [*ProcessState, *ProcessEventKind, *TriggerKind, *Change, *ReflexEvidence]


@pytest.mark.parametrize("member", MEMBERS, ids=lambda m: f"{type(m).__name__}.{m.name}")
def test_a_member_is_its_plain_string_on_the_wire(member):
    # Each member in the field its enum types (a field refuses another enum's values).
    field = {TriggerKind: "trigger_kind", Change: "change"}.get(type(member))
    body = {"time": 1.0, "trigger": f"{member}(host=onboard)", "outcome": str(member),
            "decision": {field: member} if field else {}}
    decoded = messages.decode(messages.encode("adaptation_event", body), "adaptation_event")
    values = [decoded["outcome"], *(decoded["decision"][field] for _ in [1] if field)]
    if isinstance(member, ProcessEventKind):
        event = messages.decode(messages.encode("deploy_event", {"event": member, "host": "onboard", "instance": "det1",
                                                                 "time": 1.0}), "deploy_event")
        values.append(event["event"])
    if isinstance(member, ProcessState):
        reply = messages.decode(messages.encode("deploy_reply", {"ok": True, "detail": {"state": member}}), "deploy_reply")
        values.append(reply["detail"]["state"])
    if isinstance(member, ReflexEvidence):
        reflex = messages.decode(messages.encode("reflex", {
            "instance": "det1", "host": "onboard", "previous": "a", "band": "dark", "evidence": member, "seq": 1,
            "frame_time": 1.0, "time": 1.0, "count": 1}), "reflex")
        values.append(reflex["evidence"])
    assert len(values) == 2
    for value in values:
        assert type(value) is str and value == member.value and value == member
    assert decoded["trigger"] == f"{member.value}(host=onboard)"
    assert json.loads(json.dumps({"state": member})) == {"state": member.value}
    assert type(member).__name__ not in f"{member}" + str(member)  # formatting gives the value, not the enum's name
    assert type(member)(member.value) is member  # what a receiver decodes maps back to the member
