"""The detector always comes back: whatever stops it, the manager notices and the planner's choice runs again.

The whole robot in real processes (kgadapt/operator/cluster.py). The detector is
stopped by an operator, migrated away by an operator, and kill -9'd until its
deployer gives up on it; after each, a detector of the planner's choice
answers again and exactly one runs.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from kgadapt.deploy.client import DeployerClient
from kgadapt.shared.messages import ProcessDetail
from kgadapt.shared.states import KEPT_STATES
from tests.adaptation.test_adaptation_e2e import Run

pytestmark = pytest.mark.slow


def _live(run: Run) -> list[ProcessDetail]:
    return [p for p in DeployerClient(run.session, "quad1").processes("*") if p.state in KEPT_STATES]


def _back_after(run: Run, gone: str, since: float) -> float:
    """Seconds from ``since`` to the first detection of an instance other than ``gone``."""
    t = run.wait_for(lambda: next((t for t, i, *_ in run.recorder.detections if t > since and i != gone), None),
                     10, f"detections from a detector other than {gone}")
    return t - since


def _one_detector(run: Run, host: str) -> ProcessDetail:
    def single():
        live = _live(run)
        return live[0] if len(live) == 1 and live[0].host == host and live[0].state in ("ready", "running") else None
    return run.wait_for(single, 10, f"exactly one detector, on {host}")


def test_a_stopped_migrated_or_failed_detector_is_replaced_by_the_planners_choice(tmp_path):
    figures = {}
    with Run(tmp_path, [[0, 120], [300, 120]]) as run:
        run.wait_for(run.decision("startup"), 20, "the first detector")
        first = _one_detector(run, "onboard")
        deployers = DeployerClient(run.session, "quad1")

        # 1. An operator stops it.
        stopped_at = time.time()
        deployers.stop("onboard", first.instance)
        figures["stop"] = _back_after(run, first.instance, stopped_at)
        gone = run.wait_for(run.decision("detector_gone"), 5, "the stop to be noticed")
        assert gone.host == "onboard" and gone.outcome.startswith("started")
        second = _one_detector(run, "onboard")
        assert second.instance != first.instance

        # 2. An operator migrates it away (docs/deploy.md); the planner wants it onboard: back it comes.
        moved_at = time.time()
        result = subprocess.run([sys.executable, "-m", "kgadapt", "deploy", "migrate", second.instance, "--to", "remote",
                                 "--connect", run.cluster.endpoint], capture_output=True, text=True, timeout=60)
        assert result.returncode == 0, result.stderr
        third = run.wait_for(lambda: next((p for p in _live(run) if p.host == "onboard"
                                           and p.instance != second.instance), None), 10, "a new onboard detector")
        figures["migrate"] = _back_after(run, second.instance, moved_at)
        third = _one_detector(run, "onboard")  # the migrated twin on the remote host is stopped

        # 3. kill -9 until its deployer gives up (state failed): not a dead end.
        killed = 0
        while True:
            status = deployers.status("onboard", third.instance)
            if status.state not in KEPT_STATES:
                break
            if status.state in ("ready", "running") and status.pid:
                try:
                    os.kill(int(status.pid), signal.SIGKILL)
                except ProcessLookupError:
                    pass  # the last one killed, reaped before its deployer's status said so: ask again
                else:
                    killed += 1
                    last_kill = time.time()
            time.sleep(0.1)
            if killed > 10:
                break
        assert status.state == "failed" or _live(run)[0].instance != third.instance, status
        figures["failed"] = _back_after(run, third.instance, last_kill)
        fourth = _one_detector(run, "onboard")
        assert fourth.instance != third.instance
        run.wait_for(lambda: [d.kind for d in run.recorder.decisions].count("detector_gone") >= 3, 5,
                     "the third detector_gone decision")
    print(f"detector back after: {', '.join(f'{k} {v * 1000:.0f} ms' for k, v in figures.items())}; "
          f"kill -9 x{killed}")
    assert not any(d.outcome.startswith("failed") for d in run.recorder.decisions), run.recorder.decisions
