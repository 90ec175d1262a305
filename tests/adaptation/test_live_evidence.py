"""Live evidence changes the ranking: real FalkorDB, the real knowledge service over Zenoh, ``kgadapt why`` as a process.

Synthetic calibration ranks the day configuration (A) over the dark one (B) in
band dark. The adaptation manager's live windows (onboard/adaptation/live_rate.py), fed the
frames of a day -> dark step (A finds nothing while the markers seen a moment
before are expected, then B finds them), are written through the manager's own
write path (``write/onboard/live_rate``); the planner then picks B, and ``why``
names the live evidence as what decided.
"""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.loader import load_models
from kgadapt.knowledge.runtime import record_calibration, update_platform
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.onboard.adaptation import adaptation_policy as policy
from kgadapt.onboard.adaptation.adaptation import Placement, Planner, Trigger
from kgadapt.onboard.adaptation.live_rate import LiveRates, LiveSettings
from kgadapt.shared.errors import RemoteError
from kgadapt.shared.keys import DEFAULT_ROBOT
from kgadapt.shared.session import ZenohSettings, open_session
from kgadapt.shared.states import TriggerKind
from tests.conftest import REPO, free_port
from tests.support import wait_for

A, B = "marker_detection_day", "marker_detection_dark"
LIVE = LiveSettings(min_expected=20, window=300, expect_s=1.0, max_age_s=120.0)
FPS = 30.0


def step_frames(rates: LiveRates, start: float) -> float:
    """A day -> dark step: A sees 2 markers a frame in day, then nothing in dark; B, taking over, sees both."""
    t = start
    for _ in range(30):
        rates.add(config=A, band="day", found=2, now=t, run_id="run-a", host="onboard")
        t += 1 / FPS
    for _ in range(45):  # markers expected for the second after the last one seen, then not: A's evidence
        rates.add(config=A, band="dark", found=0, now=t, run_id="run-a", host="onboard")
        t += 1 / FPS
    for i in range(60):
        rates.add(config=B, band="dark", found=2 if i % 10 else 1, now=t, run_id="run-a", host="onboard")
        t += 1 / FPS
    return t


def test_live_evidence_changes_the_ranking_and_why_names_it(resp_store):
    load_models(resp_store, [REPO / "knowledge" / "models"])
    for host in ("onboard", "remote"):
        update_platform(resp_store, name=host, time=1.0, memory_total_mb=4096, memory_free_mb=2000, online=True)
    record_calibration(resp_store, config=A, band="dark", detection_rate=0.95, false_per_frame=0.0,
                       ms_per_frame=4.0, time=1.0)
    record_calibration(resp_store, config=B, band="dark", detection_rate=0.70, false_per_frame=0.0,
                       ms_per_frame=9.0, time=1.0)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohSettings(mode="router", listen=(endpoint,)))
    service = KnowledgeService(resp_store, ServiceSettings(robot=DEFAULT_ROBOT, sandbox=False,
                                                            mark_offline_at_start=False))
    service.setup(router)
    session = open_session(ZenohSettings(mode="client", connect=(endpoint,)))
    try:
        manager = KnowledgeClient(session, DEFAULT_ROBOT, own=True, host="onboard", timeout=3.0)  # the manager's path
        remote = KnowledgeClient(session, DEFAULT_ROBOT, own=True, host="remote", timeout=3.0)
        wait_for(lambda: bool(manager.query("platforms", {})), 5, "the service to answer")
        planner = Planner(ask=manager.query, live=LIVE)
        day = Placement(config=A, deployment="detector_day", host="onboard", instance="i1", demand_mb=72,
                        held_mb=70, run_id="run-a")
        before = planner.plan(band="dark", running=day)
        assert before.target.config == A and before.inputs["evidence"] == "synthetic"  # without live evidence

        rates = LiveRates(settings=LIVE)
        now = step_frames(rates, time.time() - 10.0)
        writes = rates.due(now)
        assert {(w["config"], w["band"]) for w in writes} == {(A, "day"), (A, "dark"), (B, "dark")}
        for params in writes:
            assert manager.write("live_rate", params) == []
        # Only the manager's host writes live figures.
        with pytest.raises(RemoteError, match="only the adaptation manager's host"):
            remote.write("live_rate", writes[0])
        live = {r["config"]: r for r in manager.query("live_rates", {"band": "dark"})}
        assert live[A]["detection_rate"] == 0.0 and live[A]["frames_seen"] == 0 and live[A]["frames_expected"] >= 20
        assert live[B]["detection_rate"] > 0.9 and live[B]["frames_seen"] == live[B]["frames_expected"] == 60

        after = planner.plan(band="dark", running=day)
        assert after.target.config == B and after.inputs["evidence"] == "live"
        assert [r["config"] for r in after.inputs["ranking"]] == [B, A] and "live_rates" in after.queries
        assert "live rate" in after.reason

        # Updated, not appended: another window's write replaces the figures.
        for _ in range(3):
            now = step_frames(rates, now)
            for params in rates.due(now + LIVE.write_every_s):
                manager.write("live_rate", params)
        count = resp_store.execute(f"MATCH ()-[l:{S.LIVE_RATE}]->() RETURN count(l) AS n")[0]["n"]
        assert count == 3

        # The manager records the decision as it does; why (a process, over Zenoh) names the evidence.
        manager.write("process_start", {"run_id": "run-b", "instance": "i2", "deployment": "detector_dark",
                                        "config": B, "host": "onboard", "pid": 4242, "start_time": time.time()})
        outcome = policy.Outcome(trigger=Trigger(TriggerKind.RATE_COLLAPSED, time.time(), {"config": A}),
                                 plan=after, outcome="reconfigured")
        params, _event = policy.decision_record(outcome, robot=DEFAULT_ROBOT, wall=time.time(), seq=1, instance="i2")
        manager.write("decision", params)
        why = subprocess.run([sys.executable, "-m", "kgadapt", "why", "--connect", endpoint],
                             capture_output=True, text=True, timeout=60)
        assert why.returncode == 0, why.stderr
        lines = why.stdout.splitlines()
        assert any("decided by: live evidence" in line for line in lines), why.stdout
        first = next(line for line in lines if line.strip().startswith("1."))
        second = next(line for line in lines if line.strip().startswith("2."))
        assert B in first and "from live evidence (rate 0.9" in first, why.stdout
        assert A in second and "from live evidence (rate 0 " in second and "calibrated rate 0.95" in second
    finally:
        session.close()
        service.shutdown()
        router.close()
