"""The vehicle's pose at a frame's time (FlightLink.pose_at), as the confirmation and the targets use it.

A real FlightLink hears a minimal autopilot peer (pymavlink's encoder over loopback UDP) send
ATTITUDE and LOCAL_POSITION_NED at known values; between two attitudes the pose is interpolated,
and a position is carried to the asked time with its velocity (not the nearest sample unchanged).
"""

from __future__ import annotations

import socket
import time

from pymavlink.dialects.v20 import common as mavlink2

from kgadapt.onboard.flight.mavlink import FlightLink, LinkSettings
from tests.flight.conftest import free_udp_port
from tests.support import wait_for


class _Writer:
    def __init__(self, sock: socket.socket, port: int) -> None:
        self.sock, self.port = sock, port

    def write(self, data: bytes) -> None:
        self.sock.sendto(data, ("127.0.0.1", self.port))


def test_the_pose_at_a_time_between_samples_is_interpolated_and_carried_with_the_velocity():
    port = free_udp_port()
    link = FlightLink(LinkSettings(url=f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=5.0, stream_rates=()))
    link.setup()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        mav = mavlink2.MAVLink(_Writer(sock, port), srcSystem=1, srcComponent=1)
        mav.heartbeat_send(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0)
        link.wait_for_heartbeat(5.0)
        # Flying north at 2 m/s, 10 m up.
        mav.local_position_ned_send(1000, 5.0, 0.0, -10.0, 2.0, 0.0, 0.0)
        mav.attitude_send(1000, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0)
        wait_for(lambda: link.state.attitude is not None and link.state.position_ned is not None, 5, "the pose")
        first_heard = time.time()
        time.sleep(0.1)
        before_second = time.time()
        mav.attitude_send(1100, 0.0, 0.0, 0.3, 0.0, 0.0, 0.0)
        wait_for(lambda: link.state.attitude is not None and abs(link.state.attitude[2] - 0.3) < 1e-6, 5,
                 "the second attitude")
        between = (first_heard + before_second) / 2  # after the first attitude arrived, before the second
        attitude, position = link.pose_at(between)
        assert 0.1 + 1e-3 < attitude[2] < 0.3 - 1e-3, attitude  # not either sample: between them
        _, later = link.pose_at(between + 0.1)
        assert abs((later[0] - position[0]) - 0.2) < 1e-6, (position, later)  # 2 m/s for 0.1 s
        assert later[1:] == position[1:] == (0.0, -10.0)
        assert link.pose_at(between + 10.0) is None  # nothing heard near then
    finally:
        sock.close()
        link.shutdown()
