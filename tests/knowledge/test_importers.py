"""Each notation's importer: what a good file becomes, and how a bad one is refused (file, line, reason)."""

from __future__ import annotations

import json
import re
import shutil

import pytest

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.importers import aadl, deployment_file, feature_model, parse_file, rpsl, systemd
from kgadapt.knowledge.loader import check_models, load_models
from kgadapt.shared.errors import ModelError

from .conftest import KNOWN, SHIPPED, signature


def _nodes(model):
    return {(n.label, n.name): n for n in model.nodes}


def _edges(model):
    return {(e.type, e.source.name, e.target.name) for e in model.edges}


def test_the_paper_fig3_model_parses_into_components_ports_and_a_connected_graph():
    text = '''
rpsl.sensor_component do
  name "camera"
  add_port :out, "out_port", "rgb_image"
end

rpsl.processing_component do
  name "aruco"
  add_port :in, "in_port", "rgb_image"
  add_port :out, "out_port", "marker"
end

rpsl.perception_graph do
  name "marker_detection"
  connect "camera", "out_port", "aruco", "in_port"
end
'''
    model = rpsl.parse(text, "fig3.rpsl")
    nodes = _nodes(model)
    assert nodes[(S.COMPONENT, "camera")].extra_labels == (S.SENSOR_COMPONENT,)
    assert nodes[(S.COMPONENT, "aruco")].extra_labels == (S.PROCESSING_COMPONENT,)
    assert nodes[(S.PORT, "aruco/in_port")].props["direction"] == "in"
    assert (S.PERCEPTION_GRAPH, "marker_detection") in nodes
    assert _edges(model) == {
        (S.HAS_PORT, "camera", "camera/out_port"), (S.HAS_PORT, "aruco", "aruco/in_port"),
        (S.HAS_PORT, "aruco", "aruco/out_port"),
        (S.CONTAINS, "marker_detection", "camera"), (S.CONTAINS, "marker_detection", "aruco"),
        (S.CONNECTED_TO, "camera/out_port", "aruco/in_port"),
    }
    assert nodes[(S.COMPONENT, "camera")].origin.line == 2


def test_a_camera_gets_its_resolution_and_intrinsics_and_the_camera_label():
    camera = _nodes(parse_file(KNOWN / "components.rpsl"))[(S.COMPONENT, "cam")]
    assert S.CAMERA in camera.extra_labels
    assert {k: camera.props[k] for k in ("width", "height", "fx", "fy", "cx", "cy", "fps")} == {
        "width": 640, "height": 480, "fx": 600.0, "fy": 601.0, "cx": 320.0, "cy": 240.0, "fps": 30}


def test_a_detector_component_carries_its_settings_as_config_json_in_the_written_order():
    det_b = _nodes(parse_file(KNOWN / "graphs.rpsl"))[(S.COMPONENT, "det_b")]
    assert json.loads(det_b.props["config_json"]) == {
        "dictionary": "DICT_4X4_50",
        "preprocess": [{"op": "gamma", "gamma": 0.5}, {"op": "blur", "ksize": 3}],
        "parameters": {"adaptiveThreshConstant": 3},
    }
    assert det_b.props["memory_demand_mb"] == 500 and det_b.props["dictionary"] == "DICT_4X4_50"


def test_a_platform_model_sums_its_memories_and_processors():
    nodes = _nodes(aadl.parse((KNOWN / "platforms.platform").read_text(), "p.platform"))
    beta = nodes[(S.PLATFORM, "beta")].props
    assert (beta["memory_total_mb"], beta["cpu_cores"], beta["cpu_capacity"]) == (4000.0, 4, 400.0)
    assert beta["compute_units"] == ["cpu: processor, 3 cores", "gpu_host: processor, 1 cores",
                                     "ram: memory, 3000 MiB", "extra: memory, 1000 MiB"]
    assert nodes[(S.PLATFORM, "alpha")].props["description"] == "small"


def test_a_systemd_unit_names_the_deployment_after_its_file_and_splits_execstart_like_a_shell():
    model = systemd.parse((KNOWN / "d_a.service").read_text(), "/x/d_a.service")
    node = _nodes(model)[(S.DEPLOYMENT, "d_a")]
    assert node.extra_labels == (S.SYSTEMD_SERVICE_FILE,)
    assert node.props["executable"] == "{python}"
    assert node.props["arguments"] == ["-m", "kgadapt.onboard.perception.detector", "--config", "{config}", "--host", "{host}"]
    assert node.props["environment"] == ["A=1", "B=two words"]
    assert _edges(model) == {(S.DEPLOYS, "d_a", "g_a"), (S.EXECUTABLE_ON, "d_a", "alpha"),
                             (S.EXECUTABLE_ON, "d_a", "beta")}


def test_a_systemd_line_continuation_joins_the_command():
    text = "[Service]\nExecStart={python} -m json.tool \\\n  --flag {robot}\n[X-Kgadapt]\nDeploys=g\nExecutableOn=a\n"
    node = systemd.parse(text, "u.service").nodes[0]
    assert node.props["arguments"] == ["-m", "json.tool", "--flag", "{robot}"]


def test_a_plain_deployment_file_becomes_a_deployment_file_node():
    model = deployment_file.parse((KNOWN / "d_c.deploy").read_text(), "/x/whatever.deploy")
    node = _nodes(model)[(S.DEPLOYMENT, "d_c")]  # the name: key wins over the file name
    assert node.extra_labels == (S.DEPLOYMENT_FILE,)
    assert (node.props["executable"], node.props["arguments"]) == \
        ("/usr/bin/env", ["{python}", "-m", "kgadapt.onboard.perception.detector"])
    assert _edges(model) == {(S.DEPLOYS, "d_c", "g_c"), (S.EXECUTABLE_ON, "d_c", "alpha")}


def test_a_feature_model_gives_features_requirements_and_bands():
    model = feature_model.parse((KNOWN / "features.features").read_text(), "f.features")
    nodes = _nodes(model)
    assert nodes[(S.ILLUMINATION_BAND, "dark")].props == {"name": "dark", "min_level": 0.0, "max_level": 10.0}
    assert nodes[(S.FEATURE, "MarkerDetection")].props["description"] == "Find markers"
    assert _edges(model) == {(S.REQUIRES, "Localization", "MarkerDetection")}


def test_the_shipped_models_check_clean_and_hold_what_the_adaptation_needs():
    resolved = check_models([SHIPPED])
    nodes = resolved.nodes
    onboard, remote = nodes[(S.PLATFORM, "onboard")].props, nodes[(S.PLATFORM, "remote")].props
    assert remote["memory_total_mb"] > onboard["memory_total_mb"] == 1024.0
    bands = {name for (label, name) in nodes if label == S.ILLUMINATION_BAND}
    assert bands == {"day", "dusk", "dark"}
    suited = {e.source.name: e.target.name for e, _, _ in resolved.edges if e.type == S.SUITED_FOR}
    assert sorted(suited.values()) == ["dark", "day", "dusk"]
    demand = {}
    for edge, _, _ in resolved.edges:
        if edge.type == S.CONTAINS:
            demand[edge.source.name] = demand.get(edge.source.name, 0) + \
                nodes[(S.COMPONENT, edge.target.name)].props["memory_demand_mb"]
    dark = next(g for g, b in suited.items() if b == "dark")
    day = next(g for g, b in suited.items() if b == "day")
    assert demand[dark] >= 300 > demand[day]  # the dark detector does not fit a squeezed onboard computer
    kinds = {n.extra_labels[0] for (label, _), n in nodes.items() if label == S.DEPLOYMENT}
    assert kinds == {S.SYSTEMD_SERVICE_FILE, S.DEPLOYMENT_FILE}
    resolutions = {(n.props["width"], n.props["height"]) for n in nodes.values() if S.CAMERA in n.extra_labels}
    assert len(resolutions) >= 2
    for (label, name), node in nodes.items():
        if label == S.DEPLOYMENT and name != "flight_control":
            assert node.props["arguments"][:2] == ["-m", "kgadapt.onboard.perception.detector"]


# --- malformed models: (file name, text, line, what the message says) -----------------------

GRAPH_HEAD = 'rpsl.perception_graph do\n  name "g_new"\n  realizes "MarkerDetection"\n'
MALFORMED = [
    ("missing_end.rpsl", 'rpsl.sensor_component do\n  name "x"\n  memory_demand_mb 1\n', 1, r"has no 'end'"),
    ("nested.rpsl", 'rpsl.sensor_component do\n  name "x"\nrpsl.processing_component do\n  name "y"\nend\n',
     3, r"opened inside rpsl.sensor_component \(line 1\), which has no 'end'"),
    ("stray_end.rpsl", "# nothing\nend\n", 2, r"'end' without an open block"),
    ("unknown_statement.rpsl", 'rpsl.sensor_component do\n  name "x"\n  launch_rockets 3\nend\n',
     3, r"unknown statement 'launch_rockets'"),
    ("unknown_top.rpsl", 'rpsl.actuator do\nend\n', 1, r"unknown statement 'rpsl.actuator'"),
    ("negative.rpsl", 'rpsl.processing_component do\n  name "x"\n  memory_demand_mb -5\nend\n',
     3, r"memory_demand_mb must not be negative"),
    ("noname.rpsl", 'rpsl.processing_component do\n  cpu_load 3\nend\n', 1, r"block has no name"),
    ("dup_port.rpsl", 'rpsl.processing_component do\n  name "x"\n  add_port :in, "p", "t"\n  add_port :out, "p", "t"\nend\n',
     4, r"duplicate port 'p'"),
    ("bad_direction.rpsl", 'rpsl.processing_component do\n  name "x"\n  add_port :sideways, "p", "t"\nend\n',
     3, r"direction must be :in or :out"),
    ("string.rpsl", 'rpsl.processing_component do\n  name "x\nend\n', 2, r"string opened at column 8 is not closed"),
    ("bad_char.rpsl", 'rpsl.processing_component do\n  name "x"\n  cpu_load 3 @\nend\n', 3, r"unexpected character '@'"),
    ("bad_op.rpsl", 'rpsl.processing_component do\n  name "x"\n  dictionary "DICT_4X4_50"\n'
     '  preprocess :sharpen, amount: 2\nend\n', 4, r"unknown step :sharpen"),
    ("bad_range.rpsl", 'rpsl.processing_component do\n  name "x"\n  dictionary "DICT_4X4_50"\n'
     '  preprocess :gamma, gamma: 20\nend\n', 4, r"gamma 20 is outside \[0.05, 10\]"),
    ("even_blur.rpsl", 'rpsl.processing_component do\n  name "x"\n  dictionary "DICT_4X4_50"\n'
     '  preprocess :blur, ksize: 4\nend\n', 4, r"ksize must be odd"),
    ("bad_param.rpsl", 'rpsl.processing_component do\n  name "x"\n  dictionary "DICT_4X4_50"\n'
     '  parameter "adaptiveThreshWinSizMax", 5\nend\n', 4, r"not an attribute of cv2.aruco.DetectorParameters"),
    ("unknown_component.rpsl", GRAPH_HEAD + '  connect "cam", "out_port", "ghost", "in_port"\nend\n',
     4, r"unknown component 'ghost'"),
    ("unknown_port.rpsl", GRAPH_HEAD + '  connect "cam", "nope", "det_a", "in_port"\nend\n',
     4, r"unknown port 'nope' of component 'cam'"),
    ("wrong_way.rpsl", GRAPH_HEAD + '  connect "det_a", "in_port", "det_b", "in_port"\nend\n',
     4, r"det_a/in_port is an input port"),
    ("wrong_type.rpsl", GRAPH_HEAD + '  connect "det_a", "out_port", "det_b", "in_port"\nend\n',
     4, r"carries marker but det_b/in_port expects rgb_image"),
    ("unknown_feature.rpsl", 'rpsl.perception_graph do\n  name "g_new"\n  realizes "Teleportation"\nend\n',
     3, r"unknown feature 'Teleportation'"),
    ("duplicate.rpsl", '\n\nrpsl.sensor_component do\n  name "cam"\nend\n', 3,
     r"duplicate Component name 'cam' \(first defined at .*components.rpsl:1\)"),
    ("missing_end.platform", "platform gamma\n  processor cpu\n    cores => 1\n  end cpu\n", 1, r"platform gamma has no 'end'"),
    ("negative.platform", "platform gamma\n  memory ram\n    size_mb => -512\n  end ram\nend gamma\n",
     3, r"size_mb must be positive"),
    ("unknown.platform", "platform gamma\n  turbo => true\nend gamma\n", 2, r"unknown property 'turbo'"),
    ("mismatch.platform", "platform gamma\n  processor cpu\n    cores => 1\n  end gpu\nend gamma\n",
     4, r"closes processor cpu"),
    ("nomemory.platform", "platform gamma\n  processor cpu\n    cores => 1\n  end cpu\nend gamma\n",
     1, r"platform gamma has no memory"),
    ("unknown_section.service", "[Service]\nExecStart=/bin/true\n[Timer]\nOnCalendar=daily\n", 3, r"unknown section \[Timer\]"),
    ("twice.service", "[Service]\nExecStart=/bin/true\nExecStart=/bin/false\n[X-Kgadapt]\nDeploys=g_a\nExecutableOn=alpha\n",
     3, r"ExecStart= given twice"),
    ("placeholder.service", "[Service]\nExecStart={python} --home {home}\n[X-Kgadapt]\nDeploys=g_a\nExecutableOn=alpha\n",
     2, r"unknown placeholder \{home\}"),
    ("noequals.service", "[Service]\nExecStart=/bin/true\njust words here\n", 3, r"unknown statement 'just words here'"),
    ("unknown_platform.service", "[Service]\nExecStart=/bin/true\n[X-Kgadapt]\nDeploys=g_a\nExecutableOn=alpha mars\n",
     5, r"unknown platform 'mars'"),
    ("unknown_key.deploy", "deploys: g_a\nexecutable: /bin/true\nexecutable_on: alpha\nreplicas: 3\n", 4,
     r"unknown key 'replicas'"),
    ("no_deploys.deploy", "executable: /bin/true\nexecutable_on: alpha\n", 1, r"does not say what it deploys"),
    ("ghost_graph.deploy", "deploys: g_ghost\nexecutable: /bin/true\nexecutable_on: alpha\n",
     1, r"unknown perception graph or component 'g_ghost'"),
    ("unknown_platform.deploy", "# a comment\ndeploys: g_a\nexecutable: /bin/true\nexecutable_on: alpha, pluto\n",
     4, r"unknown platform 'pluto'"),
    ("overlap.features", "band dim\n  min_level 5\n  max_level 20\nend\nband bright\n  min_level 15\n  max_level 30\nend\n",
     5, r"band bright \[15, 30\) overlaps band dim"),
    ("inverted.features", "band odd\n  min_level 50\n  max_level 20\nend\n", 1, r"min_level 50 is not below max_level 20"),
    ("too_bright.features", "band glare\n  min_level 200\n  max_level 300\nend\n", 3, r"above 255"),
    ("requires.features", "feature Flying\n  requires Hovering\nend\n", 2, r"unknown feature 'Hovering'"),
    ("wide_margin.features", "band thin\n  min_level 10\n  max_level 16\n  margin 3\nend\n", 1,
     r"band thin: margin 3 is not below half the band's width \(6\)"),
    ("budget.features", "feature Fast\n  frame_budget_ms 0\nend\n", 2, r"frame_budget_ms 0 is outside"),
]


@pytest.mark.parametrize("filename, text, line, message", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_a_malformed_model_is_refused_with_file_line_and_reason_and_nothing_is_written(
        resp_store, tmp_path, filename, text, line, message):
    models = tmp_path / "models"
    shutil.copytree(KNOWN, models)
    load_models(resp_store, [models])
    before = signature(resp_store)
    (models / "new_feature.features").write_text("feature Extra\nend\n")  # good, but must not land either
    bad = models / filename
    bad.write_text(text)
    with pytest.raises(ModelError) as caught:
        load_models(resp_store, [models])
    error = caught.value
    assert error.path == str(bad) and error.line == line, str(error)
    assert re.search(message, error.message), str(error)
    assert str(error).startswith(f"{bad}:{line}: ")
    assert signature(resp_store) == before


def test_an_unknown_file_kind_named_on_its_own_is_refused(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("hello")
    with pytest.raises(ModelError, match=r"no importer for '.txt'"):
        check_models([path])


def test_a_missing_path_is_refused_by_name(tmp_path):
    with pytest.raises(ModelError, match="no such file or directory"):
        check_models([tmp_path / "absent"])
