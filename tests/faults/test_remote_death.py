"""kill -9 of the remote agent while it runs the detector: the detector comes back onboard.

Waits for the new detector's first detections onboard (generous timeout, so a
loaded machine does not fail it); how fast that is, is measured by
``kgadapt bench reliability`` (bench/results/reliability.json).
"""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.netns


def test_a_detector_runs_onboard_after_kill_9_of_the_remote_agent(robot):
    result = robot.kill_remote(timeout=60.0)  # returns once the new onboard detector's detections arrive

    assert result["new_instance"] != result["old_instance"]
    assert result["remote_detector_gone"], "the remote detector outlived its agent (parent-death signal)"
    running = robot.settle()
    assert (running["instance"], running["host"]) == (result["new_instance"], "onboard")
    assert robot.orphans() == []
    platforms = robot.platforms()  # as another robot on the network sees the graph
    assert platforms["remote"]["online"] is False
    assert platforms["onboard"]["online"] is True
