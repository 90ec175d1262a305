"""``kgadapt bench table1`` runs end to end on real stores and writes well-formed results.

Functional only: no timing is asserted here (the figures go to bench/results/).
"""

from __future__ import annotations

import json
import subprocess

import pytest

from kgadapt.bench.table1 import OPS, PAPER

TIMED_OPS = {"floor", "insert", "insert_create", "sample", "sample_after_create", "query", "query_named"}
NUMBERS = ("mean_ms", "sd_ms", "p50_ms", "p99_ms")


def _run(cmd: list[str], *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([*cmd, "bench", "table1", *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """One small run on the two embedded servers: N = 10, 5 repetitions."""
    import sys

    out = tmp_path_factory.mktemp("table1")
    result = _run([sys.executable, "-m", "kgadapt"], "--n", "10", "--reps", "5", "--warmup", "1", "--fig5-reps", "1",
                  "--out", str(out / "table1.json"), "--markdown", str(out / "table1.md"))
    assert result.returncode == 0, result.stderr
    return out, result, json.loads((out / "table1.json").read_text())


def _check_shape(record: dict) -> None:
    assert isinstance(record["store"], str) and record["store"]
    assert isinstance(record["n"], int) and isinstance(record["op"], str)
    for key in NUMBERS:
        assert isinstance(record[key], (int, float)) and record[key] >= 0, (record["op"], key)
    assert record["min_ms"] <= record["p50_ms"] <= record["p99_ms"] <= record["max_ms"]


def test_a_small_run_times_every_op_on_both_embedded_stores(small_run):
    _, _, records = small_run
    for record in records:
        _check_shape(record)
    ops = {(r["store"], r["op"]) for r in records}
    assert {op for _, op in ops} <= set(OPS)
    for store in ("embedded", "embedded-nofsync"):
        assert {op for s, op in ops if s == store} >= TIMED_OPS | {"bulk_load"}
    assert ("embedded", "fig5_literal") in ops and ("embedded", "disk_fsync") in ops
    # the same statements sent bare, beside ours: what the store layer costs (issue 32)
    assert {("embedded", "query_bare"), ("embedded", "insert_bare")} <= ops
    timed = [r for r in records if r["op"] in TIMED_OPS]
    assert all(r["reps"] == 5 and r["n"] == 10 for r in timed)
    assert {r["durable"] for r in records if r["store"] == "embedded"} == {True}
    assert {r["durable"] for r in records if r["store"] == "embedded-nofsync"} == {False}


def test_the_loaded_graph_has_three_nodes_and_six_relations_per_model(small_run):
    _, _, records = small_run
    load = next(r for r in records if r["op"] == "bulk_load" and r["store"] == "embedded")
    # + Feature, camera and the two platforms shared by every model
    assert (load["nodes"], load["relationships"]) == (3 * 10 + 4, 6 * 10)


def test_the_literal_fig5_query_reports_rows_or_timeouts(small_run):
    _, _, records = small_run
    fig5 = next(r for r in records if r["op"] == "fig5_literal")
    assert fig5["reps"] == 1 and fig5["timeout_ms"] > 0
    assert fig5["timeouts"] == 1 or fig5["rows"] > 0


def test_the_paper_figures_are_printed_beside_ours_with_a_plot_and_markdown(small_run):
    out, result, _ = small_run
    assert "paper insert mean" in result.stdout and f"{PAPER[10]['insert'][0]:.1f}" in result.stdout
    assert (out / "table1.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    markdown = (out / "table1.md").read_text()
    assert "| 10 |" in markdown and "## Targets" in markdown


def test_the_report_regenerates_from_the_json_alone(small_run, kgadapt_cmd):
    out, _, records = small_run
    result = _run(kgadapt_cmd, "--from-json", str(out / "table1.json"), "--markdown", str(out / "again.md"), "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == records
    assert (out / "again.md").read_text() == (out / "table1.md").read_text()


def test_a_bolt_server_given_by_url_is_measured(bolt_server, kgadapt_cmd, tmp_path):
    url = f"bolt://127.0.0.1:{bolt_server.bolt_port}"
    result = _run(kgadapt_cmd, "--store", url, "--allow-clear", "--n", "10", "--reps", "3", "--warmup", "1",
                  "--fig5-reps", "1", "--out", str(tmp_path / "b.json"), "--markdown", "-")
    assert result.returncode == 0, result.stderr
    records = json.loads((tmp_path / "b.json").read_text())
    assert {r["store"] for r in records} == {url}
    assert {r["op"] for r in records} >= TIMED_OPS | {"bulk_load", "fig5_literal"}
    assert not (tmp_path / "b.md").exists()


def test_a_one_graph_server_is_not_cleared_without_consent(kgadapt_cmd, tmp_path):
    result = _run(kgadapt_cmd, "--store", "bolt://127.0.0.1:9", "--n", "10", "--out", str(tmp_path / "x.json"))
    assert result.returncode == 1
    assert "--allow-clear" in result.stderr and "bolt://127.0.0.1:9" in result.stderr
    assert not (tmp_path / "x.json").exists()


def test_a_bad_n_is_refused_naming_it(kgadapt_cmd, tmp_path):
    result = _run(kgadapt_cmd, "--n", "0", "--out", str(tmp_path / "x.json"))
    assert result.returncode == 1 and "--n 0" in result.stderr


def test_bench_help_lists_table1(kgadapt_cmd):
    result = subprocess.run([*kgadapt_cmd, "bench", "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "table1" in result.stdout
