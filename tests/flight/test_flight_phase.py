"""Final descent on the safe side: the landed state, or a landing mode while the landed state is unknown."""

from __future__ import annotations

import pytest

from kgadapt.onboard.flight.flight_phase import in_final_descent
from kgadapt.onboard.flight.mavlink import FlightState
from kgadapt.shared import messages


@pytest.mark.parametrize("state, expected", [
    ({"landed_state": "LANDING", "mode": "LOITER"}, True),
    ({"landed_state": "IN_AIR", "mode": "RTL", "alt_rel_m": 15.0}, False),  # RTL's return at altitude
    ({"landed_state": "IN_AIR", "mode": "RTL", "alt_rel_m": 6.0}, True),  # its last metres
    ({"landed_state": "IN_AIR", "mode": "LAND"}, False),  # altitude unknown, the autopilot says in the air
    ({"landed_state": "IN_AIR", "mode": "LOITER", "alt_rel_m": 2.0}, False),
    ({"landed_state": "ON_GROUND", "mode": "LAND"}, False),
    ({"mode": "LAND"}, True),  # landed state unknown: its stream stopped, or after a reboot
    ({"landed_state": "UNDEFINED", "mode": "RTL"}, True),
    ({"mode": "AUTO.PRECLAND"}, True),
    ({"mode": "LOITER"}, False),
    ({}, False),
])
def test_final_descent(state, expected):
    assert in_final_descent(state) is expected


def test_a_flight_state_message_with_the_landed_state_unknown_in_land_is_final_descent():
    # what the bridge publishes when EXTENDED_SYS_STATE stopped during LAND
    body = FlightState(time=1.0, link=True, armed=True, mode="LAND", landed_state=None).as_message()
    assert in_final_descent(messages.decode_as(messages.encode(body), messages.FlightState))


@pytest.mark.parametrize("state, expected", [
    (FlightState(time=1.0, link=True, mode="LAND", landed_state=None), True),  # its stream stopped in LAND
    (FlightState(time=1.0, link=True, mode="RTL", landed_state="IN_AIR", alt_rel_m=5.0), True),
    (FlightState(time=1.0, link=True, mode="RTL", landed_state="IN_AIR", alt_rel_m=30.0), False),
    (FlightState(time=1.0, link=True, mode="LOITER", landed_state="LANDING"), True),
    (FlightState(time=1.0, link=True, mode="LOITER", landed_state="IN_AIR"), False),
])
def test_the_onboard_agents_manager_sees_the_bridges_final_descent_as_a_flight_state_message_would(state, expected):
    # In one agent the manager reads the bridge beside it, not flight_state messages: it must see the same
    # phase (it saw only a landed state of LANDING, so not LAND or RTL with the landed state unknown).
    from types import SimpleNamespace

    from kgadapt.onboard.cli import FlightPart

    part = FlightPart(robot="quad1", url="udpin:127.0.0.1:14550", camera_model="cam")
    assert part.in_final_descent() is False  # before setup
    part.bridge = SimpleNamespace(state=state)
    assert part.in_final_descent() is expected
    assert in_final_descent(messages.decode_as(messages.encode(state.as_message()), messages.FlightState)) is expected
