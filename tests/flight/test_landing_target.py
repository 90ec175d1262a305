"""From a marker's corners and the camera intrinsics to LANDING_TARGET fields."""

from __future__ import annotations

import pytest

from kgadapt.onboard.flight.flight import CameraIntrinsics, choose_marker, landing_target, marker_points
from kgadapt.shared.errors import FlightLinkError, MessageError
from tests.support import detections

K = CameraIntrinsics(fx=600.0, fy=500.0, cx=320.0, cy=240.0)
# A 40 x 40 px marker centred on (400, 300): 80 px right and 60 px below the principal point.
SQUARE = [[380.0, 280.0], [420.0, 280.0], [420.0, 320.0], [380.0, 320.0]]
# Worked by hand: atan(80 / 600) and atan(60 / 500).
ANGLE_X = 0.13255153229667402
ANGLE_Y = 0.11942892601833845


def test_angles_are_measured_from_the_principal_point_with_the_focal_lengths():
    target = landing_target(SQUARE, K, frame_time=1000.0, marker_id=7)
    assert target.angle_x == pytest.approx(ANGLE_X, abs=1e-9)
    assert target.angle_y == pytest.approx(ANGLE_Y, abs=1e-9)
    assert target.target_num == 7 and target.time == 1000.0
    assert target.position is None and target.distance == 0.0


def test_a_marker_up_and_left_of_centre_gives_negative_angles():
    corners = [[180.0, 180.0], [220.0, 180.0], [220.0, 220.0], [180.0, 220.0]]  # centre (200, 200)
    target = landing_target(corners, K, frame_time=0.0)
    assert target.angle_x == pytest.approx(-0.19739555984988078)  # atan(-120 / 600)
    assert target.angle_y == pytest.approx(-0.07982998571223732)  # atan(-40 / 500)


def test_the_angular_size_spans_the_marker():
    target = landing_target(SQUARE, K, frame_time=0.0)
    assert target.size_x == pytest.approx(0.065480, abs=1e-6)  # atan(100/600) - atan(60/600)
    assert target.size_y == pytest.approx(0.078825, abs=1e-6)  # atan(80/500) - atan(40/500)


def test_opencv_shaped_and_flat_corners_give_the_same_target():
    flat = [v for point in SQUARE for v in point]
    assert landing_target([SQUARE], K, frame_time=0.0) == landing_target(SQUARE, K, frame_time=0.0)
    assert landing_target(flat, K, frame_time=0.0) == landing_target(SQUARE, K, frame_time=0.0)


def test_a_pose_in_the_camera_frame_becomes_a_valid_body_frd_position():
    # 0.3 m right of and 0.2 m below the image centre (towards the tail), 4 m down.
    target = landing_target(SQUARE, K, frame_time=0.0, pose=[0.3, 0.2, 4.0])
    assert target.position == pytest.approx((-0.2, 0.3, 4.0))
    assert target.distance == pytest.approx((0.3 ** 2 + 0.2 ** 2 + 16) ** 0.5)


@pytest.mark.parametrize("corners", [
    [[1, 2], [3, 4], [5, 6]], [[1, 2], [3, 4], [5, 6], [7, "x"]], "nope", [[1, 2, 3]] * 4, [float("nan")] * 8,
])
def test_bad_corners_are_refused_with_a_message_error(corners):
    with pytest.raises(MessageError, match="corner"):
        marker_points(corners)


def test_the_largest_marker_is_chosen_unless_a_target_id_is_given():
    small = [[0, 0], [10, 0], [10, 10], [0, 10]]
    found = detections([[3], [9]], [SQUARE, small])  # ids as OpenCV's N x 1 array
    assert choose_marker(found, None) == 0
    assert choose_marker(found, 9) == 1
    assert choose_marker(found, 5) is None
    assert choose_marker(detections([], []), None) is None
    with pytest.raises(MessageError, match="2 ids but 1 corner"):
        choose_marker(detections([1, 2], [SQUARE]), None)


@pytest.mark.parametrize("values", [dict(fx=0.0), dict(fy=-1.0), dict(cx=float("inf")), dict(cy="240")])
def test_bad_intrinsics_are_refused(values):
    with pytest.raises(FlightLinkError):
        CameraIntrinsics(**{**dict(fx=600.0, fy=600.0, cx=320.0, cy=240.0), **values})
