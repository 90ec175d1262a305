"""Luminance figures, smoothing, and the mapping of a level to a band of the knowledge graph."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kgadapt.onboard.perception.illumination import Smoother, band_for_level, bands_from_rows, luminance
from kgadapt.shared.errors import ConfigError

# Rows as the named query detector_configs gives them (bands of the shipped models).
ROWS = [
    {"config": "marker_detection_dark", "band": "dark", "min_level": 0, "max_level": 12},
    {"config": "marker_detection_dusk", "band": "dusk", "min_level": 12, "max_level": 40},
    {"config": "marker_detection_day", "band": "day", "min_level": 40, "max_level": 255},
    {"config": "marker_detection_day_subpix", "band": "day", "min_level": 40, "max_level": 255},
    {"config": "marker_detection_hd", "band": None, "min_level": None, "max_level": None},
]


def test_luminance_of_a_half_dark_half_bright_frame():
    image = np.zeros((480, 640), np.uint8)
    image[:, 320:] = 200
    figures = luminance(image)
    assert figures.mean == pytest.approx(100, abs=0.5)
    assert figures.p5 == 0 and figures.p95 == 200


def test_luminance_percentiles_are_not_moved_by_a_few_hot_pixels():
    rng = np.random.default_rng(1)
    image = np.clip(rng.normal(60, 5, (480, 640)), 0, 255).astype(np.uint8)
    before = luminance(image)
    image[::40, ::40] = 255  # hot pixels and specular glints
    after = luminance(image)
    # 1 % of the pixels at full scale move the mean by about 2 levels; the percentiles by at most 1.
    assert after.mean - before.mean > 1.5
    assert after.p5 == before.p5
    assert abs(after.p50 - before.p50) <= 1 and abs(after.p95 - before.p95) <= 1


def test_luminance_refuses_a_colour_image():
    with pytest.raises(ConfigError, match="grey uint8"):
        luminance(np.zeros((4, 4, 3), np.uint8))


def test_the_smoother_covers_63_percent_of_a_step_in_one_time_constant_at_any_frame_rate():
    for fps in (10, 30, 120):
        smoother = Smoother(tau_s=0.5)
        smoother.update(0.0, 0.0)
        value = 0.0
        for i in range(1, int(0.5 * fps) + 1):
            value = smoother.update(100.0, i / fps)
        assert value == pytest.approx(100 * (1 - math.exp(-1)), abs=0.5)


@pytest.mark.parametrize(
    "level, band",
    [(0, "dark"), (11.9, "dark"), (12, "dusk"), (39.9, "dusk"), (40, "day"), (255, "day"), (300, "day"), (-3, "dark")],
)
def test_a_level_maps_to_the_band_whose_range_holds_it(level, band):
    assert band_for_level(level, ROWS) == band


def test_hysteresis_keeps_the_current_band_near_its_edge():
    assert band_for_level(13, ROWS, current="dark", hysteresis=2) == "dark"
    assert band_for_level(14.5, ROWS, current="dark", hysteresis=2) == "dusk"
    assert band_for_level(13, ROWS) == "dusk"


def test_a_level_in_a_gap_between_bands_goes_to_the_nearer_band():
    rows = [{"band": "low", "min_level": 0, "max_level": 10}, {"band": "high", "min_level": 50, "max_level": 255}]
    assert band_for_level(20, rows) == "low"
    assert band_for_level(45, rows) == "high"


def test_bands_are_distinct_and_ordered_from_dark_to_bright():
    assert [b.name for b in bands_from_rows(reversed(ROWS))] == ["dark", "dusk", "day"]


def test_a_band_with_conflicting_or_missing_limits_is_refused_by_name():
    with pytest.raises(ConfigError, match="'day'.*different limits"):
        bands_from_rows(ROWS + [{"band": "day", "min_level": 50, "max_level": 255}])
    with pytest.raises(ConfigError, match="'odd'.*bad limits"):
        bands_from_rows([{"band": "odd", "min_level": 10, "max_level": None}])
    with pytest.raises(ConfigError, match="no illumination bands"):
        band_for_level(10, [{"config": "x", "band": None}])
