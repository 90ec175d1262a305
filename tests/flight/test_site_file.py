"""One site file for the confirmer and the landing targets (onboard/flight/site.py)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from kgadapt.cli import build_parser
from kgadapt.onboard.flight.confirmation import ConfirmationSettings, MarkerConfirmer
from kgadapt.onboard.flight.landing_targets import CameraModel, TargetBuilder, load_site_markers
from kgadapt.onboard.flight.site import load_site
from kgadapt.shared.errors import ModelError

DEMO = Path(__file__).resolve().parents[2] / "knowledge" / "models" / "sites" / "demo.site"
SQUARE = [[300.0, 220.0], [340.0, 220.0], [340.0, 260.0], [300.0, 260.0]]


def test_the_shipped_site_gives_the_confirmer_its_ids_and_the_targets_their_sizes():
    site = load_site(DEMO)
    assert load_site_markers is load_site  # the flight side's name for the same loader
    assert (site.site, site.dictionary) == ("demo-hall", "DICT_4X4_50")
    confirmer = MarkerConfirmer(ConfirmationSettings(site=site, frames=1))
    assert confirmer.update([33, 34], [SQUARE, SQUARE], 1.0) == [0]  # 34 is not at the site
    builder = TargetBuilder(CameraModel(fx=615.0, fy=615.0, cx=320.0, cy=240.0, width=640, height=480), site)
    assert builder.markers.size_of(33) == 0.26 and builder.markers.size_of(34) is None


def test_names_are_kept_and_unknown_keys_are_refused(tmp_path):
    path = tmp_path / "pad.site"
    path.write_text(json.dumps({"markers": [{"id": 7, "size_m": 0.3, "name": "pad A"}]}))
    site = load_site(path)
    assert (site.site, site.names, site.ids) == ("pad", {7: "pad A"}, {7})  # the site is named after its file
    path.write_text(json.dumps({"markers": [{"id": 7, "size_m": 0.3}], "marker_size": 0.3}))
    with pytest.raises(ModelError, match="unknown key 'marker_size'") as info:
        load_site(path)
    assert "pad.site" in str(info.value)


@pytest.mark.parametrize("command", [["flight", "bridge", "--robot", "r"], ["onboard"]])
def test_one_site_option_for_the_bridge_and_the_agent(command):
    args = build_parser().parse_args([*command, "--site", str(DEMO), "--site-name", "demo-hall"])
    assert (args.site, args.site_name) == (str(DEMO), "demo-hall")
    for old in ("--markers", "--fc-markers"):  # the one format replaced them
        with pytest.raises(SystemExit):
            build_parser().parse_args([*command, old, str(DEMO)])


def test_a_site_file_with_a_misspelt_dictionary_is_refused_naming_file_and_line(tmp_path):
    path = tmp_path / "hall.site"
    path.write_text('{"site": "hall",\n "dictionary": "DICT_4X4_5O",\n "markers": [{"id": 7, "size_m": 0.3}]}')
    with pytest.raises(ModelError, match=r"hall\.site:2: .*'DICT_4X4_5O'"):
        load_site(path)
    path.write_text('{"site": "hall",\n "markers": [\n  {"id": 7, "size_m": 0.3},\n'
                    '  {"id": 9, "size_m": 0.3, "dictionary": "DICT_6X6_25O"}]}')
    with pytest.raises(ModelError, match=r"hall\.site:4: .*'DICT_6X6_25O'"):
        load_site(path)


@pytest.mark.parametrize("command", [["onboard", "--host", "onboard", "--fc", "udpin:127.0.0.1:9"],
                                     ["flight", "bridge", "--robot", "r", "--camera-file", "c.json"]])
def test_the_agent_and_the_bridge_refuse_a_misspelt_dictionary_before_starting(kgadapt_cmd, tmp_path, command):
    bad = tmp_path / "pad.site"
    bad.write_text('{"site": "pad",\n "dictionary": "DICT_4X4_5O",\n "markers": [{"id": 7, "size_m": 0.3}]}')
    (tmp_path / "c.json").write_text(json.dumps({"fx": 600, "fy": 600, "cx": 320, "cy": 240}))
    done = subprocess.run([*kgadapt_cmd, *command, "--site", str(bad)], cwd=tmp_path, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 1 and f"{bad}:2: " in done.stderr and "DICT_4X4_5O" in done.stderr, done.stderr


def test_a_site_says_how_its_markers_are_printed_and_a_misspelt_layout_is_refused_naming_file_and_line(tmp_path):
    from kgadapt.knowledge.importers.site_model import parse

    path = tmp_path / "board.site"
    text = ('{"site": "board",\n "dictionary": "DICT_ARUCO_MIP_36h12",\n "layout": "touching",\n'
            ' "markers": [{"id": 1, "size_m": 0.022}, {"id": 3, "size_m": 0.022}]}')
    path.write_text(text)
    assert load_site(path).layout == "touching"
    assert load_site(DEMO).layout == "apart"  # a site that does not say prints its markers apart
    board = load_site(Path(__file__).resolve().parents[2] / "sim" / "photographs" / "charuco2_board.site")
    assert (board.layout, board.dictionary, len(board.ids)) == ("touching", "DICT_ARUCO_MIP_36h12", 23)
    # The model loader reads the same file: the layout is the Site node's, beside its dictionary.
    site_node = next(n for n in parse(text, str(path)).nodes if n.name == "board")
    assert site_node.props == {"dictionary": "DICT_ARUCO_MIP_36h12", "layout": "touching"}
    for wrong in ('"touchng"', '["touching"]', "0.1"):
        path.write_text(text.replace('"touching"', wrong))
        with pytest.raises(ModelError, match=r"board\.site:3: 'layout' must be one of apart, chessboard, touching"):
            load_site(path)
        with pytest.raises(ModelError, match=r"board\.site:3: 'layout'"):
            parse(path.read_text(), str(path))
