"""The remote host's link cut for 5 s and restored: failover, then exactly one detector, a right graph, no restarts.

The link stays cut until the remote host is seen lost and detections flow
onboard (each waited for with a generous timeout); the times are measured by
``kgadapt bench reliability``.
"""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.netns


def test_a_cut_link_fails_over_onboard_and_heals_to_exactly_one_detector_without_restarting_anything(robot):
    # partition() returns only after, during the cut, the remote host was seen lost and
    # detections came from onboard, then after the heal the twin was stopped and the detector moved back.
    result = robot.partition(5.0, timeout=60.0)

    assert result["twin_ran_during_cut"], "the remote detector should have kept running on its side of the cut"
    # After the heal: the twin on the remote host is stopped by the adaptation manager, one detector is left.
    assert result["host_back_outcome"].startswith("stopped twin"), result
    # Then the preference (remote-first) brings it back, as a new instance, not the twin.
    assert result["running_host_after"] == "remote" and result["running_after"] != result["twin"]
    assert len(robot.live_detectors()) == 1 and len(robot.detector_processes()) == 1
    assert result["orphans"] == 0
    # The graph is right again: both hosts online, the twin's run has ended.
    assert result["graph_healed"], result
    assert result["online"] == {"onboard": True, "remote": True}
    assert [p["end_time"] is not None for p in result["twin_profile"]] == [True]
    # Nothing was restarted to heal.
    assert result["restarted"] == []
