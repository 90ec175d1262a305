"""Run-time writes: late-bound figures land on the model's nodes, idempotently, and bad input is refused."""

from __future__ import annotations

import pytest

from kgadapt.knowledge import runtime as R
from kgadapt.shared.errors import NamedQueryError


def _row(store, cypher, **params):
    rows = store.execute(cypher, params, read_only=True)
    assert len(rows) == 1, rows
    return rows[0]


def test_platform_figures_fill_in_the_modelled_node_and_keep_what_a_later_update_omits(known_store):
    R.update_platform(known_store, name="alpha", time=10.0, memory_free_mb=400.0, cpu_load=30.0, online=True)
    R.update_platform(known_store, name="alpha", time=11.0, cpu_load=35.0)
    row = _row(known_store, "MATCH (p:Platform {name: 'alpha'}) RETURN p.memory_free_mb AS free, p.cpu_load AS cpu, "
                            "p.online AS online, p.last_seen AS seen, p.memory_total_mb AS total")
    assert row == {"free": 400.0, "cpu": 35.0, "online": True, "seen": 11.0, "total": 1000.0}
    assert _row(known_store, "MATCH (p:Platform) RETURN count(p) AS n")["n"] == 2


def test_a_host_the_models_do_not_name_is_refused_by_every_writer_and_gets_no_platform_node(known_store):
    from kgadapt.shared.errors import UnknownHost

    before = _row(known_store, "MATCH (n) RETURN count(n) AS n")["n"]
    for writer, params in [
        (R.update_platform, {"name": "visitor", "time": 5.0, "memory_total_mb": 2048.0, "memory_free_mb": 1024.0}),
        (R.update_platform, {"name": "visitor", "time": 5.0, "memory_free_mb": 10.0}),
        (R.update_platform, {"name": "visitor", "time": 5.0, "cpu_load": 1.0}),
        (R.set_platform_online, {"name": "visitor", "online": True, "time": 5.0}),
        (R.record_process_start, {"run_id": "v-run", "instance": "v", "deployment": "d_b", "config": "g_b",
                                  "host": "visitor", "pid": 5, "start_time": 5.0}),
        (R.record_decision, {"name": "v-decision", "time": 5.0, "trigger": "startup", "config": "g_b",
                             "host": "visitor"}),
    ]:
        with pytest.raises(UnknownHost, match="host 'visitor' is no Platform of the models"):
            writer(known_store, **params)
    # Nothing written: no Platform, no profile, no decision.
    assert _row(known_store, "MATCH (n) RETURN count(n) AS n")["n"] == before
    # A decision that names no host is still taken.
    R.record_decision(known_store, name="no-host", time=5.0, trigger="startup")


def test_going_offline_keeps_the_last_time_the_host_was_seen(known_store):
    R.set_platform_online(known_store, name="beta", online=True, time=20.0)
    R.set_platform_online(known_store, name="beta", online=False, time=25.0)
    row = _row(known_store, "MATCH (p:Platform {name: 'beta'}) RETURN p.online AS online, p.last_seen AS seen")
    assert row == {"online": False, "seen": 20.0}


def test_a_process_profile_links_to_its_deployment_host_and_configuration_once(known_store):
    for _ in range(2):
        R.record_process_start(known_store, run_id="run-9", instance="det", deployment="d_b", config="g_b",
                               host="beta", pid=99, start_time=3.0)
    row = _row(known_store, """
        MATCH (r:ProcessProfile {name: 'run-9'})
        RETURN size([(r)-[:PROFILE_OF]->(:Deployment {name: 'd_b'}) | 1]) AS profile_of,
               size([(r)-[:RAN_ON]->(:Platform {name: 'beta'}) | 1]) AS ran_on,
               size([(r)-[:RAN_CONFIG]->(:PerceptionGraph {name: 'g_b'}) | 1]) AS ran_config,
               r.pid AS pid, r.instance AS instance, r.end_time AS end_time""")
    assert row == {"profile_of": 1, "ran_on": 1, "ran_config": 1, "pid": 99, "instance": "det", "end_time": None}
    R.record_process_sample(known_store, run_id="run-9", rss_mb_last=50.0, rss_mb_mean=45.5, rss_mb_max=52.0,
                            cpu_percent_mean=33.0)
    R.record_process_end(known_store, run_id="run-9", end_time=9.0, exit_status=-15)
    row = _row(known_store, "MATCH (r:ProcessProfile {name: 'run-9'}) RETURN r.rss_mb_mean AS m, r.end_time AS e, "
                            "r.exit_status AS x")
    assert row == {"m": 45.5, "e": 9.0, "x": -15}


def test_a_profile_of_an_unknown_deployment_is_still_recorded_without_dangling_links(known_store):
    R.record_process_sample(known_store, run_id="early", rss_mb_last=1.0, rss_mb_mean=1.0, rss_mb_max=1.0,
                            cpu_percent_mean=0.0)  # a sample may arrive before the start
    R.record_process_start(known_store, run_id="early", instance="x", deployment="ghost", config="g_ghost",
                           host="alpha", pid=5, start_time=1.0)
    row = _row(known_store, "MATCH (r:ProcessProfile {name: 'early'}) OPTIONAL MATCH (r)-[e]->(n) "
                            "RETURN r.deployment AS d, r.rss_mb_mean AS m, collect(type(e)) AS links")
    assert (row["d"], row["m"], row["links"]) == ("ghost", 1.0, ["RAN_ON"])


def test_a_recording_figures_sit_beside_the_synthetic_ones_and_an_unnamed_old_one_is_taken_as_synthetic(known_store):
    from kgadapt.knowledge.queries import run_named

    # A relation written before sources were named.
    known_store.execute("MATCH (g:PerceptionGraph {name: $g}), (b:IlluminationBand {name: $b}) "
                        "CREATE (g)-[:CALIBRATED {condition: $c, detection_rate: 0.5, false_per_frame: 0.0, "
                        "ms_per_frame: 6.0, at: 1.0}]->(b)", {"g": "g_a", "b": "day", "c": "all"})
    before = run_named(known_store, "config_ranking", {"band": "day"})
    R.record_calibration(known_store, config="g_a", band="day", detection_rate=0.9, ms_per_frame=5.0, time=2.0,
                         source="frames:flight-7")
    rows = known_store.execute("MATCH (:PerceptionGraph {name: $g})-[c:CALIBRATED]->(:IlluminationBand {name: $b}) "
                               "RETURN c.source AS source, c.detection_rate AS rate ORDER BY source",
                               {"g": "g_a", "b": "day"})
    assert rows == [{"source": "frames:flight-7", "rate": 0.9}, {"source": "synthetic", "rate": 0.5}]
    after = run_named(known_store, "config_ranking", {"band": "day"})
    recorded = run_named(known_store, "config_ranking", {"band": "day",
                                                         "source": "frames:flight-7"})
    assert [r["detection_rate"] for r in before] == [r["detection_rate"] for r in after] == [0.5]
    assert [r["detection_rate"] for r in recorded] == [0.9]
    R.record_calibration(known_store, config="g_a", band="day", detection_rate=0.7, ms_per_frame=5.0, time=3.0)
    assert [r["detection_rate"] for r in run_named(known_store, "config_ranking",
                                                   {"band": "day"})] == [0.7]


def test_calibration_is_one_relation_per_configuration_and_band_replaced_by_the_next(known_store):
    R.record_calibration(known_store, config="g_a", band="day", detection_rate=0.5, false_rate=0.1,
                         ms_per_frame=6.0, time=1.0)
    R.record_calibration(known_store, config="g_a", band="day", detection_rate=0.97, false_rate=0.0,
                         ms_per_frame=4.0, time=2.0)
    row = _row(known_store, "MATCH (:PerceptionGraph {name: 'g_a'})-[c:CALIBRATED]->(:IlluminationBand {name: 'day'}) "
                            "RETURN count(c) AS n, max(c.detection_rate) AS r, max(c.at) AS at")
    assert row == {"n": 1, "r": 0.97, "at": 2.0}
    with pytest.raises(NamedQueryError, match="no detector configuration 'g_zz'"):
        R.record_calibration(known_store, config="g_zz", band="day", detection_rate=0.5, false_rate=0.0,
                             ms_per_frame=1.0, time=3.0)
    with pytest.raises(NamedQueryError, match="detection_rate 1.5 is not between 0 and 1"):
        R.record_calibration(known_store, config="g_a", band="day", detection_rate=1.5, false_rate=0.0,
                             ms_per_frame=1.0, time=3.0)


def test_a_live_rate_is_one_relation_per_configuration_band_and_condition_updated_not_appended(known_store):
    live = {"config": "g_a", "band": "day", "frames": 40, "frames_expected": 30, "frames_seen": 3, "since": 1.0}
    R.record_live_rate(known_store, **live, detection_rate=0.1, time=2.0, run_id="r1", host="onboard")
    R.record_live_rate(known_store, **{**live, "frames_seen": 30}, detection_rate=1.0, time=4.0, run_id="r2")
    R.record_live_rate(known_store, **live, detection_rate=0.5, time=4.0, condition="blur")
    rows = known_store.execute("MATCH (:PerceptionGraph {name: 'g_a'})-[l:LIVE_RATE]->(:IlluminationBand {name: 'day'}) "
                               "RETURN l.condition AS c, l.detection_rate AS r, l.at AS at, l.run_id AS run, "
                               "l.host AS host ORDER BY c")
    assert rows == [{"c": "all", "r": 1.0, "at": 4.0, "run": "r2", "host": None},
                    {"c": "blur", "r": 0.5, "at": 4.0, "run": None, "host": None}]
    for bad, message in [({"frames_seen": 31}, "frames_seen 31 is not between 0 and 30"),
                         ({"frames_expected": 41}, "frames_expected 41 is not between 0 and 40"),
                         ({"since": 9.0}, "since 9.0 is not between 0 and 4"),
                         ({"detection_rate": 1.2}, "detection_rate 1.2 is not between 0 and 1"),
                         ({"config": "g_zz"}, "no detector configuration 'g_zz'")]:
        with pytest.raises(NamedQueryError, match=message):
            R.record_live_rate(known_store, **{**live, "detection_rate": 0.0, "time": 4.0, **bad})
    assert known_store.execute("MATCH ()-[l:LIVE_RATE]->() RETURN count(l) AS n")[0]["n"] == 2


def test_a_decision_links_to_the_configuration_and_host_it_chose(known_store):
    R.record_decision(known_store, name="d-1", time=1.5, trigger="illumination 5 (dark)", inputs_json='{"level": 5}',
                      query="placement", config="g_b", host="beta", duration_ms=2.5, outcome="started")
    row = _row(known_store, "MATCH (a:AdaptationDecision {name: 'd-1'})-[:CHOSE]->(g), (a)-[:PLACED_ON]->(p) "
                            "RETURN g.name AS g, p.name AS p, a.inputs_json AS i, a.duration_ms AS ms")
    assert row == {"g": "g_b", "p": "beta", "i": '{"level": 5}', "ms": 2.5}


def test_the_flight_state_lands_on_the_flight_control_component(known_store):
    R.update_flight_control(known_store, name="fc", time=12.0, link=True, armed=False, mode="LOITER",
                            battery_pct=80.0, autopilot_load_pct=22.0)
    row = _row(known_store, "MATCH (c:Component:FlightControl {name: 'fc'}) RETURN c.link AS link, c.mode AS mode, "
                            "c.autopilot_load_pct AS apl, c.cpu_load AS cpu, c.last_seen AS seen")
    assert row == {"link": True, "mode": "LOITER", "apl": 22.0, "cpu": 70, "seen": 12.0}
    assert _row(known_store, "MATCH (c:Component {name: 'fc'}) RETURN count(c) AS n")["n"] == 1


def test_cpu_load_without_cores_is_bounded_by_the_cores_the_graph_holds(known_store):
    cores = _row(known_store, "MATCH (p:Platform {name: 'alpha'}) RETURN p.cpu_cores AS n")["n"]
    assert isinstance(cores, int) and cores >= 1
    R.update_platform(known_store, name="alpha", time=1.0, cpu_load=100.0 * cores)
    with pytest.raises(NamedQueryError, match=rf"cpu_load 5000.0 is not between 0 and {100 * cores}"):
        R.update_platform(known_store, name="alpha", time=2.0, cpu_load=5000.0)
    refused = R.update_platforms(known_store, [{"name": "alpha", "time": 3.0, "cpu_load": 5000.0}])
    assert set(refused) == {"alpha"}
    assert _row(known_store, "MATCH (p:Platform {name: 'alpha'}) RETURN p.cpu_load AS load")["load"] == 100.0 * cores


def test_the_writers_are_the_contract_verbs():
    assert set(R.WRITERS) == {"platform", "platform_online", "process_start", "process_sample", "process_end",
                              "process_reconfigured",
                              "calibration", "live_rate", "decision", "flight_state", "fleet_forget"}
    assert R.writer_params("process_end") == {"run_id": True, "end_time": True, "exit_status": True}


@pytest.mark.parametrize("verb, params, message", [
    ("reboot", {}, r"unknown write 'reboot'"),
    ("platform", {"name": "a", "time": 1.0, "colour": "red"}, r"'platform' has no parameter 'colour'"),
    ("process_end", {"run_id": "r", "end_time": 1.0}, r"'process_end' needs parameter 'exit_status'"),
    ("process_start", {"run_id": "r", "instance": "i", "deployment": "d", "config": "c", "host": "h",
                       "pid": "12", "start_time": 1.0}, r"'pid' must be int, not str"),
    ("platform", {"name": "a", "time": 1.0, "memory_free_mb": True}, r"'memory_free_mb' must be a number, not a bool"),
    ("platform", {"name": "a", "time": float("nan")}, r"'time' must be a finite number"),
    ("platform_online", {"name": "", "online": True, "time": 1.0}, r"'name' is empty"),
    # Negative times, each writer's (the contract: "negative times and durations" are refused).
    ("platform_online", {"name": "a", "online": True, "time": -5.0}, r"'platform_online': time -5.0 is not between"),
    ("process_reconfigured", {"run_id": "r", "config": "c", "deployment": "d", "time": -100.0},
     r"'process_reconfigured': time -100.0 is not between"),
    ("process_sample", {"run_id": "r", "rss_mb_last": 1.0, "rss_mb_mean": 1.0, "rss_mb_max": 1.0,
                        "cpu_percent_mean": 1.0, "received": -1.0}, r"'process_sample': received -1.0"),
    ("flight_state", {"name": "fc", "time": 1.0, "link": True, "last_heartbeat": -7.0},
     r"'flight_state': last_heartbeat -7.0 is not between"),
])
def test_a_malformed_write_is_refused_naming_the_verb_and_parameter(resp_store, verb, params, message):
    resp_store.execute("CREATE (:Marker {name: 'm'})")
    with pytest.raises(NamedQueryError, match=message):
        R.run_write(resp_store, verb, params)
    assert resp_store.execute("MATCH (n) RETURN count(n) AS c")[0]["c"] == 1  # nothing written
