"""The light estimate a window, a lamp or a black corner cannot fool (issue 11)."""

from __future__ import annotations

import numpy as np
import pytest

from kgadapt.onboard.perception.illumination import (
    LightSettings,
    LightSource,
    band_for_level,
    estimate_light,
    luminance,
    marker_boxes,
    marker_histogram,
    marker_mask,
)
from kgadapt.onboard.perception.scene import IlluminationProfile, LightLayout, SceneSettings, SyntheticScene
from kgadapt.shared.errors import ConfigError
from kgadapt.sim.photos import PHOTO_DICTIONARIES, load_photo, photo_truth

ROWS = [
    {"config": "marker_detection_dark", "band": "dark", "min_level": 0, "max_level": 12},
    {"config": "marker_detection_dusk", "band": "dusk", "min_level": 12, "max_level": 40},
    {"config": "marker_detection_day", "band": "day", "min_level": 40, "max_level": 255},
]


@pytest.fixture(scope="module")
def scene():
    return SyntheticScene(SceneSettings())


def render(scene, level, **light):
    return scene.render(0.3, IlluminationProfile.constant(level, light=LightLayout(**light)), np.random.default_rng(3))


def test_a_saturated_window_strip_over_a_dark_scene_stays_dark(scene):
    frame = render(scene, 6, window=0.15)
    # The whole-frame mean is fooled: the window lifts it from 6 into the day band.
    assert luminance(frame.image).mean > 40
    light = estimate_light(frame.image)
    assert band_for_level(light.level, ROWS) == "dark"
    assert light.saturated == pytest.approx(0.15, abs=0.01)  # it says what it left out
    assert light.source is LightSource.FRAME


def test_a_bright_scene_with_a_black_corner_stays_day(scene):
    frame = render(scene, 60)
    image = frame.image.copy()
    image[:, : int(0.45 * image.shape[1])] = 0  # a deep shadow over 45 % of the frame, clipped at the floor
    assert band_for_level(luminance(image).mean, ROWS) == "dusk"  # the mean is fooled
    light = estimate_light(image)
    assert band_for_level(light.level, ROWS) == "day"
    assert light.black > 0.4


def test_a_dark_object_over_much_of_a_bright_scene_is_outweighed_by_the_markers_in_the_light(scene):
    frame = render(scene, 60)
    image = frame.image.copy()
    image[:, : int(0.45 * image.shape[1])] = 12  # a dark object, not clipped: it counts in the frame figure
    seen = [t.corners for t in frame.truth if min(x for x, _ in t.corners) > 0.45 * image.shape[1]]
    assert len(seen) == 3
    assert band_for_level(estimate_light(image).level, ROWS) == "dusk"  # the frame alone is fooled here
    assert band_for_level(estimate_light(image, seen).level, ROWS) == "day"  # the markers' light is not


def test_a_spotlight_on_the_markers_reads_the_light_they_are_in(scene):
    # A dark hall, a lamp on the small marker at the lower right: the frame says dark,
    # the light around the marker is day.
    frame = render(scene, 10, spot=(0.88, 0.74, 0.08), spot_gain=300.0)
    marker = next(t for t in frame.truth if t.id == 42)
    without = estimate_light(frame.image)
    with_markers = estimate_light(frame.image, [marker.corners])
    assert band_for_level(without.level, ROWS) == "dark"
    assert with_markers.source is LightSource.MARKERS and with_markers.markers == 1
    assert with_markers.marker_level > 40
    assert with_markers.level > 3 * without.level
    assert band_for_level(with_markers.level, ROWS) != "dark"


def test_markers_in_shadow_pull_a_bright_frame_down(scene):
    frame = render(scene, 50, stripes=0)
    image = frame.image.copy()
    marker = next(t for t in frame.truth if t.id == 33)
    xs = [int(x) for x, _ in marker.corners]
    ys = [int(y) for _, y in marker.corners]
    y0, y1, x0, x1 = min(ys) - 40, max(ys) + 40, min(xs) - 40, max(xs) + 40
    image[y0:y1, x0:x1] = (image[y0:y1, x0:x1] * 0.3).astype(np.uint8)  # the marker sits in a shadow
    assert band_for_level(estimate_light(image).level, ROWS) == "day"
    assert band_for_level(estimate_light(image, [marker.corners]).level, ROWS) == "dusk"


def test_an_evenly_lit_scene_reads_close_to_its_mean(scene):
    for level in (6, 20, 100):
        frame = render(scene, level)
        light = estimate_light(frame.image)
        # Clipped blacks are left out, so a dark frame reads a little high: within 15 %, 5 % from 20 up.
        assert level * 0.97 <= light.level <= level * (1.15 if level < 20 else 1.05), (level, light)


def test_an_all_black_frame_falls_back_and_says_so():
    light = estimate_light(np.zeros((48, 64), np.uint8))
    assert light.level == 0 and light.source is LightSource.CLIPPED and light.usable == 0
    light = estimate_light(np.full((48, 64), 255, np.uint8))
    assert light.saturated == 1.0 and light.source is LightSource.CLIPPED


def test_bad_settings_and_images_are_refused():
    with pytest.raises(ConfigError, match="black"):
        LightSettings(black=250, saturated=200)
    with pytest.raises(ConfigError, match="grey uint8"):
        estimate_light(np.zeros((4, 4, 3), np.uint8))


def test_the_marker_mask_over_every_kth_pixel_is_the_full_masks_sample():
    rng = np.random.default_rng(11)
    for _ in range(2000):
        h, w = (int(v) for v in rng.integers(5, 200, 2))
        step = int(rng.integers(1, 5))
        markers = [rng.uniform(-20, 250, (4, 2)).tolist() for _ in range(int(rng.integers(1, 4)))]
        full, sampled = marker_mask((h, w), markers, 0.5), marker_mask((h, w), markers, 0.5, step=step)
        assert (full is None) == (sampled is None)
        if full is not None:
            assert np.array_equal(full[::step, ::step], sampled), (h, w, step, markers)


def test_the_histogram_around_markers_counts_each_sampled_pixel_of_their_boxes_once():
    rng = np.random.default_rng(12)
    for _ in range(500):
        h, w = (int(v) for v in rng.integers(20, 160, 2))
        gray = rng.integers(0, 256, (h, w), dtype=np.uint8)
        markers = [rng.uniform(-20, 180, (4, 2)).tolist() for _ in range(int(rng.integers(1, 5)))]
        boxes = marker_boxes((h, w), markers, 0.5)
        if not boxes:
            continue
        step = int(rng.integers(1, 5))
        # The reference: every pixel of the union on the grid anchored at the boxes' top left corner.
        x0, y0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
        inside = np.zeros((h, w), bool)
        for xa, ya, xb, yb in boxes:
            inside[ya:yb, xa:xb] = True
        grid = np.zeros((h, w), bool)
        grid[y0::step, x0::step] = True
        expected = np.bincount(gray[inside & grid], minlength=256)
        assert np.array_equal(marker_histogram(gray, boxes, step), expected.astype(np.float32))
        if step == 1:
            assert np.array_equal(marker_histogram(gray, boxes, 1), np.bincount(gray[marker_mask((h, w), markers, 0.5) > 0],
                                                                                minlength=256).astype(np.float32))


def test_corners_as_arrays_nested_lists_or_flat_lists_make_the_same_boxes():
    corners = [[10.5, 20.0], [60.0, 22.0], [58.0, 70.0], [12.0, 68.0]]
    flat = marker_boxes((480, 640), [corners], 0.5)
    assert flat == marker_boxes((480, 640), [np.array(corners, np.float32)], 0.5)
    assert flat == marker_boxes((480, 640), [[corners]], 0.5)  # cv2's 1 x 4 x 2 nesting
    assert marker_boxes((480, 640), [[[1.0, 2.0], [float("nan"), 3.0], [4.0, 5.0], [6.0, 7.0]]], 0.5) == []
    assert marker_boxes((480, 640), [[[-90.0, -90.0], [-80.0, -90.0], [-80.0, -80.0]]], 0.5) == []  # outside


@pytest.mark.parametrize("name", sorted(n for n, d in PHOTO_DICTIONARIES.items() if d.startswith("DICT_")))
def test_the_light_around_markers_read_from_a_sample_reads_as_every_pixel_on_photographs(name):
    # The region around the markers is read as coarsely as leaves marker_samples pixels (every 4th each way
    # on these, where markers cover much of the frame); on the real photographs the estimate stays within a
    # grey level of every pixel's (bands are tens of levels wide).
    photo = load_photo(name)
    markers = [m["corners"] for m in photo_truth(photo, PHOTO_DICTIONARIES[name])]
    assert markers
    every = estimate_light(photo, markers, LightSettings(marker_samples=photo.size))
    sampled = estimate_light(photo, markers)
    assert sampled.source is LightSource.MARKERS and sampled.markers == len(markers)
    assert sampled.level == pytest.approx(every.level, abs=1.0)
    assert sampled.frame_level == every.frame_level


def test_malformed_or_absent_markers_are_left_out_of_the_estimate_not_an_error_of_the_frame(scene):
    # The camera weighs markers from any detector's detections on the wire: one malformed entry must not cost
    # the frame its light figures.
    frame = render(scene, 60)
    good = [t.as_wire()["corners"] for t in frame.truth]
    bad = [[[1, 2], [3]], [["a", "b"]], [[1, 2], [3, 4], [5, "x"]], [5], [[None]], [[float("nan"), 1.0]] * 4,
           [[-90.0, -90.0], [-80.0, -90.0], [-80.0, -80.0], [-90.0, -80.0]]]  # the last: outside the frame
    alone = estimate_light(frame.image, good)
    mixed = estimate_light(frame.image, [*bad[:3], *good, *bad[3:]])
    assert mixed.level == alone.level and mixed.markers == alone.markers == len(good)
    nothing = estimate_light(frame.image, bad)
    assert nothing.source is not LightSource.MARKERS and nothing.markers == 0
    assert nothing.level == estimate_light(frame.image).level
