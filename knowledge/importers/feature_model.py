"""Feature models (``.features``): the robot's features and the illumination bands.

::

    # What the quadcopter can do, and the light it meets.
    feature Localization
      description "Know where the quadcopter is, indoors and without GPS"
      requires MarkerDetection
    end

    feature MarkerDetection
      description "Find ArUco markers in camera frames"
    end

    band dark
      description "Mean luminance below 12 of 255"
      min_level 0
      max_level 12
      margin 3
    end

Features become ``Feature`` nodes (``requires`` gives ``(Feature)-[:REQUIRES]->(Feature)``);
``frame_budget_ms`` is what one frame's detection may cost (a hedging detector
runs a second configuration only within it).
Bands become ``IlluminationBand`` nodes over mean luminance 0..255, half-open
``[min_level, max_level)`` (the top band includes 255); the bands of one file
may touch but not overlap. ``margin`` (optional, levels): how far past an edge
a frame's light must be before the detector's reflex leaves the band.
"""

from __future__ import annotations

from typing import Any

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.importers.model import EdgeSpec, NodeSpec, Origin, ParsedModel, Ref
from kgadapt.knowledge.importers.tokens import Statement, expect_args, name_arg, number_arg, read_statements, text_arg

NOTATION = "feature model"
_BLOCKS = {"feature": S.FEATURE, "band": S.ILLUMINATION_BAND}


class _Block:
    def __init__(self, kind: str, name: str, origin: Origin) -> None:
        self.kind, self.name, self.origin = kind, name, origin
        self.props: dict[str, Any] = {"name": name}
        self.requires: list[tuple[str, Origin]] = []


def parse(text: str, path: str) -> ParsedModel:
    """Read one ``.features`` file (raises ModelError naming file and line)."""
    model = ParsedModel(path=path, notation=NOTATION)
    block: _Block | None = None
    bands: list[_Block] = []
    for st in read_statements(text, path):
        kw = st.keyword
        if kw in _BLOCKS:
            if block is not None:
                raise st.origin.error(f"{kw} opened inside {block.kind} {block.name} "
                                      f"(line {block.origin.line}), which has no 'end'")
            expect_args(st, 1, f"{kw} NAME")
            block = _Block(kw, name_arg(st, st.args[0]), st.origin)
        elif kw == "end":
            if block is None:
                raise st.origin.error("'end' without an open feature or band")
            expect_args(st, 0, "nothing after 'end'")
            _close(model, block, bands)
            block = None
        elif block is None:
            raise st.origin.error(f"unknown statement {kw!r} outside a block (expected feature NAME or band NAME)")
        else:
            _statement(block, st)
    if block is not None:
        raise block.origin.error(f"{block.kind} {block.name} has no 'end'")
    return model


def _statement(b: _Block, st: Statement) -> None:
    kw = st.keyword
    if kw == "description":
        expect_args(st, 1, 'description "TEXT"')
        _once(b, st, "description", text_arg(st, st.args[0], "description"))
    elif b.kind == "feature" and kw == "requires":
        expect_args(st, 1, "requires FEATURE")
        b.requires.append((name_arg(st, st.args[0], "feature"), st.origin))
    elif b.kind == "band" and kw in ("min_level", "max_level"):
        expect_args(st, 1, f"{kw} NUMBER (0..255)")
        value = number_arg(st, st.args[0], kw)
        if value > 255:
            raise st.origin.error(f"{kw} {value} is above 255 (levels are mean luminance 0..255)")
        _once(b, st, kw, float(value))
    elif b.kind == "band" and kw == "margin":
        expect_args(st, 1, "margin NUMBER (levels, >= 0)")
        value = number_arg(st, st.args[0], kw)
        if value < 0 or value > 64:
            raise st.origin.error(f"margin {value} is outside 0..64 (levels of mean luminance)")
        _once(b, st, kw, float(value))
    elif b.kind == "feature" and kw == "frame_budget_ms":
        expect_args(st, 1, "frame_budget_ms NUMBER (> 0)")
        value = number_arg(st, st.args[0], kw)
        if not 0 < value <= 10_000:
            raise st.origin.error(f"frame_budget_ms {value} is outside (0, 10000] ms")
        _once(b, st, kw, float(value))
    else:
        raise st.origin.error(f"unknown statement {kw!r} in {b.kind} {b.name}")


def _once(b: _Block, st: Statement, key: str, value: Any) -> None:
    if key in b.props:
        raise st.origin.error(f"{key} set twice in {b.kind} {b.name}")
    b.props[key] = value


def _close(model: ParsedModel, b: _Block, bands: list[_Block]) -> None:
    if b.kind == "band":
        for key in ("min_level", "max_level"):
            if key not in b.props:
                raise b.origin.error(f"band {b.name} has no {key}")
        low, high = b.props["min_level"], b.props["max_level"]
        if low >= high:
            raise b.origin.error(f"band {b.name}: min_level {low:g} is not below max_level {high:g}")
        if b.props.get("margin", 0.0) * 2 >= high - low:
            raise b.origin.error(f"band {b.name}: margin {b.props['margin']:g} is not below half the band's "
                                 f"width ({high - low:g})")
        for other in bands:
            if low < other.props["max_level"] and other.props["min_level"] < high:
                raise b.origin.error(f"band {b.name} [{low:g}, {high:g}) overlaps band {other.name} "
                                     f"[{other.props['min_level']:g}, {other.props['max_level']:g}) "
                                     f"(line {other.origin.line})")
        bands.append(b)
    model.nodes.append(NodeSpec(_BLOCKS[b.kind], b.name, b.props, b.origin))
    for required, origin in b.requires:
        if required == b.name:
            raise origin.error(f"feature {b.name} requires itself")
        model.edges.append(EdgeSpec(S.REQUIRES, Ref((S.FEATURE,), b.name, "feature"),
                                    Ref((S.FEATURE,), required, "feature"), origin))
