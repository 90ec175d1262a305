"""``kgadapt bench zenoh`` runs end to end on a real service, store and echo, and writes its records.

Functional only: no timing is asserted here (the figures go to bench/results/).
"""

from __future__ import annotations

import json
import subprocess
import sys

OPS = {"zenoh_bare", "zenoh_queued", "rpc_queued", "store_trivial", "zenoh_trivial", "store_named", "zenoh_named",
       "status_lag"}


def test_a_small_run_writes_every_op_with_the_load_it_ran_at_and_stops_its_children_quietly(tmp_path):
    out = tmp_path / "zenoh.json"
    done = subprocess.run([sys.executable, "-m", "kgadapt", "bench", "zenoh", "--reps", "5", "--warmup", "1",
                           "--hosts", "2", "--probe-hosts", "1", "--duration", "2", "--out", str(out)],
                          capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr
    records = json.loads(out.read_text())
    assert {r["op"] for r in records} == OPS
    for record in records:
        before, after = record["loadavg_1m"]  # what the report's load column reads
        assert before >= 0 and after >= 0
        assert record["min_ms"] <= record["p50_ms"] <= record["max_ms"], record["op"]
    # The echo and the service are stopped with SIGINT first: neither prints a traceback for it.
    assert "Traceback" not in done.stderr + done.stdout
