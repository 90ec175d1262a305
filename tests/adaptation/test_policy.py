"""The adaptation loop's rules (onboard/adaptation/adaptation_policy.py), on plain values: no store, no Zenoh, no process."""

from __future__ import annotations

import json

import pytest

from kgadapt.onboard.adaptation import adaptation_policy as P
from kgadapt.onboard.adaptation.adaptation import Analyzer, Band, BandTracker, HostView, Placement, Plan, Trigger
from kgadapt.shared.messages import ProcessDetail
from kgadapt.shared.states import Change, ProcessState, TriggerKind

BANDS = [Band("dark", 0, 25), Band("dusk", 25, 80), Band("day", 80, 256)]
RUNNING = Placement(config="day", deployment="day_onboard", host="onboard", instance="i1", demand_mb=120,
                    held_mb=50, run_id="r1")
STANDBY = Placement(config="dusk", deployment="dusk_remote", host="remote", instance="i2", demand_mb=100,
                    held_mb=80, run_id="r2")


def analyzer(*online: str) -> Analyzer:
    a = Analyzer(tracker=BandTracker(bands=BANDS))
    for host in online:
        a.hosts[host] = HostView(name=host, online=True)
    return a


def plan(config: str = "dusk", host: str = "onboard", **inputs) -> Plan:
    return Plan(target=Placement(config=config, deployment=f"{config}_{host}", host=host, demand_mb=100),
                reason="because", inputs={"band": "dusk", "expected_rate": 0.8, **inputs}, queries=("placement",))


def trigger(kind: TriggerKind, **detail) -> Trigger:
    return Trigger(kind, 10.0, detail)


# -- the schedule -------------------------------------------------------------------------


def test_a_change_settles_statuses_forgets_the_held_check_and_keeps_the_plans_promise():
    state = P.after_change(P.LoopState(held_checked=5.0), plan(), wall=100.0, settle_s=1.0)
    assert (state.changed_at, state.settled_after, state.held_checked) == (100.0, 101.0, 0.0)
    assert state.expected == ("dusk", "dusk", 0.8)
    assert P.expected_rate(state, {}, "dusk", "dusk") == 0.8
    # Another configuration or band: the graph's figure for its own band, else none.
    configs = {"day": {"band": "day", "detection_rate": 0.9}}
    assert P.expected_rate(state, configs, "day", "day") == 0.9
    assert P.expected_rate(state, configs, "day", "dusk") is None


def test_held_memory_is_asked_again_only_when_due_or_forced():
    state = P.LoopState(held_checked=10.0)
    assert P.held_refresh(state, wall=11.0, every_s=2.0) is None
    assert P.held_refresh(state, wall=12.0, every_s=2.0).held_checked == 12.0
    assert P.held_refresh(state, wall=10.5, every_s=2.0, force=True).held_checked == 10.5


def test_a_retry_comes_back_once_when_its_time_has_come():
    lost = trigger(TriggerKind.HOST_LOST, host="remote")
    state = P.retry_later(P.LoopState(), lost, mono=5.0, retry_s=1.0)
    assert P.due_retry(state, mono=5.5) == (None, state)
    again, state = P.due_retry(state, mono=6.0)
    assert again is lost and again.time == 10.0  # latency still runs from the loss
    assert P.due_retry(state, mono=7.0)[0] is None


def test_the_loop_waits_until_its_next_own_check_and_no_longer():
    state = P.LoopState(next_check=10.5, next_standby_check=10.2, next_leftover_check=11.0)
    wake = dict(probing=True, starting=False, leftovers=False, standby=False, startup_poll_s=0.2)
    assert P.next_wake(state, mono=10.0, **wake) == pytest.approx(0.5)
    assert P.next_wake(state, mono=10.0, **{**wake, "standby": True}) == pytest.approx(0.2)
    assert P.next_wake(state, mono=12.0, **wake) == 0.0  # overdue: at once
    # Its host lost: no probe is due, nothing of its own either: it waits for news (bounded).
    assert P.next_wake(state, mono=10.0, **{**wake, "probing": False}) == P.IDLE_WAKE_S
    assert P.next_wake(P.LoopState(), mono=10.0, **{**wake, "starting": True}) == 0.2
    retry = P.retry_later(state, trigger(TriggerKind.HOST_LOST), mono=10.0, retry_s=0.1)
    assert P.next_wake(retry, mono=10.0, **wake) == pytest.approx(0.1)


def test_refusals_are_logged_once_per_host_and_interval():
    assert P.refusal_log_due(None, 100.0)
    assert not P.refusal_log_due(100.0, 100.0 + P.REFUSAL_LOG_EVERY_S - 0.1)
    assert P.refusal_log_due(100.0, 100.0 + P.REFUSAL_LOG_EVERY_S)


def test_history_size_must_keep_something():
    with pytest.raises(ValueError, match="history_size"):
        P.AdaptationSettings(robot="quad1", history_size=0)


# -- analyse ----------------------------------------------------------------------------------


def test_only_a_detector_that_looks_short_is_measured_again_and_only_once_settled():
    kw = dict(running=RUNNING, standby=STANDBY)
    assert P.to_measure("onboard", 69, settled=True, **kw) is RUNNING  # 69 + 50 < 120
    assert P.to_measure("onboard", 70, settled=True, **kw) is None
    assert P.to_measure("onboard", 10, settled=False, **kw) is None
    assert P.to_measure("remote", 19, settled=True, **kw) is STANDBY  # 19 + 80 < 100
    # The standby sharing the running detector's host: the running one is the question there.
    beside = Placement(config="dusk", deployment="x", host="onboard", instance="i2", demand_mb=500, held_mb=1)
    assert P.to_measure("onboard", 100, settled=True, running=RUNNING, standby=beside) is None


def test_memory_short_from_a_status_needs_a_settled_measured_detector():
    a = analyzer("onboard", "remote")
    state = P.LoopState(changed_at=100.0, settled_after=101.0)
    kw = dict(cpu_load=5.0, standby=None, state=state)
    # Received before the change settled: measured while two detectors ran.
    assert P.host_status_trigger(a, "onboard", free_mb=10, wall=102, running=RUNNING, received=100.5, **kw) is None
    short = P.host_status_trigger(a, "onboard", free_mb=10, wall=102, running=RUNNING, received=101.5, **kw)
    assert short.kind == TriggerKind.MEMORY_SHORT and short.detail["held_mb"] == 50
    # Only its exec-time sample known: the benefit of the doubt for MEASURE_WITHIN_S after the change.
    fresh = Placement(config="day", deployment="d", host="onboard", instance="i1", demand_mb=120, held_mb=3)
    assert P.host_status_trigger(a, "onboard", free_mb=10, wall=105, running=fresh, received=105, **kw) is None
    late = 100.0 + P.MEASURE_WITHIN_S
    assert P.host_status_trigger(a, "onboard", free_mb=10, wall=late, running=fresh, received=late, **kw).kind \
        == TriggerKind.MEMORY_SHORT


def test_a_measured_standby_short_of_memory_is_a_trigger_naming_it():
    a = analyzer("onboard", "remote")
    kw = dict(cpu_load=5.0, wall=200.0, running=RUNNING, state=P.LoopState(), received=200.0)
    short = P.host_status_trigger(a, "remote", free_mb=19, standby=STANDBY, **kw)
    assert short.kind == TriggerKind.MEMORY_SHORT and short.detail["standby"] == "i2"
    assert P.host_status_trigger(a, "remote", free_mb=20, standby=STANDBY, **kw) is None
    unmeasured = Placement(config="dusk", deployment="x", host="remote", instance="i2", demand_mb=100, held_mb=2)
    assert P.host_status_trigger(a, "remote", free_mb=1, standby=unmeasured, **kw) is None


def test_detections_count_only_from_our_instance_and_clean_cells():
    assert P.own_detection(RUNNING, body_instance="i1", key_instance="i1")
    assert not P.own_detection(RUNNING, body_instance="i1", key_instance="forged")
    assert not P.own_detection(None, body_instance="i1", key_instance="i1")
    assert P.clean_markers([1, 2, 3], None) == 3
    assert P.clean_markers([1, 2, 3], [True, False, None]) == 2
    assert P.clean_markers([1], [True, True]) == 1


def test_a_process_that_ran_its_last_is_noticed_and_a_gone_detector_is_a_trigger():
    assert P.ended(RUNNING, instance="i1", event="exited")
    assert not P.ended(RUNNING, instance="i1", event="ready")
    assert not P.ended(RUNNING, instance="other", event="stopped")
    assert P.gone_trigger(RUNNING, "running", wall=1.0) is None
    gone = P.gone_trigger(RUNNING, "failed", wall=1.0)
    assert gone.kind == TriggerKind.DETECTOR_GONE and gone.detail == {"instance": "i1", "host": "onboard",
                                                                       "state": "failed"}


def test_a_standby_that_exited_unasked_is_to_be_stopped_not_restarted_active():
    assert P.crashed_standby(STANDBY, instance="i2", event="exited")
    assert not P.crashed_standby(STANDBY, instance="i2", event="stopped")  # stopped on request: over already
    assert not P.crashed_standby(STANDBY, instance="i1", event="exited")  # another process
    assert not P.crashed_standby(None, instance="i2", event="exited")


def test_the_deployer_is_not_asked_while_the_running_host_is_lost():
    hosts = {"onboard": HostView(name="onboard", online=False)}
    assert not P.probe_due(P.LoopState(), RUNNING, hosts, mono=1.0)
    hosts["onboard"].online = True
    assert P.probe_due(P.LoopState(next_check=0.5), RUNNING, hosts, mono=1.0)
    assert not P.probe_due(P.LoopState(next_check=1.5), RUNNING, hosts, mono=1.0)


def test_the_first_placement_waits_for_a_band_our_host_in_the_graph_and_confirmed_figures():
    a = analyzer("onboard", "remote")
    asked = []

    def platforms():
        asked.append(1)
        return [{"platform": "onboard", "online": True, "memory_free_mb": 400.0}]

    kw = dict(own_host="onboard", platforms=platforms, wall=5.0)
    assert P.startup_trigger(a, within_grace=True, confirmed=lambda h: True, **kw) is None  # no band yet
    assert asked == []  # the graph is not asked for nothing
    a.on_illumination(120.0, 0.0)
    assert P.startup_trigger(a, within_grace=True, confirmed=lambda h: h == "onboard", **kw) is None  # all, in grace
    assert P.startup_trigger(a, within_grace=False, confirmed=lambda h: h == "onboard", **kw).kind == "startup"
    started = P.startup_trigger(a, within_grace=True, confirmed=lambda h: True, **kw)
    assert started.detail == {"band": "day"}
    assert P.startup_trigger(a, within_grace=True, confirmed=lambda h: True, **{**kw, "platforms": lambda: []}) is None


# -- plan -------------------------------------------------------------------------------------------


def test_a_host_back_without_confirmed_figures_waits_unless_the_detector_is_lost():
    back = trigger(TriggerKind.HOST_BACK, host="remote")
    waiting = P.confirm_host_back(P.LoopState(), back, host_confirmed=False, mono=3.0, window_s=1.5)
    assert waiting.retry.detail == {"host": "remote", "confirming": 1} and waiting.retry_at == 4.5
    assert P.confirm_host_back(P.LoopState(), back, host_confirmed=True, mono=3.0, window_s=1.5) is None
    # Still unconfirmed a window later (statuses late on a loaded machine): it waits again, not plans...
    retry, mono = waiting.retry, 4.5
    for tries in range(2, P.HOST_BACK_WINDOWS + 1):
        again = P.confirm_host_back(P.LoopState(), retry, host_confirmed=False, mono=mono, window_s=1.5)
        assert again is not None and again.retry.detail["confirming"] == tries and again.retry_at == mono + 1.5
        retry, mono = again.retry, mono + 1.5
    # ...but not for ever: after HOST_BACK_WINDOWS it is planned as it stands.
    assert P.confirm_host_back(P.LoopState(), retry, host_confirmed=False, mono=mono, window_s=1.5) is None
    # one retry at a time: a state already waiting is not given another
    assert P.confirm_host_back(waiting, waiting.retry, host_confirmed=False, mono=5.0, window_s=1.5) is None
    kw = dict(standby=None, landing=False, deferred=())
    assert P.triage(back, running=RUNNING, lost=(), waiting=True, **kw) == P.Action.WAIT
    assert P.triage(back, running=RUNNING, lost=("onboard",), waiting=True, **kw) == P.Action.PLAN


def test_in_a_descent_only_the_loss_of_the_detectors_own_host_is_acted_on():
    kw = dict(standby=None, landing=True, deferred=())
    assert P.triage(trigger(TriggerKind.HOST_LOST, host="onboard"), running=RUNNING, lost=("onboard",), **kw) \
        == P.Action.PLAN
    assert P.triage(trigger(TriggerKind.HOST_LOST, host="remote"), running=RUNNING, lost=("remote",), **kw) \
        == P.Action.DEFER
    assert P.triage(trigger(TriggerKind.HOST_LOST, host="remote"), running=RUNNING, lost=("remote",),
                    **{**kw, "landing": False}) == P.Action.PLAN


def test_memory_short_with_a_standby_stops_it_first_and_a_descent_defers_once_per_kind():
    short = trigger(TriggerKind.MEMORY_SHORT, host="remote")
    assert P.triage(short, running=RUNNING, standby=STANDBY, lost=(), landing=False, deferred=()) \
        == P.Action.STOP_STANDBY
    band = trigger(TriggerKind.BAND_CHANGED)
    kw = dict(running=RUNNING, standby=None, landing=True)
    assert P.triage(band, lost=(), deferred=(), **kw) == P.Action.DEFER
    assert P.triage(band, lost=(), deferred={"band_changed"}, **kw) == P.Action.DEFER_AGAIN
    # Losing the running detector is acted on in the descent too.
    assert P.triage(trigger(TriggerKind.HOST_LOST), lost=("onboard",), deferred=(), **kw) == P.Action.PLAN
    assert P.triage(trigger(TriggerKind.DETECTOR_GONE), lost=(), deferred=(), **kw) == P.Action.PLAN


def test_plans_count_confirmed_figures_and_the_running_host_its_roomiest():
    hosts = {"onboard": HostView(name="onboard", online=True), "remote": HostView(name="remote", online=True),
             "spare": HostView(name="spare", online=False)}
    live = P.live_free(hosts, here="onboard", roomiest=lambda h: 500.0, confirmed=lambda h: 100.0 if h != "x" else None)
    assert live == {"onboard": 500.0, "remote": 100.0}
    assert P.live_free(hosts, here=None, roomiest=lambda h: 500.0, confirmed=lambda h: None) == {}


def no_change(_a, _b):
    raise AssertionError("the graph is not asked")


def test_how_a_plan_is_carried_out():
    kw = dict(standby=None, lost=(), change=no_change)
    same = plan("day", "onboard")
    assert P.execution(same, trigger(TriggerKind.BAND_CHANGED), running=RUNNING, **kw).how == P.Execution.KEEP
    assert P.execution(same, trigger(TriggerKind.STARTUP), running=RUNNING, **kw).how == P.Execution.NOTHING
    assert P.execution(same, trigger(TriggerKind.DETECTOR_GONE), running=RUNNING, **kw).how == P.Execution.START
    assert P.execution(plan(), trigger(TriggerKind.STARTUP), running=None, **kw).how == P.Execution.START
    in_place = plan(change=Change.RECONFIGURE, change_why="same family")
    assert P.execution(in_place, trigger(TriggerKind.BAND_CHANGED), running=RUNNING, **kw) \
        == P.Execute(P.Execution.RECONFIGURE, "same family")
    assert P.execution(plan("dusk", "remote"), trigger(TriggerKind.BAND_CHANGED), running=RUNNING, **kw).how \
        == P.Execution.MIGRATE


def test_the_standby_serves_a_plan_for_its_configuration_and_a_failover_it_can_take_in_place():
    kw = dict(running=RUNNING, standby=STANDBY)
    switch = P.execution(plan("dusk", "onboard"), trigger(TriggerKind.BAND_CHANGED), lost=(), change=no_change, **kw)
    assert switch.how == P.Execution.STANDBY and switch.reconfigure_to is None and "a switch" in switch.why
    # Another configuration, and nothing is lost: no standby.
    assert P.execution(plan("dark", "onboard"), trigger(TriggerKind.BAND_CHANGED), lost=(), change=no_change,
                       **kw).how == P.Execution.MIGRATE
    lost = trigger(TriggerKind.HOST_LOST, host="onboard")
    asked = []

    def change(frm, to):
        asked.append((frm.config, to.config, to.host))
        return Change.RECONFIGURE, "same family"

    failover = P.execution(plan("dark", "onboard"), lost, lost=("onboard",), change=change, **kw)
    assert failover.how == P.Execution.STANDBY and failover.reconfigure_to == "dark"
    assert asked == [("dusk", "dark", "remote")]
    migrate = P.execution(plan("dark", "onboard"), lost, lost=("onboard",),
                          change=lambda a, b: (Change.MIGRATE, "no"), **kw)
    assert migrate.how == P.Execution.START
    # A standby on a lost host serves nothing.
    assert P.execution(plan("dusk", "remote"), lost, lost=("onboard", "remote"), change=no_change, **kw).how \
        == P.Execution.START


def test_the_move_for_a_host_loss_is_planned_ahead_and_used_only_while_what_it_rests_on_holds():
    """Issue 32 item 1: the failover's plan is ready before the loss."""
    basis = P.move_basis(band="dusk", running=RUNNING, standby=STANDBY, lost=(), exclude=())
    assert P.needs_move(None, host="onboard", basis=basis, mono=0.0, every_s=2.0)
    how = P.execution(plan("dusk", "remote"), trigger(TriggerKind.HOST_LOST, host="onboard"), running=RUNNING,
                      standby=STANDBY, lost=("onboard",), change=no_change)
    assert how.how == P.Execution.STANDBY  # the standby's configuration: a switch, nothing started
    move = P.ReadyMove(host="onboard", basis=basis, plan=plan("dusk", "remote"), how=how, at=100.0)
    assert not P.needs_move(move, host="onboard", basis=basis, mono=101.0, every_s=2.0)
    assert P.needs_move(move, host="onboard", basis=basis, mono=102.0, every_s=2.0)  # the figures moved on
    lost = trigger(TriggerKind.HOST_LOST, host="onboard")
    use = dict(running=RUNNING, basis=basis, mono=101.0, max_age_s=2.0)
    assert P.ready_move(move, lost, **use) is move
    # Not for another host's loss, another trigger, or once what it rests on changed.
    assert P.ready_move(move, trigger(TriggerKind.HOST_LOST, host="remote"), **use) is None
    assert P.ready_move(move, trigger(TriggerKind.BAND_CHANGED), **use) is None
    other = P.move_basis(band="dusk", running=RUNNING, standby=None, lost=(), exclude=())
    assert other != basis and P.needs_move(move, host="onboard", basis=other, mono=101.0, every_s=2.0)
    assert P.ready_move(move, lost, **{**use, "basis": other}) is None
    assert P.ready_move(move, lost, **{**use, "mono": 103.0}) is None


def test_the_move_into_each_other_band_is_planned_ahead_and_used_only_while_what_it_rests_on_holds():
    """Issue 32: a change of band (the detector's reflex, the band tracker) has its plan ready before it comes."""
    def basis(band: str, running: Placement = RUNNING) -> tuple:
        return P.move_basis(band=band, running=running, standby=None, lost=(), exclude=())

    moves: dict[str, P.BandMove] = {}
    due = dict(bands=["dusk", "dark"], basis=basis, every_s=2.0)
    assert P.band_move_due(moves, mono=0.0, **due) == "dusk"
    how = P.execution(plan("dusk"), trigger(TriggerKind.BAND_CHANGED), running=RUNNING, standby=None, lost=(),
                      change=no_change)
    moves["dusk"] = P.BandMove(band="dusk", basis=basis("dusk"), at=100.0, plan=plan("dusk"), how=how)
    assert P.band_move_due(moves, mono=100.5, **due) == "dark"
    moves["dark"] = P.BandMove(band="dark", basis=basis("dark"), at=100.5)  # planning failed: not again at once
    assert P.band_move_due(moves, mono=101.0, **due) is None
    assert P.band_move_due(moves, mono=102.0, **due) == "dusk"  # the graph's figures moved on
    other = Placement(config="day", deployment="day_onboard", host="onboard", instance="i9", demand_mb=120)
    assert P.band_move_due(moves, mono=101.0, **{**due, "basis": lambda b: basis(b, other)}) == "dusk"
    use = dict(basis=basis("dusk"), mono=101.0, max_age_s=2.0)
    for kind in (TriggerKind.REFLEX, TriggerKind.BAND_CHANGED):
        assert P.band_move(moves["dusk"], trigger(kind), **use) is moves["dusk"]
    # Not for another trigger, once what it rests on changed, too old, or a move that could not be planned.
    assert P.band_move(moves["dusk"], trigger(TriggerKind.MEMORY_SHORT), **use) is None
    assert P.band_move(moves["dusk"], trigger(TriggerKind.REFLEX), **{**use, "basis": basis("dusk", other)}) is None
    left_out = P.move_basis(band="dusk", running=RUNNING, standby=None, lost=(), exclude=("dusk",))
    assert P.band_move(moves["dusk"], trigger(TriggerKind.REFLEX), **{**use, "basis": left_out}) is None
    assert P.band_move(moves["dusk"], trigger(TriggerKind.REFLEX), **{**use, "mono": 102.5}) is None
    assert P.band_move(moves["dark"], trigger(TriggerKind.REFLEX), **{**use, "basis": basis("dark")}) is None


def test_what_the_warm_standby_needs():
    hosts = {"remote": HostView(name="remote", online=True)}
    kw = dict(running=RUNNING, landing=False, paused=False, retrying=False, band="dusk", hosts=hosts)
    assert P.standby_step(standby=None, first_for=no_change, **kw) == P.StandbyStep.START
    assert P.standby_step(standby=STANDBY, first_for=lambda b: "dusk", **kw) == P.StandbyStep.NOTHING
    assert P.standby_step(standby=STANDBY, first_for=lambda b: "dark", **kw) == P.StandbyStep.STOP
    assert P.standby_step(standby=STANDBY, first_for=lambda b: None, **kw) == P.StandbyStep.NOTHING
    hosts["remote"].online = False
    assert P.standby_step(standby=STANDBY, first_for=no_change, **kw) == P.StandbyStep.DROP
    for quiet in ("landing", "paused", "retrying"):
        assert P.standby_step(standby=None, first_for=no_change, **{**kw, quiet: True}) == P.StandbyStep.NOTHING


def test_adoption_keeps_one_of_ours_onboard_first_and_the_rest_are_twins():
    configs = {"day": {}, "dusk": {}}
    processes = [
        ProcessDetail(instance="b", host="remote", config="day", state=ProcessState.RUNNING),
        ProcessDetail(instance="c", host="onboard", config="dusk", state=ProcessState.READY),
        ProcessDetail(instance="d", host="onboard", config="day", state=ProcessState.STOPPING),  # on its way out
        ProcessDetail(instance="e", host="onboard", config="not_ours", state=ProcessState.RUNNING),
    ]
    keep, twins = P.adoption(processes, configs, onboard_host="onboard")
    assert keep is not None and keep.instance == "c" and [t.instance for t in twins] == ["b"]
    assert P.adoption(processes[2:], configs, onboard_host="onboard") == (None, [])
    running = Placement(config="dusk", deployment="x", host="onboard", instance="c")
    standby = Placement(config="day", deployment="y", host="remote", instance="b")
    assert P.twins(processes, configs, running=running, standby=standby) == []
    assert [t.instance for t in P.twins(processes, configs, running=running, standby=None)] == ["b"]


def test_a_decision_record_carries_trigger_plan_and_outcome():
    outcome = P.Outcome(trigger=trigger(TriggerKind.BAND_CHANGED, to="dusk"), plan=plan(), outcome="migrated",
                        latency_ms=123.456, detail={"previous_instance": "i0", "change": Change.MIGRATE})
    params, event = P.decision_record(outcome, robot="quad1", wall=1000.5, seq=7, instance="i1")
    assert params["name"] == "quad1-decision-1000500-7"
    assert params["outcome"] == "migrated: because" and params["duration_ms"] == 123.5
    assert json.loads(params["inputs_json"])["trigger"] == {"to": "dusk"}
    assert params["query"] == "placement" and (params["config"], params["host"]) == ("dusk", "onboard")
    d = event.decision
    assert d is not None
    assert (d.instance, d.previous_instance, d.change, d.trigger_time) == ("i1", "i0", "migrate", 10.0)
    bare, _ = P.decision_record(P.Outcome(trigger=trigger(TriggerKind.HOST_BACK), outcome="kept"), robot="quad1",
                                wall=1.0, seq=1, instance=None)
    assert bare["config"] is None and bare["outcome"] == "kept" and bare["query"] is None


def test_the_manager_s_settings_and_the_planner_default_alike_wherever_they_share_a_setting():
    # The manager builds its planner from these settings; a default spelt twice could drift (issue 31).
    import dataclasses

    from kgadapt.onboard.adaptation import planning_defaults as D
    from kgadapt.onboard.adaptation.adaptation import Planner

    def defaults(obj) -> dict:
        return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}

    settings, planner = defaults(P.AdaptationSettings(robot="r")), defaults(Planner(ask=lambda name, params: []))
    shared = settings.keys() & planner.keys()
    assert {"preference", "onboard_host", "in_place", "feature", "live"} <= shared
    assert {k: settings[k] for k in shared} == {k: planner[k] for k in shared}
    assert (settings["preference"], settings["onboard_host"], settings["in_place"]) == (
        D.DEFAULT_PREFERENCE, D.ONBOARD_HOST, D.IN_PLACE) == ("onboard-first", "onboard", True)


def test_a_reflex_tried_on_the_frames_evidence_stands_and_one_on_the_light_is_planned():
    # A collapse (or a fall of the count) in steady light: the band's plan is what collapsed, so the
    # try stands until the detector's trial reverts it or the band changes.
    assert P.reflex_stands({"evidence": "collapse", "config": "marker_detection_dark", "band": "day"})
    # The light, a hedge near an edge, a revert: the manager's plan for the band decides.
    for evidence in ("light", "hedge", "revert"):
        assert not P.reflex_stands({"evidence": evidence, "config": "marker_detection_dark", "band": "day"})
    # Nothing taken in place (the reflex only told): nothing stands.
    assert not P.reflex_stands({"evidence": "collapse", "band": "day"})
