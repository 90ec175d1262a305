"""The planning step against the shipped quadcopter models in a real FalkorDB."""

from __future__ import annotations

from functools import partial

import pytest

from knowledge.loader import load_models
from knowledge.queries import run_named
from knowledge.runtime import record_calibration, update_platform
from onboard.adaptation import Placement, Planner, PlanningError
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
    assert plan.target.deployment and plan.queries == ("detector_configs", "placement")


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


def test_calibration_decides_between_configurations_of_one_band(graph):
    # Two configurations calibrated in the dusk band: the higher detection rate wins.
    record_calibration(graph, config="marker_detection_dusk", band="dusk", detection_rate=0.7,
                       false_rate=0.0, ms_per_frame=12, time=1.0)
    record_calibration(graph, config="marker_detection_dark", band="dusk", detection_rate=0.95,
                       false_rate=0.0, ms_per_frame=35, time=1.0)
    config, _ = planner(graph).choose_config("dusk")
    assert config["config"] in ("marker_detection_dusk", "marker_detection_dark")
    rows = run_named(graph, "detector_configs", {})
    dusk = {r["config"]: r["detection_rate"] for r in rows if r["band"] == "dusk"}
    assert config["config"] == max(dusk, key=lambda c: dusk[c] or 0)


def test_the_plan_explains_itself(graph):
    plan = planner(graph).plan(band="day", running=None)
    assert "marker_detection_day" in plan.reason and "onboard" in plan.reason
    assert plan.inputs["band"] == "day" and plan.inputs["platforms"][0]["platform"] == "onboard"


def test_a_squeeze_seen_live_before_the_graph_shows_it_already_counts(graph):
    # The graph still says 400 MiB free onboard; the status just received says 200.
    plan = planner(graph).plan(band="dark", running=None, live_free={"onboard": 200.0})
    assert plan.target.host == "remote"
