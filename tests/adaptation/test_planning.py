"""The planning step against the shipped quadcopter models in a real FalkorDB."""

from __future__ import annotations

from functools import partial

import pytest

from kgadapt.knowledge.loader import load_models
from kgadapt.knowledge.queries import run_named
from kgadapt.knowledge.runtime import record_calibration, update_platform
from kgadapt.onboard.adaptation.adaptation import Placement, Planner, PlanningError
from tests.conftest import REPO


@pytest.fixture
def graph(resp_store):
    load_models(resp_store, [REPO / "knowledge" / "models"])
    update_platform(resp_store, name="onboard", time=1.0, memory_free_mb=400, online=True)
    update_platform(resp_store, name="remote", time=1.0, memory_free_mb=4000, online=True)
    return resp_store


def planner(store, **kw) -> Planner:
    return Planner(ask=partial(run_named, store), **kw)


def test_each_band_gets_the_configuration_suited_for_it(graph):
    p = planner(graph)
    assert p.plan(band="day", running=None).target.config == "marker_detection_day"
    assert p.plan(band="dusk", running=None).target.config == "marker_detection_dusk"
    assert p.plan(band="dark", running=None).target.config == "marker_detection_dark"


def test_onboard_first_keeps_the_detector_onboard_while_it_fits(graph):
    plan = planner(graph).plan(band="dark", running=None)
    assert plan.target.host == "onboard"  # 324 MiB demand, 400 MiB free
    assert plan.target.deployment and plan.queries == ("config_ranking", "placement")


def test_remote_first_sends_it_to_the_remote_host(graph):
    assert planner(graph, preference="remote-first").plan(band="day", running=None).target.host == "remote"


def test_a_squeezed_onboard_host_sends_the_dark_detector_remote(graph):
    update_platform(graph, name="onboard", time=2.0, memory_free_mb=200)
    assert planner(graph).plan(band="dark", running=None).target.host == "remote"


def test_the_running_host_gets_its_detector_memory_back_when_it_is_replaced(graph):
    # 260 free + 70 held by the running day detector covers the 324 of the dark one.
    update_platform(graph, name="onboard", time=2.0, memory_free_mb=260)
    running = Placement(config="marker_detection_day", deployment="x", host="onboard", demand_mb=72, held_mb=70)
    assert planner(graph).plan(band="dark", running=running).target.host == "onboard"
    assert planner(graph).plan(band="dark", running=None).target.host == "remote"


def test_a_lost_host_is_never_chosen(graph):
    plan = planner(graph).plan(band="day", running=None, lost_hosts=("onboard",))
    assert plan.target.host == "remote"


def test_no_platform_online_is_a_planning_error(graph):
    update_platform(graph, name="onboard", time=2.0, online=False)
    update_platform(graph, name="remote", time=2.0, online=False)
    with pytest.raises(PlanningError, match="no online platform"):
        planner(graph).plan(band="day", running=None)


def calibrate(store, band, **rates):
    """Calibration figures for ``band``: config=(rate, false_per_frame, ms) (condition all)."""
    for config, (rate, false, ms) in rates.items():
        record_calibration(store, config=f"marker_detection_{config}", band=band, detection_rate=rate,
                           false_per_frame=false, ms_per_frame=ms, time=1.0)


def test_every_configuration_calibrated_in_the_band_is_ranked_not_only_the_suited_one(graph):
    calibrate(graph, "dusk", dusk=(0.7, 0.0, 12), dark=(0.95, 0.0, 35), day=(0.5, 0.0, 3))
    p = planner(graph)
    assert [r["config"] for r in p.ranking("dusk")] == [
        "marker_detection_dark", "marker_detection_dusk", "marker_detection_day"]
    plan = p.plan(band="dusk", running=None)
    assert plan.target.config == "marker_detection_dark"
    assert [r["config"] for r in plan.inputs["ranking"]][0] == "marker_detection_dark"
    assert plan.inputs["expected_rate"] == 0.95 and "first in the ranking" in plan.reason


def test_false_markers_are_a_penalty_and_ties_go_to_the_faster(graph):
    calibrate(graph, "day", day=(0.98, 0.0, 3), dusk=(1.0, 0.10, 9), dark=(0.978, 0.0, 7))
    ranked = [r["config"] for r in planner(graph).ranking("day")]
    # dusk: 1.0 - 0.10 = 0.90 (phantoms); day 0.98 and dark 0.978 tie within half a point: the faster first.
    assert ranked == ["marker_detection_day", "marker_detection_dark", "marker_detection_dusk"]


def test_a_tie_in_rate_is_not_decided_by_timing_noise_but_by_robustness_for_planner_and_reflexes_alike(graph):
    from kgadapt.onboard.perception.markers import parse_config
    from kgadapt.onboard.perception.reflex import ReflexTable

    # The day band as a loaded calibration saw it (issue 29): day and dusk tie on rate, dusk timed 5 % faster
    # (noise: on a loaded machine that order flips between runs), and day finds more of the blurred markers.
    calibrate(graph, "day", day=(0.99, 0.0, 10.0), dusk=(0.99, 0.0, 9.5), dark=(0.97, 0.0, 16.0))
    for condition, rates in (("clean", {"day": 1.0, "dusk": 1.0, "dark": 1.0}),
                             ("blur", {"day": 0.60, "dusk": 0.43, "dark": 0.55}),
                             ("window", {"day": 1.0, "dusk": 1.0, "dark": 1.0})):
        for config, rate in rates.items():
            record_calibration(graph, config=f"marker_detection_{config}", band="day", condition=condition,
                               detection_rate=rate, false_per_frame=0.0, ms_per_frame=9.0, time=1.0)

    def reflex_order() -> list[str]:
        rows = run_named(graph, "reflex_table", {"deployment": "detector_day", "host": "onboard"})
        table = ReflexTable.from_rows(rows, parse=lambda name, raw, dictionary: parse_config(name, raw,
                                                                                             dictionary=dictionary))
        return [c.config for c in table.entry("day").choices]

    p = planner(graph)
    plan = p.plan(band="day", running=None)
    assert plan.target.config == "marker_detection_day" and "config_robustness" in plan.queries
    ranked = [(r["config"], r["robustness"]) for r in plan.inputs["ranking"]]
    assert ranked[0] == ("marker_detection_day", pytest.approx((1.0 + 0.60 + 1.0) / 3))
    assert ranked[1] == ("marker_detection_dusk", pytest.approx((1.0 + 0.43 + 1.0) / 3))
    assert reflex_order()[:2] == ["marker_detection_day", "marker_detection_dusk"]  # the detector's table agrees
    # Ranked in one condition, robustness is the others' (not the band as a whole): clean ties, blur decides.
    assert p.ranking("day", condition="clean")[0]["config"] == "marker_detection_day"
    # Speed still counts where it is beyond the timing's noise: dusk a third faster goes first.
    calibrate(graph, "day", dusk=(0.99, 0.0, 6.5))
    assert planner(graph).plan(band="day", running=None).target.config == "marker_detection_dusk"
    assert reflex_order()[0] == "marker_detection_dusk"


def test_equally_fast_equally_robust_configurations_go_by_name_whatever_order_the_rows_come_in():
    from kgadapt.onboard.perception.ranking import rank_graph_rows

    rows = [{"config": c, "score": 0.9, "ms_per_frame": ms} for c, ms in (("b", 10.0), ("c", 9.8), ("a", 10.3))]
    for order in (rows, rows[::-1], rows[1:] + rows[:1]):
        assert [r["config"] for r in rank_graph_rows(order)] == ["a", "b", "c"]
    # 1 ms apart at 3 ms a frame is timer jitter too: the absolute margin.
    assert [r["config"] for r in rank_graph_rows([{"config": "b", "score": 0.9, "ms_per_frame": 2.5},
                                                  {"config": "a", "score": 0.9, "ms_per_frame": 3.4}])] == ["a", "b"]


def test_memory_and_time_are_constraints_the_ranking_steps_past(graph):
    calibrate(graph, "dark", dark=(0.8, 0.0, 20), dusk=(0.5, 0.0, 8), day=(0.02, 0.0, 2))
    update_platform(graph, name="onboard", time=2.0, memory_free_mb=200)
    update_platform(graph, name="remote", time=2.0, online=False)
    plan = planner(graph).plan(band="dark", running=None)  # the dark one needs 324 MiB: nowhere
    assert plan.target.config == "marker_detection_dusk" and plan.target.host == "onboard"
    assert plan.inputs["skipped"][0]["config"] == "marker_detection_dark"
    assert [r["config"] for r in planner(graph, max_ms=10).ranking("dark")] == [
        "marker_detection_dusk", "marker_detection_day"]


def test_a_collapse_excludes_the_running_configuration(graph):
    calibrate(graph, "day", day=(1.0, 0.0, 3), dusk=(0.99, 0.0, 9), dark=(0.95, 0.0, 7))
    plan = planner(graph).plan(band="day", running=None, exclude=("marker_detection_day",))
    assert plan.target.config == "marker_detection_dusk" and plan.inputs["excluded"] == ["marker_detection_day"]
    with pytest.raises(PlanningError, match="other than"):
        planner(graph).plan(band="day", running=None, exclude=(
            "marker_detection_day", "marker_detection_dusk", "marker_detection_dark"))


def test_the_plan_explains_itself(graph):
    plan = planner(graph).plan(band="day", running=None)
    assert "marker_detection_day" in plan.reason and "onboard" in plan.reason
    assert plan.inputs["band"] == "day" and plan.inputs["platforms"][0]["platform"] == "onboard"


def test_a_squeeze_seen_live_before_the_graph_shows_it_already_counts(graph):
    # The graph still says 400 MiB free onboard; the status just received says 200.
    plan = planner(graph).plan(band="dark", running=None, live_free={"onboard": 200.0, "remote": 4000.0})
    assert plan.target.host == "remote"


def test_a_host_without_a_confirmed_figure_is_no_target_whatever_the_graph_says(graph):
    # The graph says remote has 4000 MiB (one status may have put it there); the caller has confirmed
    # only onboard's figures, which are too small for the dark detector.
    with pytest.raises(PlanningError, match="no online platform"):
        planner(graph).plan(band="dark", running=None, live_free={"onboard": 200.0})
    # The running host keeps its own detector without a confirmed figure (it gets its memory back).
    running = Placement(config="marker_detection_dark", deployment="x", host="remote", demand_mb=324, held_mb=300)
    assert planner(graph).plan(band="dark", running=running, live_free={"onboard": 200.0}).target.host == "remote"


def test_why_shows_the_ranking_the_plan_used(graph):
    from kgadapt.onboard.adaptation.adaptation_cli import render

    calibrate(graph, "dark", dark=(0.8, 0.0, 20), dusk=(0.5, 0.0, 8), day=(0.02, 0.0, 2))
    plan = planner(graph).plan(band="dark", running=None, exclude=("marker_detection_dark",))
    text = render({
        "running": {"instance": "i1", "config": plan.target.config, "host": plan.target.host, "pid": 1},
        "decision": {"name": "d1", "trigger": "rate_collapsed(rate=0.0)", "outcome": plan.reason,
                     "inputs": dict(plan.inputs)},
        "placement_now": [], "history": []})
    lines = text.splitlines()
    assert any("ranking for band dark (named query config_ranking" in line for line in lines)
    first = next(line for line in lines if line.strip().startswith("1."))
    assert "marker_detection_dark" in first and "left out: its detections collapsed" in first
    assert any(line.strip().startswith("2. marker_detection_dusk: score 0.5") for line in lines)


def test_the_planner_reconfigures_in_place_on_the_same_host_and_migrates_across_hosts(graph):
    day = Placement(config="marker_detection_day", deployment="detector_day", host="onboard", instance="d1",
                    demand_mb=72.0, held_mb=80.0)
    plan = planner(graph).plan(band="dark", running=day)
    assert (plan.target.host, plan.inputs["change"]) == ("onboard", "reconfigure")
    assert "marker-detector" in plan.inputs["change_why"] and "in_place_change" in plan.queries
    moved = planner(graph, preference="remote-first").plan(band="dark", running=day)
    assert (moved.target.host, moved.inputs["change"]) == ("remote", "migrate")
    assert planner(graph, in_place=False).plan(band="dark", running=day).inputs["change"] == "migrate"
    # The graph decides: without the family on the running deployment, a new process.
    graph.execute("MATCH (d:Deployment {name: 'detector_day'}) REMOVE d.reconfigurable_as")
    refused = planner(graph).plan(band="dark", running=day)
    assert refused.inputs["change"] == "migrate" and "does not let detector_day" in refused.inputs["change_why"]


def test_a_standby_for_the_neighbouring_band_goes_where_there_is_room_as_well(graph):
    day = Placement(config="marker_detection_day", deployment="x", host="onboard", instance="i", demand_mb=72,
                    held_mb=70)
    plan = planner(graph).standby(band="dusk", running=day)
    assert (plan.target.config, plan.target.host) == ("marker_detection_dusk", "onboard")
    assert plan.inputs["standby"] and "beside the running marker_detection_day@onboard" in plan.reason
    # No credit for the running detector's memory: the standby comes in addition to it.
    update_platform(graph, name="onboard", time=2.0, memory_free_mb=100)
    assert planner(graph).standby(band="dark", running=day).target.host == "remote"
    assert planner(graph).standby(band="dark", running=day, lost_hosts=("remote",)) is None
    # The running configuration serves the band already: nothing to keep warm.
    assert planner(graph).standby(band="day", running=day) is None
