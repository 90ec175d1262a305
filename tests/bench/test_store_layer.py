"""``kgadapt bench store-layer`` runs end to end on a real embedded FalkorDB and names every part it timed.

Functional only: no timing is asserted (the figures go to bench/results/store_layer.json).
"""

from __future__ import annotations

import json
import subprocess
import sys


def test_a_small_run_times_each_op_and_each_part_of_the_layer(tmp_path):
    out = tmp_path / "store_layer.json"
    done = subprocess.run([sys.executable, "-m", "kgadapt", "bench", "store-layer", "--n", "10", "--reps", "5",
                           "--warmup", "1", "--out", str(out)], capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr
    result = json.loads(out.read_text())
    assert {r["op"] for r in result["records"]} == {"query_bare", "query_execute", "query_named", "insert_bare",
                                                    "insert"}
    assert all(r["reps"] == 5 and r["n"] == 10 for r in result["records"])
    parts = result["parts_us_p50"]
    assert any("read-only guard" in name and "before" in name for name in parts)
    assert all(value >= 0 for value in parts.values()) and len(parts) == 7
    assert set(result["ratios_p50"]) == {"query_named/query_bare", "query_execute/query_bare", "insert/insert_bare"}
    assert "query_named/query_bare" in done.stdout and "load average" in done.stdout
