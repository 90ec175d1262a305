"""The detector configuration's schema (kgadapt.shared.preprocessing): the op table comes from the step Structs,
read_settings fills defaults and refuses what the detector would, and the importer writes what it reads."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kgadapt.knowledge.importers import parse_file
from kgadapt.shared.errors import ConfigError
from kgadapt.shared.preprocessing import OPS, STEPS, Blur, Clahe, ConfigJson, Gamma, Setting, read_settings

MODELS = Path(__file__).resolve().parent / "knowledge"


def test_the_op_table_is_the_step_structs_defaults_and_ranges():
    assert list(OPS) == list(STEPS) == ["gamma", "clahe", "stretch", "blur"]
    assert OPS["blur"] == {"ksize": Setting(kind=int, default=3, low=1, high=31, odd=True)}
    assert OPS["clahe"]["clip_limit"] == Setting(kind=float, default=2.0, low=0.1, high=100.0)
    for op, cls in STEPS.items():
        assert set(OPS[op]) == set(cls.__struct_fields__)
        assert cls() == cls(**{k: s.default for k, s in OPS[op].items()})  # every setting has its default


def test_read_settings_fills_defaults_and_types_the_steps():
    settings = read_settings({"preprocess": [{"op": "clahe", "tile": 4.0}, {"op": "gamma"}],
                              "parameters": {"adaptiveThreshConstant": 3}}, "c", dictionary="DICT_5X5_50")
    assert settings == ConfigJson(dictionary="DICT_5X5_50", preprocess=[Clahe(tile=4), Gamma()],
                                        parameters={"adaptiveThreshConstant": 3})
    assert type(settings.preprocess[0].tile) is int  # type: ignore[union-attr]
    assert settings.steps() == (("clahe", (("clip_limit", 2.0), ("tile", 4))), ("gamma", (("gamma", 1.0),)))
    assert read_settings(json.loads(settings.to_json()), "c") == settings  # what is written is read back


@pytest.mark.parametrize(("data", "words"), [
    ({"preprocess": [{"op": "blur", "ksize": 4}]}, "preprocess[0] blur.ksize must be odd"),
    ({"preprocess": [{"op": "sharpen"}]}, "preprocess[0] has unknown op 'sharpen'"),
    ({"preprocess": [{"op": "gamma", "gamma": 0.5, "strength": 2}]}, "has no argument 'strength'"),
    ({"parameters": {"minDistanceToBorder": [1, 2]}}, "parameters"),
    ({"thresholds": {}}, "unknown key 'thresholds'"),
    ([1], "must be an object"),
])
def test_read_settings_refuses_naming_the_place(data, words):
    with pytest.raises(ConfigError, match=r"^cfg: ") as info:
        read_settings(data, "cfg")
    assert words in str(info.value)


def test_the_importer_writes_config_json_through_the_schema():
    nodes = {n.name: n for n in parse_file(MODELS / "known_models" / "graphs.rpsl").nodes}
    written = json.loads(nodes["det_b"].props["config_json"])
    settings = read_settings(written, "det_b")
    assert settings.preprocess == [Gamma(gamma=0.5), Blur(ksize=3)]
    assert json.loads(settings.to_json()) == written
