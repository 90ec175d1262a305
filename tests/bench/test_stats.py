"""The shared timing helpers compute what their names say."""

from __future__ import annotations

import json

import pytest

from kgadapt.bench.stats import format_table, make_record, percentile, read_records, summarize, time_calls, write_records
from kgadapt.shared.errors import ConfigError


def test_percentiles_interpolate_between_ranks():
    samples = [4.0, 1.0, 3.0, 2.0, 5.0]
    assert percentile(samples, 50) == 3.0
    assert percentile(samples, 0) == 1.0
    assert percentile(samples, 100) == 5.0
    assert percentile(samples, 25) == 2.0
    assert percentile([1.0, 2.0], 99) == pytest.approx(1.99)


def test_a_summary_has_the_sample_standard_deviation():
    s = summarize([2.0, 4.0, 4.0, 4.0, 5.0, 5.0, 7.0, 9.0])
    assert s.mean_ms == 5.0
    assert s.sd_ms == pytest.approx(2.138, abs=1e-3)
    assert (s.min_ms, s.max_ms, s.count) == (2.0, 9.0, 8)


def test_one_sample_summarizes_with_zero_spread_and_none_is_refused():
    assert summarize([1.5]).sd_ms == 0.0
    with pytest.raises(ValueError):
        summarize([])


def test_timing_calls_runs_warmup_untimed_and_returns_one_sample_per_rep():
    calls = []
    samples = time_calls(lambda: calls.append(1), 7, warmup=2)
    assert len(calls) == 9
    assert len(samples) == 7 and all(s >= 0 for s in samples)
    with pytest.raises(ConfigError):
        time_calls(lambda: None, 0)


def test_records_round_trip_through_json_and_incomplete_ones_are_refused(tmp_path):
    record = make_record(store="s", n=10, op="query", samples_ms=[1.0, 2.0, 3.0], extra_field="x")
    path = write_records(tmp_path / "r" / "out.json", [record])
    assert read_records(path) == [record]
    assert record["p50_ms"] == 2.0 and record["reps"] == 3 and record["extra_field"] == "x"
    with pytest.raises(ValueError, match="p99_ms"):
        write_records(tmp_path / "bad.json", [{k: v for k, v in record.items() if k != "p99_ms"}])


def test_reading_a_file_that_is_not_a_list_of_records_names_the_file(tmp_path):
    path = tmp_path / "x.json"
    path.write_text(json.dumps({"not": "a list"}))
    with pytest.raises(ConfigError, match="x.json"):
        read_records(path)


def test_tables_align_and_render_as_markdown():
    text = format_table([[10, 0.4321, None], [10000, 12.5, "x"]], ["N", "ms", "note"])
    lines = text.splitlines()
    assert len({len(line) for line in lines}) == 1
    assert "10,000" in text and "0.432" in text and "-" in lines[2]
    md = format_table([[1, 2.0]], ["a", "b"], markdown=True)
    assert md.splitlines()[0] == "| a | b |" and md.splitlines()[2] == "| 1 | 2.000 |"
