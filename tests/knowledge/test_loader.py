"""Loading models: idempotent, a changed model replaces its old version, run-time facts survive."""

from __future__ import annotations

from pathlib import Path

import pytest

from kgadapt.knowledge import runtime as R
from kgadapt.knowledge.loader import load_models
from kgadapt.shared.errors import ModelError

from .conftest import counts, signature


def _one(store, cypher, **params):
    rows = store.execute(cypher, params, read_only=True)
    assert len(rows) == 1, rows
    return rows[0]


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, f"{old!r} not in {path}"
    path.write_text(text.replace(old, new))


def test_loading_writes_every_node_and_relation_the_models_define(known_store):
    # 2 features + 2 bands + 2 platforms + 6 components + 6 ports + 4 graphs + 5 deployments
    # relations: 1 REQUIRES + 6 HAS_PORT + 4 REALIZES + 2 SUITED_FOR + 7 CONTAINS + 3 CONNECTED_TO
    #            + 5 DEPLOYS + 6 EXECUTABLE_ON
    assert counts(known_store) == (27, 34)
    row = _one(known_store, "MATCH (c:Component:SensorComponent:Camera {name: $n}) RETURN c.width AS w, "
                            "c.model_file AS f", n="cam")
    assert row["w"] == 640 and row["f"].endswith("components.rpsl")


def test_loading_the_same_models_twice_changes_nothing(known_store, known_dir):
    before = signature(known_store)
    report = load_models(known_store, [known_dir])
    assert signature(known_store) == before
    assert report.labels["Component"] == 6 and report.relations["EXECUTABLE_ON"] == 6


def test_a_changed_model_replaces_its_old_version_without_duplicates(known_store, known_dir):
    _edit(known_dir / "graphs.rpsl", 'name "g_a"', 'name "g_a2"')
    _edit(known_dir / "graphs.rpsl", "memory_demand_mb 100", "memory_demand_mb 150")
    _edit(known_dir / "graphs.rpsl", '  add_port :out, "out_port", "marker"\n', "")
    _edit(known_dir / "d_a.service", "Deploys=g_a", "Deploys=g_a2")
    _edit(known_dir / "d_a.service", "ExecutableOn=alpha beta", "ExecutableOn=beta")
    load_models(known_store, [known_dir])
    assert counts(known_store) == (26, 32)  # one port fewer; its HAS_PORT and one EXECUTABLE_ON gone
    names = [r["n"] for r in known_store.execute("MATCH (g:PerceptionGraph) RETURN g.name AS n ORDER BY n")]
    assert names == ["g_a2", "g_b", "g_c", "g_other"]
    assert _one(known_store, "MATCH (c:Component {name: 'det_a'}) RETURN c.memory_demand_mb AS m")["m"] == 150
    platforms = known_store.execute("MATCH (:Deployment {name: 'd_a'})-[:EXECUTABLE_ON]->(p) RETURN p.name AS p")
    assert [r["p"] for r in platforms] == ["beta"]
    deploys = known_store.execute("MATCH (:Deployment {name: 'd_a'})-[:DEPLOYS]->(g) RETURN g.name AS g")
    assert [r["g"] for r in deploys] == ["g_a2"]


def test_a_property_or_label_dropped_from_a_model_is_dropped_from_the_graph(known_store, known_dir):
    _edit(known_dir / "features.features", '  description "Find markers"\n', "")
    _edit(known_dir / "platforms.platform", '  description => "small"\n', "")
    _edit(known_dir / "components.rpsl", 'rpsl.sensor_component do\n  name "cam2"',
          'rpsl.processing_component do\n  name "cam2"')
    _edit(known_dir / "components.rpsl", "  resolution 1920, 1080\n", "")
    load_models(known_store, [known_dir])
    assert _one(known_store, "MATCH (f:Feature {name: 'MarkerDetection'}) RETURN f.description AS d")["d"] is None
    assert _one(known_store, "MATCH (p:Platform {name: 'alpha'}) RETURN p.description AS d")["d"] is None
    labels = _one(known_store, "MATCH (c:Component {name: 'cam2'}) RETURN labels(c) AS l")["l"]
    assert sorted(labels) == ["Component", "ProcessingComponent"]


def test_a_model_file_removed_from_a_loaded_directory_takes_its_nodes_with_it(known_store, known_dir):
    (known_dir / "d_other.deploy").unlink()
    load_models(known_store, [known_dir])
    assert known_store.execute("MATCH (d:Deployment {name: 'd_other'}) RETURN d") == []
    assert counts(known_store) == (26, 32)  # the deployment, its DEPLOYS and its EXECUTABLE_ON


def test_a_file_removed_from_a_directory_named_through_dot_dot_takes_its_nodes_with_it(known_store, known_dir,
                                                                                       monkeypatch):
    # The files' paths were normalised, the directory's not: "../known" never matched what came from it.
    elsewhere = known_dir.parent / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    dotted = f"../{known_dir.name}"
    load_models(known_store, [dotted])
    (known_dir / "d_other.deploy").unlink()
    load_models(known_store, [dotted])
    assert known_store.execute("MATCH (d:Deployment {name: 'd_other'}) RETURN d") == []


def test_run_time_facts_survive_a_reload_of_the_models(known_store, known_dir):
    R.update_platform(known_store, name="alpha", time=50.0, memory_free_mb=321.0, cpu_load=12.5, online=True)
    R.record_process_start(known_store, run_id="run-1", instance="det-1", deployment="d_a", config="g_a",
                           host="alpha", pid=77, start_time=40.0)
    R.record_process_sample(known_store, run_id="run-1", rss_mb_last=60.0, rss_mb_mean=55.0, rss_mb_max=70.0,
                            cpu_percent_mean=20.0)
    R.record_calibration(known_store, config="g_a", band="day", detection_rate=0.9, false_rate=0.01,
                         ms_per_frame=4.0, time=45.0)
    R.record_decision(known_store, name="dec-1", time=39.0, trigger="level 80", config="g_a", host="alpha",
                      outcome="started")
    R.update_flight_control(known_store, name="fc", time=51.0, link=True, mode="LAND")
    _edit(known_dir / "platforms.platform", "size_mb => 1000", "size_mb => 2000")
    _edit(known_dir / "components.rpsl", "  cpu_load 70\n", "")
    load_models(known_store, [known_dir])
    row = _one(known_store, "MATCH (p:Platform {name: 'alpha'}) RETURN p.memory_free_mb AS free, "
                            "p.cpu_load AS cpu, p.online AS online, p.last_seen AS seen, p.memory_total_mb AS total")
    assert row == {"free": 321.0, "cpu": 12.5, "online": True, "seen": 50.0, "total": 2000.0}
    row = _one(known_store, """
        MATCH (r:ProcessProfile {name: 'run-1'})-[:PROFILE_OF]->(:Deployment {name: 'd_a'}),
              (r)-[:RAN_ON]->(:Platform {name: 'alpha'}), (r)-[:RAN_CONFIG]->(:PerceptionGraph {name: 'g_a'})
        RETURN r.pid AS pid, r.rss_mb_mean AS mean""")
    assert row == {"pid": 77, "mean": 55.0}
    assert _one(known_store, "MATCH (:PerceptionGraph {name: 'g_a'})-[c:CALIBRATED]->(:IlluminationBand {name: 'day'}) "
                             "RETURN c.detection_rate AS r")["r"] == 0.9
    assert _one(known_store, "MATCH (:AdaptationDecision {name: 'dec-1'})-[:CHOSE]->(g) RETURN g.name AS g")["g"] == "g_a"
    row = _one(known_store, "MATCH (c:Component {name: 'fc'}) RETURN c.mode AS mode, c.link AS link, "
                            "c.cpu_load AS cpu, c.memory_demand_mb AS mem")
    assert row == {"mode": "LAND", "link": True, "cpu": None, "mem": 50}  # run-time kept, dropped design key gone


def test_a_single_model_file_may_name_what_an_earlier_load_defined(known_store, tmp_path):
    extra = tmp_path / "later" / "d_new.deploy"
    extra.parent.mkdir()
    extra.write_text("deploys: g_b\nexecutable: /bin/true\nexecutable_on: alpha\n")
    load_models(known_store, [extra])
    row = _one(known_store, "MATCH (d:Deployment {name: 'd_new'})-[:DEPLOYS]->(g), (d)-[:EXECUTABLE_ON]->(p) "
                            "RETURN g.name AS g, p.name AS p")
    assert row == {"g": "g_b", "p": "alpha"}


def test_a_platform_known_only_from_run_time_does_not_count_as_modelled(known_store, tmp_path):
    # A Platform no model made (written by a version that still let run-time facts add hosts).
    known_store.execute("CREATE (:Platform {name: 'gamma', last_seen: 1.0, memory_free_mb: 10.0})")
    extra = tmp_path / "d_gamma.deploy"
    extra.write_text("deploys: g_b\nexecutable: /bin/true\nexecutable_on: gamma\n")
    with pytest.raises(ModelError, match="unknown platform 'gamma'"):
        load_models(known_store, [extra])


def test_a_load_of_many_files_with_one_bad_writes_none_of_them(store, known_dir):
    store.execute("CREATE (:Marker {name: 'before'})")
    _edit(known_dir / "d_other.deploy", "executable_on: beta", "executable_on: beta, nowhere")
    with pytest.raises(ModelError, match="d_other.deploy:3: unknown platform 'nowhere'"):
        load_models(store, [known_dir])
    assert counts(store) == (1, 0)


def test_a_reference_to_nothing_in_a_fresh_store_is_a_model_error(store, tmp_path):
    lone = tmp_path / "lone.deploy"
    lone.write_text("deploys: g_a\nexecutable: /bin/true\nexecutable_on: alpha\n")
    with pytest.raises(ModelError, match=r"lone.deploy:1: unknown perception graph or component 'g_a'"):
        load_models(store, [lone])
