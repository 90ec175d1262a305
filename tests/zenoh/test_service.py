"""The knowledge service in-process on a real FalkorDB and real Zenoh sessions on loopback."""

from __future__ import annotations

import time

import pytest

from kgadapt.knowledge import queries, schema
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.shared import keys, messages
from kgadapt.shared.errors import RemoteError, RequestTimeout
from tests.zenoh.conftest import platform_row, wait_for, wait_until_serving


def load_tiny_graph(store, *, onboard_free: float = 100.0, remote_free: float = 1000.0) -> None:
    """One feature, one detector configuration of 200 MiB, deployable on two online platforms."""
    # The platforms are the fixture's (the models' hosts): given their figures here.
    store.execute(
        f"MERGE (on:{schema.PLATFORM} {{name: 'onboard'}}) "
        "SET on += {memory_total_mb: 2048.0, memory_free_mb: $onboard_free, online: true} "
        f"MERGE (re:{schema.PLATFORM} {{name: 'remote'}}) "
        "SET re += {memory_total_mb: 8192.0, memory_free_mb: $remote_free, online: true} "
        f"WITH on, re CREATE (f:{schema.FEATURE} {{name: 'MarkerDetection'}}), "
        f"(pg:{schema.PERCEPTION_GRAPH} {{name: 'marker_detection_day'}}), "
        f"(cam:{schema.COMPONENT}:{schema.SENSOR_COMPONENT}:{schema.CAMERA} {{name: 'camera', memory_demand_mb: 50.0}}), "
        f"(det:{schema.COMPONENT}:{schema.PROCESSING_COMPONENT} {{name: 'detector_day', memory_demand_mb: 150.0}}), "
        f"(d:{schema.DEPLOYMENT} {{name: 'detector_day_service', kind: 'SystemdServiceFile'}}), "
        f"(pg)-[:{schema.REALIZES}]->(f), (pg)-[:{schema.CONTAINS}]->(cam), (pg)-[:{schema.CONTAINS}]->(det), "
        f"(d)-[:{schema.DEPLOYS}]->(pg), (d)-[:{schema.EXECUTABLE_ON}]->(on), (d)-[:{schema.EXECUTABLE_ON}]->(re)",
        {"onboard_free": onboard_free, "remote_free": remote_free},
    )


def test_a_named_query_over_zenoh_answers_what_the_store_answers(client, resp_store):
    load_tiny_graph(resp_store)
    params = {"feature": "MarkerDetection"}
    over_zenoh = client.query("placement", params)
    direct = queries.run_named(resp_store, "placement", params)
    assert over_zenoh == direct
    assert [row["platform"] for row in over_zenoh] == ["remote"]  # onboard's 100 MiB < 200 MiB demand
    assert client.last_elapsed_ms is not None and client.last_elapsed_ms > 0


def test_named_query_parameters_may_come_in_the_selector(zenoh_pair, client, robot, resp_store):
    load_tiny_graph(resp_store)
    _, session = zenoh_pair
    replies = list(session.get(keys.knowledge_query(robot, "placement") + "?feature=MarkerDetection", timeout=3))
    assert len(replies) == 1 and replies[0].ok is not None
    rows = messages.decode(replies[0].ok.payload.to_bytes(), "rows")["rows"]
    assert [row["platform"] for row in rows] == ["remote"]


def test_an_unknown_query_is_refused_with_an_error_naming_it(client):
    with pytest.raises(RemoteError, match="no_such_query"):
        client.query("no_such_query", {})


def test_a_missing_parameter_is_refused_with_an_error_naming_it(client):
    assert queries.QUERIES["feature_deployments"].params["platform"].required
    with pytest.raises(RemoteError, match="'platform'"):
        client.query("feature_deployments", {"feature": "MarkerDetection"})


def test_an_ill_typed_parameter_is_refused_with_an_error_naming_it(client):
    with pytest.raises(RemoteError, match="feature"):
        client.query("placement", {"feature": 42})


def test_an_unknown_parameter_is_refused_with_an_error_naming_it(client):
    with pytest.raises(RemoteError, match="colour"):
        client.query("placement", {"feature": "MarkerDetection", "colour": "red"})


def test_read_only_cypher_answers_with_rows_and_takes_parameters(client, resp_store):
    load_tiny_graph(resp_store)
    rows = client.cypher("MATCH (p:Platform) WHERE p.name = $name RETURN p.memory_free_mb AS free", {"name": "remote"})
    assert rows == [{"free": 1000.0}]


@pytest.mark.parametrize("cypher", [
    "CREATE (x:Intruder {name: 'x'}) RETURN x",
    "MATCH (p:Platform) SET p.memory_free_mb = 0 RETURN p",
    "MATCH (p:Platform) DETACH DELETE p",
    "MERGE (x:Intruder {name: 'x'})",
])
def test_cypher_that_writes_is_refused_and_the_graph_is_unchanged(client, resp_store, cypher):
    load_tiny_graph(resp_store)
    with pytest.raises(RemoteError, match="read-only"):
        client.cypher(cypher)
    assert resp_store.execute("MATCH (x:Intruder) RETURN count(x) AS n")[0]["n"] == 0
    assert resp_store.execute("MATCH (p:Platform) RETURN min(p.memory_free_mb) AS m")[0]["m"] == 100.0


def test_malformed_cypher_is_refused_naming_where(client):
    with pytest.raises(RemoteError, match=r"offset 9 \('RETURN'\): expected '\)'"):
        client.cypher("MATCH (n RETURN n")


def test_cypher_the_store_rejects_is_answered_with_the_stores_reason(client):
    with pytest.raises(RemoteError, match="store rejected.*[Dd]ivision by zero"):
        client.cypher("RETURN 1 / 0 AS x")


def test_a_write_verb_changes_the_graph(client, resp_store):
    client.write("platform", {"name": "h1", "time": 1.0, "memory_free_mb": 321.0})
    rows = resp_store.execute("MATCH (p:Platform {name: 'h1'}) RETURN p.memory_free_mb AS free")
    assert rows == [{"free": 321.0}]


def test_an_unknown_write_verb_is_refused_with_an_error_naming_it(client):
    with pytest.raises(RemoteError, match="drop_everything"):
        client.write("drop_everything", {})


def test_a_write_with_a_missing_parameter_is_refused_naming_it(client):
    with pytest.raises(RemoteError, match="'time'"):
        client.write("platform", {"name": "spare"})


def test_a_write_with_an_ill_typed_parameter_is_refused_naming_it(client, resp_store):
    with pytest.raises(RemoteError, match="memory_free_mb"):
        client.write("platform", {"name": "spare", "time": 1.0, "memory_free_mb": "lots"})
    assert resp_store.execute("MATCH (p:Platform {name: 'spare'}) RETURN count(p) AS n")[0]["n"] == 0


def test_a_write_with_an_unknown_parameter_is_refused_naming_it(client):
    with pytest.raises(RemoteError, match="owner"):
        client.write("platform", {"name": "spare", "time": 1.0, "owner": "me"})


def test_a_read_only_service_declares_no_write_verbs(resp_store, zenoh_pair, robot):
    server, session = zenoh_pair
    schema.ensure_indexes(resp_store)
    svc = KnowledgeService(resp_store, ServiceSettings(robot=robot, writes=False))
    svc.setup(server)
    try:
        wait_until_serving(session, robot, writes=False)
        client = KnowledgeClient(session, robot, timeout=1.0)
        with pytest.raises(RequestTimeout):  # no queryable answers: the client tries until its timeout
            client.write("platform", {"name": "spare", "time": 1.0})
        assert client.cypher("RETURN 1 AS one") == [{"one": 1}]
    finally:
        svc.shutdown()
    assert resp_store.execute("MATCH (p:Platform {name: 'spare'}) RETURN count(p) AS n")[0]["n"] == 0


def test_a_client_with_no_service_gets_a_request_timeout(zenoh_pair):
    _, session = zenoh_pair
    with pytest.raises(RequestTimeout, match="nobody"):
        KnowledgeClient(session, "nobody", timeout=0.5).query("platforms", {})


def test_a_host_status_updates_its_platform_figures(zenoh_pair, client, robot):
    _, session = zenoh_pair
    before = time.time()
    status = {"host": "remote", "time": before, "memory_total_mb": 4096.0, "memory_free_mb": 1234.5,
              "cpu_load": 37.0, "cpu_cores": 4}
    session.put(keys.host_status(robot, "remote"), messages.encode("host_status", status))
    row = wait_for(lambda: (r := platform_row(client, "remote")) and r["memory_free_mb"] == 1234.5 and r,
                   3, "the status in the graph")
    assert row["memory_total_mb"] == 4096.0 and row["cpu_load"] == 37.0
    assert row["last_seen"] >= before


def test_a_status_naming_another_host_than_its_key_is_dropped(zenoh_pair, client, service, robot):
    _, session = zenoh_pair
    status = {"host": "onboard", "time": time.time(), "memory_total_mb": 1.0, "memory_free_mb": 1.0, "cpu_load": 0.0}
    session.put(keys.host_status(robot, "remote"), messages.encode("host_status", status))
    wait_for(lambda: service.stats().get("events_dropped"), 3, "the drop")
    assert "names host 'onboard'" in service.stats()["last_drop"]
    assert platform_row(client, "onboard")["memory_free_mb"] is None
    assert platform_row(client, "remote")["memory_free_mb"] is None


def test_a_liveliness_token_marks_its_platform_online_and_offline(zenoh_pair, client, robot):
    _, session = zenoh_pair
    token = session.liveliness().declare_token(keys.host_alive(robot, "remote"))
    wait_for(lambda: (platform_row(client, "remote") or {}).get("online") is True, 3, "remote online")
    token.undeclare()
    wait_for(lambda: (platform_row(client, "remote") or {}).get("online") is False, 3, "remote offline")


def test_a_host_alive_before_the_service_starts_is_seen_online(resp_store, zenoh_pair, robot):
    server, session = zenoh_pair
    token = session.liveliness().declare_token(keys.host_alive(robot, "remote"))
    resp_store.execute("CREATE (:Platform {name: 'onboard', online: true})")  # stale: nobody holds its token
    resp_store.execute("CREATE (:Platform {name: 'remote'})")
    svc = KnowledgeService(resp_store, ServiceSettings(robot=robot))
    svc.setup(server)
    try:
        wait_until_serving(session, robot)
        client = KnowledgeClient(session, robot)
        wait_for(lambda: (platform_row(client, "remote") or {}).get("online") is True, 3, "remote online from history")
        assert platform_row(client, "onboard")["online"] is False
    finally:
        svc.shutdown()
        token.undeclare()


def test_only_the_models_add_hosts_a_ghost_is_refused_counted_and_logged_once(zenoh_pair, client, service, robot,
                                                                               resp_store, caplog):
    _, session = zenoh_pair
    platforms = lambda: sorted(r["platform"] for r in client.query("platforms", {}))  # noqa: E731
    before = platforms()
    status = {"time": time.time(), "memory_total_mb": 4096.0, "memory_free_mb": 100.0, "cpu_load": 0.0}
    with caplog.at_level("WARNING", logger="kgadapt.knowledge.service"):
        token = session.liveliness().declare_token(keys.host_alive(robot, "ghost"))
        for _ in range(3):
            session.put(keys.host_status(robot, "ghost"), messages.encode("host_status", {"host": "ghost", **status}))
        wait_for(lambda: service.stats().get("unknown_host_refused", 0) >= 4, 5, "the ghost's token and statuses refused")
        token.undeclare()
        wait_for(lambda: service.stats().get("unknown_host_refused", 0) >= 5, 5, "the end of the ghost's token refused")
        for verb, params in [
            ("platform", {"name": "ghost", "time": 1.0, "memory_free_mb": 1.0}),
            ("platform_online", {"name": "ghost", "online": True, "time": 1.0}),
            ("process_start", {"run_id": "ghost-run", "instance": "g", "deployment": "d", "config": "c",
                               "host": "ghost", "pid": 1, "start_time": 1.0}),
            ("decision", {"name": "ghost-decision", "time": 1.0, "trigger": "host_lost", "host": "ghost"}),
        ]:
            with pytest.raises(RemoteError, match="host 'ghost' is no Platform of the models"):
                client.write(verb, params)
    assert platforms() == before  # no Platform, and nothing else written about the ghost
    assert resp_store.execute("MATCH (n) WHERE n.name STARTS WITH 'ghost' RETURN n.name AS n") == []
    stats = client.service_stats()  # knowledge/own/stats: what `kgadapt status` counts
    assert stats["unknown_host_refused"] == 9 and stats["unknown_hosts"] == ["ghost"]
    assert len([r for r in caplog.records if "refused host 'ghost'" in r.getMessage()]) == 1  # logged once
    from kgadapt.operator.status import gather

    shown = gather(session, robot, listen_s=0.0, timeout=2.0)  # what `kgadapt status` shows
    assert shown["refused_hosts"] == {"count": 9, "hosts": ["ghost"]}
    assert any("refused 9 message(s) naming hosts no model names: ghost" in p for p in shown["problems"])
    assert "ghost" not in {h["host"] for h in shown["hosts"]}


def test_a_decisions_time_is_the_services_not_the_senders(client, resp_store):
    sent = time.time() + 3600.0  # a sender's clock an hour ahead
    client.write("decision", {"name": "dated", "time": sent, "trigger": "startup", "host": "onboard"})
    taken = resp_store.execute("MATCH (a:AdaptationDecision {name: 'dated'}) RETURN a.time AS t")[0]["t"]
    assert taken <= time.time() < sent


def test_another_robots_question_waits_while_the_robots_own_request_is_answered(resp_store, robot):
    import threading

    schema.ensure_indexes(resp_store)
    svc = KnowledgeService(resp_store, ServiceSettings(robot=robot, own_first_wait_s=60.0))  # not set up: no Zenoh
    answered = threading.Event()
    asker = threading.Thread(target=lambda: (svc.answer_named("platforms", None, public=True), answered.set()))
    with svc.own_first.serving():  # an own request being answered
        asker.start()
        assert not answered.wait(0.5)  # the public question has not run meanwhile
        # The own request's own steps never wait for it: a literal query on the own door answers at once.
        started = time.monotonic()
        svc.answer_named("fig5_literal", None)
        assert time.monotonic() - started < 30.0
    assert answered.wait(10)  # and it runs as soon as the own request is done
    asker.join()
