"""Illumination profiles: parsing, interpolation, flicker, and errors that name file and line."""

from __future__ import annotations

import numpy as np
import pytest

from kgadapt.onboard.perception.scene import (
    DEMO_PROFILE,
    IlluminationProfile,
    load_profile,
    parse_profile_csv,
    parse_profile_json,
)
from kgadapt.shared.errors import ModelError


def test_a_bare_json_list_is_interpolated_linearly_between_points():
    profile = parse_profile_json("[[0, 100], [10, 20], [20, 20]]")
    assert profile.level_at(0) == 100
    assert profile.level_at(5) == pytest.approx(60)
    assert profile.level_at(15) == 20
    assert profile.duration == 20


def test_a_looped_profile_starts_over_and_an_unlooped_one_holds_its_last_level():
    looped = parse_profile_json('{"points": [[0, 0], [10, 100]], "loop": true}')
    held = parse_profile_json('{"points": [[0, 0], [10, 100]], "loop": false}')
    assert looped.level_at(15) == pytest.approx(50)
    assert held.level_at(15) == 100


def test_flicker_depth_is_interpolated_and_shows_as_row_bands():
    profile = parse_profile_json('{"points": [[0, 50, 0.0, 10], [10, 50, 0.4, 10]], "readout_s": 0.05}')
    assert profile.flicker_at(5) == (pytest.approx(0.2), 10)
    assert profile.flicker_at(5.025)[0] == pytest.approx(0.201)
    rows = profile.row_gains(5.025, 480)  # a quarter cycle on: the readout sweeps peak to trough
    assert rows is not None and rows.shape == (480,)
    assert rows.max() > 1.1 and rows.min() < 0.9
    assert parse_profile_json("[[0, 50]]").row_gains(1.0, 480) is None


def test_the_demo_profile_goes_day_dusk_dark_flicker_day_in_about_a_minute():
    profile = load_profile(DEMO_PROFILE)
    assert 50 <= profile.duration <= 70
    levels = [profile.level_at(t) for t in (5, 18, 30, 45, 57)]
    day, dusk, dark, flicker, day_again = levels
    assert day > 40 and day_again > 40 and 12 <= dusk < 40 and dark < 12
    assert profile.flicker_at(45)[0] > 0.3 and profile.flicker_at(5)[0] == 0


def test_a_csv_profile_with_header_and_comments_parses():
    text = "# a ramp\nt,level,flicker_depth,flicker_hz\n0,10\n\n5,60,0.2,7\n"
    profile = parse_profile_csv(text, source="ramp.csv")
    assert [p.level for p in profile.points] == [10, 60]
    assert profile.points[1].flicker_hz == 7


@pytest.mark.parametrize(
    "text, line, words",
    [
        ('[\n  [0, 10],\n  [5, 20],\n  [5, 30]\n]', 4, "must increase"),
        ('[\n  [0, 10],\n  [5, 300]\n]', 3, "outside 0..255"),
        ('{"points": [\n  [0, 10],\n  [1, "bright"]\n]}', 3, "a point is"),
        ('{"points": [[0, 10]],\n "sparkle": 1}', 2, "unknown profile key 'sparkle'"),
        ('{"points": [[0, 10]],\n "noise": -1}', 2, "'noise' must be"),
        ('[\n  [0, 10],\n  [5, 20, 1.5, 7]\n]', 3, "flicker depth"),
        ('[\n  [0, 10]\n  [5, 20]\n]', 3, "not valid JSON"),
        ("[]", 1, "no points"),
    ],
)
def test_json_profile_errors_name_the_file_and_line(tmp_path, text, line, words):
    path = tmp_path / "light.json"
    path.write_text(text)
    with pytest.raises(ModelError) as caught:
        load_profile(path)
    assert caught.value.path == str(path) and caught.value.line == line
    assert words in str(caught.value)
    assert str(caught.value).startswith(f"{path}:{line}: ")


@pytest.mark.parametrize(
    "text, line, words",
    [
        ("t,level\n0,10\n4,dim\n", 3, "'dim' is not a number"),
        ("0,10\n# pause\n2,20\n1,30\n", 4, "must increase"),
        ("0,10,0.1,7,99\n", 1, "a point is"),
    ],
)
def test_csv_profile_errors_name_the_file_and_line(tmp_path, text, line, words):
    path = tmp_path / "light.csv"
    path.write_text(text)
    with pytest.raises(ModelError) as caught:
        load_profile(path)
    assert (caught.value.path, caught.value.line) == (str(path), line)
    assert words in str(caught.value)


def test_a_missing_profile_file_is_named(tmp_path):
    with pytest.raises(ModelError, match="nowhere.json"):
        load_profile(tmp_path / "nowhere.json")


def test_a_constant_profile_renders_frames_whose_mean_is_the_level():
    from kgadapt.onboard.perception.scene import SyntheticScene

    scene = SyntheticScene()
    for level in (5.0, 30.0, 150.0):
        frame = scene.render(1.0, IlluminationProfile.constant(level), np.random.default_rng(0))
        assert frame.image.shape == (480, 640)
        assert frame.image.mean() == pytest.approx(level, rel=0.08, abs=0.6)
