"""The fake flight controller does what ArduCopter does, behaviour by behaviour (see its docstring for the source).

Each test names the ArduPilot function whose behaviour it checks.
"""

from __future__ import annotations

import math
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from kgadapt.onboard.flight.mavlink import LandingTarget
from kgadapt.onboard.flight.mavlink_commands import CommandOutcome
from kgadapt.sim.fake_fc import VehicleState
from tests.flight.conftest import wait_until

HOVER = VehicleState(armed=True, mode="LOITER", landed_state="IN_AIR", alt=8.0)
CUSTOM = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


def _stream_targets(link, make, hz: float, seconds: float) -> None:
    """Send ``make()`` at ``hz`` for ``seconds`` (the way a detector would), and at least ``hz * seconds``
    messages: on a loaded machine the sleeps overshoot, and a count the test relies on must still be sent."""
    stop, sent = time.monotonic() + seconds, 0
    while time.monotonic() < stop or sent < hz * seconds:
        link.send_landing_target(make())
        sent += 1
        time.sleep(1.0 / hz)


def _angles(ax: float = 0.1, ay: float = -0.1, distance: float = 0.0):
    return lambda: LandingTarget(time=time.time(), angle_x=ax, angle_y=ay, distance=distance)


# -- AC_PrecLand_MAVLink::handle_msg / AC_PrecLand::construct_pos_meas_using_rangefinder

def test_angles_without_a_distance_and_without_a_rangefinder_are_never_acquired(ardu):
    link, fc = ardu(vehicle=HOVER, fc=dict(rangefinder=False))
    _stream_targets(link, _angles(), 20, 2.6)
    wait_until(lambda: fc.precland.counters["received"] >= 40, 5, "40 targets received")
    assert fc.precland.counters["no_height"] >= 40 and fc.precland.counters["measurements"] == 0
    assert not fc.precland.acquired


def test_angles_with_a_rangefinder_are_acquired_after_2_s_of_updates_and_placed_by_the_height(ardu):
    link, fc = ardu(vehicle=HOVER)
    _stream_targets(link, _angles(ax=math.atan(0.25), ay=math.atan(-0.5)), 20, 2.4)
    wait_until(lambda: fc.precland.acquired, 1, "acquired")
    # los (-tan(ay), tan(ax), 1) scaled to the 8 m height: 4 m forward, 2 m right
    assert fc.precland.target_ne == pytest.approx((4.0, 2.0), abs=0.01)
    assert "PrecLand: Init Complete" in fc.texts


def test_angles_with_a_distance_are_acquired_without_a_rangefinder(ardu):
    link, fc = ardu(vehicle=HOVER, fc=dict(rangefinder=False))
    _stream_targets(link, _angles(ax=0.0, ay=0.0, distance=8.0), 20, 2.4)
    wait_until(lambda: fc.precland.acquired, 1, "acquired")
    assert fc.precland.target_ne == pytest.approx((0.0, 0.0), abs=0.01)


def test_a_position_in_body_frd_with_its_distance_is_acquired(ardu):
    link, fc = ardu(vehicle=HOVER, fc=dict(rangefinder=False))
    _stream_targets(link, lambda: LandingTarget(time=time.time(), angle_x=0, angle_y=0, distance=math.sqrt(1 + 4 + 64),
                                                position=(1.0, -2.0, 8.0)), 20, 2.4)
    wait_until(lambda: fc.precland.acquired, 1, "acquired")
    assert fc.precland.target_ne == pytest.approx((1.0, -2.0), abs=0.01)


def test_a_position_in_local_ned_is_refused_as_an_unsupported_frame(ardu):
    link, fc = ardu(vehicle=HOVER)
    _stream_targets(link, lambda: LandingTarget(time=time.time(), angle_x=0, angle_y=0, distance=8.0,
                                                position=(0.0, 0.0, 0.0), frame=mavlink2.MAV_FRAME_LOCAL_NED), 20, 1.0)
    assert fc.precland.counters["frame_unsupported"] >= 10 and fc.precland.counters["measurements"] == 0
    assert fc.texts.count("Plnd: Frame not supported ") == 1  # said once


def test_a_position_without_a_distance_is_dropped(ardu):
    link, fc = ardu(vehicle=HOVER)
    _stream_targets(link, lambda: LandingTarget(time=time.time(), angle_x=0, angle_y=0, distance=0.0,
                                                position=(0.0, 0.0, 8.0)), 20, 1.0)
    assert fc.precland.counters["no_distance"] >= 10 and fc.precland.counters["measurements"] == 0


# -- AC_PrecLand::check_ekf_init_timeout / target_acquired

def test_one_target_a_second_fails_the_estimator_init(ardu):
    link, fc = ardu(vehicle=HOVER)
    _stream_targets(link, _angles(), 1.0, 4.5)
    assert fc.precland.counters["measurements"] >= 4
    assert fc.precland.counters["init_failed"] >= 3 and not fc.precland.acquired
    assert "PrecLand: Init Failed" in fc.texts


def test_the_target_is_lost_2_s_after_the_last_measurement(ardu):
    link, fc = ardu(vehicle=HOVER)
    _stream_targets(link, _angles(), 20, 2.4)
    wait_until(lambda: fc.precland.acquired, 1, "acquired")
    last = time.monotonic()
    wait_until(lambda: not fc.precland.acquired, 4, "lost")
    assert time.monotonic() - last >= 1.9
    assert "PrecLand: Target Lost" in fc.texts


# -- GCS_MAVLINK::set_message_interval, and streams after a reboot

def test_message_intervals_set_stop_and_restore_defaults_and_refuse_unknown_messages(ardu):
    link, fc = ardu(fc=dict(sys_status_hz=2.0))
    cmd = mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL
    assert link.command(cmd, mavlink2.MAVLINK_MSG_ID_SYS_STATUS, 50_000) is CommandOutcome.ACCEPTED
    assert fc.stream_rate("SYS_STATUS") == pytest.approx(20.0)
    assert link.command(cmd, mavlink2.MAVLINK_MSG_ID_SYS_STATUS, -1) is CommandOutcome.ACCEPTED
    assert fc.stream_rate("SYS_STATUS") is None
    assert link.command(cmd, mavlink2.MAVLINK_MSG_ID_SYS_STATUS, 0) is CommandOutcome.ACCEPTED
    assert fc.stream_rate("SYS_STATUS") == pytest.approx(2.0)
    assert link.command(cmd, mavlink2.MAVLINK_MSG_ID_VFR_HUD, 100_000) is CommandOutcome.FAILED


def test_after_a_reboot_streams_are_back_at_their_defaults(ardu):
    link, fc = ardu(fc=dict(sys_status_hz=2.0))
    assert fc.stream_rate("ATTITUDE") == pytest.approx(20.0)  # asked by the link
    link.shutdown()  # nobody to ask again
    fc.reboot()
    wait_until(lambda: fc.reboots == 1, 5, "the reboot")
    assert fc.stream_rate("ATTITUDE") is None and fc.stream_rate("EXTENDED_SYS_STATE") is None
    assert fc.stream_rate("SYS_STATUS") == pytest.approx(2.0) and fc.stream_rate("HEARTBEAT") == pytest.approx(10.0)
    assert fc.boot_ms < 2000


def test_reboot_command_wants_param1_1_or_3(ardu):
    link, fc = ardu()
    assert link.command(mavlink2.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 2) is CommandOutcome.UNSUPPORTED
    assert not fc.rebooting


# -- Mode::allows_arming, do_user_takeoff, landed_state, mode_land

def test_arming_is_refused_in_land_and_takeoff_only_in_guided_armed_on_the_ground(ardu):
    link, fc = ardu(vehicle=VehicleState(mode="LAND"))
    assert link.command(mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 1) is CommandOutcome.FAILED
    assert link.command(mavlink2.MAV_CMD_DO_SET_MODE, CUSTOM, 5) is CommandOutcome.ACCEPTED  # LOITER
    assert link.command(mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 1) is CommandOutcome.ACCEPTED
    assert link.command(mavlink2.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5) is CommandOutcome.FAILED  # not GUIDED
    assert link.command(mavlink2.MAV_CMD_DO_SET_MODE, CUSTOM, 99) is CommandOutcome.FAILED  # no such mode


def test_takeoff_land_and_touchdown_move_the_landed_state_as_arducopter_does(ardu):
    link, fc = ardu(fc=dict(climb_ms=10.0, land_speed_ms=5.0))
    seen: list[str] = []
    link.on_state(lambda s: s.landed_state and (not seen or seen[-1] != s.landed_state) and seen.append(s.landed_state))
    assert link.command(mavlink2.MAV_CMD_DO_SET_MODE, CUSTOM, 4) is CommandOutcome.ACCEPTED  # GUIDED
    assert link.command(mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 1) is CommandOutcome.ACCEPTED
    assert link.command(mavlink2.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 3) is CommandOutcome.ACCEPTED
    wait_until(lambda: link.state.landed_state == "IN_AIR" and link.state.alt_rel_m > 2.9, 5, "at 3 m")
    assert link.command(mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 0) is CommandOutcome.FAILED  # not in the air
    assert link.command(mavlink2.MAV_CMD_DO_SET_MODE, CUSTOM, 9) is CommandOutcome.ACCEPTED  # LAND
    wait_until(lambda: link.state.landed_state == "ON_GROUND" and link.state.armed is False, 5, "touchdown, disarmed")
    assert link.state.mode == "LAND"
    assert seen[-4:] == ["TAKEOFF", "IN_AIR", "LANDING", "ON_GROUND"]


# -- AC_PrecLand::run_estimator (KALMAN_FILTER): outlier rejection

def _three_outliers_then_a_fourth(link, fc) -> bool:
    """Acquire the target straight below, then send four far ones in a row, each once the last was taken in.
    False when the estimator restarted on the way: all of it must fit in LANDING_TARGET_TIMEOUT_MS (2 s)
    after the last fused target, or ArduPilot, and so the fake, loses the target (a stalled test on a
    loaded machine); anything else the estimator does wrong fails the test."""
    _stream_targets(link, _angles(ax=0.0, ay=0.0), 20, 2.4)
    wait_until(lambda: fc.precland.acquired, 1, "acquired")
    assert fc.precland.target_ne == pytest.approx((0.0, 0.0), abs=0.01)
    started, before = fc.precland.init_ms, fc.precland.counters["outliers"]

    def restarted() -> bool:
        return not fc.precland.acquired or fc.precland.init_ms != started

    far = _angles(ax=math.atan(0.5), ay=0.0)  # 4 m to the right: far outside the filter's spread
    for rejected in (1, 2, 3):
        link.send_landing_target(far())
        wait_until(lambda: fc.precland.counters["outliers"] - before == rejected or restarted(), 2,
                   f"outlier {rejected} rejected")
        if restarted():
            return False
        assert fc.precland.target_ne == pytest.approx((0.0, 0.0), abs=0.01)
    link.send_landing_target(far())  # the 4th in a row is fused: three were rejected before it
    wait_until(lambda: fc.precland.target_ne[1] > 0.5 or restarted(), 2, "the estimate moving right")
    if restarted():
        return False
    assert fc.precland.counters["outliers"] - before == 3
    return True


def test_a_single_outlier_is_rejected_and_three_in_a_row_are_taken(ardu):
    link, fc = ardu(vehicle=HOVER)
    # Up to three tries, each on a target acquired anew: only a restart of the estimator (the 2 s timeout) retries.
    assert any(_three_outliers_then_a_fourth(link, fc) for _ in range(3)), \
        "the estimator restarted in each of three tries: the test stalled beyond LANDING_TARGET_TIMEOUT_MS each time"


# -- AC_PosControl::accel_to_lean_angles: LAND's correction towards the target tilts the vehicle

def test_lands_correction_leans_the_vehicle_and_moves_the_marker_across_the_image_between_slow_frames(ardu):
    from kgadapt.onboard.flight.geometry import ned_to_body
    from kgadapt.onboard.flight.landing_targets import CameraModel
    from kgadapt.sim.landing_scene import MarkerScene

    link, fc = ardu(vehicle=HOVER, fc=dict(land_speed_ms=0.5))
    marker = (2.5, 2.0)

    def target():
        v = fc.vehicle
        body = ned_to_body((v.roll, v.pitch, v.yaw), (marker[0] - v.north, marker[1] - v.east, v.alt))
        return LandingTarget(time=time.time(), angle_x=0.0, angle_y=0.0, distance=math.sqrt(sum(c * c for c in body)),
                             position=body)

    assert link.command(mavlink2.MAV_CMD_DO_SET_MODE, CUSTOM, 9) is CommandOutcome.ACCEPTED  # LAND
    scene = MarkerScene(CameraModel(fx=615.0, fy=615.0, cx=320.0, cy=240.0), north=marker[0], east=marker[1],
                        size_m=0.5)
    frames, leans = [], []
    next_frame = time.monotonic()
    stop = time.monotonic() + 6.0
    while time.monotonic() < stop:
        link.send_landing_target(target())
        v = fc.vehicle
        leans.append(max(abs(v.roll), abs(v.pitch)))
        if time.monotonic() >= next_frame:  # what a camera at 1 frame a second sees
            frames.append(scene.corners(((v.roll, v.pitch, v.yaw), v.position_ned)))
            next_frame += 1.0
        time.sleep(0.05)
    assert fc.precland.acquired
    assert max(leans) > math.radians(10)  # 2.5 m/s/s leans the vehicle about 14 degrees

    def centre_and_side(corners):
        centre = (sum(p[0] for p in corners) / 4, sum(p[1] for p in corners) / 4)
        return centre, math.dist(corners[0], corners[1])

    seen = [centre_and_side(c) for c in frames if c is not None]
    jumps = [math.dist(a[0], b[0]) / max(a[1], b[1]) for a, b in zip(seen, seen[1:])]
    assert max(jumps) > 0.5, jumps  # a rule "within half a side between frames" would start over


# -- GCS_MAVLINK::send_home_position, send_local_position: nothing without home / an EKF origin;
#    set_ap_message_interval: a new interval first sends one interval later

def test_after_a_reboot_home_and_local_position_come_only_once_there_is_an_origin(ardu):
    link, fc = ardu(fc=dict(home_after_reboot_s=3.0, origin_after_reboot_s=5.0), link=dict(heartbeat_timeout_s=3.0))
    wait_until(lambda: (link.state.boot_ms or 0) > 1500, 5, "1.5 s of uptime")
    assert link.command(mavlink2.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1, label="reboot") is CommandOutcome.ACCEPTED
    wait_until(lambda: fc.reboots == 1, 5, "the reboot")
    booted = time.monotonic()
    wait_until(lambda: link.state.attitude is not None and link.state.landed_state is not None, 5, "ATTITUDE back")
    assert link.state.position_ned is None and link.state.home is None  # asked for, but no origin yet
    assert fc.stream_rate("LOCAL_POSITION_NED") == pytest.approx(20.0)  # the interval is set all the same
    wait_until(lambda: link.state.home is not None, 6, "HOME_POSITION once home is set")
    assert time.monotonic() - booted >= 3.0 - 0.1
    wait_until(lambda: link.state.position_ned is not None, 6, "LOCAL_POSITION_NED once there is an origin")
    assert time.monotonic() - booted >= 5.0 - 0.1


def test_a_stream_given_a_new_interval_is_first_sent_one_interval_later(ardu):
    from tests.flight.conftest import ALL_FAST

    link, fc = ardu(link=dict(stream_rates=tuple(r for r in ALL_FAST if r[0] != "BATTERY_STATUS")))
    assert "BATTERY_STATUS" not in fc.sent_times  # ArduCopter's default on a companion port: not streamed
    asked = time.time()
    assert link.command(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink2.MAVLINK_MSG_ID_BATTERY_STATUS,
                        1_000_000) is CommandOutcome.ACCEPTED
    got = wait_until(lambda: list(fc.sent_times.get("BATTERY_STATUS", ())), 3, "BATTERY_STATUS")
    assert got[0] - asked >= 0.9  # a bucket of its own: last_sent_ms = now, so one interval from the request
