"""A failover without a warm standby, with the launchers' pool: the surviving host's idle detector takes it.

Issue 32 item 1. The whole robot in real processes (kgadapt/operator/cluster.py), remote-first, no
standby, both agents with ``--pool 1``: the onboard deployer keeps an idle detector for the kinds of
start the graph lets run onboard from the moment its launcher is ready, though nothing was started
there; ``kill -9`` of the remote agent running the detector then hands the move planned ahead for
that loss to this idle detector. It is no fork, and the process asks the graph nothing: its
configuration came with the start, its reflex table was prepared while it waited.
"""

from __future__ import annotations

import signal
import time

import pytest

from kgadapt.deploy.client import DeployerClient
from tests.adaptation.test_adaptation_e2e import Run
from tests.adaptation.test_standby import decision_inputs, detectors

pytestmark = pytest.mark.slow

DUSK = "marker_detection_dusk"


def idle_members(deployers: DeployerClient, host: str) -> list[int]:
    launcher = deployers.launchers(host).get(host)
    return list(launcher.idle_members or []) if launcher is not None else []


def test_a_failover_without_a_standby_takes_the_idle_detector_the_surviving_host_kept(tmp_path):
    pool = ("--pool", "1")
    with Run(tmp_path, [[0, 16], [120, 16]], prefer="remote-first", extra_onboard_args=pool,
             extra_remote_args=pool) as run:
        first = run.wait_for(run.decision("startup"), 40, "the first detector")
        deployers = DeployerClient(run.session, "quad1", timeout=20.0)
        idle = run.wait_for(lambda: idle_members(deployers, "onboard"), 60, "an idle detector onboard")
        started_onboard = detectors(run, "onboard")
        # The manager plans the move for the remote host's loss in its quiet moments (every ready_move_s).
        run.wait_for(lambda: time.time() > first.time + 5.0, 10, "the move for a loss planned ahead")
        run.cluster.kill("remote", signal.SIGKILL)
        lost = run.wait_for(run.decision("host_lost"), 30, "the lost host")
        run.wait_for(lambda: (DUSK, "onboard") in run.running(lost.time), 30, "dusk detections onboard")
        taken = deployers.status("onboard", lost.instance)
        inputs = decision_inputs(run, "host_lost")

    assert (first.config, first.host) == (DUSK, "remote"), first
    assert started_onboard == {}, "the idle detector was kept before anything started onboard"
    assert (lost.config, lost.host) == (DUSK, "onboard") and lost.outcome.startswith("started"), lost
    assert "planned_ahead_ms" in inputs, inputs
    # The idle detector took the start: no fork, no new interpreter.
    assert taken.via == "pool" and taken.pid in idle, (taken.via, taken.pid, idle)
    output = "\n".join(taken.output or [])
    assert (f"configuration {DUSK} carried by the start request; reflex table prepared in the launcher's pool"
            in output), output
