"""Calibration that follows the site (issue 29): each configuration on its own dictionary's markers,
the site's ids and sizes, and calibration on recorded frames labelled by the configurations' agreement.

The recorded frames are the real photographs (sim/photographs, DICT_6X6_250
markers) taken by the camera model at dark, dusk and day light and written as
JPEG files, as a robot's recording would be.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import replace

import cv2
import numpy as np
import pytest

from kgadapt.bench.perception_quality import shipped_configs
from kgadapt.onboard.flight.site import SiteMarkers
from kgadapt.onboard.perception.calibration import CalibrationSettings, best_per_band, calibrate, render_test_frames
from kgadapt.onboard.perception.illumination import Band
from kgadapt.onboard.perception.ranking import TIE_RATE
from kgadapt.onboard.perception.recorded_calibration import label_and_score, read_frames
from kgadapt.shared.errors import ConfigError
from kgadapt.shared.resources import models
from kgadapt.sim.photos import PHOTO_DICTIONARIES, load_photo, photo_frames, photo_truth
from tests.conftest import REPO

BANDS = [Band("dark", 0.0, 12.0), Band("dusk", 12.0, 45.0), Band("day", 45.0, 256.0)]
SMALL = CalibrationSettings(frames_per_level=2, levels_per_band=2)
PHOTOS = [n for n, d in PHOTO_DICTIONARIES.items() if d == "DICT_6X6_250"]


@pytest.mark.parametrize("dictionary", ["DICT_6X6_250", "DICT_ARUCO_MIP_36h12"])
def test_a_configuration_naming_another_dictionary_calibrates_on_its_markers(dictionary):
    configs = [replace(c, dictionary=dictionary) for c in shipped_configs()]
    results = calibrate(configs, BANDS, replace(SMALL, conditions=("clean", "small")))
    by = {(r.config, r.band): r.detection_rate for r in results if r.condition == "all"}
    assert all(rate > 0 for (config, band), rate in by.items() if band != "dark"), by
    # Not flat: in the dark the dark configuration finds far more than the day one, and is ranked first.
    assert by[("marker_detection_dark", "dark")] - by[("marker_detection_day", "dark")] > 0.3, by
    assert best_per_band(results)["dark"] == "marker_detection_dark"


def test_configurations_of_different_dictionaries_are_each_shown_their_own_markers():
    day = next(c for c in shipped_configs() if c.name == "marker_detection_day")
    configs = [replace(day, name=d, dictionary=d) for d in ("DICT_4X4_50", "DICT_5X5_1000", "DICT_6X6_250")]
    results = calibrate(configs, [BANDS[2]], replace(SMALL, conditions=("clean",)))
    assert {r.config: r.detection_rate for r in results if r.condition == "clean"} == {
        "DICT_4X4_50": 1.0, "DICT_5X5_1000": 1.0, "DICT_6X6_250": 1.0}


def test_the_calibration_scene_shows_the_site_ids_at_their_relative_sizes():
    site = SiteMarkers(site="hall", dictionary="DICT_5X5_1000", sizes_m={500: 0.4, 610: 0.2, 777: 0.2, 999: 0.2})
    frames = render_test_frames([BANDS[2]], replace(SMALL, conditions=("clean",)), dictionary="DICT_5X5_1000",
                                site=site)
    _level, _gray, truth, _hidden = frames[("day", "clean")][0]
    assert sorted(t.id for t in truth) == [500, 610, 777, 999]
    side = {t.id: float(np.linalg.norm(np.subtract(t.corners[0], t.corners[1]))) for t in truth}
    assert side[500] > 1.5 * min(side[610], side[777], side[999])  # twice the print, about twice the side
    # A site of another dictionary leaves this dictionary's scene alone; ids the dictionary lacks are refused.
    other = render_test_frames([BANDS[2]], replace(SMALL, conditions=("clean",)), dictionary="DICT_4X4_50",
                               site=site)[("day", "clean")][0][2]
    assert all(t.id < 50 for t in other)
    with pytest.raises(ConfigError, match="none of the site's ids"):
        render_test_frames([BANDS[2]], replace(SMALL, conditions=("clean",)), dictionary="DICT_4X4_50",
                           site=replace(site, dictionary="DICT_4X4_50"))


def _corner_shade(scene_settings, outward_px=2.0, *, sides=False, outward_of_side=0.0):
    """The reflectance just beyond each marker's corners, along its diagonal (a touching neighbour is dark there);
    ``sides``: beyond the middle of each side instead, ``outward_of_side`` x the side further out."""
    from kgadapt.onboard.perception.scene import SyntheticScene

    image, truth = SyntheticScene(scene_settings).reflectance(0.0)
    shades = []
    for marker in truth:
        corners = np.float32(marker.corners)
        centre = corners.mean(axis=0)
        points = (corners + np.roll(corners, -1, axis=0)) / 2 if sides else corners
        side = float(np.linalg.norm(corners[0] - corners[1]))
        for point in points:
            away = (point - centre) / np.linalg.norm(point - centre)
            x, y = np.round(point + away * (outward_px + outward_of_side * side)).astype(int)
            shades.append(float(image[y, x]))
    return shades


def test_a_site_whose_markers_touch_is_drawn_so_and_ranks_the_configurations_as_such_a_board_does():
    # The markers of a ChArUco2 board (a marker in every square) touch at the corners: the day
    # configuration misses many of them, the dark one (CLAHE, wider windows) does not. Drawn apart, as
    # before the site could say so, the day configuration finds as many.
    from kgadapt.onboard.perception.scene import SceneSettings

    ids = {i: 0.022 for i in range(1, 46, 2)}
    touching = SiteMarkers(site="board", dictionary="DICT_ARUCO_MIP_36h12", sizes_m=ids, layout="touching")
    apart = replace(touching, layout="apart")
    settings = replace(SMALL, conditions=("clean", "small"))
    frames = render_test_frames([BANDS[2]], settings, dictionary="DICT_ARUCO_MIP_36h12", site=touching)
    _level, _gray, truth, _hidden = frames[("day", "clean")][0]
    assert {t.id for t in truth} <= set(ids) and len(truth) >= 4
    # Drawn touching: just beyond every corner of every marker lies the black border of its diagonal neighbour.
    drawn = _corner_shade(SceneSettings(dictionary="DICT_ARUCO_MIP_36h12", print_layout="touching"))
    alone = _corner_shade(SceneSettings(dictionary="DICT_ARUCO_MIP_36h12"))
    assert max(drawn) < 0.3 < min(alone), (drawn, alone)
    # On a ChArUco board (chessboard): beyond each side's white margin, the black square next to it.
    beside = _corner_shade(SceneSettings(dictionary="DICT_ARUCO_MIP_36h12", print_layout="chessboard"),
                           sides=True, outward_of_side=0.32)
    margin_only = _corner_shade(SceneSettings(dictionary="DICT_ARUCO_MIP_36h12"), sides=True, outward_of_side=0.32)
    assert max(beside) < 0.3 < min(margin_only), (beside, margin_only)
    configs = [replace(c, dictionary="DICT_ARUCO_MIP_36h12") for c in shipped_configs()]
    on_board = calibrate(configs, [BANDS[2]], settings, site=touching)
    by = {r.config: r.detection_rate for r in on_board if r.condition == "all"}
    assert by["marker_detection_dark"] - by["marker_detection_day"] > 0.05, by
    assert best_per_band(on_board)["day"] == "marker_detection_dark"
    # Drawn apart, the dark configuration finds no more than the day one: which wins the tie is then
    # speed beyond timing noise, which a loaded machine decides (CI once ranked the dark one first there).
    by_apart = {r.config: r.detection_rate for r in calibrate(configs, [BANDS[2]], settings, site=apart)
                if r.condition == "all"}
    assert by_apart["marker_detection_dark"] - by_apart["marker_detection_day"] <= TIE_RATE, by_apart


def _recording(folder, levels=(6.0, 25.0, None), count=2):
    """The photographs of DICT_6X6_250 markers at dark, dusk and their own light, as JPEG frames."""
    folder.mkdir()
    k = 0
    for name in PHOTOS:
        photo = load_photo(name)
        for level in levels:
            for frame in photo_frames(photo, level, count=count, seed=k):
                cv2.imwrite(str(folder / f"{k:04d}.jpg"), frame.image, [cv2.IMWRITE_JPEG_QUALITY, 85])
                k += 1
    return folder


def test_recorded_frames_are_labelled_by_agreement_as_the_photographs_truth_says(tmp_path):
    folder = _recording(tmp_path / "rec")
    configs = [replace(c, dictionary="DICT_6X6_250") for c in shipped_configs()]
    results, labels = label_and_score(configs, read_frames(folder), BANDS)
    truth = set()
    for name in PHOTOS:
        truth |= {t["id"] for t in photo_truth(load_photo(name), "DICT_6X6_250")}
    assert set(labels.real["DICT_6X6_250"]) == truth  # every real marker, and nothing else
    assert labels.frames_per_band == {"dark": 12, "dusk": 12, "day": 12}
    by = {(r.config, r.band): r for r in results}
    assert by[("marker_detection_dark", "dark")].detection_rate > 0.8
    assert by[("marker_detection_day", "dark")].detection_rate < 0.3  # the day configuration is blind in the dark
    assert by[("marker_detection_day", "day")].detection_rate > 0.95
    assert all(r.false_per_frame == 0 for r in results)


def test_a_phantom_two_configurations_agree_on_is_not_taken_for_a_marker(tmp_path):
    # Read with DICT_4X4_50, the photograph of six DICT_6X6_250 markers gives id 17 to both the day and
    # the dusk configuration, at the same place: its cells do not read clean, so it is not agreed on.
    folder = _recording(tmp_path / "rec", levels=(None,), count=1)
    results, labels = label_and_score(shipped_configs(), read_frames(folder), BANDS)
    assert 17 in labels.rejected.get("DICT_4X4_50", []) and not labels.real
    by = {r.config: r for r in results}
    assert by["marker_detection_day"].markers == 0 and by["marker_detection_day"].false_per_frame > 0


def test_a_missing_or_empty_recording_is_refused_by_name(tmp_path):
    with pytest.raises(ConfigError, match="nowhere"):
        list(read_frames(tmp_path / "nowhere"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match="no images"):
        list(read_frames(tmp_path / "empty"))
    (tmp_path / "video.mp4").write_bytes(b"not a video")
    with pytest.raises(ConfigError, match="video.mp4"):
        list(read_frames(tmp_path / "video.mp4"))


def test_calibrate_from_frames_records_the_figures_beside_the_synthetic_ones(tmp_path, kgadapt_cmd):
    # The shipped models, for a site whose markers are DICT_6X6_250.
    shutil.copytree(models(), tmp_path / "models")
    for path in (tmp_path / "models" / "perception").glob("*.rpsl"):
        path.write_text(path.read_text().replace('"DICT_4X4_50"', '"DICT_6X6_250"'))
    store = f"embedded:{tmp_path}/store"
    folder = _recording(tmp_path / "flight-7")

    def run(*args):
        done = subprocess.run([*kgadapt_cmd, *args], cwd=REPO, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        return done

    run("knowledge", "load", "--store", store, str(tmp_path / "models"))
    run("perception", "calibrate", "--store", store, "--frames", "1", "--levels", "1", "--conditions", "clean",
        "--out", str(tmp_path / "cal.json"), "--plot", "")
    done = run("perception", "calibrate", "--store", store, "--frames-from", str(folder),
               "--out", str(tmp_path / "frames.json"))
    assert "recorded 9 CALIBRATED relations (source frames:flight-7)" in done.stdout
    data = json.loads((tmp_path / "frames.json").read_text())
    assert data["source"] == "frames:flight-7" and len(data["labels"]["real"]["DICT_6X6_250"]) == 23
    synthetic = json.loads(run("knowledge", "query", "--store", store, "config_ranking", "--param", "band=dark",
                               "--json").stdout)
    recorded = json.loads(run("knowledge", "query", "--store", store, "config_ranking", "--param", "band=dark",
                              "--param", "source=frames:flight-7", "--json").stdout)
    assert len(synthetic) == len(recorded) == 3
    rates = {r["config"]: r["detection_rate"] for r in recorded}
    assert rates == {r["config"]: r["detection_rate"] for r in data["results"] if r["band"] == "dark"}
    assert rates["marker_detection_day"] < 0.3 < rates["marker_detection_dark"]
    # The synthetic figures are still there, and were not overwritten by the recording's.
    assert {r["config"]: r["detection_rate"] for r in synthetic} != rates


def test_on_the_real_touching_board_the_day_pick_of_a_calibration_with_its_site_is_the_best():
    # The photograph (rmsalinas/charuco2 board_image.jpg, sim/photographs/SOURCES.txt) is awaited, not shipped.
    from kgadapt.onboard.flight.site import load_site
    from kgadapt.onboard.perception.markers import MarkerDetector, Score, score
    from kgadapt.sim.photos import PHOTO_DIR, shifted

    name = "charuco2_board_image.jpg"
    if not (PHOTO_DIR / name).is_file():
        pytest.skip(f"{name} is not placed in sim/photographs yet (SOURCES.txt names its source)")
    site = load_site(PHOTO_DIR / "charuco2_board.site")
    configs = [replace(c, dictionary=site.dictionary) for c in shipped_configs()]
    pick = best_per_band(calibrate(configs, [BANDS[2]], replace(SMALL, conditions=("clean", "small")), site=site))["day"]
    photo = load_photo(name)
    truth = photo_truth(photo, site.dictionary)
    scores = {c.name: Score() for c in configs}
    detectors = {c.name: MarkerDetector(c) for c in configs}
    for level in (60.0, 140.0):
        for frame in photo_frames(photo, level, count=2, seed=3):
            _ok, jpeg = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, 80])  # as on the wire
            image = cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE)
            for n, detector in detectors.items():
                found = detector.detect(image)
                scores[n].add(score(found.ids, found.corners, shifted(truth, frame.shift)))
    rates = {n: s.detection_rate for n, s in scores.items()}
    assert max(rates.values()) - rates[pick] <= 0.05, (pick, rates)
