"""Two faults at once: the knowledge store and the remote host die together."""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.netns


def test_the_detector_comes_back_onboard_even_when_the_knowledge_store_dies_with_the_remote_host(robot):
    # The first plan finds the store gone; the manager tries again until the service has it back.
    # Returns once detections come from a new onboard detector (the time: kgadapt bench reliability).
    result = robot.kill_store_and_remote(timeout=60.0)
    running = robot.settle()
    assert (running["instance"], running["host"]) == (result["new_instance"], "onboard")
    assert robot.orphans() == []
    lost = [d for d in robot.probe.events if d["ev"] == "decision" and d.get("kind") == "host_lost"]
    assert lost and lost[-1]["outcome"].startswith("started"), lost
