"""Fixtures for the flight tests: a fake autopilot and our link, talking real MAVLink 2 over loopback UDP."""

from __future__ import annotations

import pytest

from kgadapt.onboard.flight.mavlink import FlightLink, LinkSettings
from kgadapt.operator import cluster
from kgadapt.sim.fake_fc import FakeFCSettings, FakeFlightController, VehicleState
from tests.support import wait_for as wait_until  # noqa: F401 (the tests import it from here)

# What the tests' links ask of the fake autopilot (the defaults, 1-2 Hz, would slow the tests down).
FAST_STREAMS = (("SYS_STATUS", 10.0), ("BATTERY_STATUS", 10.0), ("EXTENDED_SYS_STATE", 10.0))


def free_udp_port() -> int:
    """A UDP port on loopback that was free a moment ago."""
    return cluster.free_udp_port()


@pytest.fixture
def connect():
    """``connect(vehicle=, heartbeat_timeout_s=, stream_hz=, on_state=)`` -> (link, fc), link up; closed after."""
    opened: list = []

    def _connect(*, vehicle: VehicleState = VehicleState(), heartbeat_timeout_s: float = 0.5,
                 stream_hz: float = 10.0, on_state=None) -> tuple[FlightLink, FakeFlightController]:
        port = free_udp_port()
        link = FlightLink(LinkSettings(url=f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=heartbeat_timeout_s,
                                       stream_rates=FAST_STREAMS))
        if on_state is not None:
            link.on_state(on_state)  # before anything is heard, so no event is missed
        link.setup()
        opened.append(link)
        fc = FakeFlightController(
            FakeFCSettings(url=f"udpout:127.0.0.1:{port}", heartbeat_hz=stream_hz, sys_status_hz=stream_hz,
                           battery_hz=stream_hz, extended_state_hz=stream_hz, drain_pct_per_min=0.0),
            vehicle,
        )
        fc.setup()
        opened.append(fc)
        link.wait_for_heartbeat(5.0)
        return link, fc

    yield _connect
    for part in reversed(opened):
        part.shutdown()


# Every stream the link knows, fast (the tests' vehicle moves in seconds, not minutes).
ALL_FAST = (("SYS_STATUS", 10.0), ("BATTERY_STATUS", 10.0), ("EXTENDED_SYS_STATE", 10.0), ("ATTITUDE", 20.0),
            ("GLOBAL_POSITION_INT", 10.0), ("LOCAL_POSITION_NED", 20.0), ("DISTANCE_SENSOR", 10.0),
            ("HOME_POSITION", 2.0))
# ArduCopter on a companion port: HEARTBEAT at 1 Hz (10 here, for speed), nothing else until asked.
ARDUCOPTER_DEFAULTS = dict(heartbeat_hz=10.0, sys_status_hz=0.0, battery_hz=0.0, extended_state_hz=0.0)


@pytest.fixture
def ardu():
    """``ardu(vehicle=, fc=dict, link=dict)`` -> (link, fc): the fake FC with ArduCopter's defaults, every stream asked."""
    opened: list = []

    def _start(*, vehicle: VehicleState = VehicleState(), fc: dict | None = None, link: dict | None = None,
               wait: bool = True) -> tuple[FlightLink, FakeFlightController]:
        port = free_udp_port()
        link_settings = dict(url=f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=1.0, stream_rates=ALL_FAST)
        link_settings.update(link or {})
        the_link = FlightLink(LinkSettings(**link_settings))
        the_link.setup()
        opened.append(the_link)
        fc_settings = dict(url=f"udpout:127.0.0.1:{port}", drain_pct_per_min=0.0, **ARDUCOPTER_DEFAULTS)
        fc_settings.update(fc or {})
        the_fc = FakeFlightController(FakeFCSettings(**fc_settings), vehicle)
        the_fc.setup()
        opened.append(the_fc)
        if wait:
            the_link.wait_for_heartbeat(5.0)
            wait_until(lambda: the_link.state.attitude is not None and the_link.state.landed_state, 5,
                       "the streams the link asked for")
        return the_link, the_fc

    yield _start
    for part in reversed(opened):
        part.shutdown()
