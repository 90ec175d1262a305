"""The short soak: the whole robot across namespaces under seeded random faults, invariants every second.

``kgadapt bench soak --minutes 3`` as a test (bench/soak_bench.py): kill -9 of
the store, the agents (restarted as systemd would) and detectors, link cuts,
memory squeezes and forged statuses, at random, for 3 minutes. It fails on any
invariant violation (two detectors beyond the handover bound, detections
missing outside a fault's explained window, graph and processes disagreeing
beyond their bound, a placement on the remote host no squeeze explains), on a
lost acknowledged write, or a long-running process gone at the end.
"""

from __future__ import annotations

import pytest

from kgadapt.bench.soak_bench import Soak, SoakSettings

pytestmark = [pytest.mark.netns, pytest.mark.slow]


@pytest.mark.timeout(540)  # 3 minutes of soak, plus the robot's start and stop on a loaded machine
def test_three_minutes_of_random_faults_break_no_invariant(tmp_path, needs_namespaces):
    lines: list[str] = []
    report = Soak(SoakSettings(minutes=3.0, seed=18, warmup_s=60.0, subnet="10.213.11"), tmp_path / "soak",
                  lines.append).run()
    log = "\n".join(lines)
    faults = report["faults"]
    assert faults["total"] - faults["failed_to_inject"] >= 9, log
    assert report["violations"]["total"] == 0, log
    assert report["writes"]["acked"] >= 90 and report["writes"]["lost"] == 0, report["writes"]
    assert all(report["processes_alive_at_end"].values()), report["processes_alive_at_end"]
