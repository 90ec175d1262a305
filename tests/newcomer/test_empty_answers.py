"""An empty answer says why, or is an error when the question names what is not there (issue 15).

Typed as a newcomer types them, on an embedded store of its own.
"""

from __future__ import annotations

import json
import subprocess
import sys

from tests.support import REPO


def kgadapt(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "kgadapt", *args], capture_output=True, text=True, timeout=120,
                          cwd=REPO)


def test_empty_answers_explain_themselves_and_mistakes_are_errors_naming_the_store(tmp_path):
    store = f"embedded:{tmp_path / 'store'}"
    typo = f"embedded:{tmp_path / 'stroe'}"
    nothing = kgadapt("knowledge", "query", "placement", "--store", store)
    assert nothing.returncode == 1 and nothing.stdout == ""
    assert f"store {store} holds no models: nothing is loaded there" in nothing.stderr
    assert kgadapt("knowledge", "load", "knowledge/models", "--store", store).returncode == 0

    placement = kgadapt("knowledge", "query", "placement", "--store", store)
    assert placement.returncode == 0 and placement.stdout.startswith("(no rows: no platform is online yet")

    misspelt = kgadapt("knowledge", "query", "placement", "-p", "config=marker_detection_darkk", "--store", store)
    assert misspelt.returncode == 1 and misspelt.stdout == ""
    assert "no detector configuration 'marker_detection_darkk'" in misspelt.stderr
    assert "known: marker_detection_blur, marker_detection_dark, marker_detection_day" in misspelt.stderr
    platform = kgadapt("knowledge", "query", "cpu_overload", "-p", "platform=onbord", "-p", "limit_pct=80",
                       "--store", store)
    assert platform.returncode == 1 and "no platform 'onbord'" in platform.stderr

    decisions = kgadapt("knowledge", "query", "decisions", "--json", "--store", store)
    assert decisions.returncode == 0 and json.loads(decisions.stdout) == []
    assert "no adaptation decision yet" in decisions.stderr

    new_store = kgadapt("knowledge", "cypher", "MATCH (p:Platform) RETURN p.name AS name", "--store", typo)
    assert new_store.returncode == 1 and f"store {typo} holds no models" in new_store.stderr
    real_empty = kgadapt("knowledge", "cypher", "MATCH (p:Platform) WHERE p.name = 'mars' RETURN p.name AS name",
                         "--store", store)
    assert real_empty.returncode == 0 and real_empty.stdout.strip() == "(no rows)"  # nothing to explain
