"""The MAVLink adapter against the fake flight controller over real UDP (and a pty, and TCP)."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import threading
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from kgadapt.onboard.flight.mavlink import (
    DEFAULT_STREAM_RATES,
    LINK_LOST,
    LINK_RESTORED,
    LINK_UP,
    Endpoint,
    FlightLink,
    LandingTarget,
    LinkSettings,
    mode_name,
)
from kgadapt.shared.errors import FlightLinkError
from kgadapt.sim.fake_fc import FakeFCSettings, FakeFlightController, VehicleState
from tests.flight.conftest import FAST_STREAMS, free_udp_port, wait_until


def _complete(link: FlightLink):
    """The state once every stream (heartbeat, status, battery, landed state) has been heard."""
    state = link.state
    return state if state.landed_state and state.battery_pct is not None and state.onboard_load is not None else None


def test_link_reads_armed_mode_landed_state_battery_and_load_from_the_fake_fc(connect):
    link, fc = connect(vehicle=VehicleState(armed=True, mode="GUIDED", landed_state="IN_AIR",
                                            battery_pct=76.0, load_pct=31.5))
    state = wait_until(lambda: _complete(link), 3, "all four streams")
    assert state.link is True
    assert state.armed is True
    assert state.mode == "GUIDED"
    assert state.landed_state == "IN_AIR"
    assert state.battery_pct == 76.0
    assert state.battery_v == pytest.approx(fc.battery_v, abs=0.01)
    assert state.onboard_load == pytest.approx(31.5)
    assert state.system_id == 1 and state.autopilot == "ardupilot"


def test_link_follows_changes_and_the_scripted_final_descent(connect):
    link, fc = connect(vehicle=VehicleState(armed=True, mode="LOITER", landed_state="IN_AIR"))
    wait_until(lambda: _complete(link), 3, "all four streams")
    seen: list[tuple] = []
    link.on_state(lambda s: seen.append((s.mode, s.landed_state, s.armed)))
    fc.land(descent_s=0.4)
    wait_until(lambda: link.state.landed_state == "LANDING" and link.state.mode == "LAND", 2, "LANDING")
    wait_until(lambda: link.state.landed_state == "ON_GROUND" and link.state.armed is False, 3, "touchdown")
    assert ("LAND", "LANDING", True) in seen


def test_link_loss_is_noticed_within_3_5_s_with_the_default_timeout_and_recovery_after_resume(connect):
    link, fc = connect(heartbeat_timeout_s=LinkSettings(url="udpin:127.0.0.1:1").heartbeat_timeout_s)
    lost, restored = threading.Event(), threading.Event()
    link.on_state(lambda s: lost.set() if s.event == LINK_LOST else restored.set() if s.event == LINK_RESTORED else None)
    paused_at = time.monotonic()
    fc.pause()
    assert lost.wait(4.5), "link loss not noticed"
    noticed_after = time.monotonic() - paused_at
    assert 2.5 <= noticed_after <= 3.5, noticed_after
    assert link.state.link is False
    fc.resume()
    assert restored.wait(2.0), "recovery not noticed"
    assert link.state.link is True and link.counters["links_lost"] == 1


def test_link_events_come_in_order_up_lost_restored(connect):
    events: list[str] = []
    link, fc = connect(heartbeat_timeout_s=0.3, on_state=lambda s: s.event and events.append(s.event))
    wait_until(lambda: events, 1, "link_up event")
    fc.pause()
    wait_until(lambda: LINK_LOST in events, 2, "link_lost")
    fc.resume()
    wait_until(lambda: LINK_RESTORED in events, 2, "link_restored")
    assert events == [LINK_UP, LINK_LOST, LINK_RESTORED]


def test_the_link_asks_the_autopilot_for_its_streams_each_time_the_link_comes_up():
    port = free_udp_port()
    fc = FakeFlightController(FakeFCSettings(url=f"udpout:127.0.0.1:{port}", heartbeat_hz=10, extended_state_hz=0))
    assert fc.stream_rate("EXTENDED_SYS_STATE") is None  # like ArduCopter: not streamed unless asked
    with FlightLink(LinkSettings(url=f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=0.3)) as link, fc:
        link.wait_for_heartbeat(3)
        wait_until(lambda: link.state.landed_state == "ON_GROUND", 3, "EXTENDED_SYS_STATE after the request")
        assert fc.stream_rate("EXTENDED_SYS_STATE") == pytest.approx(2.0)
        assert fc.stream_rate("SYS_STATUS") == pytest.approx(2.0)
        assert fc.stream_rate("ATTITUDE") == pytest.approx(20.0)
        wait_until(lambda: len(fc.received("COMMAND_LONG")) >= len(DEFAULT_STREAM_RATES), 3, "every stream request")
        requests = [c.fields for c in fc.received("COMMAND_LONG")]
        asked = {(r["param1"], round(r["param2"])) for r in requests}
        assert asked == {(float(getattr(mavlink2, f"MAVLINK_MSG_ID_{n}")), round(1e6 / hz)) for n, hz in DEFAULT_STREAM_RATES}
        assert {r["command"] for r in requests} == {mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL}
        assert all(r["target_system"] == 1 and r["target_component"] == 1 for r in requests)
        fc.pause()
        wait_until(lambda: not link.state.link, 2, "link_lost")
        fc.clear_received()
        fc.resume()
        fc.wait_for("COMMAND_LONG", len(DEFAULT_STREAM_RATES), timeout=3)  # asked again: an autopilot may have rebooted meanwhile


def test_landing_target_arrives_as_mavlink2_with_frame_type_and_validity(connect):
    link, fc = connect()
    t = time.time()
    link.send_landing_target(LandingTarget(time=t, angle_x=0.125, angle_y=-0.25, size_x=0.05, size_y=0.04,
                                           target_num=7))
    link.send_landing_target(LandingTarget(time=t + 0.1, angle_x=0.0, angle_y=0.0, distance=2.5,
                                           position=(0.5, -0.25, 2.0)))
    first, second = fc.wait_for("LANDING_TARGET", 2, timeout=2)[:2]
    assert first.mavlink2 and first.src_component == mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER
    f = first.fields
    assert f["frame"] == mavlink2.MAV_FRAME_BODY_FRD
    assert f["type"] == mavlink2.LANDING_TARGET_TYPE_VISION_FIDUCIAL
    assert f["position_valid"] == 0 and f["target_num"] == 7
    assert f["angle_x"] == pytest.approx(0.125) and f["angle_y"] == pytest.approx(-0.25)
    assert f["time_usec"] == int(t * 1e6)
    g = second.fields
    assert g["position_valid"] == 1 and g["distance"] == pytest.approx(2.5)
    assert (g["x"], g["y"], g["z"]) == pytest.approx((0.5, -0.25, 2.0))


def test_our_heartbeat_reaches_the_fc_about_once_a_second_as_an_onboard_controller(connect):
    link, fc = connect()
    beats = fc.wait_for("HEARTBEAT", 3, timeout=4)
    assert all(b.mavlink2 for b in beats)
    assert beats[0].fields["type"] == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
    assert beats[0].fields["autopilot"] == mavlink2.MAV_AUTOPILOT_INVALID
    assert beats[0].src_component == mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER
    gap = beats[2].time - beats[1].time
    assert 0.7 <= gap <= 1.5, gap


def test_malformed_datagrams_do_not_stop_the_reader_nor_steal_the_reply_address(connect):
    link, fc = connect()
    encoder = mavlink2.MAVLink(None, 1, 1)
    good = bytearray(encoder.heartbeat_encode(2, 3, 0, 0, 4).pack(encoder))
    bad_crc = bytes(good[:-1]) + bytes([good[-1] ^ 0xFF])
    truncated = bytes([0xFD, 200, 0, 0, 1, 1, 1, 0, 0, 0])  # promises 200 bytes, gives none
    port = link._transport.local_address[1]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as intruder:
        for junk in (b"\x00" * 64, os.urandom(300), bad_crc, truncated, b"\xfe", b""):
            intruder.sendto(junk, ("127.0.0.1", port))
    wait_until(lambda: link.counters["bad"] >= 3, 2, "bad packets counted")
    fc.set(mode="RTL")
    wait_until(lambda: link.state.mode == "RTL", 2, "a change after the junk")
    assert all(t.is_alive() for t in link._threads)
    fc.clear_received()
    link.send_landing_target(LandingTarget(time=time.time(), angle_x=0.1, angle_y=0.1))
    fc.wait_for("LANDING_TARGET", 1, timeout=2)  # still goes to the autopilot, not the intruder


def test_another_component_of_the_autopilots_system_changes_neither_the_state_nor_where_replies_go():
    # A gimbal (1/154) or our own LANDING_TARGET coming back through a router (1/191) shares the autopilot's
    # system id; only the autopilot (1/1, whose heartbeat it follows) may fold into the state or move replies.
    port = free_udp_port()
    with FlightLink(LinkSettings(url=f"udpin:127.0.0.1:{port}", stream_rates=FAST_STREAMS)) as link:
        fc = FakeFlightController(FakeFCSettings(url=f"udpout:127.0.0.1:{port}", heartbeat_hz=10.0,
                                                 drain_pct_per_min=0.0), VehicleState())
        fc.setup()
        try:
            link.wait_for_heartbeat(5.0)
            gimbal, ours = mavlink2.MAVLink(None, 1, 154), mavlink2.MAVLink(None, 1, 191)
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
                other.sendto(gimbal.attitude_encode(1000, 0.5, 0.0, 1.0, 0.0, 0.0, 0.0).pack(gimbal),
                             ("127.0.0.1", port))
                other.sendto(ours.landing_target_encode(0, 0, mavlink2.MAV_FRAME_BODY_FRD, 0.1, 0.1, 5.0, 0, 0)
                             .pack(ours), ("127.0.0.1", port))
                fc.set(mode="RTL")  # sent after them: once it is seen, so were they
                wait_until(lambda: link.state.mode == "RTL", 3, "the autopilot's change after the others")
                assert link.state.attitude is None  # the gimbal's attitude was not taken for the vehicle's
                fc.clear_received()
                link.send_landing_target(LandingTarget(time=time.time(), angle_x=0.1, angle_y=0.1))
                fc.wait_for("LANDING_TARGET", 1, timeout=2)  # replies still go to the autopilot
        finally:
            fc.shutdown()


def test_a_heartbeat_from_a_ground_station_does_not_bring_the_link_up():
    port = free_udp_port()
    with FlightLink(LinkSettings(url=f"udpin:127.0.0.1:{port}")) as link:
        gcs = mavlink2.MAVLink(None, 255, 190)
        packet = gcs.heartbeat_encode(mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 4).pack(gcs)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(packet, ("127.0.0.1", port))
        wait_until(lambda: link.counters["received"] >= 1, 2, "the GCS heartbeat")
        assert link.state.link is False
        with pytest.raises(FlightLinkError, match="nowhere to send"):
            link.send_landing_target(LandingTarget(time=time.time(), angle_x=0.0, angle_y=0.0))


@pytest.mark.parametrize("url", [
    "", "udpin:localhost", "udpout:127.0.0.1:99999", "bogus:127.0.0.1:14550", "tcp:", "/dev/ttyS0:12345",
    "serial:", "udpin:127.0.0.1:14550; rm -rf",
])
def test_a_bad_url_fails_with_flight_link_error_naming_it(url):
    with pytest.raises(FlightLinkError, match=re.escape(repr(url))):
        FlightLink(LinkSettings(url=url))


def test_a_missing_serial_device_fails_at_setup_naming_it():
    link = FlightLink(LinkSettings(url="/dev/kgadapt-no-such-tty:115200"))
    with pytest.raises(FlightLinkError, match="/dev/kgadapt-no-such-tty:115200"):
        link.setup()


def test_a_refused_tcp_connection_fails_at_setup_naming_it():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # bound, not listening: connections are refused
        link = FlightLink(LinkSettings(url=f"tcp:127.0.0.1:{port}", open_timeout_s=1.0))
        with pytest.raises(FlightLinkError, match=f"tcp:127.0.0.1:{port}"):
            link.setup()


def test_urls_parse_into_endpoints():
    assert Endpoint.parse("udpin:0.0.0.0:14550") == Endpoint("udpin:0.0.0.0:14550", "udpin", "0.0.0.0", 14550)
    assert Endpoint.parse("udp:127.0.0.1:14550").kind == "udpin"
    assert Endpoint.parse("tcp:[::1]:5760").host == "::1"
    serial = Endpoint.parse("/dev/ttyACM0:115200")
    assert (serial.kind, serial.device, serial.baud) == ("serial", "/dev/ttyACM0", 115200)
    assert Endpoint.parse("serial:/dev/serial/by-id/usb-Hex_CubeOrange-if00").baud == 57600


def _autopilot_packet(seq_mav: mavlink2.MAVLink, mode: int = 5) -> bytes:
    return seq_mav.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                    mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode, 3).pack(seq_mav)


def test_a_serial_link_reads_the_autopilot_and_writes_our_heartbeat_through_a_pty():
    master, slave = os.openpty()
    try:
        with FlightLink(LinkSettings(url=f"{os.ttyname(slave)}:115200")) as link:
            fc = mavlink2.MAVLink(None, 1, 1)
            packet = _autopilot_packet(fc, mode=9)
            os.write(master, b"\x55\xaa" + packet[:5])  # line noise, then a packet split across writes
            os.write(master, packet[5:])
            state = link.wait_for_heartbeat(3)
            assert state.mode == "LAND"
            parser = mavlink2.MAVLink(None, 0, 0)
            got = []
            deadline = time.monotonic() + 3
            while not got and time.monotonic() < deadline:
                got = [m for m in parser.parse_buffer(os.read(master, 1024)) or [] if m.get_type() == "HEARTBEAT"]
            assert got and got[0].type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
    finally:
        os.close(master)
        os.close(slave)


def test_a_tcp_link_reads_the_autopilot_and_writes_our_heartbeat():
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        with FlightLink(LinkSettings(url=f"tcp:127.0.0.1:{server.getsockname()[1]}")) as link:
            conn, _ = server.accept()
            with conn:
                conn.sendall(_autopilot_packet(mavlink2.MAVLink(None, 1, 1), mode=4))
                assert link.wait_for_heartbeat(3).mode == "GUIDED"
                conn.settimeout(3)
                parser = mavlink2.MAVLink(None, 0, 0)
                got = parser.parse_buffer(conn.recv(1024)) or []
                assert got and got[0].get_type() == "HEARTBEAT"


def test_mode_names_are_decoded_for_ardupilot_and_px4():
    custom = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert mode_name(mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, mavlink2.MAV_TYPE_QUADROTOR, custom, 9) == "LAND"
    assert mode_name(mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, mavlink2.MAV_TYPE_QUADROTOR, custom, 99) == "MODE_99"
    px4_precland = (4 << 16) | (9 << 24)
    assert mode_name(mavlink2.MAV_AUTOPILOT_PX4, mavlink2.MAV_TYPE_QUADROTOR, custom, px4_precland) == "AUTO.PRECLAND"
    assert mode_name(mavlink2.MAV_AUTOPILOT_PX4, mavlink2.MAV_TYPE_QUADROTOR, custom, 3 << 16) == "POSCTL"


def test_importing_the_flight_modules_leaves_the_mavlink_environment_and_globals_alone():
    code = (
        "import json, os, sys\n"
        "before = dict(os.environ)\n"
        "import kgadapt.onboard.flight.mavlink, kgadapt.sim.fake_fc, kgadapt.onboard.flight.flight\n"
        "import kgadapt.onboard.flight.flight_cli\n"
        "from kgadapt.onboard.flight.mavlink import new_mavlink\n"
        "from pymavlink.dialects.v20 import common\n"
        "m = common.MAVLink(None, 1, 191)\n"
        "packet = m.landing_target_encode(0, 0, 12, 0.1, 0.2, 0, 0, 0, 1, 2, 3, (1, 0, 0, 0), 2, 1).pack(m)\n"
        "print(json.dumps({'changed': sorted(k for k in set(before) | set(os.environ)\n"
        "                                    if before.get(k) != os.environ.get(k)),\n"
        "                  'mavutil': 'pymavlink.mavutil' in sys.modules, 'first_byte': packet[0]}))\n"
    )
    for extra in ({}, {"MAVLINK_DIALECT": "ardupilotmega"}):
        env = {k: v for k, v in os.environ.items() if k not in ("MAVLINK20", "MAVLINK09", "MAVLINK_DIALECT")}
        env.update(extra)
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=30,
                             cwd=os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
        assert out.returncode == 0, out.stderr
        result = json.loads(out.stdout)
        assert result == {"changed": [], "mavutil": False, "first_byte": 0xFD}, (extra, result)
