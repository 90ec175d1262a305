"""The perception-graph DSL of the paper's Fig. 3 (``.rpsl``), parsed, never evaluated.

Blocks open with ``rpsl.KIND do`` and close with ``end``::

    rpsl.sensor_component do            # Component:SensorComponent (+ Camera with a resolution)
      name "camera"
      add_port :out, "out_port", "rgb_image"
      resolution 640, 480
      intrinsics fx: 615.0, fy: 615.0, cx: 320.0, cy: 240.0
      fps 30
      memory_demand_mb 24
      cpu_load 6
    end

    rpsl.processing_component do        # Component:ProcessingComponent
      name "aruco_day"
      add_port :in, "in_port", "rgb_image"
      add_port :out, "out_port", "marker"
      memory_demand_mb 48
      cpu_load 30
      ms_per_frame 4
      dictionary "DICT_4X4_50"          # makes it a marker detector: config_json is built
                                        # (or "site_dict.yml": OpenCV's dictionary file, beside this file)
      parameter "adaptiveThreshConstant", 7
      preprocess :gamma, gamma: 0.5     # run in the order written
    end

    rpsl.perception_graph do            # PerceptionGraph
      name "marker_detection_day"
      realizes "MarkerDetection"
      suited_for :day
      connect "camera", "out_port", "aruco_day", "in_port"
      contains "other_component"        # components not named by a connect
    end

    rpsl.flight_control do              # Component:FlightControl
      name "flight_control"
      memory_demand_mb 64
      cpu_load 35
    end

Every block may also say ``description "text"`` and ``property "key", value``
(any extra number, string or boolean). Anything else is refused with the file
and line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.importers import detector_check
from kgadapt.knowledge.importers.model import EdgeSpec, NodeSpec, Origin, ParsedModel, Ref
from kgadapt.knowledge.importers.tokens import Statement, Symbol, expect_args, name_arg, number_arg, read_statements, text_arg
from kgadapt.shared import preprocessing

NOTATION = "perception graph DSL (rpsl)"

BLOCKS = {
    "rpsl.sensor_component": (S.COMPONENT, (S.SENSOR_COMPONENT,)),
    "rpsl.processing_component": (S.COMPONENT, (S.PROCESSING_COMPONENT,)),
    "rpsl.flight_control": (S.COMPONENT, (S.FLIGHT_CONTROL,)),
    "rpsl.perception_graph": (S.PERCEPTION_GRAPH, ()),
}
# The other sub-labels of Component, removed when a component changes kind.
COMPONENT_KINDS = (S.SENSOR_COMPONENT, S.PROCESSING_COMPONENT, S.FLIGHT_CONTROL, S.CAMERA)

# Pre-processing steps the detector program implements, with their settings' ranges: one table
# shared with onboard/perception/markers.py.
PREPROCESS_OPS = preprocessing.OPS
RESERVED = {"name", "model_file", "config_json", "width", "height", "fx", "fy", "cx", "cy", "fps",
            "memory_demand_mb", "cpu_load", "ms_per_frame", "dictionary", "description"}


def _setting(st: Statement, op: str, key: str, value: Any) -> Any:
    setting = PREPROCESS_OPS[op][key]
    value = number_arg(st, value, key, integer=setting.kind is int)
    problem = setting.problem(value)
    if problem:
        raise st.origin.error(f"preprocess :{op}: {key} {problem}")
    return value


class _Block:
    def __init__(self, kind: str, origin: Origin) -> None:
        self.kind = kind
        self.origin = origin
        self.name: str | None = None
        self.props: dict[str, Any] = {}
        self.ports: list[tuple[str, str, str, Origin]] = []  # (name, direction, data type)
        self.parameters: dict[str, Any] = {}
        self.preprocess: list[dict[str, Any]] = []
        self.origins: dict[str, Origin] = {}  # "dictionary", "parameter:KEY": where OpenCV's verdict points
        self.realizes: list[tuple[str, Origin]] = []
        self.suited_for: list[tuple[str, Origin]] = []
        self.contains: list[tuple[str, Origin]] = []
        self.connects: list[tuple[str, str, str, str, Origin]] = []


def parse(text: str, path: str) -> ParsedModel:
    """Read one ``.rpsl`` file into nodes and relations (raises ModelError naming file and line)."""
    model = ParsedModel(path=path, notation=NOTATION)
    block: _Block | None = None
    blocks: list[_Block] = []
    for st in read_statements(text, path):
        if st.keyword in BLOCKS:
            if block is not None:
                raise st.origin.error(
                    f"{st.keyword} opened inside {block.kind} (line {block.origin.line}), which has no 'end'")
            if st.args != ["do"] or st.options:
                raise st.origin.error(f"write '{st.keyword} do' to open a block")
            block = _Block(st.keyword, st.origin)
        elif st.keyword == "end":
            if block is None:
                raise st.origin.error("'end' without an open block")
            expect_args(st, 0, "nothing after 'end'")
            if block.name is None:
                raise block.origin.error(f"{block.kind} block has no name")
            blocks.append(block)
            block = None
        elif block is None:
            raise st.origin.error(f"unknown statement {st.keyword!r} outside a block "
                                  f"(expected one of: {', '.join(k + ' do' for k in BLOCKS)})")
        else:
            _statement(block, st)
    if block is not None:
        raise block.origin.error(f"{block.kind} block has no 'end'")
    for b in blocks:
        _config_json(b)
    _check_detectors(blocks, path)
    for b in blocks:
        _emit(model, b)
    return model


def _statement(b: _Block, st: Statement) -> None:
    kw = st.keyword
    component = b.kind != "rpsl.perception_graph"
    if kw == "name":
        expect_args(st, 1, 'name "NAME"')
        if b.name is not None:
            raise st.origin.error(f"{b.kind} block names itself twice")
        b.name = name_arg(st, st.args[0])
    elif kw == "description":
        expect_args(st, 1, 'description "TEXT"')
        b.props["description"] = text_arg(st, st.args[0], "description")
    elif kw == "property":
        expect_args(st, 2, 'property "KEY", VALUE')
        key = name_arg(st, st.args[0], "property key")
        if not key.isidentifier() or key in RESERVED:
            raise st.origin.error(f"property key {key!r} is not an identifier or is reserved")
        value = st.args[1]
        if isinstance(value, str):
            value = text_arg(st, value, f"property {key}")
        if key in b.props:
            raise st.origin.error(f"property {key!r} set twice")
        b.props[key] = value if not isinstance(value, Symbol) else str(value)
    elif component and kw in ("memory_demand_mb", "cpu_load", "ms_per_frame"):
        expect_args(st, 1, f"{kw} NUMBER")
        _once(b, st, kw, number_arg(st, st.args[0], kw))
    elif component and kw == "add_port":
        expect_args(st, 3, 'add_port :in|:out, "PORT", "DATA_TYPE"')
        direction = st.args[0]
        if not isinstance(direction, Symbol) or direction not in ("in", "out"):
            raise st.origin.error(f"add_port: direction must be :in or :out, not {direction!r}")
        port = name_arg(st, st.args[1], "port name")
        data_type = name_arg(st, st.args[2], "data type")
        if any(p[0] == port for p in b.ports):
            raise st.origin.error(f"duplicate port {port!r} on {b.name or 'this component'}")
        b.ports.append((port, str(direction), data_type, st.origin))
    elif b.kind == "rpsl.sensor_component" and kw == "resolution":
        expect_args(st, 2, "resolution WIDTH, HEIGHT")
        _once(b, st, "width", number_arg(st, st.args[0], "width", positive=True, integer=True))
        b.props["height"] = number_arg(st, st.args[1], "height", positive=True, integer=True)
    elif b.kind == "rpsl.sensor_component" and kw == "intrinsics":
        expect_args(st, 0, "intrinsics fx: F, fy: F, cx: C, cy: C", options=("fx", "fy", "cx", "cy"))
        for key in ("fx", "fy", "cx", "cy"):
            if key not in st.options:
                raise st.origin.error(f"intrinsics: {key} is missing")
            value = number_arg(st, st.options[key], key, positive=key in ("fx", "fy"))
            _once(b, st, key, float(value))
    elif b.kind == "rpsl.sensor_component" and kw == "fps":
        expect_args(st, 1, "fps NUMBER")
        _once(b, st, "fps", number_arg(st, st.args[0], "fps", positive=True))
    elif b.kind == "rpsl.processing_component" and kw == "dictionary":
        expect_args(st, 1, 'dictionary "DICT_4X4_50" or dictionary "FILE.yml"')
        value = _dictionary(st)
        _once(b, st, "dictionary", value)
        b.origins["dictionary"] = st.origin
    elif b.kind == "rpsl.processing_component" and kw == "parameter":
        expect_args(st, 2, 'parameter "DetectorParametersAttribute", NUMBER')
        key = name_arg(st, st.args[0], "parameter name")
        if not key.isidentifier():
            raise st.origin.error(f"parameter name {key!r} is not an identifier")
        if key in b.parameters:
            raise st.origin.error(f"parameter {key!r} set twice")
        b.parameters[key] = _parameter_value(st, key, st.args[1])
        b.origins[f"parameter:{key}"] = st.origin
    elif b.kind == "rpsl.processing_component" and kw == "preprocess":
        if len(st.args) != 1 or not isinstance(st.args[0], Symbol):
            raise st.origin.error(f"preprocess: expected :OP followed by its settings "
                                  f"(OP one of {', '.join(PREPROCESS_OPS)})")
        op = str(st.args[0])
        if op not in PREPROCESS_OPS:
            raise st.origin.error(f"preprocess: unknown step :{op} (known: {', '.join(PREPROCESS_OPS)})")
        settings = PREPROCESS_OPS[op]
        step: dict[str, Any] = {"op": op}
        for key in st.option_order:
            if key not in settings:
                raise st.origin.error(f"preprocess :{op}: unknown setting {key!r} (known: {', '.join(settings)})")
            step[key] = _setting(st, op, key, st.options[key])
        for key in settings:
            if key not in step:
                raise st.origin.error(f"preprocess :{op}: {key} is missing")
        b.preprocess.append(step)
    elif not component and kw in ("realizes", "suited_for", "contains"):
        expect_args(st, 1, f"{kw} NAME")
        getattr(b, kw).append((name_arg(st, str(st.args[0]) if isinstance(st.args[0], Symbol) else st.args[0]),
                               st.origin))
    elif not component and kw == "connect":
        expect_args(st, 4, 'connect "FROM_COMPONENT", "OUT_PORT", "TO_COMPONENT", "IN_PORT"')
        names = [name_arg(st, v) for v in st.args]
        b.connects.append((names[0], names[1], names[2], names[3], st.origin))
    else:
        raise st.origin.error(f"unknown statement {kw!r} in {b.kind} block")


def _dictionary(st: Statement) -> str:
    """A DICT_* name, or an OpenCV dictionary file (relative to the model file) as its absolute path.

    Whether the file holds a dictionary is OpenCV's to say (:func:`_check_detectors`); that it
    is there is said here, so a missing file is named even where OpenCV is not installed.
    """
    raw = st.args[0]
    if isinstance(raw, str) and not isinstance(raw, Symbol) and preprocessing.is_dictionary_file(raw):
        text = text_arg(st, raw, "dictionary file")
        path = Path(text) if Path(text).is_absolute() else Path(st.origin.path).parent / text
        if not path.is_file():
            raise st.origin.error(f"dictionary file {text!r} not found (looked for {path})")
        return str(path.resolve())
    value = name_arg(st, raw, "dictionary")
    if not value.startswith("DICT_"):
        raise st.origin.error(f"dictionary {value!r} is neither an ArUco dictionary name (DICT_...) "
                              f"nor a dictionary file ({', '.join(preprocessing.DICTIONARY_FILE_SUFFIXES)})")
    return value


def _once(b: _Block, st: Statement, key: str, value: Any) -> None:
    if key in b.props:
        raise st.origin.error(f"{st.keyword}: {key} set twice")
    b.props[key] = value


def _parameter_value(st: Statement, key: str, value: Any) -> Any:
    """A number; whether OpenCV has such a parameter is asked with the rest (:func:`_check_detectors`)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise st.origin.error(f"parameter {key}: value must be a number, not {value!r}")
    return value


# cornerRefinementMethod is an enum OpenCV does not check: CORNER_REFINE_NONE, SUBPIX, CONTOUR, APRILTAG.
_PARAMETER_RANGES = {"cornerRefinementMethod": (0, 3)}


def _config_json(b: _Block) -> None:
    if b.kind != "rpsl.processing_component":
        return
    if "dictionary" in b.props:
        # Written through the detector's schema: what the importer writes is what parse_config reads.
        b.props["config_json"] = preprocessing.DetectorSettings(
            dictionary=b.props["dictionary"], parameters=b.parameters,
            preprocess=[preprocessing.make_step(step["op"], {k: v for k, v in step.items() if k != "op"})
                        for step in b.preprocess],
        ).to_json()
    elif b.parameters or b.preprocess:
        raise b.origin.error(f"{b.name}: detector parameters or preprocess steps need a dictionary statement")


def _check_detectors(blocks: list[_Block], path: str) -> None:
    """Judge every detector configuration of the file as the detector program would at start.

    The names, types and ranges OpenCV accepts are OpenCV's to say, but this
    process must not load it: :mod:`kgadapt.knowledge.importers.detector_check` asks a
    child process, for all of the file's configurations at once. Where OpenCV
    is not installed the detector program checks at start.
    """
    detectors = [b for b in blocks if "config_json" in b.props]
    for b in detectors:
        for key, (low, high) in _PARAMETER_RANGES.items():
            value = b.parameters.get(key)
            if isinstance(value, (int, float)) and not low <= value <= high:
                raise b.origin.error(f"{b.name}: parameter {key} = {value} is outside [{low}, {high}]")
    asked = [(str(b.name), b.props["config_json"]) for b in detectors]
    for b, verdict in zip(detectors, detector_check.verdicts(asked, path)):
        if verdict is not None:
            at = verdict["at"] if verdict["at"] == "dictionary" else f"parameter:{verdict['key']}"
            raise b.origins.get(at, b.origin).error(verdict["message"])


def _emit(model: ParsedModel, b: _Block) -> None:
    label, extra = BLOCKS[b.kind]
    assert b.name is not None
    props = {"name": b.name, **b.props}
    if b.kind == "rpsl.sensor_component" and "width" in props:
        extra = extra + (S.CAMERA,)
    if b.kind == "rpsl.sensor_component" and "width" not in props and any(k in props for k in ("fx", "fps")):
        raise b.origin.error(f"{b.name}: intrinsics or fps without a resolution statement")
    model.nodes.append(NodeSpec(label, b.name, props, b.origin, extra))
    for port, direction, data_type, origin in b.ports:
        key = f"{b.name}/{port}"
        model.nodes.append(NodeSpec(S.PORT, key, {"name": key, "key": key, "port": port, "component": b.name,
                                                  "direction": direction, "data_type": data_type}, origin))
        model.edges.append(EdgeSpec(S.HAS_PORT, Ref((S.COMPONENT,), b.name, "component"),
                                    Ref((S.PORT,), key, "port"), origin))
    if b.kind != "rpsl.perception_graph":
        return
    me = Ref((S.PERCEPTION_GRAPH,), b.name, "perception graph")
    for feature, origin in b.realizes:
        model.edges.append(EdgeSpec(S.REALIZES, me, Ref((S.FEATURE,), feature, "feature"), origin))
    for band, origin in b.suited_for:
        model.edges.append(EdgeSpec(S.SUITED_FOR, me, Ref((S.ILLUMINATION_BAND,), band, "illumination band"), origin))
    contained: dict[str, Origin] = {}
    for name, origin in b.contains:
        if name in contained:
            raise origin.error(f"{b.name} contains {name!r} twice")
        contained[name] = origin
    for src, _, dst, _, origin in b.connects:
        contained.setdefault(src, origin)
        contained.setdefault(dst, origin)
    for name, origin in contained.items():
        model.edges.append(EdgeSpec(S.CONTAINS, me, Ref((S.COMPONENT,), name, "component"), origin))
    for src, out_port, dst, in_port, origin in b.connects:
        model.edges.append(EdgeSpec(
            S.CONNECTED_TO,
            Ref((S.PORT,), f"{src}/{out_port}", "port", f"port {out_port!r} of component {src!r}"),
            Ref((S.PORT,), f"{dst}/{in_port}", "port", f"port {in_port!r} of component {dst!r}"),
            origin, key={"graph": b.name}, check=_check_connection,
        ))


def _check_connection(source: NodeSpec | None, target: NodeSpec | None) -> str | None:
    if source is None or target is None:
        return None  # defined only in the store: checked when that model was loaded
    if source.props["direction"] != "out":
        return f"connect: {source.name} is an input port; connections go from an output port"
    if target.props["direction"] != "in":
        return f"connect: {target.name} is an output port; connections go to an input port"
    if source.props["data_type"] != target.props["data_type"]:
        return (f"connect: {source.name} carries {source.props['data_type']} "
                f"but {target.name} expects {target.props['data_type']}")
    return None
