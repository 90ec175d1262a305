"""A migration whose source host stops answering half-way leaves exactly one detector.

The soak's case (bench/results/soak_60min.json): a make-before-break migration
started the new detector, then the source's host was cut off, so stopping the
old one failed. The manager used to record the migration as failed and keep
believing in the old detector, while the new one ran on unknown to it: two
detectors for minutes. Here the remote agent is stopped (SIGSTOP) the moment
the migration's new detector starts onboard, and continued later.
"""

from __future__ import annotations

import os
import signal
import threading

import pytest

from kgadapt.deploy.client import DeployerClient
from kgadapt.shared import keys, messages
from kgadapt.shared.hostmonitor import squeeze
from kgadapt.shared.states import KEPT_STATES
from tests.adaptation.test_adaptation_e2e import Run

pytestmark = pytest.mark.slow


def test_a_migration_whose_source_host_is_cut_off_leaves_one_detector(tmp_path):
    with Run(tmp_path, [[0, 5], [600, 5]], prefer="remote-first") as run:  # dark: the 324 MiB detector
        first = run.wait_for(run.decision("startup"), 30, "the first detector")
        assert first.host == "remote"
        remote = run.cluster.children["remote"].process.pid
        started = threading.Event()

        def on_event(sample) -> None:  # a Zenoh callback: a signal sent and a flag set, nothing that blocks
            body = messages.decode(sample.payload.to_bytes(), "deploy_event")
            if body.get("event") == "started" and not started.is_set():
                # Its deployer cannot stop the old detector now. Sent here, as the start is heard, not after
                # the test's thread wakes: on a loaded machine the migration once finished first (118 ms).
                os.kill(remote, signal.SIGSTOP)
                started.set()

        events = run.session.declare_subscriber(keys.deployer_events("quad1", "onboard"), on_event)
        try:
            squeeze(run.session, "quad1", "remote", 4000.0)  # the remote host is full: migrate onboard
            assert started.wait(60), f"no detector started onboard after the remote host filled up: {run.recorder.decisions}"
            moved = run.wait_for(run.decision("memory_short", host="onboard"), 60, "the migration onboard")
            assert moved.outcome == "migrated", moved
            log = run.cluster.children["onboard"].log_path.read_text(errors="replace")
            assert "will be stopped when remote answers" in log, "the old detector was stopped at once: no cut-off"
        finally:
            os.kill(remote, signal.SIGCONT)
            events.undeclare()

        def one_onboard():
            live = [p for p in DeployerClient(run.session, "quad1").processes("*") if p.state in KEPT_STATES]
            return live if len(live) == 1 and live[0].host == "onboard" else None

        # The old detector is stopped once the remote deployer answers again; the new one stays
        # (the remote host is still full, so remote-first does not bring it back).
        live = run.wait_for(one_onboard, 60, "exactly one detector, onboard")
        assert live[0].instance == moved.instance  # the migration's new detector, the manager's own
