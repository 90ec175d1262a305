"""A site's own ArUco dictionary in OpenCV's YAML file format, named in a perception model (issue 29).

The file is the OpenCV tutorials' 35-marker 6x6 dictionary (sim/photographs,
SOURCES.txt); two real photographs hold markers printed from it.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from kgadapt.knowledge.importers import rpsl
from kgadapt.onboard.perception.calibration import model_configs
from kgadapt.onboard.perception.markers import MarkerDetector, aruco_dictionary, parse_config
from kgadapt.shared.errors import ConfigError, ModelError
from kgadapt.sim.photos import PHOTO_DIR, load_photo

DICT_FILE = PHOTO_DIR / "contrib_tutorial_dict.yml"

MODEL = '''# a site printing its own markers
rpsl.processing_component do
  name "aruco_site"
  add_port :in, "in_port", "rgb_image"
  add_port :out, "out_port", "marker"
  dictionary "{dictionary}"
end

rpsl.perception_graph do
  name "marker_detection_site"
  realizes "MarkerDetection"
  suited_for :day
  connect "camera", "out_port", "aruco_site", "in_port"
end
'''


def _model(folder, dictionary="site_dict.yml"):
    path = folder / "marker_detection_site.rpsl"
    path.write_text(MODEL.format(dictionary=dictionary))
    return path


def test_a_custom_dictionary_file_reads_as_opencv_reads_it():
    import cv2

    ours = aruco_dictionary(str(DICT_FILE))
    theirs = cv2.aruco.Dictionary()
    storage = cv2.FileStorage(str(DICT_FILE), cv2.FILE_STORAGE_READ)
    assert theirs.readDictionary(storage.root())
    assert ours.markerSize == 6 and np.array_equal(ours.bytesList, theirs.bytesList)
    assert ours.maxCorrectionBits > 0  # the file says none: what its markers allow, as for OpenCV's own
    assert aruco_dictionary("DICT_6X6_250").markerSize == 6  # the old names resolve as before


def test_a_model_naming_a_dictionary_file_beside_it_loads_and_detects_the_markers_printed_from_it(tmp_path):
    shutil.copy(DICT_FILE, tmp_path / "site_dict.yml")
    model = rpsl.parse(_model(tmp_path).read_text(), str(tmp_path / "marker_detection_site.rpsl"))
    component = next(n for n in model.nodes if n.name == "aruco_site")
    assert component.props["dictionary"] == str((tmp_path / "site_dict.yml").resolve())
    configs = model_configs(tmp_path)
    assert [c.name for c in configs] == ["marker_detection_site"]
    detector = MarkerDetector(configs[0])
    # The ChArUco-style board photographed from the tutorial: 35 markers of the custom dictionary.
    found = detector.detect(load_photo("contrib_gboriginal.png"))
    assert sorted(found.ids) == list(range(35))
    # With a predefined 6x6 dictionary instead, none of them is read.
    assert MarkerDetector(parse_config("other", {"dictionary": "DICT_6X6_250"})).detect(
        load_photo("contrib_gboriginal.png")).ids == []


def test_a_missing_dictionary_file_is_refused_naming_the_model_file_and_line(tmp_path):
    path = _model(tmp_path, "site_dcit.yml")  # misspelt
    with pytest.raises(ModelError) as caught:
        rpsl.parse(path.read_text(), str(path))
    assert caught.value.path == str(path) and caught.value.line == 6
    assert "site_dcit.yml" in str(caught.value) and "not found" in str(caught.value)


def test_a_dictionary_file_with_markers_of_the_wrong_size_is_refused_naming_both_files(tmp_path):
    text = DICT_FILE.read_text().replace("markersize: 6", "markersize: 5")
    (tmp_path / "site_dict.yml").write_text(text)
    path = _model(tmp_path)
    with pytest.raises(ModelError) as caught:
        rpsl.parse(path.read_text(), str(path))
    assert caught.value.path == str(path) and caught.value.line == 6
    assert "site_dict.yml" in str(caught.value) and "marker_0 has 36 characters" in str(caught.value)


def test_an_unparsable_dictionary_file_is_refused(tmp_path):
    (tmp_path / "site_dict.yml").write_text('%YAML:1.0\nnmarkers: 2\nmarkersize: 6\nmarker_0: "1010\n')
    path = _model(tmp_path)
    with pytest.raises(ModelError) as caught:
        rpsl.parse(path.read_text(), str(path))
    assert caught.value.line == 6 and "not OpenCV's YAML format" in str(caught.value)
    with pytest.raises(ConfigError, match="site_dict.yml"):
        aruco_dictionary(str(tmp_path / "site_dict.yml"))


def test_a_misspelt_dictionary_name_is_refused_naming_the_line(tmp_path):
    path = _model(tmp_path, "DICT_6X6_205")
    with pytest.raises(ModelError) as caught:
        rpsl.parse(path.read_text(), str(path))
    assert caught.value.line == 6 and "DICT_6X6_205" in str(caught.value)


def test_a_site_naming_a_dictionary_file_beside_it_matches_the_models_configuration_from_any_directory(
        tmp_path, monkeypatch):
    # The site keeps the file's absolute path, as the models keep their configurations' (rpsl above), so
    # calibrate --site finds the site's ids for that configuration wherever it is run from.
    from kgadapt.onboard.flight.site import load_site
    from kgadapt.onboard.perception.calibration import CalibrationSettings, render_test_frames
    from kgadapt.onboard.perception.illumination import Band

    shutil.copy(DICT_FILE, tmp_path / "site_dict.yml")
    model = rpsl.parse(_model(tmp_path).read_text(), str(tmp_path / "marker_detection_site.rpsl"))
    configured = next(n for n in model.nodes if n.name == "aruco_site").props["dictionary"]
    (tmp_path / "hall.site").write_text(
        '{"site": "hall", "dictionary": "site_dict.yml", "markers": [{"id": 3, "size_m": 0.2}, {"id": 9, "size_m": 0.2}]}')
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    site = load_site(tmp_path / "hall.site")
    assert site.dictionary == configured == str((tmp_path / "site_dict.yml").resolve())
    frames = render_test_frames([Band("day", 120.0, 160.0)],
                                CalibrationSettings(frames_per_level=1, levels_per_band=1, conditions=("clean",)),
                                dictionary=configured, site=site)
    (_, _, truth, _), = frames[("day", "clean")]
    assert sorted(t.id for t in truth) == [3, 9]  # the site's markers, not the scene's own ids
