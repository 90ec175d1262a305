"""The warm standby (``kgadapt onboard --standby``), end to end with real processes.

One robot (remote-first, light near the dusk/dark edge, then dark) goes through
everything the standby is for, so the whole robot starts once: the manager keeps
the neighbouring band's configuration started but idle where the graph says a
host has room for it as well; its memory is in the graph like any process's;
losing the remote host activates it (reconfigured in place) instead of starting
a process; a step of the light is the running detector's own reflex (in place,
faster than a switch), after which the standby follows the new neighbouring
band; and it is the first thing stopped when memory gets short.
"""

from __future__ import annotations

import signal
import time

import pytest

from kgadapt.deploy.client import DeployerClient
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.store import open_store
from kgadapt.onboard.adaptation.adaptation_cli import explain, render
from kgadapt.shared.hostmonitor import squeeze
from kgadapt.shared.states import KEPT_STATES
from tests.adaptation.test_adaptation_e2e import Run, decision_inputs

pytestmark = pytest.mark.slow

DUSK, DARK = "marker_detection_dusk", "marker_detection_dark"
STEP_S = 14.0  # dusk until then: startup, the standby, the failover and the next standby all come before it


def detectors(run: Run, host: str = "*") -> dict[str, tuple[str, int, str]]:
    """instance -> (host, pid, configuration) of every live detector process (on ``host``).

    A loaded machine can keep a deployer from answering for seconds: a generous bound, not a tight one.
    """
    return {p.instance: (p.host, p.pid, p.config)
            for p in DeployerClient(run.session, "quad1", timeout=20.0).processes(host) if p.state in KEPT_STATES}


def idle_standbys(run: Run) -> list:
    """The standbys started and made idle so far (a failed start is a decision of the same kind)."""
    return [d for d in run.recorder.decisions if d.kind == "standby" and d.outcome == "standby started (idle)"]


def open_profile(run: Run, config: str) -> dict | None:
    """The open ProcessProfile of a process running ``config``, with a measured RSS, and its host."""
    with open_store(run.cluster.store_url) as store:
        rows = store.execute(
            "MATCH (p:Platform)<-[:RAN_ON]-(r:ProcessProfile)-[:RAN_CONFIG]->(:PerceptionGraph {name: $config}) "
            "WHERE r.end_time IS NULL AND r.rss_mb_max > 5 RETURN r.name AS run_id, r.rss_mb_max AS rss, p.name AS host",
            {"config": config}, read_only=True)
    return rows[0] if rows else None


def test_the_standby_is_counted_takes_over_a_lost_host_is_switched_to_and_goes_first_in_a_squeeze(tmp_path):
    points = [[0, 16], [STEP_S, 16], [STEP_S + 1, 5], [STEP_S + 60, 5]]
    with Run(tmp_path, points, prefer="remote-first", standby=True) as run:
        first = run.wait_for(run.decision("startup"), 40, "the first detector")
        ready = run.wait_for(lambda: idle_standbys(run), 30, "the standby")[0]
        # Remote-first runs the detector remote; the standby (memory, no CPU) goes onboard, for the
        # band whose edge the light is nearest (dark).
        assert (first.config, first.host, ready.config, ready.host) == (DUSK, "remote", DARK, "onboard"), (first, ready)
        profile = run.wait_for(lambda: open_profile(run, DARK), 30, "the standby's profile")
        standby = detectors(run, "onboard")
        run.wait_for(lambda: time.time() > ready.time + 1.5, 5, "a second of frames with the standby idle")
        idle_running = run.running(ready.time + 0.5)

        run.cluster.kill("remote", signal.SIGKILL)
        lost = run.wait_for(run.decision("host_lost"), 30, "the lost host")
        lost_inputs = decision_inputs(run, "host_lost")
        run.wait_for(lambda: (DUSK, "onboard") in run.running(lost.time), 30, "dusk detections onboard")
        after_failover = detectors(run, "onboard")  # only the onboard deployer: the remote one is dead

        second = run.wait_for(lambda: idle_standbys(run)[1:], 30, "the next standby")[0]
        before_switch = detectors(run, "onboard")
        # The step into the dark: the running detector takes the dark configuration itself, in place.
        switch = run.wait_for(run.decision("reflex"), 60, "the reflex into the dark")
        run.wait_for(lambda: (DARK, "onboard") in run.running(switch.time), 30, "dark detections")
        since = time.time()
        time.sleep(1.0)  # a second of detections: only the running detector's
        running = run.running(since)
        explained = explain(KnowledgeClient(run.session, "quad1", own=True, timeout=10.0).query)
        # The dark standby is the running configuration now: a dusk one (the band the light left) replaces it.
        third = run.wait_for(lambda: [d for d in idle_standbys(run)[2:] if d.config == DUSK], 60,
                             "the dusk standby")[0]
        dusk_standby = run.wait_for(lambda: [i for i, (_, _, c) in detectors(run, "onboard").items()
                                             if c == DUSK and i != switch.instance], 30, "the dusk standby's process")

        squeeze(run.session, "quad1", "onboard", 350.0, timeout=10.0)  # dark needs 300 MiB: short now
        short = run.wait_for(run.decision("memory_short"), 30, "the squeeze to be noticed")
        run.wait_for(lambda: dusk_standby[0] not in detectors(run, "onboard"), 30, "the standby's process gone")
        after_squeeze = detectors(run, "onboard")

    # Its memory counts in the graph like any process's, though it publishes nothing.
    assert (profile["host"], profile["rss"] > 5) == ("onboard", True), profile
    assert len(standby) == 1 and idle_running == {(DUSK, "remote")}, (standby, idle_running)
    # Failover: the standby, reconfigured in place to dusk, is the detector; no process started. The
    # move was planned before the loss (issue 32 item 1): no question to the graph stood before the switch.
    assert (lost.change, lost.config, lost.host) == ("standby", DUSK, "onboard"), lost
    assert "planned_ahead_ms" in lost_inputs, lost_inputs
    assert lost.outcome.startswith("switched to the standby"), lost
    # The same process, now on dusk; the only other one is the next standby (dark), which may be up already.
    assert lost.instance in standby and after_failover[lost.instance][:2] == standby[lost.instance][:2], after_failover
    assert not [i for i, (_, _, config) in after_failover.items() if i != lost.instance and config != DARK], (
        f"no new process for the failover: {after_failover}")
    # A standby again (dark beside the running dusk, a process of its own), then the step: the running
    # detector's reflex, the same process, on the frame that showed the dark.
    assert (second.config, second.host) == (DARK, "onboard"), second
    assert (switch.change, switch.config, switch.host) == ("reflex", DARK, "onboard"), switch
    assert switch.instance == lost.instance and switch.instance in before_switch, switch
    assert running == {(DARK, "onboard")}, "the idle standby publishes nothing"
    assert explained["running"]["instance"] == switch.instance
    assert explained["decision"]["inputs"]["change"] == "reflex"
    assert "the detector's own reflex" in render(explained), render(explained)
    assert (third.config, third.host) == (DUSK, "onboard"), third
    # Memory short: the standby is stopped first, the running detector stays.
    assert short.change == "standby_stopped" and short.outcome.startswith(f"stopped the standby {dusk_standby[0]}"), short
    assert list(after_squeeze) == [switch.instance], after_squeeze


def test_a_standby_that_crashes_is_stopped_not_restarted_active_and_a_new_idle_one_follows(tmp_path):
    import os

    with Run(tmp_path, [[0, 16], [120, 16]], prefer="remote-first", standby=True) as run:
        first = run.wait_for(run.decision("startup"), 40, "the first detector")
        ready = run.wait_for(lambda: idle_standbys(run), 30, "the standby")[0]
        # A decision names the running detector's instance; the standby is the other live process.
        before = run.wait_for(lambda: {i: d for i, d in detectors(run).items() if i != first.instance},
                              30, "the standby's process")
        (crashed, (host, pid, config)), = before.items()
        os.kill(pid, signal.SIGKILL)
        run.wait_for(lambda: idle_standbys(run)[1:], 60, "a new idle standby")
        live = run.wait_for(lambda: {i: d for i, d in detectors(run).items() if i != first.instance},
                            30, "the new standby's process")
        # Then a second of detections with only the running detector's.
        running = run.wait_for(lambda: run.running(time.time() - 1.0) == {(first.config, first.host)}
                               and run.running(time.time() - 1.0), 20, "only the running detector detecting")
        # A standby starts idle: neither it nor the one after the crash ever published a detection
        # (they used to, between ready and the manager's request to idle).
        ever = {(c, h) for _, _, c, h, _, _ in list(run.recorder.detections)}

    assert (host, config) == (ready.host, ready.config), before
    assert crashed not in live, f"the crashed standby was restarted (active): {live}"
    assert [(h, c) for h, _, c in live.values()] == [(ready.host, ready.config)], live
    assert running == {(first.config, first.host)}, running
    assert ever == {(first.config, first.host)}, ever


def test_a_failover_whose_standby_does_not_answer_starts_a_process_instead_of_asking_it_again(tmp_path):
    import os

    with Run(tmp_path, [[0, 16], [120, 16]], prefer="remote-first", standby=True) as run:
        first = run.wait_for(run.decision("startup"), 40, "the first detector")
        run.wait_for(lambda: idle_standbys(run), 30, "the standby")
        standby = run.wait_for(lambda: {i: d for i, d in detectors(run).items() if i != first.instance},
                               30, "the standby's process")
        (hung, (_, pid, _)), = standby.items()
        os.kill(pid, signal.SIGSTOP)  # alive, so no exit event, and it answers nothing
        try:
            run.cluster.kill("remote", signal.SIGKILL)
            lost = run.wait_for(run.decision("host_lost"), 60, "the failover")
            # The retry's decision is recorded after its first detections: wait for the decision itself.
            run.wait_for(lambda: [d for d in run.recorder.decisions
                                  if d.kind == "host_lost" and not d.outcome.startswith("failed")], 90,
                         "a failover that worked")
            run.wait_for(lambda: any(h == "onboard" for _, h in run.running(lost.time)), 30, "detections onboard")
            decisions = [d for d in run.recorder.decisions if d.kind == "host_lost"]
        finally:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass

    assert decisions[0].outcome.startswith("failed"), decisions  # the standby was asked once
    recovered = [d for d in decisions if not d.outcome.startswith("failed")]
    assert recovered and recovered[0].instance != hung and recovered[0].change != "standby", decisions
