"""What used to fail only when a detector or deployment started is refused at load time, with FILE:LINE.

Each case was a real start-time failure (issue 15): a dictionary name OpenCV does
not have, detector parameters OpenCV asserts against, a module or executable that
is not there, a ``kgadapt`` command line its own parser refuses.
"""

from __future__ import annotations

import re

import pytest

from kgadapt.knowledge.importers import deployment_file, rpsl, systemd
from kgadapt.shared.errors import ModelError

_DETECTOR = '''
rpsl.processing_component do
  name "aruco_x"
  add_port :in, "in_port", "rgb_image"
  dictionary "{dictionary}"
{parameters}
end
'''


def _detector(dictionary: str = "DICT_4X4_50", **parameters: object) -> str:
    lines = "\n".join(f'  parameter "{k}", {v}' for k, v in parameters.items())
    return _DETECTOR.format(dictionary=dictionary, parameters=lines)


def test_a_good_detector_loads_with_its_config_json():
    node = rpsl.parse(_detector(adaptiveThreshConstant=7), "d.rpsl").nodes[0]
    assert '"DICT_4X4_50"' in node.props["config_json"]


@pytest.mark.parametrize("name", ["DICT_4X4_5O", "DICT_4X4_51", "DICT_5X5"])
def test_a_dictionary_opencv_does_not_have_is_refused_on_its_line(name):
    with pytest.raises(ModelError, match=rf"d\.rpsl:5: dictionary '{name}' is not one of OpenCV's ArUco dictionaries"):
        rpsl.parse(_detector(name), "d.rpsl")


@pytest.mark.parametrize("key, value, why", [
    ("adaptiveThreshWinSizeMin", 2, r"adaptiveThreshWinSizeMin >= 3"),
    ("adaptiveThreshWinSizeStep", 0, r"adaptiveThreshWinSizeStep > 0"),
    ("markerBorderBits", 0, r"markerBorderBits > 0"),
    ("cornerRefinementMethod", 9, r"cornerRefinementMethod = 9 is outside \[0, 3\]"),
    ("adaptiveThreshConstant", "true", r"must be a number|must be float"),
])
def test_detector_parameters_opencv_refuses_fail_at_load_naming_the_file(key, value, why):
    with pytest.raises(ModelError, match=r"d\.rpsl:\d+: .*" + why):
        rpsl.parse(_detector(**{key: value}), "d.rpsl")


def _deploy(executable: str, arguments: str) -> str:
    return f"deploys: g\nexecutable: {executable}\narguments: {arguments}\nexecutable_on: onboard\n"


def test_a_deployment_of_a_module_python_can_find_loads():
    model = deployment_file.parse(_deploy("{python}", "-m kgadapt.onboard.perception.detector --config {config}"), "x.deploy")
    assert model.nodes[0].props["arguments"][:2] == ["-m", "kgadapt.onboard.perception.detector"]


@pytest.mark.parametrize("executable, arguments, line, why", [
    ("{python}", "-m onboard.detektor --config {config}", 3, r"module 'onboard.detektor' .* cannot be found"),
    ("{python}", "-m json", 3, r"module 'json' .* cannot be found"),  # a package without __main__
    ("/usr/bin/no-such-detector", "--config {config}", 3, r"executable '/usr/bin/no-such-detector' does not exist"),
    ("{python}", "-m kgadapt flight bridg --robot {robot}", 3, r"invalid choice: 'bridg'"),
    ("{python}", "-m kgadapt squeeze --host {host}", 3, r"required: SIZE"),  # a required argument left out
])
def test_a_deployment_that_could_not_start_is_refused_at_load(executable, arguments, line, why):
    with pytest.raises(ModelError, match=rf"x\.deploy:{line}: .*{why}"):
        deployment_file.parse(_deploy(executable, arguments), "x.deploy")


def test_a_systemd_unit_with_an_unknown_module_names_its_execstart_line():
    text = "[Service]\nExecStart={python} -m no_such_module --x\n[X-Kgadapt]\nDeploys=g\nExecutableOn=a\n"
    with pytest.raises(ModelError, match=re.escape("u.service:2: module 'no_such_module'")):
        systemd.parse(text, "u.service")


def test_loading_the_models_judges_detectors_with_opencv_in_a_child_and_never_imports_it(tmp_path):
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    code = ("import json, sys; from kgadapt.knowledge.loader import check_models; "
            "resolved = check_models([sys.argv[1]]); "
            "print(json.dumps({'nodes': len(resolved.nodes), 'cv2': 'cv2' in sys.modules}))")
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}  # a cold cache: the child must answer
    done = subprocess.run([sys.executable, "-c", code, str(repo / "knowledge" / "models")], cwd=repo, env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["nodes"] > 0 and out["cv2"] is False
    assert list((tmp_path / "cache" / "kgadapt" / "detector-verdicts").glob("*.json"))  # the child's verdicts, kept


def test_one_preprocessing_table_for_the_importer_and_the_detector():
    from kgadapt.onboard.perception import markers
    from kgadapt.shared import preprocessing

    assert rpsl.PREPROCESS_OPS is preprocessing.OPS and markers._OPS is preprocessing.OPS
