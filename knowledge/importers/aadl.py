"""Platform models (``.platform``): compute units, memory and CPU, AADL-like in spirit.

One or more platforms per file; subcomponents and properties as in AADL
(``name => value``, ``--`` comments, ``end NAME`` closing what it names)::

    -- The quadcopter's companion computer.
    platform onboard
      description => "Companion computer on the quadcopter"
      processor cpu
        cores => 4
        clock_mhz => 1500
        architecture => "aarch64"
      end cpu
      memory ram
        size_mb => 1024
      end ram
    end onboard

The ``onboard`` and ``remote`` names are the host names the agents use. The
graph gets one ``Platform`` node: ``memory_total_mb`` (sum of its memories),
``cpu_cores`` (sum of its processors' cores), ``cpu_capacity`` (100 per core,
in percent of one core like every CPU figure) and ``compute_units`` (a short
description of each subcomponent).
"""

from __future__ import annotations

from typing import Any

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.importers.model import NodeSpec, Origin, ParsedModel
from kgadapt.knowledge.importers.tokens import Statement, expect_args, name_arg, number_arg, read_statements, text_arg

NOTATION = "platform model (AADL-like)"

# Subcomponent kinds and the properties each accepts (with their check).
_PROPS = {
    "platform": {"description": "text", "os": "text"},
    "processor": {"cores": "count", "clock_mhz": "positive", "architecture": "text"},
    "memory": {"size_mb": "positive"},
}


class _Unit:
    def __init__(self, kind: str, name: str, origin: Origin) -> None:
        self.kind, self.name, self.origin = kind, name, origin
        self.props: dict[str, Any] = {}
        self.units: list[_Unit] = []


def parse(text: str, path: str) -> ParsedModel:
    """Read one ``.platform`` file (raises ModelError naming file and line)."""
    model = ParsedModel(path=path, notation=NOTATION)
    stack: list[_Unit] = []
    for st in read_statements(text, path):
        kw = st.keyword
        if kw in _PROPS and not st.arrow:
            expect_args(st, 1, f"{kw} NAME")
            unit = _Unit(kw, name_arg(st, st.args[0]), st.origin)
            if kw == "platform" and stack:
                raise st.origin.error(f"platform {unit.name} opened inside platform {stack[0].name} "
                                      f"(line {stack[0].origin.line}), which has no 'end'")
            if kw != "platform":
                if not stack:
                    raise st.origin.error(f"{kw} {unit.name} outside a platform")
                if len(stack) > 1:
                    raise st.origin.error(f"{kw} {unit.name} inside {stack[-1].kind} {stack[-1].name} "
                                          f"(line {stack[-1].origin.line}), which has no 'end'")
                if any(u.name == unit.name for u in stack[-1].units):
                    raise st.origin.error(f"duplicate subcomponent {unit.name!r} in platform {stack[-1].name}")
                stack[-1].units.append(unit)
            stack.append(unit)
        elif kw == "end":
            if not stack:
                raise st.origin.error("'end' without an open platform or subcomponent")
            unit = stack.pop()
            if st.args and (len(st.args) != 1 or st.args[0] != unit.name):
                raise st.origin.error(f"'end {' '.join(map(str, st.args))}' closes {unit.kind} {unit.name} "
                                      f"(opened at line {unit.origin.line})")
            if unit.kind == "platform":
                model.nodes.append(_platform_node(unit))
        elif st.arrow:
            if not stack:
                raise st.origin.error(f"property {kw!r} outside a platform")
            _property(stack[-1], st)
        else:
            raise st.origin.error(f"unknown statement {kw!r} (expected platform, processor, memory, "
                                  "'NAME => VALUE' or end)")
    if stack:
        unit = stack[-1]
        raise unit.origin.error(f"{unit.kind} {unit.name} has no 'end'")
    return model


def _property(unit: _Unit, st: Statement) -> None:
    allowed = _PROPS[unit.kind]
    if st.keyword not in allowed:
        raise st.origin.error(f"unknown property {st.keyword!r} of a {unit.kind} (known: {', '.join(allowed)})")
    expect_args(st, 1, f"{st.keyword} => VALUE")
    if st.keyword in unit.props:
        raise st.origin.error(f"property {st.keyword!r} set twice")
    check = allowed[st.keyword]
    value = st.args[0]
    if check == "text":
        unit.props[st.keyword] = text_arg(st, value, st.keyword)
    else:
        unit.props[st.keyword] = number_arg(st, value, st.keyword, positive=True, integer=check == "count")


def _platform_node(unit: _Unit) -> NodeSpec:
    processors = [u for u in unit.units if u.kind == "processor"]
    memories = [u for u in unit.units if u.kind == "memory"]
    if not processors:
        raise unit.origin.error(f"platform {unit.name} has no processor")
    if not memories:
        raise unit.origin.error(f"platform {unit.name} has no memory")
    for u in processors:
        if "cores" not in u.props:
            raise u.origin.error(f"processor {u.name} has no 'cores => N'")
    for u in memories:
        if "size_mb" not in u.props:
            raise u.origin.error(f"memory {u.name} has no 'size_mb => N'")
    cores = sum(u.props["cores"] for u in processors)
    units = []
    for u in unit.units:
        if u.kind == "processor":
            parts = [f"{u.props['cores']} cores"]
            if "clock_mhz" in u.props:
                parts.append(f"{u.props['clock_mhz']:g} MHz")
            if "architecture" in u.props:
                parts.append(u.props["architecture"])
            units.append(f"{u.name}: processor, {', '.join(parts)}")
        else:
            units.append(f"{u.name}: memory, {u.props['size_mb']:g} MiB")
    props = {
        "name": unit.name,
        **unit.props,
        "memory_total_mb": float(sum(u.props["size_mb"] for u in memories)),
        "cpu_cores": cores,
        "cpu_capacity": 100.0 * cores,
        "compute_units": units,
    }
    return NodeSpec(S.PLATFORM, unit.name, props, unit.origin)
