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
