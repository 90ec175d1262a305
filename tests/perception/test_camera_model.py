"""The realistic camera model and the scenario format that describes it (issue 11)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from kgadapt.onboard.perception.scene import (
    CameraModel,
    IlluminationProfile,
    LightLayout,
    Response,
    SceneOptions,
    SceneSettings,
    SyntheticScene,
    load_profile,
    srgb_decode,
    srgb_encode,
)
from kgadapt.shared.errors import ModelError


def test_srgb_round_trips_and_lifts_the_shadows():
    linear = np.linspace(0, 1, 1001, dtype=np.float32)
    encoded = srgb_encode(linear)
    assert encoded[0] == 0 and encoded[-1] == 255
    assert np.abs(srgb_decode(encoded) - linear).max() < 0.01
    assert srgb_encode(np.float32([0.18]))[0] == 118  # mid-grey encodes near the middle, unlike a linear camera


def test_frames_are_gamma_encoded_at_the_asked_mean_with_signal_dependent_noise():
    scene = SyntheticScene(SceneSettings(markers=(), distractors=0))
    flat = np.full((480, 640), 0.5, np.float32)
    rng = np.random.default_rng(0)
    dark = scene.expose(flat, 6, IlluminationProfile.constant(6, gradient=0.0), rng=rng)
    bright = scene.expose(flat, 120, IlluminationProfile.constant(120, gradient=0.0), rng=rng)
    assert dark.dtype == np.uint8 and abs(dark.mean() - 6) < 0.5 and abs(bright.mean() - 120) < 1.0
    # Poisson-Gaussian noise: in linear light the variance grows with the signal.
    lin_dark, lin_bright = srgb_decode(dark), srgb_decode(bright)
    assert lin_bright.var() > 5 * lin_dark.var()
    # 8-bit quantisation: a dark frame has only a handful of distinct grey levels.
    assert len(np.unique(dark)) < 40


def test_the_linear_camera_is_still_available():
    scene = SyntheticScene(SceneSettings())
    profile = IlluminationProfile.constant(20, camera=CameraModel(response=Response.LINEAR))
    assert abs(scene.render(0.0, profile).image.mean() - 20) < 1.0


def test_motion_blur_softens_edges():
    scene = SyntheticScene(SceneSettings())
    quiet = CameraModel(full_well=1e6, read_noise=0)  # little noise, so the edges dominate the gradient
    sharp = scene.render(0.0, IlluminationProfile.constant(120, camera=quiet), np.random.default_rng(1)).image
    blurred = scene.render(0.0, IlluminationProfile.constant(120, camera=CameraModel(full_well=1e6, read_noise=0,
                                                                                      blur_px=7)),
                           np.random.default_rng(1)).image
    grad = lambda im: np.percentile(np.abs(np.diff(im.astype(np.float32), axis=1)), 99.5)  # edges  # noqa: E731
    assert grad(blurred) < 0.7 * grad(sharp)


def test_a_window_saturates_and_hides_the_markers_behind_it():
    scene = SyntheticScene(SceneSettings())
    frame = scene.render(0.0, IlluminationProfile.constant(6, light=LightLayout(window=0.15)))
    assert (frame.image[:70] == 255).mean() > 0.99
    assert abs(frame.image[80:].mean() - 6) < 2
    assert all(min(y for _x, y in m.corners) > 72 for m in frame.truth)


def test_small_markers_and_printed_distractors_are_rendered():
    small = SyntheticScene(SceneSettings(marker_scale=0.3))
    frame = small.render(0.0, IlluminationProfile.constant(100))
    sides = [np.linalg.norm(np.subtract(m.corners[0], m.corners[1])) for m in frame.truth]
    assert min(sides) < 6 * 5  # under 5 px per cell (a 4x4 marker is 6 cells across)
    plain = SyntheticScene(SceneSettings(markers=())).render(0.0, IlluminationProfile.constant(100)).image
    busy = SyntheticScene(SceneSettings(markers=(), other_dict=2, charuco=1, texture=1)).render(
        0.0, IlluminationProfile.constant(100)).image
    assert np.abs(np.diff(busy.astype(np.float32))).mean() > 1.5 * np.abs(np.diff(plain.astype(np.float32))).mean()


def test_the_scenario_format_describes_camera_light_and_scene(tmp_path):
    path = tmp_path / "hard.json"
    path.write_text(json.dumps({
        "points": [[0, 6], [10, 6]],
        "camera": {"response": "srgb", "full_well": 4000, "read_noise": 2.5, "blur_px": 7, "blur_angle": 30},
        "light": {"window": 0.15, "stripes": 6, "stripe_depth": 0.5, "spot": [0.5, 0.5, 0.2], "spot_gain": 4},
        "scene": {"marker_scale": 0.5, "other_dict": 2, "charuco": 1, "texture": 1, "markers": True},
    }))
    profile = load_profile(path)
    assert profile.camera == CameraModel(full_well=4000, read_noise=2.5, blur_px=7, blur_angle=30)
    assert profile.light.window == 0.15 and profile.light.spot == (0.5, 0.5, 0.2)
    assert profile.scene == SceneOptions(marker_scale=0.5, other_dict=2, charuco=1, texture=1)
    scene = SyntheticScene(SceneSettings().with_options(profile.scene))
    assert scene.render(1.0, profile).image.shape == (480, 640)


@pytest.mark.parametrize("group, words", [
    ({"camera": {"response": "log"}}, "response must be srgb or linear"),
    ({"camera": {"exposure": 3}}, "'camera' has no 'exposure'"),
    ({"light": {"window": 0.9}}, "window 0.9"),
    ({"scene": {"charuco": "yes"}}, "scene.charuco must be an integer"),
    ({"light": {"spot": [0.5, 0.5]}}, "light.spot must be"),
])
def test_bad_camera_light_or_scene_objects_name_the_file_line_and_key(tmp_path, group, words):
    path = tmp_path / "bad.json"
    path.write_text('{"points": [[0, 6]],\n' + json.dumps(group)[1:])
    with pytest.raises(ModelError, match=words) as info:
        load_profile(path)
    assert "bad.json:2" in str(info.value)


def test_events_change_camera_light_and_marker_size_for_a_while(tmp_path):
    path = tmp_path / "events.json"
    path.write_text(json.dumps({
        "points": [[0, 100], [20, 100]],
        "events": [{"from": 5, "to": 10, "camera": {"blur_px": 9}, "marker_scale": 0.4},
                   {"from": 12, "to": 14, "light": {"window": 0.2}}],
    }))
    profile = load_profile(path)
    assert profile.at(1.0) is profile and profile.at(6.0).camera.blur_px == 9 and profile.at(13.0).light.window == 0.2
    scene = SyntheticScene(SceneSettings())
    before, during = scene.render(1.0, profile), scene.render(6.0, profile)
    side = lambda f: max(np.linalg.norm(np.subtract(m.corners[0], m.corners[1])) for m in f.truth)  # noqa: E731
    assert side(during) < 0.5 * side(before)
    assert (scene.render(13.0, profile).image[:90] == 255).mean() > 0.99
    path.write_text(json.dumps({"points": [[0, 1]], "events": [{"from": 5, "to": 2}]}))
    with pytest.raises(ModelError, match=r"events\[0\].*from < to"):
        load_profile(path)
