"""One site file for the confirmer and the landing targets (onboard/site.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kgadapt.cli import build_parser
from kgadapt.onboard.confirmation import ConfirmationSettings, MarkerConfirmer
from kgadapt.onboard.landing_targets import CameraModel, TargetBuilder, load_site_markers
from kgadapt.onboard.site import load_site
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


@pytest.mark.parametrize("flag", ["--site", "--markers"])
def test_the_bridge_takes_the_site_file_under_either_flag(flag):
    args = build_parser().parse_args(["flight", "bridge", "--robot", "r", "--url", "udpin:0.0.0.0:14550",
                                      "--camera-file", "c.json", flag, str(DEMO)])
    assert args.site == str(DEMO)
