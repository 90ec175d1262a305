"""The onboard agent stopped (SIGTERM) or killed (kill -9) and started again: no orphan, exactly one detector."""

from __future__ import annotations

import signal

import pytest

pytestmark = pytest.mark.netns


def test_a_restart_after_kill_9_adopts_the_remote_detector_the_agent_had_started(robot):
    result = robot.restart_onboard(signal.SIGKILL)

    assert result["detectors_while_down"] == [(result["before"], "remote")]  # its remote detector kept running
    assert result["orphans_while_down"] == 0  # ... under the remote agent, a live deployer
    assert result["outcome"] == "adopted" and result["after_host"] == "remote", result
    assert result["orphans_after"] == 0
    assert len(robot.live_detectors()) == 1


def test_a_restart_after_sigterm_finds_its_detector_stopped_cleanly_and_starts_one(robot):
    result = robot.restart_onboard(signal.SIGTERM)

    assert result["detectors_while_down"] == []  # a clean stop stops the detector it started
    assert result["outcome"] == "replaced", result
    assert result["orphans_after"] == 0
    assert len(robot.live_detectors()) == 1


def test_kill_9_of_the_onboard_agent_takes_its_onboard_detector_along_and_the_restart_starts_one(start_robot):
    robot = start_robot(prefer="onboard-first")
    assert robot.settle()["host"] == "onboard"

    result = robot.restart_onboard(signal.SIGKILL)

    assert result["detectors_while_down"] == []  # the parent-death signal took it along
    assert result["outcome"] == "replaced" and result["after_host"] == "onboard", result
    assert result["orphans_after"] == 0
