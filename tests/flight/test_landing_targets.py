"""Marker pose from its size, camera and marker files, per-autopilot frames, and the held target's prediction."""

from __future__ import annotations

import json
import math

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from kgadapt.onboard.flight.geometry import body_to_camera, body_to_ned, camera_to_body, ned_to_body
from kgadapt.onboard.flight.landing_targets import AutopilotProfile, CameraModel, TargetBuilder, load_camera, load_site_markers
from kgadapt.onboard.flight.mavlink import FlightState
from kgadapt.onboard.flight.site import SiteMarkers
from kgadapt.shared.errors import ConfigError, ModelError
from kgadapt.sim.landing_scene import MarkerScene

CAMERA = CameraModel(fx=615.0, fy=615.0, cx=320.0, cy=240.0, width=640, height=480)
MARKERS = SiteMarkers(site="pad", sizes_m={7: 0.5})


def _state(attitude=(0.0, 0.0, 0.0), position=(0.0, 0.0, -8.0), rangefinder=None) -> FlightState:
    return FlightState(time=0.0, link=True, attitude=attitude, position_ned=position, rangefinder_m=rangefinder)


def test_rotations_are_inverse_and_yaw_turns_north_to_east():
    att = (0.1, -0.2, 1.3)
    v = (1.0, 2.0, 3.0)
    assert ned_to_body(att, body_to_ned(att, v)) == pytest.approx(v)
    assert body_to_ned((0, 0, math.pi / 2), (1, 0, 0)) == pytest.approx((0, 1, 0), abs=1e-12)
    assert camera_to_body((1.0, 2.0, 3.0)) == pytest.approx((-2.0, 1.0, 3.0))
    assert body_to_camera(camera_to_body((1, 2, 3), yaw_deg=30, offset=(0.1, 0, 0.05)), yaw_deg=30,
                          offset=(0.1, 0, 0.05)) == pytest.approx((1, 2, 3))


@pytest.mark.parametrize("attitude", [(0.0, 0.0, 0.0), (0.15, -0.1, 0.7), (-0.2, 0.2, -2.5)])
@pytest.mark.parametrize("camera", [CAMERA, CameraModel(fx=600, fy=610, cx=330, cy=235, width=640, height=480,
                                                        yaw_deg=90, offset_m=(0.1, -0.05, 0.05))])
def test_the_marker_position_from_its_size_matches_where_it_lies(attitude, camera):
    position = (1.0, -0.5, -6.0)
    scene = MarkerScene(camera, north=2.0, east=-1.0, size_m=0.5)
    corners = scene.corners((attitude, position))
    assert corners is not None
    builder = TargetBuilder(camera, MARKERS)
    target, held = builder.build(corners, marker_id=7, frame_time=100.0, profile=AutopilotProfile.ARDUPILOT,
                                 state=_state(attitude, position))
    truth_body = ned_to_body(attitude, (2.0 - 1.0, -1.0 + 0.5, 6.0))
    assert target.frame == mavlink2.MAV_FRAME_BODY_FRD and target.position == pytest.approx(truth_body, abs=0.01)
    assert target.distance == pytest.approx(math.dist((0, 0, 0), truth_body), abs=0.01)
    # the angles say the same as the position, read the way ArduPilot reads them
    los = (-math.tan(target.angle_y), math.tan(target.angle_x), 1.0)
    assert los[0] / los[2] == pytest.approx(truth_body[0] / truth_body[2], abs=1e-3)
    assert los[1] / los[2] == pytest.approx(truth_body[1] / truth_body[2], abs=1e-3)
    px4, _ = builder.build(corners, marker_id=7, frame_time=100.0, profile=AutopilotProfile.PX4,
                           state=_state(attitude, position))
    assert px4.frame == mavlink2.MAV_FRAME_LOCAL_NED and px4.position == pytest.approx((2.0, -1.0, 0.0), abs=0.01)
    assert held.ned == pytest.approx((2.0, -1.0, 0.0), abs=0.01)


def test_the_attitude_at_the_frames_time_is_used_for_px4():
    attitude, position = (0.2, 0.0, 0.0), (0.0, 0.0, -5.0)
    corners = MarkerScene(CAMERA, north=0.5, east=0.5, size_m=0.5).corners((attitude, position))
    # the current state is level, the frame was taken rolled: the history wins
    target, _ = TargetBuilder(CAMERA, MARKERS).build(
        corners, marker_id=7, frame_time=50.0, profile=AutopilotProfile.PX4, state=_state((0, 0, 0), position),
        pose_at=lambda t: (attitude, position) if t == 50.0 else None)
    assert target.position == pytest.approx((0.5, 0.5, 0.0), abs=0.01)


def test_without_a_size_angles_go_with_the_rangefinders_distance_and_without_it_alone():
    attitude, position = (0.0, 0.1, 0.0), (0.0, 0.0, -4.0)
    corners = MarkerScene(CAMERA, north=1.0, east=0.0, size_m=0.5).corners((attitude, position))
    builder = TargetBuilder(CAMERA, None)
    slant = 4.0 / (math.cos(0.1))
    target, held = builder.build(corners, marker_id=3, frame_time=1.0, profile=AutopilotProfile.ARDUPILOT,
                                 state=_state(attitude, position, rangefinder=slant))
    assert target.position is None and target.distance == pytest.approx(math.hypot(1.0, 4.0), rel=0.02)
    assert held is not None
    alone, none = builder.build(corners, marker_id=3, frame_time=1.0, profile=AutopilotProfile.ARDUPILOT,
                                state=_state(attitude, position))
    assert alone.distance == 0.0 and alone.position is None and none is None
    assert builder.counters == {"position": 0, "rangefinder": 1, "angles": 1}


def test_the_held_target_is_predicted_for_where_the_vehicle_has_moved():
    corners = MarkerScene(CAMERA, north=1.0, east=1.0, size_m=0.5).corners(((0, 0, 0), (0, 0, -6.0)))
    _, held = TargetBuilder(CAMERA, MARKERS).build(corners, marker_id=7, frame_time=1.0,
                                                   profile=AutopilotProfile.ARDUPILOT, state=_state(position=(0, 0, -6.0)))
    moved = _state(attitude=(0.0, 0.0, math.pi / 2), position=(1.0, 0.0, -3.0))  # turned right, lower, north 1 m
    predicted = held.predict(2.0, moved, AutopilotProfile.ARDUPILOT)
    assert predicted.time == 2.0
    # the marker is now straight east of the vehicle = straight ahead after the turn
    assert predicted.position == pytest.approx((1.0, 0.0, 3.0), abs=0.01)


def test_a_camera_file_is_checked_on_load(tmp_path):
    good = tmp_path / "camera.json"
    good.write_text(json.dumps({**{k: v for k, v in CAMERA.as_dict().items() if k != "mount"},
                                "mount": {"yaw_deg": 90, "offset_m": [0.1, 0, 0.05]}}))
    camera = load_camera(good)
    assert camera.yaw_deg == 90 and camera.offset_m == (0.1, 0.0, 0.05)
    for bad, says in [
        ({"fx": 600, "fy": 600, "cx": 320}, "lacks cy"),
        ({"fx": -1, "fy": 600, "cx": 320, "cy": 240}, "fx must be positive"),
        ({"fx": 600, "fy": 600, "cx": 320, "cy": 240, "width": 640, "height": 200}, "outside"),
        ({"fx": 600, "fy": 600, "cx": 320, "cy": 240, "distortion": [1, 2]}, "distortion"),
        ({"fx": 600, "fy": 600, "cx": 320, "cy": 240, "fov": 60}, "unknown field"),
        ({"fx": 600, "fy": 600, "cx": 320, "cy": 240, "mount": {"offset_m": [1]}}, "offset_m"),
        ({"fx": "600", "fy": 600, "cx": 320, "cy": 240}, "fx must be a finite number"),
    ]:
        path = tmp_path / "bad.json"
        path.write_text(json.dumps(bad))
        with pytest.raises(ConfigError, match=says) as info:
            load_camera(path)
        assert str(path) in str(info.value)
    path = tmp_path / "broken.json"
    path.write_text("{")
    with pytest.raises(ConfigError, match="not JSON"):
        load_camera(path)


def test_a_site_marker_file_is_checked_on_load(tmp_path):
    good = tmp_path / "markers.json"
    good.write_text(json.dumps({"site": "pad", "markers": [{"id": 7, "size_m": 0.3}, {"id": 8, "size_m": 0.15}]}))
    markers = load_site_markers(good)
    assert markers.size_of(7) == 0.3 and markers.size_of(9) is None
    for bad, says in [
        ({"markers": []}, "non-empty"),
        ({"markers": [{"id": 7, "size_m": 0.3}, {"id": 7, "size_m": 0.2}]}, "listed twice"),
        ({"markers": [{"id": -1, "size_m": 0.3}]}, "'id' must be"),
        ({"markers": [{"id": 1, "size_m": 0}]}, "size_m must be positive"),
        ({"markers": [{"id": 1, "size_m": 30}]}, "not a marker's size"),
        ({"markers": [{"id": 1, "size": 0.3}]}, "marker 0 must be"),
    ]:
        path = tmp_path / "bad.json"
        path.write_text(json.dumps(bad))
        with pytest.raises(ModelError, match=says):  # the one site file format (onboard/flight/site.py)
            load_site_markers(path)


def test_the_profile_comes_from_the_heartbeat_unless_named():
    assert AutopilotProfile.of("auto", FlightState(time=0, autopilot="px4")) is AutopilotProfile.PX4
    assert AutopilotProfile.of(None, FlightState(time=0, autopilot="ardupilot")) is AutopilotProfile.ARDUPILOT
    assert AutopilotProfile.of("px4") is AutopilotProfile.PX4
    with pytest.raises(ConfigError, match="'inav'"):
        AutopilotProfile.of("inav")
