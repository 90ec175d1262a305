"""The remote host's link cut for 5 s and restored: failover, then exactly one detector, a right graph, no restarts."""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.netns


def test_a_cut_link_fails_over_onboard_and_heals_to_exactly_one_detector_without_restarting_anything(robot):
    result = robot.partition(5.0)

    # During the cut: the remote host is seen lost within about a lease and the detector comes back onboard.
    assert result["lost_seen_ms"] < 2000, result
    assert result["failover_ms"] < result["cut_s"] * 1000, result
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
