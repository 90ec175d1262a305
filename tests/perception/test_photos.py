"""Every configuration on real photographs (sim/photographs, sources in SOURCES.txt), issue 11.

The photos hold markers of DICT_6X6_250 (and a custom dictionary), not the
site's DICT_4X4_50: read with their own dictionary, they say how each
configuration's pre-processing and parameters cope with real frames at their
own light and darkened by the camera model; read with the site's dictionary
(tests/perception/test_confirmation.py), every marker found is a phantom.
The reference is what OpenCV's default detector finds in the photo at its own
brightness.
"""

from __future__ import annotations

import pytest

from kgadapt.bench.perception_quality import photo_agreement
from kgadapt.sim.photos import AWAITED_PHOTOS, PHOTO_DICTIONARIES, PHOTO_DIR, load_photo, photo_frames, photo_truth


def test_every_photo_named_in_the_sources_is_here_with_markers_to_find():
    sources = (PHOTO_DIR / "SOURCES.txt").read_text()
    for name, dictionary in PHOTO_DICTIONARIES.items():
        assert name in sources and (PHOTO_DIR / name).is_file()
        if dictionary == "DICT_6X6_250":
            assert len(photo_truth(load_photo(name), dictionary)) >= 6, name


def test_the_camera_model_darkens_a_photo_to_the_asked_level():
    photo = load_photo("contrib_singlemarkersoriginal.jpg")
    for level in (6.0, 30.0):
        frame = next(photo_frames(photo, level, count=1))
        assert abs(float(frame.image.mean()) - level) < 1.0


@pytest.fixture(scope="module")
def agreement():
    return {(r["config"], r["level"]): r for r in photo_agreement(levels=(6.0, 15.0, 30.0), frames=3)["rows"]}


def test_every_configuration_finds_every_marker_at_the_photos_own_light(agreement):
    for config in ("marker_detection_day", "marker_detection_dusk", "marker_detection_dark"):
        row = agreement[(config, None)]
        assert row["photos"] >= 0.97 and row["photo_false_per_frame"] == 0, row


def test_darkened_photos_rank_the_configurations_as_calibration_does(agreement):
    # Measured here (3 frames per photo and level): dark 0.99, dusk 0.91, day 0.19 at level 6.
    dark, dusk, day = (agreement[(f"marker_detection_{c}", 6.0)]["photos"] for c in ("dark", "dusk", "day"))
    assert dark >= 0.9 and dusk >= 0.75 and day <= 0.45
    assert dark > dusk > day


def test_photos_and_the_synthetic_scene_agree_where_a_configuration_is_not_at_its_edge(agreement):
    # Where a rate is flat (the dark configuration throughout, every one at level 30) the darkened
    # photos and the synthetic scene agree within 5 points. At the edge of a configuration's range
    # (day at 6 and 15, dusk at 6) they differ by 10-20 points: the photos' markers sit on brighter
    # paper than the scene's; docs/perception.md gives the figures.
    for config in ("marker_detection_day", "marker_detection_dusk", "marker_detection_dark"):
        assert abs(agreement[(config, 30.0)]["difference_points"]) <= 5
    for level in (6.0, 15.0):
        assert abs(agreement[("marker_detection_dark", level)]["difference_points"]) <= 5


# -- real photographs of the other dictionaries (issue 29): found with a licence, shipped once placed here --

# Their oracle gap is a benchmark figure (bench/results/perception.photos.real_*.json), not a test.


def test_every_awaited_photograph_is_named_in_the_sources_with_where_it_comes_from():
    sources = (PHOTO_DIR / "SOURCES.txt").read_text()
    for name in AWAITED_PHOTOS:
        line = next(x for x in sources.splitlines() if x.strip().startswith(name))
        assert "blob" in line or "/" in line, line


@pytest.mark.parametrize("name", sorted(AWAITED_PHOTOS))
def test_an_awaited_photograph_holds_the_markers_of_its_dictionary(name):
    if not (PHOTO_DIR / name).is_file():
        pytest.skip(f"{name} is not placed in sim/photographs yet (SOURCES.txt names its source)")
    dictionary, markers = AWAITED_PHOTOS[name]
    assert len(photo_truth(load_photo(name), dictionary)) == markers

