"""The complete flight state: every field from its stream, each with its own timeout, never stale."""

from __future__ import annotations

import math
import time

import pytest

from kgadapt.onboard.flight.mavlink import STREAM_FIELDS
from kgadapt.sim.fake_fc import VehicleState
from tests.flight.conftest import wait_until


def test_altitude_attitude_position_rangefinder_and_home_come_from_the_autopilot(ardu):
    link, fc = ardu(vehicle=VehicleState(armed=True, mode="LOITER", landed_state="IN_AIR", north=3.0, east=-2.0,
                                         alt=7.5, yaw=0.5, roll=0.1, pitch=-0.05))
    state = wait_until(lambda: link.state if link.state.home and link.state.rangefinder_m else None, 5, "home")
    assert state.alt_rel_m == pytest.approx(7.5, abs=0.01)
    assert state.alt_amsl_m == pytest.approx(fc.settings.home[2] + 7.5, abs=0.01)
    assert state.attitude == pytest.approx((0.1, -0.05, 0.5), abs=1e-4)
    assert state.rates == pytest.approx((0.0, 0.0, 0.0))
    assert state.position_ned == pytest.approx((3.0, -2.0, -7.5), abs=1e-3)
    assert state.velocity_ned == pytest.approx((0.0, 0.0, 0.0))
    assert state.rangefinder_m == pytest.approx(7.5 / (math.cos(0.1) * math.cos(-0.05)), abs=0.01)
    assert state.home == pytest.approx(fc.settings.home, abs=1e-6)
    assert state.lat_deg > fc.settings.home[0] and state.lon_deg < fc.settings.home[1]
    heard = dict(state.heard)
    assert set(heard) >= {"HEARTBEAT", "ATTITUDE", "LOCAL_POSITION_NED", "DISTANCE_SENSOR", "HOME_POSITION"}
    assert all(abs(time.time() - t) < 5 for t in heard.values())
    assert state.boot_ms is not None and state.boot_ms > 0
    body = state.as_message()
    assert body.alt_rel_m == state.alt_rel_m and body.attitude == list(state.attitude)


def test_a_stopped_stream_makes_its_fields_unknown_and_is_asked_for_again(ardu):
    link, fc = ardu(vehicle=VehicleState(armed=True, landed_state="IN_AIR", alt=5.0))
    # Known first: on a loaded machine the link may not have heard the stream yet when the fixture returns.
    wait_until(lambda: link.state.position_ned is not None, 5, "LOCAL_POSITION_NED heard")
    fc.set_stream("LOCAL_POSITION_NED", None)  # as if the autopilot had dropped it
    stopped = time.monotonic()
    wait_until(lambda: link.state.position_ned is None, 5, "LOCAL_POSITION_NED fields unknown")
    assert time.monotonic() - stopped >= link.stream_timeout("LOCAL_POSITION_NED") - 0.05
    assert link.state.velocity_ned is None
    assert link.state.attitude is not None  # other streams keep their fields
    # Reported missing from the moment it stopped until it is back (the fake answers the new request
    # within one period, so the test may only see it back).
    wait_until(lambda: "LOCAL_POSITION_NED" in link.state.missing or link.state.position_ned is not None, 3,
               "the stream reported missing")
    # the link asks again (SET_MESSAGE_INTERVAL, acknowledged), and the fields come back
    wait_until(lambda: link.state.position_ned is not None, 5, "LOCAL_POSITION_NED back")
    assert "LOCAL_POSITION_NED" not in link.state.missing
    assert link.counters["streams_stopped"] >= 1


def test_no_field_older_than_its_timeout_is_ever_reported(ardu):
    link, fc = ardu(vehicle=VehicleState(armed=True, landed_state="IN_AIR", alt=5.0))
    fc.set_stream("ATTITUDE", None)
    fc.set_stream("DISTANCE_SENSOR", None)
    deadline = time.monotonic() + 2.0
    checked = 0
    while time.monotonic() < deadline:
        state = link.state
        now = time.time()
        for stream, heard in state.heard:
            if stream != "HEARTBEAT":
                assert now - heard <= link.stream_timeout(stream) + 0.01, stream  # heard times are rounded to ms
        for stream, fields in STREAM_FIELDS.items():
            if stream not in dict(state.heard) and stream not in ("HEARTBEAT", "SYS_STATUS"):
                assert all(getattr(state, f) is None for f in fields), (stream, state)
        checked += 1
        time.sleep(0.01)
    assert checked > 50


def test_link_loss_makes_every_field_unknown(ardu):
    link, fc = ardu(vehicle=VehicleState(armed=True, landed_state="IN_AIR", alt=5.0), link=dict(heartbeat_timeout_s=0.5))
    fc.pause()
    wait_until(lambda: not link.state.link, 3, "link_lost")
    state = link.state
    for fields in STREAM_FIELDS.values():
        assert all(getattr(state, f) is None for f in fields), state
    fc.resume()
    wait_until(lambda: link.state.attitude is not None and link.state.landed_state == "IN_AIR", 5, "everything back")
