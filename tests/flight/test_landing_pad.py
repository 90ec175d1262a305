"""The site's landing pad: a big marker for the approach and small ones around the landing point, each leading
to the same spot, and a marker in view down to touchdown.

On real ArduCopter SITL the 0.26 m marker alone left the camera's view below about 0.3 m and no LANDING_TARGET
went out from the last detection to the disarm (2.3-3.3 s at 1 detection a second). The demo site's pad
(knowledge/models/sites/demo.site) adds nine 0.02 m markers, 3 cm apart, around the landing point, with the big
one beside them.
"""

from __future__ import annotations

import math

import pytest

from kgadapt.onboard.flight.confirmation import ConfirmationSettings, MarkerConfirmer, Place
from kgadapt.onboard.flight.flight import choose_marker
from kgadapt.onboard.flight.geometry import ned_to_body
from kgadapt.onboard.flight.landing_targets import AutopilotProfile, CameraModel, TargetBuilder
from kgadapt.onboard.flight.mavlink import FlightState
from kgadapt.onboard.flight.site import load_site, site_from_dict
from kgadapt.sim.landing_scene import PadScene
from tests import support
from tests.conftest import REPO

CAMERA = CameraModel(fx=615.0, fy=615.0, cx=320.0, cy=240.0, width=640, height=480)
PAD = site_from_dict({"site": "pad", "markers": [
    {"id": 45, "size_m": 0.26, "position": [0.0, -0.16, 0.0]},
    {"id": 16, "size_m": 0.02, "position": [0.0, 0.0, 0.0]},
    {"id": 33, "size_m": 0.26},
]}, where="pad.site")
LANDING = (1.3, 2.2)  # the pad's landing point, NED (m), on the ground (down 0)


def _state(attitude, position) -> FlightState:
    return FlightState(time=0.0, link=True, attitude=attitude, position_ned=position)


def test_the_demo_site_ships_a_pad_that_stays_in_view_from_ten_metres_to_the_ground():
    site = load_site(REPO / "knowledge" / "models" / "sites" / "demo.site")
    scene = PadScene.of_site(CAMERA, site, north=0.0, east=0.0, down=0.0)
    # From 10 m to resting on the ground (SITL's copter rests 0.1 m above it), straight above the landing point
    # or up to 5 cm off it in any direction: some marker of the pad is detected at every height on the way.
    for north, east in ((0.0, 0.0), (0.05, 0.05), (-0.05, 0.05), (0.05, -0.05), (-0.05, -0.05), (0.027, -0.003)):
        for height_cm in range(1000, 8, -1):
            seen = scene.detect(((0.0, 0.0, 0.0), (north, east, -height_cm / 100)))
            assert seen, f"no marker of the pad in view at {height_cm} cm, {north, east} m off"
    assert [m for m, _ in scene.detect(((0, 0, 0), (0, 0, -10.0)))] == [45]  # the small ones are too small there
    assert 45 not in [m for m, _ in scene.detect(((0, 0, 0), (0, 0, -0.1)))]
    # The single 0.02 m marker of the first pad left the view on the ground 2.7 cm off (as two SITL landings did).
    single = PadScene.of_site(CAMERA, PAD, north=0.0, east=0.0, down=0.0)
    assert single.detect(((0.0, 0.0, 0.0), (0.027, -0.003, -0.09))) == []


def test_the_demo_pad_rendered_is_found_by_opencv_every_marker_at_once():
    # The pad as it is printed (the small markers beside the big one: OpenCV's detector keeps only one of two
    # concentric candidates, so a marker nested at the centre of another hides it).
    cv2 = pytest.importorskip("cv2")
    import numpy as np

    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    px_per_m = 2000
    image = np.full((900, 1100), 255, np.uint8)
    centre = (450, 750)  # row, column of the landing point

    def paste(mid: int, size_m: float, north: float, east: float) -> None:
        side = int(round(size_m * px_per_m))
        row, col = int(centre[0] - north * px_per_m - side / 2), int(centre[1] + east * px_per_m - side / 2)
        image[row:row + side, col:col + side] = cv2.aruco.generateImageMarker(dictionary, mid, side)

    demo = load_site(REPO / "knowledge" / "models" / "sites" / "demo.site")
    for mid in demo.positions:
        paste(mid, demo.sizes_m[mid], demo.positions[mid][0], demo.positions[mid][1])
    detector = cv2.aruco.ArucoDetector(dictionary, cv2.aruco.DetectorParameters())
    corners, ids, _ = detector.detectMarkers(image)
    assert ids is not None and sorted(ids.ravel().tolist()) == sorted(demo.positions)
    for c, mid in zip(corners, ids.ravel()):
        middle = c.reshape(4, 2).mean(axis=0)
        north, east = (centre[0] - middle[1]) / px_per_m, (middle[0] - centre[1]) / px_per_m
        assert (north, east) == pytest.approx(demo.positions[int(mid)][:2], abs=0.002)


@pytest.mark.parametrize("attitude", [(0.0, 0.0, 0.0), (0.03, -0.04, math.radians(70)), (-0.04, 0.03, -2.5)])
def test_either_marker_of_the_pad_leads_to_the_same_landing_point(attitude):
    position = (1.31, 2.13, -0.7)  # low enough that both markers are in view
    scene = PadScene.of_site(CAMERA, PAD, north=LANDING[0], east=LANDING[1])
    found = dict(scene.detect((attitude, position)))
    assert set(found) == {45, 16}
    truth = ned_to_body(attitude, (LANDING[0] - position[0], LANDING[1] - position[1], -position[2]))
    builder = TargetBuilder(CAMERA, PAD)
    for mid, corners in found.items():
        target, held = builder.build(corners, marker_id=mid, frame_time=10.0, profile=AutopilotProfile.ARDUPILOT,
                                     state=_state(attitude, position), pose_at=lambda t: (attitude, position))
        assert target.position == pytest.approx(truth, abs=0.01), mid
        assert held.ned == pytest.approx((*LANDING, 0.0), abs=0.01)
        place = builder.locate(corners, marker_id=mid, frame_time=10.0, state=_state(attitude, position),
                               pose_at=lambda t: (attitude, position))
        assert place.ned == pytest.approx((*LANDING, 0.0), abs=0.01), mid
    # A marker of no pad is its own landing point: no offset.
    assert PAD.to_landing_point(33) is None and PAD.to_landing_point(16) is None
    assert PAD.to_landing_point(45) == pytest.approx((0.0, 0.16, 0.0))


def _place(ned, size=0.26, rng=0.7) -> Place:
    return Place(ned, size, rng)


def test_the_confirmation_follows_the_pad_when_the_big_marker_gives_way_to_the_small_one():
    corners_big = [[100, 100], [200, 100], [200, 200], [100, 200]]
    corners_small = [[300, 300], [340, 300], [340, 340], [300, 340]]
    at = (1.3, 2.2, 0.0)
    confirmer = MarkerConfirmer(ConfirmationSettings(site=PAD))
    for t in (1.0, 2.0):  # two sightings of the big marker, one a second
        assert confirmer.update([45], [corners_big], t, places=[_place(at)]) == []
    # the third sighting is of the small marker alone (the big one has left the view): the pad's streak goes on
    assert confirmer.update([16], [corners_small], 3.0, places=[_place((1.31, 2.2, 0.0), 0.02, 0.3)]) == [0]
    # Per id, as before the pad, the small marker would start its own streak: 2 more seconds without a target.
    per_id = MarkerConfirmer(ConfirmationSettings(site=site_from_dict(
        {"site": "ids", "markers": [{"id": 45, "size_m": 0.26}, {"id": 16, "size_m": 0.02}]}, where="ids.site")))
    for t in (1.0, 2.0):
        per_id.update([45], [corners_big], t, places=[_place(at)])
    assert per_id.update([16], [corners_small], 3.0, places=[_place((1.31, 2.2, 0.0), 0.02, 0.3)]) == []


def test_a_pad_marker_seen_somewhere_else_breaks_the_streak_and_one_id_twice_is_not_trusted():
    corners = [[100, 100], [200, 100], [200, 200], [100, 200]]
    small = [[300, 300], [340, 300], [340, 340], [300, 340]]
    confirmer = MarkerConfirmer(ConfirmationSettings(site=PAD))
    confirmer.update([45], [corners], 1.0, places=[_place((1.3, 2.2, 0.0))])
    confirmer.update([45], [corners], 2.0, places=[_place((1.3, 2.2, 0.0))])
    # a 16 that lies 1.5 m away is not the pad's landing point: no confirmation
    assert confirmer.update([16], [small], 3.0, places=[_place((2.8, 2.2, 0.0), 0.02, 0.3)]) == []
    again = MarkerConfirmer(ConfirmationSettings(site=PAD))
    for t in (1.0, 2.0, 3.0):
        assert again.update([16, 16], [small, corners], t) == []
    # both markers of the pad in one frame: the larger in the image stands for the pad, and is the one confirmed
    both = MarkerConfirmer(ConfirmationSettings(site=PAD))
    for t in (1.0, 2.0):
        both.update([16, 45], [small, corners], t, places=[_place((1.3, 2.2, 0.0), 0.02), _place((1.3, 2.2, 0.0))])
    assert both.update([16, 45], [small, corners], 3.0,
                       places=[_place((1.3, 2.2, 0.0), 0.02), _place((1.3, 2.2, 0.0))]) == [1]


def test_landing_on_a_pad_marker_takes_whichever_marker_of_the_pad_is_seen():
    small = [[300, 300], [340, 300], [340, 340], [300, 340]]
    other = [[0, 0], [300, 0], [300, 300], [0, 300]]
    detections = support.detections([[33], [16]], [[other], [small]])
    assert choose_marker(detections, 45, PAD) == 1  # asked for the pad's big marker: its small one will do
    assert choose_marker(detections, 45, None) is None  # without the site: only marker 45 itself
    assert choose_marker(detections, 33, PAD) == 0
    assert choose_marker(detections, None, PAD) == 0  # the largest
