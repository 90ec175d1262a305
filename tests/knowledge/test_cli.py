"""``kgadapt knowledge ...`` and ``kgadapt demo`` as a user runs them: real processes, a real embedded store."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from kgadapt.knowledge import runtime as R
from kgadapt.knowledge.queries import QUERIES
from kgadapt.knowledge.store import open_store

from .conftest import KNOWN

REPO = Path(__file__).resolve().parents[2]


def kgadapt(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "KGADAPT_STORE"}
    return subprocess.run([sys.executable, "-m", "kgadapt", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture
def cli_store(tmp_path):
    """An embedded store this test owns; the commands find it running and leave it running."""
    store = open_store(f"embedded:{tmp_path / 'store'}")
    store.setup()
    yield store
    store.shutdown()


def _one_line_error(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 1, (result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("kgadapt: error: "), result.stderr
    return lines[0]


def test_placement_answers_after_loading_the_shipped_models(cli_store):
    url = cli_store.url
    loaded = kgadapt("knowledge", "load", "knowledge/models", "--store", url)
    assert loaded.returncode == 0, loaded.stderr
    shipped = sum(1 for path in Path("knowledge/models").rglob("*") if path.is_file())  # every file is a model
    assert f"loaded {shipped} model files" in loaded.stdout and "PerceptionGraph" in loaded.stdout
    empty = kgadapt("knowledge", "query", "placement", "--param", "feature=MarkerDetection", "--store", url)
    assert empty.returncode == 0 and "(no rows: no platform is online yet" in empty.stdout  # no live figures yet
    R.update_platform(cli_store, name="onboard", time=1.0, memory_free_mb=200.0, online=True)
    R.update_platform(cli_store, name="remote", time=1.0, memory_free_mb=1000.0, online=True)
    result = kgadapt("knowledge", "query", "placement", "--param", "feature=MarkerDetection", "--json", "--store", url)
    assert result.returncode == 0, result.stderr
    rows = json.loads(result.stdout)
    # demands: day 24+48 = 72, dusk 24+96 = 120, dark 24+300 = 324, hd 56+120 = 176 (remote only)
    assert {(r["config"], r["platform"], r["demand_mb"]) for r in rows} == {
        ("marker_detection_day", "onboard", 72), ("marker_detection_dusk", "onboard", 120),
        ("marker_detection_day", "remote", 72), ("marker_detection_dusk", "remote", 120),
        ("marker_detection_dark", "remote", 324), ("marker_detection_hd", "remote", 176)}
    table = kgadapt("knowledge", "query", "placement", "-p", "config=marker_detection_dark", "--store", url)
    assert table.returncode == 0 and "detector_dark" in table.stdout and "onboard" not in table.stdout


def test_load_prints_counts_as_json(cli_store):
    result = kgadapt("knowledge", "load", str(KNOWN), "--json", "--store", cli_store.url)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["labels"]["Deployment"] == 5 and report["relations"]["CONTAINS"] == 7 and report["written"]


def test_a_check_with_a_store_resolves_names_an_earlier_load_defined_as_the_load_would(cli_store, tmp_path):
    assert kgadapt("knowledge", "load", str(KNOWN), "--store", cli_store.url).returncode == 0
    extra = tmp_path / "d_new.deploy"
    extra.write_text("deploys: g_b\nexecutable: /bin/true\nexecutable_on: alpha\n")
    alone = kgadapt("knowledge", "load", "--check", str(extra))  # no store: only these files count
    assert alone.returncode == 1 and "g_b" in alone.stderr
    checked = kgadapt("knowledge", "load", "--check", str(extra), "--store", cli_store.url)
    assert checked.returncode == 0, checked.stderr
    assert cli_store.execute("MATCH (d:Deployment {name: 'd_new'}) RETURN d") == []  # a check writes nothing


def test_a_bad_model_fails_the_load_with_one_line_naming_file_and_line(cli_store, tmp_path):
    bad = tmp_path / "broken.rpsl"
    bad.write_text('rpsl.processing_component do\n  name "x"\n  memory_demand_mb -1\nend\n')
    line = _one_line_error(kgadapt("knowledge", "load", str(bad), "--store", cli_store.url))
    assert f"{bad}:3: memory_demand_mb: memory_demand_mb must not be negative" in line


def test_cypher_refuses_a_write_with_exit_1_and_one_line(cli_store):
    cli_store.execute("CREATE (:Keep {name: 'k'})")
    line = _one_line_error(kgadapt("knowledge", "cypher", "MATCH (n) DETACH DELETE n", "--store", cli_store.url))
    assert "read-only" in line and "DETACH" in line
    assert cli_store.execute("MATCH (n:Keep) RETURN count(n) AS c")[0]["c"] == 1


def test_cypher_reads_with_parameters(cli_store):
    cli_store.execute("CREATE (:Keep {name: 'k', n: 3})")
    result = kgadapt("knowledge", "cypher", "MATCH (k:Keep) WHERE k.n > $n RETURN k.name AS name",
                     "--param", "n=2", "--json", "--store", cli_store.url)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == [{"name": "k"}]


def test_queries_lists_every_named_query_with_its_parameters():
    result = kgadapt("knowledge", "queries", "--json")
    assert result.returncode == 0, result.stderr
    listed = {row["name"]: row["params"] for row in json.loads(result.stdout)}
    assert set(listed) == set(QUERIES)
    assert listed["low_memory_components"] == "feature: str = MarkerDetection, threshold_mb: float"


def test_a_query_with_an_unknown_parameter_fails_with_one_line(cli_store):
    line = _one_line_error(kgadapt("knowledge", "query", "placement", "--param", "colour=red", "--store", cli_store.url))
    assert "'placement' has no parameter 'colour'" in line


def test_export_writes_cypher_to_a_file_and_dot_to_standard_output(cli_store, tmp_path):
    assert kgadapt("knowledge", "load", str(KNOWN), "--store", cli_store.url).returncode == 0
    out = tmp_path / "graph.cypher"
    result = kgadapt("knowledge", "export", "--format", "cypher", "-o", str(out), "--store", cli_store.url)
    assert result.returncode == 0, result.stderr
    assert out.read_text().count("\nCREATE (") == 27  # the known models' nodes
    dot = kgadapt("knowledge", "export", "--format", "dot", "--store", cli_store.url)
    assert dot.returncode == 0 and dot.stdout.startswith("digraph kgadapt {") and dot.stdout.count(" -> ") == 34


@pytest.mark.parametrize("args", [
    ("knowledge",), ("knowledge", "load"), ("knowledge", "query"), ("knowledge", "queries"),
    ("knowledge", "cypher"), ("knowledge", "export"), ("knowledge", "import"), ("demo",),
])
def test_every_subcommand_has_help_with_a_store_option(args):
    result = kgadapt(*args, "--help")
    assert result.returncode == 0, result.stderr
    assert "usage: kgadapt" in result.stdout
    if args != ("knowledge",):
        assert "--store" in result.stdout


def test_the_demo_answers_the_papers_queries(tmp_path):
    result = kgadapt("demo", "--queries", "--store", f"embedded:{tmp_path / 'demo'}", timeout=120)
    assert result.returncode == 0, result.stderr
    for title in ("Fig. 4", "Fig. 5 / placement", "cameras of different resolutions", "CPU load", "below 100 MiB"):
        assert title in result.stdout
    # the CPU question onboard: camera 6 + aruco_dark 200 = 206,
    # plus flight control 120 = 326, above 80 % of 4 cores (320)
    rows = [line.split() for line in result.stdout.splitlines()
            if line.split()[:2] == ["marker_detection_dark", "onboard"]]
    assert ["marker_detection_dark", "onboard", "206", "120", "326", "320", "True"] in rows
