"""kill -9 of the remote agent while it runs the detector: the detector comes back onboard.

Waits for the new detector's first detections onboard (generous timeout, so a
loaded machine does not fail it); how fast that is, is measured by
``kgadapt bench reliability`` (bench/results/reliability.json).
"""

from __future__ import annotations

import signal
import time

import pytest

from kgadapt.shared.errors import TransportError

pytestmark = pytest.mark.netns


def test_a_detector_runs_onboard_after_kill_9_of_the_remote_agent_also_right_after_a_placement_there(robot):
    result = robot.kill_remote(timeout=60.0)  # returns once the new onboard detector's detections arrive

    assert result["new_instance"] != result["old_instance"]
    assert result["remote_detector_gone"], "the remote detector outlived its agent (parent-death signal)"
    running = robot.settle()
    assert (running["instance"], running["host"]) == (result["new_instance"], "onboard")
    assert robot.orphans() == []
    platforms = robot.platforms()  # as another robot on the network sees the graph
    assert platforms["remote"]["online"] is False
    assert platforms["onboard"]["online"] is True


    # The remote host comes back and, remote-first, gets the detector back; its agent is killed
    # the moment that placement shows (the new remote detector's first detections, while the
    # migration still stops the onboard one). The manager is busy migrating and observations
    # queue up meanwhile: the loss of the host now running the detector must still be acted on.
    back_at = time.time()
    robot.cluster.respawn("remote")
    placed = robot.wait_detecting(host="remote", since=back_at, timeout=30.0)
    killed_at = time.time()
    robot.cluster.kill("remote", signal.SIGKILL)
    # Two outcomes are right, by a race the kill makes on purpose: the migration had finished (the
    # onboard detector stopped, so the loss is acted on with a new one), or its last step had not
    # been answered yet (the start's reply or the first detections reached the manager after the
    # kill: the migration fails and the onboard detector, never stopped, detects on).
    def what_happened(exc: Exception) -> AssertionError:
        seen = [e for e in robot.probe.events if e["t"] >= back_at and e["ev"] in ("decision", "deploy", "alive")]
        return AssertionError(f"{exc}; killed at {killed_at:.3f}; since the remote host came back: {seen}; "
                              f"the onboard agent's log:\n{robot.cluster.children['onboard'].tail(60)}")

    try:
        running = robot.settle(since=killed_at, timeout=30.0)
    except TransportError as exc:
        raise what_happened(exc) from exc
    assert running["host"] == "onboard" and running["instance"] != placed["instance"]
    if running["instance"] == result["new_instance"]:
        # Recorded once the half-started remote detector's stop is given up on (its host is gone).
        try:
            robot.probe.wait_event(lambda e: e["ev"] == "decision" and e["t"] >= back_at
                                   and str(e.get("outcome", "")).startswith("failed"), 60.0,
                                   "the failed migration's decision (the onboard detector detects on)")
        except TransportError as exc:
            raise what_happened(exc) from exc
    else:
        # The takeover was forked by the onboard host's launcher, or handed to the idle detector it keeps (--pool).
        assert running["via"] in ("launcher", "pool"), f"{running}"
