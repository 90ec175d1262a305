"""A command the autopilot rejects is visible: INFO when rejected, WARNING when the retries are spent, and
counted in the flight state that the bridge publishes and ``kgadapt status`` shows. Real MAVLink over UDP
with the fake ArduCopter, real Zenoh."""

from __future__ import annotations

import logging

from pymavlink.dialects.v20 import common as mavlink2

from kgadapt.onboard.flight.flight import BridgeSettings, CameraIntrinsics, FlightBridge
from kgadapt.onboard.flight.mavlink import LinkSettings
from kgadapt.onboard.flight.mavlink_commands import CommandOutcome, CommandSettings
from kgadapt.operator import status
from kgadapt.shared import keys, messages
from kgadapt.shared.session import ZenohSettings, open_session
from kgadapt.sim.fake_fc import FakeFCSettings, FakeFlightController
from tests.flight.conftest import ALL_FAST, ARDUCOPTER_DEFAULTS, free_udp_port, wait_until

INTERVAL = mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL
FAST_RETRIES = CommandSettings(first_wait_s=0.1, backoff=2.0, attempts=4)


def test_each_stream_request_rejected_once_then_accepted_is_logged_counted_and_shown(caplog):
    caplog.set_level(logging.INFO, logger="kgadapt.onboard.flight.mavlink_commands")
    robot = "refusals"
    port = free_udp_port()
    session = open_session(ZenohSettings(mode="peer", listen=(), connect=()))
    bridge = FlightBridge(BridgeSettings(robot=robot, intrinsics=CameraIntrinsics(fx=600, fy=600, cx=320, cy=240),
                                         link=LinkSettings(url=f"udpin:127.0.0.1:{port}", stream_rates=ALL_FAST,
                                                           commands=FAST_RETRIES)))
    fc = FakeFlightController(FakeFCSettings(url=f"udpout:127.0.0.1:{port}", drain_pct_per_min=0.0,
                                             temporarily_reject=((INTERVAL, 1),), **ARDUCOPTER_DEFAULTS))
    heard: list[dict] = []
    subscriber = session.declare_subscriber(keys.flight_state(robot),
                                            lambda s: heard.append(messages.decode(s.payload.to_bytes(), "flight_state")))
    try:
        bridge.setup(session)
        fc.setup()
        wanted = {name for name, _ in ALL_FAST}
        wait_until(lambda: wanted <= set(dict(bridge.state.heard)), 15, "every stream, each asked twice")
        state = bridge.state
        assert state.rejected >= len(ALL_FAST) and state.refused == ()  # rejected once each, then accepted
        assert "autopilot rejected SET_MESSAGE_INTERVAL(ATTITUDE at 20 Hz): temporarily_rejected (attempt 1)" \
            in caplog.text
        assert not [r for r in caplog.records if r.levelno >= logging.WARNING]  # accepted on retry: no warning
        wait_until(lambda: any((m.get("rejected") or 0) >= len(ALL_FAST) for m in heard), 5, "rejected published")
        data = status.gather(session, robot, listen_s=1.0, timeout=0.5)
        assert data["flight"]["rejected"] >= len(ALL_FAST)
        assert f"{data['flight']['rejected']} rejected by the autopilot (all accepted on retry)" in status.render(data)
    finally:
        subscriber.undeclare()
        bridge.shutdown()
        fc.shutdown()
        session.close()


def test_a_command_rejected_until_its_retries_are_spent_is_a_warning_and_a_refusal(ardu, caplog):
    caplog.set_level(logging.INFO, logger="kgadapt.onboard.flight.mavlink_commands")
    link, fc = ardu(fc=dict(temporarily_reject=((mavlink2.MAV_CMD_DO_SET_MODE, 255),)),
                    link=dict(commands=FAST_RETRIES))
    before = link.state.rejected
    outcome = link.command(mavlink2.MAV_CMD_DO_SET_MODE, mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4,
                           label="GUIDED")
    assert outcome is CommandOutcome.TEMPORARILY_REJECTED
    wait_until(lambda: link.state.rejected == before + 4, 2, "four rejections counted")
    assert link.state.refused[-1] == "DO_SET_MODE(GUIDED): temporarily_rejected"
    infos = [r for r in caplog.records if r.levelno == logging.INFO and "DO_SET_MODE(GUIDED)" in r.getMessage()]
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING and "DO_SET_MODE(GUIDED)" in r.getMessage()]
    assert len(infos) == 4 and len(warnings) == 1 and "retries spent" in warnings[0].getMessage()


def test_a_flight_control_no_bridge_has_written_is_no_flight_state_not_a_lost_link():
    # The models give every robot a FlightControl component; its run-time properties are null until a bridge
    # writes them. That was shown as "link lost" (a phase PROBLEMS did not list).
    never = [{"link": None, "armed": None, "mode": None, "landed_state": None, "last_seen": None}]
    assert status._flight(None, never) is None
    written = [{"link": False, "armed": None, "mode": None, "landed_state": None, "last_seen": 12.0}]
    assert status._flight(None, written)["phase"] == "link lost"
