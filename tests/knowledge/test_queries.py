"""Every named query on the known graph (tests/knowledge/known_models), answers computed by hand.

The known graph, in short (memory MiB / CPU percent of one core):

    cam 640x480 10/5     cam2 1920x1080 30/10     fc (flight control) 50/70
    det_a 100/50 (5 ms)  det_b 500/90 (20 ms)     det_c 200/60 (8 ms)
    g_a = cam + det_a  realizes MarkerDetection, suited for day [10, 255)
    g_b = cam + det_b  realizes MarkerDetection, suited for dark [0, 10)
    g_c = cam2 + det_c realizes MarkerDetection, no band
    g_other = cam2     realizes Localization
    d_a deploys g_a on alpha, beta   d_b g_b on beta   d_c g_c on alpha
    d_fc deploys fc on alpha         d_other g_other on beta
    alpha: 1000 MiB, 2 cores (capacity 200)   beta: 4000 MiB, 4 cores (capacity 400)

Demands: g_a 10+100 = 110, g_b 10+500 = 510, g_c 30+200 = 230.
"""

from __future__ import annotations

import json

import pytest

from kgadapt.knowledge import queries as Q
from kgadapt.knowledge import runtime as R
from kgadapt.shared.errors import NamedQueryError


def _live(store, *, alpha_free=300.0, beta_free=600.0, beta_online=True):
    R.update_platform(store, name="alpha", time=100.0, memory_free_mb=alpha_free, cpu_load=20.0, online=True)
    R.update_platform(store, name="beta", time=100.0, memory_free_mb=beta_free, cpu_load=40.0, online=beta_online)


def _run(store, query, /, **params):
    return Q.run_named(store, query, params)


def test_fig4_deployments_for_a_feature_on_a_platform(known_store):
    assert _run(known_store, "feature_deployments", platform="alpha") == [
        {"deployment": "d_a", "kind": "SystemdServiceFile", "config": "g_a", "platform": "alpha"},
        {"deployment": "d_c", "kind": "DeploymentFile", "config": "g_c", "platform": "alpha"},
    ]
    rows = _run(known_store, "feature_deployments", platform="beta")
    assert [r["deployment"] for r in rows] == ["d_a", "d_b"]  # d_other realizes Localization, not this feature
    rows = _run(known_store, "feature_deployments", feature="Localization", platform="beta")
    assert [r["deployment"] for r in rows] == ["d_other"]


def test_placement_lists_every_configuration_where_free_memory_covers_its_demand(known_store):
    assert _run(known_store, "placement") == []  # no live figures yet: nothing is known to fit
    _live(known_store)
    assert _run(known_store, "placement") == [
        {"config": "g_a", "deployment": "d_a", "platform": "beta", "demand_mb": 110, "free_mb": 600.0},
        {"config": "g_a", "deployment": "d_a", "platform": "alpha", "demand_mb": 110, "free_mb": 300.0},
        {"config": "g_b", "deployment": "d_b", "platform": "beta", "demand_mb": 510, "free_mb": 600.0},
        {"config": "g_c", "deployment": "d_c", "platform": "alpha", "demand_mb": 230, "free_mb": 300.0},
    ]


def test_placement_of_one_configuration_follows_free_memory_and_liveness(known_store):
    _live(known_store)
    assert [r["platform"] for r in _run(known_store, "placement", config="g_b")] == ["beta"]
    _live(known_store, beta_free=509.0)  # one MiB short of 510
    assert _run(known_store, "placement", config="g_b") == []
    _live(known_store, beta_free=2000.0, beta_online=False)
    assert _run(known_store, "placement", config="g_b") == []
    assert [r["platform"] for r in _run(known_store, "placement", config="g_a")] == ["alpha"]
    assert _run(known_store, "placement", config="g_other") == []  # realizes another feature


def test_components_of_a_feature_deployable_on_a_platform(known_store):
    assert _run(known_store, "deployable_components", platform="beta") == [
        {"component": "cam", "memory_demand_mb": 10, "configs": ["g_a", "g_b"]},
        {"component": "det_a", "memory_demand_mb": 100, "configs": ["g_a"]},
        {"component": "det_b", "memory_demand_mb": 500, "configs": ["g_b"]},
    ]
    rows = _run(known_store, "deployable_components", platform="alpha")
    assert [(r["component"], r["configs"]) for r in rows] == [
        ("cam", ["g_a"]), ("cam2", ["g_c"]), ("det_a", ["g_a"]), ("det_c", ["g_c"])]


def test_camera_resolutions_of_a_feature(known_store):
    assert _run(known_store, "camera_resolutions") == [
        {"width": 640, "height": 480, "cameras": ["cam"], "configs": ["g_a", "g_b"]},
        {"width": 1920, "height": 1080, "cameras": ["cam2"], "configs": ["g_c"]},
    ]
    assert _run(known_store, "camera_resolutions", feature="Localization") == [
        {"width": 1920, "height": 1080, "cameras": ["cam2"], "configs": ["g_other"]}]


def test_components_that_ran_with_low_average_memory(known_store):
    for run_id, config, mean in (("r1", "g_a", 80.0), ("r2", "g_a", 120.0), ("r3", "g_b", 400.0)):
        R.record_process_start(known_store, run_id=run_id, instance=run_id, deployment="d_x", config=config,
                               host="alpha", pid=1, start_time=1.0)
        R.record_process_sample(known_store, run_id=run_id, rss_mb_last=mean, rss_mb_mean=mean, rss_mb_max=mean,
                                cpu_percent_mean=1.0)
    R.record_process_start(known_store, run_id="r4", instance="r4", deployment="d_c", config="g_c", host="alpha",
                           pid=2, start_time=2.0)  # never sampled: no memory figure, not counted
    # cam ran in r1, r2, r3: (80 + 120 + 400) / 3 = 200; det_a in r1, r2: 100; det_b in r3: 400
    assert _run(known_store, "low_memory_components", threshold_mb=150.0) == [
        {"component": "det_a", "runs": 2, "avg_memory_mb": 100.0}]
    rows = _run(known_store, "low_memory_components", threshold_mb=250.0)
    assert [(r["component"], r["runs"], r["avg_memory_mb"]) for r in rows] == [("cam", 3, 200.0), ("det_a", 2, 100.0)]
    assert [r["component"] for r in _run(known_store, "low_memory_components", threshold_mb=1000.0)] == [
        "cam", "det_a", "det_b"]


def test_cpu_overload_of_detector_and_flight_control_on_one_platform(known_store):
    # alpha: capacity 200, 80 % -> 160. g_a 5+50+70 = 125, g_b 5+90+70 = 165, g_c 10+60+70 = 140
    assert _run(known_store, "cpu_overload", platform="alpha") == [
        {"config": "g_a", "platform": "alpha", "detector_load": 55, "flight_control_load": 70, "total_load": 125,
         "limit_load": 160.0, "exceeds": False},
        {"config": "g_b", "platform": "alpha", "detector_load": 95, "flight_control_load": 70, "total_load": 165,
         "limit_load": 160.0, "exceeds": True},
        {"config": "g_c", "platform": "alpha", "detector_load": 70, "flight_control_load": 70, "total_load": 140,
         "limit_load": 160.0, "exceeds": False},
    ]
    row, = _run(known_store, "cpu_overload", platform="beta", config="g_b")  # capacity 400 -> 320
    assert (row["total_load"], row["limit_load"], row["exceeds"]) == (165, 320.0, False)
    row, = _run(known_store, "cpu_overload", platform="alpha", config="g_a", limit_pct=50.0)  # -> 100
    assert (row["total_load"], row["limit_load"], row["exceeds"]) == (125, 100.0, True)


def test_detector_configs_with_bands_demand_and_calibration(known_store):
    R.record_calibration(known_store, config="g_a", band="day", detection_rate=0.95, false_rate=0.01,
                         ms_per_frame=4.5, time=7.0)
    R.record_calibration(known_store, config="g_a", band="dark", detection_rate=0.2, false_rate=0.0,
                         ms_per_frame=4.4, time=7.0)  # not its band: not reported as its rate
    rows = _run(known_store, "detector_configs")
    assert [(r["config"], r["band"], r["min_level"], r["max_level"], r["memory_demand_mb"], r["detection_rate"],
             r["ms_per_frame"]) for r in rows] == [
        ("g_b", "dark", 0.0, 10.0, 510, None, 20),
        ("g_a", "day", 10.0, 255.0, 110, 0.95, 4.5),
        ("g_c", None, None, None, 230, None, 8),
    ]


def test_detector_config_gives_the_settings_the_detector_program_needs(known_store):
    row, = _run(known_store, "detector_config", config="g_b")
    assert (row["config"], row["dictionary"], row["memory_demand_mb"], row["deployment"]) == (
        "g_b", "DICT_4X4_50", 510, "d_b")
    assert json.loads(row["config_json"])["preprocess"] == [{"op": "gamma", "gamma": 0.5}, {"op": "blur", "ksize": 3}]
    assert _run(known_store, "detector_config", config="g_nonesuch") == []


def test_deployment_describes_one_deployment(known_store):
    assert _run(known_store, "deployment", name="d_a") == [{
        "name": "d_a", "kind": "SystemdServiceFile", "executable": "{python}",
        "arguments": ["-m", "kgadapt.onboard.perception.detector", "--config", "{config}", "--host", "{host}"],
        "environment": ["A=1", "B=two words"], "platforms": ["alpha", "beta"], "deploys": ["g_a"]}]
    assert _run(known_store, "deployment", name="d_fc")[0]["deploys"] == ["fc"]
    assert _run(known_store, "deployment", name="nope") == []


def test_platforms_show_design_and_live_figures(known_store):
    rows = _run(known_store, "platforms")
    assert [(r["platform"], r["memory_total_mb"], r["memory_free_mb"], r["online"]) for r in rows] == [
        ("alpha", 1000.0, None, None), ("beta", 4000.0, None, None)]
    _live(known_store)
    alpha = _run(known_store, "platforms")[0]
    assert (alpha["memory_free_mb"], alpha["cpu_load"], alpha["online"], alpha["last_seen"], alpha["cpu_capacity"]) == (
        300.0, 20.0, True, 100.0, 200.0)


def test_decisions_newest_first_and_limited(known_store):
    for name, at in (("first", 1.0), ("third", 3.0), ("second", 2.0)):
        R.record_decision(known_store, name=name, time=at, trigger="t", config="g_a", host="alpha", outcome="ok")
    assert [r["name"] for r in _run(known_store, "decisions")] == ["third", "second", "first"]
    assert [r["name"] for r in _run(known_store, "decisions", limit=2)] == ["third", "second"]


def test_current_placement_is_the_newest_running_detector_and_the_decision_behind_it(known_store):
    assert _run(known_store, "current_placement") == []
    R.record_process_start(known_store, run_id="old", instance="i1", deployment="d_a", config="g_a", host="beta",
                           pid=10, start_time=10.0)
    R.record_process_start(known_store, run_id="new", instance="i2", deployment="d_b", config="g_b", host="alpha",
                           pid=20, start_time=30.0)
    R.record_decision(known_store, name="to-alpha", time=29.0, trigger="dark", config="g_b", host="alpha", outcome="ok")
    R.record_decision(known_store, name="to-beta", time=31.0, trigger="x", config="g_b", host="beta", outcome="ok")
    row, = _run(known_store, "current_placement")
    assert (row["instance"], row["config"], row["host"], row["pid"], row["start_time"], row["decision"]) == (
        "i2", "g_b", "alpha", 20, 30.0, "to-alpha")
    R.record_process_end(known_store, run_id="new", end_time=40.0, exit_status=0)
    row, = _run(known_store, "current_placement")
    assert (row["instance"], row["host"], row["decision"]) == ("i1", "beta", None)


def test_current_placement_is_not_a_warm_standby_until_a_decision_switches_to_it(known_store):
    R.record_process_start(known_store, run_id="run", instance="i1", deployment="d_a", config="g_a", host="alpha",
                           pid=10, start_time=10.0)
    R.record_decision(known_store, name="start", time=11.0, trigger="startup", config="g_a", host="alpha", outcome="ok")
    R.record_process_start(known_store, run_id="warm", instance="i2", deployment="d_b", config="g_b", host="alpha",
                           pid=20, start_time=12.0)
    R.record_decision(known_store, name="warm", time=13.0, trigger="standby(band=dusk)", config="g_b", host="alpha",
                      outcome="standby started (idle)")
    row, = _run(known_store, "current_placement")
    assert (row["instance"], row["decision"]) == ("i1", "start")  # the newer process is the idle standby
    R.record_decision(known_store, name="switch", time=20.0, trigger="band_changed", config="g_b", host="alpha",
                      outcome="switched to the standby")
    row, = _run(known_store, "current_placement")
    assert (row["instance"], row["decision"]) == ("i2", "switch")
    # The light goes back: the old one (idle since) is switched to again, though it started first.
    R.record_decision(known_store, name="back", time=30.0, trigger="band_changed", config="g_a", host="alpha",
                      outcome="switched to the standby")
    row, = _run(known_store, "current_placement")
    assert (row["instance"], row["decision"]) == ("i1", "back")


def _tiny_graph(store):
    """f <-REALIZES- g -CONTAINS-> c(100);  d1 -DEPLOYS-> g, d1 -> remote(free 120);
    d2 -DEPLOYS-> fc(50), d2 -> remote;  d3 -> onboard(free 200), unrelated to f."""
    store.execute("""
        CREATE (f:Feature {name: $f}), (g:PerceptionGraph {name: 'g'}), (c:Component {name: 'c', memory_demand_mb: 100}),
               (fc:Component:FlightControl {name: 'fc', memory_demand_mb: 50}),
               (r:Platform {name: 'remote', memory_free_mb: 120.0}), (o:Platform {name: 'onboard', memory_free_mb: 200.0}),
               (d1:Deployment {name: 'd1'}), (d2:Deployment {name: 'd2'}), (d3:Deployment {name: 'd3'}),
               (g)-[:REALIZES]->(f), (g)-[:CONTAINS]->(c), (d1)-[:DEPLOYS]->(g), (d1)-[:EXECUTABLE_ON]->(r),
               (d2)-[:DEPLOYS]->(fc), (d2)-[:EXECUTABLE_ON]->(r), (d3)-[:EXECUTABLE_ON]->(o)""",
                  {"f": "MarkerDetection"})


def test_fig4_literal_returns_every_deployment_on_the_platform_as_the_paper_wrote_it(store):
    _tiny_graph(store)
    rows = _run(store, "fig4_literal", platform="remote")
    # the second MATCH is not joined to the first: d2 (flight control) comes back too
    assert {r["d"]["name"] for r in rows} == {"d1", "d2"}


def test_fig5_literal_sums_every_component_reachable_from_the_feature(store):
    _tiny_graph(store)
    # reachable: c (100) directly, fc (50) through d1 -> remote <- d2: MEM = 150.
    # remote (120) falls short; onboard (200, via d3) passes although nothing links it to the feature.
    rows = _run(store, "fig5_literal")
    assert [r["p"]["name"] for r in rows] == ["onboard"]


def test_unknown_queries_and_bad_parameters_are_refused_by_name():
    with pytest.raises(NamedQueryError, match="unknown named query 'nope'"):
        Q.check_params("nope", {})
    with pytest.raises(NamedQueryError, match="'placement' has no parameter 'conf'"):
        Q.check_params("placement", {"conf": "x"})
    with pytest.raises(NamedQueryError, match="'feature_deployments' needs parameter 'platform'"):
        Q.check_params("feature_deployments", {})
    with pytest.raises(NamedQueryError, match="'threshold_mb' must be float, not str"):
        Q.check_params("low_memory_components", {"threshold_mb": "lots"})
    with pytest.raises(NamedQueryError, match="'limit' must be int, not bool"):
        Q.check_params("decisions", {"limit": True})
    # At most the rows any public question gets: the query's own LIMIT $limit must not lift that bound.
    assert Q.check_params("decisions", {"limit": 1000}) == {"limit": 1000}
    for limit in (1001, -1):
        with pytest.raises(NamedQueryError, match=rf"'decisions': parameter 'limit' {limit} is not between 0 and 1000"):
            Q.check_params("decisions", {"limit": limit})
    with pytest.raises(NamedQueryError, match="'limit' must be int, not 'ten'"):
        Q.coerce_params("decisions", {"limit": "ten"})
    assert Q.coerce_params("cpu_overload", {"limit_pct": "75", "platform": "a"}) == {"limit_pct": 75.0, "platform": "a"}
    assert Q.check_params("placement", {}) == {"feature": "MarkerDetection", "config": None}


def test_every_query_the_contract_names_exists_and_all_run_read_only(known_store):
    contract = {"placement", "detector_configs", "detector_config", "deployment", "platforms", "fig4_literal",
                "fig5_literal", "decisions", "current_placement"}
    six = {"feature_deployments", "placement", "deployable_components", "camera_resolutions",
           "low_memory_components", "cpu_overload"}
    assert contract | six <= set(Q.QUERIES)
    from kgadapt.knowledge.store import assert_read_only
    for query in Q.QUERIES.values():
        for text in (query.cypher, *query.when_missing.values()):
            assert_read_only(text)
            assert "'" not in text  # values come as parameters, never as literals
