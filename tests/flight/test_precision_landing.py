"""Precision landings on the fake flight controller (ArduCopter's AC_PrecLand behaviour), end to end.

A marker 2.5 m forward and 2 m right of where LAND starts, 10 m below; detections come over
Zenoh at 1 a second; the bridge sends LANDING_TARGETs; the fake autopilot lands.
LAND_SPEED is raised to 1.5 m/s (ArduCopter: 0.5 below 10 m) so a landing takes seconds, not half a minute.
"""

from __future__ import annotations

import pytest

from kgadapt.shared.session import ZenohSettings, open_session
from kgadapt.sim.landing_check import LandingCheckSettings, run_landing_check

FAST = dict(land_speed_ms=1.5, xy_speed_ms=3.0)
# At 1 detection a second a marker is confirmed (kgadapt.onboard.flight.confirmation: 3 steady sightings) 2 s after it
# is first seen; ArduCopter's own LAND_SPEED (0.5 m/s below 10 m) leaves the time a real landing has.
REAL_SPEED = dict(land_speed_ms=0.5, xy_speed_ms=2.0)


@pytest.fixture(scope="module")
def session():
    s = open_session(ZenohSettings(mode="peer", listen=(), connect=()))
    yield s
    s.close()


@pytest.mark.parametrize("rangefinder", [True, False], ids=["rangefinder", "no-rangefinder"])
def test_lands_on_the_marker_at_one_detection_a_second(session, rangefinder):
    result = run_landing_check(session, LandingCheckSettings(rate_hz=1.0, rangefinder=rangefinder, fake=REAL_SPEED))
    assert result.landed and result.acquired
    assert result.error_m < 0.5, result
    assert result.targets_resent > result.targets_sent  # the held target bridged the gaps


def test_without_sizes_and_without_a_rangefinder_the_target_is_never_acquired(session):
    # What SITL showed before positions were sent: angles alone, no height -> lands 3.2 m off.
    result = run_landing_check(session, LandingCheckSettings(rate_hz=10.0, rangefinder=False, sizes_known=False,
                                                             fake=FAST))
    assert result.landed and not result.acquired
    assert result.error_m == pytest.approx((2.5**2 + 2.0**2) ** 0.5, abs=0.05)


def test_without_the_held_target_one_detection_a_second_is_too_few(session):
    # What SITL showed: the estimator wants a measurement every 0.5 s during its first 2 s.
    result = run_landing_check(session, LandingCheckSettings(rate_hz=1.0, hold_s=0.0, fake=FAST))
    assert result.landed and not result.acquired
    assert result.error_m > 2.0


def test_at_one_detection_a_second_the_target_survives_the_vehicles_motion_during_the_descent(session):
    # ArduCopter SITL lost the target from 1.9 to 5.5 s after LAND: leaning towards the marker moved it across
    # the image by many of its sides between frames, and a steadiness rule kept in the image started over.
    # The fake leans the same way (AC_PosControl::accel_to_lean_angles); confirmed by its place in the local
    # frame, the marker keeps its streak: no gap over 1 s between LANDING_TARGETs after the acquisition.
    result = run_landing_check(session, LandingCheckSettings(rate_hz=1.0, rangefinder=False, fake=REAL_SPEED))
    assert result.landed and result.acquired and result.error_m < 0.5, result
    assert result.max_gap_s is not None and result.max_gap_s <= 1.0, result


def test_after_a_reboot_on_the_ground_it_takes_off_and_lands_on_the_marker(session):
    # LOCAL_POSITION_NED comes back once the autopilot has an origin (SITL: 41 s after a reboot); 3 s here.
    result = run_landing_check(session, LandingCheckSettings(rate_hz=1.0, reboot_first=True,
                                                             fake=dict(REAL_SPEED, climb_ms=5.0, home_after_reboot_s=2.0,
                                                                       origin_after_reboot_s=3.0)))
    assert result.streams_back_s is not None and result.streams_back_s < 2.2 + 5.0  # reboot silence + 5 s
    assert result.origin_back_s >= 3.0
    assert result.landed and result.acquired and result.error_m < 0.5, result
