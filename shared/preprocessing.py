"""The detector configuration (``config_json``) as a type: its pre-processing steps and their ranges.

One schema for the three places that read or write a detector configuration: the
model importer (``preprocess :gamma, gamma: 0.5`` in ``.rpsl`` files, checked at
load time, every setting written out through :class:`DetectorSettings`), the
detector program and calibration (both through
:func:`kgadapt.onboard.perception.markers.parse_config`, which calls :func:`read_settings`
and then asks OpenCV about the dictionary and parameters). A step is a Struct
tagged on ``op``; its fields' defaults and ranges are the table :data:`OPS`.
docs/CONTRACTS.md describes the ``config_json`` they share.
"""

from __future__ import annotations

import json
import math
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Union

import msgspec
from msgspec import Meta, Struct

from kgadapt.shared.errors import ConfigError

DEFAULT_DICTIONARY = "DICT_4X4_50"


class Step(Struct, frozen=True, kw_only=True, tag_field="op", forbid_unknown_fields=True):
    """One pre-processing step; ``ODD`` names the settings that take odd numbers only (kernel sizes)."""

    ODD: ClassVar[frozenset[str]] = frozenset()


class Gamma(Step, tag="gamma", frozen=True, kw_only=True, forbid_unknown_fields=True):
    gamma: Annotated[float, Meta(ge=0.05, le=10.0)] = 1.0


class Clahe(Step, tag="clahe", frozen=True, kw_only=True, forbid_unknown_fields=True):
    clip_limit: Annotated[float, Meta(ge=0.1, le=100.0)] = 2.0
    tile: Annotated[int, Meta(ge=1, le=64)] = 8


class Stretch(Step, tag="stretch", frozen=True, kw_only=True, forbid_unknown_fields=True):
    low_pct: Annotated[float, Meta(ge=0.0, le=49.0)] = 1.0
    high_pct: Annotated[float, Meta(ge=51.0, le=100.0)] = 99.0


class Blur(Step, tag="blur", frozen=True, kw_only=True, forbid_unknown_fields=True):
    ODD: ClassVar[frozenset[str]] = frozenset({"ksize"})
    ksize: Annotated[int, Meta(ge=1, le=31)] = 3


AnyStep = Union[Gamma, Clahe, Stretch, Blur]  # in the order the detector documents them
STEPS: dict[str, type[Step]] = {str(t.__struct_config__.tag): t for t in typing.get_args(AnyStep)}

def make_step(op: str, settings: Mapping[str, Any]) -> AnyStep:
    """The step ``op`` with ``settings`` (checked by the caller: :func:`read_settings` or the importer)."""
    return typing.cast(AnyStep, STEPS[op](**settings))


# A parameter of cv2.aruco.DetectorParameters (OpenCV says which names and types; CORNER_REFINE_* by name).
ParameterValue = Union[bool, int, float, str]


class DetectorSettings(Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A marker detector's ``config_json``: ArUco dictionary, pre-processing steps in order, detector parameters."""

    dictionary: str = DEFAULT_DICTIONARY
    preprocess: list[AnyStep] = []
    parameters: dict[str, ParameterValue] = {}

    def to_json(self) -> str:
        return json.dumps(msgspec.to_builtins(self))

    def steps(self) -> tuple[tuple[str, tuple[tuple[str, Any], ...]], ...]:
        """Each step as ``(op, ((setting, value), ...))``, settings in the table's order."""
        return tuple((str(s.__struct_config__.tag), tuple((k, getattr(s, k)) for k in OPS[str(s.__struct_config__.tag)]))
                     for s in self.preprocess)


@dataclass(frozen=True, kw_only=True)
class Setting:
    """One setting of a step: its type, default and inclusive range."""

    kind: type  # int or float
    default: float
    low: float
    high: float
    odd: bool = False  # a kernel size: odd numbers only

    def problem(self, value: object) -> str | None:
        """What is wrong with ``value`` in words ("must be int, not 2.5"), or None."""
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (
                self.kind is int and value != int(value)):
            return f"must be {self.kind.__name__}, not {value!r}"
        if not math.isfinite(value) or not self.low <= value <= self.high:
            return f"{value} is outside [{self.low:g}, {self.high:g}]"
        if self.odd and int(value) % 2 == 0:
            return f"must be odd, not {value}"
        return None


def _settings(cls: type[Step]) -> dict[str, Setting]:
    from msgspec import inspect as mi

    info = mi.type_info(cls)
    assert isinstance(info, mi.StructType)
    out = {}
    for f in info.fields:
        t = f.type
        assert isinstance(t, (mi.IntType, mi.FloatType)) and t.ge is not None and t.le is not None, f.name
        out[f.name] = Setting(kind=int if isinstance(t, mi.IntType) else float, default=f.default, low=t.ge, high=t.le,
                              odd=f.name in cls.ODD)
    return out


# op -> {setting: Setting}, from the Structs above, in the order the detector documents them.
OPS: dict[str, dict[str, Setting]] = {op: _settings(cls) for op, cls in STEPS.items()}


DICTIONARY_FILE_SUFFIXES = (".yml", ".yaml")


def is_dictionary_file(name: str) -> bool:
    """Whether a ``dictionary`` setting names a file of OpenCV's dictionary format rather than a DICT_* name."""
    return name.lower().endswith(DICTIONARY_FILE_SUFFIXES)


def read_settings(data: object, where: str, *, dictionary: str | None = None) -> DetectorSettings:
    """Check a decoded ``config_json``; ConfigError starting with ``where`` says what is wrong.

    A missing setting takes its default, a missing dictionary ``dictionary`` (the
    component's own property) or DICT_4X4_50. OpenCV's own checks (does the
    dictionary exist, does DetectorParameters have the parameter) are the detector's.
    """
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: config_json must be an object, not {type(data).__name__}")
    unknown = sorted(set(data) - {f.name for f in msgspec.structs.fields(DetectorSettings)})
    if unknown:
        raise ConfigError(f"{where}: unknown key {unknown[0]!r} (use dictionary, preprocess, parameters)")
    dict_name = data.get("dictionary") or dictionary or DEFAULT_DICTIONARY
    if not isinstance(dict_name, str):
        raise ConfigError(f"{where}: dictionary must be a name such as DICT_4X4_50")
    steps = data.get("preprocess") or []
    if not isinstance(steps, list):
        raise ConfigError(f"{where}: preprocess must be a list of {{op: ...}} objects")
    preprocess = []
    for i, step in enumerate(steps):
        if not isinstance(step, Mapping) or not isinstance(step.get("op"), str):
            raise ConfigError(f"{where}: preprocess[{i}] must be an object with an 'op'")
        op = step["op"]
        spec = OPS.get(op)
        if spec is None:
            raise ConfigError(f"{where}: preprocess[{i}] has unknown op {op!r} (use {', '.join(OPS)})")
        for key in step:
            if key != "op" and key not in spec:
                raise ConfigError(f"{where}: preprocess[{i}] op {op!r} has no argument {key!r} (use {', '.join(spec)})")
        args: dict[str, Any] = {}
        for key, setting in spec.items():
            value = step.get(key, setting.default)
            problem = setting.problem(value)
            if problem:
                raise ConfigError(f"{where}: preprocess[{i}] {op}.{key} {problem}")
            args[key] = setting.kind(value)
        preprocess.append(make_step(op, args))
    params = data.get("parameters") or {}
    if not isinstance(params, Mapping):
        raise ConfigError(f"{where}: parameters must be an object of cv2.aruco.DetectorParameters attributes")
    try:
        # The steps are checked above with the table's words; this checks the rest's types once more.
        return msgspec.convert({"dictionary": dict_name, "preprocess": msgspec.to_builtins(preprocess),
                                "parameters": dict(params)}, DetectorSettings)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{where}: {exc}") from exc
