"""Site models (``*.site``) in the graph: loaded with the other models, checked at load time, all or nothing."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from kgadapt.knowledge.loader import load_models
from kgadapt.knowledge.queries import run_named
from kgadapt.onboard.flight.site import site_from_rows
from kgadapt.shared.errors import ModelError
from tests.conftest import REPO

from .conftest import signature

SHIPPED = REPO / "knowledge" / "models"


def _site(path: Path, markers: list[dict], **top: object) -> Path:
    lines = ",\n".join(f"    {json.dumps(m)}" for m in markers)
    head = "".join(f'  "{k}": {json.dumps(v)},\n' for k, v in top.items())
    path.write_text("{\n" + head + '  "markers": [\n' + lines + "\n  ]\n}\n")
    return path


def test_the_shipped_site_is_loaded_and_the_named_query_gives_its_markers(resp_store):
    load_models(resp_store, [SHIPPED])
    rows = run_named(resp_store, "site_markers", {})
    site = site_from_rows(rows)
    assert site is not None and site.site == "demo-hall" and site.dictionary == "DICT_4X4_50"
    assert site.sizes_m == {3: 0.24, 7: 0.18, 12: 0.2, 21: 0.16, 33: 0.26, 42: 0.13}
    assert site.names[3] == "pad 3"
    assert run_named(resp_store, "site_markers", {"site": "demo-hall"}) == rows
    assert run_named(resp_store, "site_markers", {"site": "no-such-site"}) == []


def test_names_dictionaries_and_positions_reach_the_graph_and_a_reload_replaces_them(resp_store, tmp_path):
    path = _site(tmp_path / "pad.site", [{"id": 7, "size_m": 0.3, "name": "pad A", "position": [1.0, 2.0, 0.0]},
                                         {"id": 100, "size_m": 0.5, "dictionary": "DICT_6X6_250"}])
    load_models(resp_store, [path])
    site = site_from_rows(run_named(resp_store, "site_markers", {"site": "pad"}))
    assert site.names == {7: "pad A"} and site.positions == {7: (1.0, 2.0, 0.0)}
    assert site.dictionary_of(100) == "DICT_6X6_250" and site.dictionary_of(7) == "DICT_4X4_50"
    _site(path, [{"id": 8, "size_m": 0.2}])
    load_models(resp_store, [path])
    assert site_from_rows(run_named(resp_store, "site_markers", {})).sizes_m == {8: 0.2}  # 7 and 100 are gone


@pytest.mark.parametrize("markers, top, line, words", [
    ([{"id": 7, "size_m": 0.3}], {"dictionary": "DICT_4X4_5O"}, 2, "unknown ArUco dictionary 'DICT_4X4_5O'"),
    ([{"id": 7, "size_m": 0.3}, {"id": 8, "size_m": 0.3, "dictionary": "DICT_5X5"}], {}, 4, "'DICT_5X5'"),
    ([{"id": 7, "size_m": 0.3}, {"id": 7, "size_m": 0.2}], {}, 4, "id 7 listed twice"),
    ([{"id": 7, "size_m": 0.3}, {"id": 8, "size_m": -0.2}], {}, 4, "size_m must be positive"),
    ([{"id": 7, "size_m": 0.3}, {"id": 60, "size_m": 0.2}], {}, 4, "id 60 is not in dictionary 'DICT_4X4_50'"),
])
def test_a_bad_site_is_refused_naming_file_and_line_and_nothing_is_written(resp_store, tmp_path, markers, top,
                                                                          line, words):
    models = tmp_path / "models"
    shutil.copytree(SHIPPED, models)
    load_models(resp_store, [models])
    before = signature(resp_store)
    _site(models / "sites" / "demo.site", markers, **top)
    with pytest.raises(ModelError) as info:
        load_models(resp_store, [models])
    assert str(info.value).startswith(f"{models / 'sites' / 'demo.site'}:{line}: "), info.value
    assert words in str(info.value)
    assert signature(resp_store) == before  # all or nothing: the old site and every other model stay


def test_knowledge_load_refuses_a_misspelt_dictionary_naming_file_and_line(kgadapt_cmd, tmp_path):
    bad = _site(tmp_path / "hall.site", [{"id": 7, "size_m": 0.3}], site="hall", dictionary="DICT_4X4_5O")
    done = subprocess.run([*kgadapt_cmd, "knowledge", "load", str(bad), "--store", f"embedded:{tmp_path / 'store'}"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert f"{bad}:3: " in done.stderr and "DICT_4X4_5O" in done.stderr, done.stderr
