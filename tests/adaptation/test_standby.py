"""The warm standby (``kgadapt onboard --standby``), end to end with real processes.

The manager keeps the neighbouring band's configuration started but idle where
the graph says a host has room for it as well: a band change to it is a switch
(no new process), its memory is in the graph like any process's, and it is the
first thing stopped when memory gets short.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import pytest

from deploy.client import DeployerClient
from knowledge.store import open_store
from onboard.adaptation_cli import render
from shared.hostmonitor import squeeze
from tests.adaptation.test_adaptation_e2e import Run

pytestmark = pytest.mark.slow

LIVE = ("starting", "ready", "running", "restarting")


def detectors(run: Run, host: str = "*") -> dict[str, tuple[str, int]]:
    """instance -> (host, pid) of every live detector process (on ``host``).

    A loaded machine can keep a deployer from answering for seconds: a generous bound, not a tight one.
    """
    return {p["instance"]: (p["host"], p["pid"]) for p in DeployerClient(run.session, "quad1", timeout=20.0).list(host)
            if p.get("state") in LIVE}


def idle_standby(run: Run):
    """The first standby started and made idle (a failed start is a decision of the same kind)."""
    return run.decision("standby", outcome="standby started (idle)")


def open_profile(run: Run, config: str) -> dict | None:
    """The open ProcessProfile of a process running ``config``, with a measured RSS."""
    with open_store(run.cluster.store_url) as store:
        rows = store.execute(
            "MATCH (r:ProcessProfile)-[:RAN_CONFIG]->(:PerceptionGraph {name: $config}) "
            "WHERE r.end_time IS NULL AND r.rss_mb_max > 5 RETURN r.name AS run_id, r.rss_mb_max AS rss",
            {"config": config}, read_only=True)
    return rows[0] if rows else None


def test_a_band_change_to_the_standby_is_a_switch_without_a_new_process(tmp_path):
    points = [[0, 120], [10, 120], [11, 30], [30, 30]]  # day, then dusk near the day edge (day stays the neighbour)
    with Run(tmp_path, points, standby=True) as run:
        start = run.wait_for(run.decision("startup"), 40, "the first detector")
        ready = run.wait_for(idle_standby(run), 30, "the standby")
        assert (ready.config, ready.host) == ("marker_detection_dusk", "onboard"), run.recorder.decisions
        # Idle: its memory is in the graph (open profile) though it publishes nothing.
        profile = run.wait_for(lambda: open_profile(run, "marker_detection_dusk"), 30, "the standby's profile")
        before = detectors(run)
        assert len(before) == 2 and start.instance in before, before
        run.wait_for(lambda: time.time() > ready.time + 1.5, 3, "a second of frames with the standby idle")
        assert run.running(ready.time + 0.5) == {("marker_detection_day", "onboard")}, "an idle standby publishes nothing"
        switch = run.wait_for(run.decision("band_changed"), 40, "the band change to dusk")
        run.wait_for(lambda: ("marker_detection_dusk", "onboard") in run.running(switch.time), 20, "dusk detections")
        after = detectors(run)
        since = time.time()
        time.sleep(1.0)
        running = run.running(since)
        why_json = subprocess.run([sys.executable, "-m", "kgadapt", "why", "--json", "--connect",
                                   run.cluster.endpoint], capture_output=True, text=True, timeout=30)
    assert (switch.change, switch.config, switch.host) == ("standby", "marker_detection_dusk", "onboard"), switch
    assert switch.outcome.startswith("switched to the standby"), switch
    assert switch.instance != start.instance and switch.previous_instance == start.instance
    assert after == before, "a switch starts no process and stops none (the old one is the standby now)"
    assert running == {("marker_detection_dusk", "onboard")}, "the old detector, idle, publishes nothing"
    assert profile["rss"] > 5
    assert why_json.returncode == 0, why_json.stderr
    explained = json.loads(why_json.stdout)
    assert explained["running"]["instance"] == switch.instance  # not the old one, idle beside it
    assert explained["decision"]["inputs"]["change"] == "standby"
    assert "switch to the warm standby" in render(explained), render(explained)


def test_a_squeeze_stops_the_standby_before_anything_moves(tmp_path):
    with Run(tmp_path, [[0, 5], [120, 5]], standby=True) as run:  # dark: the 300 MiB detector
        first = run.wait_for(run.decision("startup"), 40, "the first detector")
        ready = run.wait_for(idle_standby(run), 30, "the standby")
        assert (first.host, ready.config, ready.host) == ("onboard", "marker_detection_dusk", "onboard")
        standby = next(i for i in detectors(run) if i != first.instance)
        squeeze(run.session, "quad1", "onboard", 350.0)
        short = run.wait_for(run.decision("memory_short"), 30, "the squeeze to be noticed")
        assert short.change == "standby_stopped" and short.outcome.startswith("stopped the standby"), short
        run.wait_for(lambda: standby not in detectors(run), 30, "the standby's process gone")
        assert first.instance in detectors(run)
        # Still short without the standby: then, and only then, the detector moves.
        moved = run.wait_for(run.decision("memory_short", outcome="migrated"), 30, "the migration")
        assert (moved.config, moved.host) == ("marker_detection_dark", "remote")
    kinds = [(d.kind, d.change) for d in run.recorder.decisions]
    assert kinds.index(("memory_short", "standby_stopped")) < kinds.index(("memory_short", "migrate")), kinds


def test_losing_the_remote_host_activates_the_onboard_standby_instead_of_starting_a_process(tmp_path):
    with Run(tmp_path, [[0, 120], [120, 120]], prefer="remote-first", standby=True) as run:
        first = run.wait_for(run.decision("startup"), 40, "the first detector")
        ready = run.wait_for(idle_standby(run), 30, "the standby")
        # Remote-first runs the detector remote; the standby (memory, no CPU) stays onboard.
        assert (first.host, ready.config, ready.host) == ("remote", "marker_detection_dusk", "onboard")
        onboard_before = detectors(run, "onboard")
        run.cluster.kill("remote", signal.SIGKILL)
        lost = run.wait_for(run.decision("host_lost"), 30, "the lost host")
        run.wait_for(lambda: ("marker_detection_day", "onboard") in run.running(lost.time), 30, "day detections onboard")
        onboard_after = detectors(run, "onboard")  # only the onboard deployer: the remote one is dead
    assert (lost.change, lost.config, lost.host) == ("standby", "marker_detection_day", "onboard"), lost
    assert lost.instance in onboard_before and onboard_after == onboard_before, "no new process onboard"
