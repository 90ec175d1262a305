"""Which running detector may take which configuration in place: knowledge in the deployment models.

The shipped models on a real FalkorDB, asked with the named query the adaptation
manager and the detector ask (``in_place_change``).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.importers import deployment_file, systemd
from kgadapt.knowledge.loader import load_models
from kgadapt.knowledge.queries import run_named
from kgadapt.shared.errors import ModelError

MODELS = Path(S.__file__).resolve().parent / "models"


def test_same_family_on_a_host_both_run_on_may_change_in_place_and_nothing_else(resp_store, tmp_path):
    extra = tmp_path / "extra"
    extra.mkdir()
    # The same program, but its model does not say it can be reconfigured: a new process every time.
    (extra / "detector_plain.deploy").write_text(
        "deploys: marker_detection_dusk\nexecutable: {python}\n"
        "arguments: -m kgadapt.onboard.perception.detector --config {config}\n"
        "executable_on: onboard\n")
    load_models(resp_store, [MODELS, extra])

    def may(a: str, b: str, host: str) -> bool:
        return bool(run_named(resp_store, "in_place_change", {"from": a, "to": b, "host": host}))

    assert may("detector_day", "detector_dark", "onboard")  # .service to .service
    assert may("detector_dark", "detector_dusk", "remote")  # .service to .deploy: the family counts, not the notation
    assert may("detector_hd", "detector_day", "remote")
    assert not may("detector_day", "detector_hd", "onboard")  # hd is not executable onboard
    assert not may("detector_day", "detector_plain", "onboard")  # no family declared
    assert not may("detector_plain", "detector_day", "onboard")
    assert not may("detector_day", "flight_control", "onboard")
    row = run_named(resp_store, "in_place_change", {"from": "detector_day", "to": "detector_dark", "host": "onboard"})[0]
    assert row["family"] == "marker-detector"


@pytest.mark.parametrize("parse, text, match", [
    (systemd.parse, "[Service]\nExecStart=/bin/true\n[X-Kgadapt]\nDeploys=g\nExecutableOn=a\n"
                    "ReconfigurableAs=x\nReconfigurableAs=y\n", "ReconfigurableAs= given twice"),
    (systemd.parse, "[Service]\nExecStart=/bin/true\n[X-Kgadapt]\nDeploys=g\nExecutableOn=a\n"
                    "ReconfigurableAs=two words\n", "not a valid name"),
    (deployment_file.parse, "deploys: g\nexecutable: /bin/true\nexecutable_on: a\nreconfigurable_as: a/b\n",
     "not a valid name"),
])
def test_a_bad_family_is_refused_naming_the_line(parse, text, match):
    with pytest.raises(ModelError, match=match):
        parse(text, "x.service")
